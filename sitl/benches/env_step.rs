//! The training environment's step rate: 4,096 stage-1 envs (dynamics, gate test, crash
//! rules, rewards with their terms, respawns, observations), rayon over the cores; and
//! 4,096 stage-2 envs, each with its opponent (`policies/stage1.blob`): replaying its
//! recorded flights (`race_4096`, the env's default), and flown live by firmware-core's
//! controller, 16 envs side by side (`race_4096_live`), in the same run.
//!
//! `cargo bench -p sitl --bench env_step`

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use sitl::env::{EnvConfig, VecEnv};

fn bench(c: &mut Criterion) {
    let n = 4096;
    let mut env = VecEnv::time_trial(EnvConfig::paper_along_track(n, 0));
    // Near-hover actions with a per-env differential, as an early policy flies.
    let actions: Vec<f32> = (0..n * 4)
        .map(|i| 0.52 + 0.05 * ((i % 9) as f32 - 4.0) / 4.0)
        .collect();
    let mut g = c.benchmark_group("train_env");
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("step_4096", |b| b.iter(|| env.step(&actions)));
    let opponent = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");
    let mut race = VecEnv::new(EnvConfig::stage2(n, opponent)).expect("the shipped opponent");
    g.bench_function("race_4096", |b| b.iter(|| race.step(&actions)));
    let mut live = VecEnv::new(EnvConfig::stage2(n, opponent)).expect("the shipped opponent");
    live.fly_opponents_live();
    g.bench_function("race_4096_live", |b| b.iter(|| live.step(&actions)));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
