//! The recurrent PPO update (issue "stage2"): one minibatch step of the row-G LSTM actor
//! and critic on 256 sequences × 100 steps (25,600 samples: forward through both LSTM
//! layers and the MLP head over the window, KL, clipped losses, backpropagation through
//! time, global clip, Adam), actor and critic passes on two threads. The reference:
//! PyTorch 16.5 k samples/s, burn flex about 6 k with a fused cell.
//!
//! - `g_256x100_parallel`: `burn`'s autodiff (`[ppo] update = "burn"`);
//! - `g_256x100_fused` and `g_64x100_fused`: the fused update ([`host_trainer::fused`]) on
//!   the same batch, the whole window and a quarter of the envs (a minibatch of a 256-env
//!   run with 4 minibatches);
//! - `g_64x100_privileged_fused`: `g_64x100_fused` with a privileged MLP critic instead of
//!   the LSTM one (issue "lstm-speed", item 5): the actor's windows shared between two
//!   copies of it on two threads, the light critic on a third;
//! - `prepare_256x100_{burn,fused}`: the batch's forward pass over the whole rollout (old
//!   means, values, bootstrap, the critic's next states);
//! - `sgemm_peak/1024_{one,two}_thread(s)`: what `matrixmultiply`'s sgemm, the fused
//!   update's kernel, reaches on this machine at a large square size (throughput in FLOP:
//!   `Gelem/s` reads GFLOP/s), one product or two on two threads at once (the update runs
//!   the actor and the critic on two threads).
//!
//! `cargo bench -p host-trainer --bench recurrent_update`

use burn::tensor::Device;
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::config::{TrainConfig, UpdateKind};
use host_trainer::fused::FusedLearner;
use host_trainer::model::PrivilegedCritic;
use host_trainer::nets::{PolicyNet, ValueNet};
use host_trainer::ppo::{Learner, RecurrentLearner};
use host_trainer::recurrent::{RecurrentActor, RecurrentCritic};
use host_trainer::rng::init_rng;
use host_trainer::rollout::Rollout;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SEQUENCES: usize = 256;
const STEPS: usize = 100;
const OBS: usize = 30;

/// A window of 256 envs × 100 steps with random observations, actions and rewards and an
/// episode end every 150 env-steps on average.
fn rollout() -> Rollout {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut r = Rollout::new(SEQUENCES, OBS);
    let n = SEQUENCES * STEPS;
    r.obs = (0..n * OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
    r.actions = (0..n * 4).map(|_| rng.random_range(-1.0..1.0)).collect();
    r.rewards = (0..n).map(|_| rng.random_range(-0.01..0.01)).collect();
    r.dones = (0..n).map(|_| rng.random_range(0..150) == 0).collect();
    r.timeouts = vec![false; n];
    r.last_obs = (0..SEQUENCES * OBS)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    r
}

fn update(c: &mut Criterion) {
    let config =
        TrainConfig::parse(include_str!("../configs/smoke_race.toml")).expect("smoke config");
    let p = config.ppo.clone();
    let device = Device::flex().autodiff();
    let arch = Architecture::table1(TableRow::G);
    let mut rng = init_rng(1);
    let actor = RecurrentActor::fresh(&arch, 1.0, &mut rng, &device);
    let critic = RecurrentCritic::fresh(&arch, &mut rng, &device);
    let mut learner = RecurrentLearner::new(actor, critic, 1e-5, device);
    let batch = learner.prepare(&rollout(), &p);
    let envs: Vec<usize> = (0..SEQUENCES).collect();
    let mut g = c.benchmark_group("recurrent_update");
    g.throughput(Throughput::Elements((SEQUENCES * STEPS) as u64));
    g.sample_size(10);
    let mut fused = FusedLearner::recurrent(&learner.actor, &learner.critic, None);
    let mut lr = p.learning_rate;
    g.bench_function("g_256x100_fused", |b| {
        b.iter(|| fused.train_minibatch(&batch, &envs, &p, &mut lr, true, true))
    });
    g.bench_function("g_256x100_parallel", |b| {
        b.iter(|| learner.train_minibatch(&batch, &envs, &p))
    });
    g.throughput(Throughput::Elements((SEQUENCES / 4 * STEPS) as u64));
    g.bench_function("g_64x100_fused", |b| {
        b.iter(|| fused.train_minibatch(&batch, &envs[..SEQUENCES / 4], &p, &mut lr, true, true))
    });
    // The same minibatch beside a privileged MLP critic (`[ppo] critic = "privileged-mlp"`):
    // the actor's windows shared between two copies on two threads, the critic on a third.
    let mut privileged_rollout = rollout();
    let pdim = PrivilegedCritic::input_dim(&arch);
    let mut prng = ChaCha8Rng::seed_from_u64(1);
    let mut draw =
        |n: usize| -> Vec<f32> { (0..n).map(|_| prng.random_range(-1.0..1.0)).collect() };
    privileged_rollout.privileged_dim = pdim;
    privileged_rollout.privileged = draw(SEQUENCES * STEPS * pdim);
    privileged_rollout.last_privileged = draw(SEQUENCES * pdim);
    let device = Device::flex().autodiff();
    let privileged = Learner::new(
        learner.actor.clone(),
        PrivilegedCritic::fresh(&arch, &mut init_rng(2), &device),
        1e-5,
        device,
    );
    let privileged_batch = privileged.prepare(&privileged_rollout, &p);
    let mut fused = FusedLearner::recurrent_privileged(&privileged.actor, &privileged.critic, None);
    g.bench_function("g_64x100_privileged_fused", |b| {
        b.iter(|| {
            fused.train_minibatch(
                &privileged_batch,
                &envs[..SEQUENCES / 4],
                &p,
                &mut lr,
                true,
                true,
            )
        })
    });
    g.throughput(Throughput::Elements((SEQUENCES * STEPS) as u64));
    let r = rollout();
    for (name, update) in [("burn", UpdateKind::Burn), ("fused", UpdateKind::Fused)] {
        let p = host_trainer::config::PpoConfig {
            update,
            ..p.clone()
        };
        g.bench_function(format!("prepare_256x100_{name}"), |b| {
            b.iter(|| learner.prepare(&r, &p))
        });
    }
    g.finish();
}

/// `c = a · b` for square `n × n` row-major matrices.
fn sgemm(n: usize, a: &[f32], b: &[f32], c: &mut [f32]) {
    assert!(a.len() >= n * n && b.len() >= n * n && c.len() >= n * n);
    // SAFETY: the assert keeps every n × n element inside the slices; `c` is exclusively
    // borrowed and does not alias `a` or `b`.
    unsafe {
        matrixmultiply::sgemm(
            n,
            n,
            n,
            1.0,
            a.as_ptr(),
            n as isize,
            1,
            b.as_ptr(),
            n as isize,
            1,
            0.0,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

fn sgemm_peak(c: &mut Criterion) {
    const N: usize = 1024;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut m = || -> Vec<f32> { (0..N * N).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let (a, b) = (m(), m());
    let (mut c1, mut c2) = (vec![0.0f32; N * N], vec![0.0f32; N * N]);
    let flop = 2 * N * N * N;
    let mut g = c.benchmark_group("sgemm_peak");
    g.sample_size(20);
    g.throughput(Throughput::Elements(flop as u64));
    g.bench_function("1024_one_thread", |bench| {
        bench.iter(|| sgemm(N, &a, &b, &mut c1))
    });
    g.throughput(Throughput::Elements(2 * flop as u64));
    g.bench_function("1024_two_threads", |bench| {
        bench.iter(|| {
            std::thread::scope(|s| {
                s.spawn(|| sgemm(N, &a, &b, &mut c2));
                sgemm(N, &a, &b, &mut c1);
            })
        })
    });
    g.finish();
}

criterion_group!(benches, update, sgemm_peak);
criterion_main!(benches);
