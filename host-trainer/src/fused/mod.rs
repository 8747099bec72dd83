//! The PPO minibatch step of the actor and critic written out by hand on the CPU, for the
//! feed-forward rows (A-D) and the recurrent ones (E-G): the same math as [`crate::ppo`]'s
//! `burn` passes (forward, clipped surrogate with the Gaussian log-likelihood of a
//! log-parameterised σ, entropy bonus, clipped value loss, KL(π_old ‖ π), backward, the
//! global gradient-norm clip and Adam as [`crate::ppo::adam`] configures it), without a
//! graph: parameters, gradients and Adam's moments are flat `f32` vectors, activations live
//! in buffers allocated once, the matrix products are `matrixmultiply`'s `sgemm`
//! (AVX-512/AVX2 FMA kernels chosen at run time).
//!
//! **Layout.** A network's parameters are flat in `burn`'s visiting order: for a recurrent
//! network first per LSTM layer `weight_ih` `[in, 4H]`, `weight_hh` `[H, 4H]` and the bias;
//! then per MLP layer the weight `[in, out]` row-major (`burn`'s `Linear` layout) then the
//! bias, and for the actor log σ last. [`crate::grads::flatten_gradients`] gives `burn`'s
//! gradients in the same order, which is what the parity tests
//! (`host-trainer/tests/fused.rs`, `fused_recurrent.rs`) compare.
//!
//! **Chunks.** A feed-forward minibatch runs in chunks of [`CHUNK`] samples: each chunk's
//! forward pass, loss head and backward pass, the weight gradients accumulated over the
//! chunks. Every per-sample term of the loss depends on that sample only (the means divide
//! by the minibatch size), so this is the minibatch's gradient, with activations that stay
//! in cache. A recurrent minibatch (whole env windows) runs its LSTM layers over the whole
//! window first (`lstm`: time-major, one GEMM per step for all envs), the head and the
//! loss in chunks as above, then backpropagation through time.
//!
//! **Threads.** As in the `burn` path, the actor's and the critic's passes run on two
//! threads; the gradients are clipped together by their global norm, then each network
//! takes its Adam step. Beside a privileged MLP critic, a fraction of a recurrent actor's
//! cost, a recurrent actor's minibatch is shared instead: half its windows on a second
//! copy of the actor ([`FusedLearner::recurrent_privileged`]), the gradients summed, the
//! critic on a third thread.
//!
//! The `burn` modules stay the networks of record: [`FusedLearner::new`],
//! [`FusedLearner::recurrent`] and the privileged critic's constructors copy their
//! parameters in, [`FusedLearner::write_to`] copies
//! them back, so checkpoints, export, evaluation and the guard see `burn` modules as
//! before. Adam's moments live in [`FusedOptim`], which the learner keeps between updates
//! and the checkpoint saves.

mod kernels;
mod loss;
mod lstm;
mod net;

use crate::batch::{Batch, Minibatch};
use crate::config::PpoConfig;
use crate::model::{Actor, Critic, Mlp, PrivilegedCritic};
use crate::recurrent::{LstmNet, RecurrentActor, RecurrentCritic};
use crate::update::{UpdateStats, adapt_learning_rate};
use burn::module::Module;
use loss::{actor_pass, actor_pass_part, critic_pass, finish_actor_pass, squared};
use lstm::{LstmLayout, Recurrent, Role};
use net::{FlatNet, Input, Overwrite, Side, mlp_widths};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;

/// Samples per chunk of a minibatch (see the module doc).
pub const CHUNK: usize = 1024;

/// Adam's β₁ ([`crate::ppo::adam`]: PyTorch's default).
const BETA_1: f32 = 0.9;
/// Adam's β₂.
const BETA_2: f32 = 0.999;
/// Adam's ε.
const EPSILON: f32 = 1e-8;

/// One network's Adam state: first and second moments per parameter (flat, in the
/// network's layout) and the step count of the bias correction.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AdamMoments {
    /// First moments.
    pub moment_1: Vec<f32>,
    /// Second moments.
    pub moment_2: Vec<f32>,
    /// Steps taken.
    pub time: u32,
}

impl AdamMoments {
    /// A fresh state for `n` parameters.
    pub fn new(n: usize) -> Self {
        Self {
            moment_1: vec![0.0; n],
            moment_2: vec![0.0; n],
            time: 0,
        }
    }

    /// One Adam step of `params` along `grads` at learning rate `lr`, in `burn`'s
    /// arithmetic (burn-optim's `AdaptiveMomentum::transform`, then `param − lr·update`).
    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f64) {
        self.step_split(params, grads, 0, lr, lr);
    }

    /// [`Self::step`] with the first `split` parameters at `lr_head_of_split` and the rest
    /// at `lr` (`ppo.lstm_learning_rate_scale`: the LSTM layers lead the flat layout).
    pub fn step_split(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        split: usize,
        lr_head_of_split: f64,
        lr: f64,
    ) {
        self.time += 1;
        let t = self.time as i32;
        let bias_correction2_sqrt = (1.0 - BETA_2.powi(t)).sqrt();
        let combined = bias_correction2_sqrt / (1.0 - BETA_1.powi(t));
        let eps = EPSILON * bias_correction2_sqrt;
        let (f1, f2) = (1.0 - BETA_1, 1.0 - BETA_2);
        let (lr_first, lr) = (lr_head_of_split as f32, lr as f32);
        for (i, (((p, &g), m), v)) in params
            .iter_mut()
            .zip(grads)
            .zip(&mut self.moment_1)
            .zip(&mut self.moment_2)
            .enumerate()
        {
            let lr = if i < split { lr_first } else { lr };
            *m = *m * BETA_1 + g * f1;
            *v = *v * BETA_2 + g * g * f2;
            let update = (*m * combined) / (v.sqrt() + eps);
            *p -= update * lr;
        }
    }
}

/// Adam's state for both networks of the fused update.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FusedOptim {
    /// The actor's.
    pub actor: AdamMoments,
    /// The critic's.
    pub critic: AdamMoments,
}

impl FusedOptim {
    /// As safetensors (the checkpoint's `fused_adam.safetensors`): the four moment vectors
    /// as f32 tensors, the step counts in the metadata.
    pub fn to_safetensors(&self) -> Result<Vec<u8>, String> {
        let bytes = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let parts = [
            ("actor.moment_1", bytes(&self.actor.moment_1)),
            ("actor.moment_2", bytes(&self.actor.moment_2)),
            ("critic.moment_1", bytes(&self.critic.moment_1)),
            ("critic.moment_2", bytes(&self.critic.moment_2)),
        ];
        let views = parts
            .iter()
            .map(|(name, data)| {
                TensorView::new(Dtype::F32, vec![data.len() / 4], data)
                    .map(|v| (name.to_string(), v))
                    .map_err(|e| e.to_string())
            })
            .collect::<Result<Vec<_>, _>>()?;
        let meta = HashMap::from([
            ("actor.time".to_string(), self.actor.time.to_string()),
            ("critic.time".to_string(), self.critic.time.to_string()),
        ]);
        safetensors::tensor::serialize(views, Some(meta)).map_err(|e| e.to_string())
    }

    /// Reads [`FusedOptim::to_safetensors`]'s bytes.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, String> {
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| e.to_string())?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| e.to_string())?;
        let tensor = |name: &str| -> Result<Vec<f32>, String> {
            let view = st.tensor(name).map_err(|e| format!("{name}: {e}"))?;
            if view.dtype() != Dtype::F32 {
                return Err(format!("{name}: not f32"));
            }
            Ok(view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect())
        };
        let meta = header.metadata().clone().unwrap_or_default();
        let time = |name: &str| -> Result<u32, String> {
            meta.get(name)
                .and_then(|t| t.parse().ok())
                .ok_or_else(|| format!("{name} missing"))
        };
        Ok(Self {
            actor: AdamMoments {
                moment_1: tensor("actor.moment_1")?,
                moment_2: tensor("actor.moment_2")?,
                time: time("actor.time")?,
            },
            critic: AdamMoments {
                moment_1: tensor("critic.moment_1")?,
                moment_2: tensor("critic.moment_2")?,
                time: time("critic.time")?,
            },
        })
    }
}

/// What PPO's batch needs of the networks over a whole rollout.
#[derive(Clone, Debug, Default)]
pub struct RolloutOutputs {
    /// The actor's means, one row per sample.
    pub mean: Vec<f32>,
    /// The critic's values, one per sample.
    pub values: Vec<f32>,
    /// The critic's values of the observations after the window, one per env.
    pub last_values: Vec<f32>,
    /// Recurrent: the critic's states to start the next window from
    /// ([`crate::batch::Sequences::critic_next`]); empty for feed-forward networks.
    pub critic_next: Vec<f32>,
}

/// The actor and critic as the fused update runs them (feed-forward or recurrent).
#[derive(Clone, Debug)]
pub struct FusedLearner {
    actor: Side,
    critic: Side,
    /// A second copy of a recurrent actor whose critic is light (a privileged MLP): a
    /// minibatch's windows are then shared between the two copies on two threads, the
    /// critic on a third, instead of the actor on one thread and the critic on the other
    /// (`None`: the actor's pass runs whole on one thread).
    twin: Option<Side>,
}

impl FusedLearner {
    /// The feed-forward networks' parameters copied from `actor` and `critic`, Adam's
    /// moments from `optim` (fresh where absent or of another shape).
    pub fn new(actor: &Actor, critic: &Critic, optim: Option<FusedOptim>) -> Self {
        let (oa, oc) = split(optim);
        Self {
            actor: mlp_side(actor, &actor.mlp, oa, Input::Observation),
            critic: mlp_side(critic, &critic.mlp, oc, Input::Observation),
            twin: None,
        }
    }

    /// [`FusedLearner::new`] for the recurrent networks (rows E-G).
    pub fn recurrent(
        actor: &RecurrentActor,
        critic: &RecurrentCritic,
        optim: Option<FusedOptim>,
    ) -> Self {
        let (oa, oc) = split(optim);
        Self {
            actor: recurrent_side(actor, &actor.net, oa, Role::Actor),
            critic: recurrent_side(critic, &critic.net, oc, Role::Critic),
            twin: None,
        }
    }

    /// [`FusedLearner::new`] for a feed-forward actor beside a privileged critic.
    pub fn privileged(actor: &Actor, critic: &PrivilegedCritic, optim: Option<FusedOptim>) -> Self {
        let (oa, oc) = split(optim);
        Self {
            actor: mlp_side(actor, &actor.mlp, oa, Input::Observation),
            critic: mlp_side(critic, &critic.mlp, oc, Input::Privileged),
            twin: None,
        }
    }

    /// [`FusedLearner::new`] for a recurrent actor (rows E-G) beside a privileged critic.
    pub fn recurrent_privileged(
        actor: &RecurrentActor,
        critic: &PrivilegedCritic,
        optim: Option<FusedOptim>,
    ) -> Self {
        let (oa, oc) = split(optim);
        let actor = recurrent_side(actor, &actor.net, oa, Role::Actor);
        Self {
            twin: Some(actor.clone()),
            actor,
            critic: mlp_side(critic, &critic.mlp, oc, Input::Privileged),
        }
    }

    /// Copies the parameters back into `actor` and `critic` (ids kept).
    pub fn write_to<A: Module, C: Module>(&self, actor: &mut A, critic: &mut C) {
        fn write<'a>(values: &'a [f32]) -> Overwrite<'a> {
            Overwrite { values, at: 0 }
        }
        *actor = actor.clone().map(&mut write(&self.actor.net.params));
        *critic = critic.clone().map(&mut write(&self.critic.net.params));
    }

    /// Adam's state.
    pub fn optim(&self) -> FusedOptim {
        FusedOptim {
            actor: self.actor.adam.clone(),
            critic: self.critic.adam.clone(),
        }
    }

    /// Adam's state, the learner consumed.
    pub fn into_optim(self) -> FusedOptim {
        FusedOptim {
            actor: self.actor.adam,
            critic: self.critic.adam,
        }
    }

    /// True when either network carries a state: minibatches are whole env windows.
    pub fn is_recurrent(&self) -> bool {
        self.actor.recurrent.is_some() || self.critic.recurrent.is_some()
    }

    /// The minibatch of `idx`: its samples (feed-forward networks) or its envs' whole
    /// windows (recurrent ones).
    fn minibatch(&self, b: &Batch, idx: &[usize]) -> Minibatch {
        if self.is_recurrent() {
            Minibatch::of_envs(b, idx)
        } else {
            Minibatch {
                samples: idx.to_vec(),
                envs: Vec::new(),
            }
        }
    }

    /// What PPO's batch needs of the networks over `b`, the two on two threads: the actor's
    /// means for every sample, the critic's values for them and for the states after the
    /// window (`last_obs`, the observations after it, or the batch's privileged ones) and,
    /// for a recurrent critic, its states to start the next window from. Recurrent
    /// networks run over `b`'s windows from its stored states.
    pub fn batch_outputs(&mut self, b: &Batch, last_obs: &[f32]) -> RolloutOutputs {
        let (actor, critic) = (&mut self.actor, &mut self.critic);
        std::thread::scope(|s| {
            let critic_job = s.spawn(|| critic.batch_outputs(b, Some(last_obs)));
            let (mean, _, _) = actor.batch_outputs(b, None);
            let (values, last_values, critic_next) = critic_job
                .join()
                .unwrap_or_else(|e| std::panic::resume_unwind(e));
            RolloutOutputs {
                mean,
                values,
                last_values,
                critic_next,
            }
        })
    }

    /// The gradients of the actor's loss (surrogate − entropy bonus) and of the critic's
    /// (`value_coef` × value loss) on the samples `idx` of `b`, flat in `burn`'s order (for
    /// the parity tests; no step is taken).
    pub fn gradients(&mut self, b: &Batch, idx: &[usize], p: &PpoConfig) -> (Vec<f32>, Vec<f32>) {
        let mb = self.minibatch(b, idx);
        actor_pass(&mut self.actor, b, &mb, p);
        critic_pass(&mut self.critic, b, &mb, p);
        (self.actor.grad.clone(), self.critic.grad.clone())
    }

    /// One PPO minibatch step on the samples `idx` of `b`, as
    /// [`crate::ppo::Learner::train_minibatch`] takes it: both passes (on two threads when
    /// `parallel`), the KL-adapted `learning_rate`, the global gradient clip, both Adam steps;
    /// with `train_actor` off only the critic learns and the rate stays.
    pub fn train_minibatch(
        &mut self,
        b: &Batch,
        idx: &[usize],
        p: &PpoConfig,
        learning_rate: &mut f64,
        train_actor: bool,
        parallel: bool,
    ) -> UpdateStats {
        let skipped = |lr: f64| UpdateStats {
            skipped: 1,
            learning_rate: lr,
            ..UpdateStats::default()
        };
        let max = f64::from(p.max_grad_norm);
        let mb = &self.minibatch(b, idx);
        if !train_actor {
            let value_loss = critic_pass(&mut self.critic, b, mb, p);
            let norm = squared(&self.critic.grad).sqrt();
            if !(norm.is_finite() && value_loss.is_finite()) {
                return skipped(*learning_rate);
            }
            if norm > max {
                let factor = (max / (norm + 1e-6)) as f32;
                self.critic.grad.iter_mut().for_each(|g| *g *= factor);
            }
            let critic_lr = p.critic_learning_rate.unwrap_or(*learning_rate);
            let Side {
                net, grad, adam, ..
            } = &mut self.critic;
            adam.step(&mut net.params, grad, critic_lr);
            return UpdateStats {
                value_loss,
                grad_norm: norm,
                learning_rate: *learning_rate,
                ..UpdateStats::default()
            };
        }
        let (actor, critic) = (&mut self.actor, &mut self.critic);
        let twin = self
            .twin
            .as_mut()
            .filter(|_| parallel && mb.envs.len() >= 2);
        let (a, value_loss) = if let Some(twin) = twin {
            shared_pass(actor, twin, critic, b, mb, p)
        } else if parallel {
            std::thread::scope(|s| {
                let critic_job = s.spawn(|| critic_pass(critic, b, mb, p));
                let a = actor_pass(actor, b, mb, p);
                let c = critic_job
                    .join()
                    .unwrap_or_else(|e| std::panic::resume_unwind(e));
                (a, c)
            })
        } else {
            (actor_pass(actor, b, mb, p), critic_pass(critic, b, mb, p))
        };
        let norm = (squared(&actor.grad) + squared(&critic.grad)).sqrt();
        if !(norm.is_finite()
            && a.surrogate.is_finite()
            && value_loss.is_finite()
            && a.kl.is_finite())
        {
            return skipped(*learning_rate);
        }
        *learning_rate = adapt_learning_rate(*learning_rate, a.kl, p);
        if norm > max {
            let factor = (max / (norm + 1e-6)) as f32;
            actor.grad.iter_mut().for_each(|g| *g *= factor);
            critic.grad.iter_mut().for_each(|g| *g *= factor);
        }
        let lr = *learning_rate;
        let lstm_len = if actor.recurrent.is_some() {
            actor.net.offsets.first().map_or(0, |o| o.0)
        } else {
            0
        };
        let lstm_lr = lr * p.lstm_learning_rate_scale.unwrap_or(1.0);
        actor
            .adam
            .step_split(&mut actor.net.params, &actor.grad, lstm_len, lstm_lr, lr);
        if let Some(max_std) = p.max_std {
            let ln_max = max_std.ln();
            let ls_at = actor.net.mlp_len();
            for l in &mut actor.net.params[ls_at..] {
                *l = l.min(ln_max);
            }
        }
        let critic_lr = p.critic_learning_rate.unwrap_or(lr);
        critic
            .adam
            .step(&mut critic.net.params, &critic.grad, critic_lr);
        UpdateStats {
            surrogate_loss: a.surrogate,
            value_loss,
            entropy: a.entropy,
            kl: a.kl,
            clip_fraction: a.clip_fraction,
            grad_norm: norm,
            learning_rate: lr,
            skipped: 0,
        }
    }
}

/// The actor's pass over `mb` with its windows shared between `actor` and its copy `twin`
/// on two threads, the critic's pass on a third: the gradient the whole pass gives (summed
/// in another order), in `actor.grad`.
fn shared_pass(
    actor: &mut Side,
    twin: &mut Side,
    critic: &mut Side,
    b: &Batch,
    mb: &Minibatch,
    p: &PpoConfig,
) -> (loss::ActorStats, f64) {
    twin.net.params.copy_from_slice(&actor.net.params);
    let n = mb.samples.len();
    let (first, second) = mb.envs.split_at(mb.envs.len() / 2);
    let (first, second) = (Minibatch::of_envs(b, first), Minibatch::of_envs(b, second));
    let (sums, twin_sums, value_loss) = std::thread::scope(|s| {
        let critic_job = s.spawn(|| critic_pass(critic, b, mb, p));
        let twin_job = s.spawn(|| actor_pass_part(twin, b, &second, p, n));
        let sums = actor_pass_part(actor, b, &first, p, n);
        let twin_sums = twin_job
            .join()
            .unwrap_or_else(|e| std::panic::resume_unwind(e));
        let value_loss = critic_job
            .join()
            .unwrap_or_else(|e| std::panic::resume_unwind(e));
        (sums, twin_sums, value_loss)
    });
    for (g, t) in actor.grad.iter_mut().zip(&twin.grad) {
        *g += t;
    }
    (
        finish_actor_pass(actor, p, sums.plus(twin_sums), n),
        value_loss,
    )
}

/// Adam's moments of each network, where there are any.
fn split(optim: Option<FusedOptim>) -> (Option<AdamMoments>, Option<AdamMoments>) {
    optim.map_or((None, None), |o| (Some(o.actor), Some(o.critic)))
}

/// The fused side of the feed-forward `module` whose layers are `mlp`, reading `input`.
fn mlp_side<M: Module>(module: &M, mlp: &Mlp, adam: Option<AdamMoments>, input: Input) -> Side {
    Side::new(FlatNet::of(module, mlp_widths(mlp), 0), adam, None, input)
}

/// The fused side of `module`, whose LSTM layers and head are `net`.
fn recurrent_side<M: Module>(
    module: &M,
    net: &LstmNet,
    adam: Option<AdamMoments>,
    role: Role,
) -> Side {
    let input = net.lstm.first().map_or(0, |l| l.weight_ih.val().dims()[0]);
    let layout = LstmLayout::new(input, net.hidden(), net.lstm.len());
    let flat = FlatNet::of(module, mlp_widths(&net.head), layout.len());
    Side::new(
        flat,
        adam,
        Some(Recurrent::new(layout, role)),
        Input::Observation,
    )
}

#[cfg(test)]
mod tests {
    use super::kernels::{exp_approx, gemm, tanh_in_place, tanh_loop};
    use super::*;

    /// `step_split` steps the first parameters at their own rate and the rest exactly as
    /// `step` does (the moments of both alike).
    #[test]
    fn a_split_step_moves_the_first_parameters_at_their_rate() {
        let grads: Vec<f32> = (0..10).map(|i| (i as f32 - 4.5) * 0.1).collect();
        let (mut plain, mut split) = (vec![0.5f32; 10], vec![0.5f32; 10]);
        let (mut a, mut b) = (AdamMoments::new(10), AdamMoments::new(10));
        for _ in 0..3 {
            a.step(&mut plain, &grads, 1e-2);
            b.step_split(&mut split, &grads, 4, 1e-4, 1e-2);
        }
        assert_eq!(&plain[4..], &split[4..]);
        assert_eq!((a.moment_1, a.moment_2), (b.moment_1, b.moment_2));
        for i in 0..4 {
            let (moved_plain, moved_split) = (plain[i] - 0.5, split[i] - 0.5);
            assert!((moved_split / moved_plain - 0.01).abs() < 1e-3, "{i}");
        }
    }

    #[test]
    fn exp_and_tanh_match_std() {
        let mut worst_exp = 0.0f32;
        let mut worst_tanh = 0.0f32;
        for i in -40_000..=40_000 {
            let x = i as f32 * 0.002;
            worst_exp = worst_exp.max(((exp_approx(x) - x.exp()) / x.exp()).abs());
            let mut t = [x];
            tanh_in_place(&mut t);
            worst_tanh = worst_tanh.max((t[0] - x.tanh()).abs());
        }
        assert!(worst_exp < 5e-7, "exp relative error {worst_exp}");
        let xs: Vec<f32> = (-5000..5000).map(|i| i as f32 * 0.0031).collect();
        let mut base = xs.clone();
        tanh_loop(&mut base);
        let mut dispatched = xs;
        tanh_in_place(&mut dispatched);
        assert_eq!(base, dispatched, "the vectorised tanh gives other numbers");
        assert!(worst_tanh < 3e-7, "tanh absolute error {worst_tanh}");
    }

    #[test]
    fn fused_optim_survives_its_safetensors() {
        let m = |n: usize, x: f32| AdamMoments {
            moment_1: (0..n).map(|i| i as f32 * x).collect(),
            moment_2: (0..n).map(|i| i as f32 * x * x).collect(),
            time: n as u32,
        };
        let o = FusedOptim {
            actor: m(7, 0.5),
            critic: m(3, -2.0),
        };
        let back = FusedOptim::from_safetensors(&o.to_safetensors().unwrap()).unwrap();
        assert_eq!(back, o);
    }

    #[test]
    fn gemm_with_transposed_operands_matches_a_plain_loop() {
        let (m, k, n) = (5, 7, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        // a stored as [k, m] (transposed), b as [k, n].
        let at: Vec<f32> = (0..k * m).map(|j| a[(j % m) * k + j / m]).collect();
        let mut c = vec![1.0f32; m * n];
        gemm(m, k, n, &at, (1, m), &b, (n, 1), 1.0, &mut c);
        for i in 0..m {
            for j in 0..n {
                let want: f32 = 1.0 + (0..k).map(|l| a[i * k + l] * b[l * n + j]).sum::<f32>();
                assert!((c[i * n + j] - want).abs() < 1e-5);
            }
        }
    }
}
