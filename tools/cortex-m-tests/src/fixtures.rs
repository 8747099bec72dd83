//! Fixed inputs shared by the build script (on the host) and the images (on the Cortex-M4):
//! the build script computes expected values from them with the host's firmware-core, the
//! test image recomputes them on the M4 and compares.
//!
//! This file is compiled twice: as `cortex_m_tests::fixtures` and, through `#[path]`, inside
//! `build.rs`. It may only use `core` and `firmware_core`.

use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{FIGURE_EIGHT, Gate};
use firmware_core::vehicle::VehicleState;

/// The inputs of one observation: own state, opponent, target gate, previous action.
#[derive(Clone, Copy, Debug)]
pub struct ObservationCase {
    /// The own vehicle.
    pub own: VehicleState,
    /// The opponent.
    pub opponent: VehicleState,
    /// The target gate.
    pub gate: Gate,
    /// The previous (clipped) action.
    pub previous_action: [f32; 4],
}

/// A 30-value observation case: a tilted drone flying fast towards the figure-8's upside-down
/// gate 1, an opponent spinning beside it. Several terms saturate at the clip.
pub fn observation_case() -> ObservationCase {
    ObservationCase {
        own: VehicleState {
            position_m: Vec3::new(1.5, -2.25, 0.8),
            attitude: Quat::new(0.92, 0.12, -0.28, 0.23).normalized(),
            velocity_mps: Vec3::new(4.2, -1.1, 0.35),
            body_rates_radps: Vec3::new(0.6, -4.5, 1.2),
        },
        opponent: VehicleState {
            position_m: Vec3::new(3.0, 1.0, 1.4),
            attitude: Quat::new(0.7, -0.1, 0.2, 0.68).normalized(),
            velocity_mps: Vec3::new(-2.0, 5.0, -0.5),
            body_rates_radps: Vec3::new(2.5, 0.3, -7.0),
        },
        gate: FIGURE_EIGHT[1],
        previous_action: [0.25, -1.0, 0.5, 1.0],
    }
}

/// Steps of the benchmark flight (2 s at 50 Hz).
pub const FLIGHT_STEPS: u32 = 100;

/// Own and opponent state at `step` of a straight 2.5 m/s flight through the figure-8's gate 0
/// (crossed at step 60, so the gate test and the target switch run too), no trigonometry.
pub fn flight(step: u32) -> (VehicleState, VehicleState) {
    let t = step as f32 * 0.02;
    let own = VehicleState {
        position_m: Vec3::new(-3.0, 0.4, 1.1) + Vec3::new(2.5, -0.1, 0.05) * t,
        attitude: Quat::new(0.995, 0.01, 0.06, -0.02).normalized(),
        velocity_mps: Vec3::new(2.5, -0.1, 0.05),
        body_rates_radps: Vec3::new(0.1, -0.2, 0.05 + 0.01 * t),
    };
    let opponent = VehicleState {
        position_m: Vec3::new(-4.0, -0.6, 1.0) + Vec3::new(2.6, 0.05, 0.0) * t,
        attitude: Quat::new(0.99, -0.02, 0.05, 0.1).normalized(),
        velocity_mps: Vec3::new(2.6, 0.05, 0.0),
        body_rates_radps: Vec3::new(-0.3, 0.1, 0.4),
    };
    (own, opponent)
}
