//! A run's output directory (`--out`): what is written where, and the checkpoints that make
//! a run resumable.
//!
//! - `config.toml`: the configuration the run used;
//! - `metrics.jsonl`: one JSON object per iteration ([`IterationMetrics`]: reward terms,
//!   success, crashes, losses, KL, learning rate, σ, speed) and, every `run.eval_every`
//!   iterations, the referee's evaluation of the current policy (`eval_*` keys); appended
//!   to, never rewritten (a resume cuts the lines past its checkpoint and keeps the rest
//!   byte for byte);
//! - `imitation.jsonl` and `warm_start.blob`: the warm start's rounds and its student;
//! - `forked_from.json` (`--fork-from`): the parent run, iteration and config hash a fork
//!   started from;
//! - `checkpoints/iter_NNNNNN/` (networks and Adam states as burnpack files, the fused
//!   update's Adam state as `fused_adam.safetensors` once it has one, `state.json` with the
//!   counters, the generators, the format and every file's SHA-256; a corrupt latest
//!   checkpoint is reported and the previous one used) and
//!   `checkpoints/latest`, the name of the newest complete checkpoint, replaced atomically
//!   after every file of the checkpoint is on disk: a kill at any moment leaves the previous
//!   checkpoint usable, and `--resume` loses at most `run.checkpoint_every` iterations;
//! - `checkpoints/best_iter_NNNNNN.{blob,safetensors}` (`run.keep_best`) and
//!   `checkpoints/warm_start_round_NNN.blob` (`warm_start.keep_best_round`): candidates for
//!   export, never overwritten, so a resume finds them;
//! - at the end: `<name>.blob` (firmware-core blob with provenance: run name, seed,
//!   iterations, preset, config hash), `<name>.safetensors` (the actor with RSL-RL's names)
//!   and `learning_curves.svg`.
//!
//! **Resume is bit for bit.** The networks, Adam states, learning rate, iteration, metrics
//! and the generators of the action noise and of the minibatches are restored, and so is the
//! rollout's world: every env's state ([`sitl::env::EnvSnapshot`]: drones, opponent,
//! generators, randomisation, replayed passes, observations), the policy's recurrent state in
//! every env, the critic's carried state and the episode log, in `loop.json`
//! ([`LoopSnapshot`]). A resumed run is then the uninterrupted run, weights and metrics to the
//! last bit (tested, `tests/resume.rs`). A checkpoint written before the loop was stored
//! (before the first iteration of an invocation, or by an older build) has no `loop.json`:
//! the envs are then respawned from a seed derived from the iteration, as every invocation's
//! start does, and the run says so.

use crate::config::TrainConfig;
use crate::error::{TrainError, io};
use crate::fused::FusedOptim;
use crate::metrics::{IterationMetrics, learning_curves};
use crate::model::{Actor, Critic};
use crate::nets::{PolicyNet, ValueNet};
use crate::ppo::{Learner, adam};
use crate::rng::{init_rng, restore_rng, rng_state};
use burn::tensor::Device;
use firmware_core::policy::Architecture;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sitl::files::write_atomically;
use std::path::{Path, PathBuf};

/// The rollout's world between two iterations (`loop.json` in a checkpoint): what a resumed
/// run needs to step on as the uninterrupted one would.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoopSnapshot {
    /// Every env's state.
    pub env: sitl::env::EnvSnapshot,
    /// The policy's recurrent state in every env, flat (`envs × width`; empty when
    /// feed-forward).
    pub policy_memory: Vec<f32>,
    /// The critic's state carried into the next window (empty when feed-forward or zero).
    pub critic_h0: Vec<f32>,
    /// The returns and lengths of the episodes running and recently ended.
    pub episodes: crate::rollout::EpisodeLog,
}

/// The file of a checkpoint that holds its [`LoopSnapshot`].
const LOOP_FILE: &str = "loop.json";

/// Everything that evolves during a run, and what a checkpoint keeps of it.
pub(crate) struct RunState<A = Actor, C = Critic> {
    /// The networks, their Adam states and the learning rate.
    pub learner: Learner<A, C>,
    /// Iterations done.
    pub iteration: u32,
    /// Env-steps trained on so far.
    pub samples: u64,
    /// Wall-clock seconds of training so far (all invocations).
    pub wall_s: f64,
    /// The action noise of the rollouts.
    pub noise_rng: ChaCha8Rng,
    /// The minibatch order of the updates.
    pub shuffle_rng: ChaCha8Rng,
    /// Every iteration's metrics so far.
    pub history: Vec<IterationMetrics>,
    /// The rollout's world the checkpoint this state was loaded from kept (taken by the
    /// iteration loop when it starts); `None` for a fresh state.
    pub resumed_loop: Option<LoopSnapshot>,
}

/// What `checkpoints/iter_N/state.json` holds besides the networks.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct CheckpointState {
    /// [`CHECKPOINT_FORMAT`] when written (absent: 0, before checksums).
    #[serde(default)]
    format: u32,
    /// SHA-256 of every other file of the checkpoint, by name (format 1).
    #[serde(default)]
    files: std::collections::BTreeMap<String, String>,
    iteration: u32,
    samples: u64,
    wall_s: f64,
    learning_rate: f64,
    config_hash: String,
    noise_rng: String,
    shuffle_rng: String,
}

/// The files of a run's output directory.
pub(crate) struct RunDir {
    /// The directory.
    pub out: PathBuf,
    checkpoints: PathBuf,
    latest: PathBuf,
    metrics: PathBuf,
}

/// The checkpoint format this build writes: 1 adds the files' checksums to `state.json`.
const CHECKPOINT_FORMAT: u32 = 1;

/// The fused update's Adam state in a checkpoint ([`crate::fused::FusedOptim`]), written
/// once the learner has one.
const FUSED_ADAM: &str = "fused_adam.safetensors";

/// The network files of a checkpoint.
const CHECKPOINT_FILES: [&str; 4] = [
    "actor.bpk",
    "critic.bpk",
    "actor_optim.bpk",
    "critic_optim.bpk",
];

/// The lock a trainer holds on its run directory (`run.lock`, an exclusive `flock`) from
/// before its first write to its exit: a second trainer on the same directory (a `--resume`
/// typed while the run still goes) is refused, instead of writing checkpoints beside the
/// first and cutting its metrics file. The kernel releases it when the trainer dies, so a
/// killed run resumes without clean-up. Without `flock` (not unix) nothing is locked.
#[derive(Debug)]
pub struct RunLock {
    _file: std::fs::File,
}

/// Takes the lock of the run directory `out` ([`RunLock`]), as a trainer does before writing
/// it; an error says which trainer holds it.
pub fn lock(out: &Path) -> Result<RunLock, TrainError> {
    RunDir::new(out).lock()
}

impl RunDir {
    /// Takes the run's lock (creating the directory), or says which trainer holds it.
    pub fn lock(&self) -> Result<RunLock, TrainError> {
        use std::io::Write;
        std::fs::create_dir_all(&self.out).map_err(io(&self.out))?;
        let path = self.file("run.lock");
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)
            .map_err(io(&path))?;
        #[cfg(unix)]
        if let Err(e) =
            rustix::fs::flock(&file, rustix::fs::FlockOperation::NonBlockingLockExclusive)
        {
            if e == rustix::io::Errno::WOULDBLOCK {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                return Err(TrainError::OutDir(format!(
                    "{}: another trainer is writing this run ({}); wait for it to end or stop it, then --resume",
                    self.out.display(),
                    holder.trim()
                )));
            }
            return Err(TrainError::OutDir(format!("{}: {e}", path.display())));
        }
        file.set_len(0)
            .and_then(|()| writeln!(file, "pid {}", std::process::id()))
            .map_err(io(&path))?;
        Ok(RunLock { _file: file })
    }

    /// The run directory `out` (nothing is created).
    pub fn new(out: &Path) -> Self {
        Self {
            out: out.to_path_buf(),
            checkpoints: out.join("checkpoints"),
            latest: out.join("checkpoints").join("latest"),
            metrics: out.join("metrics.jsonl"),
        }
    }

    /// Whether a run has written a checkpoint here.
    pub fn holds_run(&self) -> bool {
        self.latest.exists()
    }

    /// Creates `checkpoints/` (and the directory).
    pub fn create(&self) -> Result<(), TrainError> {
        std::fs::create_dir_all(&self.checkpoints).map_err(io(&self.checkpoints))
    }

    /// A file directly in the directory.
    pub fn file(&self, name: &str) -> PathBuf {
        self.out.join(name)
    }

    /// Where `run.keep_best` keeps the actor of evaluated iteration `iteration`.
    pub fn best_candidate(&self, iteration: u32, ext: &str) -> PathBuf {
        self.checkpoints
            .join(format!("best_iter_{iteration:06}.{ext}"))
    }

    /// Copies `parent`'s `run.keep_best` candidates of iterations up to `up_to` (a fork's
    /// start) into this run, so that a best evaluation from before the fork, which the forked
    /// history carries, is exported from here as the parent would have.
    pub fn adopt_best_candidates(&self, parent: &RunDir, up_to: u32) -> Result<(), TrainError> {
        let Ok(entries) = std::fs::read_dir(&parent.checkpoints) else {
            return Ok(());
        };
        for entry in entries.filter_map(Result::ok) {
            let name = entry.file_name().to_string_lossy().into_owned();
            let iteration = name
                .strip_prefix("best_iter_")
                .and_then(|rest| rest.split('.').next())
                .and_then(|digits| digits.parse::<u32>().ok());
            if name.ends_with(".tmp") || iteration.is_none_or(|i| i > up_to) {
                continue;
            }
            let bytes = std::fs::read(entry.path()).map_err(io(&entry.path()))?;
            let to = self.checkpoints.join(&name);
            write_atomically(&to, &bytes).map_err(io(&to))?;
        }
        Ok(())
    }

    /// Where `warm_start.keep_best_round` keeps round `round`'s student.
    pub fn warm_start_round_blob(&self, round: u32) -> PathBuf {
        self.checkpoints
            .join(format!("warm_start_round_{round:03}.blob"))
    }

    /// `config.toml`: the configuration the run uses.
    pub fn write_config(&self, config: &TrainConfig) -> Result<(), TrainError> {
        let text =
            toml::to_string(config).map_err(|e| TrainError::Export(format!("config.toml: {e}")))?;
        let p = self.file("config.toml");
        write_atomically(&p, text.as_bytes()).map_err(io(&p))
    }

    /// `metrics.jsonl` as a run starting from `history` (up to iteration `last`) finds it:
    /// where the file exists (a resume) it is cut back to the lines of iterations up to
    /// `last` (later lines belong to the interval the checkpoint lost, which the run
    /// redoes); else it is created holding `history` (a fresh run's nothing, or the lines a
    /// fork inherits). The file is only ever appended to or cut at a line's end, never
    /// rewritten: the lines kept are the bytes first written.
    pub fn start_metrics(&self, history: &[IterationMetrics], last: u32) -> Result<(), TrainError> {
        let text = match std::fs::read_to_string(&self.metrics) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let mut text = String::new();
                for m in history {
                    text.push_str(&metrics_line(m)?);
                    text.push('\n');
                }
                return write_atomically(&self.metrics, text.as_bytes()).map_err(io(&self.metrics));
            }
            Err(e) => return Err(TrainError::Io(self.metrics.clone(), e)),
        };
        let (_, keep) = kept_metrics(&text, last)
            .map_err(|e| TrainError::Checkpoint(format!("{} {e}", self.metrics.display())))?;
        let f = std::fs::OpenOptions::new()
            .create(true)
            .write(true)
            .truncate(false)
            .open(&self.metrics)
            .map_err(io(&self.metrics))?;
        f.set_len(keep as u64).map_err(io(&self.metrics))?;
        f.sync_all().map_err(io(&self.metrics))
    }

    /// One more line of `metrics.jsonl`.
    pub fn append_metrics(&self, m: &IterationMetrics) -> Result<(), TrainError> {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.metrics)
            .map_err(io(&self.metrics))?;
        writeln!(f, "{}", metrics_line(m)?).map_err(io(&self.metrics))
    }

    /// `learning_curves.svg` of `history`.
    pub fn write_curves(&self, name: &str, history: &[IterationMetrics]) -> Result<(), TrainError> {
        let p = self.file("learning_curves.svg");
        write_atomically(&p, learning_curves(name, history).as_bytes()).map_err(io(&p))
    }

    /// The metrics of the run up to iteration `last` (a resume: later lines belong to the
    /// interval the checkpoint lost). A missing file is an empty history; a line that does
    /// not parse is an error unless it is the last one (a write cut short by a kill).
    fn read_metrics(&self, last: u32) -> Result<Vec<IterationMetrics>, TrainError> {
        let text = match std::fs::read_to_string(&self.metrics) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(TrainError::Io(self.metrics.clone(), e)),
        };
        kept_metrics(&text, last)
            .map(|(history, _)| history)
            .map_err(|e| TrainError::Checkpoint(format!("{} {e}", self.metrics.display())))
    }

    /// Writes `checkpoints/iter_N/` for `s` and then points `checkpoints/latest` at it;
    /// keeps the newest two checkpoints.
    pub fn save_checkpoint<A: PolicyNet, C: ValueNet>(
        &self,
        s: &RunState<A, C>,
        config: &TrainConfig,
    ) -> Result<(), TrainError> {
        self.save_checkpoint_with_loop(s, config, None)
    }

    /// [`Self::save_checkpoint`] with the rollout's world (`loop.json`), so that a resume
    /// from it is bit for bit.
    pub fn save_checkpoint_with_loop<A: PolicyNet, C: ValueNet>(
        &self,
        s: &RunState<A, C>,
        config: &TrainConfig,
        world: Option<&LoopSnapshot>,
    ) -> Result<(), TrainError> {
        let name = format!("iter_{:06}", s.iteration);
        let dir = self.checkpoints.join(&name);
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(io(&dir))?;
        }
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let ck = |e: burn::store::RecordError| TrainError::Checkpoint(format!("{name}: {e:?}"));
        s.learner
            .actor
            .clone()
            .save_file(dir.join(CHECKPOINT_FILES[0]))
            .map_err(ck)?;
        s.learner
            .critic
            .clone()
            .save_file(dir.join(CHECKPOINT_FILES[1]))
            .map_err(ck)?;
        s.learner
            .actor_optim
            .save(dir.join(CHECKPOINT_FILES[2]))
            .map_err(ck)?;
        s.learner
            .critic_optim
            .save(dir.join(CHECKPOINT_FILES[3]))
            .map_err(ck)?;
        if let Some(optim) = &s.learner.fused_optim {
            let bytes = optim
                .to_safetensors()
                .map_err(|e| TrainError::Checkpoint(format!("{name}/{FUSED_ADAM}: {e}")))?;
            let p = dir.join(FUSED_ADAM);
            write_atomically(&p, &bytes).map_err(io(&p))?;
        }
        if let Some(world) = world {
            let json = serde_json::to_vec(world)
                .map_err(|e| TrainError::Checkpoint(format!("{name}/{LOOP_FILE}: {e}")))?;
            let p = dir.join(LOOP_FILE);
            write_atomically(&p, &json).map_err(io(&p))?;
        }
        // The files' checksums, read back from the disk (what a resume will read).
        let mut files = std::collections::BTreeMap::new();
        for f in CHECKPOINT_FILES.iter().chain([&FUSED_ADAM, &LOOP_FILE]) {
            let p = dir.join(f);
            if p.exists() {
                let bytes = std::fs::read(&p).map_err(io(&p))?;
                files.insert(f.to_string(), sitl::files::sha256_hex(&bytes));
            }
        }
        let state = CheckpointState {
            format: CHECKPOINT_FORMAT,
            files,
            iteration: s.iteration,
            samples: s.samples,
            wall_s: s.wall_s,
            learning_rate: s.learner.learning_rate,
            config_hash: format!("{:016x}", config.hash()),
            noise_rng: rng_state(&s.noise_rng),
            shuffle_rng: rng_state(&s.shuffle_rng),
        };
        let json = serde_json::to_string_pretty(&state)
            .map_err(|e| TrainError::Checkpoint(format!("{name}/state.json: {e}")))?;
        write_atomically(&dir.join("state.json"), json.as_bytes()).map_err(io(&dir))?;
        // The burnpack files are written by burn without fsync: sync the directory's files
        // before the pointer names it.
        for f in CHECKPOINT_FILES {
            let p = dir.join(f);
            std::fs::File::open(&p)
                .and_then(|h| h.sync_all())
                .map_err(io(&p))?;
        }
        write_atomically(&self.latest, name.as_bytes()).map_err(io(&self.latest))?;
        // Keep the newest two checkpoints.
        let entries = std::fs::read_dir(&self.checkpoints).map_err(io(&self.checkpoints))?;
        let mut dirs: Vec<String> = entries
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("iter_") && !n.ends_with(".tmp"))
            .collect();
        dirs.sort();
        let keep = dirs.len().saturating_sub(2);
        for old in &dirs[..keep] {
            let p = self.checkpoints.join(old);
            std::fs::remove_dir_all(&p).map_err(io(&p))?;
        }
        Ok(())
    }

    /// The run state of the checkpoint `checkpoints/latest` names, refused when it was
    /// written under another config (unless only `run.iterations` changed).
    pub fn load_checkpoint<A: PolicyNet, C: ValueNet>(
        &self,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
    ) -> Result<RunState<A, C>, TrainError> {
        Ok(self.load_latest(config, arch, device, false)?.0)
    }

    /// A fork: the run state of this directory's latest checkpoint, to be trained on under
    /// `config`, which may differ from the config the checkpoint was written under in
    /// anything but the networks' shapes (a later stage of a curriculum, or a probe of one
    /// setting from a trained state). Everything [`Self::load_checkpoint`] restores is
    /// restored, metrics and iteration count included, so the fork's curves and schedules
    /// continue the parent's. Returns the state and the parent's config hash.
    pub fn fork<A: PolicyNet, C: ValueNet>(
        &self,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
    ) -> Result<(RunState<A, C>, String), TrainError> {
        self.load_latest(config, arch, device, true)
    }

    /// The latest checkpoint's run state and the hash of the config it was written under
    /// (read from the one `state.json`, so a parent still writing checkpoints cannot pair
    /// one checkpoint with the next one's hash). A checkpoint that is corrupt (a checksum
    /// that does not match, a file that does not load, non-finite weights or moments,
    /// implausible counters) is reported and the previous one still on disk is used, said
    /// loudly; a checkpoint of another config is refused, not skipped.
    fn load_latest<A: PolicyNet, C: ValueNet>(
        &self,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
        any_config: bool,
    ) -> Result<(RunState<A, C>, String), TrainError> {
        let name = std::fs::read_to_string(&self.latest).map_err(|_| {
            TrainError::OutDir(format!(
                "nothing to resume (no checkpoint): {} does not exist",
                self.latest.display()
            ))
        })?;
        let latest = name.trim().to_string();
        // The latest first, then the older ones still on disk, newest first.
        let mut names: Vec<String> = std::fs::read_dir(&self.checkpoints)
            .map_err(io(&self.checkpoints))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("iter_") && !n.ends_with(".tmp") && *n < latest)
            .collect();
        names.sort_by(|a, b| b.cmp(a));
        names.insert(0, latest);
        let mut first_failure = None;
        for name in &names {
            match self.load_dir(name, config, arch, device, any_config) {
                Ok(loaded) => {
                    if let Some(e) = &first_failure {
                        eprintln!(
                            "WARNING: the latest checkpoint is unusable ({e}); resuming from the previous one, {name}: the iterations after it are redone"
                        );
                    }
                    return Ok(loaded);
                }
                Err(Unusable::Refused(e)) => return Err(e),
                Err(Unusable::Corrupt(e)) => {
                    eprintln!("checkpoint {name} is corrupt: {e}");
                    first_failure.get_or_insert(e);
                }
            }
        }
        Err(first_failure.unwrap_or_else(|| TrainError::Checkpoint("no checkpoint".into())))
    }

    /// The run state of checkpoint `checkpoints/<name>` (see [`Self::load_latest`]).
    fn load_dir<A: PolicyNet, C: ValueNet>(
        &self,
        name: &str,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
        any_config: bool,
    ) -> Result<(RunState<A, C>, String), Unusable> {
        let dir = self.checkpoints.join(name);
        let bad = |m: String| corrupt(&dir, m);
        let state = self.verified_state(&dir, config, any_config)?;
        let learner = load_learner::<A, C>(&dir, &state, config, arch, device)?;
        let seed = config.run.seed;
        let noise_rng =
            restore_rng(seed, &state.noise_rng).ok_or_else(|| bad("noise_rng".into()))?;
        let shuffle_rng =
            restore_rng(seed, &state.shuffle_rng).ok_or_else(|| bad("shuffle_rng".into()))?;
        let history = self
            .read_metrics(state.iteration)
            .map_err(Unusable::Refused)?;
        let loop_file = dir.join(LOOP_FILE);
        // A fork continues the parent's flights only under the parent's environment; under
        // another it starts its envs afresh, as every fork did before `loop.json`.
        let same_world = !any_config
            || TrainConfig::load(&self.file("config.toml")).is_ok_and(|c| c.env == config.env);
        let resumed_loop = if loop_file.exists() && same_world {
            let text = std::fs::read(&loop_file).map_err(|e| bad(format!("{LOOP_FILE}: {e}")))?;
            Some(
                serde_json::from_slice::<LoopSnapshot>(&text)
                    .map_err(|e| bad(format!("{LOOP_FILE}: {e}")))?,
            )
        } else {
            None
        };
        let run_state = RunState {
            learner,
            iteration: state.iteration,
            samples: state.samples,
            wall_s: state.wall_s,
            noise_rng,
            shuffle_rng,
            history,
            resumed_loop,
        };
        Ok((run_state, state.config_hash))
    }

    /// `state.json` of the checkpoint in `dir`, checked: written under this config (or one
    /// that differs only in its budget, or any with `any_config`), of a format this build
    /// reads, every file matching its checksum, and its counters plausible.
    fn verified_state(
        &self,
        dir: &Path,
        config: &TrainConfig,
        any_config: bool,
    ) -> Result<CheckpointState, Unusable> {
        let bad = |m: String| corrupt(dir, m);
        let text = std::fs::read_to_string(dir.join("state.json"))
            .map_err(|e| bad(format!("state.json: {e}")))?;
        let state: CheckpointState =
            serde_json::from_str(&text).map_err(|e| bad(format!("state.json: {e}")))?;
        let hash = format!("{:016x}", config.hash());
        if state.config_hash != hash && !any_config {
            // A changed budget is allowed: the run's own config.toml (when it is the one the
            // checkpoint was written under) tells whether that is all that changed.
            let earlier = TrainConfig::load(&self.file("config.toml"))
                .ok()
                .filter(|c| format!("{:016x}", c.hash()) == state.config_hash);
            match earlier {
                Some(c) if config.only_budget_differs_from(&c) => eprintln!(
                    "note: the run's budget changes from {} to {} iterations (nothing else may)",
                    c.run.iterations, config.run.iterations
                ),
                _ => {
                    return Err(Unusable::Refused(TrainError::Checkpoint(format!(
                        "{}: written by a run with config hash {}, this config hashes to {hash}; resume with the run's own config.toml (only run.iterations may change)",
                        dir.display(),
                        state.config_hash
                    ))));
                }
            }
        }
        if state.format > CHECKPOINT_FORMAT {
            return Err(Unusable::Refused(TrainError::Checkpoint(format!(
                "{}: checkpoint format {} is newer than this build's {CHECKPOINT_FORMAT}",
                dir.display(),
                state.format
            ))));
        }
        if state.format >= 1 {
            for f in CHECKPOINT_FILES {
                if !state.files.contains_key(f) {
                    return Err(bad(format!("state.json has no checksum of {f}")));
                }
            }
            for (f, want) in &state.files {
                let p = dir.join(f);
                let bytes = std::fs::read(&p).map_err(|e| bad(format!("{f}: {e}")))?;
                if sitl::files::sha256_hex(&bytes) != *want {
                    return Err(bad(format!("{f} does not match its checksum")));
                }
            }
        } else {
            eprintln!(
                "note: {} predates checkpoint checksums (format 0): its files are not verified",
                dir.display()
            );
        }
        // A fork's parent may have had other batches; a resume's samples are its iterations'.
        let samples_fit = any_config
            || state.samples == u64::from(state.iteration) * config.samples_per_iteration() as u64;
        let plausible = state.learning_rate.is_finite()
            && state.learning_rate > 0.0
            && state.wall_s.is_finite()
            && state.wall_s >= 0.0
            && (any_config || state.iteration <= config.run.iterations)
            && samples_fit;
        if !plausible {
            return Err(bad(format!(
                "state.json is implausible (iteration {}, samples {}, learning rate {}, wall-clock {} s)",
                state.iteration, state.samples, state.learning_rate, state.wall_s
            )));
        }
        Ok(state)
    }
}

/// A checkpoint that cannot be used as it is (the caller falls back to an earlier one).
fn corrupt(dir: &Path, message: String) -> Unusable {
    Unusable::Corrupt(TrainError::Checkpoint(format!(
        "{}: {message}",
        dir.display()
    )))
}

/// The learner of the checkpoint in `dir`: networks, Adam states (burn's and the fused
/// update's), the learning rate; non-finite weights or moments are refused.
fn load_learner<A: PolicyNet, C: ValueNet>(
    dir: &Path,
    state: &CheckpointState,
    config: &TrainConfig,
    arch: &Architecture,
    device: &Device,
) -> Result<Learner<A, C>, Unusable> {
    let bad = |m: String| corrupt(dir, m);
    let mut rng = init_rng(config.run.seed);
    let actor = A::fresh(arch, config.ppo.init_std, &mut rng, device)
        .try_load_file(dir.join(CHECKPOINT_FILES[0]))
        .map_err(|e| bad(format!("actor.bpk: {e:?}")))?;
    let critic = C::fresh(arch, &mut rng, device)
        .try_load_file(dir.join(CHECKPOINT_FILES[1]))
        .map_err(|e| bad(format!("critic.bpk: {e:?}")))?;
    if !all_finite(&actor) || !all_finite(&critic) {
        return Err(bad("non-finite weights".into()));
    }
    let actor_optim = adam()
        .load(dir.join(CHECKPOINT_FILES[2]))
        .map_err(|e| bad(format!("actor_optim.bpk: {e:?}")))?;
    let critic_optim = adam()
        .load(dir.join(CHECKPOINT_FILES[3]))
        .map_err(|e| bad(format!("critic_optim.bpk: {e:?}")))?;
    let mut learner = Learner::new(actor, critic, state.learning_rate, device.clone());
    learner.actor_optim = actor_optim;
    learner.critic_optim = critic_optim;
    let fused = dir.join(FUSED_ADAM);
    if !fused.exists()
        && state.iteration > 0
        && config.ppo.update.resolve(arch.is_recurrent()) == crate::config::UpdateKind::Fused
    {
        eprintln!(
            "note: {} has no {FUSED_ADAM} (written by the burn update): the fused update starts Adam afresh",
            dir.display()
        );
    }
    if fused.exists() {
        let bytes = std::fs::read(&fused).map_err(|e| bad(format!("{FUSED_ADAM}: {e}")))?;
        let optim =
            FusedOptim::from_safetensors(&bytes).map_err(|e| bad(format!("{FUSED_ADAM}: {e}")))?;
        let finite = [&optim.actor, &optim.critic]
            .iter()
            .all(|m| m.moment_1.iter().chain(&m.moment_2).all(|v| v.is_finite()));
        if !finite {
            return Err(bad(format!("{FUSED_ADAM}: non-finite moments")));
        }
        learner.fused_optim = Some(optim);
    }
    Ok(learner)
}

/// The lines of `metrics.jsonl` that a run resumed at iteration `last` keeps, and their
/// length in bytes: the complete (newline-terminated) lines of iterations up to `last`, in
/// order, up to the first that is not. A line that does not parse is a torn write when it is
/// the last one (dropped) and an error (`line N: why`) anywhere else. One rule for the
/// history a resume restores and for where the file is cut, so the two always agree.
fn kept_metrics(text: &str, last: u32) -> Result<(Vec<IterationMetrics>, usize), String> {
    let lines: Vec<&str> = text.split_inclusive('\n').collect();
    let mut history = Vec::new();
    let mut keep = 0;
    for (i, line) in lines.iter().enumerate() {
        match serde_json::from_str::<IterationMetrics>(line) {
            Ok(m) if line.ends_with('\n') && m.iteration <= last => {
                keep += line.len();
                history.push(m);
            }
            // Past the checkpoint (the lost interval the run redoes), or torn before its
            // newline.
            Ok(_) => break,
            Err(_) if i + 1 == lines.len() => break,
            Err(e) => return Err(format!("line {}: {e}", i + 1)),
        }
    }
    Ok((history, keep))
}

/// Why a checkpoint cannot be resumed from.
enum Unusable {
    /// Damaged: the previous checkpoint may be used instead.
    Corrupt(TrainError),
    /// Not this run's (another config, a newer format): nothing else is tried.
    Refused(TrainError),
}

/// Every float parameter of `module` is finite.
fn all_finite<M: burn::module::Module>(module: &M) -> bool {
    struct Finite(bool);
    impl burn::module::ModuleVisitor for Finite {
        fn visit_float<const D: usize>(
            &mut self,
            param: &burn::module::Param<burn::tensor::Tensor<D>>,
        ) {
            self.0 &= crate::model::values(param.val())
                .iter()
                .all(|v| v.is_finite());
        }
    }
    let mut v = Finite(true);
    module.visit(&mut v);
    v.0
}

/// One line of `metrics.jsonl`.
fn metrics_line(m: &IterationMetrics) -> Result<String, TrainError> {
    serde_json::to_string(m).map_err(|e| TrainError::Export(format!("metrics.jsonl: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(iteration: u32) -> String {
        let m = IterationMetrics {
            iteration,
            samples: u64::from(iteration) * 100,
            ..IterationMetrics::default()
        };
        metrics_line(&m).unwrap() + "\n"
    }

    #[test]
    fn resume_keeps_complete_lines_up_to_the_checkpoint_and_cuts_there() {
        let three = format!("{}{}{}", line(1), line(2), line(3));
        // Lines past the checkpoint are the lost interval: history and cut stop before them.
        let (h, keep) = kept_metrics(&three, 2).unwrap();
        assert_eq!(h.iter().map(|m| m.iteration).collect::<Vec<_>>(), [1, 2]);
        assert_eq!(keep, line(1).len() + line(2).len());
        // A last line that parses but lost its newline is torn: neither kept nor counted, so
        // the history never holds a line the cut file lacks.
        let torn = format!("{}{}", line(1), line(2).trim_end());
        let (h, keep) = kept_metrics(&torn, 5).unwrap();
        assert_eq!((h.len(), keep), (1, line(1).len()));
        // A half-written last line is dropped; garbage before the end is an error naming it.
        let half = format!("{}{{\"iteration\": 2, \"sam", line(1));
        assert_eq!(kept_metrics(&half, 5).unwrap().0.len(), 1);
        let garbage = format!("{}not json\n{}", line(1), line(2));
        assert!(
            kept_metrics(&garbage, 5)
                .unwrap_err()
                .starts_with("line 2:")
        );
        assert_eq!(kept_metrics("", 5).unwrap(), (Vec::new(), 0));
    }
}
