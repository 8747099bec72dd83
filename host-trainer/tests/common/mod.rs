//! What the tests that drive whole runs share: a scratch directory, the run options, the
//! JSON-lines files a run writes.

use burn::tensor::Device;
use host_trainer::train::RunOptions;
use std::path::{Path, PathBuf};

/// An empty scratch directory for test `group`'s run `name`, unique to this process.
pub fn tmp_dir(group: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("overtake-{group}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A fresh run into `out` on the CPU backend, quiet, to its budget.
pub fn run_options(out: &Path) -> RunOptions {
    RunOptions {
        out: out.to_path_buf(),
        resume: false,
        device: Device::flex().autodiff(),
        progress: false,
        stop_after: None,
        init_actor: None,
        fork_from: None,
    }
}

/// The lines of a JSON-lines file the run wrote (`metrics.jsonl`, `imitation.jsonl`).
pub fn read_jsonl<T: serde::de::DeserializeOwned>(path: &Path) -> Vec<T> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}
