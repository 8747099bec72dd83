//! # sitl
//!
//! The simulated world Overtake races in: cf2x quadrotor dynamics ([`dynamics`]) flying the
//! figure-8 of `firmware-core`. The referee that scores races and the MAVLink bridge that
//! flies firmware-core controllers as separate processes build on this crate (issues
//! "world" and "sitl").
//!
//! The track, the gate tests and the observation pipeline are firmware-core's: nothing here
//! re-implements them.
#![deny(missing_docs)]

pub mod dynamics;
pub mod time_trial;
