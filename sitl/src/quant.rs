//! int8 against f32 (issue "int8"): how far an int8 blob's actions are from its f32
//! original's on the same observations, and what that does to the race.
//!
//! The action error is measured on the observation sequences of races the **f32** policy
//! flies: each step, the f32 controller's next observation
//! ([`Controller::peek_folded_observation`]) also goes through the int8 policy, which keeps
//! its own recurrent state, reset when the f32 controller is. Errors are between the clipped
//! network outputs (what the motors get, before a folded step's renumbering, which permutes
//! both alike), per component. The race metrics of the int8 blob come from flying it itself, with the same
//! seeds ([`crate::eval::report`]).

use crate::eval::{EvalConfig, Report};
use crate::pilot::{Pilot, PilotSpec};
use crate::referee::{EpisodeMetrics, run_episode};
use firmware_core::blob::{AlignedBytes, Blob, WeightDtype, convert_bytes};
use firmware_core::mirror::unfold_action;
use firmware_core::policy::{Policy, PolicyState};
use firmware_core::track::Track;
use firmware_core::vehicle::{MotorCommand, VehicleState};
use firmware_core::{Controller, Observation};
use rayon::prelude::*;
use serde::Serialize;

/// The action error of the int8 policy along the f32 policy's flights.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ActionError {
    /// Steps compared (each has 4 action components).
    pub steps: u64,
    /// Largest |a_int8 − a_f32| of any component and step.
    pub max_abs: f32,
    /// Mean |a_int8 − a_f32| over components and steps.
    pub mean_abs: f64,
    /// Largest error of the unclipped means (the network outputs).
    pub max_abs_unclipped: f32,
    /// The largest error of each episode.
    pub episode_max_abs: Vec<f32>,
    /// Steps where the f32 policy replayed beside the controller did not give the
    /// controller's action (a self-check of the method: must be 0).
    pub replay_mismatches: u64,
}

/// The f32 controller flying, with the int8 policy computing on its observations.
struct Shadow<'a> {
    flying: Controller<'a>,
    int8: Policy<'a>,
    state: PolicyState,
    /// The f32 policy's state, advanced beside the controller's to read its unclipped means.
    f32_state: PolicyState,
    max: f32,
    max_unclipped: f32,
    sum: f64,
    steps: u64,
    replay_mismatches: u64,
}

impl Pilot for Shadow<'_> {
    fn command(&mut self, own: &VehicleState, opponent: Option<&VehicleState>) -> MotorCommand {
        let peeked: Option<(Observation, bool)> =
            self.flying.peek_folded_observation(own, opponent).ok();
        let out = self.flying.step(own, opponent);
        if let (Some((obs, folded)), None) = (peeked, out.fault) {
            let f32_mean = self.flying.policy().act(&obs, &mut self.f32_state);
            if let (Some(mean), Some(f32_mean)) = (self.int8.act(&obs, &mut self.state), f32_mean) {
                self.steps += 1;
                let clipped = f32_mean.map(|m| m.clamp(-1.0, 1.0));
                if unfold_action(self.flying.mirror(), folded, &clipped) != out.action {
                    self.replay_mismatches += 1;
                }
                for ((a, q), m) in clipped.iter().zip(mean).zip(f32_mean) {
                    let d = (a - q.clamp(-1.0, 1.0)).abs();
                    self.max = self.max.max(d);
                    self.sum += f64::from(d);
                    self.max_unclipped = self.max_unclipped.max((m - q).abs());
                }
            }
        }
        out.command
    }

    fn reset(&mut self, target_gate: usize) {
        self.flying.reset(target_gate);
        self.state.clear();
        self.f32_state.clear();
    }
}

/// Why an int8 check cannot run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuantError(pub String);

impl core::fmt::Display for QuantError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for QuantError {}

/// The outcome of [`compare`].
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    /// The action error along the f32 flights.
    pub action_error: ActionError,
    /// The f32 blob's race metrics (the flights the error was measured on).
    pub f32_report: Report,
    /// The int8 blob's race metrics, flown itself with the same seeds.
    pub int8_report: Report,
    /// Bytes of the f32 and the int8 blob.
    pub blob_bytes: [usize; 2],
}

impl Comparison {
    /// True when the int8 success and crash rates lie inside the f32 blob's 95% intervals.
    pub fn within_f32_intervals(&self) -> bool {
        let inside = |x: f64, ci: Option<[f64; 2]>| ci.is_some_and(|[a, b]| x >= a && x <= b);
        inside(
            self.int8_report.success_rate,
            self.f32_report.success_rate_ci95,
        ) && inside(self.int8_report.crash_rate, self.f32_report.crash_rate_ci95)
    }
}

/// Flies `config` with the f32 blob `f32_blob` as the ego (against `opponent`, if any),
/// measuring its int8 conversion's action error on the way, then flies the int8 blob itself
/// with the same seeds. `f32_blob` must be an f32 blob.
pub fn compare(
    f32_blob: &[u8],
    opponent: Option<&PilotSpec>,
    config: &EvalConfig,
) -> Result<Comparison, QuantError> {
    let f32_bytes = AlignedBytes::new(f32_blob);
    let parsed = Blob::parse(f32_bytes.as_bytes()).map_err(|e| QuantError(e.to_string()))?;
    if parsed.header().dtype != WeightDtype::F32 {
        return Err(QuantError(
            "the blob is already int8: give the f32 blob it came from".into(),
        ));
    }
    if parsed.header().observation.layout.needs_opponent() && opponent.is_none() {
        return Err(QuantError(
            "the policy observes an opponent: give one (--opponent)".into(),
        ));
    }
    let int8 = convert_bytes(f32_blob, WeightDtype::I8).map_err(|e| QuantError(e.to_string()))?;
    let int8_bytes = AlignedBytes::new(&int8);
    let race = opponent.is_some();
    let world = config.world(race);
    let episode = config.episode(race);
    let track: Track<'static> = world.track;
    let flying = crate::pilot::world_rate_controller(f32_bytes.as_bytes(), track)
        .map_err(|e| QuantError(e.to_string()))?;
    let int8_policy = Blob::parse(int8_bytes.as_bytes())
        .and_then(|b| b.policy())
        .map_err(|e| QuantError(e.to_string()))?;
    let flights: Vec<(EpisodeMetrics, Shadow<'_>)> = (0..config.episodes)
        .into_par_iter()
        .map(|i| {
            let mut shadow = Shadow {
                flying: flying.clone(),
                int8: int8_policy,
                state: int8_policy.initial_state(),
                f32_state: int8_policy.initial_state(),
                max: 0.0,
                max_unclipped: 0.0,
                sum: 0.0,
                steps: 0,
                replay_mismatches: 0,
            };
            let metrics = match opponent {
                Some(o) => {
                    let mut o = o.build(track);
                    run_episode(
                        &world,
                        &mut shadow,
                        Some(&mut *o),
                        &episode,
                        u64::from(i),
                        false,
                    )
                }
                None => run_episode(&world, &mut shadow, None, &episode, u64::from(i), false),
            }
            .metrics;
            (metrics, shadow)
        })
        .collect();
    let mut action_error = ActionError::default();
    let mut sum = 0.0;
    for (_, e) in &flights {
        action_error.steps += e.steps;
        action_error.max_abs = action_error.max_abs.max(e.max);
        action_error.max_abs_unclipped = action_error.max_abs_unclipped.max(e.max_unclipped);
        action_error.episode_max_abs.push(e.max);
        action_error.replay_mismatches += e.replay_mismatches;
        sum += e.sum;
    }
    action_error.mean_abs = sum / (4 * action_error.steps.max(1)) as f64;
    let f32_spec = PilotSpec::from_blob("f32", f32_blob).map_err(QuantError)?;
    let int8_spec = PilotSpec::from_blob("int8", &int8).map_err(QuantError)?;
    let metrics: Vec<EpisodeMetrics> = flights.into_iter().map(|(m, _)| m).collect();
    Ok(Comparison {
        action_error,
        f32_report: Report::new(&f32_spec, opponent, config, &metrics),
        int8_report: crate::eval::report(&int8_spec, opponent, config),
        blob_bytes: [f32_blob.len(), int8.len()],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::Preset;

    fn config(episodes: u32) -> EvalConfig {
        EvalConfig {
            preset: Preset::paper(),
            episodes,
            seconds: 6.0,
            seed: 3,
            spawn: None,
            perturbation: crate::perturb::Perturbation::NONE,
        }
    }

    #[test]
    fn the_int8_stage1_policy_acts_like_its_f32_original() {
        let blob = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../policies/stage1_guarded.blob"
        ))
        .expect("the shipped stage-1 policy");
        let c = compare(&blob, None, &config(3)).expect("compare");
        let e = &c.action_error;
        println!("{e:?}");
        assert_eq!(e.steps, 3 * 300, "every step compared");
        assert_eq!(e.replay_mismatches, 0);
        assert_eq!(e.episode_max_abs.len(), 3);
        assert!(e.max_abs > 0.0 && e.max_abs < 0.1, "{}", e.max_abs);
        assert!(e.mean_abs > 0.0 && e.mean_abs < 0.03, "{}", e.mean_abs);
        assert!(c.blob_bytes[1] * 3 < c.blob_bytes[0]);
        assert_eq!(c.f32_report.episodes, 3);
        assert_eq!(c.int8_report.episodes, 3);
    }

    /// A folded blob (`policies/stage1.blob`): the controller renumbers the motors of the
    /// steps flying g3-g5, and the replay beside it follows (the self-check counted every
    /// such step as a mismatch before).
    #[test]
    fn a_folded_policy_replays_exactly() {
        let blob = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../policies/stage1.blob"
        ))
        .expect("the shipped stage-1 policy");
        let header = Blob::parse(AlignedBytes::new(&blob).as_bytes())
            .expect("parse")
            .header()
            .observation;
        assert!(header.is_folded());
        // From the stage-1 spawn the first lap reaches g3 within 4 s.
        let c = compare(&blob, None, &config(1)).expect("compare");
        assert_eq!(c.action_error.steps, 300);
        assert_eq!(c.action_error.replay_mismatches, 0);
    }

    #[test]
    fn refuses_an_int8_blob_and_a_race_policy_without_an_opponent() {
        let f32_blob = firmware_core::synthetic::blob(firmware_core::TableRow::A, 1).expect("A");
        let int8 = convert_bytes(&f32_blob, WeightDtype::I8).expect("i8");
        let err = compare(&int8, None, &config(1)).expect_err("int8 input");
        assert!(err.0.contains("already int8"), "{err}");
        let g = firmware_core::synthetic::blob(firmware_core::TableRow::G, 1).expect("G");
        let err = compare(&g, None, &config(1)).expect_err("no opponent");
        assert!(err.0.contains("opponent"), "{err}");
    }
}
