//! The PPO update and a whole training iteration, stage 1 (MLP 2×128 actor and critic).
//!
//! - `ppo_update/minibatch_25600_{parallel,sequential}`: one minibatch step on 25,600
//!   samples (forward, KL, clipped losses, backward, global clip, Adam) with the actor's and
//!   the critic's passes on two threads or one after the other, in the same run;
//! - `ppo_update/minibatch_102400_{burn,fused}`: one minibatch step at RSL-RL's minibatch
//!   size (4,096 envs × 100 steps / 4) with `burn`'s autodiff and Adam, and with the fused
//!   update ([`host_trainer::fused`]), both with the passes on two threads, in the same run;
//! - `rollout_inference/512_envs_{one_by_one,lanes}`: the deployed network's means for one
//!   step of 512 envs on one thread, `Policy::act` env by env and `act_lanes` 16 envs side by
//!   side (the rollout's path since the lanes; the same bits), in the same run;
//! - `rollout_inference/G_512_envs_{one_by_one,lanes}`: the same for row G (2-layer LSTM
//!   128 + MLP 256-128-128-64, each env its own recurrent state) on race observations:
//!   `Policy::act` env by env against `step_lanes` 16 envs side by side;
//! - `train_iteration/stage1`: one PPO iteration of `configs/stage1.toml` (the shipped
//!   config) end to end (rollout of 512 envs × 100 steps with the deployed network, folded,
//!   then 5 epochs × 4 minibatches of 12,800), checkpoint load and save included.
//!
//! `cargo bench -p host-trainer --bench ppo_update`

use burn::tensor::Device;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use firmware_core::nn::LANES;
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::config::TrainConfig;
use host_trainer::fused::FusedLearner;
use host_trainer::model::{Actor, Critic};
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::Learner;
use host_trainer::rng::init_rng;
use host_trainer::rollout::Rollout;
use host_trainer::train::{RunOptions, run};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sitl::env::{EnvConfig, OBS_DIM, VecEnv};
use sitl::lanes::{act_lanes, step_lanes};

const STAGE1: &str = include_str!("../configs/stage1.toml");

fn learner() -> Learner {
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::A);
    let mut rng = init_rng(1);
    let actor = Actor::fresh(&arch, 1.0, &mut rng, &device);
    let critic = Critic::fresh(&arch, &mut rng, &device);
    Learner::new(actor, critic, 1e-4, device)
}

/// A rollout of `envs × steps` from the environment with random actions.
fn rollout(envs: usize, steps: usize) -> Rollout {
    let mut env = VecEnv::time_trial(EnvConfig::paper_along_track(envs, 0));
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut r = Rollout::new(envs, OBS_DIM);
    for _ in 0..steps {
        r.obs.extend_from_slice(env.observations());
        let a: Vec<f32> = (0..envs * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
        env.step(&a).unwrap();
        r.actions.extend_from_slice(&a);
        r.rewards.extend_from_slice(env.rewards());
        r.dones.extend_from_slice(env.dones());
        r.timeouts.extend_from_slice(env.timeouts());
    }
    r.last_obs.extend_from_slice(env.observations());
    r
}

fn update(c: &mut Criterion) {
    let config = TrainConfig::parse(STAGE1).unwrap();
    let p = config.ppo.clone();
    let mut l = learner();
    let batch = l.prepare(&rollout(256, 100), &p);
    let idx: Vec<usize> = (0..batch.len()).collect();
    let mut g = c.benchmark_group("ppo_update");
    g.throughput(Throughput::Elements(idx.len() as u64));
    g.sample_size(10);
    for parallel in [true, false] {
        l.parallel = parallel;
        let name = if parallel { "parallel" } else { "sequential" };
        g.bench_function(format!("minibatch_25600_{name}"), |b| {
            b.iter(|| l.train_minibatch(&batch, &idx, &p))
        });
    }
    // RSL-RL's minibatch: 102,400 samples.
    let mut l = learner();
    let batch = l.prepare(&rollout(1024, 100), &p);
    let idx: Vec<usize> = (0..batch.len()).collect();
    g.throughput(Throughput::Elements(idx.len() as u64));
    g.bench_function("minibatch_102400_burn", |b| {
        b.iter(|| l.train_minibatch(&batch, &idx, &p))
    });
    let mut fused = FusedLearner::new(&l.actor, &l.critic, None);
    let mut lr = l.learning_rate;
    g.bench_function("minibatch_102400_fused", |b| {
        b.iter(|| fused.train_minibatch(&batch, &idx, &p, &mut lr, true, true))
    });
    g.finish();
}

fn inference(c: &mut Criterion) {
    use firmware_core::nn::ACTION_DIM;
    use firmware_core::observation::Observation;
    use firmware_core::policy::Policy;
    let l = learner();
    let payload = l.actor.payload();
    let policy = Policy::from_payload(&Architecture::table1(TableRow::A), &payload).unwrap();
    let envs = 512;
    let env = VecEnv::time_trial(EnvConfig::paper_along_track(envs, 0));
    let obs = env.observations().to_vec();
    let mut means = vec![0.0f32; envs * ACTION_DIM];
    let mut g = c.benchmark_group("rollout_inference");
    g.throughput(Throughput::Elements(envs as u64));
    g.bench_function("512_envs_one_by_one", |b| {
        b.iter(|| {
            for (m, o) in means
                .chunks_exact_mut(ACTION_DIM)
                .zip(obs.chunks_exact(OBS_DIM))
            {
                let mut state = policy.initial_state();
                let o = Observation::from_values(o).unwrap();
                m.copy_from_slice(&policy.act(&o, &mut state).unwrap());
            }
        })
    });
    g.bench_function("512_envs_lanes", |b| {
        b.iter(|| {
            for (m, o) in means
                .chunks_exact_mut(ACTION_DIM * LANES)
                .zip(obs.chunks_exact(OBS_DIM * LANES))
            {
                let lanes = act_lanes(&policy, o).unwrap();
                m.copy_from_slice(lanes.as_flattened());
            }
        })
    });
    // Row G (synthetic weights: the cost does not depend on their values) on the race.
    let bytes = firmware_core::blob::AlignedBytes::new(
        &firmware_core::synthetic::blob(TableRow::G, 1).unwrap(),
    );
    let g_policy = firmware_core::Blob::parse(bytes.as_bytes())
        .and_then(|b| b.policy())
        .unwrap();
    let opponent = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");
    let race = VecEnv::new(EnvConfig::stage2(envs, opponent)).unwrap();
    let race_obs = race.observations().to_vec();
    let mut states = vec![g_policy.initial_state(); envs];
    g.bench_function("G_512_envs_one_by_one", |b| {
        b.iter(|| {
            for ((m, o), s) in means
                .chunks_exact_mut(ACTION_DIM)
                .zip(race_obs.chunks_exact(30))
                .zip(&mut states)
            {
                let o = Observation::from_values(o).unwrap();
                m.copy_from_slice(&g_policy.act(&o, s).unwrap());
            }
        })
    });
    g.bench_function("G_512_envs_lanes", |b| {
        b.iter(|| {
            for ((m, o), s) in means
                .chunks_exact_mut(ACTION_DIM * LANES)
                .zip(race_obs.chunks_exact(30 * LANES))
                .zip(states.chunks_exact_mut(LANES))
            {
                let s: &mut [_; LANES] = s.try_into().unwrap();
                let lanes = step_lanes(&g_policy, o, s.each_mut()).unwrap();
                m.copy_from_slice(lanes.as_flattened());
            }
        })
    });
    g.finish();
}

fn iteration(c: &mut Criterion) {
    let mut config = TrainConfig::parse(STAGE1).unwrap();
    let dir = std::env::temp_dir().join(format!("overtake-bench-{}", std::process::id()));
    // PPO iterations only (the imitation warm start runs once per run, not per iteration).
    config.warm_start = None;
    config.run.eval_every = 1_000_000;
    config.run.checkpoint_every = 1_000_000;
    config.run.iterations = 1_000_000;
    let mut g = c.benchmark_group("train_iteration");
    g.throughput(Throughput::Elements(config.samples_per_iteration() as u64));
    g.sample_size(10);
    let mut first = true;
    g.bench_function("stage1", |b| {
        b.iter(|| {
            let options = RunOptions {
                out: dir.clone(),
                resume: !first,
                device: Device::flex().autodiff(),
                progress: false,
                stop_after: Some(1),
                init_actor: None,
                fork_from: None,
            };
            first = false;
            run(&config, &options).unwrap()
        })
    });
    g.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

criterion_group!(benches, update, inference, iteration);
criterion_main!(benches);
