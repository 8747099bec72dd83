//! PPO's direction and its pieces: an update raises the probability of actions with positive
//! advantages and lowers it for negative ones; GAE against a hand computation; the Gaussian
//! log-density against the closed form.

use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::batch::{Batch, gae, gaussian_log_prob};
use host_trainer::config::{CriticKind, PpoConfig, UpdateKind};
use host_trainer::model::{Actor, Critic, values};
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::Learner;
use host_trainer::rng::init_rng;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn params() -> PpoConfig {
    PpoConfig {
        steps_per_env: 1,
        epochs: 1,
        minibatches: 1,
        clip: 0.2,
        gamma: 0.99,
        lambda: 0.95,
        value_coef: 1.0,
        entropy_coef: 0.0,
        learning_rate: 1e-3,
        desired_kl: None,
        max_grad_norm: 1.0,
        min_learning_rate: 1e-5,
        max_learning_rate: 1e-2,
        max_std: None,
        max_std_decay: None,
        critic_learning_rate: None,
        lstm_learning_rate_scale: None,
        init_std: 0.5,
        init_hover: false,
        update: UpdateKind::Fused,
        critic: CriticKind::ActorShaped,
    }
}

#[test]
fn an_update_moves_the_mean_toward_positive_advantages() {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(4);
    let actor = Actor::fresh(&arch, 0.5, &mut rng, &device);
    let critic = Critic::fresh(&arch, &mut rng, &device);
    let mut learner = Learner::new(actor, critic, 1e-3, device.clone());
    let mut r = ChaCha8Rng::seed_from_u64(2);
    let n = 2048;
    let obs: Vec<f32> = (0..n * 17).map(|_| r.random_range(-1.0..1.0)).collect();
    let mean = values(learner.actor.mean(Tensor::from_data(
        TensorData::new(obs.clone(), [n, 17]),
        &device,
    )));
    let std = [0.5f32; 4];
    // Motor 0 sampled around the mean; the advantage is the sign of its deviation: actions
    // above the mean were good.
    let mut actions = mean.clone();
    let mut advantages = Vec::new();
    for i in 0..n {
        let d: f32 = r.random_range(-0.5..0.5);
        actions[i * 4] += d;
        advantages.push(d.signum());
    }
    let old_log_prob = actions
        .chunks_exact(4)
        .zip(mean.chunks_exact(4))
        .map(|(a, m)| gaussian_log_prob(a, m, &std))
        .collect();
    let batch = Batch {
        obs_dim: 17,
        obs: obs.clone(),
        actions,
        old_log_prob,
        old_mean: mean.clone(),
        old_std: std,
        old_values: vec![0.0; n],
        returns: vec![0.0; n],
        advantages,
        sequence: None,
        critic: None,
    };
    // The diagnostic gradient (examples/gradient_snr.rs): one value per actor parameter
    // (the blob's weights and the four log σ), and a plain step along it moves motor 0 the
    // way the update does.
    let g = learner.actor_gradient(&batch, &params());
    assert_eq!(g.len(), learner.actor.payload().len() + 4);
    assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| *v != 0.0));
    let stepped = burn::optim::SgdConfig::new().init().step(
        1e-2,
        learner.actor.clone(),
        learner.actor_gradients(&batch, &params()),
    );
    let moved = values(stepped.mean(Tensor::from_data(
        TensorData::new(obs.clone(), [n, 17]),
        &device,
    )));
    let sgd_shift = (0..n).map(|i| moved[i * 4] - mean[i * 4]).sum::<f32>() / n as f32;
    assert!(
        sgd_shift > 0.0,
        "a gradient step moved motor 0 by {sgd_shift}"
    );

    let idx: Vec<usize> = (0..n).collect();
    for _ in 0..5 {
        learner.train_minibatch(&batch, &idx, &params());
    }
    let after = values(
        learner
            .actor
            .mean(Tensor::from_data(TensorData::new(obs, [n, 17]), &device)),
    );
    let shift = |k: usize| -> f32 {
        (0..n)
            .map(|i| after[i * 4 + k] - mean[i * 4 + k])
            .sum::<f32>()
            / n as f32
    };
    println!(
        "mean shift per motor: {:?}",
        [shift(0), shift(1), shift(2), shift(3)]
    );
    assert!(shift(0) > 0.01, "motor 0 moved by {}", shift(0));
    for k in 1..4 {
        assert!(
            shift(k).abs() < shift(0) / 3.0,
            "motor {k} moved by {}",
            shift(k)
        );
    }
}

#[test]
fn gae_matches_a_hand_computation() {
    // One env, three steps, a done after the second.
    let (g, l) = (0.9f32, 0.5f32);
    let rewards = [1.0, 2.0, 3.0];
    let dones = [false, true, false];
    let values = [0.5, 0.25, 1.0];
    let last = [2.0];
    let returns = gae(&rewards, &dones, &values, &last, g, l);
    // t = 2: δ = 3 + 0.9·2 − 1 = 3.8, A = 3.8.
    // t = 1 (done): δ = 2 − 0.25 = 1.75, A = 1.75.
    // t = 0: δ = 1 + 0.9·0.25 − 0.5 = 0.725, A = 0.725 + 0.9·0.5·1.75 = 1.5125.
    let expected = [1.5125 + 0.5, 1.75 + 0.25, 3.8 + 1.0];
    for (r, e) in returns.iter().zip(expected) {
        assert!((r - e).abs() < 1e-6, "{returns:?} vs {expected:?}");
    }
}

#[test]
fn gaussian_log_prob_is_the_closed_form() {
    let lp = gaussian_log_prob(
        &[0.3, -0.2, 0.0, 1.0],
        &[0.1, 0.1, 0.0, 0.5],
        &[0.5, 1.0, 2.0, 0.25],
    );
    let mut e = 0.0f64;
    for (a, m, s) in [
        (0.3, 0.1, 0.5),
        (-0.2, 0.1, 1.0),
        (0.0, 0.0, 2.0),
        (1.0, 0.5, 0.25),
    ] {
        let z: f64 = (a - m) / s;
        e += -0.5 * z * z - f64::ln(s) - 0.5 * f64::ln(2.0 * std::f64::consts::PI);
    }
    assert!((f64::from(lp) - e).abs() < 1e-5, "{lp} vs {e}");
}

/// The actor's and the critic's passes on two threads give exactly the update of the two
/// passes one after the other.
#[test]
fn parallel_passes_equal_sequential_passes() {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let make = || {
        let mut rng = init_rng(9);
        let actor = Actor::fresh(&arch, 0.5, &mut rng, &device);
        let critic = Critic::fresh(&arch, &mut rng, &device);
        Learner::new(actor, critic, 1e-3, device.clone())
    };
    let mut r = ChaCha8Rng::seed_from_u64(5);
    let n = 4096;
    let mut f = |k: usize, a: f32| -> Vec<f32> { (0..k).map(|_| r.random_range(-a..a)).collect() };
    let obs = f(n * 17, 1.0);
    let actions = f(n * 4, 1.0);
    let old_mean = f(n * 4, 0.5);
    let old_log_prob = f(n, 1.0).iter().map(|x| x - 4.0).collect();
    let batch = Batch {
        obs_dim: 17,
        obs,
        actions,
        old_log_prob,
        old_mean,
        old_std: [0.5; 4],
        old_values: f(n, 0.2),
        returns: f(n, 0.5),
        advantages: f(n, 2.0),
        sequence: None,
        critic: None,
    };
    let idx: Vec<usize> = (0..n).collect();
    let mut p = params();
    p.desired_kl = Some(0.01);
    let (mut a, mut b) = (make(), make());
    b.parallel = false;
    for _ in 0..3 {
        let sa = a.train_minibatch(&batch, &idx, &p);
        let sb = b.train_minibatch(&batch, &idx, &p);
        assert_eq!(sa, sb);
    }
    assert_eq!(a.actor.payload(), b.actor.payload());
    let v = |l: &Learner| {
        values(l.critic.value(Tensor::from_data(
            TensorData::new(batch.obs[..17 * 64].to_vec(), [64, 17]),
            &device,
        )))
    };
    assert_eq!(v(&a), v(&b));
}

/// A non-finite advantage (or loss) skips the minibatch and leaves both networks as they
/// were, instead of writing NaN into every weight through Adam.
#[test]
fn a_nan_minibatch_changes_nothing() {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(2);
    let actor = Actor::fresh(&arch, 0.5, &mut rng, &device);
    let critic = Critic::fresh(&arch, &mut rng, &device);
    let mut learner = Learner::new(actor, critic, 1e-3, device.clone());
    let n = 256;
    let mut advantages = vec![0.5f32; n];
    advantages[17] = f32::NAN;
    let batch = Batch {
        obs_dim: 17,
        obs: vec![0.1; n * 17],
        actions: vec![0.2; n * 4],
        old_log_prob: vec![-3.0; n],
        old_mean: vec![0.0; n * 4],
        old_std: [0.5; 4],
        old_values: vec![0.0; n],
        returns: vec![0.1; n],
        advantages,
        sequence: None,
        critic: None,
    };
    let before = learner.actor.payload();
    let idx: Vec<usize> = (0..n).collect();
    let s = learner.train_minibatch(&batch, &idx, &params());
    assert_eq!(s.skipped, 1);
    assert_eq!(learner.actor.payload(), before);
    assert!(learner.actor.payload().iter().all(|w| w.is_finite()));
}

/// `max_std`: a large entropy bonus drives σ up; with the ceiling every σ stops at it after
/// each step (the log-σ parameter keeps its id, so Adam's moments follow it), without it σ
/// passes it; on burn's update and on the fused one.
#[test]
fn the_std_ceiling_holds_against_the_entropy_bonus() {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut r = ChaCha8Rng::seed_from_u64(5);
    let n = 256;
    let obs: Vec<f32> = (0..n * 17).map(|_| r.random_range(-1.0..1.0)).collect();
    let run = |max_std: Option<f32>, fused: bool| -> (Vec<f32>, Vec<f32>) {
        let mut rng = init_rng(4);
        let actor = Actor::fresh(&arch, 0.5, &mut rng, &device);
        let critic = Critic::fresh(&arch, &mut rng, &device);
        let mut learner = Learner::new(actor, critic, 1e-2, device.clone());
        let mean = values(learner.actor.mean(Tensor::from_data(
            TensorData::new(obs.clone(), [n, 17]),
            &device,
        )));
        let std = [0.5f32; 4];
        let old_log_prob = mean
            .chunks_exact(4)
            .map(|m| gaussian_log_prob(m, m, &std))
            .collect();
        let batch = Batch {
            obs_dim: 17,
            obs: obs.clone(),
            actions: mean.clone(),
            old_log_prob,
            old_mean: mean.clone(),
            old_std: std,
            old_values: vec![0.0; n],
            returns: vec![0.0; n],
            advantages: vec![0.0; n],
            sequence: None,
            critic: None,
        };
        let p = PpoConfig {
            entropy_coef: 1.0,
            learning_rate: 1e-2,
            max_std,
            ..params()
        };
        let idx: Vec<usize> = (0..n).collect();
        let mut seen = Vec::new();
        for _ in 0..30 {
            if fused {
                learner.train_minibatch_fused(&batch, &idx, &p);
            } else {
                learner.train_minibatch(&batch, &idx, &p);
            }
            seen.push(learner.actor.std().into_iter().fold(0.0, f32::max));
        }
        (learner.actor.std(), seen)
    };
    for fused in [false, true] {
        let (free, _) = run(None, fused);
        assert!(
            free.iter().all(|s| *s > 0.6),
            "fused {fused}, no ceiling: σ {free:?}"
        );
        let (capped, seen) = run(Some(0.6), fused);
        assert!(
            seen.iter().all(|s| *s <= 0.6 + 1e-6),
            "fused {fused}: {seen:?}"
        );
        assert!(
            capped.iter().all(|s| (s - 0.6).abs() < 1e-5),
            "fused {fused}: {capped:?}"
        );
    }
}

/// The rollout runs a recurrent policy 16 envs side by side too (`Policy::step_lanes`, each
/// env's LSTM state its own, zeroed at its episode ends), racing `policies/stage1.blob`:
/// every recorded action is the deployed network's `act`, replayed env by env from each
/// env's own state, plus σ times the serially drawn noise, across two windows (the state
/// carries over) and the episode ends inside them. 83 envs: four lane groups in the first
/// task, then one lane group and three envs one by one.
#[test]
fn recurrent_rollout_actions_are_act_from_each_envs_own_state() {
    use firmware_core::blob::AlignedBytes;
    use host_trainer::rollout::{Rollout, collect_rollout};
    use sitl::env::{EnvConfig, VecEnv};
    let bytes = AlignedBytes::new(&firmware_core::synthetic::blob(TableRow::G, 3).unwrap());
    let policy = firmware_core::Blob::parse(bytes.as_bytes())
        .and_then(|b| b.policy())
        .unwrap();
    let std = [0.3f32; 4];
    let (envs, steps) = (83, 40);
    let opponent = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");
    let mut env = VecEnv::new(EnvConfig::stage2(envs, opponent)).unwrap();
    let mut rollout = Rollout::new(envs, 30);
    let mut noise = ChaCha8Rng::seed_from_u64(4);
    let mut replay = noise.clone();
    let mut states = vec![policy.initial_state(); envs];
    let mut ends = 0;
    for window in 0..2 {
        collect_rollout(
            &mut env,
            &policy,
            &std,
            steps,
            &mut noise,
            &mut rollout,
            |_, _| {},
        )
        .unwrap();
        let label = format!("window {window}");
        ends += assert_rollout_replays(&policy, &std, &rollout, &mut states, &mut replay, &label);
    }
    assert!(ends > 0, "no episode ended: the resets went untested");
}

/// The rollout runs a feed-forward policy 16 envs side by side (`Policy::act_lanes`, built
/// for the CPU's vector unit) and the rest of each 64-env task one by one: every recorded
/// action is still exactly the deployed network's `act` on the recorded observation plus
/// σ times the serially drawn noise. 83 envs: one full task of four lane groups, then 19
/// envs (one lane group and three one by one).
#[test]
fn rollout_actions_are_the_deployed_networks_act_plus_noise() {
    use firmware_core::policy::Policy;
    use host_trainer::rollout::{Rollout, collect_rollout};
    use sitl::env::{EnvConfig, VecEnv};
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(11);
    let actor = Actor::fresh(&arch, 0.3, &mut rng, &device);
    let payload = actor.payload();
    let policy = Policy::from_payload(&arch, &payload).unwrap();
    let std = actor.std();
    let (envs, steps) = (83, 12);
    let mut env = VecEnv::time_trial(EnvConfig::paper_along_track(envs, 3));
    let mut rollout = Rollout::new(envs, 17);
    let mut noise = ChaCha8Rng::seed_from_u64(4);
    let mut replay = noise.clone();
    collect_rollout(
        &mut env,
        &policy,
        &std,
        steps,
        &mut noise,
        &mut rollout,
        |_, _| {},
    )
    .unwrap();
    assert_eq!(rollout.actions.len(), envs * steps * 4);
    let mut states = vec![policy.initial_state(); envs];
    assert_rollout_replays(
        &policy,
        &std,
        &rollout,
        &mut states,
        &mut replay,
        "one window",
    );
}

/// Replays `rollout` env by env: every recorded action must be, bit for bit, `policy.act` on
/// the recorded observation from that env's own state in `states` (zeroed at the env's
/// episode ends; a feed-forward policy's states are stateless) plus σ times the noise drawn
/// serially from `replay`. Returns the number of episode ends seen.
fn assert_rollout_replays(
    policy: &firmware_core::policy::Policy<'_>,
    std: &[f32],
    rollout: &host_trainer::rollout::Rollout,
    states: &mut [firmware_core::policy::PolicyState],
    replay: &mut ChaCha8Rng,
    label: &str,
) -> usize {
    use firmware_core::observation::Observation;
    let (envs, dim) = (states.len(), policy.obs_dim());
    let mut ends = 0;
    for (i, ((o, a), done)) in rollout
        .obs
        .chunks_exact(dim)
        .zip(rollout.actions.chunks_exact(4))
        .zip(&rollout.dones)
        .enumerate()
    {
        let z: [f32; 4] = core::array::from_fn(|_| host_trainer::rng::normal(replay));
        let state = &mut states[i % envs];
        let mean = policy
            .act(&Observation::from_values(o).unwrap(), state)
            .unwrap();
        let want: [f32; 4] = core::array::from_fn(|k| mean[k] + std[k] * z[k]);
        assert_eq!(
            a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            want.map(f32::to_bits),
            "{label}, env {}, step {}",
            i % envs,
            i / envs
        );
        if *done {
            state.clear();
            ends += 1;
        }
    }
    ends
}
