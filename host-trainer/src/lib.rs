//! # host-trainer
//!
//! Turns the simulator into trained racing policies and the policies into flash blobs.
//! Today it holds the vectorised training environment ([`env`](mod@env): sitl worlds in parallel, the
//! SPEC reward term by term, firmware-core's observations), the run configuration
//! ([`config`]), the export path every trainer will use ([`export`]: f32 weights in payload
//! order written as a firmware-core blob), and the interchange with RSL-RL, the paper's own
//! stack ([`rslrl`]), the feed-forward actor and critic on `burn` ([`model`]), the LSTM
//! actor and critic of rows E-G with a fused cell ([`recurrent`]), PPO and recurrent PPO
//! ([`ppo`]) and the training run with its checkpoints, metrics and export ([`train`]). The
//! environment is the stage-1 time trial or, with a `[race]` config, the stage-2 race
//! against a frozen opponent blob.
#![deny(missing_docs)]

pub mod config;
pub mod env;
pub mod export;
pub mod imitation;
pub mod model;
pub mod ppo;
pub mod recurrent;
pub mod rslrl;
pub mod train;
