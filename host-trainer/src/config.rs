//! Training configuration: one TOML file per run (`host-trainer/configs/*.toml`), every
//! field with its unit and the paper's value beside ours. Unknown keys are errors, so a typo
//! cannot silently fall back to a default.
//!
//! The paper's values live in code too: every section's `Default` is the paper's stage 1
//! (RSL-RL's PPO settings), [`TrainConfig::paper`] is the whole paper stage-1 run
//! (`configs/stage1_paper.toml`) and [`TrainConfig::ours`] this project's stage-1 pipeline
//! (`configs/stage1.toml`, PPO from a random network); a test holds each preset equal to its
//! TOML file.

use serde::{Deserialize, Serialize};
use sitl::env::{EnvConfig, RaceConfig, RewardWeights};
use std::path::Path;

mod presets;
mod validate;

/// A whole training run. Its TOML sections are `[run]`, `[env]`, `[ppo]`, `[reward]`,
/// `[pass_decay]`, `[randomize_ramp]`, `[warm_start]`, `[guard]`, `[race]` and
/// `[[opponent_curriculum]]`; the
/// environment's three
/// (`[env]`, `[reward]`, `[race]`) all land in [`TrainConfig::env`], sitl's one environment
/// schema.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "TrainFile", into = "TrainFile")]
pub struct TrainConfig {
    /// Name, seed, budget and bookkeeping.
    pub run: RunConfig,
    /// The vectorised environment: `[env]`, with `[reward]` as `env.reward` (the paper's
    /// weights when absent) and `[race]` as `env.race` (stage 2: race a frozen opponent;
    /// absent: the stage-1 time trial). `env.layout` follows `run.row` and `env.seed`
    /// `run.seed` ([`TrainConfig::env_config`] sets both).
    pub env: EnvConfig,
    /// PPO hyper-parameters.
    pub ppo: PpoConfig,
    /// Optional fall of the pass reward's weight over the run (not in the paper).
    pub pass_decay: Option<PassDecay>,
    /// Optional rise of the share of randomised spawns over the run (`env.randomize`; not in
    /// the paper).
    pub randomize_ramp: Option<RandomizeRamp>,
    /// Optional imitation warm start before PPO (not in the paper).
    pub warm_start: Option<WarmStart>,
    /// Optional test of every actor update on the measured return (not in the paper).
    pub guard: Option<Guard>,
    /// Races only: the opponents raced before `[race].opponent`, in order, each until its
    /// iteration (not in the paper; its authors' proposal against data saturated with
    /// trailing). Empty: `[race].opponent` from the first iteration.
    pub opponent_curriculum: Vec<CurriculumStage>,
}

/// One stage of an opponent curriculum (`[[opponent_curriculum]]`): the training races fly
/// against `opponent` until `until_iteration`. The in-training referee always races
/// `[race].opponent`, the opponent the result is judged against.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurriculumStage {
    /// The opponent's blob: a time-trial (17-value) policy, as `[race].opponent`.
    pub opponent: std::path::PathBuf,
    /// The first iteration that no longer races it (iterations count from 0): the stages'
    /// iterations rise, and the last is below `run.iterations`.
    pub until_iteration: u32,
}

/// The TOML file's layout of a [`TrainConfig`]: the sections in the order of the canonical
/// TOML that [`TrainConfig::hash`] reads (every shipped blob records that hash).
#[derive(Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TrainFile {
    run: RunConfig,
    env: EnvConfig,
    ppo: PpoConfig,
    #[serde(default)]
    reward: RewardWeights,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pass_decay: Option<PassDecay>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    randomize_ramp: Option<RandomizeRamp>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    warm_start: Option<WarmStart>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    guard: Option<Guard>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    race: Option<RaceConfig>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    opponent_curriculum: Vec<CurriculumStage>,
}

impl From<TrainFile> for TrainConfig {
    fn from(f: TrainFile) -> Self {
        let mut config = Self {
            env: EnvConfig {
                reward: f.reward,
                race: f.race,
                ..f.env
            },
            run: f.run,
            ppo: f.ppo,
            pass_decay: f.pass_decay,
            randomize_ramp: f.randomize_ramp,
            warm_start: f.warm_start,
            guard: f.guard,
            opponent_curriculum: f.opponent_curriculum,
        };
        config.env = config.env_config(config.run.seed);
        config
    }
}

impl From<TrainConfig> for TrainFile {
    fn from(c: TrainConfig) -> Self {
        Self {
            reward: c.env.reward,
            race: c.env.race.clone(),
            run: c.run,
            env: c.env,
            ppo: c.ppo,
            pass_decay: c.pass_decay,
            randomize_ramp: c.randomize_ramp,
            warm_start: c.warm_start,
            guard: c.guard,
            opponent_curriculum: c.opponent_curriculum,
        }
    }
}

/// A line search on the measured return after each PPO update (not in the paper; see
/// docs/journal/stage1.md "Why PPO leaves the student"): the updated actor, and if it is worse
/// the update scaled by 1/2 and 1/4, must reach at least the old actor's reward per step on
/// one rollout with common random numbers (the same fresh seeds for environments and action
/// noise for both). If none does, the actor stays as it was, its Adam state is reset and the
/// learning rate halves. The critic's update is always kept.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Guard {
    /// Environments of the test rollout.
    pub envs: usize,
    /// Steps per env before measuring (to leave the spawns).
    pub warmup_steps: usize,
    /// Steps per env measured.
    pub steps: usize,
}

/// Imitation of the classical baseline before PPO (DAgger): the actor's mean is regressed
/// onto the baseline's actions on states that the mixture of teacher and student visits,
/// then PPO runs with the critic trained alone for its first iterations. Not in the paper;
/// see docs/TRAINING.md for why and what it changes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WarmStart {
    /// Cruise speed of the baseline teacher (m/s); it flies without a crash up to 10.
    pub teacher_cruise_mps: f32,
    /// A time-trial (17-value) blob whose mean labels the states instead of the baseline:
    /// stage 2 imitates the stage-1 policy (issue "stage2"). Relative to the working
    /// directory. Absent: the baseline at `teacher_cruise_mps`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub teacher_blob: Option<String>,
    /// A blob of the run's row whose actor the rounds start from (relative to the working
    /// directory), to refine an earlier student; absent: the run's fresh initialisation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub student: Option<String>,
    /// The student starts as the teacher itself: `teacher_blob` (a feed-forward time-trial
    /// policy) embedded in this row's network so that it computes the same actions
    /// ([`crate::transplant`]; the units it does not use keep the seed's initialisation).
    /// Instead of `student`; with `rounds = 0` the run starts PPO from the teacher's own
    /// flight, a warm start from an RL-trained policy that is exact rather than fitted.
    #[serde(default, skip_serializing_if = "is_false")]
    pub transplant: bool,
    /// DAgger rounds; the teacher's share of the executed actions falls linearly from 1 to
    /// 0 over the first half. 0 with a `student`: the student as given (refereed, then the
    /// critic-only iterations).
    pub rounds: u32,
    /// Env-steps per env per round.
    pub steps_per_env: usize,
    /// Passes over the aggregated data per round.
    pub epochs: usize,
    /// Minibatch size of the regression.
    pub minibatch: usize,
    /// Most recent samples kept for the regression.
    pub max_samples: usize,
    /// Adam learning rate of the regression (round 1).
    pub learning_rate: f64,
    /// The regression's learning rate in the last round: the rate falls geometrically from
    /// `learning_rate` to this over the rounds. Absent: constant.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learning_rate_final: Option<f64>,
    /// The teacher's share of the executed actions in round 1 (it falls linearly to 0 at
    /// the half-way round). 0 refines a student on its own states from the first round.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub teacher_share_start: f64,
    /// σ of the noise on the student's executed actions (state diversity).
    pub student_noise_std: f32,
    /// PPO iterations after the warm start that train the critic only.
    pub critic_iterations: u32,
    /// Referee every round's student (`run.eval_races` races on `run.eval_seed`, logged in
    /// `imitation.jsonl`, its blob kept as `checkpoints/warm_start_round_NNN.blob`) and end
    /// the warm start with the best-scored one (as `run.keep_best` ranks them) instead of the
    /// last. For all the stages; set it here, not per refine stage.
    #[serde(default, skip_serializing_if = "is_false")]
    pub keep_best_round: bool,
    /// Label the states with the teacher's means clamped to the rotor-command range
    /// [-1, 1], the commands it actually flies (a PPO teacher's means can lie far outside,
    /// where the clamp makes them all the same command, and fitting them wastes the
    /// student's capacity). Off by default: the shipped students were labelled unclamped.
    #[serde(default, skip_serializing_if = "is_false")]
    pub clamp_labels: bool,
    /// Further DAgger stages after these rounds, in order, each from the student the last
    /// one made, with the student flying from its first round (`[[warm_start.refine]]`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub refine: Vec<Refine>,
}

/// A refinement stage of the warm start: more DAgger rounds on the student's own states,
/// with their own length, data and learning rate; the teacher, minibatch and action noise
/// are the warm start's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Refine {
    /// DAgger rounds.
    pub rounds: u32,
    /// Env-steps per env per round (a round starts from fresh spawns).
    pub steps_per_env: usize,
    /// Passes over the kept data per round.
    pub epochs: usize,
    /// Most recent samples kept for the regression.
    pub max_samples: usize,
    /// Adam learning rate in the stage's first round.
    pub learning_rate: f64,
    /// The rate in its last round (geometric in between); absent: constant.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learning_rate_final: Option<f64>,
}

/// Name, seed, budget and bookkeeping of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Short name, recorded in the exported blob (at most 32 bytes).
    pub name: String,
    /// Table 1 row of the policy ("A" for stage 1).
    pub row: char,
    /// Seed of the environment and the network initialisation.
    pub seed: u64,
    /// PPO iterations (each: a rollout of `steps_per_env` per env, then the update).
    pub iterations: u32,
    /// Iterations between checkpoints.
    pub checkpoint_every: u32,
    /// Iterations between the referee's evaluations of the deterministic policy (logged as
    /// `eval_*` in the metrics). Default 10.
    #[serde(default = "default_eval_every")]
    pub eval_every: u32,
    /// Races of the in-training evaluation when the config races an opponent (45 s each,
    /// stage-2 spawns). Default 4.
    #[serde(
        default = "default_eval_races",
        skip_serializing_if = "is_default_eval_races"
    )]
    pub eval_races: u32,
    /// Seed of the in-training evaluation's spawns (race `i` uses stream `i`). Default 0;
    /// with `keep_best`, pick seeds the final evaluation does not use.
    #[serde(default, skip_serializing_if = "is_zero_u64")]
    pub eval_seed: u64,
    /// Races only: fly the in-training evaluation from jittered starts (`sitl eval --jitter`:
    /// 5 cm, 5°, 0.2 m/s). The nominal race spawn is one deterministic flight per gate, so
    /// 20 nominal races are six flights re-weighted, and the referee's best of many
    /// evaluations is chosen on those six (docs/journal/stage2.md). Default off.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub eval_jitter: bool,
    /// Export the evaluated actor the referee scored best (highest success rate, then the
    /// lower crash rate, then the earlier iteration) instead of the last one. Default off.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub keep_best: bool,
    /// What `keep_best` ranks a race's evaluations by: "success" (the default, as above) or
    /// "win-rate": the evaluations at or above [`RACE_SUCCESS_FLOOR`] success first, among
    /// them the higher win rate, then the higher success; below the floor, by success.
    #[serde(default, skip_serializing_if = "KeepBestBy::is_default")]
    pub keep_best_by: KeepBestBy,
    /// With `keep_best` in a time trial: rank the candidates on this validation instead of
    /// the referee's stage-1 episode, which is the evaluation the result is judged on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub select: Option<Selection>,
}

/// The success rate a race's candidate must reach before `run.keep_best_by = "win-rate"`
/// ranks it by its win rate (issue "race": success >= 0.9).
pub const RACE_SUCCESS_FLOOR: f64 = 0.9;

/// What `run.keep_best` ranks a race's evaluations by (`run.keep_best_by`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeepBestBy {
    /// The higher success rate, then the fewer crashes per second.
    #[default]
    Success,
    /// Success at or above [`RACE_SUCCESS_FLOOR`] first; then the higher win rate, then the
    /// higher success rate, then the fewer crashes.
    WinRate,
}

impl KeepBestBy {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// The validation `run.keep_best` ranks candidates by (`run.select`): the deterministic
/// policy flown `episodes` × 45 s from `spawn` (seed `seed`) at every evaluation from
/// `from_iteration` on, alone in a time trial and against the config's opponent in a race.
/// The order: with `referee_floor` or `race_bar`, the candidates whose referee met them
/// first; then the higher success rate, the fewer crashes per second, the shorter mean lap,
/// the earlier iteration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Selection {
    /// Spawn of the validation episodes: "along-track" (a random point of the centreline,
    /// at rest) or "stage2" (at rest 2 m or 1 m before a random gate); not the stage-1
    /// spawn, the referee's.
    pub spawn: sitl::referee::SpawnMode,
    /// Episodes of 45 s per validation.
    pub episodes: u32,
    /// Seed of the validation's spawns (pick one the final evaluations do not use).
    pub seed: u64,
    /// The first iteration whose evaluation is a candidate (earlier ones are not validated).
    pub from_iteration: u32,
    /// The validation flown under these perturbations (`sitl eval --perturb`'s text; spans
    /// drawn per episode), so that a recipe trained for robustness ranks its candidates by
    /// how they fly under them. One text, or a list of them (`""` is the unperturbed flight):
    /// `episodes` under each, and the candidate's success, crashes and mean lap are the
    /// means over the list, so that e.g. `["motor-tau-ms=20", "latency=1"]` ranks by both
    /// conditions of a robustness bar rather than by their combination, which a single
    /// text's spans would draw. Absent: unperturbed.
    #[serde(
        default,
        with = "one_or_many_perturbations",
        skip_serializing_if = "Vec::is_empty"
    )]
    pub perturb: Vec<sitl::perturb::PerturbSpec>,
    /// Jitter every validation start as `sitl eval --jitter` does (its text: `""` for ±5 cm,
    /// ±5° and ±0.2 m/s), under each of `perturb`: the starts a robustness bar is judged
    /// from. Absent: the spawns exactly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jitter: Option<sitl::perturb::JitterSpec>,
    /// The referee's success (the in-training evaluation: a race's `run.eval_races` exact
    /// races) a candidate must reach to rank before those that do not, e.g. issue "race"'s
    /// 0.9: a race ego chosen for its robustness under `perturb` must still fly the nominal
    /// races. Absent: the referee does not rank.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub referee_floor: Option<f64>,
    /// Races only: a candidate ranks before those that do not only if its referee's races
    /// also meet issue "race"'s per-race bar ([`sitl::eval::RaceBar::RACE`]: success >= 0.9,
    /// crashes <= 0.1 /s, best lap <= 8.0 s, half of the overtakes and >= 16 per 20 races
    /// sustained, at >= 3 gates), so that the actor chosen for its robustness still overtakes
    /// as the shipped ego must. With `referee_floor`, a candidate must meet both.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub race_bar: bool,
}

/// `run.select.perturb` as a config writes it: one `--perturb` text or a list of them. One
/// is written back as the text alone, so a config's hash does not depend on which was used.
mod one_or_many_perturbations {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};
    use sitl::perturb::PerturbSpec;

    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Texts {
        One(String),
        Many(Vec<String>),
    }

    pub fn serialize<S: Serializer>(specs: &[PerturbSpec], s: S) -> Result<S::Ok, S::Error> {
        match specs {
            [one] => one.serialize(s),
            many => many.serialize(s),
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<PerturbSpec>, D::Error> {
        let texts = match Texts::deserialize(d)? {
            Texts::One(text) => vec![text],
            Texts::Many(texts) => texts,
        };
        texts
            .iter()
            .map(|t| PerturbSpec::parse(t).map_err(serde::de::Error::custom))
            .collect()
    }
}

fn default_eval_races() -> u32 {
    4
}

fn is_default_eval_races(v: &u32) -> bool {
    *v == default_eval_races()
}

fn is_zero_u64(v: &u64) -> bool {
    *v == 0
}

fn is_false(v: &bool) -> bool {
    !*v
}

fn one() -> f64 {
    1.0
}

fn is_one(v: &f64) -> bool {
    *v == 1.0
}

fn default_min_learning_rate() -> f64 {
    1e-5
}

fn default_max_learning_rate() -> f64 {
    1e-2
}

fn is_default_max_learning_rate(v: &f64) -> bool {
    *v == default_max_learning_rate()
}

fn is_default_min_learning_rate(v: &f64) -> bool {
    *v == default_min_learning_rate()
}

fn default_eval_every() -> u32 {
    10
}

/// A falling σ ceiling ([`PpoConfig::max_std_decay`]). Its iterations are absolute, not
/// fractions of the budget, so a run extended by `--resume` trains as before.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StdDecay {
    /// The ceiling from `to_iteration` on.
    pub final_std: f32,
    /// The last iteration at `max_std` (iterations count from 0, the first update's).
    pub from_iteration: u32,
    /// The first iteration at `final_std`.
    pub to_iteration: u32,
}

/// A falling pass-reward weight ([`TrainConfig::pass_decay`], not in the paper): `reward.pass`
/// until `from_iteration`, then linearly to `final_weight` at `to_iteration`. The pass reward
/// `1 − ‖rel_gate‖` pays for crossing a gate near its centre, which helps a network find the
/// gates early and costs lap time late (the fast line cuts the openings' edges;
/// docs/journal/stage1.md "The reward keeps the line at the gates' centres"). Iterations are
/// absolute, like [`StdDecay`]'s.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PassDecay {
    /// The pass weight from `to_iteration` on.
    pub final_weight: f32,
    /// The last iteration at `reward.pass`.
    pub from_iteration: u32,
    /// The first iteration at `final_weight`.
    pub to_iteration: u32,
}

/// A rising share of randomised training spawns ([`TrainConfig::randomize_ramp`], not in the
/// paper): none of the ego's spawns is drawn from `env.randomize` until `from_iteration`, then
/// a share rising linearly to `env.randomize_share` at `to_iteration`. The network first
/// learns the track on the nominal airframe (fast, as `stage1.toml` does), then to fly it
/// under the draws with its own critic still learning (docs/journal/stage1.md "Randomisation
/// switched on late"). Iterations are absolute, like [`PassDecay`]'s.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RandomizeRamp {
    /// The last iteration without randomised spawns.
    pub from_iteration: u32,
    /// The first iteration at `env.randomize_share`.
    pub to_iteration: u32,
}

/// PPO hyper-parameters (docs/DESIGN.md "Learning"; the defaults are RSL-RL's and the paper's
/// stage 1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoConfig {
    /// Env-steps per env per iteration. Paper: 100.
    pub steps_per_env: usize,
    /// Passes over the rollout per iteration. Paper: 5.
    pub epochs: usize,
    /// Minibatches per epoch. Paper: 4.
    pub minibatches: usize,
    /// Surrogate and value clip. Paper: 0.2.
    pub clip: f32,
    /// Discount γ. Paper: 0.99.
    pub gamma: f32,
    /// GAE λ. Paper: 0.95.
    pub lambda: f32,
    /// Value-loss coefficient. Paper: 1.0.
    pub value_coef: f32,
    /// Entropy coefficient. Paper stage 1: 0.01.
    pub entropy_coef: f32,
    /// Initial learning rate. Paper stage 1: 1e-4.
    pub learning_rate: f64,
    /// KL target of the adaptive learning rate (`None`: fixed rate). Paper: 0.01.
    pub desired_kl: Option<f64>,
    /// Gradient norm clip. Paper: 1.0.
    pub max_grad_norm: f32,
    /// Floor of the adaptive learning rate. Paper (RSL-RL): 1e-5. Default 1e-5. (Left out of
    /// the canonical TOML at its default, so configs written before it existed keep their
    /// hash.)
    #[serde(
        default = "default_min_learning_rate",
        skip_serializing_if = "is_default_min_learning_rate"
    )]
    pub min_learning_rate: f64,
    /// Ceiling of the adaptive learning rate. Paper (RSL-RL): 1e-2. Default 1e-2 (left out
    /// of the canonical TOML at its default, as `min_learning_rate`).
    #[serde(
        default = "default_max_learning_rate",
        skip_serializing_if = "is_default_max_learning_rate"
    )]
    pub max_learning_rate: f64,
    /// Ceiling of the action standard deviation: after every Adam step each log-σ is
    /// clamped to ln(this). With actions clipped to their range, σ beyond it costs the
    /// policy nothing the surrogate can see, so the entropy bonus alone grows it. Paper:
    /// none. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_std: Option<f32>,
    /// The σ ceiling lowered during the run: from `max_std` it falls linearly to
    /// `final_std` between two iterations (an annealed exploration noise). With the entropy
    /// bonus holding σ at its ceiling, this is σ's schedule. Needs `max_std`. Paper: none.
    /// Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_std_decay: Option<StdDecay>,
    /// A fixed critic learning rate instead of the actor's adaptive one. Paper: none (one
    /// rate). Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub critic_learning_rate: Option<f64>,
    /// The actor's LSTM layers step at `learning_rate` × this (the head at `learning_rate`):
    /// a recurrent actor whose LSTM is far more sensitive than its head (a transplant's
    /// carrying units, `warm_start.transplant`) otherwise spends the KL budget of every
    /// update there. In (0, 1]; the fused update only. Paper: none (one rate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lstm_learning_rate_scale: Option<f64>,
    /// Initial action standard deviation. Paper: 1.0.
    pub init_std: f32,
    /// Start the actor's output bias at the preset's hover action (a ≈ 0.52 with `paper`)
    /// instead of PyTorch's random initialisation, so the first rollouts hover rather than
    /// fall. Paper: false. Default false.
    #[serde(default)]
    pub init_hover: bool,
    /// How the networks take their PPO steps: `"fused"`, the hand-written CPU update of
    /// [`crate::fused`] (feed-forward and recurrent networks), or `"burn"`, the same update
    /// on `burn`'s autodiff. Absent: fused for the feed-forward rows A-D, burn for the
    /// recurrent rows E-G, which is how the shipped E-G policies were trained (before the
    /// recurrent fused update existed), so their configs still make them; new recurrent
    /// configs say `update = "fused"`. (Left out of the canonical TOML when absent, so
    /// configs written before it existed keep their hash.)
    #[serde(default, skip_serializing_if = "UpdateKind::is_default")]
    pub update: UpdateKind,
    /// What the value function is: `"actor-shaped"` (default), the actor's architecture on
    /// the actor's observation (the paper's, and RSL-RL's); or `"privileged-mlp"`, an MLP of
    /// the row's head widths on the env's privileged state (`VecEnv::privileged_observations`:
    /// the noise-free observation, the episode's randomised airframe and latency, its time
    /// left). The critic trains beside the actor and is never deployed, so the exported
    /// actor is the same kind of network either way; for a recurrent row the critic then
    /// carries no state and costs a fraction of the LSTM critic (issue "lstm-speed", item 5).
    /// (Left out of the canonical TOML at its default.)
    #[serde(default, skip_serializing_if = "CriticKind::is_default")]
    pub critic: CriticKind,
}

/// The value function PPO trains ([`PpoConfig::critic`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CriticKind {
    /// The actor's architecture with one output, on the actor's observation.
    #[default]
    ActorShaped,
    /// A feed-forward MLP on the env's privileged state.
    PrivilegedMlp,
}

impl CriticKind {
    /// The default (for `skip_serializing_if`).
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// Which implementation takes the PPO steps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UpdateKind {
    /// Not set: [`UpdateKind::Fused`] for feed-forward networks, [`UpdateKind::Burn`] for
    /// recurrent ones (see [`PpoConfig::update`]).
    #[default]
    Auto,
    /// The fused CPU update ([`crate::fused`]): the same math, several times faster.
    Fused,
    /// `burn`'s autodiff and Adam.
    Burn,
}

impl UpdateKind {
    /// The implementation that runs for a network that is `recurrent` or not.
    pub fn resolve(self, recurrent: bool) -> Self {
        match self {
            Self::Auto if recurrent => Self::Burn,
            Self::Auto => Self::Fused,
            k => k,
        }
    }

    /// The default (for `skip_serializing_if`).
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// Why a configuration could not be used.
#[derive(Debug)]
pub enum ConfigError {
    /// The file could not be read.
    Read(std::io::Error),
    /// The TOML does not parse or does not match the schema.
    Parse(String),
    /// A value is out of its range.
    Invalid(String),
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Read(e) => write!(f, "cannot read the config: {e}"),
            Self::Parse(e) => write!(f, "the config does not parse: {e}"),
            Self::Invalid(e) => write!(f, "the config is invalid: {e}"),
        }
    }
}

impl std::error::Error for ConfigError {}

impl WarmStart {
    /// The warm start's stages in order: itself, then each `refine` stage as a warm start of
    /// its own (the student flying from the first round).
    pub fn stages(&self) -> Vec<WarmStart> {
        let mut stages = vec![WarmStart {
            refine: Vec::new(),
            ..self.clone()
        }];
        for r in &self.refine {
            stages.push(WarmStart {
                rounds: r.rounds,
                steps_per_env: r.steps_per_env,
                epochs: r.epochs,
                max_samples: r.max_samples,
                learning_rate: r.learning_rate,
                learning_rate_final: r.learning_rate_final,
                teacher_share_start: 0.0,
                student: None,
                transplant: false,
                refine: Vec::new(),
                ..self.clone()
            });
        }
        stages
    }

    /// The teacher's share β of the executed actions in round `round` (0-based):
    /// `teacher_share_start`, falling linearly to 0 at the half-way round.
    pub fn teacher_share(&self, round: u32) -> f64 {
        let half = (self.rounds / 2).max(1);
        (self.teacher_share_start * (1.0 - f64::from(round) / f64::from(half))).max(0.0)
    }

    /// The regression's learning rate in round `round` (0-based): `learning_rate`, falling
    /// geometrically to `learning_rate_final` in the last round where that is set.
    pub fn round_learning_rate(&self, round: u32) -> f64 {
        match self.learning_rate_final {
            Some(last) if self.rounds > 1 => {
                let t = f64::from(round.min(self.rounds - 1)) / f64::from(self.rounds - 1);
                self.learning_rate * (last / self.learning_rate).powf(t)
            }
            _ => self.learning_rate,
        }
    }
}

impl PpoConfig {
    /// The σ ceiling of the update that follows `iteration` iterations: `max_std`, lowered
    /// by `max_std_decay` when there is one.
    pub fn max_std_at(&self, iteration: u32) -> Option<f32> {
        let max = self.max_std?;
        let Some(d) = &self.max_std_decay else {
            return Some(max);
        };
        Some(linear_fall(
            max,
            d.final_std,
            d.from_iteration,
            d.to_iteration,
            iteration,
        ))
    }
}

/// `start` until iteration `from`, then linearly to `end` at iteration `to` and after (the
/// σ ceiling's and the pass weight's schedules).
fn linear_fall(start: f32, end: f32, from: u32, to: u32, iteration: u32) -> f32 {
    let span = to.saturating_sub(from).max(1) as f32;
    let t = (iteration.saturating_sub(from) as f32 / span).min(1.0);
    start + (end - start) * t
}

impl TrainConfig {
    /// The reward weights of the rollout of iteration `iteration` (0-based): `reward`, its pass
    /// weight lowered by `pass_decay` when there is one.
    pub fn reward_at(&self, iteration: u32) -> RewardWeights {
        let Some(d) = &self.pass_decay else {
            return self.env.reward;
        };
        RewardWeights {
            pass: linear_fall(
                self.env.reward.pass,
                d.final_weight,
                d.from_iteration,
                d.to_iteration,
                iteration,
            ),
            ..self.env.reward
        }
    }

    /// The share of the ego's spawns that `env.randomize` draws for in the rollout of
    /// `iteration`: `env.randomize_share`, raised from 0 by `randomize_ramp` when there is one.
    pub fn randomize_share_at(&self, iteration: u32) -> f32 {
        let Some(r) = &self.randomize_ramp else {
            return self.env.randomize_share;
        };
        linear_fall(
            0.0,
            self.env.randomize_share,
            r.from_iteration,
            r.to_iteration,
            iteration,
        )
    }

    /// The race the training envs fly at `iteration`: `[race]` with the opponent of the
    /// `[[opponent_curriculum]]` stage that iteration falls in, or `[race]` itself past the
    /// curriculum (and `None` in a time trial).
    pub fn race_at(&self, iteration: u32) -> Option<RaceConfig> {
        let race = self.env.race.as_ref()?;
        let opponent = self
            .opponent_curriculum
            .iter()
            .find(|s| iteration < s.until_iteration)
            .map_or(&race.opponent, |s| &s.opponent);
        Some(RaceConfig {
            opponent: opponent.clone(),
            ..race.clone()
        })
    }

    /// Reads and validates the TOML file at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(ConfigError::Read)?;
        Self::parse(&text)
    }

    /// Parses and validates TOML text.
    pub fn parse(text: &str) -> Result<Self, ConfigError> {
        let c: Self = toml::from_str(text).map_err(|e| ConfigError::Parse(e.to_string()))?;
        validate::validate(&c)?;
        Ok(c)
    }

    /// A stable 64-bit hash of the configuration (FNV-1a of its canonical TOML), recorded in
    /// checkpoints and blobs: a resumed run refuses a changed config. A field added to the
    /// schema later must be left out of the canonical TOML at its default, or every earlier
    /// blob's hash stops matching its config (`host-trainer/tests/shipped_policies.rs`
    /// catches that).
    ///
    /// Every config this crate parses or builds serialises (a test round-trips each committed
    /// one); were one not to, its `Debug` text is hashed instead, so that two different
    /// configs never share the hash of an empty text and a resume cannot accept a changed one.
    pub fn hash(&self) -> u64 {
        let canonical = toml::to_string(self).unwrap_or_else(|e| format!("{e}: {self:?}"));
        canonical.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        })
    }

    /// Whether `self` is `earlier` with at most its budget (`run.iterations`) changed: the
    /// one change a resumed run accepts, since nothing else in a run depends on the budget
    /// (a run extended by `--resume` trains as one started with the larger budget would).
    pub fn only_budget_differs_from(&self, earlier: &TrainConfig) -> bool {
        let mut same_budget = earlier.clone();
        same_budget.run.iterations = self.run.iterations;
        same_budget.hash() == self.hash()
    }

    /// Samples per iteration (envs × steps per env).
    pub fn samples_per_iteration(&self) -> usize {
        self.env.num_envs * self.ppo.steps_per_env
    }
}
