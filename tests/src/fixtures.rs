//! Seeds and the golden-vector file format shared by the golden tests and the Cortex-M test
//! image's build script.
//!
//! A golden file (`tests/golden/row_X.golden`) is text: comment lines start with `#`, then
//! `row X`, `seed N`, `dim D`, and per step one `obs` line (D f32 values, shortest
//! round-trip decimal) and one `mean` line (4 values of the float64 reference, 17 significant
//! digits). The Cortex-M image regenerates the blob from the seed with
//! `firmware_core::synthetic` and checks its outputs against the `mean` lines.

use firmware_core::policy::{Architecture, TableRow};
use firmware_core::synthetic;
use std::fmt::Write as _;
use std::path::PathBuf;

use crate::reference::{ReferencePolicy, Shape};

/// Steps per golden sequence (the recurrent rows carry state across them).
pub const GOLDEN_STEPS: usize = 6;

pub use firmware_core::synthetic::{GOLDEN_ROWS, golden_seed};

/// The folder of the committed golden files.
pub fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("golden")
}

/// The reference shape of `arch`.
pub fn shape(arch: &Architecture) -> Shape {
    Shape {
        obs_dim: usize::from(arch.obs_dim),
        lstm_layers: usize::from(arch.lstm_layers),
        hidden: usize::from(arch.lstm_hidden),
        mlp: arch.mlp_hidden.iter().map(|&w| usize::from(w)).collect(),
    }
}

/// The golden sequence of `row`: observations and the float64 reference's means.
pub fn golden_sequence(row: TableRow) -> (Vec<Vec<f32>>, Vec<Vec<f64>>) {
    let arch = Architecture::table1(row);
    let seed = golden_seed(row);
    let weights = synthetic::weights(&arch, seed);
    let obs = synthetic::observations(usize::from(arch.obs_dim), GOLDEN_STEPS, seed);
    let mut reference = ReferencePolicy::new(shape(&arch), &weights);
    let means = obs.iter().map(|o| reference.step(o)).collect();
    (obs, means)
}

/// The golden file text of `row`.
pub fn golden_text(row: TableRow) -> String {
    let arch = Architecture::table1(row);
    let (obs, means) = golden_sequence(row);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Overtake golden vectors: synthetic weights (firmware_core::synthetic),"
    );
    let _ = writeln!(
        s,
        "# expected Gaussian means from the float64 reference (tests/src/reference.rs)."
    );
    let _ = writeln!(
        s,
        "# Regenerate with OVERTAKE_BLESS=1 cargo test -p overtake-tests --test golden_vectors"
    );
    let _ = writeln!(s, "row {}", row.letter());
    let _ = writeln!(s, "seed {}", golden_seed(row));
    let _ = writeln!(s, "dim {}", arch.obs_dim);
    for (o, m) in obs.iter().zip(&means) {
        let _ = writeln!(
            s,
            "obs {}",
            o.iter()
                .map(|v| format!("{v:?}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
        let _ = writeln!(
            s,
            "mean {}",
            m.iter()
                .map(|v| format!("{v:.17e}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    s
}
