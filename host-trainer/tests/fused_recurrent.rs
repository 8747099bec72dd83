//! The fused recurrent update ([`host_trainer::fused`] with LSTM layers) against `burn`'s
//! autodiff on rows E, F and G: every parameter's gradient over windows that start from
//! stored non-zero states and hold episode ends, the batch `prepare` builds (means, values,
//! bootstrap, the critic's next states), one minibatch step and a whole update.

use burn::tensor::Device;
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::batch::Batch;
use host_trainer::config::{PpoConfig, UpdateKind};
use host_trainer::fused::FusedLearner;
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::RecurrentLearner;
use host_trainer::recurrent::{LstmState, RecurrentActor, RecurrentCritic};
use host_trainer::rng::init_rng;
use host_trainer::rollout::Rollout;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod fused_common;
use fused_common::{
    assert_networks_close, assert_prepared_close, assert_stats_close, clip_crossing_batch, flat,
    params, relative_error,
};

const ROWS: [TableRow; 3] = [TableRow::E, TableRow::F, TableRow::G];

fn learner(row: TableRow, seed: u64) -> RecurrentLearner {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(row);
    let mut rng = init_rng(seed);
    let actor = RecurrentActor::fresh(&arch, 0.6, &mut rng, &device);
    let critic = RecurrentCritic::fresh(&arch, &mut rng, &device);
    RecurrentLearner::new(actor, critic, 1e-4, device)
}

/// A random rollout of `envs × steps` with episode ends inside the windows (about one in
/// twelve steps) and non-zero starting states for both networks.
fn rollout(l: &RecurrentLearner, row: TableRow, envs: usize, steps: usize, seed: u64) -> Rollout {
    let obs_dim = usize::from(Architecture::table1(row).obs_dim);
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let n = envs * steps;
    let width = LstmState::width(l.actor.net.lstm.len(), l.actor.net.hidden());
    let mut f = |k: usize, a: f32| -> Vec<f32> { (0..k).map(|_| r.random_range(-a..a)).collect() };
    let mut out = Rollout::new(envs, obs_dim);
    out.obs = f(n * obs_dim, 1.0);
    out.actions = f(n * 4, 1.0);
    out.rewards = f(n, 0.1);
    out.last_obs = f(envs * obs_dim, 1.0);
    out.actor_h0 = f(envs * width, 0.5);
    out.critic_h0 = f(envs * width, 0.5);
    let ends = f(n, 1.0);
    out.dones = ends.iter().map(|u| *u > 0.83).collect();
    out.timeouts = ends.iter().map(|u| *u > 0.92).collect();
    out
}

fn batch(l: &RecurrentLearner, r: &Rollout, seed: u64) -> Batch {
    clip_crossing_batch(l, r, seed)
}

/// Per-tensor spans of a recurrent network's flat parameters in `burn`'s order.
fn tensors(l: &RecurrentLearner, actor: bool) -> Vec<(String, usize, usize)> {
    let net = if actor { &l.actor.net } else { &l.critic.net };
    let mut v = Vec::new();
    let mut at = 0;
    let mut push = |name: String, n: usize| {
        v.push((name, at, at + n));
        at += n;
    };
    for (k, cell) in net.lstm.iter().enumerate() {
        let [i, g] = cell.weight_ih.val().dims();
        let [h, _] = cell.weight_hh.val().dims();
        push(format!("lstm {k} weight_ih"), i * g);
        push(format!("lstm {k} weight_hh"), h * g);
        push(format!("lstm {k} bias"), g);
    }
    for (k, layer) in net.head.layers.iter().enumerate() {
        let [i, o] = layer.weight.val().dims();
        push(format!("head {k} weight"), i * o);
        push(format!("head {k} bias"), o);
    }
    if actor {
        push("log_std".into(), 4);
    }
    v
}

#[test]
fn fused_recurrent_gradients_equal_burns() {
    for (k, row) in ROWS.into_iter().enumerate() {
        let l = learner(row, 3 + k as u64);
        let r = rollout(&l, row, 9, 14, 1 + k as u64);
        assert!(r.dones.iter().filter(|d| **d).count() > 5);
        let b = batch(&l, &r, 2);
        let p = params(UpdateKind::Fused);
        let burn_actor = l.actor_gradient(&b, &p);
        let burn_critic = l.critic_gradient(&b, &p);
        let envs: Vec<usize> = (0..9).collect();
        let (actor, critic) =
            FusedLearner::recurrent(&l.actor, &l.critic, None).gradients(&b, &envs, &p);
        for (name, fused, burn, is_actor) in [
            ("actor", &actor, &burn_actor, true),
            ("critic", &critic, &burn_critic, false),
        ] {
            assert_eq!(fused.len(), burn.len(), "{row:?} {name}");
            for (t, from, to) in tensors(&l, is_actor) {
                let e = relative_error(&fused[from..to], &burn[from..to]);
                println!("{row:?} {name} {t}: relative error {e:e}");
                assert!(e <= 1e-5, "{row:?} {name} {t}: relative error {e:e}");
                assert!(
                    burn[from..to].iter().any(|g| *g != 0.0),
                    "{row:?} {name} {t}: zero"
                );
            }
        }
    }
}

/// `prepare` with the fused forward pass builds the batch `burn`'s builds: old means and
/// values, the bootstrap after the window, returns, advantages and the critic's states for
/// the next window (zeroed where an episode ended at the window's last step).
#[test]
fn a_fused_recurrent_prepare_equals_burns() {
    for (k, row) in ROWS.into_iter().enumerate() {
        let l = learner(row, 20 + k as u64);
        // More envs than one group of the fused pass, the last group partial.
        let mut r = rollout(&l, row, 70, 9, 5 + k as u64);
        // Some envs end their episode at the window's last step.
        for e in 0..70 {
            r.dones[8 * 70 + e] = e % 5 == 0;
        }
        let fused = l.prepare(&r, &params(UpdateKind::Fused));
        let burn = l.prepare(&r, &params(UpdateKind::Burn));
        assert_prepared_close(&fused, &burn, &format!("{row:?}"));
        let (fs, bs) = (fused.sequence.unwrap(), burn.sequence.unwrap());
        assert!(bs.critic_next.iter().any(|v| *v != 0.0));
        let e = relative_error(&fs.critic_next, &bs.critic_next);
        assert!(e < 1e-5, "{row:?} critic_next: relative error {e:e}");
        let zeroed = (0..70).filter(|e| e % 5 == 0);
        let width = fs.critic_next.len() / 70;
        for e in zeroed {
            assert!(
                fs.critic_next[e * width..(e + 1) * width]
                    .iter()
                    .all(|v| *v == 0.0)
            );
        }
    }
}

/// One minibatch of windows (half the envs), with the global clip active and inactive, the
/// KL adapting the rate: the same parameters and statistics as `burn`'s step.
#[test]
fn a_fused_recurrent_minibatch_step_equals_burns() {
    for max_grad_norm in [0.05, 100.0] {
        let (mut fused, mut burn) = (learner(TableRow::G, 7), learner(TableRow::G, 7));
        let r = rollout(&burn, TableRow::G, 10, 12, 3);
        let b = batch(&burn, &r, 4);
        let p = PpoConfig {
            max_grad_norm,
            ..params(UpdateKind::Fused)
        };
        let envs = [1, 4, 5, 8, 9];
        let sb = burn.train_minibatch(&b, &envs, &p);
        let sf = fused.train_minibatch_fused(&b, &envs, &p);
        assert!(sb.clip_fraction > 0.05, "{sb:?}");
        assert_eq!(sb.grad_norm > max_grad_norm.into(), max_grad_norm < 1.0);
        assert_stats_close(&sf, &sb);
        assert_networks_close(&fused, &burn, 1e-5);
        assert_ne!(flat(&fused.actor), flat(&learner(TableRow::G, 7).actor));
    }
}

/// A whole update (2 epochs × 2 minibatches of windows, the same shuffles) through
/// `Learner::update` lands where `burn`'s does, and keeps Adam's state.
#[test]
fn a_fused_recurrent_update_follows_burns() {
    let (mut fused, mut burn) = (learner(TableRow::G, 11), learner(TableRow::G, 11));
    let r = rollout(&burn, TableRow::G, 8, 10, 6);
    let b = batch(&burn, &r, 7);
    let sf = fused.update(
        &b,
        &params(UpdateKind::Fused),
        &mut ChaCha8Rng::seed_from_u64(1),
    );
    let sb = burn.update(
        &b,
        &params(UpdateKind::Burn),
        &mut ChaCha8Rng::seed_from_u64(1),
    );
    assert!(burn.fused_optim.is_none());
    let optim = fused.fused_optim.as_ref().expect("Adam's state kept");
    assert_eq!((optim.actor.time, optim.critic.time), (4, 4));
    assert_stats_close(&sf, &sb);
    assert_networks_close(&fused, &burn, 2e-5);
}
