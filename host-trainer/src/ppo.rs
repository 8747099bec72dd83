//! PPO (docs/DESIGN.md "Learning"; RSL-RL's `algorithms/ppo.py`): a rollout becomes a batch
//! ([`Learner::prepare`]: old log-probabilities, values, time-out bootstrap, GAE, normalised
//! advantages), then `epochs × minibatches` steps of the clipped-surrogate update with a
//! clipped value loss, an entropy bonus, the adaptive-KL learning rate, a global
//! gradient-norm clip and Adam ([`Learner::update`]). The buffer and the estimators are in
//! [`crate::batch`], the networks behind [`crate::nets`]'s traits.
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
//! **The fused update.** The minibatch steps and the batch's forward pass can run in
//! [`crate::fused`], a hand-written CPU implementation of exactly this math for the
//! feed-forward and the recurrent networks (its parity with the `burn` passes below is
//! tested in `host-trainer/tests/fused.rs` and `fused_recurrent.rs`): by default for the
//! feed-forward networks, with `[ppo] update = "fused"` for the recurrent ones
//! ([`crate::config::PpoConfig::update`]). The `burn` modules stay the networks of record.
//!
//! Departures from RSL-RL, each documented in docs/TRAINING.md: a fresh minibatch permutation
//! every epoch (RSL-RL draws one per update), a log-parameterised σ (RSL-RL's default stores σ
//! itself, which can go negative).
//!
//! **Recurrent PPO** is the same update on [`crate::recurrent`]'s networks ([`crate::nets::PpoNet`] says
//! how a network computes its outputs for a minibatch): a minibatch is a set of whole env
//! windows (RSL-RL's recurrent generator splits by env), the networks run over each window
//! from the recurrent states stored when the rollout began, with the state zeroed after an
//! episode end, and the gradients flow back through the window (truncated backpropagation
//! through time over `steps_per_env` steps).

use crate::batch::{
    Batch, CriticInputs, LN_2PI, Minibatch, Sequences, gae, gather, gaussian_log_prob, tensor2,
};
use crate::config::{PpoConfig, UpdateKind};
use crate::fused::{FusedLearner, FusedOptim, RolloutOutputs};
use crate::grads::{flatten_gradients, scale, squared_norm};
use crate::model::{Actor, Critic, PrivilegedCritic, values};
use crate::nets::{PolicyNet, PpoNet};
use crate::recurrent::{RecurrentActor, RecurrentCritic};
use crate::rollout::Rollout;
pub use crate::update::{UpdateStats, adapt_learning_rate};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use firmware_core::nn::ACTION_DIM;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

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
    /// Adam's state of the fused update ([`crate::fused`]; feed-forward networks with
    /// `[ppo] update = "fused"`), kept between updates; `None` until its first step. The
    /// `burn` optimisers above hold the state of the `burn` update instead.
    pub fused_optim: Option<FusedOptim>,
}

/// Adam as PyTorch's defaults (β 0.9/0.999, ε 1e-8), which RSL-RL uses.
pub fn adam() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(1e-8).init()
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
            fused_optim: None,
        }
    }

    /// Forgets the actor's Adam state (both updates'), as after a rejected update.
    pub fn reset_actor_optim(&mut self) {
        self.actor_optim = adam();
        if let Some(o) = &mut self.fused_optim {
            o.actor = crate::fused::AdamMoments::default();
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
            critic: (r.privileged_dim != 0).then(|| CriticInputs {
                dim: r.privileged_dim,
                obs: r.privileged.clone(),
                last_obs: r.last_privileged.clone(),
            }),
        };
        let (old_mean, old_values, last_values, critic_next) =
            match self.fused_outputs(&batch, &r.last_obs, p) {
                Some(o) => (o.mean, o.values, o.last_values, o.critic_next),
                None => {
                    let (mean, _, _) = actor.rollout_outputs(&batch, None, &device);
                    let (values, last, next) =
                        critic.rollout_outputs(&batch, Some(&r.last_obs), &device);
                    (mean, values, last, next)
                }
            };
        let std = actor.std();
        let old_std: [f32; ACTION_DIM] =
            core::array::from_fn(|k| std.get(k).copied().unwrap_or(1.0));
        let old_log_prob: Vec<f32> = r
            .actions
            .chunks_exact(ACTION_DIM)
            .zip(old_mean.chunks_exact(ACTION_DIM))
            .map(|(a, m)| gaussian_log_prob(a, m, &old_std))
            .collect();
        let flown_values = &old_values[..];
        let rewards: Vec<f32> = r
            .rewards
            .iter()
            .zip(&r.timeouts)
            .zip(flown_values)
            .map(|((&rw, &to), &v)| if to { rw + p.gamma * v } else { rw })
            .collect();
        let returns = gae(
            &rewards,
            &r.dones,
            flown_values,
            &last_values,
            p.gamma,
            p.lambda,
        );
        let mut advantages: Vec<f32> = returns
            .iter()
            .zip(flown_values)
            .map(|(g, v)| g - v)
            .collect();
        let count = advantages.len().max(1) as f64;
        let mean = advantages.iter().map(|&a| f64::from(a)).sum::<f64>() / count;
        let var = advantages
            .iter()
            .map(|&a| (f64::from(a) - mean).powi(2))
            .sum::<f64>()
            / (count - 1.0).max(1.0);
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

    /// [`Learner::prepare`]'s means and values of the batch's observations, bootstrap values
    /// of `last_obs` and the critic's next window states (recurrent networks) from the
    /// fused forward pass where the update is fused, else `None`.
    fn fused_outputs(
        &self,
        batch: &Batch,
        last_obs: &[f32],
        p: &PpoConfig,
    ) -> Option<RolloutOutputs> {
        if p.update.resolve(Self::RECURRENT) != UpdateKind::Fused {
            return None;
        }
        Some(self.fused_learner(None)?.batch_outputs(batch, last_obs))
    }

    /// The fused update's copy of these networks with Adam's state `optim` (`None` for
    /// networks it does not run).
    fn fused_learner(&self, optim: Option<FusedOptim>) -> Option<FusedLearner> {
        let this: &dyn std::any::Any = self;
        if let Some(l) = this.downcast_ref::<Learner<Actor, Critic>>() {
            return Some(FusedLearner::new(&l.actor, &l.critic, optim));
        }
        if let Some(l) = this.downcast_ref::<RecurrentLearner>() {
            return Some(FusedLearner::recurrent(&l.actor, &l.critic, optim));
        }
        if let Some(l) = this.downcast_ref::<Learner<Actor, PrivilegedCritic>>() {
            return Some(FusedLearner::privileged(&l.actor, &l.critic, optim));
        }
        let l = this.downcast_ref::<Learner<RecurrentActor, PrivilegedCritic>>()?;
        Some(FusedLearner::recurrent_privileged(
            &l.actor, &l.critic, optim,
        ))
    }

    /// The fused update's copy of these networks, Adam's state moved into it (`None`, the
    /// state kept, for networks it does not run).
    fn take_fused(&mut self) -> Option<FusedLearner> {
        let optim = self.fused_optim.take();
        let fused = self.fused_learner(optim.clone());
        if fused.is_none() {
            self.fused_optim = optim;
        }
        fused
    }

    /// Copies the fused update's parameters back into the networks and keeps its Adam
    /// state.
    fn put_fused(&mut self, fused: FusedLearner) {
        fused.write_to(&mut self.actor, &mut self.critic);
        self.fused_optim = Some(fused.into_optim());
    }

    /// The gradient of the actor's loss (clipped surrogate minus the entropy bonus) over all
    /// of `batch` with the current networks, flattened: at the start of an update (ratio 1)
    /// it is the policy-gradient estimate the first Adam step follows. For measuring its
    /// signal-to-noise ratio across independent rollouts (`examples/gradient_snr.rs`).
    pub fn actor_gradient(&self, batch: &Batch, p: &PpoConfig) -> Vec<f32> {
        flatten_gradients(&self.actor, &self.actor_gradients(batch, p))
    }

    /// The gradient of the critic's loss (`value_coef` × clipped value loss) over all of
    /// `batch`, flattened (for the fused update's parity tests).
    pub fn critic_gradient(&self, batch: &Batch, p: &PpoConfig) -> Vec<f32> {
        let (grads, _) = critic_pass(&self.critic, batch, &Minibatch::all(batch), p, &self.device);
        flatten_gradients(&self.critic, &grads)
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
    /// for feed-forward networks, whole env windows for recurrent ones. The steps are the
    /// fused update's ([`crate::fused`]) or `burn`'s as `p.update` resolves for these
    /// networks ([`crate::config::PpoConfig::update`]).
    pub fn update(&mut self, batch: &Batch, p: &PpoConfig, rng: &mut ChaCha8Rng) -> UpdateStats {
        let n = match &batch.sequence {
            Some(s) if Self::RECURRENT => s.num_envs,
            _ => batch.len(),
        };
        let fused = match p.update.resolve(Self::RECURRENT) {
            UpdateKind::Fused => self.take_fused(),
            _ => None,
        };
        if let Some(mut fused) = fused {
            // The parameters copied out of the `burn` modules once, every minibatch step
            // taken on them, the result copied back.
            let (lr, train_actor, parallel) =
                (&mut self.learning_rate, self.train_actor, self.parallel);
            let stats = epochs(n, p, rng, |mb| {
                fused.train_minibatch(batch, mb, p, lr, train_actor, parallel)
            });
            self.put_fused(fused);
            return UpdateStats {
                learning_rate: self.learning_rate,
                ..stats
            };
        }
        let stats = epochs(n, p, rng, |mb| self.train_minibatch(batch, mb, p));
        UpdateStats {
            learning_rate: self.learning_rate,
            ..stats
        }
    }

    /// [`Learner::train_minibatch`] in the fused update (copying the parameters and Adam's
    /// state in and out around the one step: for tests and benchmarks; [`Learner::update`]
    /// copies once per update); `burn`'s step for networks the fused update does not run.
    pub fn train_minibatch_fused(
        &mut self,
        b: &Batch,
        idx: &[usize],
        p: &PpoConfig,
    ) -> UpdateStats {
        let Some(mut fused) = self.take_fused() else {
            return self.train_minibatch(b, idx, p);
        };
        let s = fused.train_minibatch(
            b,
            idx,
            p,
            &mut self.learning_rate,
            self.train_actor,
            self.parallel,
        );
        self.put_fused(fused);
        s
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
        self.learning_rate = adapt_learning_rate(self.learning_rate, kl, p);
        let max = f64::from(p.max_grad_norm);
        if norm > max {
            let factor = (max / (norm + 1e-6)) as f32;
            scale(&self.actor, &mut actor_grads, factor);
            scale(&self.critic, &mut critic_grads, factor);
        }
        let lr = self.learning_rate;
        let actor = self.actor_optim.step(lr, self.actor.clone(), actor_grads);
        self.actor = match p.max_std {
            Some(max_std) => actor.with_std_at_most(max_std),
            None => actor,
        };
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

/// `epochs × minibatches` calls of `step` on minibatches of `0..n` drawn from `rng` (a fresh
/// permutation every epoch), their statistics averaged over the steps not skipped (the
/// learning rate left to the caller).
fn epochs(
    n: usize,
    p: &PpoConfig,
    rng: &mut ChaCha8Rng,
    mut step: impl FnMut(&[usize]) -> UpdateStats,
) -> UpdateStats {
    let size = n / p.minibatches.max(1);
    let mut stats = UpdateStats::default();
    let mut count = 0.0;
    let mut order: Vec<usize> = (0..n).collect();
    for _ in 0..p.epochs {
        order.shuffle(rng);
        for mb in order.chunks_exact(size.max(1)) {
            let s = step(mb);
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
    stats
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
    let z = (actions - mean.clone()) * inv_std;
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
