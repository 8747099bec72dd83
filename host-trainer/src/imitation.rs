//! The imitation warm start (DAgger, Ross et al. 2011): before PPO, the actor's mean is
//! regressed onto the classical baseline's actions on the states that a mixture of the
//! baseline and the student visits. Round `k` executes the teacher's action with
//! probability β_k (1 → 0 over the first half of the rounds) and the student's noisy action
//! otherwise; every visited state is labelled with the teacher's action, and the data of all
//! rounds (up to `max_samples`) is fitted by mean squared error.
//!
//! Why: with SPEC's reward at this machine's budget, PPO from a random actor learns to hover
//! and then stays there (docs/TRAINING.md has the runs). A student that already flies the
//! track sees the progress reward from its first PPO iteration.

use crate::config::{TrainConfig, WarmStart};
use crate::env::{OBS_DIM, TrainEnv};
use crate::model::{Actor, values};
use crate::train::{TrainError, env_config};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::baseline::BaselineController;
use firmware_core::nn::ACTION_DIM;
use firmware_core::policy::{Architecture, Policy};
use firmware_core::track::Track;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sitl::dynamics::Preset;

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
    /// Gates passed per simulated second by the executed mixture.
    pub gates_per_s: f64,
    /// Crashes per simulated second by the executed mixture.
    pub crash_rate_per_s: f64,
}

/// Runs the warm start on `actor` and returns the student (σ unchanged) with the rounds'
/// statistics; `log` receives one line per round.
pub fn imitate(
    mut actor: Actor,
    arch: &Architecture,
    config: &TrainConfig,
    warm: &WarmStart,
    device: &Device,
    log: &mut dyn FnMut(&ImitationRound),
) -> Result<(Actor, Vec<ImitationRound>), TrainError> {
    let preset = Preset::by_name(&config.env.preset).unwrap_or_else(Preset::paper);
    let mut teacher_config = sitl::pilot::baseline_config_for(&preset);
    teacher_config.cruise_speed_mps = warm.teacher_cruise_mps;
    let teacher = BaselineController::new(teacher_config, Track::figure_eight());
    let mut env = TrainEnv::new(env_config(config, config.run.seed ^ 0x0da6_9e12)?);
    let n = env.num_envs();
    let mut rng = ChaCha8Rng::seed_from_u64(config.run.seed);
    rng.set_stream(u64::MAX - 3);
    let mut optim = crate::ppo::adam();
    let mut data_obs: Vec<f32> = Vec::new();
    let mut data_act: Vec<f32> = Vec::new();
    let mut labels = vec![0.0f32; n * ACTION_DIM];
    let mut executed = vec![0.0f32; n * ACTION_DIM];
    let mut rounds = Vec::new();
    let half = (warm.rounds / 2).max(1);
    for round in 0..warm.rounds {
        let beta = (1.0 - f64::from(round) / f64::from(half)).max(0.0);
        let payload = actor.payload();
        let Ok(Policy::A(net)) = Policy::from_payload(arch, &payload) else {
            return Err(TrainError::Unsupported("imitation: row A only".into()));
        };
        let mut from_teacher = 0usize;
        for _ in 0..warm.steps_per_env {
            let obs = env.observations().to_vec();
            env.teacher_actions(&teacher, &mut labels);
            for e in 0..n {
                let out = &mut executed[e * ACTION_DIM..(e + 1) * ACTION_DIM];
                if rng.random::<f64>() < beta {
                    out.copy_from_slice(&labels[e * ACTION_DIM..(e + 1) * ACTION_DIM]);
                    from_teacher += 1;
                } else {
                    let o = <&[f32; OBS_DIM]>::try_from(&obs[e * OBS_DIM..(e + 1) * OBS_DIM])
                        .map_err(|_| TrainError::Unsupported("observation size".into()))?;
                    let mean = net.forward(o);
                    for k in 0..ACTION_DIM {
                        out[k] = mean[k] + warm.student_noise_std * crate::train::normal(&mut rng);
                    }
                }
            }
            data_obs.extend_from_slice(&obs);
            data_act.extend_from_slice(&labels);
            env.step(&executed)
                .map_err(|e| TrainError::Unsupported(e.to_string()))?;
        }
        let stats = env.take_stats();
        let excess = (data_act.len() / ACTION_DIM).saturating_sub(warm.max_samples);
        data_obs.drain(..excess * OBS_DIM);
        data_act.drain(..excess * ACTION_DIM);

        // Regression of the mean onto the labels.
        let count = data_act.len() / ACTION_DIM;
        let mut order: Vec<usize> = (0..count).collect();
        let mut mse = 0.0;
        for _ in 0..warm.epochs {
            order.shuffle(&mut rng);
            let (mut sum, mut batches) = (0.0, 0.0);
            for idx in order.chunks(warm.minibatch) {
                let mut o = Vec::with_capacity(idx.len() * OBS_DIM);
                let mut a = Vec::with_capacity(idx.len() * ACTION_DIM);
                for &i in idx {
                    o.extend_from_slice(&data_obs[i * OBS_DIM..(i + 1) * OBS_DIM]);
                    a.extend_from_slice(&data_act[i * ACTION_DIM..(i + 1) * ACTION_DIM]);
                }
                let obs_t =
                    Tensor::<2>::from_data(TensorData::new(o, [idx.len(), OBS_DIM]), device);
                let act_t =
                    Tensor::<2>::from_data(TensorData::new(a, [idx.len(), ACTION_DIM]), device);
                let loss = (actor.mean(obs_t) - act_t).square().mean();
                sum += f64::from(values(loss.clone().inner()).first().copied().unwrap_or(0.0));
                batches += 1.0;
                let grads = GradientsParams::from_grads(loss.backward(), &actor);
                actor = optim.step(warm.learning_rate, actor, grads);
            }
            mse = sum / f64::max(batches, 1.0);
        }
        let sim_s = stats.steps as f64 * f64::from(env.dt_s());
        let r = ImitationRound {
            round: round + 1,
            teacher_share: from_teacher as f64 / (n * warm.steps_per_env).max(1) as f64,
            samples: count,
            mse,
            gates_per_s: stats.gates_passed as f64 / sim_s.max(1e-9),
            crash_rate_per_s: stats.crashes as f64 / sim_s.max(1e-9),
        };
        log(&r);
        rounds.push(r);
    }
    Ok((actor, rounds))
}
