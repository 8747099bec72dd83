//! The fused PPO update ([`host_trainer::fused`]) against `burn`'s on the same networks and
//! batch: every parameter's gradient, one whole minibatch step (parameters and statistics),
//! Adam's bias-corrected steps, and a whole update through `Learner::update`.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::batch::{Batch, gaussian_log_prob};
use host_trainer::config::{PpoConfig, UpdateKind};
use host_trainer::fused::{AdamMoments, FusedLearner};
use host_trainer::model::{Actor, Critic, values};
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::{Learner, adam};
use host_trainer::rng::init_rng;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod fused_common;
use fused_common::{
    assert_networks_close, assert_prepared_close, assert_stats_close, flat, relative_error,
};

fn learner(seed: u64) -> Learner {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(seed);
    let actor = Actor::fresh(&arch, 0.7, &mut rng, &device);
    let critic = Critic::fresh(&arch, &mut rng, &device);
    Learner::new(actor, critic, 1e-4, device)
}

fn params() -> PpoConfig {
    fused_common::params(UpdateKind::Fused)
}

/// A batch of `n` random samples whose old log-probabilities and values are the networks'
/// own, perturbed so that a share of the ratios and of the values starts outside the clip
/// range (both branches of both clipped losses are exercised).
fn batch(l: &Learner, n: usize, seed: u64) -> Batch {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let mut f = |k: usize, a: f32| -> Vec<f32> { (0..k).map(|_| r.random_range(-a..a)).collect() };
    let obs = f(n * 17, 1.0);
    let noise = f(n * 4, 1.0);
    let lp_noise = f(n, 0.5);
    let v_noise = f(n, 0.5);
    let returns = f(n, 1.0);
    let advantages = f(n, 2.0);
    let device = &l.device;
    let x = || Tensor::from_data(TensorData::new(obs.clone(), [n, 17]), device);
    let mean = values(l.actor.mean(x()));
    let value = values(l.critic.value(x()));
    let std_v = l.actor.std();
    let std: [f32; 4] = core::array::from_fn(|k| std_v[k]);
    let actions: Vec<f32> = mean
        .iter()
        .zip(&noise)
        .enumerate()
        .map(|(i, (m, e))| m + e * std[i % 4])
        .collect();
    let old_log_prob = actions
        .chunks_exact(4)
        .zip(mean.chunks_exact(4))
        .zip(&lp_noise)
        .map(|((a, m), e)| gaussian_log_prob(a, m, &std) + e)
        .collect();
    let old_mean = mean.iter().zip(&noise).map(|(m, e)| m + 0.1 * e).collect();
    Batch {
        obs_dim: 17,
        obs,
        actions,
        old_log_prob,
        old_mean,
        old_std: std.map(|s| s * 1.1),
        old_values: value.iter().zip(&v_noise).map(|(v, e)| v + e).collect(),
        returns,
        advantages,
        sequence: None,
        critic: None,
    }
}

/// The offsets of a flat 17→128→128→k MLP's tensors, with their names.
fn tensors(out: usize, log_std: bool) -> Vec<(String, usize, usize)> {
    let mut v = Vec::new();
    let mut at = 0;
    for (l, (i, o)) in [(17, 128), (128, 128), (128, out)].into_iter().enumerate() {
        v.push((format!("layer {l} weight"), at, at + i * o));
        at += i * o;
        v.push((format!("layer {l} bias"), at, at + o));
        at += o;
    }
    if log_std {
        v.push(("log_std".into(), at, at + 4));
    }
    v
}

#[test]
fn fused_gradients_equal_burns() {
    let l = learner(3);
    let b = batch(&l, 3000, 1);
    let p = params();
    let idx: Vec<usize> = (0..b.len()).collect();
    let burn_actor = l.actor_gradient(&b, &p);
    let burn_critic = l.critic_gradient(&b, &p);
    let (actor, critic) = FusedLearner::new(&l.actor, &l.critic, None).gradients(&b, &idx, &p);
    for (name, net, fused, burn, log_std) in [
        ("actor", 4, &actor, &burn_actor, true),
        ("critic", 1, &critic, &burn_critic, false),
    ] {
        assert_eq!(fused.len(), burn.len(), "{name}");
        for (t, from, to) in tensors(net, log_std) {
            let e = relative_error(&fused[from..to], &burn[from..to]);
            assert!(e < 1e-4, "{name} {t}: relative error {e}");
            assert!(burn[from..to].iter().any(|g| *g != 0.0), "{name} {t}: zero");
        }
    }
}

/// One minibatch step from identical networks, with the global clip active (and once with
/// it inactive), the KL adapting the rate: the same parameters and statistics.
#[test]
fn a_fused_minibatch_step_equals_burns() {
    for max_grad_norm in [0.05, 100.0] {
        let (mut fused, mut burn) = (learner(5), learner(5));
        let b = batch(&burn, 4096, 2);
        let p = PpoConfig {
            max_grad_norm,
            ..params()
        };
        let idx: Vec<usize> = (0..b.len()).step_by(2).collect();
        let sb = burn.train_minibatch(&b, &idx, &p);
        let sf = fused.train_minibatch_fused(&b, &idx, &p);
        assert!(sb.clip_fraction > 0.05, "{sb:?}");
        assert_eq!(sb.grad_norm > max_grad_norm.into(), max_grad_norm < 1.0);
        assert_ne!(sb.learning_rate, 1e-4, "the KL moved the rate");
        assert_stats_close(&sf, &sb);
        assert_networks_close(&fused, &burn, 1e-5);
        assert_ne!(flat(&fused.actor), flat(&learner(5).actor));
    }
}

/// Adam's bias correction and moments over several steps with changing gradients and
/// learning rates: the fused Adam equals `burn`'s (`ppo::adam()`).
#[test]
fn fused_adam_equals_burns_over_steps() {
    let l = learner(7);
    let mut module = l.critic.clone();
    let mut optim = adam();
    let mut params = flat(&module);
    let mut moments = AdamMoments::new(params.len());
    let mut r = ChaCha8Rng::seed_from_u64(3);
    for (step, lr) in [1e-3, 1e-3, 5e-4, 2e-3, 1e-3, 1e-4].into_iter().enumerate() {
        let scale = 10f32.powi(step as i32 - 3);
        let g: Vec<f32> = (0..params.len())
            .map(|_| r.random_range(-1.0..1.0) * scale)
            .collect();
        // The same gradients as burn's, registered parameter by parameter.
        struct Register<'a> {
            g: &'a [f32],
            at: usize,
            out: GradientsParams,
        }
        impl ModuleVisitor for Register<'_> {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                let v = param.val();
                let n: usize = v.dims().iter().product();
                let data = TensorData::new(self.g[self.at..self.at + n].to_vec(), v.dims());
                self.at += n;
                let t = Tensor::<D>::from_data(data, &v.device().without_autodiff());
                self.out.register(param.id, t);
            }
        }
        let mut reg = Register {
            g: &g,
            at: 0,
            out: GradientsParams::new(),
        };
        module.visit(&mut reg);
        module = optim.step(lr, module, reg.out);
        moments.step(&mut params, &g, lr);
        let e = relative_error(&params, &flat(&module));
        assert!(e < 1e-6, "step {step}: relative error {e}");
        let moved = params
            .iter()
            .zip(&flat(&l.critic))
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(moved > 0.0);
    }
}

/// A whole update (2 epochs × 2 minibatches, the same shuffles) through `Learner::update`:
/// `update = "fused"` lands where `"burn"` does and keeps Adam's state for the next update.
#[test]
fn a_fused_update_follows_burns() {
    let (mut fused, mut burn) = (learner(11), learner(11));
    let b = batch(&burn, 4096, 4);
    let pf = params();
    let pb = PpoConfig {
        update: UpdateKind::Burn,
        ..params()
    };
    let sf = fused.update(&b, &pf, &mut ChaCha8Rng::seed_from_u64(1));
    let sb = burn.update(&b, &pb, &mut ChaCha8Rng::seed_from_u64(1));
    assert!(burn.fused_optim.is_none());
    let optim = fused
        .fused_optim
        .as_ref()
        .expect("the fused update keeps Adam's state");
    assert_eq!((optim.actor.time, optim.critic.time), (4, 4));
    assert_stats_close(&sf, &sb);
    assert_networks_close(&fused, &burn, 2e-5);
}

/// The batch built with the fused forward pass (`update = "fused"`) equals the one built
/// with `burn`'s: old means and values, bootstrapped returns, normalised advantages.
#[test]
fn a_fused_prepare_equals_burns() {
    let l = learner(13);
    let (envs, steps) = (300, 7);
    let mut r = ChaCha8Rng::seed_from_u64(6);
    let mut rollout = host_trainer::rollout::Rollout::new(envs, 17);
    let n = envs * steps;
    rollout.obs = (0..n * 17).map(|_| r.random_range(-1.0..1.0)).collect();
    rollout.actions = (0..n * 4).map(|_| r.random_range(-1.0..1.0)).collect();
    rollout.rewards = (0..n).map(|_| r.random_range(-0.1..0.1)).collect();
    rollout.dones = (0..n).map(|_| r.random_range(0.0..1.0) < 0.05).collect();
    rollout.timeouts = rollout
        .dones
        .iter()
        .map(|&d| d && r.random_range(0.0..1.0) < 0.5)
        .collect();
    rollout.last_obs = (0..envs * 17).map(|_| r.random_range(-1.0..1.0)).collect();
    let fused = l.prepare(&rollout, &params());
    let burn = l.prepare(
        &rollout,
        &PpoConfig {
            update: UpdateKind::Burn,
            ..params()
        },
    );
    assert_prepared_close(&fused, &burn, "row A");
}

/// With the actor frozen (the critic's warm-up after a warm start) only the critic steps,
/// as in `burn`'s update, and the learning rate stays.
#[test]
fn a_fused_critic_only_step_equals_burns() {
    let (mut fused, mut burn) = (learner(17), learner(17));
    fused.train_actor = false;
    burn.train_actor = false;
    let b = batch(&burn, 2048, 8);
    let p = params();
    let idx: Vec<usize> = (0..b.len()).collect();
    for _ in 0..3 {
        let sb = burn.train_minibatch(&b, &idx, &p);
        let sf = fused.train_minibatch_fused(&b, &idx, &p);
        assert_stats_close(&sf, &sb);
        assert_eq!(sf.learning_rate, 1e-4);
    }
    assert_eq!(flat(&fused.actor), flat(&learner(17).actor));
    assert_networks_close(&fused, &burn, 1e-5);
    assert_ne!(flat(&fused.critic), flat(&learner(17).critic));
}
