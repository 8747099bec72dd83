//! # host-trainer
//!
//! Learning: turns sitl's vectorised environments ([`sitl::env`]) into trained racing
//! policies and the policies into flash blobs. One module per job:
//!
//! | module | job |
//! |---|---|
//! | [`config`] | the run's TOML configuration, its defaults and named presets |
//! | [`setup`] | what a run derives from its config: row, architecture, preset, observation spec, environment |
//! | [`train`] | the run: start or resume, the iteration loop, evaluation, export at the end |
//! | [`rollout`] | the rollout buffer and collecting it with the deployed network |
//! | [`batch`] | a rollout as PPO's samples: GAE, log-likelihoods, minibatches, recurrent windows |
//! | [`ppo`] | the PPO update (RSL-RL's algorithm), feed-forward and recurrent |
//! | [`nets`] | the traits PPO needs of a network |
//! | [`model`] | the feed-forward actor and critic (rows A-D) on `burn` |
//! | [`recurrent`] | the LSTM actor and critic (rows E-G) with a fused cell |
//! | [`fused`] | the PPO minibatch step by hand, feed-forward and recurrent: forward, loss, backward, clip, Adam |
//! | [`update`] | what one PPO update reports, and the KL-adaptive learning rate both updates share |
//! | [`grads`] | gradient norms, clipping and moving gradients between network copies |
//! | [`guard`] | the optional line search of each update on the measured return |
//! | [`imitation`] | DAgger: one round collector, the feed-forward and recurrent regressions |
//! | [`warm_start`] | the warm start's stages, logs and round selection before PPO |
//! | [`transplant`] | a time-trial MLP embedded exactly in a larger row's network (`warm_start.transplant`) |
//! | [`evaluation`] | the referee inside a run and how `keep_best` ranks its verdicts |
//! | [`memory`] | a run's memory estimated from its config and checked before allocation |
//! | [`metrics`] | `metrics.jsonl` lines, learning curves, the terminal |
//! | [`run_dir`] | the output directory: checkpoints (atomic), resume, metrics files |
//! | [`latest`] | a run's latest checkpoint as a learner, an actor or a blob, outside the loop |
//! | [`export`] | the only blob-header builder; actor to blob and safetensors, blob to actor |
//! | [`rslrl`] | interchange with RSL-RL, the paper's own stack |
//! | [`rng`] | the run's seeded random streams |
//! | [`error`] | why a run stopped |
#![deny(missing_docs)]

pub mod batch;
pub mod config;
pub mod error;
pub mod evaluation;
pub mod export;
pub mod fused;
pub mod grads;
pub mod guard;
pub mod imitation;
pub mod latest;
pub mod memory;
pub mod metrics;
pub mod model;
pub mod nets;
pub mod ppo;
pub mod recurrent;
pub mod rng;
pub mod rollout;
pub mod rslrl;
pub mod run_dir;
pub mod setup;
pub mod train;
pub mod transplant;
pub mod update;
pub mod warm_start;
