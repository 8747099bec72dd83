//! # sitl
//!
//! The simulated world Overtake races in, and everything that steps it:
//!
//! | module | owns |
//! |---|---|
//! | [`dynamics`] | cf2x rigid-body dynamics (RK4 substeps) and the presets `paper`, `nominal`, `realistic` |
//! | [`world`] | worlds of one or two drones on firmware-core's figure-8: stepping, gate passes, crash rules, spawn points |
//! | [`mirror`] | the figure-8's mirror symmetry (x = 0): reflected states, gates and motors, for symmetry augmentation |
//! | [`mod@env`] | the vectorised environments any learner steps: time trial and race, spawns, auto-reset, reward terms, time-outs |
//! | [`perturb`] | what the referee can perturb: start jitter, the ego's airframe, motor lag, latency, sensor noise |
//! | [`pilot`] | who flies a drone: the classical baseline or a blob's controller (both firmware-core) |
//! | [`referee`] | scoring of 45 s episodes: gates, crashes by cause, laps, progress, overtakes; the episode runner |
//! | [`eval`] | many seeded episodes in parallel, aggregated with 95% intervals, as text and JSON (`sitl eval`) |
//! | [`robustness`] | the robustness sweep: standard perturbation levels, f32 and int8, the largest level survived (`sitl robustness`) |
//! | [`stats`] | means and Student-t 95% intervals |
//! | [`quant`] | int8 against f32: action error and both blobs' race metrics (`sitl int8-check`) |
//! | [`frames`] | ENU/FLU to NED/FRD conversions, for the bridge and for in-process pilots alike |
//! | [`bridge`] | MAVLink lockstep races: a controller as an endpoint, the simulator as the clock, the ground station, framing and signing |
//! | [`plot`] | standalone SVG plots: learning curves, the top-down view of a race |
//! | [`replay`] | the 3-D replay of recorded episodes: one self-contained HTML page (three.js) |
//! | [`files`] | atomic file writes |
//! | [`shipped`] | the shipped policies the commands fly when none is named |
//!
//! The track, the gate tests, the crash rules and the observation pipeline are
//! firmware-core's: nothing here re-implements them. Nothing here knows of a learning
//! library: host-trainer (burn) and Python learners step [`mod@env`] from outside.
#![deny(missing_docs)]

pub mod bridge;
pub mod dynamics;
pub mod env;
pub mod eval;
pub mod files;
pub mod frames;
pub mod lanes;
pub mod mirror;
pub mod perturb;
pub mod pilot;
pub mod plot;
pub mod quant;
pub mod referee;
pub mod replay;
pub mod robustness;
pub mod shipped;
pub mod stats;
pub mod world;
