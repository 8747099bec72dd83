//! The privileged critic (`[ppo] critic = "privileged-mlp"`): an MLP on the env's
//! privileged state beside a recurrent (row G) or feed-forward (row A) actor. The fused
//! update against `burn`'s autodiff (the batch `prepare` builds, every gradient, one
//! minibatch step, its windows shared between two copies of the actor or not), and that
//! the critic reads the privileged state, not the observation.

use burn::tensor::Device;
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::config::{PpoConfig, UpdateKind};
use host_trainer::fused::FusedLearner;
use host_trainer::model::{Actor, PrivilegedCritic};
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::Learner;
use host_trainer::recurrent::{LstmState, RecurrentActor};
use host_trainer::rng::init_rng;
use host_trainer::rollout::Rollout;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod fused_common;
use fused_common::{
    assert_networks_close, assert_prepared_close, assert_stats_close, clip_crossing_batch, flat,
    params, relative_error,
};

fn learner<A: PolicyNet>(row: TableRow, seed: u64) -> Learner<A, PrivilegedCritic> {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(row);
    let mut rng = init_rng(seed);
    let actor = A::fresh(&arch, 0.6, &mut rng, &device);
    let critic = PrivilegedCritic::fresh(&arch, &mut rng, &device);
    Learner::new(actor, critic, 1e-4, device)
}

/// A random rollout of `envs × steps` with episode ends inside the windows, non-zero
/// starting states for a recurrent actor, and privileged states.
fn rollout(row: TableRow, envs: usize, steps: usize, seed: u64) -> Rollout {
    let arch = Architecture::table1(row);
    let obs_dim = usize::from(arch.obs_dim);
    let pdim = PrivilegedCritic::input_dim(&arch);
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let n = envs * steps;
    let mut f = |k: usize, a: f32| -> Vec<f32> { (0..k).map(|_| r.random_range(-a..a)).collect() };
    let mut out = Rollout::new(envs, obs_dim);
    out.obs = f(n * obs_dim, 1.0);
    out.actions = f(n * 4, 1.0);
    out.rewards = f(n, 0.1);
    out.last_obs = f(envs * obs_dim, 1.0);
    if arch.is_recurrent() {
        let width = LstmState::width(usize::from(arch.lstm_layers), 128);
        out.actor_h0 = f(envs * width, 0.5);
    }
    out.privileged_dim = pdim;
    out.privileged = f(n * pdim, 1.0);
    out.last_privileged = f(envs * pdim, 1.0);
    let ends = f(n, 1.0);
    out.dones = ends.iter().map(|u| *u > 0.83).collect();
    out.timeouts = ends.iter().map(|u| *u > 0.92).collect();
    out
}

/// Row G: `prepare`'s fused pass builds `burn`'s batch (no critic state to carry), and
/// every gradient of both networks is `burn`'s to 1e-5.
#[test]
fn a_privileged_critic_beside_a_recurrent_actor_has_burns_gradients() {
    let l = learner::<RecurrentActor>(TableRow::G, 3);
    let r = rollout(TableRow::G, 9, 14, 1);
    let fused = l.prepare(&r, &params(UpdateKind::Fused));
    let burn = l.prepare(&r, &params(UpdateKind::Burn));
    assert_prepared_close(&fused, &burn, "row G");
    assert!(burn.sequence.as_ref().unwrap().critic_next.is_empty());
    let b = clip_crossing_batch(&l, &r, 2);
    let p = params(UpdateKind::Fused);
    let burn_actor = l.actor_gradient(&b, &p);
    let burn_critic = l.critic_gradient(&b, &p);
    let envs: Vec<usize> = (0..9).collect();
    let (actor, critic) =
        FusedLearner::recurrent_privileged(&l.actor, &l.critic, None).gradients(&b, &envs, &p);
    for (name, fused, burn) in [
        ("actor", &actor, &burn_actor),
        ("critic", &critic, &burn_critic),
    ] {
        assert_eq!(fused.len(), burn.len(), "{name}");
        let e = relative_error(fused, burn);
        assert!(e <= 1e-5, "{name}: relative error {e:e}");
        assert!(burn.iter().filter(|g| **g != 0.0).count() > burn.len() / 2);
    }
}

/// One minibatch step of whole windows (row G) and of samples (row A), the clip active and
/// not: the same networks and statistics as `burn`'s step.
#[test]
fn a_fused_minibatch_step_with_a_privileged_critic_equals_burns() {
    for max_grad_norm in [0.05, 100.0] {
        let p = PpoConfig {
            max_grad_norm,
            ..params(UpdateKind::Fused)
        };
        let (mut fused, mut burn) = (
            learner::<RecurrentActor>(TableRow::G, 7),
            learner::<RecurrentActor>(TableRow::G, 7),
        );
        let r = rollout(TableRow::G, 10, 12, 3);
        let b = clip_crossing_batch(&burn, &r, 4);
        let envs = [1, 4, 5, 8, 9];
        let sb = burn.train_minibatch(&b, &envs, &p);
        // The windows shared between two copies of the actor on two threads (the default)
        // and the whole pass on one.
        let sf = fused.train_minibatch_fused(&b, &envs, &p);
        let mut serial = learner::<RecurrentActor>(TableRow::G, 7);
        serial.parallel = false;
        let ss = serial.train_minibatch_fused(&b, &envs, &p);
        assert_stats_close(&sf, &sb);
        assert_stats_close(&ss, &sb);
        assert_networks_close(&fused, &burn, 1e-5);
        assert_networks_close(&fused, &serial, 1e-6);
        assert_ne!(
            flat(&fused.critic),
            flat(&learner::<RecurrentActor>(TableRow::G, 7).critic)
        );

        let (mut fused, mut burn) = (
            learner::<Actor>(TableRow::A, 8),
            learner::<Actor>(TableRow::A, 8),
        );
        let r = rollout(TableRow::A, 16, 8, 5);
        let b = clip_crossing_batch(&burn, &r, 6);
        let samples: Vec<usize> = (0..b.len()).step_by(3).collect();
        let sb = burn.train_minibatch(&b, &samples, &p);
        let sf = fused.train_minibatch_fused(&b, &samples, &p);
        assert_stats_close(&sf, &sb);
        assert_networks_close(&fused, &burn, 1e-5);
    }
}

/// The critic's values follow the privileged states and ignore the observations, in both
/// updates' batches.
#[test]
fn a_privileged_critic_reads_the_privileged_state() {
    let l = learner::<RecurrentActor>(TableRow::G, 11);
    let r = rollout(TableRow::G, 6, 10, 7);
    let mut other_obs = r.clone();
    other_obs.obs.iter_mut().for_each(|o| *o = -*o);
    other_obs.last_obs.iter_mut().for_each(|o| *o = -*o);
    let mut other_state = r.clone();
    other_state.privileged.iter_mut().for_each(|o| *o = -*o);
    for update in [UpdateKind::Fused, UpdateKind::Burn] {
        let p = params(update);
        let base = l.prepare(&r, &p);
        assert_eq!(
            l.prepare(&other_obs, &p).old_values,
            base.old_values,
            "{update:?}"
        );
        assert_ne!(
            l.prepare(&other_state, &p).old_values,
            base.old_values,
            "{update:?}"
        );
    }
}
