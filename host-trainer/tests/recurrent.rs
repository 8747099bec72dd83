//! The recurrent networks on burn against firmware-core, the code a flight controller runs:
//! a blob exported from a burn LSTM actor gives the same actions step by step (max |Δ| ≤
//! 1e-5, the bound of the feed-forward parity test) for rows E, F and G, from a stored
//! non-zero state, across an episode end in the middle of the window (the controller's
//! reset, i.e. RSL-RL's split-at-dones), and the payload round-trips bit for bit.

use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::observation::Observation;
use firmware_core::policy::{Architecture, Policy, PolicyState, TableRow};
use host_trainer::model::values;
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::recurrent::{LstmState, RecurrentActor};
use host_trainer::rng::init_rng;
use host_trainer::rollout::push_flat_state;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The flat state (per layer h, c) of a firmware-core recurrent state.
fn flat(state: &PolicyState) -> Vec<f32> {
    let mut v = Vec::new();
    push_flat_state(state, &mut v);
    v
}

fn observation(values: &[f32]) -> Observation {
    Observation::from_values(values).unwrap()
}

fn max_diff_over_a_window(row: TableRow) -> f32 {
    let device = Device::flex();
    let arch = Architecture::table1(row);
    let actor = RecurrentActor::fresh(&arch, 0.5, &mut init_rng(7), &device);
    let payload = actor.net.payload();
    assert_eq!(payload.len(), arch.param_count());
    let back = RecurrentActor::from_payload(&arch, &payload, &actor.std(), &device).unwrap();
    assert_eq!(back.net.payload(), payload, "payload round trip");
    let policy = Policy::from_payload(&arch, &payload).unwrap();

    let (envs, warmup, steps, obs_dim) = (3usize, 10usize, 40usize, 30usize);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
    // Firmware-core: a warm-up to reach a non-zero state, then the window; env 1's episode
    // ends after window step 19 (its controller resets before step 20).
    let mut states: Vec<PolicyState> = (0..envs).map(|_| policy.initial_state()).collect();
    for s in &mut states {
        for o in draw(warmup * obs_dim).chunks_exact(obs_dim) {
            policy.act(&observation(o), s).unwrap();
        }
    }
    let h0: Vec<f32> = states.iter().flat_map(flat).collect();
    let obs = draw(steps * envs * obs_dim); // time-major [t][env][obs]
    let mut keep = vec![1.0f32; steps * envs];
    keep[20 * envs + 1] = 0.0;
    let mut fw = Vec::new();
    for t in 0..steps {
        for (e, s) in states.iter_mut().enumerate() {
            if keep[t * envs + e] == 0.0 {
                s.clear();
            }
            let o = &obs[(t * envs + e) * obs_dim..(t * envs + e + 1) * obs_dim];
            fw.extend(policy.act(&observation(o), s).unwrap());
        }
    }

    let layers = usize::from(arch.lstm_layers);
    let state = LstmState::from_flat(&h0, layers, 128, &device);
    assert_eq!(state.to_flat(), h0, "flat state round trip");
    let obs_t = Tensor::<3>::from_data(TensorData::new(obs, [steps, envs, obs_dim]), &device);
    let keep_t = Tensor::<2>::from_data(TensorData::new(keep, [steps, envs]), &device);
    let (mean, after) = actor.net.sequence(obs_t, keep_t, state);
    let burn = values(mean);
    assert_eq!(burn.len(), fw.len());
    let end: Vec<f32> = states.iter().flat_map(flat).collect();
    let state_diff = after
        .to_flat()
        .iter()
        .zip(&end)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(state_diff <= 1e-5, "final state: max |Δ| = {state_diff:e}");
    burn.iter()
        .zip(&fw)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max)
}

#[test]
fn burn_lstm_actors_act_as_firmware_core_over_a_window() {
    for row in [TableRow::E, TableRow::F, TableRow::G] {
        let d = max_diff_over_a_window(row);
        println!("row {}: max |Δ| = {d:e}", row.letter());
        assert!(d <= 1e-5, "row {}: max |Δ| = {d:e}", row.letter());
    }
}

// ---- Recurrent PPO's bookkeeping ------------------------------------------------------

use host_trainer::batch::Minibatch;
use host_trainer::config::TrainConfig;
use host_trainer::ppo::RecurrentLearner;
use host_trainer::recurrent::RecurrentCritic;
use host_trainer::rollout::Rollout;
use host_trainer::rollout::collect_rollout;
use sitl::env::{EnvConfig, VecEnv};

fn race_env(envs: usize) -> VecEnv {
    VecEnv::new(EnvConfig {
        seed: 4,
        ..EnvConfig::stage2(
            envs,
            concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/../policies/stage1_guarded.blob"
            ),
        )
    })
    .unwrap()
}

/// With σ = 0 the rollout's actions are firmware-core's means, computed step by step with
/// each env's controller state carried across windows and cleared at its episode ends. The
/// update's view of the same window, burn over the whole window from the stored start
/// states with the resets, must give the same means (≤ 1e-5), in the first window and in
/// the second (which starts from carried, non-zero states); and the critic started from the
/// first window's `critic_next` must give the values of one pass over both windows.
#[test]
fn the_update_sees_the_rollouts_recurrent_states() {
    let device = Device::flex();
    let arch = Architecture::table1(TableRow::G);
    let config = TrainConfig::parse(include_str!("../configs/smoke_race.toml")).unwrap();
    let p = &config.ppo;
    let actor = RecurrentActor::fresh(&arch, 0.5, &mut init_rng(3), &device);
    let critic = RecurrentCritic::fresh(&arch, &mut init_rng(4), &device);
    let learner = RecurrentLearner::new(actor, critic, 1e-4, device.clone());
    let payload = learner.actor.net.payload();
    let policy = Policy::from_payload(&arch, &payload).unwrap();
    let (envs, steps) = (16, 60);
    let mut env = race_env(envs);
    let mut rollout = Rollout::new(envs, 30);
    let mut noise = ChaCha8Rng::seed_from_u64(0);
    let zero = [0.0f32; 4];
    let mut windows = Vec::new();
    let mut batches = Vec::new();
    let mut dones = 0;
    for _ in 0..2 {
        collect_rollout(
            &mut env,
            &policy,
            &zero,
            steps,
            &mut noise,
            &mut rollout,
            |_, d| {
                dones += d.iter().filter(|d| **d).count();
            },
        )
        .unwrap();
        let batch = learner.prepare(&rollout, p);
        let worst = batch
            .old_mean
            .iter()
            .zip(&rollout.actions)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        println!("window {}: max |Δ| = {worst:e}", windows.len());
        assert!(
            worst <= 1e-5,
            "window {}: max |Δ| = {worst:e}",
            windows.len()
        );
        rollout.critic_h0 = batch.sequence.as_ref().unwrap().critic_next.clone();
        windows.push(rollout.clone());
        batches.push(batch);
    }
    assert!(dones > 0, "some episodes ended inside the windows");
    assert!(windows[1].actor_h0.iter().any(|v| *v != 0.0));

    // The critic over both windows at once, from zero.
    let mut both = windows[0].clone();
    both.obs.extend_from_slice(&windows[1].obs);
    both.actions.extend_from_slice(&windows[1].actions);
    both.rewards.extend_from_slice(&windows[1].rewards);
    both.dones.extend_from_slice(&windows[1].dones);
    both.timeouts.extend_from_slice(&windows[1].timeouts);
    both.last_obs.clone_from(&windows[1].last_obs);
    both.critic_h0.clear();
    let joint = learner.prepare(&both, p);
    let second = &batches[1];
    let n = envs * steps;
    let worst = joint.old_values[n..]
        .iter()
        .zip(&second.old_values)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-5, "critic across windows: max |Δ| = {worst:e}");
    // Minibatches of whole windows cover every sample once.
    let mb = Minibatch::of_envs(second, &[3, 7]);
    assert_eq!(mb.samples.len(), 2 * steps);
    assert_eq!(&mb.samples[..3], &[3, 7, envs + 3]);
}

/// The recurrent warm start splits each minibatch over the two cores: the size-weighted sum
/// of the two halves' gradients, one half on a copy of the actor on another thread (its
/// gradients moved onto the actor's parameters), is the gradient of the whole minibatch's
/// mean squared error (to rounding).
#[test]
fn two_halves_of_a_minibatch_give_its_gradient() {
    use burn::optim::GradientsParams;
    use host_trainer::grads::{flatten_gradients, transfer_gradients, weighted_sum};
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::G);
    let actor = RecurrentActor::fresh(&arch, 0.5, &mut init_rng(9), &device);
    let (steps, envs, obs_dim) = (12usize, 5usize, 30usize);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let obs: Vec<f32> = (0..steps * envs * obs_dim)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let labels: Vec<f32> = (0..steps * envs * 4)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let grad_of = |actor: &RecurrentActor, sel: &[usize]| -> GradientsParams {
        let b = sel.len();
        let (mut o, mut a) = (Vec::new(), Vec::new());
        for t in 0..steps {
            for &e in sel {
                let i = t * envs + e;
                o.extend_from_slice(&obs[i * obs_dim..(i + 1) * obs_dim]);
                a.extend_from_slice(&labels[i * 4..(i + 1) * 4]);
            }
        }
        let o = Tensor::<3>::from_data(TensorData::new(o, [steps, b, obs_dim]), &device);
        let keep = Tensor::<2>::ones([steps, b], &device);
        let a = Tensor::<2>::from_data(TensorData::new(a, [steps * b, 4]), &device);
        let (mean, _) = actor
            .net
            .sequence(o, keep, actor.net.zero_state(b, &device));
        GradientsParams::from_grads((mean - a).square().mean().backward(), actor)
    };
    let whole = flatten_gradients(&actor, &grad_of(&actor, &[0, 1, 2, 3, 4]));
    let twin =
        RecurrentActor::from_payload(&arch, &actor.net.payload(), &actor.std(), &device).unwrap();
    let (left, right) = std::thread::scope(|s| {
        let job = s.spawn(|| grad_of(&twin, &[0, 1]));
        let r = grad_of(&actor, &[2, 3, 4]);
        (job.join().unwrap(), r)
    });
    let left = transfer_gradients(&twin, left, &actor);
    let merged = flatten_gradients(&actor, &weighted_sum(&actor, left, 0.4, right, 0.6));
    assert_eq!(whole.len(), merged.len());
    let scale = whole.iter().fold(0.0f32, |m, g| m.max(g.abs()));
    let worst = whole
        .iter()
        .zip(&merged)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(worst <= 1e-5 * scale, "max |Δ| {worst:e} of {scale:e}");
}
