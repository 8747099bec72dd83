//! The imitation warm start (DAgger, Ross et al. 2011): before PPO, the actor's mean is
//! regressed onto a teacher's actions (the classical baseline's, or a time-trial blob's:
//! stage 2 imitates the stage-1 policy) on the states that a mixture of the
//! baseline and the student visits. Round `k` executes the teacher's action with
//! probability β_k (1 → 0 over the first half of the rounds) and the student's noisy action
//! otherwise; every visited state is labelled with the teacher's action, and the data of all
//! rounds (up to `max_samples`) is fitted by mean squared error. Both students, the
//! feed-forward one ([`imitate`]) and the recurrent one ([`imitate_recurrent`]), fly their
//! rounds through one collector (`collect_round`); they differ in how they fit.
//!
//! Why: with the paper's reward (docs/DESIGN.md "Rewards") at this machine's budget, PPO from a random actor learns to hover
//! and then stays there (docs/journal/stage1.md has the runs). A student that already flies the
//! track sees the progress reward from its first PPO iteration.

mod recurrent;

use crate::config::{TrainConfig, WarmStart};
use crate::error::TrainError;
use crate::model::{Actor, values};
use crate::nets::PolicyNet;
use crate::ppo::adam;
use crate::recurrent::RecurrentActor;
use crate::rng::normal;
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::baseline::BaselineController;
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::Observation;
use firmware_core::policy::{Architecture, Policy};
use firmware_core::track::Track;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use recurrent::RecurrentFit;
use serde::{Deserialize, Serialize};
use sitl::env::{EnvStats, VecEnv};

/// One DAgger round, a line of `imitation.jsonl`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct ImitationRound {
    /// Round (1-based).
    pub round: u32,
    /// Share of executed actions that were the teacher's.
    pub teacher_share: f64,
    /// Samples in the regression set.
    pub samples: usize,
    /// Mean squared error of the student's mean against the labels, last epoch.
    pub mse: f64,
    /// The same in the round's first epoch (recurrent warm start; 0 where not recorded).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub mse_first_epoch: f64,
    /// Gates passed per simulated second by the executed mixture.
    pub gates_per_s: f64,
    /// Crashes per simulated second by the executed mixture.
    pub crash_rate_per_s: f64,
    /// The referee's success rate of the round's student (`warm_start.keep_best_round`:
    /// `run.eval_races` races on `run.eval_seed`); absent where not refereed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub referee_success_rate: Option<f64>,
    /// The referee's crashes per second of the round's student, likewise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub referee_crash_rate: Option<f64>,
}

/// An actor the warm start can train: the feed-forward one by [`imitate`], the recurrent
/// one by [`imitate_recurrent`].
pub trait Imitate: PolicyNet {
    /// Runs the warm start on `self` and returns the student with the rounds' statistics.
    fn imitate(
        self,
        arch: &Architecture,
        config: &TrainConfig,
        warm: &WarmStart,
        device: &Device,
        log: &mut dyn FnMut(&ImitationRound, &[f32]),
    ) -> Result<(Self, Vec<ImitationRound>), TrainError>;
}

impl Imitate for Actor {
    fn imitate(
        self,
        arch: &Architecture,
        config: &TrainConfig,
        warm: &WarmStart,
        device: &Device,
        log: &mut dyn FnMut(&ImitationRound, &[f32]),
    ) -> Result<(Self, Vec<ImitationRound>), TrainError> {
        imitate(self, arch, config, warm, device, log)
    }
}

impl Imitate for RecurrentActor {
    fn imitate(
        self,
        arch: &Architecture,
        config: &TrainConfig,
        warm: &WarmStart,
        device: &Device,
        log: &mut dyn FnMut(&ImitationRound, &[f32]),
    ) -> Result<(Self, Vec<ImitationRound>), TrainError> {
        imitate_recurrent(self, arch, config, warm, device, log)
    }
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// A copy of `actor` (σ kept) holding `payload`, with parameters of its own.
fn actor_holding<A: PolicyNet>(
    actor: &A,
    arch: &Architecture,
    payload: &[f32],
    device: &Device,
) -> Result<A, TrainError> {
    A::from_payload(arch, payload, &actor.std(), device)
        .ok_or_else(|| TrainError::Export("imitation: the actor's copy does not load".into()))
}

/// The teacher, the environment and the generator of a warm start (its own seeds).
fn set_up(
    config: &TrainConfig,
    warm: &WarmStart,
) -> Result<(Teacher, VecEnv, ChaCha8Rng), TrainError> {
    let teacher = Teacher::of(config, warm)?;
    let env = config.make_env(config.run.seed ^ 0x0da6_9e12)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.run.seed);
    rng.set_stream(u64::MAX - 3);
    Ok((teacher, env, rng))
}

/// Who labels the states of a warm start.
enum Teacher {
    /// The classical baseline at a cruise speed.
    Baseline(Box<BaselineController<'static>>),
    /// A time-trial blob's mean, observing through its own spec.
    Blob {
        policy: Box<Policy<'static>>,
        spec: firmware_core::observation::ObservationSpec,
    },
}

impl Teacher {
    fn of(config: &TrainConfig, warm: &WarmStart) -> Result<Self, TrainError> {
        let Some(path) = &warm.teacher_blob else {
            let preset = config.preset();
            let mut c = sitl::pilot::baseline_config_for(&preset);
            c.cruise_speed_mps = warm.teacher_cruise_mps;
            return Ok(Self::Baseline(Box::new(BaselineController::new(
                c,
                Track::figure_eight(),
            ))));
        };
        let raw = std::fs::read(path).map_err(crate::error::io(std::path::Path::new(path)))?;
        let refused = |reason: String| TrainError::Blob {
            what: format!("warm_start.teacher_blob '{path}'"),
            reason,
        };
        // Parsed once; the policy views the weights in place for the rest of the process.
        let bytes = sitl::env::interned(&firmware_core::blob::AlignedBytes::new(&raw));
        let blob = firmware_core::blob::Blob::parse(bytes.as_bytes())
            .map_err(|e| refused(e.to_string()))?;
        let policy = blob.policy().map_err(|e| refused(e.to_string()))?;
        if policy.is_recurrent() || blob.header().observation.layout.needs_opponent() {
            return Err(refused(
                "the teacher must be a feed-forward time-trial policy".into(),
            ));
        }
        Ok(Self::Blob {
            policy: Box::new(policy),
            spec: blob.header().observation,
        })
    }

    /// The teacher's actions for every env of `env` now, with `clamp` clamped to the
    /// rotor-command range [-1, 1] (`warm_start.clamp_labels`).
    fn label(&self, env: &VecEnv, out: &mut [f32], clamp: bool) {
        match self {
            Self::Baseline(b) => env.teacher_actions(b, out),
            Self::Blob { policy, spec } => env.policy_actions(policy, spec, out),
        }
        if clamp {
            out.iter_mut().for_each(|a| *a = a.clamp(-1.0, 1.0));
        }
    }
}

/// What one DAgger round flew: the states, the teacher's labels for them and the episode
/// boundaries, time-major (`[step][env]`).
struct Round {
    obs: Vec<f32>,
    labels: Vec<f32>,
    /// 0 where the env's episode ended at the step before (the student's state was zeroed
    /// there), else 1.
    keep: Vec<f32>,
}

/// The round collector both students share: round `round` of `warm`, `warm.steps_per_env`
/// steps of every env of `env`, each executed action the teacher's with the round's
/// probability ([`WarmStart::teacher_share`]) and otherwise the student's mean (`policy`,
/// through firmware-core, its recurrent state following the flight and zeroed at episode
/// ends) plus `warm.student_noise_std` Gaussian noise, all drawn from `rng`. Returns the
/// round and the share of teacher actions.
fn collect_round(
    env: &mut VecEnv,
    teacher: &Teacher,
    policy: &Policy<'_>,
    warm: &WarmStart,
    round: u32,
    rng: &mut ChaCha8Rng,
) -> Result<(Round, f64), TrainError> {
    let (beta, steps) = (warm.teacher_share(round), warm.steps_per_env);
    let (n, obs_dim) = (env.num_envs(), env.obs_dim());
    let mut memory = vec![policy.initial_state(); n];
    let mut labels = vec![0.0f32; n * ACTION_DIM];
    let mut executed = vec![0.0f32; n * ACTION_DIM];
    let mut previous_done = vec![false; n];
    let mut flown = Round {
        obs: Vec::with_capacity(steps * n * obs_dim),
        labels: Vec::with_capacity(steps * n * ACTION_DIM),
        keep: Vec::with_capacity(steps * n),
    };
    let mut from_teacher = 0usize;
    for _ in 0..steps {
        let obs = env.observations();
        teacher.label(env, &mut labels, warm.clamp_labels);
        for e in 0..n {
            let out = &mut executed[e * ACTION_DIM..(e + 1) * ACTION_DIM];
            // The student steps every time, so its state follows the flight.
            let mean = Observation::from_values(&obs[e * obs_dim..(e + 1) * obs_dim])
                .and_then(|o| policy.act(&o, &mut memory[e]))
                .ok_or_else(|| {
                    TrainError::Rollout(format!(
                        "imitation: the student does not take the environment's {obs_dim} observations"
                    ))
                })?;
            if rng.random::<f64>() < beta {
                out.copy_from_slice(&labels[e * ACTION_DIM..(e + 1) * ACTION_DIM]);
                from_teacher += 1;
            } else {
                for k in 0..ACTION_DIM {
                    out[k] = mean[k] + warm.student_noise_std * normal(rng);
                }
            }
        }
        flown.obs.extend_from_slice(obs);
        flown.labels.extend_from_slice(&labels);
        flown
            .keep
            .extend(previous_done.iter().map(|d| if *d { 0.0 } else { 1.0 }));
        env.step(&executed)
            .map_err(|e| TrainError::Rollout(e.to_string()))?;
        previous_done.copy_from_slice(env.dones());
        for (m, _) in memory.iter_mut().zip(env.dones()).filter(|(_, d)| **d) {
            m.clear();
        }
    }
    Ok((flown, from_teacher as f64 / (n * steps).max(1) as f64))
}

/// The log line of round `round` (0-based): its teacher share, data, fit and what the
/// executed mixture flew (`stats`, steps of `dt_s`).
fn round_line(
    round: u32,
    teacher_share: f64,
    samples: usize,
    (mse, mse_first_epoch): (f64, f64),
    stats: &EnvStats,
    dt_s: f32,
) -> ImitationRound {
    let sim_s = stats.steps as f64 * f64::from(dt_s);
    ImitationRound {
        round: round + 1,
        teacher_share,
        samples,
        mse,
        mse_first_epoch,
        gates_per_s: stats.gates_passed as f64 / sim_s.max(1e-9),
        crash_rate_per_s: stats.crashes as f64 / sim_s.max(1e-9),
        ..ImitationRound::default()
    }
}

/// The student a round flies: its weights viewed by firmware-core.
fn flying_policy<'w>(payload: &'w [f32], arch: &Architecture) -> Result<Policy<'w>, TrainError> {
    Policy::from_payload(arch, payload).map_err(|e| TrainError::Export(format!("imitation: {e}")))
}

/// The one DAgger loop of both warm starts: every round the student and the teacher fly a
/// round on the config's environment (a recurrent student from fresh spawns, so its state
/// starts at zero), the teacher labels the states, the data is kept by `fit`, and
/// `warm.epochs` passes of `fit` regress the student's mean onto the labels. Returns the
/// student (σ unchanged) with the rounds' statistics; `log` receives one line per round with
/// the round's student.
fn dagger<A: PolicyNet>(
    mut actor: A,
    fit: &mut dyn Regression<A>,
    arch: &Architecture,
    config: &TrainConfig,
    warm: &WarmStart,
    log: &mut dyn FnMut(&ImitationRound, &[f32]),
) -> Result<(A, Vec<ImitationRound>), TrainError> {
    let (teacher, mut env, mut rng) = set_up(config, warm)?;
    let mut rounds = Vec::new();
    for round in 0..warm.rounds {
        let payload = actor.payload();
        let policy = flying_policy(&payload, arch)?;
        if A::RECURRENT {
            env.respawn_all();
        }
        let (flown, teacher_share) =
            collect_round(&mut env, &teacher, &policy, warm, round, &mut rng)?;
        let stats = env.take_stats();
        let samples = fit.keep(flown);
        let (mut mse, mut mse_first_epoch) = (0.0, 0.0);
        for epoch in 0..warm.epochs {
            let (a, epoch_mse) = fit.epoch(actor, round, &mut rng)?;
            actor = a;
            mse = epoch_mse;
            if epoch == 0 && A::RECURRENT {
                mse_first_epoch = mse;
            }
        }
        let r = round_line(
            round,
            teacher_share,
            samples,
            (mse, mse_first_epoch),
            &stats,
            env.dt_s(),
        );
        log(&r, &actor.payload());
        rounds.push(r);
    }
    Ok((actor, rounds))
}

/// What a kind of student brings to [`dagger`]: how the flown rounds are kept and how one
/// epoch regresses the student onto them.
trait Regression<A> {
    /// Keeps the round `flown`, the oldest data dropped beyond `warm_start.max_samples`;
    /// returns the samples kept.
    fn keep(&mut self, flown: Round) -> usize;
    /// One pass over the kept data in DAgger round `round`: the student and the pass's mean
    /// squared error.
    fn epoch(&mut self, actor: A, round: u32, rng: &mut ChaCha8Rng)
    -> Result<(A, f64), TrainError>;
}

/// The warm start of a feed-forward actor (rows A-D): the one DAgger loop with the samples kept
/// flat and regressed in shuffled minibatches.
pub fn imitate(
    actor: Actor,
    arch: &Architecture,
    config: &TrainConfig,
    warm: &WarmStart,
    device: &Device,
    log: &mut dyn FnMut(&ImitationRound, &[f32]),
) -> Result<(Actor, Vec<ImitationRound>), TrainError> {
    let mut fit = FeedForwardFit {
        warm,
        device,
        obs_dim: config.observation_spec().dim(),
        optim: adam(),
        obs: Vec::new(),
        labels: Vec::new(),
        order: Vec::new(),
    };
    dagger(actor, &mut fit, arch, config, warm, log)
}

/// The feed-forward regression of one warm-start stage and the samples it keeps.
struct FeedForwardFit<'a> {
    warm: &'a WarmStart,
    device: &'a Device,
    obs_dim: usize,
    optim: ModuleOptimizer,
    obs: Vec<f32>,
    labels: Vec<f32>,
    /// The samples' order, shuffled in place by every epoch of a round (so each epoch's
    /// permutation follows from the last).
    order: Vec<usize>,
}

impl Regression<Actor> for FeedForwardFit<'_> {
    fn keep(&mut self, flown: Round) -> usize {
        self.obs.extend_from_slice(&flown.obs);
        self.labels.extend_from_slice(&flown.labels);
        let excess = (self.labels.len() / ACTION_DIM).saturating_sub(self.warm.max_samples);
        self.obs.drain(..excess * self.obs_dim);
        self.labels.drain(..excess * ACTION_DIM);
        let count = self.labels.len() / ACTION_DIM;
        self.order = (0..count).collect();
        count
    }

    fn epoch(
        &mut self,
        mut actor: Actor,
        round: u32,
        rng: &mut ChaCha8Rng,
    ) -> Result<(Actor, f64), TrainError> {
        let (obs_dim, warm, device) = (self.obs_dim, self.warm, self.device);
        self.order.shuffle(rng);
        let (mut sum, mut batches) = (0.0, 0.0);
        for idx in self.order.chunks(warm.minibatch) {
            let mut o = Vec::with_capacity(idx.len() * obs_dim);
            let mut a = Vec::with_capacity(idx.len() * ACTION_DIM);
            for &i in idx {
                o.extend_from_slice(&self.obs[i * obs_dim..(i + 1) * obs_dim]);
                a.extend_from_slice(&self.labels[i * ACTION_DIM..(i + 1) * ACTION_DIM]);
            }
            let obs_t = Tensor::<2>::from_data(TensorData::new(o, [idx.len(), obs_dim]), device);
            let act_t = Tensor::<2>::from_data(TensorData::new(a, [idx.len(), ACTION_DIM]), device);
            let loss = (actor.mean(obs_t) - act_t).square().mean();
            sum += f64::from(values(loss.clone().inner()).first().copied().unwrap_or(0.0));
            batches += 1.0;
            let grads = GradientsParams::from_grads(loss.backward(), &actor);
            actor = self
                .optim
                .step(warm.round_learning_rate(round), actor, grads);
        }
        Ok((actor, sum / f64::max(batches, 1.0)))
    }
}

/// The warm start of a recurrent actor (rows E-G): the one DAgger loop on the config's environment
/// (the race, for stage 2), each round from fresh spawns, the student acting through
/// firmware-core with its state carried step by step. The regression runs the student over
/// windows of `ppo.steps_per_env` steps with backpropagation through each window; the state
/// each window starts from is recomputed by the current student at every epoch (from zero at
/// the round's start), so old rounds are not fitted from stale states.
pub fn imitate_recurrent(
    actor: RecurrentActor,
    arch: &Architecture,
    config: &TrainConfig,
    warm: &WarmStart,
    device: &Device,
    log: &mut dyn FnMut(&ImitationRound, &[f32]),
) -> Result<(RecurrentActor, Vec<ImitationRound>), TrainError> {
    let mut fit = RecurrentFit {
        arch,
        warm,
        device,
        n: config.env.num_envs,
        obs_dim: config.observation_spec().dim(),
        window: config.ppo.steps_per_env.max(1),
        optim: adam(),
        data: Vec::new(),
    };
    dagger(actor, &mut fit, arch, config, warm, log)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `stage1_nominal.blob`'s means leave [-1, 1] in the race's states (which is why its students
    /// clamp them): unclamped labels show it, clamped ones stay in range and agree with the
    /// unclamped ones wherever those are in range.
    #[test]
    fn clamped_labels_are_the_commands_the_teacher_flies() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut config = TrainConfig::parse(include_str!("../../configs/smoke_race.toml")).unwrap();
        config.env.num_envs = 64;
        if let Some(race) = config.env.race.as_mut() {
            race.opponent = root.join("policies/stage1_nominal.blob");
        }
        let warm = WarmStart {
            teacher_blob: Some(
                root.join("policies/stage1_nominal.blob")
                    .display()
                    .to_string(),
            ),
            ..WarmStart::default()
        };
        let (teacher, mut env, _) = set_up(&config, &warm).unwrap();
        let (mut raw, mut clamped) = (vec![0.0; 64 * ACTION_DIM], vec![0.0; 64 * ACTION_DIM]);
        let mut outside = 0;
        for _ in 0..50 {
            teacher.label(&env, &mut raw, false);
            teacher.label(&env, &mut clamped, true);
            for (r, c) in raw.iter().zip(&clamped) {
                assert!((-1.0..=1.0).contains(c));
                if r.abs() > 1.0 {
                    outside += 1;
                } else {
                    assert_eq!(r, c);
                }
            }
            env.step(&clamped).unwrap();
        }
        assert!(outside > 0, "no label left [-1, 1]");
    }
}
