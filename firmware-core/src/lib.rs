//! # firmware-core
//!
//! The `#![no_std]`, allocation-free half of Overtake: everything a flight controller needs to
//! fly a trained racing policy, and everything the simulator and trainer must share with it.
//!
//! * [`track`]: gates, the paper's figure-8, next-gate bookkeeping, the gate-plane tests;
//! * [`observation`]: the 17-, 20- and 30-value observations (docs/DESIGN.md "Observations");
//! * [`mirror`]: the track's mirror symmetry and the folded observation that uses it;
//! * [`nn`] and [`policy`]: fixed-size Linear / LSTM / MLP inference and the Table 1
//!   architectures A–G, viewing weights in place;
//! * [`blob`]: the flash-ready weight format (postcard header, aligned payload, CRC-32);
//! * [`controller`]: the learned controller, with a fail-safe for bad inputs;
//! * [`baseline`]: a classical cascaded controller that flies the same track.
//!
//! Frames: world z up; body x forward, y left, z up; quaternions (w, x, y, z) map body to
//! world. Units are SI (m, s, rad) unless a name says otherwise (`rpm`, `_ns`).
//!
//! Feature `std` adds the blob encoder (`blob::encode`, `encode_i8`, `convert`, ...) and
//! `blob::AlignedBytes` for host tools.
#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]
#![cfg_attr(
    not(test),
    deny(clippy::unwrap_used, clippy::expect_used, clippy::panic)
)]
#![cfg_attr(not(test), deny(clippy::indexing_slicing))]

pub mod baseline;
pub mod blob;
pub mod controller;
pub mod crc32;
mod format;
pub mod math;
pub mod mirror;
pub mod nn;
pub mod observation;
pub mod policy;
#[cfg(feature = "std")]
pub mod synthetic;
pub mod track;
pub mod vehicle;

pub use baseline::{BaselineConfig, BaselineController};
pub use blob::{Blob, BlobError, BlobHeader};
pub use controller::{Controller, ControllerError, StepFault, StepOutput};
pub use math::{Quat, Vec3};
pub use observation::{Observation, ObservationLayout, ObservationSpec};
pub use policy::{Architecture, Policy, PolicyState, TableRow};
pub use track::{Centerline, Gate, GateCrossing, GateEvent, GateProgress, Track};
pub use vehicle::{ActionMap, Cf2x, MotorCommand, PAPER_CONTROL_PERIOD_NS, VehicleState};
