//! The world: gate passes found between two 20 ms steps, and determinism of parallel
//! stepping and of evaluations (same seed, same result, on any number of threads).

use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{CrashRules, GateEvent, GateProgress};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, evaluate};
use sitl::pilot::PilotSpec;
use sitl::world::{Drone, DroneStep, World, stage2_spawn};

fn world() -> World {
    World::figure_eight(Preset::paper(), CrashRules::STAGE1)
}

fn drone_at(p: Vec3, target: usize) -> Drone {
    Drone {
        body: sitl::dynamics::Body::new(VehicleState::at_rest(p, Quat::IDENTITY)),
        progress: GateProgress::targeting(target),
    }
}

/// g2's frame is upside down; a step from 0.3 m before its plane to 0.4 m past it (neither
/// end near the plane) at 0.5 m right and 0.2 m below the centre is a pass, and the target
/// moves on to g3. The same step 0.9 m right is a gate-frame crash.
#[test]
fn a_pass_between_two_steps_through_an_upside_down_gate() {
    let w = world();
    let g2 = w.track.gate(2);
    for (y, passed) in [(0.5, true), (0.9, false)] {
        let from = g2.to_world_frame(Vec3::new(-0.3, y, -0.2));
        let to = g2.to_world_frame(Vec3::new(0.4, y, -0.2));
        let mut drones = [drone_at(to, 2)];
        let [step] = w.judge(&mut drones, &[from]);
        match step.gate_event {
            GateEvent::Passed { gate, crossing_m } => {
                assert!(passed);
                assert_eq!(gate, 2);
                assert!((crossing_m - Vec3::new(0.0, 0.5, -0.2)).norm() < 1e-5);
                assert_eq!(drones[0].progress.target, 3);
                assert_eq!(step.crash, None);
            }
            GateEvent::Collided { gate, .. } => {
                assert!(!passed);
                assert_eq!(gate, 2);
                assert_eq!(
                    step.crash,
                    Some(sitl::world::CrashCause::GateFrame { gate: 2 })
                );
                assert_eq!(drones[0].progress.target, 2);
            }
            GateEvent::None => panic!("the crossing was missed"),
        }
    }
    // Back to front is not a pass.
    let mut drones = [drone_at(g2.to_world_frame(Vec3::new(-0.3, 0.0, 0.0)), 2)];
    let [step] = w.judge(&mut drones, &[g2.to_world_frame(Vec3::new(0.4, 0.0, 0.0))]);
    assert_eq!(step.gate_event, GateEvent::None);
}

#[test]
fn a_nan_state_is_a_crash_not_a_panic() {
    let w = world();
    let mut drones = [drone_at(Vec3::new(f32::NAN, 0.0, 1.0), 0)];
    let [step] = w.judge(&mut drones, &[Vec3::new(0.0, 0.0, 1.0)]);
    assert_eq!(step.crash, Some(sitl::world::CrashCause::NonFinite));
    // A NaN command: the motors stop (the dynamics treat it as 0 rpm), nothing diverges.
    let mut drones = [drone_at(Vec3::new(-1.0, -1.0, 1.0), 0)];
    w.step(&mut drones, &[MotorCommand { rpm: [f32::NAN; 4] }]);
    assert!(drones[0].body.state.is_finite());
}

/// 1,000 two-drone worlds with different commands, stepped 50 times with `par_step` on one
/// thread and on four, and one by one with `step`: bit-identical.
#[test]
fn parallel_stepping_is_deterministic() {
    let w = World::figure_eight(Preset::paper(), CrashRules::STAGE2);
    let hover = w.preset.hover_rpm();
    let n = 1000;
    let start: Vec<[Drone; 2]> = (0..n)
        .map(|i| stage2_spawn(&w.track, i % 6).map(Drone::spawned))
        .collect();
    let commands: Vec<[MotorCommand; 2]> = (0..n)
        .map(|i| {
            let d = (i % 23) as f32 * 10.0;
            [
                MotorCommand {
                    rpm: [hover + d, hover, hover - d, hover + 1.0],
                },
                MotorCommand {
                    rpm: [hover, hover + d, hover, hover - d],
                },
            ]
        })
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let mut worlds = start.clone();
        let mut out = vec![[DroneStep::default(); 2]; n];
        pool.install(|| {
            for _ in 0..50 {
                w.par_step(&mut worlds, &commands, &mut out);
            }
        });
        (worlds, out)
    };
    let (one, out1) = run(1);
    let (four, out4) = run(4);
    assert_eq!(one, four);
    assert_eq!(out1, out4);
    let mut serial = start.clone();
    for _ in 0..50 {
        for (d, c) in serial.iter_mut().zip(&commands) {
            w.step(d, c);
        }
    }
    assert_eq!(one, serial);
    // The commands differ, so the worlds do too.
    assert_ne!(one[0], one[1]);
}

/// An evaluation is a function of its seed: the same on 1 and 3 threads, and different
/// spawns for a different seed.
#[test]
fn evaluations_are_deterministic_per_seed() {
    let preset = Preset::paper();
    let ego = PilotSpec::load("baseline:8:0.4", &preset).unwrap();
    let opp = PilotSpec::load("baseline:6.5", &preset).unwrap();
    let config = |seed| EvalConfig {
        preset,
        episodes: 6,
        seconds: 10.0,
        seed,
        spawn: None,
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| evaluate(&ego, Some(&opp), &config(seed), true))
    };
    let a = run(1, 7);
    let b = run(3, 7);
    let c = run(3, 8);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.metrics, y.metrics);
        assert_eq!(x.trace, y.trace);
    }
    let starts = |e: &[sitl::referee::Episode]| -> Vec<Vec3> {
        e.iter().map(|x| x.trace.ego_m[0]).collect()
    };
    assert_ne!(starts(&a), starts(&c));
    assert_eq!(a[0].trace.ego_m.len(), 500);
    assert_eq!(a[0].trace.opponent_m.len(), 500);
}
