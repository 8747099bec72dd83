//! Overtake's command-line helpers (`cargo run -p tools -- <subcommand>`):
//!
//! * `inspect <blob>`: decode a weight blob with firmware-core and print its header, or the
//!   typed [`firmware_core::BlobError`] (non-zero exit);
//! * `size-report`: build the Cortex-M4 size images (one f32 blob each, rows A and G, profile
//!   `firmware`) and report their flash and RAM from the ELF against an STM32F405;
//! * `overtake-figure --trace FILE`: an overtake of a recorded race drawn from above, like
//!   the paper's Fig. 3 ([`figure`]);
//! * `learning-curves --run DIR[=LABEL] ...`: training runs (ours or RSL-RL's) against
//!   samples and wall-clock on one page, beside the authors' run ([`curves`]);
//! * `cortex-m test`, `cortex-m icount [--breakdown]`: run the QEMU test image or the
//!   instruction-count bench (`tools/cortex-m-tests`, see `docs/cortex-m.md`).
//!
//! The logic lives in the modules below; `main.rs` only forwards the arguments to
//! [`cli::main`].

pub mod cli;
pub mod cortex_m;
pub mod curves;
pub mod error;
pub mod figure;
pub mod inspect;
pub mod size;

pub use error::{Error, Result};
