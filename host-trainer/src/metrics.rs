//! What a run logs: one [`IterationMetrics`] line per iteration in `metrics.jsonl`, and
//! the learning curves drawn from them.

use crate::ppo::UpdateStats;
use serde::{Deserialize, Serialize};

/// One line of `metrics.jsonl`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct IterationMetrics {
    /// Iteration (1-based).
    pub iteration: u32,
    /// Env-steps trained on so far.
    pub samples: u64,
    /// Wall-clock seconds of training so far (summed over resumed invocations).
    pub wall_s: f64,
    /// Samples per second of this iteration, rollout and update.
    pub samples_per_s: f64,
    /// Seconds of the rollout.
    pub rollout_s: f64,
    /// Seconds of the update.
    pub update_s: f64,
    /// Mean reward per env-step.
    pub reward_per_step: f64,
    /// Mean progress term per env-step.
    pub reward_progress: f64,
    /// Mean command term per env-step.
    pub reward_command: f64,
    /// Mean smoothness term per env-step.
    pub reward_smoothness: f64,
    /// Mean pass term per env-step.
    pub reward_pass: f64,
    /// Mean crash term per env-step.
    pub reward_crash: f64,
    /// Races only: mean competition term per env-step.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reward_competition: Option<f64>,
    /// Races only: episodes cut short by the opponent's crash, per simulated second.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub opponent_crash_rate_per_s: Option<f64>,
    /// Mean return of the episodes that ended recently (last 200).
    pub episode_return: f64,
    /// Mean length of those episodes (s).
    pub episode_s: f64,
    /// Gates passed / (passed + crashes) in the rollout (the noisy policy).
    pub success_rate: f64,
    /// Crashes per simulated second in the rollout.
    pub crash_rate_per_s: f64,
    /// Gates passed per simulated second in the rollout.
    pub gates_per_s: f64,
    /// The update's statistics (flattened: `surrogate_loss`, `value_loss`, `entropy`, `kl`,
    /// `clip_fraction`, `grad_norm`, `learning_rate` after the update,
    /// `skipped_minibatches`).
    #[serde(flatten)]
    pub update: UpdateStats,
    /// Mean σ of the policy.
    pub action_std: f64,
    /// Referee, deterministic policy, 45 s from the stage-1 spawn (a time trial) or
    /// `run.eval_races` 45 s races from stage-2 spawns (a race): success rate.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_success_rate: Option<f64>,
    /// Referee: crashes per second.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_crash_rate: Option<f64>,
    /// Referee: best lap (s), `None` without a complete lap.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_best_lap_s: Option<f64>,
    /// Referee: gates passed in the 45 s.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_gates: Option<u64>,
    /// Referee, races only: overtakes of the opponent.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_overtakes: Option<u64>,
    /// Referee, races only: overtakes whose lead was held 2 s.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_sustained_overtakes: Option<u64>,
    /// Referee, races only: the ego's win rate (docs/DESIGN.md "Metrics").
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub eval_win_rate: Option<f64>,
    /// Referee, races only: where the overtakes were taken and held, by gate (gates
    /// without an overtake left out), as `sitl eval --json` writes `overtakes_by_gate`.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub eval_overtakes_by_gate: Vec<sitl::eval::GateOvertakes>,
    /// With `run.select`, from its first iteration: the validation's success rate (the
    /// deterministic policy, `run.select.episodes` × 45 s from its spawns).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub select_success_rate: Option<f64>,
    /// The validation's crashes per second.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub select_crash_rate: Option<f64>,
    /// The validation's mean lap (s), `None` without a complete lap.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub select_mean_lap_s: Option<f64>,
    /// With `[guard]`: the share of the update kept (1, 0.5, 0.25, or 0 when rejected).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub guard_step: Option<f64>,
    /// With `[guard]`: the measured reward per step of the actor before the update.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub guard_reward_before: Option<f64>,
    /// With `[guard]`: the measured reward per step of the actor kept.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub guard_reward_after: Option<f64>,
}

/// A lap for the terminal: "7.78 s", or "DNF" without a complete lap.
pub fn lap_text(lap_s: Option<f64>) -> String {
    lap_s.map_or("DNF".to_string(), |l| format!("{l:.2} s"))
}

/// Learning curves of a run as one SVG (reward terms, success and crashes, referee laps,
/// losses and σ), against iterations.
pub fn learning_curves(name: &str, history: &[IterationMetrics]) -> String {
    use sitl::plot::{Series, grid, line_chart};
    let series = |label: &str, f: &dyn Fn(&IterationMetrics) -> Option<f64>| Series {
        name: label.to_string(),
        points: history
            .iter()
            .filter_map(|m| f(m).map(|y| (f64::from(m.iteration), y)))
            .collect(),
    };
    let it = "iteration";
    let charts = vec![
        line_chart(
            &format!("{name}: reward per env-step, by term"),
            it,
            "reward per step",
            &[
                series("total", &|m| Some(m.reward_per_step)),
                series("progress", &|m| Some(m.reward_progress)),
                series("pass", &|m| Some(m.reward_pass)),
                series("crash", &|m| Some(m.reward_crash)),
                series("competition (races)", &|m| m.reward_competition),
                series("command+smooth", &|m| {
                    Some(m.reward_command + m.reward_smoothness)
                }),
            ],
        ),
        line_chart(
            &format!("{name}: success rate"),
            it,
            "gates passed / encountered",
            &[
                series("rollout (noisy policy)", &|m| Some(m.success_rate)),
                series("referee (deterministic policy)", &|m| m.eval_success_rate),
                series("referee win rate (races)", &|m| m.eval_win_rate),
                series("referee sustained / overtakes (races)", &|m| match (
                    m.eval_sustained_overtakes,
                    m.eval_overtakes,
                ) {
                    (Some(s), Some(o)) if o > 0 => Some(s as f64 / o as f64),
                    _ => None,
                }),
            ],
        ),
        line_chart(
            &format!("{name}: referee lap time and crash rate"),
            it,
            "best lap (s) / crashes per 10 s",
            &[
                series("best lap (s)", &|m| m.eval_best_lap_s),
                series("referee crashes per 10 s", &|m| {
                    m.eval_crash_rate.map(|c| 10.0 * c)
                }),
                series("rollout crashes per 10 s", &|m| {
                    Some(10.0 * m.crash_rate_per_s)
                }),
            ],
        ),
        line_chart(
            &format!("{name}: PPO"),
            it,
            "value",
            &[
                series("value loss", &|m| Some(m.update.value_loss)),
                series("action σ", &|m| Some(m.action_std)),
                series("KL ×100", &|m| Some(100.0 * m.update.kl)),
                series("learning rate ×1000", &|m| {
                    Some(1000.0 * m.update.learning_rate)
                }),
            ],
        ),
    ];
    grid(&charts, 2)
}

/// A run's terminal: a progress bar (or none, `--quiet`) with lines printed above it.
pub(crate) struct Console {
    bar: indicatif::ProgressBar,
    shown: bool,
}

impl Console {
    /// A bar of `len` steps with `template` (indicatif's syntax), shown when `shown`;
    /// hidden, lines go to stdout.
    pub fn new(shown: bool, len: u64, template: &str) -> Self {
        let bar = if shown {
            let b = indicatif::ProgressBar::new(len);
            b.set_style(
                indicatif::ProgressStyle::with_template(template)
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            b
        } else {
            indicatif::ProgressBar::hidden()
        };
        Self { bar, shown }
    }

    /// The bar.
    pub fn bar(&self) -> &indicatif::ProgressBar {
        &self.bar
    }

    /// A line above the bar, or on stdout without one.
    pub fn say(&self, line: String) {
        if self.shown {
            self.bar.println(line);
        } else {
            println!("{line}");
        }
    }
}
