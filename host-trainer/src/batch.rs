//! A rollout turned into PPO's training samples: the flat [`Batch`], the window structure
//! of recurrent networks ([`Sequences`]), the minibatches drawn from it ([`Minibatch`]), and
//! the estimators the batch is built with: generalised advantage estimation ([`gae`]) and the
//! Gaussian log-likelihood ([`gaussian_log_prob`]). RSL-RL keeps the same in
//! `storage/rollout_storage.py`.

use crate::rollout::Rollout;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::nn::ACTION_DIM;

/// ln(2π).
pub const LN_2PI: f32 = 1.837_877_1;

/// The rollout turned into training samples: flat `[sample]` arrays.
#[derive(Clone, Debug)]
pub struct Batch {
    /// Observation size.
    pub obs_dim: usize,
    /// Observations.
    pub obs: Vec<f32>,
    /// Actions.
    pub actions: Vec<f32>,
    /// log π_old(a|o).
    pub old_log_prob: Vec<f32>,
    /// μ_old(o), for the KL.
    pub old_mean: Vec<f32>,
    /// σ_old.
    pub old_std: [f32; ACTION_DIM],
    /// V_old(o).
    pub old_values: Vec<f32>,
    /// GAE returns (value targets).
    pub returns: Vec<f32>,
    /// Normalised advantages.
    pub advantages: Vec<f32>,
    /// Recurrent networks: the windows (`None` for feed-forward ones).
    pub sequence: Option<Sequences>,
    /// A privileged critic's inputs (`[ppo] critic = "privileged-mlp"`); `None` when the
    /// critic sees the actor's observations.
    pub critic: Option<CriticInputs>,
}

/// What a privileged critic sees ([`crate::model::PrivilegedCritic`]): the env's privileged
/// state (`sitl::env::VecEnv::privileged_observations`) per sample and after the window.
#[derive(Clone, Debug, Default)]
pub struct CriticInputs {
    /// Values per state.
    pub dim: usize,
    /// One row per sample (the batch's order).
    pub obs: Vec<f32>,
    /// One row per env: the states after the window (for the bootstrap).
    pub last_obs: Vec<f32>,
}

impl Batch {
    /// Samples.
    pub fn len(&self) -> usize {
        self.returns.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.returns.is_empty()
    }
}

/// The window structure a recurrent network needs: which steps continue an episode and the
/// states the window starts from.
#[derive(Clone, Debug, Default)]
pub struct Sequences {
    /// Envs.
    pub num_envs: usize,
    /// Steps per env.
    pub steps: usize,
    /// `[step][env]`: 0 where the env's episode ended at the step before (its state is
    /// zeroed before this step), else 1.
    pub keep: Vec<f32>,
    /// `[env]`: the same for the observation after the window.
    pub last_keep: Vec<f32>,
    /// The actor's states at the window's start, `envs × width`.
    pub actor_h0: Vec<f32>,
    /// The critic's states at the window's start, `envs × width`.
    pub critic_h0: Vec<f32>,
    /// The critic's states to start the next window from (after this window's last step,
    /// zeroed where its episode ended there).
    pub critic_next: Vec<f32>,
}

impl Sequences {
    /// The windows of rollout `r` (the critic's next state left empty).
    pub fn of(r: &Rollout) -> Self {
        let n = r.num_envs;
        let steps = r.steps();
        let keep_after = |i: usize| if r.dones[i] { 0.0 } else { 1.0 };
        let mut keep = vec![1.0f32; steps * n];
        for (i, k) in keep.iter_mut().enumerate().skip(n) {
            *k = keep_after(i - n);
        }
        let last_keep = (0..n)
            .map(|e| {
                if steps == 0 {
                    1.0
                } else {
                    keep_after((steps - 1) * n + e)
                }
            })
            .collect();
        Self {
            num_envs: n,
            steps,
            keep,
            last_keep,
            actor_h0: r.actor_h0.clone(),
            critic_h0: r.critic_h0.clone(),
            critic_next: Vec::new(),
        }
    }
}

/// The samples of one minibatch: their indices into the batch (the rows of a network's
/// outputs) and, for a recurrent network, the envs whose windows they are.
#[derive(Clone, Debug, Default)]
pub struct Minibatch {
    /// Sample indices (time-major `step · envs + env`).
    pub samples: Vec<usize>,
    /// Recurrent: the envs, in the order the samples take them at each step.
    pub envs: Vec<usize>,
}

impl Minibatch {
    /// Every sample of `b`, every env.
    pub fn all(b: &Batch) -> Self {
        let envs = b.sequence.as_ref().map_or(0, |s| s.num_envs);
        Self {
            samples: (0..b.len()).collect(),
            envs: (0..envs).collect(),
        }
    }

    /// The windows of `envs`: their samples step by step.
    pub fn of_envs(b: &Batch, envs: &[usize]) -> Self {
        let (n, steps) = b
            .sequence
            .as_ref()
            .map_or((0, 0), |s| (s.num_envs, s.steps));
        Self {
            samples: (0..steps)
                .flat_map(|t| envs.iter().map(move |e| t * n + e))
                .collect(),
            envs: envs.to_vec(),
        }
    }
}

/// log N(a; μ, σ) summed over the action dimensions.
pub fn gaussian_log_prob(action: &[f32], mean: &[f32], std: &[f32; ACTION_DIM]) -> f32 {
    action
        .iter()
        .zip(mean)
        .zip(std)
        .map(|((a, m), s)| {
            let z = (a - m) / s;
            -0.5 * z * z - s.ln() - 0.5 * LN_2PI
        })
        .sum()
}

/// GAE(γ, λ) over a time-major rollout: returns the value targets (`returns`); advantages are
/// `returns − values`. `values` has `steps × envs` entries, `last_values` the bootstrap of
/// the state after the last step; a done stops the recursion (rewards already carry the
/// time-out bootstrap).
pub fn gae(
    rewards: &[f32],
    dones: &[bool],
    values: &[f32],
    last_values: &[f32],
    gamma: f32,
    lambda: f32,
) -> Vec<f32> {
    let n = last_values.len();
    let steps = rewards.len() / n.max(1);
    let mut returns = vec![0.0; rewards.len()];
    let mut advantage = vec![0.0f32; n];
    for t in (0..steps).rev() {
        for e in 0..n {
            let i = t * n + e;
            let next_value = if t + 1 == steps {
                last_values[e]
            } else {
                values[i + n]
            };
            let live = if dones[i] { 0.0 } else { 1.0 };
            let delta = rewards[i] + live * gamma * next_value - values[i];
            advantage[e] = delta + live * gamma * lambda * advantage[e];
            returns[i] = advantage[e] + values[i];
        }
    }
    returns
}

/// A batch of rows as a `[n, width]` tensor.
pub fn tensor2(data: Vec<f32>, width: usize, device: &Device) -> Tensor<2> {
    let n = data.len() / width.max(1);
    Tensor::from_data(TensorData::new(data, [n, width]), device)
}

/// Rows `idx` of a row-major `[_, width]` array.
pub fn gather(src: &[f32], width: usize, idx: &[usize]) -> Vec<f32> {
    let mut out = Vec::with_capacity(idx.len() * width);
    for &i in idx {
        out.extend_from_slice(&src[i * width..(i + 1) * width]);
    }
    out
}
