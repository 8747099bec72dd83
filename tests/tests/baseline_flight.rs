//! The classical baseline controller flies the figure-8 in the simulated cf2x dynamics: the
//! proof that the track, the gate frames and the dynamics are flyable. (The referee's full
//! scoring of the baseline comes with the "world" issue's `sitl eval`.)

use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::track::Track;
use sitl::dynamics::{Body, Preset};
use sitl::time_trial::{fly, stage1_spawn};

#[test]
fn baseline_holds_altitude_from_the_spawn() {
    let preset = Preset::paper();
    let mut body = Body::new(stage1_spawn());
    let mut ctrl = BaselineController::new(BaselineConfig::paper(), Track::figure_eight());
    for _ in 0..50 {
        let (c, _) = ctrl.step(&body.state);
        body.step(&preset, &c, 0.02);
    }
    let z = body.state.position_m.z;
    assert!((0.6..1.4).contains(&z), "z after 1 s: {z}");
}

#[test]
fn baseline_flies_laps_of_the_figure_eight() {
    for (preset, config) in [
        (Preset::paper(), BaselineConfig::paper()),
        (Preset::nominal(), BaselineConfig::nominal()),
    ] {
        let track = Track::figure_eight();
        let mut pilot = BaselineController::new(config, track);
        let s = fly(&mut pilot, &track, &preset, 45.0, 0.02);
        println!("{}: {s:?}", preset.name);
        assert_eq!(s.crashes, 0, "{}", preset.name);
        assert!(
            s.gates_passed >= 18,
            "{}: only {} gates in 45 s",
            preset.name,
            s.gates_passed
        );
        assert!(s.lap_times_s.len() >= 2, "{}", preset.name);
        assert!(s.best_lap_s().is_some_and(|t| t < 14.0), "{}", preset.name);
    }
}

#[test]
fn a_pilot_that_cuts_the_motors_crashes_and_is_respawned() {
    struct Off;
    impl sitl::time_trial::Pilot for Off {
        fn command(&mut self, _: &firmware_core::VehicleState) -> firmware_core::MotorCommand {
            firmware_core::MotorCommand::STOP
        }
        fn reset(&mut self, _: usize) {}
    }
    // Free fall from 1 m to 0.1 m takes sqrt(2 * 0.9 / 9.81) = 0.43 s: 22 steps, so 10 s holds
    // 22 crashes of 22 steps and one partial fall.
    let s = fly(
        &mut Off,
        &Track::figure_eight(),
        &Preset::paper(),
        10.0,
        0.02,
    );
    assert_eq!(s.crashes, 500 / 22);
    assert_eq!(s.gates_passed, 0);
    assert_eq!(s.gates_encountered, s.crashes);
    assert_eq!(s.best_lap_s(), None);
}
