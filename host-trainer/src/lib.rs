//! # host-trainer
//!
//! Turns the simulator into trained racing policies and the policies into flash blobs.
//! Today it holds the export path every trainer will use ([`export`]): a flat list of f32
//! weights in payload order, with its architecture, observation spec and provenance, written
//! as a firmware-core blob. PPO and recurrent PPO on `burn` come with the "stage1" and
//! "stage2" issues.
#![deny(missing_docs)]

pub mod config;
pub mod env;
pub mod export;
pub mod rslrl;
