//! Build script of the STM32F405 fit image (runs on the host).
//!
//! * puts this crate's `memory.x` (STM32F405: 1 MB flash, 128 KB SRAM) on the linker search
//!   path for cortex-m-rt's `link.x`;
//! * writes `stage1.bin` and `stage2.bin` to `OUT_DIR`: the stage-1 (row A) and stage-2
//!   (row G) policies `policy_source::source_blob` picks (the first shipped candidate of each
//!   slot, else synthetic weights) converted to int8 (`firmware_core::blob::convert_bytes`).
//!   With feature `f32`, the f32 blobs instead.
use std::env;
use std::fs;
use std::path::PathBuf;

use firmware_core::blob::{WeightDtype, convert_bytes};

#[path = "policy_source.rs"]
mod policy_source;

fn main() {
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR"));
    let root = manifest.join("../..");
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-changed=policy_source.rs");
    println!("cargo::rerun-if-changed=memory.x");
    for slot in policy_source::IMAGE_POLICIES {
        for p in slot.candidates {
            println!("cargo::rerun-if-changed={}", root.join(p).display());
        }
    }
    fs::copy(manifest.join("memory.x"), out.join("memory.x")).expect("copy memory.x");
    println!("cargo::rustc-link-search={}", out.display());

    let dtype = if env::var_os("CARGO_FEATURE_F32").is_some() {
        WeightDtype::F32
    } else {
        WeightDtype::I8
    };
    for (n, slot) in policy_source::IMAGE_POLICIES.iter().enumerate() {
        let (what, source) = policy_source::source_blob(&root, slot)
            .unwrap_or_else(|e| panic!("the {} blob: {e}", slot.role));
        let bytes = convert_bytes(&source, dtype).unwrap_or_else(|e| panic!("{what}: {e}"));
        let file = format!("stage{}.bin", n + 1);
        fs::write(out.join(&file), &bytes).unwrap_or_else(|e| panic!("write {file}: {e}"));
    }
}
