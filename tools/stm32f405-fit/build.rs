//! Build script of the STM32F405 fit image (runs on the host).
//!
//! * puts this crate's `memory.x` (STM32F405: 1 MB flash, 128 KB SRAM) on the linker search
//!   path for cortex-m-rt's `link.x`;
//! * writes `policy.bin` to `OUT_DIR`: the shipped row-G policy, `policies/stage2.blob`,
//!   converted to int8 (`firmware_core::blob::convert_bytes`); while that blob does not exist, row
//!   G's synthetic weights in int8 (the same size: an int8 G blob's length depends only on
//!   the architecture and the header). With feature `f32`, the f32 blob instead.
use std::env;
use std::fs;
use std::path::PathBuf;

use firmware_core::blob::{WeightDtype, convert_bytes};
use firmware_core::policy::TableRow;
use firmware_core::synthetic;

fn main() {
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR"));
    let shipped = manifest.join("../../policies/stage2.blob");
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=memory.x");
    println!("cargo::rerun-if-changed={}", shipped.display());
    fs::copy(manifest.join("memory.x"), out.join("memory.x")).expect("copy memory.x");
    println!("cargo::rustc-link-search={}", out.display());

    let dtype = if env::var_os("CARGO_FEATURE_F32").is_some() {
        WeightDtype::F32
    } else {
        WeightDtype::I8
    };
    let source = match fs::read(&shipped) {
        Ok(bytes) => bytes,
        Err(_) => synthetic::blob(TableRow::G, synthetic::golden_seed(TableRow::G))
            .expect("synthetic G blob"),
    };
    let bytes =
        convert_bytes(&source, dtype).unwrap_or_else(|e| panic!("{}: {e}", shipped.display()));
    fs::write(out.join("policy.bin"), &bytes).expect("write policy.bin");
}
