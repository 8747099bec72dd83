//! A single-drone time trial on a track (SPEC stage 1): spawn at (−1, −1, 1) at rest, fly for
//! a fixed time, respawn after every crash with the clock running on, time the laps.
//!
//! The gate tests, crash rules and bookkeeping are firmware-core's; this module only applies
//! them to a simulated [`Body`]. The two-drone referee of the "world" issue extends it.

use crate::dynamics::{Body, Preset};
use firmware_core::baseline::BaselineController;
use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{CrashRules, GateEvent, GateProgress, Track};
use firmware_core::vehicle::{MotorCommand, VehicleState};

/// Anything that flies a drone: one motor command per control step.
pub trait Pilot {
    /// The command for the drone's current state.
    fn command(&mut self, own: &VehicleState) -> MotorCommand;
    /// A new flight from a spawn, targeting `target_gate`.
    fn reset(&mut self, target_gate: usize);
}

impl Pilot for BaselineController<'_> {
    fn command(&mut self, own: &VehicleState) -> MotorCommand {
        self.step(own).0
    }
    fn reset(&mut self, target_gate: usize) {
        BaselineController::reset(self, target_gate);
    }
}

/// A learned controller flies alone (a time trial): it sees no opponent.
impl Pilot for firmware_core::Controller<'_> {
    fn command(&mut self, own: &VehicleState) -> MotorCommand {
        self.step(own, None).command
    }
    fn reset(&mut self, target_gate: usize) {
        firmware_core::Controller::reset(self, target_gate);
    }
}

/// Stage-1 spawn of the paper's code: (−1, −1, 1) m, level, at rest, first target g0.
pub fn stage1_spawn() -> VehicleState {
    VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY)
}

/// What a time trial measured.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TimeTrialSummary {
    /// Simulated time (s).
    pub sim_seconds: f32,
    /// Gates passed.
    pub gates_passed: u32,
    /// Gates passed plus gates that were the target at a crash.
    pub gates_encountered: u32,
    /// Crash resets.
    pub crashes: u32,
    /// Times of the complete laps g0 → g0 without a crash inside (s), in order.
    pub lap_times_s: Vec<f32>,
}

impl TimeTrialSummary {
    /// Gates passed / gates encountered (1 when none was encountered).
    pub fn success_rate(&self) -> f32 {
        if self.gates_encountered == 0 {
            1.0
        } else {
            self.gates_passed as f32 / self.gates_encountered as f32
        }
    }

    /// Crash resets per second.
    pub fn crash_rate_per_s(&self) -> f32 {
        if self.sim_seconds > 0.0 {
            self.crashes as f32 / self.sim_seconds
        } else {
            0.0
        }
    }

    /// The fastest complete lap (s), `None` for a DNF.
    pub fn best_lap_s(&self) -> Option<f32> {
        self.lap_times_s.iter().copied().reduce(f32::min)
    }
}

/// Flies `pilot` on `track` with `preset` dynamics for `seconds` at control period `dt_s`.
pub fn fly(
    pilot: &mut dyn Pilot,
    track: &Track<'_>,
    preset: &Preset,
    seconds: f32,
    dt_s: f32,
) -> TimeTrialSummary {
    let rules = CrashRules::STAGE1;
    let mut body = Body::new(stage1_spawn());
    let mut progress = GateProgress::targeting(0);
    pilot.reset(0);
    let steps = (seconds / dt_s).round() as u32;
    let mut summary = TimeTrialSummary {
        sim_seconds: steps as f32 * dt_s,
        ..Default::default()
    };
    let mut lap_start_s: Option<f32> = None;
    for k in 0..steps {
        let command = pilot.command(&body.state);
        let from = body.state.position_m;
        body.step(preset, &command, dt_s);
        let t = (k + 1) as f32 * dt_s;
        let to = body.state.position_m;
        let event = progress.advance(track, from, to);
        let target = track.gate(progress.target).center_m;
        let crashed = matches!(event, GateEvent::Collided { .. })
            || !body.state.is_finite()
            || rules.below_ground(to)
            || rules.out_of_bounds(target, to);
        if crashed {
            summary.crashes += 1;
            summary.gates_encountered += 1;
            body = Body::new(stage1_spawn());
            progress = GateProgress::targeting(0);
            pilot.reset(0);
            lap_start_s = None;
            continue;
        }
        if let GateEvent::Passed { gate, .. } = event {
            summary.gates_passed += 1;
            summary.gates_encountered += 1;
            if gate == 0 {
                if let Some(t0) = lap_start_s {
                    summary.lap_times_s.push(t - t0);
                }
                lap_start_s = Some(t);
            }
        }
    }
    summary
}
