//! # sitl
//!
//! The simulated world Overtake races in: cf2x quadrotor dynamics ([`dynamics`]), worlds of
//! one or two drones on firmware-core's figure-8 with the crash rules ([`world`]), the pilots
//! that fly them ([`pilot`]), the referee that scores 45 s episodes ([`referee`]), and
//! evaluation over many seeded episodes with 95% intervals ([`eval`]), SVG plots
//! ([`plot`]) and atomic file writes ([`files`]), and the MAVLink bridge that races
//! firmware-core controllers as separate MAVLink endpoints in lockstep ([`bridge`]).
//!
//! The track, the gate tests, the crash rules and the observation pipeline are
//! firmware-core's: nothing here re-implements them.
#![deny(missing_docs)]

pub mod bridge;
pub mod dynamics;
pub mod eval;
pub mod files;
pub mod frames;
pub mod pilot;
pub mod plot;
pub mod quant;
pub mod referee;
pub mod stats;
pub mod world;
