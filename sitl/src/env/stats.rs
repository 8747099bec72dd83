//! What the environments count: per batch ([`EnvStats`]) and per env and step
//! ([`StepRecord`]).

use super::RewardTerms;

/// Per-step statistics of the whole batch, drained by [`super::VecEnv::take_stats`].
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EnvStats {
    /// Env-steps taken.
    pub steps: u64,
    /// Reward terms summed over those steps.
    pub terms: RewardTerms,
    /// Gates passed.
    pub gates_passed: u64,
    /// Crashes (episode ends that are not time-outs).
    pub crashes: u64,
    /// Episodes ended by the time limit.
    pub timeouts: u64,
    /// Stage 2: episodes ended by the opponent's crash alone (truncations).
    pub opponent_crashes: u64,
    /// Action components that were NaN or infinite, flown as 0 ([`super::VecEnv::step`]): a
    /// learner that counts any has diverged.
    pub nonfinite_actions: u64,
}

impl EnvStats {
    /// Gates passed / (gates passed + crashes): the success rate of docs/DESIGN.md "Metrics" over the
    /// steps counted (each crash meets one gate it did not pass).
    pub fn success_rate(&self) -> f64 {
        let met = self.gates_passed + self.crashes;
        if met == 0 {
            0.0
        } else {
            self.gates_passed as f64 / met as f64
        }
    }

    pub(super) fn add(&mut self, o: &Self) {
        self.steps += o.steps;
        self.terms.add(&o.terms);
        self.gates_passed += o.gates_passed;
        self.crashes += o.crashes;
        self.timeouts += o.timeouts;
        self.opponent_crashes += o.opponent_crashes;
        self.nonfinite_actions += o.nonfinite_actions;
    }
}

/// What one env's last step was made of: its reward term by term and its events. The
/// per-step counterpart of [`EnvStats`], for learners that log or filter per env.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepRecord {
    /// The reward's terms; `terms.total() as f32` is the env's reward.
    pub terms: RewardTerms,
    /// The ego passed its target gate.
    pub gate_passed: bool,
    /// The ego crashed (a terminal step).
    pub crashed: bool,
    /// The episode reached its time limit (a truncation).
    pub timed_out: bool,
    /// Stage 2: the opponent crashed while the ego did not (a truncation too).
    pub opponent_crashed: bool,
}
