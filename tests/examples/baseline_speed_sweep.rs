//! Sweeps the baseline's cruise speed on a preset: gates, crashes and best lap in 45 s.
//! `cargo run --release -p overtake-tests --example baseline_speed_sweep [paper|nominal]`
use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{CrashRules, GateEvent, Track};
use firmware_core::vehicle::VehicleState;
use sitl::dynamics::{Body, Preset};

fn main() {
    let name = std::env::args().nth(1).unwrap_or_else(|| "paper".into());
    let preset = Preset::by_name(&name).expect("preset: paper, nominal or realistic");
    let base = if name == "paper" { BaselineConfig::paper() } else { BaselineConfig::nominal() };
    let track = Track::figure_eight();
    let rules = CrashRules::STAGE1;
    let spawn = VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY);
    for speed in [4.0f32, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0] {
        let config = BaselineConfig { cruise_speed_mps: speed, ..base };
        let mut body = Body::new(spawn);
        let mut ctrl = BaselineController::new(config, track);
        let (mut gates, mut crashes, mut best, mut lap_start) = (0, 0, f32::INFINITY, None::<f32>);
        for k in 0..2250 {
            let t = k as f32 * 0.02;
            let (c, e) = ctrl.step(&body.state);
            if let GateEvent::Passed { gate, .. } = e {
                gates += 1;
                if gate == 0 {
                    if let Some(t0) = lap_start { best = best.min(t - t0) }
                    lap_start = Some(t);
                }
            }
            let target = track.gate(ctrl.progress().target).center_m;
            if matches!(e, GateEvent::Collided { .. }) || rules.below_ground(body.state.position_m) || rules.out_of_bounds(target, body.state.position_m) {
                crashes += 1;
                body = Body::new(spawn);
                ctrl.reset(0);
                lap_start = None;
                continue;
            }
            body.step(&preset, &c, 0.02);
        }
        println!("{name} cruise {speed:4.1} m/s: {gates:3} gates, {crashes} crashes, best lap {best:.2} s");
    }
}
