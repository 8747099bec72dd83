//! The training run: the loop that starts or resumes a run, alternates rollouts
//! ([`crate::rollout`]) and PPO updates ([`crate::ppo`]), lets the referee evaluate the
//! policy, logs metrics and checkpoints ([`crate::run_dir`]), and exports the trained actor
//! ([`crate::export`]). [`run`] reads top to bottom: `start`, then `iteration` after
//! iteration, each followed by `evaluate` and the bookkeeping, then `finish`.

use crate::config::{CriticKind, PpoConfig, TrainConfig};
use crate::error::TrainError;
use crate::evaluation::{
    best_evaluation, keep_best_prefers, race_opponent, referee_eval, selection_eval,
};
use crate::export::{actor_blob, actor_from_blob, actor_safetensors, actor_transplanted_from};
use crate::guard::guard_update;
use crate::imitation::Imitate;
use crate::metrics::{Console, IterationMetrics, lap_text};
use crate::model::{Actor, Critic, PrivilegedCritic};
use crate::nets::{PolicyNet, ValueNet};
use crate::ppo::Learner;
use crate::recurrent::{RecurrentActor, RecurrentCritic};
use crate::rng::{generator, init_rng};
use crate::rollout::{EpisodeLog, Rollout, collect_rollout};
use crate::run_dir::{LoopSnapshot, RunDir, RunState};
use crate::warm_start::warm_start;
use burn::tensor::Device;
use firmware_core::policy::{Architecture, Policy};
use sitl::env::{EnvConfig, RaceConfig, VecEnv};
use sitl::files::write_atomically;
use std::path::PathBuf;
use std::time::Instant;

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
    /// Start a fresh run from the latest checkpoint of the run in this directory (networks,
    /// σ, Adam states, learning rate, iteration, samples, wall-clock, metrics) under this
    /// run's config, which may differ in anything but the networks: a fork. `forked_from.json`
    /// in `out` records the parent. Ignored on resume.
    pub fork_from: Option<PathBuf>,
}

/// `forked_from.json` in a forked run's directory: where its first state came from.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct ForkedFrom {
    /// The parent run's directory.
    pub run: String,
    /// The parent's iteration the fork starts from.
    pub iteration: u32,
    /// The parent's samples at that iteration.
    pub samples: u64,
    /// The hash of the config the parent's checkpoint was written under.
    pub config_hash: String,
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

/// Runs (or resumes) the training run of `config` into `options.out`: PPO on the
/// feed-forward networks of rows A-D, recurrent PPO on the LSTM networks of rows E-G.
pub fn run(config: &TrainConfig, options: &RunOptions) -> Result<RunSummary, TrainError> {
    let recurrent = config.architecture()?.is_recurrent();
    match (recurrent, config.ppo.critic) {
        (true, CriticKind::ActorShaped) => {
            run_networks::<RecurrentActor, RecurrentCritic>(config, options)
        }
        (true, CriticKind::PrivilegedMlp) => {
            run_networks::<RecurrentActor, PrivilegedCritic>(config, options)
        }
        (false, CriticKind::ActorShaped) => run_networks::<Actor, Critic>(config, options),
        (false, CriticKind::PrivilegedMlp) => {
            run_networks::<Actor, PrivilegedCritic>(config, options)
        }
    }
}

/// [`run`] for one pair of networks.
fn run_networks<A: Imitate, C: ValueNet>(
    config: &TrainConfig,
    options: &RunOptions,
) -> Result<RunSummary, TrainError> {
    let dir = RunDir::new(&options.out);
    refuse_unstartable(config)?;
    // Held from before the first write (a fresh run's directory, a fork's first checkpoint,
    // a resume's cut metrics) to the end.
    let _lock = dir.lock()?;
    let mut state = start::<A, C>(config, options, &dir)?;
    dir.write_config(config)?;
    dir.start_metrics(&state.history, state.iteration)?;
    let mut lp = Loop::new(config, &mut state)?;
    let total = config.run.iterations;
    let stop_at = options
        .stop_after
        .map_or(total, |k| (state.iteration + k).min(total));
    let console = Console::new(
        options.progress,
        u64::from(total),
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} it  {msg}",
    );
    console.bar().set_position(u64::from(state.iteration));
    let eval_every = config.run.eval_every.max(1);
    while state.iteration < stop_at {
        let mut m = iteration(&mut state, &mut lp, config)?;
        if state.iteration % eval_every == 0 || state.iteration == total {
            evaluate(&mut m, &state, config, &dir, &lp.arch, &console)?;
        }
        console.bar().set_position(u64::from(state.iteration));
        console.bar().set_message(format!(
            "{:.0} samples/s  reward/step {:+.4}  success {:.3}  σ {:.2}",
            m.samples_per_s, m.reward_per_step, m.success_rate, m.action_std
        ));
        let evaluated = m.eval_success_rate.is_some();
        dir.append_metrics(&m)?;
        state.history.push(m);
        if evaluated {
            // Curves to watch while the run goes on.
            dir.write_curves(&config.run.name, &state.history)?;
        }
        if state.iteration % config.run.checkpoint_every == 0 || state.iteration == stop_at {
            dir.save_checkpoint_with_loop(&state, config, Some(&lp.snapshot()))?;
        }
    }
    console.bar().finish_and_clear();
    finish(&state, config, &dir, &lp.arch)
}

/// Refuses, before anything is allocated or written, a run that cannot fit in memory or whose
/// opponents (the curriculum's included) cannot be read.
fn refuse_unstartable(config: &TrainConfig) -> Result<(), TrainError> {
    crate::memory::check(config, &config.architecture()?)?;
    // Refuse an unreadable opponent, the curriculum's included, before any work.
    VecEnv::new(EnvConfig {
        num_envs: 1,
        ..config.env_config(0)
    })?;
    for stage in &config.opponent_curriculum {
        VecEnv::new(EnvConfig {
            num_envs: 1,
            race: config.race_at(stage.until_iteration - 1),
            ..config.env_config(0)
        })?;
    }
    Ok(())
}

/// The run state to train from: the latest checkpoint (`--resume`), or a fresh one (refused
/// where `out` holds a run) initialised from the seed, then from `--init-actor` or by the
/// warm start.
fn start<A: Imitate, C: ValueNet>(
    config: &TrainConfig,
    options: &RunOptions,
    dir: &RunDir,
) -> Result<RunState<A, C>, TrainError> {
    let arch = config.architecture()?;
    let device = options.device.clone();
    if options.resume {
        return dir.load_checkpoint(config, &arch, &device);
    }
    if dir.holds_run() {
        return Err(TrainError::OutDir(format!(
            "{} already holds a run (checkpoints/latest); pass --resume to continue it or choose another --out",
            dir.out.display()
        )));
    }
    dir.create()?;
    if let Some(parent) = &options.fork_from {
        if options.init_actor.is_some() {
            return Err(TrainError::OutDir(
                "--fork-from and --init-actor both say where the actor starts; pass one".into(),
            ));
        }
        let parent_dir = RunDir::new(parent);
        let (state, config_hash) = parent_dir.fork::<A, C>(config, &arch, &device)?;
        dir.adopt_best_candidates(&parent_dir, state.iteration)?;
        let record = ForkedFrom {
            run: parent.display().to_string(),
            iteration: state.iteration,
            samples: state.samples,
            config_hash,
        };
        let json = serde_json::to_string_pretty(&record)
            .map_err(|e| TrainError::Export(format!("forked_from.json: {e}")))?;
        let p = dir.file("forked_from.json");
        write_atomically(&p, json.as_bytes()).map_err(crate::error::io(&p))?;
        println!(
            "forked from {} at iteration {} ({} samples)",
            parent.display(),
            record.iteration,
            record.samples
        );
        dir.save_checkpoint(&state, config)?;
        return Ok(state);
    }
    let mut rng = init_rng(config.run.seed);
    let mut actor = A::fresh(&arch, config.ppo.init_std, &mut rng, &device);
    let critic = C::fresh(&arch, &mut rng, &device);
    if config.ppo.init_hover {
        actor = actor.with_output_bias(config.hover_action());
    }
    let mut state = RunState {
        learner: Learner::new(actor, critic, config.ppo.learning_rate, device.clone()),
        iteration: 0,
        samples: 0,
        wall_s: 0.0,
        noise_rng: generator(config.run.seed, u64::MAX - 1),
        shuffle_rng: generator(config.run.seed, u64::MAX - 2),
        history: Vec::new(),
        resumed_loop: None,
    };
    if let Some(path) = &options.init_actor {
        let actor = actor_from_blob(path, &arch, config, &device)?;
        state.learner = Learner::new(
            actor,
            state.learner.critic.clone(),
            state.learner.learning_rate,
            device.clone(),
        );
        println!("actor initialised from {}", path.display());
        dir.create()?;
        dir.save_checkpoint(&state, config)?;
    } else if let Some(warm) = &config.warm_start {
        let student = match (&warm.student, &warm.teacher_blob) {
            (Some(path), _) => {
                println!("the warm start refines the student {path}");
                actor_from_blob(std::path::Path::new(path), &arch, config, &device)?
            }
            (None, Some(teacher)) if warm.transplant => {
                println!(
                    "the student is {teacher} transplanted into row {}'s network",
                    config.run.row
                );
                actor_transplanted_from(
                    std::path::Path::new(teacher),
                    &state.learner.actor,
                    &arch,
                    config,
                    &device,
                )?
            }
            _ => state.learner.actor.clone(),
        };
        warm_start(
            &mut state,
            student,
            config,
            warm,
            dir,
            &device,
            options.progress,
        )?;
    }
    Ok(state)
}

/// What the iterations of one invocation share: the environment (respawned from a seed
/// derived from the iteration it starts at), the rollout buffer and the episode log.
struct Loop {
    arch: Architecture,
    env: VecEnv,
    rollout: Rollout,
    episodes: EpisodeLog,
}

impl Loop {
    /// The loop of a fresh state: envs spawned from a seed derived from the iteration; of a
    /// resumed one: the world its checkpoint kept ([`LoopSnapshot`]), bit for bit.
    fn new<A: PolicyNet, C>(
        config: &TrainConfig,
        state: &mut RunState<A, C>,
    ) -> Result<Self, TrainError> {
        let env_seed = config
            .run
            .seed
            .wrapping_add(u64::from(state.iteration).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        // The opponent of the curriculum's stage the loop starts in.
        let mut env = VecEnv::new(EnvConfig {
            race: config.race_at(state.iteration),
            randomize_share: config.randomize_share_at(state.iteration),
            ..config.env_config(env_seed)
        })?;
        let mut rollout = Rollout::new(env.num_envs(), env.obs_dim());
        if config.ppo.critic == CriticKind::PrivilegedMlp {
            rollout.privileged_dim = env.privileged_dim();
        }
        let mut episodes = EpisodeLog::new(env.num_envs());
        let arch = config.architecture()?;
        match state.resumed_loop.take() {
            Some(world) => {
                let bad = |why: String| {
                    TrainError::Checkpoint(format!("loop.json does not fit this run: {why}"))
                };
                env.restore(&world.env).map_err(|e| bad(e.to_string()))?;
                let policy_payload = state.learner.actor.payload();
                let policy = Policy::from_payload(&arch, &policy_payload)
                    .map_err(|e| bad(format!("the actor: {e}")))?;
                let width = policy.initial_state().flat_len();
                let n = env.num_envs();
                if world.policy_memory.len() != n * width {
                    return Err(bad(format!(
                        "{} recurrent values, {n} envs of {width} expected",
                        world.policy_memory.len()
                    )));
                }
                rollout.memory = vec![policy.initial_state(); n];
                if width > 0 {
                    for (m, v) in rollout
                        .memory
                        .iter_mut()
                        .zip(world.policy_memory.chunks_exact(width))
                    {
                        m.read_flat(v);
                    }
                }
                rollout.critic_h0 = world.critic_h0;
                episodes = world.episodes;
            }
            None if state.iteration > 0 => println!(
                "note: the envs are respawned at iteration {} (the checkpoint keeps no env state, loop.json, or a fork changed [env]): the run is not bit for bit the uninterrupted one from there",
                state.iteration
            ),
            None => {}
        }
        Ok(Self {
            arch,
            rollout,
            episodes,
            env,
        })
    }

    /// The next stage of an opponent curriculum from `iteration` on: every env respawned
    /// against `race`'s opponent, and the recurrent states and the open episodes' returns
    /// started afresh with them (the same whether the run goes on or resumes here).
    fn change_opponent(&mut self, race: RaceConfig, iteration: u32) -> Result<(), TrainError> {
        println!(
            "iteration {iteration}: the training races fly against {} from now on",
            race.opponent.display()
        );
        self.env.set_race(race)?;
        self.rollout.memory.clear();
        self.rollout.critic_h0.clear();
        self.episodes = EpisodeLog::new(self.env.num_envs());
        Ok(())
    }

    /// The rollout's world now, for a checkpoint.
    fn snapshot(&self) -> LoopSnapshot {
        let width = self.rollout.memory.first().map_or(0, |m| m.flat_len());
        let mut policy_memory = vec![0.0; width * self.rollout.memory.len()];
        if width > 0 {
            for (m, out) in self
                .rollout
                .memory
                .iter()
                .zip(policy_memory.chunks_exact_mut(width))
            {
                m.write_flat(out);
            }
        }
        LoopSnapshot {
            env: self.env.snapshot(),
            policy_memory,
            critic_h0: self.rollout.critic_h0.clone(),
            episodes: self.episodes.clone(),
        }
    }
}

/// One PPO iteration: a rollout with the deployed network, the update, the guard (`[guard]`);
/// returns its metrics, not yet evaluated by the referee.
fn iteration<A: PolicyNet, C: ValueNet>(
    state: &mut RunState<A, C>,
    lp: &mut Loop,
    config: &TrainConfig,
) -> Result<IterationMetrics, TrainError> {
    let started = Instant::now();
    let params = &PpoConfig {
        max_std: config.ppo.max_std_at(state.iteration),
        ..config.ppo.clone()
    };
    state.learner.train_actor = config
        .warm_start
        .as_ref()
        .is_none_or(|w| state.iteration >= w.critic_iterations);
    lp.env.set_reward_weights(config.reward_at(state.iteration));
    lp.env
        .set_randomize_share(config.randomize_share_at(state.iteration))?;
    if state.iteration > 0 {
        let race = config.race_at(state.iteration);
        if race != config.race_at(state.iteration - 1)
            && let Some(race) = race
        {
            lp.change_opponent(race, state.iteration)?;
        }
    }
    // Rollout with the deployed network.
    let payload = state.learner.actor.payload();
    let std = state.learner.actor.std();
    let policy = Policy::from_payload(&lp.arch, &payload)
        .map_err(|e| TrainError::Export(format!("actor does not load as a blob: {e}")))?;
    let episodes = &mut lp.episodes;
    collect_rollout(
        &mut lp.env,
        &policy,
        &std,
        params.steps_per_env,
        &mut state.noise_rng,
        &mut lp.rollout,
        |rewards, dones| episodes.record(rewards, dones),
    )?;
    let env_stats = lp.env.take_stats();
    let rollout_s = started.elapsed().as_secs_f64();

    // Update.
    let t_update = Instant::now();
    let batch = state.learner.prepare(&lp.rollout, params);
    if let Some(seq) = &batch.sequence {
        // The critic's state for the next window (the actor's lives in the rollout).
        lp.rollout.critic_h0.clone_from(&seq.critic_next);
    }
    let update = state.learner.update(&batch, params, &mut state.shuffle_rng);
    let guarded = match (&config.guard, state.learner.train_actor) {
        (Some(g), true) => Some(guard_update(
            &mut state.learner,
            (&payload, &std),
            &lp.arch,
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
    let batch_samples = (lp.env.num_envs() * params.steps_per_env) as u64;
    state.samples += batch_samples;
    let iter_s = started.elapsed().as_secs_f64();
    state.wall_s += iter_s;
    let dt = f64::from(lp.env.dt_s());
    let per_step = |v: f64| v / env_stats.steps.max(1) as f64;
    let sim_s = env_stats.steps as f64 * dt;
    let std_now = state.learner.actor.std();
    let race = config.env.race.is_some();
    Ok(IterationMetrics {
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
        reward_competition: race.then(|| per_step(env_stats.terms.competition)),
        opponent_crash_rate_per_s: race
            .then(|| env_stats.opponent_crashes as f64 / sim_s.max(1e-9)),
        episode_return: lp.episodes.mean_return(),
        episode_s: lp.episodes.mean_length_s(dt),
        success_rate: env_stats.success_rate(),
        crash_rate_per_s: env_stats.crashes as f64 / sim_s.max(1e-9),
        gates_per_s: env_stats.gates_passed as f64 / sim_s.max(1e-9),
        update,
        action_std: std_now.iter().map(|&s| f64::from(s)).sum::<f64>()
            / std_now.len().max(1) as f64,
        guard_step: guarded.map(|g| g.0),
        guard_reward_before: guarded.map(|g| g.1),
        guard_reward_after: guarded.map(|g| g.2),
        ..IterationMetrics::default()
    })
}

/// The referee's evaluation of the current actor into `m`; with `run.keep_best` a new best
/// actor is kept as a candidate for export (written before the metrics line that makes it
/// the best, so a resume from any later checkpoint finds it).
fn evaluate<A: PolicyNet, C: ValueNet>(
    m: &mut IterationMetrics,
    state: &RunState<A, C>,
    config: &TrainConfig,
    dir: &RunDir,
    arch: &Architecture,
    console: &Console,
) -> Result<(), TrainError> {
    let blob = actor_blob(&state.learner.actor, config, state.iteration)?;
    if let Some(r) = referee_eval(&blob, config.preset(), config) {
        m.eval_success_rate = Some(r.success_rate);
        m.eval_crash_rate = Some(r.crash_rate);
        m.eval_best_lap_s = r.best_lap_s;
        m.eval_gates = Some(r.gates_passed);
        if config.env.race.is_some() {
            m.eval_overtakes = Some(r.overtakes);
            m.eval_sustained_overtakes = Some(r.sustained_overtakes);
            m.eval_win_rate = r.win_rate;
            m.eval_overtakes_by_gate = r.overtakes_by_gate;
        }
    }
    if let Some(select) = &config.run.select
        && state.iteration >= select.from_iteration
        && let Some(opponent) = race_opponent(config.preset(), config)
        && let Some(r) = selection_eval(&blob, config.preset(), select, opponent.as_ref())
    {
        m.select_success_rate = Some(r.success_rate);
        m.select_crash_rate = Some(r.crash_rate);
        m.select_mean_lap_s = r.mean_lap_s;
    }
    if config.run.keep_best
        && keep_best_prefers(m, best_evaluation(&state.history, &config.run), &config.run)
    {
        dir.create()?;
        let p = dir.best_candidate(state.iteration, "blob");
        write_atomically(&p, &blob).map_err(crate::error::io(&p))?;
        let p = dir.best_candidate(state.iteration, "safetensors");
        write_atomically(&p, &actor_safetensors(&state.learner.actor, arch)?)
            .map_err(crate::error::io(&p))?;
    }
    let lap = lap_text(m.eval_best_lap_s);
    let validation = match m.select_success_rate {
        Some(sr) => format!(
            "  validation: success {sr:.3}, crashes {:.3}/s, mean lap {}",
            m.select_crash_rate.unwrap_or(0.0),
            lap_text(m.select_mean_lap_s)
        ),
        None => String::new(),
    };
    console.say(format!(
        "it {:>5}  {:>6.0} s  {:>7.0} samples/s  reward/step {:+.4}  rollout success {:.3}  referee: success {:.3}, crashes {:.3}/s, best lap {lap}{validation}",
        m.iteration,
        m.wall_s,
        m.samples_per_s,
        m.reward_per_step,
        m.success_rate,
        m.eval_success_rate.unwrap_or(0.0),
        m.eval_crash_rate.unwrap_or(0.0),
    ));
    Ok(())
}

/// The end of an invocation: the curves, and when the run reached its budget the exported
/// actor (the last, or with `run.keep_best` the referee's best) as `<name>.blob` and
/// `<name>.safetensors`.
fn finish<A: PolicyNet, C: ValueNet>(
    state: &RunState<A, C>,
    config: &TrainConfig,
    dir: &RunDir,
    arch: &Architecture,
) -> Result<RunSummary, TrainError> {
    dir.write_curves(&config.run.name, &state.history)?;
    let best = if config.run.keep_best {
        best_evaluation(&state.history, &config.run).cloned()
    } else {
        None
    };
    let mut blob_path = None;
    if state.iteration >= config.run.iterations {
        let (blob, st) = match &best {
            Some(b) => {
                let read = |ext| {
                    let p = dir.best_candidate(b.iteration, ext);
                    std::fs::read(&p).map_err(crate::error::io(&p))
                };
                (read("blob")?, read("safetensors")?)
            }
            None => (
                actor_blob(&state.learner.actor, config, state.iteration)?,
                actor_safetensors(&state.learner.actor, arch)?,
            ),
        };
        let p = dir.file(&format!("{}.blob", config.run.name));
        write_atomically(&p, &blob).map_err(crate::error::io(&p))?;
        let sp = dir.file(&format!("{}.safetensors", config.run.name));
        write_atomically(&sp, &st).map_err(crate::error::io(&sp))?;
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
