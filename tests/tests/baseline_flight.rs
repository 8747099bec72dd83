//! The classical baseline controller flies the figure-8 in the simulated cf2x dynamics, scored
//! by the referee: the proof that the track, the gate frames and the dynamics are flyable,
//! and the numbers the README quotes (`sitl eval --ego baseline`).

use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::track::{CrashRules, Track};
use firmware_core::{MotorCommand, VehicleState};
use sitl::dynamics::{Body, Preset};
use sitl::eval::{EvalConfig, Report};
use sitl::pilot::{Pilot, PilotSpec};
use sitl::referee::{EpisodeConfig, SpawnMode, run_episode};
use sitl::world::{World, stage1_spawn};

#[test]
fn baseline_holds_altitude_from_the_spawn() {
    let preset = Preset::paper();
    let mut body = Body::new(stage1_spawn().state);
    let mut ctrl = BaselineController::new(BaselineConfig::paper(), Track::figure_eight());
    for _ in 0..50 {
        let (c, _) = ctrl.step(&body.state);
        body.step(&preset, &c, 0.02);
    }
    let z = body.state.position_m.z;
    assert!((0.6..1.4).contains(&z), "z after 1 s: {z}");
}

fn report(ego: &str, opponent: Option<&str>, preset: Preset, spawn: Option<SpawnMode>) -> Report {
    let config = EvalConfig {
        preset,
        episodes: 8,
        seconds: 45.0,
        seed: 1,
        spawn,
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let ego = PilotSpec::load(ego, &preset).expect("ego");
    let opponent = opponent.map(|o| PilotSpec::load(o, &preset).expect("opponent"));
    let r = sitl::eval::report(&ego, opponent.as_ref(), &config);
    print!("{}", r.table());
    r
}

/// The README's claim: the baseline completes laps on `paper` (success >= 0.95) and on
/// `nominal`, from the stage-1 spawn and from random points of the track.
#[test]
fn baseline_flies_laps_of_the_figure_eight() {
    for preset in [Preset::paper(), Preset::nominal()] {
        for spawn in [None, Some(SpawnMode::AlongTrack), Some(SpawnMode::Stage2)] {
            let r = report("baseline", None, preset, spawn);
            assert!(r.success_rate >= 0.95, "{}", preset.name);
            assert_eq!(r.crashes, 0, "{}", preset.name);
            assert!(r.laps >= 8 * 2, "{}", preset.name);
            assert!(r.best_lap_s.is_some_and(|t| t < 13.0), "{}", preset.name);
        }
    }
}

/// A faster baseline on a line 0.4 m to the left overtakes a slower one, and the referee
/// sees it: the overtake logic on real flight, not only on scripts.
#[test]
fn a_faster_baseline_overtakes_a_slower_one() {
    let r = report(
        "baseline:8.5:0.4",
        Some("baseline:6"),
        Preset::paper(),
        None,
    );
    assert!(r.overtakes >= 8, "{} overtakes", r.overtakes);
    assert!(r.sustained_overtake_rate.is_some_and(|s| s >= 0.5));
    // The same pair the other way round never gets ahead for long.
    let r = report(
        "baseline:6",
        Some("baseline:8.5:0.4"),
        Preset::paper(),
        None,
    );
    assert!(r.sustained_overtakes <= r.overtakes / 2, "{r:?}");
}

#[test]
fn a_pilot_that_cuts_the_motors_crashes_and_is_respawned() {
    struct Off;
    impl Pilot for Off {
        fn command(&mut self, _: &VehicleState, _: Option<&VehicleState>) -> MotorCommand {
            MotorCommand::STOP
        }
        fn reset(&mut self, _: usize) {}
    }
    // Free fall from 1 m to 0.1 m takes sqrt(2 * 0.9 / 9.81) = 0.43 s: 22 steps, so 10 s holds
    // 22 crashes of 22 steps and one partial fall.
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    let m = run_episode(
        &world,
        &mut Off,
        None,
        &EpisodeConfig::time_trial(10.0),
        0,
        false,
    )
    .metrics;
    assert_eq!(m.crashes, 500 / 22);
    assert_eq!(m.crash_causes.ground, m.crashes);
    assert_eq!(m.gates_passed, 0);
    assert_eq!(m.gates_encountered, m.crashes);
    assert_eq!(m.best_lap_s(), None);
    assert_eq!(m.success_rate(), 0.0);
}
