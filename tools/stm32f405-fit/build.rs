//! Build script of the STM32F405 fit image (runs on the host).
//!
//! * puts this crate's `memory.x` (STM32F405: 1 MB flash, 128 KB SRAM) on the linker search
//!   path for cortex-m-rt's `link.x`;
//! * writes `policy.bin` to `OUT_DIR`: the first shipped row-G policy of `SHIPPED_G`
//!   converted to int8 (`firmware_core::blob::convert_bytes`), or, with none, row G's
//!   synthetic weights in int8 (an int8 G blob's length depends only on the architecture and
//!   a few header bytes). With feature `f32`, the f32 blob instead.
use std::env;
use std::fs;
use std::path::PathBuf;

use firmware_core::blob::{WeightDtype, convert_bytes};
use firmware_core::policy::TableRow;
use firmware_core::synthetic;

/// The row-G blobs the image holds, in order of preference (as `tools size-report` reads
/// them): the stage-2 policy, then the imitation student of `configs/stage2_G.toml`.
const SHIPPED_G: [&str; 2] = ["policies/stage2.blob", "policies/stage2_G_student.blob"];

fn main() {
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR"));
    let root = manifest.join("../..");
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=memory.x");
    for p in SHIPPED_G {
        println!("cargo::rerun-if-changed={}", root.join(p).display());
    }
    fs::copy(manifest.join("memory.x"), out.join("memory.x")).expect("copy memory.x");
    println!("cargo::rustc-link-search={}", out.display());

    let dtype = if env::var_os("CARGO_FEATURE_F32").is_some() {
        WeightDtype::F32
    } else {
        WeightDtype::I8
    };
    let shipped = SHIPPED_G
        .iter()
        .find_map(|p| fs::read(root.join(p)).ok().map(|b| (*p, b)));
    let (what, source) = match shipped {
        Some(found) => found,
        None => (
            "synthetic G",
            synthetic::blob(TableRow::G, synthetic::golden_seed(TableRow::G))
                .expect("synthetic G blob"),
        ),
    };
    let bytes = convert_bytes(&source, dtype).unwrap_or_else(|e| panic!("{what}: {e}"));
    fs::write(out.join("policy.bin"), &bytes).expect("write policy.bin");
}
