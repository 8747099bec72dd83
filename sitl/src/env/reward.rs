//! The reward of the vectorised environments (docs/DESIGN.md "Rewards", paper eq. 4-7),
//! every term × dt and kept apart for the logs:
//!
//! - progress `λ₁ (d_{t−1} − d_t)`, both distances to the gate the drone was flying to during
//!   the step (so a gate pass is not a jump to the next gate's distance);
//! - command `− λ₂ ‖a_t‖ − λ₃ ‖a_t − a_{t−1}‖²` on the clipped actions the motors got;
//! - pass `1 − ‖p_t − g‖` when the step passed gate g;
//! - crash `− 5` when the step crashed (gate frame, ground, bounds, non-finite);
//! - stage 2, competition `λ_c r_comp` (paper λ_c = 0.5): dense `tanh(−0.1 d_fwd)` with
//!   `d_fwd` the opponent's position relative to the ego along the ego's body x after the step
//!   (eq. 6), sparse `1` when the step passed a gate while ahead of the opponent in gates
//!   passed since the spawn (eq. 7), or our `lead`. Like progress, it is not paid on the ego's
//!   crash step.

use crate::referee::TrackProgress;
use crate::world::Drone;
use firmware_core::math::Vec3;
use firmware_core::nn::ACTION_DIM;

/// The reward's weights (docs/DESIGN.md "Rewards"; defaults are the paper's).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardWeights {
    /// λ₁, progress toward the target gate (per m). Paper 0.5.
    pub progress: f32,
    /// λ₂, action magnitude ‖a‖. Paper 0.0005.
    pub command: f32,
    /// λ₃, action change ‖a_t − a_{t−1}‖². Paper 0.0002.
    pub smoothness: f32,
    /// Scale of the pass reward `1 − ‖rel_gate‖`. Paper 1.
    pub pass: f32,
    /// Crash penalty. Paper 5.
    pub crash: f32,
}

impl Default for RewardWeights {
    fn default() -> Self {
        Self {
            progress: 0.5,
            command: 0.0005,
            smoothness: 0.0002,
            pass: 1.0,
            crash: 5.0,
        }
    }
}

/// The reward's terms summed over steps and envs, each already × dt and signed as it enters
/// the reward (so `total` is their sum).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RewardTerms {
    /// Progress toward the target gate.
    pub progress: f64,
    /// − action magnitude.
    pub command: f64,
    /// − action change.
    pub smoothness: f64,
    /// Gate passes.
    pub pass: f64,
    /// − crashes.
    pub crash: f64,
    /// Stage 2: the competition reward (0 in a time trial).
    pub competition: f64,
}

impl RewardTerms {
    /// Sum of the terms.
    pub fn total(&self) -> f64 {
        self.progress + self.command + self.smoothness + self.pass + self.crash + self.competition
    }

    /// Adds `o` term by term.
    pub(super) fn add(&mut self, o: &Self) {
        self.progress += o.progress;
        self.command += o.command;
        self.smoothness += o.smoothness;
        self.pass += o.pass;
        self.crash += o.crash;
        self.competition += o.competition;
    }
}

/// The competition reward of stage 2 (paper eq. 6 and 7).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Competition {
    /// `tanh(−0.1 d_fwd)` every step (eq. 6; the paper's Table 1 rows B, C, E-G).
    Dense,
    /// `1` on a gate passed while ahead in gates (eq. 7; row D).
    Sparse,
    /// `tanh(0.1 · lead)` every step, `lead` the ego's progress along the track minus the
    /// opponent's (m, as the referee measures overtakes). Not in the paper: eq. 6 measures the
    /// opponent along the ego's body x, which an ego can earn by facing away from the
    /// opponent instead of racing (docs/journal/stage2.md, s2-g3); this form pays only for being
    /// ahead on the track.
    Lead,
}

impl Competition {
    /// The term called `name` ("dense", "sparse", "lead", as in training configs).
    pub fn by_name(name: &str) -> Option<Self> {
        match name {
            "dense" => Some(Self::Dense),
            "sparse" => Some(Self::Sparse),
            "lead" => Some(Self::Lead),
            _ => None,
        }
    }
}

/// The reward's weights and, in a race, the competition term and its weight.
#[derive(Clone, Copy, Debug)]
pub(super) struct Rewards {
    /// The weights of the paper's terms.
    pub weights: RewardWeights,
    /// In a race: the competition term and its weight λ_c.
    pub competition: Option<(Competition, f32)>,
}

/// `tanh(−0.1 d_fwd)` (paper eq. 6): `d_fwd` is the opponent's position relative to the ego
/// along the ego's body x (m); positive when the ego leads.
pub fn dense_competition(ego: &firmware_core::vehicle::VehicleState, opponent_m: Vec3) -> f32 {
    let rel_body = ego.attitude.conjugate().rotate(opponent_m - ego.position_m);
    (-0.1 * rel_body.x).tanh()
}

/// What the reward of one env-step looks at: the ego before and after the step, the gate it
/// flew to, the actions, the step's outcome and, in a race, the opponent.
pub(super) struct StepOutcome<'a> {
    /// Control period (s).
    pub dt_s: f32,
    /// Centre of the gate the ego flew to during the step (m).
    pub gate_m: Vec3,
    /// The ego's position before the step (m).
    pub before_m: Vec3,
    /// The clipped action the motors got.
    pub action: &'a [f32; ACTION_DIM],
    /// The action of the step before (zero after a spawn).
    pub previous_action: &'a [f32; ACTION_DIM],
    /// The ego crashed in the step.
    pub crashed: bool,
    /// The ego passed its gate in the step (never with a crash).
    pub passed: bool,
    /// The ego after the step.
    pub ego: &'a Drone,
    /// The opponent after the step (unused in a time trial).
    pub opponent: &'a Drone,
    /// Each drone's centreline segment at its spawn (for `lead`).
    pub spawn_segment: [u64; 2],
    /// The track's centreline (for `lead`).
    pub progress: &'a TrackProgress,
}

impl Rewards {
    /// The terms of one step, each × dt and signed as it enters the reward. On the ego's
    /// crash step only the command, smoothness and crash terms are paid.
    pub(super) fn terms(&self, s: &StepOutcome<'_>) -> RewardTerms {
        let (w, dt, action, gate) = (&self.weights, s.dt_s, s.action, s.gate_m);
        let norm = |v: &[f32; ACTION_DIM]| v.iter().map(|x| x * x).sum::<f32>();
        let change: [f32; ACTION_DIM] = core::array::from_fn(|k| action[k] - s.previous_action[k]);
        let mut terms = RewardTerms {
            command: f64::from(-dt * w.command * norm(action).sqrt()),
            smoothness: f64::from(-dt * w.smoothness * norm(&change)),
            ..RewardTerms::default()
        };
        if s.crashed {
            terms.crash = f64::from(-dt * w.crash);
            return terms;
        }
        let (ego, opp) = (s.ego, s.opponent);
        let after = ego.position_m();
        terms.progress =
            f64::from(dt * w.progress * ((s.before_m - gate).norm() - (after - gate).norm()));
        if s.passed {
            terms.pass = f64::from(dt * w.pass * (1.0 - (after - gate).norm()));
        }
        terms.competition = match self.competition {
            None => 0.0,
            Some((Competition::Dense, weight)) => {
                f64::from(dt * weight * dense_competition(&ego.body.state, opp.position_m()))
            }
            Some((Competition::Sparse, weight)) => {
                let ahead = ego.progress.gates_passed > opp.progress.gates_passed;
                if s.passed && ahead {
                    f64::from(dt * weight)
                } else {
                    0.0
                }
            }
            Some((Competition::Lead, weight)) => {
                let [se, so] = s.spawn_segment;
                let lead = s
                    .progress
                    .progress_m(se, ego.progress.gates_passed, ego.position_m())
                    - s.progress
                        .progress_m(so, opp.progress.gates_passed, opp.position_m());
                f64::from(dt * weight * (0.1 * lead).tanh())
            }
        };
        terms
    }
}
