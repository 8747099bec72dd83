//! [`EnvConfig`], the one description of the training environment: what host-trainer's
//! `[env]` table deserialises into, what the Python binding's keyword arguments build, and
//! what [`super::VecEnv::new`] takes. Every field has its unit and the paper's value; the
//! `Default` is the paper's stage 1 ([`EnvConfig::paper`]), and [`EnvConfig::stage1`] /
//! [`EnvConfig::stage2`] are the shipped pipelines' (`host-trainer/configs/stage1.toml`,
//! the race config), held equal to those files by host-trainer's tests.
//!
//! A training config states the environment in three places, which land here: `[env]` is
//! the serialised part of this struct; `[reward]` is [`EnvConfig::reward`] and `[race]` is
//! [`EnvConfig::race`] (both their own TOML tables, so `#[serde(skip)]` here); the row of
//! `[run]` picks [`EnvConfig::layout`] and the run's seed is [`EnvConfig::seed`].

use super::reward::{Competition, RewardWeights};
use crate::dynamics::{Preset, PresetName};
use crate::perturb::{JitterSpec, PerturbSpec};
use crate::referee::SpawnMode;
use firmware_core::observation::{ObservationLayout, ObservationSpec};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The most envs one environment holds: a bound that keeps an absurd request a clear error
/// instead of an allocation failure (memory is allocated up front, ~1 kB per env).
pub const MAX_ENVS: usize = 1 << 20;

/// Highest spawn speed accepted (m/s): beyond the fastest flight the track allows.
pub const MAX_SPAWN_SPEED_MPS: f32 = 20.0;

/// The paper's divisor of the own body-frame velocity in the observation (m/s).
pub const PAPER_VELOCITY_SCALE_MPS: f32 = 3.0;

/// What the envs fly: alone against the clock, or a race against a frozen opponent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Task {
    /// Stage 1: one drone per world.
    #[default]
    TimeTrial,
    /// Stage 2: the ego and an opponent in one world.
    Race,
}

impl Task {
    /// Its name as the Python binding writes it (`"time_trial"`, `"race"`).
    pub fn name(self) -> &'static str {
        match self {
            Self::TimeTrial => "time_trial",
            Self::Race => "race",
        }
    }
}

impl core::str::FromStr for Task {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "time_trial" => Ok(Self::TimeTrial),
            "race" => Ok(Self::Race),
            _ => Err(format!("task '{s}': expected 'time_trial' or 'race'")),
        }
    }
}

/// The opponent and the competition reward of a stage-2 environment (`[race]` in a training
/// config).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RaceConfig {
    /// The opponent's blob: a time-trial (17-value) policy, feed-forward or recurrent, read
    /// and validated when the environment is built. Relative to the working directory (the
    /// repository root for the commands in the docs). Paper: the stage-1 policy (row A).
    pub opponent: PathBuf,
    /// Which competition reward: "dense" (eq. 6; rows B, C, E-G), "sparse" (eq. 7; row D),
    /// or "lead" (not the paper's: the lead in track progress).
    pub competition: Competition,
    /// Its weight λ_c (× dt like every term). Paper: 0.5. Default 0.5.
    #[serde(default = "paper_competition_weight")]
    pub competition_weight: f32,
    /// The share of training spawns (0 to 1) with the roles swapped: the ego at the
    /// opponent's place, 1 m ahead, the opponent at the ego's. Not the paper's (its ego always
    /// starts behind, so its data is saturated with trailing: a policy never trained in the
    /// lead flies worse there, docs/journal/stage2.md). Default 0: the paper's spawn, and
    /// no random number drawn.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ego_ahead_fraction: f32,
}

fn paper_competition_weight() -> f32 {
    0.5
}

fn paper_velocity_scale() -> f32 {
    PAPER_VELOCITY_SCALE_MPS
}

fn is_zero(v: &f32) -> bool {
    *v == 0.0
}

fn one() -> f32 {
    1.0
}

fn is_one(v: &f32) -> bool {
    *v == 1.0
}

fn is_false(v: &bool) -> bool {
    !*v
}

/// How the training environment is built. The serialised fields are a training config's
/// `[env]`; their order and the ones left out at their defaults are part of every shipped
/// blob's config hash, so a field added later must be skipped at its default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvConfig {
    /// Parallel envs (1 to [`MAX_ENVS`]). Paper: 8,192 (on a GPU).
    pub num_envs: usize,
    /// Dynamics preset. Paper: `paper`.
    pub preset: PresetName,
    /// Where time-trial episodes start: `stage1` (the paper's fixed spawn), `along-track` (a
    /// random point of the centreline, at rest) or `stage2` (2 m before a random gate). A
    /// race always starts at the paper's stage-2 spawn and must say `stage2`.
    pub spawn: SpawnMode,
    /// Episode length before a time-out (s). Paper stage 1: 15.
    pub episode_s: f32,
    /// Start every env at a random point of its first episode (RSL-RL's
    /// `init_at_random_ep_len`), so that time-outs are spread over iterations. Paper: true.
    pub random_initial_episode_length: bool,
    /// Divisor of the own body-frame velocity in the observation (m/s). Paper: 3 (the
    /// observation saturates at 3 m/s); the shipped policies: 12. Default 3. Recorded in the
    /// exported blob's observation spec.
    #[serde(default = "paper_velocity_scale")]
    pub velocity_scale_mps: f32,
    /// Highest initial speed (m/s) of a time-trial spawn along its heading, drawn uniformly
    /// from [0, this], at most [`MAX_SPAWN_SPEED_MPS`]. Paper: 0 (at rest). Default 0.
    #[serde(default)]
    pub spawn_speed_mps: f32,
    /// Share of time-trial respawns at the paper's fixed stage-1 spawn (at rest) whatever
    /// `spawn` is: the start the referee evaluates stage 1 from. Paper: 0. Default 0.
    #[serde(default)]
    pub stage1_fraction: f32,
    /// Share of the time-trial respawns that are neither replayed nor stage-1 at the paper's
    /// stage-2 spawn (at rest, 2 m or 1 m before a random gate and targeting it: the ego's or
    /// the opponent's start of a race, each half the time), where the stage-1 policy starts
    /// as stage 2's opponent. Paper: 0. Default 0 (left out of the TOML at 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub stage2_fraction: f32,
    /// Share of time-trial respawns that restart from a state the env itself flew through
    /// right after one of its recent gate passes (position, attitude, velocity, rates,
    /// propeller speeds, next target and previous action), when it has one: Song et al.
    /// 2023's "states from successful gate passes". Paper: 0. Default 0 (left out at 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub replay_fraction: f32,
    /// Fold the track onto one half by its mirror symmetry (`firmware_core::mirror`): steps
    /// flying to the mirrored half's gates (g3-g5) observe their mirror image and fly the
    /// image's action renumbered back. Recorded in the blob (observation pipeline version
    /// 2), so the controller folds as training did. Paper: false. Default false (left out).
    #[serde(default, skip_serializing_if = "is_false")]
    pub fold_mirror: bool,
    /// Domain randomisation of the ego (not the paper's): the referee's perturbations
    /// (docs/DESIGN.md "Perturbations") in `sitl eval --perturb`'s words, e.g.
    /// `"latency=0:1,motor-tau-ms=0:30,noise=1"`. The airframe and the latency are drawn at
    /// every spawn, the sensor noise is added to the ego's observed state every step; the
    /// opponent flies the nominal airframe. Default none (left out).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub randomize: Option<PerturbSpec>,
    /// The share of spawns whose ego `randomize` draws (the others fly the nominal airframe
    /// and latency, without noise): a trainer raises it over a run (`[randomize_ramp]`).
    /// Whether a spawn is drawn comes from the randomisation generator, so the spawns stay
    /// where they were. Default 1 (left out at 1).
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub randomize_share: f32,
    /// Jitter of the ego's start (not the paper's): every spawn that is not a replayed pass
    /// moved as the referee's `sitl eval --jitter` moves a start (`""`: ±5 cm, ±5°, ±0.2 m/s
    /// per axis; or `pos=M,att-deg=DEG,vel=MPS`), drawn from the spawn generator. A race's
    /// opponent keeps its place (its recorded flight is keyed by it). Default none (left
    /// out): no draw, so configs without it keep their streams.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spawn_jitter: Option<JitterSpec>,
    /// Which terms an observation holds: 17 values for a time trial (row A), 20 for row B,
    /// 30 for rows C-G. In a training config, `run.row` sets it.
    #[serde(skip, default = "time_trial_layout")]
    pub layout: ObservationLayout,
    /// The reward's weights: a training config's `[reward]` table. Paper: the defaults.
    #[serde(skip)]
    pub reward: RewardWeights,
    /// Stage 2: race an opponent (`None`: a time trial): a training config's `[race]`
    /// table. A race spawns at the paper's stage-2 spawn.
    #[serde(skip)]
    pub race: Option<RaceConfig>,
    /// Seed of the spawns and initial episode lengths (env i draws from stream i). In a
    /// training config, the trainer's seed for each environment it builds.
    #[serde(skip)]
    pub seed: u64,
}

fn time_trial_layout() -> ObservationLayout {
    ObservationLayout::TimeTrial17
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self::paper(1)
    }
}

/// A field of an [`EnvConfig`] out of its range: the field as a config writes it
/// (`velocity_scale_mps`, `reward.crash`, `race.competition_weight`) and what it must be.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvConfigError {
    /// The field.
    pub field: &'static str,
    /// What is wrong, with the value.
    pub problem: String,
}

impl core::fmt::Display for EnvConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{}: {}", self.field, self.problem)
    }
}

impl std::error::Error for EnvConfigError {}

fn refuse(field: &'static str, problem: String) -> Result<(), EnvConfigError> {
    Err(EnvConfigError { field, problem })
}

impl EnvConfig {
    /// `num_envs` envs of the paper's stage 1: the `paper` preset, its reward and
    /// observation (velocity scale 3), 15 s episodes from the fixed stage-1 spawn with
    /// random initial episode lengths, seed 0.
    pub fn paper(num_envs: usize) -> Self {
        Self {
            num_envs,
            preset: PresetName::Paper,
            spawn: SpawnMode::Stage1,
            episode_s: 15.0,
            random_initial_episode_length: true,
            velocity_scale_mps: PAPER_VELOCITY_SCALE_MPS,
            spawn_speed_mps: 0.0,
            stage1_fraction: 0.0,
            stage2_fraction: 0.0,
            replay_fraction: 0.0,
            fold_mirror: false,
            randomize: None,
            randomize_share: 1.0,
            spawn_jitter: None,
            layout: ObservationLayout::TimeTrial17,
            reward: RewardWeights::default(),
            race: None,
            seed: 0,
        }
    }

    /// `num_envs` envs with the paper's settings spawned along the track at rest, seeded
    /// with `seed`: the base that tests adjust.
    pub fn paper_along_track(num_envs: usize, seed: u64) -> Self {
        Self {
            spawn: SpawnMode::AlongTrack,
            seed,
            ..Self::paper(num_envs)
        }
    }

    /// The environment of the shipped stage-1 pipeline (`host-trainer/configs/stage1.toml`'s
    /// `[env]` and `[reward]`, before its pass weight decays): spawns along the track moving
    /// at up to 8 m/s, 20 % at the stage-1 spawn, 30 % replayed, a quarter of the rest at
    /// stage-2 starts; the track folded; velocity scale 12; crash weight 1. What
    /// `policies/stage1.blob` observes.
    pub fn stage1(num_envs: usize) -> Self {
        Self {
            spawn: SpawnMode::AlongTrack,
            velocity_scale_mps: 12.0,
            spawn_speed_mps: 8.0,
            stage1_fraction: 0.2,
            stage2_fraction: 0.25,
            replay_fraction: 0.3,
            fold_mirror: true,
            reward: RewardWeights {
                crash: 1.0,
                ..RewardWeights::default()
            },
            ..Self::paper(num_envs)
        }
    }

    /// The environment of the shipped stage-2 pipeline: the paper's race (stage-2 spawns,
    /// row G's 30 values, the dense competition reward at 0.5, the paper's reward weights)
    /// against `opponent`, with the shipped velocity scale of 12.
    pub fn stage2(num_envs: usize, opponent: impl Into<PathBuf>) -> Self {
        Self {
            spawn: SpawnMode::Stage2,
            velocity_scale_mps: 12.0,
            layout: ObservationLayout::FullOpponent30,
            race: Some(RaceConfig {
                opponent: opponent.into(),
                competition: Competition::Dense,
                competition_weight: paper_competition_weight(),
                ego_ahead_fraction: 0.0,
            }),
            ..Self::paper(num_envs)
        }
    }

    /// What the envs fly.
    pub fn task(&self) -> Task {
        if self.race.is_some() {
            Task::Race
        } else {
            Task::TimeTrial
        }
    }

    /// The dynamics preset's parameters.
    pub fn preset(&self) -> Preset {
        self.preset.preset()
    }

    /// The observation spec every observation follows, as the exported blob's header records
    /// it: the paper's scales for [`EnvConfig::layout`] with `velocity_scale_mps`, folded
    /// with `fold_mirror`.
    pub fn observation_spec(&self) -> ObservationSpec {
        let mut spec = ObservationSpec::paper(self.layout);
        spec.velocity_scale_mps = self.velocity_scale_mps;
        spec.with_fold(self.fold_mirror)
    }

    /// The settings of a policy that observes through `spec`: its layout, velocity scale and
    /// fold; the task follows the layout (an opponent-observing layout races).
    pub fn observing_as(self, spec: &ObservationSpec) -> Self {
        Self {
            layout: spec.layout,
            velocity_scale_mps: spec.velocity_scale_mps,
            fold_mirror: spec.is_folded(),
            ..self
        }
    }

    /// Refuses a policy that observes through `spec` when these envs observe otherwise
    /// (another layout, velocity scale, fold or scale): flown here, it would see
    /// observations it was not trained on. The error names every difference.
    pub fn check_policy(&self, spec: &ObservationSpec) -> Result<(), EnvConfigError> {
        let ours = self.observation_spec();
        if ours == *spec {
            return Ok(());
        }
        let mut differences = Vec::new();
        if ours.layout != spec.layout {
            differences.push(format!(
                "layout: the policy observes {} values, the envs {}",
                spec.layout.dim(),
                ours.layout.dim()
            ));
        }
        if ours.velocity_scale_mps != spec.velocity_scale_mps {
            differences.push(format!(
                "velocity_scale_mps: the policy's is {}, the envs' {}",
                spec.velocity_scale_mps, ours.velocity_scale_mps
            ));
        }
        if ours.is_folded() != spec.is_folded() {
            differences.push(format!(
                "fold_mirror: the policy's is {}, the envs' {}",
                spec.is_folded(),
                ours.is_folded()
            ));
        }
        if differences.is_empty() {
            differences.push(format!(
                "the policy's other observation scales differ ({spec:?} against {ours:?})"
            ));
        }
        refuse(
            "observation",
            format!(
                "the policy and the environment disagree ({}); build the envs the policy expects (make_vec_env(policy=PATH), EnvConfig::observing_as)",
                differences.join("; ")
            ),
        )
    }

    /// Every field in its range, the layout matching the task, and the reward weights and
    /// race finite; the error names the first field that is not.
    pub fn validate(&self) -> Result<(), EnvConfigError> {
        if !(1..=MAX_ENVS).contains(&self.num_envs) {
            return refuse(
                "num_envs",
                format!(
                    "{}: expected 1 to {MAX_ENVS} (memory is allocated up front)",
                    self.num_envs
                ),
            );
        }
        if !(self.episode_s.is_finite() && self.episode_s > 0.0) {
            return refuse(
                "episode_s",
                format!("{}: expected a positive number of seconds", self.episode_s),
            );
        }
        // The observation pipeline's own check (the one a blob's header passes).
        if !self.observation_spec().is_supported() {
            return refuse(
                "velocity_scale_mps",
                format!("{}: expected a positive speed", self.velocity_scale_mps),
            );
        }
        if !(0.0..=MAX_SPAWN_SPEED_MPS).contains(&self.spawn_speed_mps) {
            return refuse(
                "spawn_speed_mps",
                format!(
                    "{}: expected a speed in [0, {MAX_SPAWN_SPEED_MPS}] m/s",
                    self.spawn_speed_mps
                ),
            );
        }
        for (field, share) in [
            ("stage1_fraction", self.stage1_fraction),
            ("stage2_fraction", self.stage2_fraction),
            ("replay_fraction", self.replay_fraction),
            ("randomize_share", self.randomize_share),
        ] {
            if !(0.0..=1.0).contains(&share) {
                return refuse(field, format!("{share}: expected a share in [0, 1]"));
            }
        }
        self.validate_reward()?;
        self.validate_task()
    }

    fn validate_reward(&self) -> Result<(), EnvConfigError> {
        let w = &self.reward;
        for (field, weight) in [
            ("reward.progress", w.progress),
            ("reward.command", w.command),
            ("reward.smoothness", w.smoothness),
            ("reward.pass", w.pass),
            ("reward.crash", w.crash),
        ] {
            if !(weight.is_finite() && weight >= 0.0) {
                return refuse(field, format!("{weight}: expected a finite weight >= 0"));
            }
        }
        Ok(())
    }

    /// The layout and spawn against the task.
    fn validate_task(&self) -> Result<(), EnvConfigError> {
        let racing = self.race.is_some();
        if self.layout.needs_opponent() != racing {
            return refuse(
                "layout",
                format!(
                    "{} values: a {} needs a layout that observes {}",
                    self.layout.dim(),
                    self.task().name(),
                    if racing {
                        "the opponent (20 or 30 values, rows B-G)"
                    } else {
                        "no opponent (17 values, row A)"
                    }
                ),
            );
        }
        let Some(r) = &self.race else {
            return Ok(());
        };
        if self.spawn != SpawnMode::Stage2 {
            return refuse(
                "spawn",
                format!(
                    "'{}': a race starts at the paper's stage-2 spawn, write \"stage2\"",
                    self.spawn.name()
                ),
            );
        }
        if r.opponent.as_os_str().is_empty() {
            return refuse("race.opponent", "must name a blob".into());
        }
        if !(r.competition_weight.is_finite() && r.competition_weight >= 0.0) {
            return refuse(
                "race.competition_weight",
                format!("{}: expected a finite weight >= 0", r.competition_weight),
            );
        }
        if !(0.0..=1.0).contains(&r.ego_ahead_fraction) {
            return refuse(
                "race.ego_ahead_fraction",
                format!("{}: expected a share from 0 to 1", r.ego_ahead_fraction),
            );
        }
        Ok(())
    }
}
