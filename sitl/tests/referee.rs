//! The referee on scripted trajectories whose answers are known by hand: drones are moved
//! along given paths (no dynamics), each step judged by the world's gate test and crash
//! rules and scored by the referee, exactly as in an episode.

use firmware_core::math::Vec3;
use firmware_core::track::{Centerline, CrashRules, Track};
use sitl::dynamics::Preset;
use sitl::referee::{EpisodeMetrics, Referee};
use sitl::world::{CrashCause, Drone, SpawnPoint, World, along_track_spawn};

const DT: f32 = 0.02;

fn world(rules: CrashRules) -> World {
    World::figure_eight(Preset::paper(), rules)
}

fn line() -> Centerline {
    Centerline::new(&Track::figure_eight())
}

/// The point of the centreline at parameter `s`, moved `offset_m` to the left (horizontal).
fn on_line(line: &Centerline, s: f32, offset_m: f32) -> Vec3 {
    let t = line.tangent(s);
    let left = Vec3::new(-t.y, t.x, 0.0);
    line.point(s) + left.scale(offset_m / left.norm())
}

/// When the first crash happened (s) and each drone's cause.
type FirstCrash<const N: usize> = (f32, [Option<CrashCause>; N]);

/// Moves the drones along `paths` (position at time t, s) for `seconds`, scoring each step.
/// Returns the metrics, and the time of the first crash (the script stops there).
fn script<const N: usize>(
    world: &World,
    starts: [SpawnPoint; N],
    paths: [&dyn Fn(f32) -> Vec3; N],
    seconds: f32,
) -> (EpisodeMetrics, Option<FirstCrash<N>>) {
    let mut drones = starts.map(Drone::spawned);
    for (d, p) in drones.iter_mut().zip(&paths) {
        d.body.state.position_m = p(0.0);
    }
    let mut referee = Referee::new(&world.track, DT);
    referee.restart(&drones);
    let steps = (seconds / DT).round() as u32;
    for k in 1..=steps {
        let t = k as f32 * DT;
        let from = drones.each_ref().map(Drone::position_m);
        for (d, p) in drones.iter_mut().zip(&paths) {
            d.body.state.position_m = p(t);
        }
        let results = world.judge(&mut drones, &from);
        if referee.score(&drones, &results) {
            let causes = results.map(|r| r.crash);
            return (referee.finish(), Some((t, causes)));
        }
    }
    (referee.finish(), None)
}

/// Along the centreline at one parameter unit per second (a lap of six gates in 6 s, about
/// 11.4 m/s) from s = 5.51, just before g0, for 15 s: it crosses s = 6, 7, …, 20, which is
/// 15 gates, and g0 at s = 6, 12 and 18: two laps of exactly 300 steps.
#[test]
fn a_scripted_lap() {
    let line = line();
    let path = |t: f32| line.point(5.51 + t);
    let start = along_track_spawn(&line, 5.51);
    assert_eq!(start.target_gate, 0);
    let (m, crash) = script(&world(CrashRules::STAGE1), [start], [&path], 15.0);
    assert_eq!(crash, None);
    assert_eq!(m.gates_passed, 15);
    assert_eq!(m.gates_encountered, 15);
    assert_eq!(m.crashes, 0);
    assert_eq!(m.lap_times_s.len(), 2);
    for lap in &m.lap_times_s {
        assert!((lap - 6.0).abs() < 1e-5, "lap {lap} s");
    }
    assert_eq!(m.success_rate(), 1.0);
    assert!((m.sim_seconds - 15.0).abs() < 1e-4);
}

/// Through g0 and g1, then straight down: the ground (z < 0.1 m, from z = 1 at 1 m/s) is hit
/// 0.91 s after leaving the line. Two gates passed, the third (g2) encountered at the crash.
#[test]
fn a_scripted_crash_into_the_ground() {
    let line = line();
    let leave = 7.3; // past g1 (s = 7), on the segment to g2
    let path = |t: f32| {
        let s = 5.51 + t;
        if s < leave {
            line.point(s)
        } else {
            line.point(leave) - Vec3::new(0.0, 0.0, t - (leave - 5.51))
        }
    };
    let (m, crash) = script(
        &world(CrashRules::STAGE1),
        [along_track_spawn(&line, 5.51)],
        [&path],
        10.0,
    );
    let (t, [cause]) = crash.expect("crashes");
    assert_eq!(cause, Some(CrashCause::Ground));
    let expected = (leave - 5.51) + 0.9;
    assert!(
        (t - expected).abs() <= DT + 1e-4,
        "crash at {t} s, expected {expected}"
    );
    assert_eq!((m.gates_passed, m.gates_encountered, m.crashes), (2, 3, 1));
    assert!((m.success_rate() - 2.0 / 3.0).abs() < 1e-12);
    assert!(m.lap_times_s.is_empty());
}

/// A path that crosses g0's plane 1 m to the side of the centre (outside the 0.8 m
/// half-opening): a gate-frame crash, with g0 encountered and not passed.
#[test]
fn a_scripted_crash_into_a_gate_frame() {
    let track = Track::figure_eight();
    let g0 = track.gate(0);
    // 9 m/s along g0's x axis, 1 m to its left: the plane is crossed between two steps.
    let path = |t: f32| g0.to_world_frame(Vec3::new(-2.0 + 9.0 * t, 1.0, 0.0));
    let start = SpawnPoint {
        state: firmware_core::VehicleState::at_rest(path(0.0), firmware_core::math::Quat::IDENTITY),
        target_gate: 0,
    };
    let (m, crash) = script(&world(CrashRules::STAGE1), [start], [&path], 2.0);
    let (t, [cause]) = crash.expect("crashes");
    assert_eq!(cause, Some(CrashCause::GateFrame { gate: 0 }));
    // The plane is at 2/9 s = 0.222 s: crossed in the step ending at 0.24 s.
    assert!((t - 0.24).abs() < 1e-4, "{t}");
    assert_eq!((m.gates_passed, m.gates_encountered, m.crashes), (0, 1, 1));
}

/// Ego and opponent on the centreline, the ego 0.5 m to the side: the opponent from s = 1.5
/// at 1 /s, the ego from s = 1.3 at 1.2 /s. The ego draws level at t = 1 s (s = 2.5) and
/// leads from then on, across gates and the lap wrap at g0: one overtake, sustained (at
/// t = 3 s).
#[test]
fn a_scripted_sustained_overtake() {
    let line = line();
    let ego = |t: f32| on_line(&line, 1.3 + 1.2 * t, 0.5);
    let opp = |t: f32| on_line(&line, 1.5 + t, 0.0);
    let starts = [along_track_spawn(&line, 1.3), along_track_spawn(&line, 1.5)];
    let (m, crash) = script(&world(CrashRules::STAGE2), starts, [&ego, &opp], 8.0);
    assert_eq!(crash, None);
    assert_eq!(m.overtakes, 1);
    assert_eq!(m.sustained_overtakes, 1);
    // Taken at s = 2.5, flying towards the gate at s = 3: counted there.
    let gates = Track::figure_eight().gates().len();
    assert_eq!(m.overtakes_by_gate.len(), 3 % gates + 1, "{m:?}");
    assert_eq!(m.overtakes_by_gate.get(3 % gates), Some(&[1, 1]));
    assert_eq!(m.overtakes_by_gate.iter().flatten().sum::<u32>(), 2);
    // The ego crossed s = 2, 3, …, 10 (it ends at s = 10.9): 9 gates.
    assert_eq!(m.gates_passed, 9);

    // Stopping at 2.9 s, before the lead is 2 s old: the overtake is not sustained yet.
    let (m, _) = script(&world(CrashRules::STAGE2), starts, [&ego, &opp], 2.9);
    assert_eq!((m.overtakes, m.sustained_overtakes), (1, 0));
    assert_eq!(m.overtakes_by_gate.get(3 % gates), Some(&[1, 0]));
    let (m, _) = script(&world(CrashRules::STAGE2), starts, [&ego, &opp], 3.02);
    assert_eq!((m.overtakes, m.sustained_overtakes), (1, 1));
}

/// The same overtake at t = 1 s, but the ego slows to 0.5 /s at t = 1.5 s (s = 3.1) and the
/// opponent draws level again at t = 1.7 s: an overtake held 0.7 s, not sustained.
#[test]
fn a_scripted_overtake_that_is_not_sustained() {
    let line = line();
    let ego_s = |t: f32| {
        if t < 1.5 {
            1.3 + 1.2 * t
        } else {
            3.1 + 0.5 * (t - 1.5)
        }
    };
    let ego = |t: f32| on_line(&line, ego_s(t), 0.5);
    let opp = |t: f32| on_line(&line, 1.5 + t, 0.0);
    let starts = [along_track_spawn(&line, 1.3), along_track_spawn(&line, 1.5)];
    let (m, crash) = script(&world(CrashRules::STAGE2), starts, [&ego, &opp], 6.0);
    assert_eq!(crash, None);
    assert_eq!((m.overtakes, m.sustained_overtakes), (1, 0));
}

/// An overtake ended by the ego's crash within 2 s is not sustained; the crash counts and
/// the drones must be respawned.
#[test]
fn an_overtake_lost_to_a_crash() {
    let line = line();
    let ego = |t: f32| {
        let p = on_line(&line, 1.3 + 1.2 * t, 0.5);
        if t < 2.0 {
            p
        } else {
            p - Vec3::new(0.0, 0.0, 2.0 * (t - 2.0))
        }
    };
    let opp = |t: f32| on_line(&line, 1.5 + t, 0.0);
    let starts = [along_track_spawn(&line, 1.3), along_track_spawn(&line, 1.5)];
    let (m, crash) = script(&world(CrashRules::STAGE2), starts, [&ego, &opp], 6.0);
    let (t, [ego_crash, opp_crash]) = crash.expect("the ego crashes");
    assert_eq!(ego_crash, Some(CrashCause::Ground));
    assert_eq!(opp_crash, None);
    assert!((t - 2.46).abs() < 0.021, "{t}");
    assert_eq!((m.overtakes, m.sustained_overtakes, m.crashes), (1, 0, 1));
}

/// Two drones passing through each other between two steps, 1 m and 2 m apart at its ends:
/// the closest approach (0.05 m) is a collision for both.
#[test]
fn drones_that_cross_between_two_steps_collide() {
    let line = line();
    let a = |t: f32| Vec3::new(100.0 * t, 0.05, 3.0);
    let b = |t: f32| Vec3::new(1.0 - 50.0 * t, 0.0, 3.0);
    let starts = [along_track_spawn(&line, 0.5), along_track_spawn(&line, 0.5)];
    let (_, crash) = script(&world(CrashRules::STAGE2), starts, [&a, &b], 0.1);
    let (t, causes) = crash.expect("collision");
    assert!((t - 0.02).abs() < 1e-6);
    assert_eq!(
        causes,
        [
            Some(CrashCause::Collision { other: 1 }),
            Some(CrashCause::Collision { other: 0 })
        ]
    );
    // 1 m apart at every instant: no collision.
    let beside = |t: f32| a(t) + Vec3::new(0.0, 1.0, 0.0);
    // (Two steps only: at 100 m/s the first drone reaches g1's plane, far off its opening,
    // at t = 0.067 s.)
    let (_, crash) = script(&world(CrashRules::STAGE2), starts, [&a, &beside], 0.04);
    assert_eq!(crash, None);
}

/// A recorded race marks its overtakes where the referee counts them: in every episode of
/// the shipped stage-1 policy against the baseline (16 overtakes in 20 races), the trace
/// holds as many overtakes and sustained ones as the metrics, each at a step where the ego
/// has just moved ahead; and the trace survives its JSON form.
#[test]
fn recorded_traces_mark_the_referees_overtakes() {
    use sitl::eval::{EvalConfig, evaluate};
    use sitl::pilot::PilotSpec;
    use sitl::referee::{SpawnMode, Trace};
    let preset = Preset::paper();
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../policies/stage1_guarded.blob"
    );
    let ego = PilotSpec::load(path, &preset).unwrap();
    let opponent = PilotSpec::load("baseline", &preset).unwrap();
    let config = EvalConfig {
        preset,
        episodes: 20,
        seconds: 45.0,
        seed: 0,
        spawn: Some(SpawnMode::Stage2),
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let episodes = evaluate(&ego, Some(&opponent), &config, true);
    let mut total = 0;
    for e in &episodes {
        let t = &e.trace;
        assert_eq!(t.overtakes.len() as u32, e.metrics.overtakes);
        let sustained = t.overtakes.iter().filter(|m| m.sustained).count() as u32;
        assert_eq!(sustained, e.metrics.sustained_overtakes);
        let by_gate = |c: usize| -> u32 { e.metrics.overtakes_by_gate.iter().map(|g| g[c]).sum() };
        assert_eq!((by_gate(0), by_gate(1)), (e.metrics.overtakes, sustained));
        for m in &t.overtakes {
            assert!((m.step as usize) <= t.ego_m.len() && m.step > 0);
        }
        assert_eq!(Trace::from_json(&t.to_json()).as_ref(), Some(t));
        total += t.overtakes.len();
    }
    assert!(
        total > 0,
        "the policy overtakes the baseline (16 in 20 races)"
    );
}

/// A recurrent blob trained at another control period than the world's (10 ms against
/// 20 ms) is refused by the pilot that would fly it (referee, `sitl fc`, quant checks), with
/// both periods named; an MLP at another period flies (it keeps no state between steps).
#[test]
fn a_recurrent_blob_of_another_period_is_refused_by_the_pilot() {
    use firmware_core::policy::TableRow;
    use sitl::pilot::PilotSpec;
    let blob = |row: TableRow, period_ns: u32| {
        let mut h = firmware_core::synthetic::header(row, 2);
        h.control_period_ns = period_ns;
        let w = firmware_core::synthetic::weights(&h.architecture, 2);
        firmware_core::blob::encode(&h, &w).expect("encode")
    };
    let e = PilotSpec::from_blob("g10ms", &blob(TableRow::G, 10_000_000)).expect_err("refused");
    assert!(
        e.contains("10000000 ns") && e.contains("20000000 ns"),
        "{e}"
    );
    assert!(PilotSpec::from_blob("g20ms", &blob(TableRow::G, 20_000_000)).is_ok());
    assert!(PilotSpec::from_blob("a10ms", &blob(TableRow::A, 10_000_000)).is_ok());
}

/// Flights and the win rate (docs/DESIGN.md "Metrics"): a flight the episode's end finds the
/// ego ahead is won, behind lost; one that the opponent's crash alone ends is won, the ego's
/// crash lost; a time trial has no flights.
#[test]
fn flights_are_won_ahead_at_the_end_or_by_the_opponent_crashing_alone() {
    let line = line();
    let ego = |t: f32| on_line(&line, 1.3 + 1.2 * t, 0.5);
    let opp = |t: f32| on_line(&line, 1.5 + t, 0.0);
    let starts = [along_track_spawn(&line, 1.3), along_track_spawn(&line, 1.5)];
    let race = world(CrashRules::STAGE2);

    // Past the overtake at 1 s: one flight, won.
    let (m, _) = script(&race, starts, [&ego, &opp], 4.0);
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 1, 0));
    assert_eq!(m.win_rate(), Some(1.0));
    // Before it: one flight, lost.
    let (m, _) = script(&race, starts, [&ego, &opp], 0.5);
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 0, 0));
    assert_eq!(m.win_rate(), Some(0.0));

    // The ego ahead, then into the ground: lost, and the episode's end does not count the
    // crashed flight twice.
    let falling_ego = |t: f32| {
        let p = ego(t);
        if t < 2.0 {
            p
        } else {
            p - Vec3::new(0.0, 0.0, 2.0 * (t - 2.0))
        }
    };
    let (m, crash) = script(&race, starts, [&falling_ego, &opp], 6.0);
    assert!(crash.is_some());
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 0, 0));

    // The opponent ahead, then into the ground: won by the ego, still behind.
    let slow_ego = |t: f32| on_line(&line, 1.3 + 0.8 * t, 0.5);
    let falling_opp = |t: f32| {
        let p = opp(t);
        if t < 1.0 {
            p
        } else {
            p - Vec3::new(0.0, 0.0, 2.0 * (t - 1.0))
        }
    };
    let (m, crash) = script(&race, starts, [&slow_ego, &falling_opp], 6.0);
    let (_, [ego_crash, opp_crash]) = crash.expect("the opponent crashes");
    assert_eq!((ego_crash, opp_crash.is_some()), (None, true));
    assert_eq!(m.overtakes, 0);
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 1, 0));

    // A collision: both crash on the same step, and the drone ahead along the track wins.
    // The ego 0.3 m behind on the line at 2.4 m/s, the opponent at rest: the ego runs into it.
    let s0 = 1.5;
    let rear = |t: f32| line.point(s0 - 0.03 + 0.2 * t);
    let parked = |_t: f32| line.point(s0);
    let starts = [
        along_track_spawn(&line, s0 - 0.03),
        along_track_spawn(&line, s0),
    ];
    let (m, crash) = script(&race, starts, [&rear, &parked], 1.0);
    let (_, [ego_crash, opp_crash]) = crash.expect("a collision");
    assert!(
        matches!(ego_crash, Some(CrashCause::Collision { .. })),
        "{ego_crash:?}"
    );
    assert!(
        matches!(opp_crash, Some(CrashCause::Collision { .. })),
        "{opp_crash:?}"
    );
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 0, 0));
    // The same, the roles swapped: the drone ahead is the ego, and it wins.
    let (m, _) = script(&race, [starts[1], starts[0]], [&parked, &rear], 1.0);
    assert_eq!((m.flights, m.flights_won, m.flights_tied), (1, 1, 0));

    // A time trial: no flights, no win rate.
    let path = |t: f32| line.point(5.51 + t);
    let (m, _) = script(
        &world(CrashRules::STAGE1),
        [along_track_spawn(&line, 5.51)],
        [&path],
        3.0,
    );
    assert_eq!((m.flights, m.win_rate()), (0, None));
}

/// Issue "race"'s per-race bar names each miss, scales the sustained overtakes with the
/// races, and counts only the gates where an overtake was held.
#[test]
fn the_race_bar_names_what_a_race_set_misses() {
    use sitl::eval::{GateOvertakes, RaceBar, RaceOutcome};
    let gate = |gate, overtakes, sustained| GateOvertakes {
        gate,
        overtakes,
        sustained,
    };
    let meets = RaceOutcome {
        episodes: 20,
        success_rate: 0.95,
        crash_rate: 0.02,
        best_lap_s: Some(7.8),
        overtakes: 30,
        sustained_overtakes: 16,
        overtakes_by_gate: vec![gate(0, 10, 6), gate(2, 10, 5), gate(4, 8, 5), gate(5, 2, 0)],
    };
    let bar = RaceBar::RACE;
    assert!(bar.misses(&meets).is_empty(), "{:?}", bar.misses(&meets));
    let misses = |change: &dyn Fn(&mut RaceOutcome)| {
        let mut o = meets.clone();
        change(&mut o);
        bar.misses(&o)
    };
    let one = |change: &dyn Fn(&mut RaceOutcome), says: &str| {
        let m = misses(change);
        assert!(m.len() == 1 && m[0].contains(says), "{says}: {m:?}");
    };
    one(&|o| o.success_rate = 0.89, "success");
    one(&|o| o.success_rate = f64::NAN, "success");
    one(&|o| o.crash_rate = 0.11, "crashes");
    one(&|o| o.best_lap_s = Some(8.01), "best lap");
    one(&|o| o.best_lap_s = None, "DNF");
    one(&|o| o.overtakes = 33, "of 33 overtakes");
    // 16 held in 20 races meets the bar; in 21 races it does not (16.8 needed).
    one(&|o| o.episodes = 21, "per 20");
    // The same 16 at two gates: the third gate held no overtake.
    one(
        &|o| o.overtakes_by_gate = vec![gate(0, 15, 8), gate(2, 15, 8), gate(4, 1, 0)],
        "2 gates",
    );
    assert_eq!(misses(&|o| *o = RaceOutcome::default()).len(), 3);
}

/// A race report's JSON reads into the [`sitl::eval::RaceOutcome`] the report gives, so the
/// bar judges the committed `eval.json` files as the trainer judges its referee.
#[test]
fn a_race_reports_json_reads_into_its_race_outcome() {
    use sitl::eval::{EvalConfig, RaceOutcome, report};
    use sitl::pilot::PilotSpec;
    let preset = Preset::paper();
    let blob = |name: &str| format!("{}/../policies/{name}", env!("CARGO_MANIFEST_DIR"));
    let ego = PilotSpec::load(&blob("stage2.blob"), &preset).unwrap();
    let opponent = PilotSpec::load(&blob("stage1.blob"), &preset).unwrap();
    let config = EvalConfig {
        preset,
        episodes: 4,
        seconds: 45.0,
        seed: 0,
        spawn: None,
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let report = report(&ego, Some(&opponent), &config);
    let read: RaceOutcome = serde_json::from_str(&report.to_json()).unwrap();
    assert_eq!(read, RaceOutcome::from(&report));
    assert!(
        read.overtakes > 0 && !read.overtakes_by_gate.is_empty(),
        "{read:?}"
    );
}
