//! The training run: rollouts in the vectorised environment, PPO updates, metrics,
//! checkpoints, resume, learning curves and the export of the trained actor.
//!
//! **Rollouts fly the deployed network.** Every iteration the actor's weights are written in
//! blob payload order and viewed by firmware-core's `Policy`, the code the flight controller
//! runs; the rollout's Gaussian means come from it (in parallel over envs), the noise from one
//! seeded generator. The update recomputes means and values with `burn` in one batched pass,
//! so the ratio of the first minibatch is 1 up to the parity of the two implementations
//! (< 1e-5, tested).
//!
//! **Output directory** (`--out`):
//! - `config.toml`: the configuration the run used;
//! - `metrics.jsonl`: one JSON object per iteration (reward terms, success, crashes, losses,
//!   KL, learning rate, σ, speed) and, every `run.eval_every` iterations, the referee's
//!   evaluation of the current policy (`eval_*` keys);
//! - `checkpoints/iter_NNNNNN/` (networks and Adam states as burnpack files, `state.json`) and
//!   `checkpoints/latest`, the name of the newest complete checkpoint, replaced atomically
//!   after every file of the checkpoint is on disk: a kill at any moment leaves the previous
//!   checkpoint usable, and `--resume` loses at most `run.checkpoint_every` iterations;
//! - at the end: `<name>.blob` (firmware-core blob with provenance: run name, seed,
//!   iterations, preset, config hash), `<name>.safetensors` (the actor with RSL-RL's names)
//!   and `learning_curves.svg`.
//!
//! **Resume.** The networks, Adam states, learning rate, iteration, metrics and the
//! generators of the action noise and of the minibatches are restored. The environments are
//! not stored: a resumed run respawns them (with a seed derived from the iteration and random
//! initial episode lengths), so its trajectory differs from an uninterrupted run's from that
//! point, its learning state does not.

use crate::config::{Guard, TrainConfig};
use crate::env::{EnvConfig, EnvStats, RaceConfig, TrainEnv};
use crate::imitation::Imitate;
use crate::model::{Actor, Critic, init_rng};
use crate::ppo::{Learner, PolicyNet, Rollout, UpdateStats, ValueNet, adam};
use crate::recurrent::{RecurrentActor, RecurrentCritic};
use burn::tensor::Device;
use firmware_core::blob::AlignedBytes;
use firmware_core::blob::{BlobHeader, Provenance, encode};
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::{Observation, ObservationLayout, ObservationSpec};
use firmware_core::policy::{Architecture, Policy, TableRow};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, Report, report};
use sitl::files::write_atomically;
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Why a run stopped early.
#[derive(Debug)]
pub enum TrainError {
    /// A file could not be read or written.
    Io(PathBuf, std::io::Error),
    /// The output directory holds a run and `--resume` was not given, or there is nothing
    /// to resume.
    OutDir(String),
    /// A checkpoint could not be used.
    Checkpoint(String),
    /// The configuration cannot be trained by this trainer.
    Unsupported(String),
    /// The trained network could not be exported.
    Export(String),
}

impl core::fmt::Display for TrainError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Io(p, e) => write!(f, "{}: {e}", p.display()),
            Self::OutDir(m) | Self::Checkpoint(m) | Self::Unsupported(m) | Self::Export(m) => {
                f.write_str(m)
            }
        }
    }
}

impl std::error::Error for TrainError {}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |e| TrainError::Io(path.to_path_buf(), e)
}

/// How a run is started.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Continue from `out/checkpoints/latest`.
    pub resume: bool,
    /// The autodiff device of the update.
    pub device: Device,
    /// Show a progress bar (off for tests and non-interactive logs).
    pub progress: bool,
    /// Stop after this many iterations of this invocation (tests of resume); `None` runs to
    /// the configured budget.
    pub stop_after: Option<u32>,
    /// Start a fresh run's actor from this blob's weights (σ from the config) instead of a
    /// random initialisation and the warm start: fine-tuning a policy, e.g. one imported from
    /// RSL-RL. Ignored on resume.
    pub init_actor: Option<PathBuf>,
}

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
    /// Update statistics.
    pub surrogate_loss: f64,
    /// Value loss.
    pub value_loss: f64,
    /// Entropy.
    pub entropy: f64,
    /// Mean KL per minibatch.
    pub kl: f64,
    /// Clip fraction.
    pub clip_fraction: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Learning rate after the update.
    pub learning_rate: f64,
    /// Mean σ of the policy.
    pub action_std: f64,
    /// Minibatches skipped for a non-finite loss or gradient.
    #[serde(default)]
    pub skipped_minibatches: u32,
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

/// What `checkpoints/iter_N/state.json` holds besides the networks.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct CheckpointState {
    iteration: u32,
    samples: u64,
    wall_s: f64,
    learning_rate: f64,
    config_hash: String,
    noise_rng: String,
    shuffle_rng: String,
}

/// The end of a run.
#[derive(Clone, Debug)]
pub struct RunSummary {
    /// Iterations done in total.
    pub iterations: u32,
    /// Wall-clock seconds of training (all invocations).
    pub wall_s: f64,
    /// The exported blob, when the run reached its budget.
    pub blob: Option<PathBuf>,
    /// The last referee evaluation.
    pub last: IterationMetrics,
    /// With `run.keep_best`: the metrics of the iteration whose actor was exported.
    pub best: Option<IterationMetrics>,
}

/// Whether the referee scored evaluation `a` better than `b` (`run.keep_best`): the higher
/// success rate, then the lower crash rate; an exact tie keeps the earlier (`b`).
pub fn referee_prefers(a: &IterationMetrics, b: &IterationMetrics) -> bool {
    let key = |m: &IterationMetrics| {
        (
            m.eval_success_rate.unwrap_or(f64::NEG_INFINITY),
            -m.eval_crash_rate.unwrap_or(f64::INFINITY),
        )
    };
    let (ka, kb) = (key(a), key(b));
    ka.0 > kb.0 || (ka.0 == kb.0 && ka.1 > kb.1)
}

/// The best-scored evaluation of `history` (`run.keep_best`): the one [`referee_prefers`]
/// to every other, the earliest of equals.
pub fn best_evaluation(history: &[IterationMetrics]) -> Option<&IterationMetrics> {
    history
        .iter()
        .filter(|m| m.eval_success_rate.is_some())
        .fold(None, |best, m| match best {
            Some(b) if !referee_prefers(m, b) => Some(b),
            _ => Some(m),
        })
}

/// The actor (weights and σ) as RSL-RL's safetensors, written beside every exported blob.
fn actor_safetensors<A: PolicyNet>(actor: &A, arch: &Architecture) -> Result<Vec<u8>, TrainError> {
    crate::rslrl::export_actor(arch, &actor.payload(), Some(&actor.std()))
        .map_err(|e| TrainError::Export(e.to_string()))
}

/// Where `run.keep_best` keeps the actor of an evaluated iteration (never overwritten, so a
/// resume finds the best of the metrics it kept).
fn best_candidate_path(paths: &Paths, iteration: u32, ext: &str) -> PathBuf {
    paths
        .checkpoints
        .join(format!("best_iter_{iteration:06}.{ext}"))
}

fn rng_state(r: &ChaCha8Rng) -> String {
    format!("{}:{}", r.get_stream(), r.get_word_pos())
}

fn restore_rng(seed: u64, s: &str) -> Option<ChaCha8Rng> {
    let (stream, pos) = s.split_once(':')?;
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream.parse().ok()?);
    r.set_word_pos(pos.parse().ok()?);
    Some(r)
}

fn generator(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream);
    r
}

/// A standard normal sample (Box–Muller).
pub fn normal(rng: &mut ChaCha8Rng) -> f32 {
    let u1: f32 = rng.random_range(f32::EPSILON..1.0);
    let u2: f32 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (core::f32::consts::TAU * u2).cos()
}

/// The Table 1 row and architecture of a config (A in a time trial, B to G in a race).
pub fn architecture(config: &TrainConfig) -> Result<(TableRow, Architecture), TrainError> {
    let row = match config.run.row {
        'A' => TableRow::A,
        'B' => TableRow::B,
        'C' => TableRow::C,
        'D' => TableRow::D,
        'E' => TableRow::E,
        'F' => TableRow::F,
        'G' => TableRow::G,
        r => {
            return Err(TrainError::Unsupported(format!(
                "run.row '{r}': Table 1 has rows A to G"
            )));
        }
    };
    Ok((row, Architecture::table1(row)))
}

/// The environment of a config, seeded with `seed`: a time trial, or a race against the
/// config's opponent (read and validated here).
pub fn make_env(config: &TrainConfig, seed: u64) -> Result<TrainEnv, TrainError> {
    build_env(env_config(config, seed)?)
}

/// The environment of `config` (a time trial, or a race against its opponent).
fn build_env(config: EnvConfig) -> Result<TrainEnv, TrainError> {
    TrainEnv::with_race(config).map_err(|e| TrainError::Unsupported(e.to_string()))
}

/// The training environment of a config, seeded with `seed`.
pub fn env_config(config: &TrainConfig, seed: u64) -> Result<EnvConfig, TrainError> {
    let preset = Preset::by_name(&config.env.preset)
        .ok_or_else(|| TrainError::Unsupported(format!("preset '{}'", config.env.preset)))?;
    let spawn = SpawnMode::by_name(&config.env.spawn)
        .ok_or_else(|| TrainError::Unsupported(format!("spawn '{}'", config.env.spawn)))?;
    Ok(EnvConfig {
        num_envs: config.env.num_envs,
        preset,
        spawn,
        episode_s: config.env.episode_s,
        random_initial_episode_length: config.env.random_initial_episode_length,
        spawn_speed_mps: config.env.spawn_speed_mps,
        stage1_fraction: config.env.stage1_fraction,
        reward: config.reward,
        observation: observation_spec(config),
        seed,
        race: match &config.race {
            None => None,
            Some(r) => {
                let raw = std::fs::read(&r.opponent).map_err(|e| {
                    TrainError::Unsupported(format!("race.opponent '{}': {e}", r.opponent))
                })?;
                Some(RaceConfig {
                    opponent: AlignedBytes::new(&raw),
                    competition: r.competition,
                    competition_weight: r.competition_weight,
                })
            }
        },
    })
}

/// The action that holds hover with the config's preset and the paper's action map.
pub fn hover_action(config: &TrainConfig) -> f32 {
    let preset = Preset::by_name(&config.env.preset).unwrap_or_else(Preset::paper);
    firmware_core::vehicle::ActionMap::PAPER.action_for_rpm(preset.hover_rpm())
}

/// The observation spec of a config: the paper's layout for its row (17 values for A, 20
/// for B, 30 for the others) with the configured velocity scale.
pub fn observation_spec(config: &TrainConfig) -> ObservationSpec {
    let layout = match config.run.row {
        'A' => ObservationLayout::TimeTrial17,
        'B' => ObservationLayout::OpponentPosition20,
        _ => ObservationLayout::FullOpponent30,
    };
    let mut spec = ObservationSpec::paper(layout);
    spec.velocity_scale_mps = config.env.velocity_scale_mps;
    spec
}

/// The actor as a firmware-core blob with the run's provenance.
pub fn actor_blob<A: PolicyNet>(
    actor: &A,
    config: &TrainConfig,
    iterations: u32,
) -> Result<Vec<u8>, TrainError> {
    payload_blob(&actor.payload(), config, iterations)
}

/// The blob of the weights `payload` (firmware-core order) under the run's header, as
/// [`actor_blob`].
fn payload_blob(
    payload: &[f32],
    config: &TrainConfig,
    iterations: u32,
) -> Result<Vec<u8>, TrainError> {
    let (row, _) = architecture(config)?;
    let mut name = heapless::String::new();
    name.push_str(&config.run.name)
        .map_err(|_| TrainError::Export("run.name longer than 32 bytes".into()))?;
    let mut preset = heapless::String::new();
    preset
        .push_str(&config.env.preset)
        .map_err(|_| TrainError::Export("preset name longer than 16 bytes".into()))?;
    let provenance = Provenance {
        name,
        seed: config.run.seed,
        iterations,
        preset,
        config_hash: config.hash(),
    };
    let mut header = BlobHeader::paper(row, provenance);
    header.observation = observation_spec(config);
    encode(&header, payload).map_err(|e| TrainError::Export(format!("blob export failed: {e:?}")))
}

/// The referee's verdict on the deterministic policy. A time trial: one 45 s episode from the
/// stage-1 spawn (the evaluation of issue "stage1"; the fixed spawn and the deterministic
/// policy make every such episode identical, so one is enough). A race: `run.eval_races`
/// 45 s races against the config's opponent from stage-2 spawns (seed `run.eval_seed`).
fn referee_eval(blob: &[u8], preset: Preset, config: &TrainConfig) -> Option<Report> {
    let spec = PilotSpec::from_blob("training", blob).ok()?;
    let opponent = match &config.race {
        None => None,
        Some(r) => Some(PilotSpec::load(&r.opponent, &preset).ok()?),
    };
    let eval = EvalConfig {
        preset,
        episodes: if opponent.is_some() {
            config.run.eval_races
        } else {
            1
        },
        seconds: 45.0,
        seed: config.run.eval_seed,
        spawn: Some(if opponent.is_some() {
            SpawnMode::Stage2
        } else {
            SpawnMode::Stage1
        }),
    };
    Some(report(&spec, opponent.as_ref(), &eval))
}

struct Paths {
    out: PathBuf,
    checkpoints: PathBuf,
    latest: PathBuf,
    metrics: PathBuf,
}

impl Paths {
    fn new(out: &Path) -> Self {
        Self {
            out: out.to_path_buf(),
            checkpoints: out.join("checkpoints"),
            latest: out.join("checkpoints").join("latest"),
            metrics: out.join("metrics.jsonl"),
        }
    }
}

/// Everything that evolves during a run.
struct RunState<A = Actor, C = Critic> {
    learner: Learner<A, C>,
    iteration: u32,
    samples: u64,
    wall_s: f64,
    noise_rng: ChaCha8Rng,
    shuffle_rng: ChaCha8Rng,
    history: Vec<IterationMetrics>,
}

fn save_checkpoint<A: PolicyNet, C: ValueNet>(
    paths: &Paths,
    s: &RunState<A, C>,
    config: &TrainConfig,
) -> Result<(), TrainError> {
    let name = format!("iter_{:06}", s.iteration);
    let dir = paths.checkpoints.join(&name);
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(io(&dir))?;
    }
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let ck = |e: burn::store::RecordError| TrainError::Checkpoint(format!("{name}: {e:?}"));
    s.learner
        .actor
        .clone()
        .save_file(dir.join("actor.bpk"))
        .map_err(ck)?;
    s.learner
        .critic
        .clone()
        .save_file(dir.join("critic.bpk"))
        .map_err(ck)?;
    s.learner
        .actor_optim
        .save(dir.join("actor_optim.bpk"))
        .map_err(ck)?;
    s.learner
        .critic_optim
        .save(dir.join("critic_optim.bpk"))
        .map_err(ck)?;
    let state = CheckpointState {
        iteration: s.iteration,
        samples: s.samples,
        wall_s: s.wall_s,
        learning_rate: s.learner.learning_rate,
        config_hash: format!("{:016x}", config.hash()),
        noise_rng: rng_state(&s.noise_rng),
        shuffle_rng: rng_state(&s.shuffle_rng),
    };
    let json = serde_json::to_string_pretty(&state).unwrap_or_default();
    write_atomically(&dir.join("state.json"), json.as_bytes()).map_err(io(&dir))?;
    // The burnpack files are written by burn without fsync: sync the directory's files
    // before the pointer names it.
    for f in [
        "actor.bpk",
        "critic.bpk",
        "actor_optim.bpk",
        "critic_optim.bpk",
    ] {
        let p = dir.join(f);
        std::fs::File::open(&p)
            .and_then(|h| h.sync_all())
            .map_err(io(&p))?;
    }
    write_atomically(&paths.latest, name.as_bytes()).map_err(io(&paths.latest))?;
    // Keep the newest two checkpoints.
    if let Ok(entries) = std::fs::read_dir(&paths.checkpoints) {
        let mut dirs: Vec<String> = entries
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("iter_") && !n.ends_with(".tmp"))
            .collect();
        dirs.sort();
        let keep = dirs.len().saturating_sub(2);
        for old in &dirs[..keep] {
            let _ = std::fs::remove_dir_all(paths.checkpoints.join(old));
        }
    }
    Ok(())
}

fn load_checkpoint<A: PolicyNet, C: ValueNet>(
    paths: &Paths,
    config: &TrainConfig,
    arch: &Architecture,
    device: &Device,
) -> Result<RunState<A, C>, TrainError> {
    let name = std::fs::read_to_string(&paths.latest).map_err(|_| {
        TrainError::OutDir(format!(
            "nothing to resume: {} does not exist",
            paths.latest.display()
        ))
    })?;
    let dir = paths.checkpoints.join(name.trim());
    let bad = |m: String| TrainError::Checkpoint(format!("{}: {m}", dir.display()));
    let state: CheckpointState =
        serde_json::from_str(&std::fs::read_to_string(dir.join("state.json")).map_err(io(&dir))?)
            .map_err(|e| bad(format!("state.json: {e}")))?;
    let hash = format!("{:016x}", config.hash());
    if state.config_hash != hash {
        return Err(bad(format!(
            "written by a run with config hash {}, this config hashes to {hash}; resume with the run's own config.toml",
            state.config_hash
        )));
    }
    let seed = config.run.seed;
    let mut rng = init_rng(seed);
    let actor = A::fresh(arch, config.ppo.init_std, &mut rng, device)
        .try_load_file(dir.join("actor.bpk"))
        .map_err(|e| bad(format!("actor.bpk: {e:?}")))?;
    let critic = C::fresh(arch, &mut rng, device)
        .try_load_file(dir.join("critic.bpk"))
        .map_err(|e| bad(format!("critic.bpk: {e:?}")))?;
    let actor_optim = adam()
        .load(dir.join("actor_optim.bpk"))
        .map_err(|e| bad(format!("actor_optim.bpk: {e:?}")))?;
    let critic_optim = adam()
        .load(dir.join("critic_optim.bpk"))
        .map_err(|e| bad(format!("critic_optim.bpk: {e:?}")))?;
    let mut learner = Learner::new(actor, critic, state.learning_rate, device.clone());
    learner.actor_optim = actor_optim;
    learner.critic_optim = critic_optim;
    let noise_rng = restore_rng(seed, &state.noise_rng).ok_or_else(|| bad("noise_rng".into()))?;
    let shuffle_rng =
        restore_rng(seed, &state.shuffle_rng).ok_or_else(|| bad("shuffle_rng".into()))?;
    // The metrics up to the checkpoint; later lines belong to the lost interval.
    let history: Vec<IterationMetrics> = std::fs::read_to_string(&paths.metrics)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<IterationMetrics>(l).ok())
        .filter(|m| m.iteration <= state.iteration)
        .collect();
    Ok(RunState {
        learner,
        iteration: state.iteration,
        samples: state.samples,
        wall_s: state.wall_s,
        noise_rng,
        shuffle_rng,
        history,
    })
}

/// The learner (actor, critic, Adam states, learning rate) of the latest checkpoint in `out`
/// and its iteration (for diagnostics on a run's networks).
pub fn checkpoint_learner(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Learner), TrainError> {
    let (_, arch) = architecture(config)?;
    let state = load_checkpoint::<Actor, Critic>(&Paths::new(out), config, &arch, device)?;
    Ok((state.iteration, state.learner))
}

/// The actor of the latest checkpoint in `out` as a blob with the run's provenance (for
/// exporting a run that has not finished), feed-forward or recurrent, and its iteration.
pub fn checkpoint_blob(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Vec<u8>), TrainError> {
    fn latest<A: PolicyNet, C: ValueNet>(
        paths: &Paths,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
    ) -> Result<(u32, Vec<u8>), TrainError> {
        let s = load_checkpoint::<A, C>(paths, config, arch, device)?;
        Ok((
            s.iteration,
            actor_blob(&s.learner.actor, config, s.iteration)?,
        ))
    }
    let (_, arch) = architecture(config)?;
    let paths = Paths::new(out);
    if arch.is_recurrent() {
        latest::<RecurrentActor, RecurrentCritic>(&paths, config, &arch, device)
    } else {
        latest::<Actor, Critic>(&paths, config, &arch, device)
    }
}

/// The feed-forward actor of the latest checkpoint in `out` (for checking a resume).
pub fn checkpoint_actor(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Actor), TrainError> {
    let (_, arch) = architecture(config)?;
    let state = load_checkpoint::<Actor, Critic>(&Paths::new(out), config, &arch, device)?;
    Ok((state.iteration, state.learner.actor))
}

fn write_curves(paths: &Paths, name: &str, history: &[IterationMetrics]) -> Result<(), TrainError> {
    let p = paths.out.join("learning_curves.svg");
    write_atomically(&p, learning_curves(name, history).as_bytes()).map_err(io(&p))
}

fn write_metrics(paths: &Paths, history: &[IterationMetrics]) -> Result<(), TrainError> {
    let mut text = String::new();
    for m in history {
        text.push_str(&serde_json::to_string(m).unwrap_or_default());
        text.push('\n');
    }
    write_atomically(&paths.metrics, text.as_bytes()).map_err(io(&paths.metrics))
}

fn append_metrics(paths: &Paths, m: &IterationMetrics) -> Result<(), TrainError> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&paths.metrics)
        .map_err(io(&paths.metrics))?;
    let line = serde_json::to_string(m).unwrap_or_default();
    writeln!(f, "{line}").map_err(io(&paths.metrics))
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
                series("value loss", &|m| Some(m.value_loss)),
                series("action σ", &|m| Some(m.action_std)),
                series("KL ×100", &|m| Some(100.0 * m.kl)),
                series("learning rate ×1000", &|m| Some(1000.0 * m.learning_rate)),
            ],
        ),
    ];
    grid(&charts, 2)
}

/// An actor holding the weights of the blob at `path`, which must be a row-A blob with the
/// config's observation spec; σ is the config's `init_std`.
fn actor_from_blob<A: PolicyNet>(
    path: &Path,
    arch: &Architecture,
    config: &TrainConfig,
    device: &Device,
) -> Result<A, TrainError> {
    let raw = std::fs::read(path).map_err(io(path))?;
    let bytes = firmware_core::blob::AlignedBytes::new(&raw);
    let blob = firmware_core::blob::Blob::parse(bytes.as_bytes())
        .map_err(|e| TrainError::Checkpoint(format!("{}: {e}", path.display())))?;
    if blob.header().architecture != *arch {
        return Err(TrainError::Checkpoint(format!(
            "{}: not a row-{} blob",
            path.display(),
            config.run.row
        )));
    }
    if blob.header().observation != observation_spec(config) {
        return Err(TrainError::Checkpoint(format!(
            "{}: its observation spec differs from the config's (env.velocity_scale_mps?)",
            path.display()
        )));
    }
    let std = vec![config.ppo.init_std; usize::from(arch.action_dim)];
    A::from_payload(arch, &blob.dequantized(), &std, device)
        .ok_or_else(|| TrainError::Checkpoint(format!("{}: weights do not fit", path.display())))
}

/// The imitation warm start of a fresh run from `student` (the initial actor, or
/// `warm_start.student`): the result replaces the initial actor (its σ
/// kept), the rounds go to `imitation.jsonl`, and a checkpoint at iteration 0 keeps a resume
/// from redoing it.
#[allow(clippy::too_many_arguments)]
fn warm_start<A: PolicyNet, C: ValueNet>(
    state: &mut RunState<A, C>,
    student: A,
    config: &TrainConfig,
    warm: &crate::config::WarmStart,
    paths: &Paths,
    device: &Device,
    progress: bool,
    imitate: impl Fn(
        A,
        &crate::config::WarmStart,
        &mut dyn FnMut(&crate::imitation::ImitationRound, &[f32]),
    ) -> Result<(A, Vec<crate::imitation::ImitationRound>), TrainError>,
) -> Result<(), TrainError> {
    let started = Instant::now();
    let teacher = match &warm.teacher_blob {
        Some(p) => p.clone(),
        None => format!("the baseline at {} m/s", warm.teacher_cruise_mps),
    };
    let rounds: u32 = warm.stages().iter().map(|s| s.rounds).sum();
    println!("imitation warm start: {rounds} DAgger rounds of {teacher}");
    let bar = if progress {
        ProgressBar::new(u64::from(rounds))
    } else {
        ProgressBar::hidden()
    };
    let log_path = paths.out.join("imitation.jsonl");
    let mut text = String::new();
    // A line above the progress bar, or on stdout without one.
    let say = |line: String| {
        if progress {
            bar.println(line);
        } else {
            println!("{line}");
        }
    };
    let mut actor = student;
    let preset = Preset::by_name(&config.env.preset).unwrap_or_else(Preset::paper);
    if warm.keep_best_round {
        std::fs::create_dir_all(&paths.checkpoints).map_err(io(&paths.checkpoints))?;
    }
    // `warm_start.keep_best_round`: the best-refereed round so far, its weights.
    let mut best: Option<(crate::imitation::ImitationRound, Vec<f32>)> = None;
    let mut failure: Option<TrainError> = None;
    // Rounds are numbered through the stages in the log.
    let mut before = 0;
    for (k, stage) in warm.stages().iter().enumerate() {
        if k > 0 {
            say(format!(
                "refine stage {k}: {} rounds of {} steps, the student flying",
                stage.rounds, stage.steps_per_env
            ));
        }
        let last = stage.rounds;
        actor = imitate(actor, stage, &mut |r, payload| {
            let mut r = crate::imitation::ImitationRound {
                round: before + r.round,
                ..r.clone()
            };
            if warm.keep_best_round && failure.is_none() {
                match referee_round(&r, payload, config, paths, preset) {
                    Ok(refereed) => r = refereed,
                    Err(e) => failure = Some(e),
                }
                if round_prefers(&r, best.as_ref().map(|b| &b.0)) {
                    best = Some((r.clone(), payload.to_vec()));
                }
            }
            bar.inc(1);
            bar.set_message(format!("mse {:.4}", r.mse));
            text.push_str(&serde_json::to_string(&r).unwrap_or_default());
            text.push('\n');
            if r.round.is_multiple_of(5) || r.round == before + last {
                let referee = match (r.referee_success_rate, r.referee_crash_rate) {
                    (Some(s), Some(c)) => format!("  referee: success {s:.3}, crashes {c:.3}/s"),
                    _ => String::new(),
                };
                say(format!(
                    "round {:>3}  teacher {:.2}  {} samples  mse {:.4}  gates {:.2}/s  crashes {:.3}/s{referee}",
                    r.round, r.teacher_share, r.samples, r.mse, r.gates_per_s, r.crash_rate_per_s
                ));
            }
        })?
        .0;
        if let Some(e) = failure.take() {
            return Err(e);
        }
        before += last;
    }
    if let Some((round, payload)) = best {
        let (_, arch) = architecture(config)?;
        actor = A::from_payload(&arch, &payload, &actor.std(), device)
            .ok_or_else(|| TrainError::Unsupported("warm start: best round's weights".into()))?;
        say(format!(
            "the warm start ends with round {}'s student, the referee's best",
            round.round
        ));
    }
    bar.finish_and_clear();
    write_atomically(&log_path, text.as_bytes()).map_err(io(&log_path))?;
    let elapsed = started.elapsed().as_secs_f64();
    state.wall_s += elapsed;
    state.learner = Learner::new(
        actor,
        state.learner.critic.clone(),
        state.learner.learning_rate,
        device.clone(),
    );
    if let Some(r) = referee_eval(
        &actor_blob(&state.learner.actor, config, 0)?,
        preset,
        config,
    ) {
        println!(
            "imitation done in {elapsed:.0} s; the student, referee: success {:.3}, crashes {:.3}/s, best lap {}{}",
            r.success_rate,
            r.crash_rate,
            r.best_lap_s.map_or("DNF".into(), |l| format!("{l:.2} s")),
            if config.race.is_some() {
                format!(
                    ", {} overtakes ({} sustained)",
                    r.overtakes, r.sustained_overtakes
                )
            } else {
                String::new()
            }
        );
    }
    let student = paths.out.join("warm_start.blob");
    write_atomically(&student, &actor_blob(&state.learner.actor, config, 0)?)
        .map_err(io(&student))?;
    std::fs::create_dir_all(&paths.checkpoints).map_err(io(&paths.checkpoints))?;
    save_checkpoint(paths, state, config)
}

/// Where `warm_start.keep_best_round` keeps a round's student.
fn warm_start_round_blob(paths: &Paths, round: u32) -> PathBuf {
    paths
        .checkpoints
        .join(format!("warm_start_round_{round:03}.blob"))
}

/// `round` with the referee's scores of its student `payload` (`run.eval_races` races on
/// `run.eval_seed`), whose blob is written to [`warm_start_round_blob`].
fn referee_round(
    round: &crate::imitation::ImitationRound,
    payload: &[f32],
    config: &TrainConfig,
    paths: &Paths,
    preset: Preset,
) -> Result<crate::imitation::ImitationRound, TrainError> {
    let blob = payload_blob(payload, config, 0)?;
    let path = warm_start_round_blob(paths, round.round);
    write_atomically(&path, &blob).map_err(io(&path))?;
    let report = referee_eval(&blob, preset, config);
    Ok(crate::imitation::ImitationRound {
        referee_success_rate: report.as_ref().map(|r| r.success_rate),
        referee_crash_rate: report.as_ref().map(|r| r.crash_rate),
        ..round.clone()
    })
}

/// Whether the refereed round `a` is better than `b` (absent: none yet): the higher success,
/// then the fewer crashes, the earlier of equals ([`referee_prefers`]'s order).
fn round_prefers(
    a: &crate::imitation::ImitationRound,
    b: Option<&crate::imitation::ImitationRound>,
) -> bool {
    let key = |r: &crate::imitation::ImitationRound| IterationMetrics {
        eval_success_rate: r.referee_success_rate,
        eval_crash_rate: r.referee_crash_rate,
        ..IterationMetrics::default()
    };
    a.referee_success_rate.is_some() && b.is_none_or(|b| referee_prefers(&key(a), &key(b)))
}

/// Collects `steps` steps of every env of `env` into `rollout` (cleared first): actions are
/// `policy`'s Gaussian means (firmware-core's network, the deployed code, in parallel over
/// envs) plus `std`-scaled noise drawn serially from `noise_rng`. `on_step` sees each step's
/// rewards and dones.
pub fn collect_rollout(
    env: &mut TrainEnv,
    policy: &Policy<'_>,
    std: &[f32],
    steps: usize,
    noise_rng: &mut ChaCha8Rng,
    rollout: &mut Rollout,
    mut on_step: impl FnMut(&[f32], &[bool]),
) -> Result<(), TrainError> {
    let obs_dim = env.obs_dim();
    if policy.obs_dim() != obs_dim {
        return Err(TrainError::Unsupported(format!(
            "the policy observes {} values, the environment gives {obs_dim}",
            policy.obs_dim()
        )));
    }
    let n = env.num_envs();
    rollout.clear();
    // The recurrent state of every env carries over from the last window; a new rollout (or
    // a different env count) starts from zero.
    if rollout.memory.len() != n {
        rollout.memory = vec![policy.initial_state(); n];
    }
    if policy.is_recurrent() {
        for s in &rollout.memory {
            crate::recurrent::push_flat_state(s, &mut rollout.actor_h0);
        }
    }
    let mut actions = vec![0.0f32; n * ACTION_DIM];
    let mut noise = vec![0.0f32; n * ACTION_DIM];
    for _ in 0..steps {
        let obs = env.observations();
        rollout.obs.extend_from_slice(obs);
        for z in &mut noise {
            *z = normal(noise_rng);
        }
        actions
            .par_chunks_mut(ACTION_DIM * 64)
            .zip(obs.par_chunks(obs_dim * 64))
            .zip(noise.par_chunks(ACTION_DIM * 64))
            .zip(rollout.memory.par_chunks_mut(64))
            .for_each(|(((a, o), z), memory)| {
                for (((a, o), z), memory) in a
                    .chunks_exact_mut(ACTION_DIM)
                    .zip(o.chunks_exact(obs_dim))
                    .zip(z.chunks_exact(ACTION_DIM))
                    .zip(memory)
                {
                    let mean = Observation::from_values(o).and_then(|o| policy.act(&o, memory));
                    let Some(mean) = mean else {
                        continue;
                    };
                    for k in 0..ACTION_DIM {
                        a[k] = mean[k] + std.get(k).copied().unwrap_or(0.0) * z[k];
                    }
                }
            });
        rollout.actions.extend_from_slice(&actions);
        env.step(&actions)
            .map_err(|e| TrainError::Unsupported(e.to_string()))?;
        rollout.rewards.extend_from_slice(env.rewards());
        rollout.dones.extend_from_slice(env.dones());
        rollout.timeouts.extend_from_slice(env.timeouts());
        for (m, _) in rollout
            .memory
            .iter_mut()
            .zip(env.dones())
            .filter(|(_, d)| **d)
        {
            m.clear();
        }
        on_step(env.rewards(), env.dones());
    }
    rollout.last_obs.extend_from_slice(env.observations());
    Ok(())
}

/// Reward per step of the Gaussian policy with weights `payload` and σ `std` on the guard's
/// test rollout, the environments and the action noise seeded by `seed`.
pub fn measured_return(
    payload: &[f32],
    std: &[f32],
    arch: &Architecture,
    config: &TrainConfig,
    guard: &Guard,
    seed: u64,
) -> Result<f64, TrainError> {
    let policy = Policy::from_payload(arch, payload)
        .map_err(|e| TrainError::Export(format!("actor does not load as a blob: {e}")))?;
    let mut c = env_config(config, seed)?;
    c.num_envs = guard.envs;
    let mut env = build_env(c)?;
    let mut rng = generator(seed, 7);
    let mut rollout = Rollout::new(guard.envs, env.obs_dim());
    if guard.warmup_steps > 0 {
        collect_rollout(
            &mut env,
            &policy,
            std,
            guard.warmup_steps,
            &mut rng,
            &mut rollout,
            |_, _| {},
        )?;
    }
    let (mut sum, mut count) = (0.0f64, 0usize);
    collect_rollout(
        &mut env,
        &policy,
        std,
        guard.steps,
        &mut rng,
        &mut rollout,
        |r, _| {
            sum += r.iter().map(|&x| f64::from(x)).sum::<f64>();
            count += r.len();
        },
    )?;
    Ok(sum / count.max(1) as f64)
}

/// The guard's line search after an update from `before` (weights, log σ): keeps the
/// largest of 1, 1/2, 1/4 of the update whose measured return is at least the old one's,
/// else restores `before`, resets the actor's Adam state and halves the learning rate.
/// Returns (share kept, return before, return kept).
fn guard_update<A: PolicyNet, C: ValueNet>(
    learner: &mut Learner<A, C>,
    before: (&[f32], &[f32]),
    arch: &Architecture,
    config: &TrainConfig,
    guard: &Guard,
    seed: u64,
) -> Result<(f64, f64, f64), TrainError> {
    let (old_w, old_std) = before;
    let new_w = learner.actor.payload();
    let new_std = learner.actor.std();
    let base = measured_return(old_w, old_std, arch, config, guard, seed)?;
    for share in [1.0f32, 0.5, 0.25] {
        let w: Vec<f32> = old_w
            .iter()
            .zip(&new_w)
            .map(|(a, b)| a + share * (b - a))
            .collect();
        let std: Vec<f32> = old_std
            .iter()
            .zip(&new_std)
            .map(|(a, b)| (a.ln() + share * (b.ln() - a.ln())).exp())
            .collect();
        let r = measured_return(&w, &std, arch, config, guard, seed)?;
        if r >= base {
            if share < 1.0 {
                learner.actor = A::from_payload(arch, &w, &std, &learner.device)
                    .ok_or_else(|| TrainError::Export("guard: weights do not fit".into()))?;
            }
            return Ok((f64::from(share), base, r));
        }
    }
    learner.actor = A::from_payload(arch, old_w, old_std, &learner.device)
        .ok_or_else(|| TrainError::Export("guard: weights do not fit".into()))?;
    learner.actor_optim = adam();
    learner.learning_rate = (learner.learning_rate / 2.0).max(config.ppo.min_learning_rate);
    Ok((0.0, base, base))
}
/// Runs (or resumes) the training run of `config` into `options.out`: PPO on the
/// feed-forward networks of rows A-D, recurrent PPO on the LSTM networks of rows E-G.
pub fn run(config: &TrainConfig, options: &RunOptions) -> Result<RunSummary, TrainError> {
    let (_, arch) = architecture(config)?;
    if arch.is_recurrent() {
        run_networks::<RecurrentActor, RecurrentCritic>(config, options)
    } else {
        run_networks::<Actor, Critic>(config, options)
    }
}

/// [`run`] for one pair of networks.
fn run_networks<A: Imitate, C: ValueNet>(
    config: &TrainConfig,
    options: &RunOptions,
) -> Result<RunSummary, TrainError> {
    let (_, arch) = architecture(config)?;
    // Refuse an unreadable opponent before any work.
    make_env(
        &TrainConfig {
            env: crate::config::EnvSection {
                num_envs: 1,
                ..config.env.clone()
            },
            ..config.clone()
        },
        0,
    )?;
    let paths = Paths::new(&options.out);
    let device = options.device.clone();
    let mut state = if options.resume {
        load_checkpoint(&paths, config, &arch, &device)?
    } else {
        if paths.latest.exists() {
            return Err(TrainError::OutDir(format!(
                "{} already holds a run (checkpoints/latest); pass --resume to continue it or choose another --out",
                paths.out.display()
            )));
        }
        std::fs::create_dir_all(&paths.checkpoints).map_err(io(&paths.checkpoints))?;
        let mut rng = init_rng(config.run.seed);
        let mut actor = A::fresh(&arch, config.ppo.init_std, &mut rng, &device);
        let critic = C::fresh(&arch, &mut rng, &device);
        if config.ppo.init_hover {
            actor = actor.with_output_bias(hover_action(config));
        }
        RunState {
            learner: Learner::new(actor, critic, config.ppo.learning_rate, device.clone()),
            iteration: 0,
            samples: 0,
            wall_s: 0.0,
            noise_rng: generator(config.run.seed, u64::MAX - 1),
            shuffle_rng: generator(config.run.seed, u64::MAX - 2),
            history: Vec::new(),
        }
    };
    if state.iteration == 0 && !options.resume {
        if let Some(path) = &options.init_actor {
            let actor = actor_from_blob(path, &arch, config, &device)?;
            state.learner = Learner::new(
                actor,
                state.learner.critic.clone(),
                state.learner.learning_rate,
                device.clone(),
            );
            println!("actor initialised from {}", path.display());
            std::fs::create_dir_all(&paths.checkpoints).map_err(io(&paths.checkpoints))?;
            save_checkpoint(&paths, &state, config)?;
        } else if let Some(warm) = &config.warm_start {
            let student = match &warm.student {
                Some(path) => {
                    println!("the warm start refines the student {path}");
                    actor_from_blob(Path::new(path), &arch, config, &device)?
                }
                None => state.learner.actor.clone(),
            };
            warm_start(
                &mut state,
                student,
                config,
                warm,
                &paths,
                &device,
                options.progress,
                |actor, stage, log| A::imitate(actor, &arch, config, stage, &device, log),
            )?;
        }
    }
    let config_text = toml::to_string(config).unwrap_or_default();
    write_atomically(&paths.out.join("config.toml"), config_text.as_bytes())
        .map_err(io(&paths.out))?;
    write_metrics(&paths, &state.history)?;

    let preset = Preset::by_name(&config.env.preset).unwrap_or_else(Preset::paper);
    let env_seed = config
        .run
        .seed
        .wrapping_add(u64::from(state.iteration).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let mut env = make_env(config, env_seed)?;
    let n = env.num_envs();
    let steps = config.ppo.steps_per_env;
    let params = &config.ppo;
    let dt = f64::from(env.dt_s());
    let mut rollout = Rollout::new(n, env.obs_dim());
    let mut episode_return = vec![0.0f64; n];
    let mut episode_len = vec![0u32; n];
    let mut finished: VecDeque<(f64, u32)> = VecDeque::with_capacity(200);
    let total = config.run.iterations;
    let stop_at = options
        .stop_after
        .map_or(total, |k| (state.iteration + k).min(total));

    let bar = if options.progress {
        let b = ProgressBar::new(u64::from(total));
        b.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} it  {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        b.set_position(u64::from(state.iteration));
        b
    } else {
        ProgressBar::hidden()
    };
    let eval_every = config.run.eval_every.max(1);

    while state.iteration < stop_at {
        let started = Instant::now();
        state.learner.train_actor = config
            .warm_start
            .as_ref()
            .is_none_or(|w| state.iteration >= w.critic_iterations);
        // Rollout with the deployed network.
        let payload = state.learner.actor.payload();
        let std = state.learner.actor.std();
        let policy = Policy::from_payload(&arch, &payload)
            .map_err(|e| TrainError::Export(format!("actor does not load as a blob: {e}")))?;
        collect_rollout(
            &mut env,
            &policy,
            &std,
            steps,
            &mut state.noise_rng,
            &mut rollout,
            |rewards, dones| {
                for e in 0..n {
                    episode_return[e] += f64::from(rewards[e]);
                    episode_len[e] += 1;
                    if dones[e] {
                        if finished.len() == 200 {
                            finished.pop_front();
                        }
                        finished.push_back((episode_return[e], episode_len[e]));
                        episode_return[e] = 0.0;
                        episode_len[e] = 0;
                    }
                }
            },
        )?;
        let env_stats: EnvStats = env.take_stats();
        let rollout_s = started.elapsed().as_secs_f64();

        // Update.
        let t_update = Instant::now();
        let batch = state.learner.prepare(&rollout, params);
        if let Some(seq) = &batch.sequence {
            // The critic's state for the next window (the actor's lives in the rollout).
            rollout.critic_h0.clone_from(&seq.critic_next);
        }
        let u: UpdateStats = state.learner.update(&batch, params, &mut state.shuffle_rng);
        let guarded = match (&config.guard, state.learner.train_actor) {
            (Some(g), true) => Some(guard_update(
                &mut state.learner,
                (&payload, &std),
                &arch,
                config,
                g,
                config
                    .run
                    .seed
                    .wrapping_mul(0x2545_f491_4f6c_dd1d)
                    .wrapping_add(u64::from(state.iteration)),
            )?),
            _ => None,
        };
        let update_s = t_update.elapsed().as_secs_f64();

        state.iteration += 1;
        let batch_samples = (n * steps) as u64;
        state.samples += batch_samples;
        let iter_s = started.elapsed().as_secs_f64();
        state.wall_s += iter_s;
        let per_step = |v: f64| v / env_stats.steps.max(1) as f64;
        let sim_s = env_stats.steps as f64 * dt;
        let std_now = state.learner.actor.std();
        let mut m = IterationMetrics {
            iteration: state.iteration,
            samples: state.samples,
            wall_s: state.wall_s,
            samples_per_s: batch_samples as f64 / iter_s,
            rollout_s,
            update_s,
            reward_per_step: per_step(env_stats.terms.total()),
            reward_progress: per_step(env_stats.terms.progress),
            reward_command: per_step(env_stats.terms.command),
            reward_smoothness: per_step(env_stats.terms.smoothness),
            reward_pass: per_step(env_stats.terms.pass),
            reward_crash: per_step(env_stats.terms.crash),
            reward_competition: config
                .race
                .as_ref()
                .map(|_| per_step(env_stats.terms.competition)),
            opponent_crash_rate_per_s: config
                .race
                .as_ref()
                .map(|_| env_stats.opponent_crashes as f64 / sim_s.max(1e-9)),
            episode_return: finished.iter().map(|e| e.0).sum::<f64>()
                / finished.len().max(1) as f64,
            episode_s: finished.iter().map(|e| f64::from(e.1)).sum::<f64>() * dt
                / finished.len().max(1) as f64,
            success_rate: env_stats.success_rate(),
            crash_rate_per_s: env_stats.crashes as f64 / sim_s.max(1e-9),
            gates_per_s: env_stats.gates_passed as f64 / sim_s.max(1e-9),
            surrogate_loss: u.surrogate_loss,
            value_loss: u.value_loss,
            entropy: u.entropy,
            kl: u.kl,
            clip_fraction: u.clip_fraction,
            grad_norm: u.grad_norm,
            learning_rate: u.learning_rate,
            skipped_minibatches: u.skipped,
            action_std: std_now.iter().map(|&s| f64::from(s)).sum::<f64>()
                / std_now.len().max(1) as f64,
            ..IterationMetrics::default()
        };
        if let Some((share, before, after)) = guarded {
            m.guard_step = Some(share);
            m.guard_reward_before = Some(before);
            m.guard_reward_after = Some(after);
        }
        if state.iteration % eval_every == 0 || state.iteration == total {
            let blob = actor_blob(&state.learner.actor, config, state.iteration)?;
            if let Some(r) = referee_eval(&blob, preset, config) {
                m.eval_success_rate = Some(r.success_rate);
                m.eval_crash_rate = Some(r.crash_rate);
                m.eval_best_lap_s = r.best_lap_s;
                m.eval_gates = Some(r.gates_passed);
                if config.race.is_some() {
                    m.eval_overtakes = Some(r.overtakes);
                    m.eval_sustained_overtakes = Some(r.sustained_overtakes);
                }
            }
            if config.run.keep_best
                && m.eval_success_rate.is_some()
                && best_evaluation(&state.history).is_none_or(|b| referee_prefers(&m, b))
            {
                // Written before the metrics line that makes it the best, so a resume from
                // any later checkpoint finds it.
                std::fs::create_dir_all(&paths.checkpoints).map_err(io(&paths.checkpoints))?;
                let p = best_candidate_path(&paths, state.iteration, "blob");
                write_atomically(&p, &blob).map_err(io(&p))?;
                let p = best_candidate_path(&paths, state.iteration, "safetensors");
                write_atomically(&p, &actor_safetensors(&state.learner.actor, &arch)?)
                    .map_err(io(&p))?;
            }
            let lap = m
                .eval_best_lap_s
                .map_or("DNF".to_string(), |l| format!("{l:.2} s"));
            let line = format!(
                "it {:>5}  {:>6.0} s  {:>7.0} samples/s  reward/step {:+.4}  rollout success {:.3}  referee: success {:.3}, crashes {:.3}/s, best lap {lap}",
                m.iteration,
                m.wall_s,
                m.samples_per_s,
                m.reward_per_step,
                m.success_rate,
                m.eval_success_rate.unwrap_or(0.0),
                m.eval_crash_rate.unwrap_or(0.0),
            );
            if options.progress {
                bar.println(line);
            } else {
                println!("{line}");
            }
        }
        bar.set_position(u64::from(state.iteration));
        bar.set_message(format!(
            "{:.0} samples/s  reward/step {:+.4}  success {:.3}  σ {:.2}",
            m.samples_per_s, m.reward_per_step, m.success_rate, m.action_std
        ));
        let evaluated = m.eval_success_rate.is_some();
        append_metrics(&paths, &m)?;
        state.history.push(m);
        if evaluated {
            // Curves to watch while the run goes on.
            write_curves(&paths, &config.run.name, &state.history)?;
        }
        if state.iteration % config.run.checkpoint_every == 0 || state.iteration == stop_at {
            save_checkpoint(&paths, &state, config)?;
        }
    }
    bar.finish_and_clear();

    write_curves(&paths, &config.run.name, &state.history)?;
    let mut blob_path = None;
    let best = if config.run.keep_best {
        best_evaluation(&state.history).cloned()
    } else {
        None
    };
    if state.iteration >= total {
        let (blob, st) = match &best {
            Some(b) => {
                let read = |ext| {
                    let p = best_candidate_path(&paths, b.iteration, ext);
                    std::fs::read(&p).map_err(io(&p))
                };
                (read("blob")?, read("safetensors")?)
            }
            None => (
                actor_blob(&state.learner.actor, config, state.iteration)?,
                actor_safetensors(&state.learner.actor, &arch)?,
            ),
        };
        let p = paths.out.join(format!("{}.blob", config.run.name));
        write_atomically(&p, &blob).map_err(io(&p))?;
        let sp = paths.out.join(format!("{}.safetensors", config.run.name));
        write_atomically(&sp, &st).map_err(io(&sp))?;
        blob_path = Some(p);
    }
    Ok(RunSummary {
        iterations: state.iteration,
        wall_s: state.wall_s,
        blob: blob_path,
        last: state.history.last().cloned().unwrap_or_default(),
        best,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_referee_prefers_success_then_fewer_crashes_then_the_earlier() {
        let eval = |iteration, success, crashes| IterationMetrics {
            iteration,
            eval_success_rate: Some(success),
            eval_crash_rate: Some(crashes),
            ..IterationMetrics::default()
        };
        let history = [
            eval(5, 0.80, 0.10),
            IterationMetrics {
                iteration: 6,
                ..IterationMetrics::default()
            },
            eval(10, 0.85, 0.20),
            eval(15, 0.85, 0.10),
            eval(20, 0.85, 0.10),
            eval(25, 0.70, 0.00),
        ];
        assert_eq!(best_evaluation(&history).map(|m| m.iteration), Some(15));
        assert!(referee_prefers(&history[2], &history[0]));
        assert!(!referee_prefers(&history[4], &history[3]));
        assert!(best_evaluation(&history[1..2]).is_none());
    }

    /// stage1.toml with a small guard, and the shipped student as its actor.
    fn student_learner() -> (TrainConfig, Architecture, Learner) {
        let mut config = TrainConfig::parse(include_str!("../configs/stage1.toml")).unwrap();
        config.guard = Some(Guard {
            envs: 64,
            warmup_steps: 10,
            steps: 100,
        });
        let (_, arch) = architecture(&config).unwrap();
        let device = Device::flex().autodiff();
        let blob = Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies/stage1_imitation.blob");
        let actor = actor_from_blob(&blob, &arch, &config, &device).unwrap();
        let critic = Critic::new(&arch, &mut init_rng(1), &device);
        (config, arch, Learner::new(actor, critic, 1e-4, device))
    }

    #[test]
    fn the_guard_rejects_an_update_that_lowers_the_measured_return() {
        let (config, arch, mut learner) = student_learner();
        let guard = config.guard.clone().unwrap();
        let (w, std) = (learner.actor.payload(), learner.actor.std());
        // The same seed measures the same return: the comparison is common random numbers.
        let r = measured_return(&w, &std, &arch, &config, &guard, 5).unwrap();
        assert_eq!(
            r,
            measured_return(&w, &std, &arch, &config, &guard, 5).unwrap()
        );
        // An "update" that adds ±1e-2 to every weight (it breaks the student): rejected, the
        // student restored, the learning rate halved.
        let mut rng = generator(3, 0);
        let broken: Vec<f32> = w.iter().map(|v| v + 1e-2 * normal(&mut rng)).collect();
        learner.actor = Actor::from_payload(&arch, &broken, &std, &learner.device).unwrap();
        let (share, before, after) =
            guard_update(&mut learner, (&w, &std), &arch, &config, &guard, 5).unwrap();
        assert_eq!(share, 0.0, "before {before}, after {after}");
        assert_eq!(learner.actor.payload(), w);
        assert_eq!(learner.learning_rate, 5e-5);
        // No change at all is no loss: kept whole.
        let (share, before, after) =
            guard_update(&mut learner, (&w, &std), &arch, &config, &guard, 6).unwrap();
        assert_eq!((share, before), (1.0, after));
    }
}
