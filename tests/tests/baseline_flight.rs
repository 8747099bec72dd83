//! The classical baseline controller flies the figure-8 in the simulated cf2x dynamics: the
//! proof that the track, the gate frames and the dynamics are flyable. (The referee's full
//! scoring of the baseline comes with the "world" issue's `sitl eval`.)

use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{CrashRules, GateEvent, Track};
use firmware_core::vehicle::VehicleState;
use sitl::dynamics::{Body, Preset};

struct Flight {
    gates_passed: u32,
    crashes: u32,
    first_lap_s: Option<f32>,
}

fn fly(preset: Preset, config: BaselineConfig, seconds: f32) -> Flight {
    let track = Track::figure_eight();
    let rules = CrashRules::STAGE1;
    let spawn = VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY);
    let mut body = Body::new(spawn);
    let mut ctrl = BaselineController::new(config, track);
    let dt = 0.02;
    let steps = (seconds / dt) as usize;
    let mut flight = Flight { gates_passed: 0, crashes: 0, first_lap_s: None };
    let mut lap_start: Option<f32> = None;
    for k in 0..steps {
        let (command, event) = ctrl.step(&body.state);
        let t = k as f32 * dt;
        match event {
            GateEvent::Passed { gate, .. } => {
                flight.gates_passed += 1;
                if gate == 0 {
                    if let (Some(t0), None) = (lap_start, flight.first_lap_s) {
                        flight.first_lap_s = Some(t - t0);
                    }
                    lap_start = Some(t);
                }
            }
            GateEvent::Collided { .. } => flight.crashes += 1,
            GateEvent::None => {}
        }
        let crashed = matches!(event, GateEvent::Collided { .. })
            || rules.below_ground(body.state.position_m)
            || rules.out_of_bounds(track.gate(ctrl.progress().target).center_m, body.state.position_m);
        if crashed {
            if !matches!(event, GateEvent::Collided { .. }) {
                flight.crashes += 1;
            }
            body = Body::new(spawn);
            ctrl.reset(0);
            lap_start = None;
            continue;
        }
        body.step(&preset, &command, dt);
    }
    flight
}

#[test]
fn baseline_hovers_at_the_spawn_without_drifting_down() {
    // The first second from rest: the drone must neither fall nor climb away.
    let preset = Preset::paper();
    let mut body = Body::new(VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY));
    let mut ctrl = BaselineController::new(BaselineConfig::paper(), Track::figure_eight());
    for _ in 0..50 {
        let (c, _) = ctrl.step(&body.state);
        body.step(&preset, &c, 0.02);
    }
    let z = body.state.position_m.z;
    assert!((0.6..1.4).contains(&z), "z after 1 s: {z}");
}

#[test]
fn baseline_flies_laps_of_the_figure_eight_on_the_paper_preset() {
    let f = fly(Preset::paper(), BaselineConfig::paper(), 45.0);
    println!("paper: {} gates, {} crashes, first lap {:?} s", f.gates_passed, f.crashes, f.first_lap_s);
    assert_eq!(f.crashes, 0);
    assert!(f.gates_passed >= 18, "only {} gates in 45 s", f.gates_passed);
    assert!(f.first_lap_s.is_some());
}

#[test]
fn baseline_flies_laps_on_the_nominal_preset() {
    let f = fly(Preset::nominal(), BaselineConfig::nominal(), 45.0);
    println!("nominal: {} gates, {} crashes, first lap {:?} s", f.gates_passed, f.crashes, f.first_lap_s);
    assert_eq!(f.crashes, 0);
    assert!(f.gates_passed >= 18, "only {} gates in 45 s", f.gates_passed);
}
