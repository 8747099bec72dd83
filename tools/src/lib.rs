//! Overtake's command-line helpers (`cargo run -p tools -- <subcommand>`):
//!
//! * `inspect <blob>`: decode a weight blob with firmware-core and print its header, or the
//!   typed [`firmware_core::BlobError`] (non-zero exit);
//! * `convert --dtype f32|i8 --in BLOB --out BLOB`, `synth-blob --row X --out FILE`:
//!   re-encode a blob, or write one with seeded random weights ([`blobs`]);
//! * `size-report`: build the Cortex-M4 size images (one f32 blob each, rows A and G, profile
//!   `firmware`) and report their flash and RAM from the ELF against an STM32F405;
//! * `overtake-figure --trace FILE`: an overtake of a recorded race drawn from above, like
//!   the paper's Fig. 3 ([`figure`]);
//! * `learning-curves --run DIR[=LABEL] ...`: training runs (ours or RSL-RL's) against
//!   samples and wall-clock on one page, beside the authors' run ([`curves`]);
//! * `cortex-m test`, `cortex-m icount [--breakdown]`: run the QEMU test image or the
//!   instruction-count bench (`tools/cortex-m-tests`, see `docs/cortex-m.md`).
//!
//! The command line is [`cli::Cli`] (clap derive; `--help` on any subcommand documents its
//! flags); the logic lives in the modules below, and `main.rs` only calls [`cli::main`].

pub mod blobs;
pub mod cli;
pub mod cortex_m;
pub mod curves;
pub mod error;
pub mod figure;
pub mod inspect;
pub mod manoeuvre;
pub mod size;

pub use error::{Error, Result};
