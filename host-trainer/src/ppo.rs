//! PPO (SPEC "Learning", RSL-RL's `PPO`): a rollout buffer, generalised advantage
//! estimation, and the clipped-surrogate update with a clipped value loss, an entropy bonus,
//! the adaptive-KL learning rate, a global gradient-norm clip and Adam.
//!
//! **Actor and critic in parallel.** The actor and the critic are separate networks and the
//! PPO loss is a sum of an actor part (surrogate, entropy) and a critic part (value loss), so
//! each part's forward and backward pass runs on its own thread; the gradients are then
//! clipped together by their global norm (PyTorch's `clip_grad_norm_` over all parameters, as
//! RSL-RL does) and each network takes its Adam step. This is the same update as one joint
//! backward pass: Adam is per parameter, and the two graphs share no node. `burn`'s flex
//! matmuls at these sizes use one core, so this is what makes the second core work (measured
//! in docs/PERFORMANCE.md).
//!
//! Departures from RSL-RL, each documented in docs/TRAINING.md: a fresh minibatch permutation
//! every epoch (RSL-RL draws one per update), a log-parameterised σ (RSL-RL's default stores σ
//! itself, which can go negative).
//!
//! **Recurrent PPO** is the same update on [`crate::recurrent`]'s networks ([`PpoNet`] says
//! how a network computes its outputs for a minibatch): a minibatch is a set of whole env
//! windows (RSL-RL's recurrent generator splits by env), the networks run over each window
//! from the recurrent states stored when the rollout began, with the state zeroed after an
//! episode end, and the gradients flow back through the window (truncated backpropagation
//! through time over `steps_per_env` steps).

use crate::config::PpoConfig;
use crate::model::{Actor, Critic, values};
use crate::recurrent::{LstmState, RecurrentActor, RecurrentCritic};
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::nn::ACTION_DIM;
use firmware_core::policy::Architecture;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

/// ln(2π).
const LN_2PI: f32 = 1.837_877_1;

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
    /// Recurrent policies: the actor's state in every env when the window began, flat
    /// (`envs × width`, see [`LstmState::from_flat`]); empty for a feed-forward policy.
    pub actor_h0: Vec<f32>,
    /// Recurrent policies: the critic's state in every env when the window began (the
    /// previous batch's [`Sequences::critic_next`]; empty means zero).
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
        self.actor_h0.clear();
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
    fn of(r: &Rollout) -> Self {
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

/// How PPO runs a network (the feed-forward MLPs of [`crate::model`] or the LSTM networks of
/// [`crate::recurrent`]).
pub trait PpoNet: Module + Sync + 'static {
    /// Minibatches are whole env windows (the network carries a state) rather than samples.
    const RECURRENT: bool;
    /// The outputs for `mb`'s samples, one row each in `mb.samples` order (autodiff when
    /// the network is on an autodiff device).
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2>;
    /// The outputs for every sample of `b`; with `last_obs` (the observations after the
    /// window) also the outputs for those and the state to start the next window from
    /// (empty when feed-forward), else both empty.
    fn rollout_outputs(
        &self,
        b: &Batch,
        last_obs: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>);
}

/// A Gaussian policy PPO trains: outputs are the means; σ is state-independent. Its weights
/// map one-to-one onto a firmware-core blob payload.
pub trait PolicyNet: PpoNet + Sized {
    /// log σ per action (a parameter).
    fn log_std(&self) -> Tensor<1>;
    /// σ per action.
    fn std(&self) -> Vec<f32>;
    /// A fresh actor of `arch` with σ = `init_std`, initialised from `rng`.
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self;
    /// The weights in firmware-core payload order.
    fn payload(&self) -> Vec<f32>;
    /// The actor holding `payload` with σ = `std`; `None` when they do not fit `arch`.
    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self>;
    /// The same actor with its output bias set to `action` on every motor.
    fn with_output_bias(self, action: f32) -> Self;
}

/// A value function PPO trains.
pub trait ValueNet: PpoNet {
    /// A fresh critic with `arch`'s shape and one output, initialised from `rng`.
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self;
}

impl PpoNet for Actor {
    const RECURRENT: bool = false;
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
        self.mean(tensor2(
            gather(&b.obs, b.obs_dim, &mb.samples),
            b.obs_dim,
            device,
        ))
    }
    fn rollout_outputs(
        &self,
        b: &Batch,
        last: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let all = values(self.mean(tensor2(b.obs.clone(), b.obs_dim, device)));
        let last = last.map_or_else(Vec::new, |l| {
            values(self.mean(tensor2(l.to_vec(), b.obs_dim, device)))
        });
        (all, last, Vec::new())
    }
}

impl PolicyNet for Actor {
    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }
    fn std(&self) -> Vec<f32> {
        Actor::std(self)
    }
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        Actor::new(arch, init_std, rng, device)
    }
    fn payload(&self) -> Vec<f32> {
        Actor::payload(self)
    }
    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self> {
        Actor::from_payload(arch, payload, std, device)
    }
    fn with_output_bias(self, action: f32) -> Self {
        Actor::with_output_bias(self, action)
    }
}

impl ValueNet for Critic {
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        Critic::new(arch, rng, device)
    }
}

impl PpoNet for Critic {
    const RECURRENT: bool = false;
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
        self.value(tensor2(
            gather(&b.obs, b.obs_dim, &mb.samples),
            b.obs_dim,
            device,
        ))
    }
    fn rollout_outputs(
        &self,
        b: &Batch,
        last: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let all = values(self.value(tensor2(b.obs.clone(), b.obs_dim, device)));
        let last = last.map_or_else(Vec::new, |l| {
            values(self.value(tensor2(l.to_vec(), b.obs_dim, device)))
        });
        (all, last, Vec::new())
    }
}

/// The windows of `mb.envs` through `net` from the states `h0` (`envs × width` rows of
/// the whole batch).
fn window_outputs(
    net: &crate::recurrent::LstmNet,
    b: &Batch,
    mb: &Minibatch,
    h0: &[f32],
    device: &Device,
) -> Tensor<2> {
    let Some(seq) = &b.sequence else {
        return Tensor::zeros([0, 1], device);
    };
    let (layers, hidden) = (net.lstm.len(), net.hidden());
    let width = LstmState::width(layers, hidden);
    let envs = mb.envs.len();
    let obs = tensor2(gather(&b.obs, b.obs_dim, &mb.samples), b.obs_dim, device)
        .reshape([seq.steps, envs, b.obs_dim]);
    let keep: Vec<f32> = mb.samples.iter().map(|&i| seq.keep[i]).collect();
    let keep = Tensor::<2>::from_data(TensorData::new(keep, [seq.steps, envs]), device);
    let state = if h0.is_empty() {
        net.zero_state(envs, device)
    } else {
        LstmState::from_flat(&gather(h0, width, &mb.envs), layers, hidden, device)
    };
    net.sequence(obs, keep, state).0
}

/// The whole rollout through `net` (no autodiff): every sample's output and, with
/// `last_obs`, the outputs for the observations after the window and the state after the
/// window (zeroed where the episode ended at its last step).
fn window_rollout_outputs(
    net: &crate::recurrent::LstmNet,
    b: &Batch,
    last_obs: Option<&[f32]>,
    h0: &[f32],
    device: &Device,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let Some(seq) = &b.sequence else {
        return (Vec::new(), Vec::new(), Vec::new());
    };
    let n = seq.num_envs;
    let state = if h0.is_empty() {
        net.zero_state(n, device)
    } else {
        LstmState::from_flat(h0, net.lstm.len(), net.hidden(), device)
    };
    let obs = tensor2(b.obs.clone(), b.obs_dim, device).reshape([seq.steps, n, b.obs_dim]);
    let keep = Tensor::<2>::from_data(TensorData::new(seq.keep.clone(), [seq.steps, n]), device);
    let (all, after) = net.sequence(obs, keep, state);
    let Some(last_obs) = last_obs else {
        return (values(all), Vec::new(), Vec::new());
    };
    let last_keep = Tensor::<2>::from_data(TensorData::new(seq.last_keep.clone(), [1, n]), device);
    let last = tensor2(last_obs.to_vec(), b.obs_dim, device).reshape([1, n, b.obs_dim]);
    let kept = LstmState {
        layers: after
            .layers
            .iter()
            .map(|(h, c)| {
                let k = last_keep.clone().reshape([n, 1]);
                (h.clone() * k.clone(), c.clone() * k)
            })
            .collect(),
    };
    let (last_out, _) = net.sequence(last, last_keep.clone(), after);
    (values(all), values(last_out), kept.to_flat())
}

impl PpoNet for RecurrentActor {
    const RECURRENT: bool = true;
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
        let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.actor_h0);
        window_outputs(&self.net, b, mb, h0, device)
    }
    fn rollout_outputs(
        &self,
        b: &Batch,
        last: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.actor_h0);
        window_rollout_outputs(&self.net, b, last, h0, device)
    }
}

impl PolicyNet for RecurrentActor {
    fn log_std(&self) -> Tensor<1> {
        self.log_std.val()
    }
    fn std(&self) -> Vec<f32> {
        RecurrentActor::std(self)
    }
    fn fresh(arch: &Architecture, init_std: f32, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        RecurrentActor::new(arch, init_std, rng, device)
    }
    fn payload(&self) -> Vec<f32> {
        self.net.payload()
    }
    fn from_payload(
        arch: &Architecture,
        payload: &[f32],
        std: &[f32],
        device: &Device,
    ) -> Option<Self> {
        RecurrentActor::from_payload(arch, payload, std, device)
    }
    fn with_output_bias(mut self, action: f32) -> Self {
        self.net.head = self.net.head.with_output_bias(action);
        self
    }
}

impl ValueNet for RecurrentCritic {
    fn fresh(arch: &Architecture, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        RecurrentCritic::new(arch, rng, device)
    }
}

impl PpoNet for RecurrentCritic {
    const RECURRENT: bool = true;
    fn outputs(&self, b: &Batch, mb: &Minibatch, device: &Device) -> Tensor<2> {
        let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.critic_h0);
        window_outputs(&self.net, b, mb, h0, device)
    }
    fn rollout_outputs(
        &self,
        b: &Batch,
        last: Option<&[f32]>,
        device: &Device,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let h0 = b.sequence.as_ref().map_or(&[][..], |s| &s.critic_h0);
        window_rollout_outputs(&self.net, b, last, h0, device)
    }
}

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
fn tensor2(data: Vec<f32>, width: usize, device: &Device) -> Tensor<2> {
    let n = data.len() / width.max(1);
    Tensor::from_data(TensorData::new(data, [n, width]), device)
}

/// Rows `idx` of a row-major `[_, width]` array.
fn gather(src: &[f32], width: usize, idx: &[usize]) -> Vec<f32> {
    let mut out = Vec::with_capacity(idx.len() * width);
    for &i in idx {
        out.extend_from_slice(&src[i * width..(i + 1) * width]);
    }
    out
}

/// Statistics of one update, averaged over its minibatches.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UpdateStats {
    /// Clipped surrogate loss.
    pub surrogate_loss: f64,
    /// Clipped value loss (before its coefficient).
    pub value_loss: f64,
    /// Policy entropy (nats).
    pub entropy: f64,
    /// KL(π_old ‖ π) measured before each step.
    pub kl: f64,
    /// Fraction of samples whose ratio left [1 − ε, 1 + ε].
    pub clip_fraction: f64,
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// Learning rate after the update.
    pub learning_rate: f64,
    /// Minibatches skipped because a loss or the gradient norm was not finite (the networks
    /// are left as they were).
    pub skipped: u32,
}

/// Sums the squares of the gradients of a module's parameters.
struct SquaredNorm<'a> {
    grads: &'a GradientsParams,
    sum: f64,
}

impl ModuleVisitor for SquaredNorm<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            self.sum += f64::from(g.square().sum().into_scalar::<f32>());
        }
    }
}

/// Scales the gradients of a module's parameters.
struct Scale<'a> {
    grads: &'a mut GradientsParams,
    factor: f32,
}

impl ModuleVisitor for Scale<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.remove::<D>(param.id) {
            self.grads.register(param.id, g.mul_scalar(self.factor));
        }
    }
}

/// Collects the gradients of a module's parameters, flattened in visiting order.
struct Flatten<'a> {
    grads: &'a GradientsParams,
    out: Vec<f32>,
}

impl ModuleVisitor for Flatten<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            self.out.extend(values(g));
        }
    }
}

/// The gradients of `module`'s parameters, flattened in visiting order.
pub fn flatten_gradients<M: Module>(module: &M, grads: &GradientsParams) -> Vec<f32> {
    let mut v = Flatten {
        grads,
        out: Vec::new(),
    };
    module.visit(&mut v);
    v.out
}

/// `grads` of `from`'s parameters, registered under the ids of `to`'s (a copy of `from`
/// with the same structure and fresh parameter ids), matched in visiting order.
pub fn transfer_gradients<M: Module>(from: &M, grads: GradientsParams, to: &M) -> GradientsParams {
    struct Take {
        grads: GradientsParams,
        taken: Vec<Option<Vec<f32>>>,
    }
    impl ModuleVisitor for Take {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let g = self.grads.remove::<D>(param.id);
            self.taken.push(g.map(values));
        }
    }
    struct Give {
        taken: std::vec::IntoIter<Option<Vec<f32>>>,
        out: GradientsParams,
    }
    impl ModuleVisitor for Give {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(Some(g)) = self.taken.next() {
                let v = param.val();
                let t = Tensor::<D>::from_data(TensorData::new(g, v.dims()), &v.device());
                self.out.register(param.id, t);
            }
        }
    }
    let mut take = Take {
        grads,
        taken: Vec::new(),
    };
    from.visit(&mut take);
    let mut give = Give {
        taken: take.taken.into_iter(),
        out: GradientsParams::new(),
    };
    to.visit(&mut give);
    give.out
}

/// `wa · a + wb · b` for every parameter of `module` (gradients of two parts of one
/// minibatch, computed apart).
pub fn weighted_sum<M: Module>(
    module: &M,
    a: GradientsParams,
    wa: f32,
    b: GradientsParams,
    wb: f32,
) -> GradientsParams {
    struct Sum {
        a: GradientsParams,
        b: GradientsParams,
        out: GradientsParams,
        wa: f32,
        wb: f32,
    }
    impl ModuleVisitor for Sum {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let g = match (self.a.remove::<D>(param.id), self.b.remove::<D>(param.id)) {
                (Some(x), Some(y)) => Some(x.mul_scalar(self.wa) + y.mul_scalar(self.wb)),
                (Some(x), None) => Some(x.mul_scalar(self.wa)),
                (None, Some(y)) => Some(y.mul_scalar(self.wb)),
                (None, None) => None,
            };
            if let Some(g) = g {
                self.out.register(param.id, g);
            }
        }
    }
    let mut v = Sum {
        a,
        b,
        out: GradientsParams::new(),
        wa,
        wb,
    };
    module.visit(&mut v);
    v.out
}

fn squared_norm<M: Module>(module: &M, grads: &GradientsParams) -> f64 {
    let mut v = SquaredNorm { grads, sum: 0.0 };
    module.visit(&mut v);
    v.sum
}

fn scale<M: Module>(module: &M, grads: &mut GradientsParams, factor: f32) {
    let mut v = Scale { grads, factor };
    module.visit(&mut v);
}

/// The learner: actor, critic, their Adam states and the adaptive learning rate. The
/// feed-forward networks by default; `Learner<RecurrentActor, RecurrentCritic>` is
/// recurrent PPO.
pub struct Learner<A = Actor, C = Critic> {
    /// The policy.
    pub actor: A,
    /// The value function.
    pub critic: C,
    /// Adam on the actor's parameters.
    pub actor_optim: ModuleOptimizer,
    /// Adam on the critic's parameters.
    pub critic_optim: ModuleOptimizer,
    /// Current learning rate.
    pub learning_rate: f64,
    /// The autodiff device.
    pub device: Device,
    /// Run the actor's and the critic's passes on two threads (default). Off, they run one
    /// after the other: the same numbers, for measuring what the second thread brings.
    pub parallel: bool,
    /// Update the actor (default). Off, only the critic learns (the critic warm-up after an
    /// imitation warm start) and the learning rate stays.
    pub train_actor: bool,
}

/// Adam as PyTorch's defaults (β 0.9/0.999, ε 1e-8), which RSL-RL uses.
pub fn adam() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(1e-8).init()
}

/// What the actor's thread returns from one minibatch.
struct ActorPass {
    grads: GradientsParams,
    surrogate: f64,
    entropy: f64,
    kl: f64,
    clip_fraction: f64,
}

/// The critic's clipped value loss on a minibatch and its gradients.
fn critic_pass<C: PpoNet>(
    critic: &C,
    b: &Batch,
    mb: &Minibatch,
    p: &PpoConfig,
    device: &Device,
) -> (GradientsParams, f64) {
    let idx = &mb.samples;
    let pick = |v: &[f32]| -> Vec<f32> { idx.iter().map(|&i| v[i]).collect() };
    let old_v = tensor2(pick(&b.old_values), 1, device);
    let ret = tensor2(pick(&b.returns), 1, device);
    let v = critic.outputs(b, mb, device);
    let v_clipped = old_v.clone() + (v.clone() - old_v).clamp(-p.clip, p.clip);
    let loss_raw = (v - ret.clone())
        .square()
        .max_pair((v_clipped - ret).square())
        .mean();
    let value_loss = f64::from(loss_raw.clone().into_scalar::<f32>());
    let loss = loss_raw.mul_scalar(p.value_coef);
    (
        GradientsParams::from_grads(loss.backward(), critic),
        value_loss,
    )
}

/// The actor's clipped surrogate and entropy bonus on a minibatch, its gradients, and the
/// KL(π_old ‖ π) before the step (RSL-RL's adaptive schedule measures it there).
fn actor_pass<A: PolicyNet>(
    actor: &A,
    b: &Batch,
    mb: &Minibatch,
    p: &PpoConfig,
    device: &Device,
) -> ActorPass {
    let idx = &mb.samples;
    let pick = |v: &[f32]| -> Vec<f32> { idx.iter().map(|&i| v[i]).collect() };
    let actions = tensor2(gather(&b.actions, ACTION_DIM, idx), ACTION_DIM, device);
    let old_lp = tensor2(pick(&b.old_log_prob), 1, device);
    let adv = tensor2(pick(&b.advantages), 1, device);
    let mean = actor.outputs(b, mb, device);
    let log_std = actor.log_std();
    let mu = values(mean.clone().inner());
    let std_now = actor.std();
    let old_mu = gather(&b.old_mean, ACTION_DIM, idx);
    let mut kl = 0.0f64;
    for (m, om) in mu
        .chunks_exact(ACTION_DIM)
        .zip(old_mu.chunks_exact(ACTION_DIM))
    {
        for k in 0..ACTION_DIM {
            let (s, so) = (f64::from(std_now[k]), f64::from(b.old_std[k]));
            let dm = f64::from(om[k] - m[k]);
            kl += (s / so).ln() + (so * so + dm * dm) / (2.0 * s * s) - 0.5;
        }
    }
    kl /= idx.len().max(1) as f64;
    let inv_std = log_std.clone().neg().exp().unsqueeze::<2>();
    let z = (actions - mean) * inv_std;
    let log_prob = (z.square().sum_dim(1).mul_scalar(-0.5)
        - log_std.clone().sum().unsqueeze::<2>())
    .sub_scalar(0.5 * LN_2PI * ACTION_DIM as f32);
    let ratio = (log_prob - old_lp).exp();
    let clipped = ratio.clone().clamp(1.0 - p.clip, 1.0 + p.clip);
    let ratio_v = values(ratio.clone().inner());
    let clip_fraction = ratio_v
        .iter()
        .filter(|r| (**r - 1.0).abs() > p.clip)
        .count() as f64
        / ratio_v.len().max(1) as f64;
    let surrogate = (adv.clone().neg() * ratio)
        .max_pair(adv.neg() * clipped)
        .mean();
    let entropy = log_std
        .sum()
        .add_scalar(0.5 * (1.0 + LN_2PI) * ACTION_DIM as f32);
    let surrogate_v = f64::from(surrogate.clone().into_scalar::<f32>());
    let entropy_v = f64::from(entropy.clone().into_scalar::<f32>());
    let loss = surrogate - entropy.mul_scalar(p.entropy_coef);
    ActorPass {
        grads: GradientsParams::from_grads(loss.backward(), actor),
        surrogate: surrogate_v,
        entropy: entropy_v,
        kl,
        clip_fraction,
    }
}

/// Recurrent PPO's learner (rows E-G).
pub type RecurrentLearner = Learner<RecurrentActor, RecurrentCritic>;

impl<A: PolicyNet, C: PpoNet> Learner<A, C> {
    /// Either network carries a state: minibatches are whole env windows.
    const RECURRENT: bool = A::RECURRENT || C::RECURRENT;

    /// A learner with fresh optimisers.
    pub fn new(actor: A, critic: C, learning_rate: f64, device: Device) -> Self {
        Self {
            actor,
            critic,
            actor_optim: adam(),
            critic_optim: adam(),
            learning_rate,
            device,
            parallel: true,
            train_actor: true,
        }
    }

    /// Turns a rollout into training samples: old log-probabilities, means and values from
    /// one batched forward pass without autodiff, time-outs bootstrapped with γ·V of the
    /// step's observation (RSL-RL), GAE returns, advantages normalised over the rollout.
    ///
    /// Recurrent networks run over the window from the rollout's stored states; the batch's
    /// [`Sequences::critic_next`] is the critic's state for the next window.
    pub fn prepare(&self, r: &Rollout, p: &PpoConfig) -> Batch {
        let actor = self.actor.valid();
        let critic = self.critic.valid();
        let device = self.device.clone().without_autodiff();
        let mut batch = Batch {
            obs_dim: r.obs_dim,
            obs: r.obs.clone(),
            actions: r.actions.clone(),
            old_log_prob: Vec::new(),
            old_mean: Vec::new(),
            old_std: [1.0; ACTION_DIM],
            old_values: Vec::new(),
            returns: Vec::new(),
            advantages: Vec::new(),
            sequence: Self::RECURRENT.then(|| Sequences::of(r)),
        };
        let (old_mean, _, _) = actor.rollout_outputs(&batch, None, &device);
        let (old_values, last_values, critic_next) =
            critic.rollout_outputs(&batch, Some(&r.last_obs), &device);
        let std = actor.std();
        let old_std: [f32; ACTION_DIM] =
            core::array::from_fn(|k| std.get(k).copied().unwrap_or(1.0));
        let old_log_prob = r
            .actions
            .chunks_exact(ACTION_DIM)
            .zip(old_mean.chunks_exact(ACTION_DIM))
            .map(|(a, m)| gaussian_log_prob(a, m, &old_std))
            .collect();
        let rewards: Vec<f32> = r
            .rewards
            .iter()
            .zip(&r.timeouts)
            .zip(&old_values)
            .map(|((&rw, &to), &v)| if to { rw + p.gamma * v } else { rw })
            .collect();
        let returns = gae(
            &rewards,
            &r.dones,
            &old_values,
            &last_values,
            p.gamma,
            p.lambda,
        );
        let mut advantages: Vec<f32> = returns
            .iter()
            .zip(&old_values)
            .map(|(g, v)| g - v)
            .collect();
        let n = advantages.len().max(1) as f64;
        let mean = advantages.iter().map(|&a| f64::from(a)).sum::<f64>() / n;
        let var = advantages
            .iter()
            .map(|&a| (f64::from(a) - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0).max(1.0);
        let sd = var.sqrt() + 1e-8;
        for a in &mut advantages {
            *a = ((f64::from(*a) - mean) / sd) as f32;
        }
        if let Some(seq) = &mut batch.sequence {
            seq.critic_next = critic_next;
        }
        Batch {
            old_log_prob,
            old_mean,
            old_std,
            old_values,
            returns,
            advantages,
            ..batch
        }
    }

    /// The gradient of the actor's loss (clipped surrogate minus the entropy bonus) over all
    /// of `batch` with the current networks, flattened: at the start of an update (ratio 1)
    /// it is the policy-gradient estimate the first Adam step follows. For measuring its
    /// signal-to-noise ratio across independent rollouts (`examples/gradient_snr.rs`).
    pub fn actor_gradient(&self, batch: &Batch, p: &PpoConfig) -> Vec<f32> {
        flatten_gradients(&self.actor, &self.actor_gradients(batch, p))
    }

    /// A learner with copies of the networks and fresh optimisers (for diagnostics that
    /// step a copy).
    pub fn clone_networks(&self) -> Self {
        Self::new(
            self.actor.clone(),
            self.critic.clone(),
            self.learning_rate,
            self.device.clone(),
        )
    }

    /// [`Learner::actor_gradient`] as burn's gradients, for an optimiser's step.
    pub fn actor_gradients(&self, batch: &Batch, p: &PpoConfig) -> GradientsParams {
        actor_pass(&self.actor, batch, &Minibatch::all(batch), p, &self.device).grads
    }

    /// `epochs × minibatches` PPO steps on `batch`, minibatches drawn from `rng`: samples
    /// for feed-forward networks, whole env windows for recurrent ones.
    pub fn update(&mut self, batch: &Batch, p: &PpoConfig, rng: &mut ChaCha8Rng) -> UpdateStats {
        let n = match &batch.sequence {
            Some(s) if Self::RECURRENT => s.num_envs,
            _ => batch.len(),
        };
        let size = n / p.minibatches.max(1);
        let mut stats = UpdateStats::default();
        let mut count = 0.0;
        let mut order: Vec<usize> = (0..n).collect();
        for _ in 0..p.epochs {
            order.shuffle(rng);
            for mb in order.chunks_exact(size.max(1)) {
                let s = self.train_minibatch(batch, mb, p);
                if s.skipped > 0 {
                    stats.skipped += s.skipped;
                    continue;
                }
                stats.surrogate_loss += s.surrogate_loss;
                stats.value_loss += s.value_loss;
                stats.entropy += s.entropy;
                stats.kl += s.kl;
                stats.clip_fraction += s.clip_fraction;
                stats.grad_norm += s.grad_norm;
                count += 1.0;
            }
        }
        if count > 0.0 {
            stats.surrogate_loss /= count;
            stats.value_loss /= count;
            stats.entropy /= count;
            stats.kl /= count;
            stats.clip_fraction /= count;
            stats.grad_norm /= count;
        }
        stats.learning_rate = self.learning_rate;
        stats
    }

    /// One minibatch: actor and critic passes (on two threads when `parallel`), the
    /// KL-adapted learning rate, the global gradient clip, both Adam steps. `idx` are the
    /// minibatch's sample indices into `b` for feed-forward networks, its envs (whole
    /// windows) for recurrent ones.
    pub fn train_minibatch(&mut self, b: &Batch, idx: &[usize], p: &PpoConfig) -> UpdateStats {
        let mb = if Self::RECURRENT {
            Minibatch::of_envs(b, idx)
        } else {
            Minibatch {
                samples: idx.to_vec(),
                envs: Vec::new(),
            }
        };
        let mb = &mb;
        let (actor, critic, device) = (&self.actor, &self.critic, &self.device);
        let critic_lr = p.critic_learning_rate.unwrap_or(self.learning_rate);
        if !self.train_actor {
            let (mut grads, value_loss) = critic_pass(critic, b, mb, p, device);
            let norm = squared_norm(critic, &grads).sqrt();
            if !(norm.is_finite() && value_loss.is_finite()) {
                return UpdateStats {
                    skipped: 1,
                    learning_rate: self.learning_rate,
                    ..UpdateStats::default()
                };
            }
            let max = f64::from(p.max_grad_norm);
            if norm > max {
                scale(critic, &mut grads, (max / (norm + 1e-6)) as f32);
            }
            self.critic = self
                .critic_optim
                .step(critic_lr, self.critic.clone(), grads);
            return UpdateStats {
                value_loss,
                grad_norm: norm,
                learning_rate: self.learning_rate,
                ..UpdateStats::default()
            };
        }
        let (actor_pass, (critic_grads, value_loss)) = if self.parallel {
            std::thread::scope(|s| {
                let critic_job = s.spawn(|| critic_pass(critic, b, mb, p, device));
                let a = actor_pass(actor, b, mb, p, device);
                let c = critic_job
                    .join()
                    .unwrap_or_else(|e| std::panic::resume_unwind(e));
                (a, c)
            })
        } else {
            (
                actor_pass(actor, b, mb, p, device),
                critic_pass(critic, b, mb, p, device),
            )
        };
        let ActorPass {
            grads: mut actor_grads,
            surrogate,
            entropy,
            kl,
            clip_fraction,
        } = actor_pass;
        let mut critic_grads = critic_grads;
        let norm = (squared_norm(&self.actor, &actor_grads)
            + squared_norm(&self.critic, &critic_grads))
        .sqrt();
        if !(norm.is_finite() && surrogate.is_finite() && value_loss.is_finite() && kl.is_finite())
        {
            // A NaN or an overflow would spread into every weight through Adam: keep the
            // networks and count the minibatch instead.
            return UpdateStats {
                skipped: 1,
                learning_rate: self.learning_rate,
                ..UpdateStats::default()
            };
        }
        if let Some(target) = p.desired_kl {
            if kl > 2.0 * target {
                self.learning_rate = (self.learning_rate / 1.5).max(p.min_learning_rate);
            } else if kl < target / 2.0 && kl > 0.0 {
                self.learning_rate = (self.learning_rate * 1.5).min(1e-2);
            }
        }
        let max = f64::from(p.max_grad_norm);
        if norm > max {
            let factor = (max / (norm + 1e-6)) as f32;
            scale(&self.actor, &mut actor_grads, factor);
            scale(&self.critic, &mut critic_grads, factor);
        }
        let lr = self.learning_rate;
        self.actor = self.actor_optim.step(lr, self.actor.clone(), actor_grads);
        let critic_lr = p.critic_learning_rate.unwrap_or(lr);
        self.critic = self
            .critic_optim
            .step(critic_lr, self.critic.clone(), critic_grads);
        UpdateStats {
            surrogate_loss: surrogate,
            value_loss,
            entropy,
            kl,
            clip_fraction,
            grad_norm: norm,
            learning_rate: lr,
            skipped: 0,
        }
    }
}
