//! Parity of the trained actor and the deployed network: the blob the trainer exports, run
//! through firmware-core, gives the burn actor's actions (max |Δ| ≤ 1e-5) on the same
//! observations: random ones, observations the environment produces, and after PPO updates
//! have moved the weights away from their initialisation.

use burn::tensor::{Device, Tensor, TensorData};
use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::policy::{Architecture, Policy, TableRow};
use host_trainer::config::TrainConfig;
use host_trainer::export::actor_blob;
use host_trainer::model::{Actor, Critic, values};
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::Learner;
use host_trainer::rng::init_rng;
use host_trainer::rollout::Rollout;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sitl::env::{EnvConfig, OBS_DIM, VecEnv};

const CONFIG: &str = include_str!("../configs/experiments/stage1_finetune.toml");

/// Max |burn − firmware-core| over `obs` (rows of 17), the firmware side read from the
/// exported blob.
fn max_action_diff(actor: &Actor, config: &TrainConfig, obs: &[f32], device: &Device) -> f32 {
    let blob = actor_blob(actor, config, 7).unwrap();
    let aligned = AlignedBytes::new(&blob);
    let parsed = Blob::parse(aligned.as_bytes()).unwrap();
    assert_eq!(parsed.header().provenance.seed, config.run.seed);
    assert_eq!(parsed.header().provenance.iterations, 7);
    assert_eq!(parsed.header().provenance.config_hash, config.hash());
    let Ok(Policy::A(net)) = parsed.policy() else {
        panic!("the blob does not hold a row-A policy")
    };
    let n = obs.len() / OBS_DIM;
    let burn_mean = values(actor.mean(Tensor::from_data(
        TensorData::new(obs.to_vec(), [n, OBS_DIM]),
        device,
    )));
    let mut worst = 0.0f32;
    for (o, m) in obs.chunks_exact(OBS_DIM).zip(burn_mean.chunks_exact(4)) {
        let fw = net.forward(<&[f32; OBS_DIM]>::try_from(o).unwrap());
        for k in 0..4 {
            worst = worst.max((fw[k] - m[k]).abs());
        }
    }
    worst
}

fn env_observations(steps: usize) -> (Vec<f32>, Rollout) {
    let mut env = VecEnv::time_trial(EnvConfig::paper_along_track(32, 5));
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut rollout = Rollout::new(32, OBS_DIM);
    let mut all = Vec::new();
    for _ in 0..steps {
        all.extend_from_slice(env.observations());
        rollout.obs.extend_from_slice(env.observations());
        let actions: Vec<f32> = (0..32 * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
        rollout.actions.extend_from_slice(&actions);
        env.step(&actions).unwrap();
        rollout.rewards.extend_from_slice(env.rewards());
        rollout.dones.extend_from_slice(env.dones());
        rollout.timeouts.extend_from_slice(env.timeouts());
    }
    rollout.last_obs.extend_from_slice(env.observations());
    (all, rollout)
}

#[test]
fn exported_blob_acts_as_the_burn_actor() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(config.run.seed);
    let actor = Actor::fresh(&arch, 1.0, &mut rng, &device);
    let critic = Critic::fresh(&arch, &mut rng, &device);

    // Random observations over the whole clipped range, and beyond it.
    let mut r = ChaCha8Rng::seed_from_u64(1);
    let random: Vec<f32> = (0..1000 * OBS_DIM)
        .map(|_| r.random_range(-1.5..1.5))
        .collect();
    let d0 = max_action_diff(&actor, &config, &random, &device);
    assert!(d0 <= 1e-5, "fresh actor: max |Δ| = {d0:e}");

    // The environment's own observations.
    let (obs, rollout) = env_observations(40);
    let d1 = max_action_diff(&actor, &config, &obs, &device);
    assert!(d1 <= 1e-5, "env observations: max |Δ| = {d1:e}");

    // After PPO updates at a high learning rate have moved every weight.
    let mut learner = Learner::new(actor, critic, 3e-3, device.clone());
    let before = learner.actor.payload();
    let mut p = config.ppo.clone();
    p.desired_kl = None;
    let batch = learner.prepare(&rollout, &p);
    learner.update(&batch, &p, &mut r);
    let after = learner.actor.payload();
    let moved = before.iter().zip(&after).filter(|(a, b)| a != b).count();
    assert!(moved > before.len() * 9 / 10, "only {moved} weights moved");
    let d2 = max_action_diff(&learner.actor, &config, &obs, &device);
    let d3 = max_action_diff(&learner.actor, &config, &random, &device);
    println!("max |Δ|: fresh {d0:e}, env obs {d1:e}, trained {d2:e} / {d3:e}");
    assert!(d2 <= 1e-5 && d3 <= 1e-5, "trained actor: {d2:e}, {d3:e}");
}

#[test]
fn payload_round_trips_through_the_actor() {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let actor = Actor::fresh(&arch, 0.7, &mut init_rng(3), &device);
    let payload = actor.payload();
    assert_eq!(payload.len(), arch.param_count());
    let back = Actor::from_payload(&arch, &payload, &actor.std(), &device).unwrap();
    assert_eq!(back.payload(), payload);
    let std = back.std();
    assert!(std.iter().all(|s| (s - 0.7).abs() < 1e-6), "{std:?}");
    assert!(Actor::from_payload(&arch, &payload[1..], &std, &device).is_none());
}
