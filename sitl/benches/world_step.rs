//! Env-steps per second: one drone, one 20 ms control step (physics substeps, the gate test,
//! the crash rules) and its 17-value observation from firmware-core's pipeline; a crashed
//! drone is respawned as a training environment would. Single-threaded, and 4,096 worlds on
//! one thread and on rayon's pool.
//!
//! `cargo bench -p sitl --bench world_step`

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use firmware_core::observation::{ObservationLayout, ObservationSpec};
use firmware_core::track::CrashRules;
use firmware_core::vehicle::MotorCommand;
use rayon::prelude::*;
use sitl::dynamics::Preset;
use sitl::world::{Drone, PAR_CHUNK_WORLDS, World, stage1_spawn};
use std::hint::black_box;

const WORLDS: usize = 4096;

struct Env {
    drones: [Drone; 1],
    command: MotorCommand,
    previous_action: [f32; 4],
    observation: [f32; 17],
}

fn envs(world: &World) -> Vec<Env> {
    let hover = world.preset.hover_rpm();
    (0..WORLDS)
        .map(|i| {
            // A small differential per world so that no two worlds fly the same numbers.
            let d = (i % 17) as f32 - 8.0;
            Env {
                drones: [Drone::spawned(stage1_spawn())],
                command: MotorCommand {
                    rpm: [hover + d, hover - d, hover + 0.5 * d, hover - 0.5 * d],
                },
                previous_action: [0.5; 4],
                observation: [0.0; 17],
            }
        })
        .collect()
}

/// One env-step: integrate, judge, respawn on a crash, observe.
#[inline]
fn env_step(world: &World, spec: &ObservationSpec, env: &mut Env) {
    let [result] = world.step(&mut env.drones, &[env.command]);
    if result.crash.is_some() {
        env.drones = [Drone::spawned(stage1_spawn())];
    }
    let d = &env.drones[0];
    let gate = world.track.gate(d.progress.target);
    if let Ok(obs) = spec.observe(&d.body.state, &gate, &env.previous_action, None) {
        env.observation.copy_from_slice(obs.as_slice());
    }
}

fn bench(c: &mut Criterion) {
    let spec = ObservationSpec::paper(ObservationLayout::TimeTrial17);
    for preset in [Preset::paper(), Preset::realistic()] {
        let world = World::figure_eight(preset, CrashRules::STAGE1);
        let mut g = c.benchmark_group(format!("env_step/{}", preset.name));
        g.throughput(Throughput::Elements(1));
        let mut one = envs(&world).swap_remove(0);
        g.bench_function("single", |b| {
            b.iter(|| env_step(&world, &spec, black_box(&mut one)))
        });
        g.throughput(Throughput::Elements(WORLDS as u64));
        let mut batch = envs(&world);
        g.bench_function("4096_serial", |b| {
            b.iter(|| {
                for e in batch.iter_mut() {
                    env_step(&world, &spec, e);
                }
            })
        });
        g.bench_function("4096_rayon", |b| {
            b.iter(|| {
                batch.par_chunks_mut(PAR_CHUNK_WORLDS).for_each(|chunk| {
                    for e in chunk {
                        env_step(&world, &spec, e);
                    }
                })
            })
        });
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
