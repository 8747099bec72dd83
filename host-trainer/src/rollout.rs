//! Collecting experience: the rollout buffer of one iteration and the loop that fills it by
//! flying the deployed network in the vectorised environment.
//!
//! **Rollouts fly the deployed network.** Every iteration the actor's weights are written in
//! blob payload order and viewed by firmware-core's `Policy`, the code the flight controller
//! runs; the rollout's Gaussian means come from it (in parallel over envs), the noise from one
//! seeded generator. The update recomputes means and values with `burn` in one batched pass,
//! so the ratio of the first minibatch is 1 up to the parity of the two implementations
//! (< 1e-5, tested).

use crate::error::TrainError;
use crate::rng::normal;
use firmware_core::nn::{ACTION_DIM, LANES};
use firmware_core::observation::Observation;
use firmware_core::policy::{Policy, PolicyState};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use sitl::env::VecEnv;
use sitl::lanes::step_lanes;
use std::collections::VecDeque;

/// One iteration's transitions, time-major (`[step][env]`).
#[derive(Clone, Debug, Default)]
pub struct Rollout {
    /// Envs.
    pub num_envs: usize,
    /// Observation size.
    pub obs_dim: usize,
    /// Observations at the start of each step, `steps × envs × obs_dim`.
    pub obs: Vec<f32>,
    /// Actions taken (unclipped samples), `steps × envs × 4`.
    pub actions: Vec<f32>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// Episode ended in the step.
    pub dones: Vec<bool>,
    /// The end was a time-out (bootstrapped with γ·V).
    pub timeouts: Vec<bool>,
    /// Observations after the last step, `envs × obs_dim`.
    pub last_obs: Vec<f32>,
    /// Values per privileged state when the rollout records them for a privileged critic
    /// (`sitl::env::VecEnv::privileged_dim`); 0: not recorded.
    pub privileged_dim: usize,
    /// The env's privileged states at the start of each step, `steps × envs ×
    /// privileged_dim` (empty when not recorded).
    pub privileged: Vec<f32>,
    /// The privileged states after the last step, `envs × privileged_dim`.
    pub last_privileged: Vec<f32>,
    /// Recurrent policies: the actor's state in every env when the window began, flat
    /// (`envs × width`, see [`crate::recurrent::LstmState::from_flat`]); empty for a feed-forward policy.
    pub actor_h0: Vec<f32>,
    /// Recurrent policies: the critic's state in every env when the window began (the
    /// previous batch's [`crate::batch::Sequences::critic_next`]; empty means zero).
    pub critic_h0: Vec<f32>,
    /// Recurrent policies: the policy's state in every env, carried from one window to the
    /// next by the rollout (zeroed at episode ends, as the controller does); not cleared.
    pub memory: Vec<firmware_core::policy::PolicyState>,
}

impl Rollout {
    /// An empty buffer for `num_envs` envs.
    pub fn new(num_envs: usize, obs_dim: usize) -> Self {
        Self {
            num_envs,
            obs_dim,
            ..Self::default()
        }
    }

    /// Steps recorded.
    pub fn steps(&self) -> usize {
        self.rewards.len() / self.num_envs.max(1)
    }

    /// Empties the buffer, keeping its allocations.
    pub fn clear(&mut self) {
        self.obs.clear();
        self.actions.clear();
        self.rewards.clear();
        self.dones.clear();
        self.timeouts.clear();
        self.last_obs.clear();
        self.privileged.clear();
        self.last_privileged.clear();
        self.actor_h0.clear();
    }
}

/// Collects `steps` steps of every env of `env` into `rollout` (cleared first): actions are
/// `policy`'s Gaussian means (firmware-core's network, the deployed code, in parallel over
/// envs) plus `std`-scaled noise drawn serially from `noise_rng`. `on_step` sees each step's
/// rewards and dones. An observation the policy cannot act on (not finite: the environment
/// never gives one) stops the collection with an error instead of flying a stale action.
pub fn collect_rollout(
    env: &mut VecEnv,
    policy: &Policy<'_>,
    std: &[f32],
    steps: usize,
    noise_rng: &mut ChaCha8Rng,
    rollout: &mut Rollout,
    mut on_step: impl FnMut(&[f32], &[bool]),
) -> Result<(), TrainError> {
    let obs_dim = env.obs_dim();
    if policy.obs_dim() != obs_dim {
        return Err(TrainError::Rollout(format!(
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
            push_flat_state(s, &mut rollout.actor_h0);
        }
    }
    if rollout.privileged_dim != 0 && rollout.privileged_dim != env.privileged_dim() {
        return Err(TrainError::Rollout(format!(
            "the critic observes {} privileged values, the environment gives {}",
            rollout.privileged_dim,
            env.privileged_dim()
        )));
    }
    let mut privileged = Vec::new();
    let mut actions = vec![0.0f32; n * ACTION_DIM];
    let mut noise = vec![0.0f32; n * ACTION_DIM];
    let refused = std::sync::atomic::AtomicUsize::new(0);
    for _ in 0..steps {
        let obs = env.observations();
        rollout.obs.extend_from_slice(obs);
        if rollout.privileged_dim != 0 {
            env.privileged_observations(&mut privileged);
            rollout.privileged.extend_from_slice(&privileged);
        }
        for z in &mut noise {
            *z = normal(noise_rng);
        }
        actions
            .par_chunks_mut(ACTION_DIM * ENVS_PER_TASK)
            .zip(obs.par_chunks(obs_dim * ENVS_PER_TASK))
            .zip(noise.par_chunks(ACTION_DIM * ENVS_PER_TASK))
            .zip(rollout.memory.par_chunks_mut(ENVS_PER_TASK))
            .for_each(|(((a, o), z), memory)| {
                // LANES envs side by side (the same bits as one by one, each env's
                // recurrent state its own), the rest of the chunk one by one.
                let mut done = 0;
                for (((a, o), z), memory) in a
                    .chunks_exact_mut(ACTION_DIM * LANES)
                    .zip(o.chunks_exact(obs_dim * LANES))
                    .zip(z.chunks_exact(ACTION_DIM * LANES))
                    .zip(memory.chunks_exact_mut(LANES))
                {
                    let Ok(memory) = <&mut [PolicyState; LANES]>::try_from(memory) else {
                        break;
                    };
                    let Some(means) = step_lanes(policy, o, memory.each_mut()) else {
                        break;
                    };
                    for ((a, mean), z) in a
                        .chunks_exact_mut(ACTION_DIM)
                        .zip(means)
                        .zip(z.chunks_exact(ACTION_DIM))
                    {
                        explore(a, &mean, std, z);
                    }
                    done += LANES;
                }
                for (((a, o), z), memory) in a
                    .chunks_exact_mut(ACTION_DIM)
                    .zip(o.chunks_exact(obs_dim))
                    .zip(z.chunks_exact(ACTION_DIM))
                    .zip(memory)
                    .skip(done)
                {
                    match Observation::from_values(o).and_then(|o| policy.act(&o, memory)) {
                        Some(mean) => explore(a, &mean, std, z),
                        None => {
                            refused.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        }
                    }
                }
            });
        let refused = refused.swap(0, std::sync::atomic::Ordering::Relaxed);
        if refused > 0 {
            return Err(TrainError::Rollout(format!(
                "the policy could not act on {refused} observations of a step (not finite?): the rollout stops rather than fly stale actions"
            )));
        }
        rollout.actions.extend_from_slice(&actions);
        env.step(&actions)
            .map_err(|e| TrainError::Rollout(e.to_string()))?;
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
    if rollout.privileged_dim != 0 {
        env.privileged_observations(&mut privileged);
        rollout.last_privileged.extend_from_slice(&privileged);
    }
    Ok(())
}

/// The action flown: the mean plus σ times the drawn noise, per motor.
#[inline(always)]
fn explore(action: &mut [f32], mean: &[f32; ACTION_DIM], std: &[f32], noise: &[f32]) {
    for k in 0..ACTION_DIM {
        action[k] = mean[k] + std.get(k).copied().unwrap_or(0.0) * noise[k];
    }
}

/// Envs per parallel task of the rollout's inference (a multiple of [`LANES`]).
const ENVS_PER_TASK: usize = 64;

/// Appends a firmware-core recurrent state in the flat layout of
/// [`crate::recurrent::LstmState`] (per layer `h` then `c`); nothing for a feed-forward
/// policy.
pub fn push_flat_state(state: &PolicyState, out: &mut Vec<f32>) {
    match state {
        PolicyState::Stateless => {}
        PolicyState::Lstm1(s) => {
            out.extend_from_slice(&s.first.h);
            out.extend_from_slice(&s.first.c);
        }
        PolicyState::Lstm2(s) => {
            out.extend_from_slice(&s.first.h);
            out.extend_from_slice(&s.first.c);
            for d in &s.deep {
                out.extend_from_slice(&d.h);
                out.extend_from_slice(&d.c);
            }
        }
    }
}

/// The returns and lengths of the episodes that ended recently, for the logs.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpisodeLog {
    /// The running return of every env's current episode.
    running_return: Vec<f64>,
    /// The running length (steps) of every env's current episode.
    running_steps: Vec<u32>,
    /// (return, steps) of the last [`EpisodeLog::KEPT`] episodes that ended.
    finished: VecDeque<(f64, u32)>,
}

impl EpisodeLog {
    /// Episodes kept for the means.
    pub const KEPT: usize = 200;

    /// A log for `num_envs` envs, no episode ended yet.
    pub fn new(num_envs: usize) -> Self {
        Self {
            running_return: vec![0.0; num_envs],
            running_steps: vec![0; num_envs],
            finished: VecDeque::with_capacity(Self::KEPT),
        }
    }

    /// One step's rewards and episode ends of every env.
    pub fn record(&mut self, rewards: &[f32], dones: &[bool]) {
        for (e, (&r, &done)) in rewards.iter().zip(dones).enumerate() {
            self.running_return[e] += f64::from(r);
            self.running_steps[e] += 1;
            if done {
                if self.finished.len() == Self::KEPT {
                    self.finished.pop_front();
                }
                self.finished
                    .push_back((self.running_return[e], self.running_steps[e]));
                self.running_return[e] = 0.0;
                self.running_steps[e] = 0;
            }
        }
    }

    /// Mean return of the kept episodes (0 before any ended).
    pub fn mean_return(&self) -> f64 {
        self.finished.iter().map(|e| e.0).sum::<f64>() / self.finished.len().max(1) as f64
    }

    /// Mean length of the kept episodes (s), with steps of `dt_s`.
    pub fn mean_length_s(&self, dt_s: f64) -> f64 {
        self.finished.iter().map(|e| f64::from(e.1)).sum::<f64>() * dt_s
            / self.finished.len().max(1) as f64
    }
}
