//! The training environment: rewards by hand, episode ends, observations from firmware-core's
//! pipeline, and the baseline controller flying through it.

use firmware_core::baseline::BaselineController;
use firmware_core::observation::{ObservationLayout, ObservationSpec};
use firmware_core::track::{CrashRules, Track};
use firmware_core::vehicle::{ActionMap, MotorCommand};
use sitl::dynamics::Preset;
use sitl::env::{EnvConfig, OBS_DIM, VecEnv};
use sitl::referee::SpawnMode;
use sitl::world::{Drone, World, stage1_spawn};

fn config(num_envs: usize) -> EnvConfig {
    EnvConfig {
        spawn: SpawnMode::Stage1,
        random_initial_episode_length: false,
        ..EnvConfig::paper_along_track(num_envs, 3)
    }
}

/// One step from the stage-1 spawn with a known action: every term against a hand
/// computation on an independent world stepped with the same motor command.
#[test]
fn reward_terms_of_one_step_by_hand() {
    let mut env = VecEnv::time_trial(config(1));
    let a = [0.6f32, 0.5, 0.55, 0.45];
    env.step(&a).unwrap();
    let stats = env.take_stats();

    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    let mut d = [Drone::spawned(stage1_spawn())];
    let g0 = world.track.gate(0).center_m;
    let before = (d[0].position_m() - g0).norm();
    world.step(&mut d, &[ActionMap::PAPER.command(&a)]);
    let after = (d[0].position_m() - g0).norm();
    let dt = 0.02f64;
    let norm = a.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>();
    let expected_progress = dt * 0.5 * f64::from(before - after);
    let expected_command = -dt * 0.0005 * norm.sqrt();
    let expected_smooth = -dt * 0.0002 * norm; // previous action is 0 after a spawn
    let t = stats.terms;
    assert!((t.progress - expected_progress).abs() < 1e-9, "{t:?}");
    assert!((t.command - expected_command).abs() < 1e-9);
    assert!((t.smoothness - expected_smooth).abs() < 1e-9);
    assert_eq!((t.pass, t.crash), (0.0, 0.0));
    assert!((f64::from(env.rewards()[0]) - t.total()).abs() < 1e-7);
    assert_eq!((env.dones()[0], env.timeouts()[0]), (false, false));

    // The observation is firmware-core's for that state and the clipped previous action.
    let spec = ObservationSpec::paper(ObservationLayout::TimeTrial17);
    let obs = spec
        .observe(&d[0].body.state, &world.track.gate(0), &a, None)
        .unwrap();
    assert_eq!(env.observations(), obs.as_slice());
}

/// Motors at the bottom of their range: the drone falls from 1 m and crashes on the ground;
/// that step gets −5·dt, ends the episode (not a time-out), and the next observation is the
/// spawn's.
#[test]
fn a_crash_is_penalised_and_respawned() {
    let mut env = VecEnv::time_trial(config(1));
    let spawn_obs = env.observations().to_vec();
    let mut steps = 0;
    loop {
        env.step(&[-1.0; 4]).unwrap();
        steps += 1;
        if env.dones()[0] {
            break;
        }
        assert!(steps < 100, "never crashed");
    }
    assert!(!env.timeouts()[0]);
    let stats = env.take_stats();
    assert_eq!(stats.crashes, 1);
    assert!((stats.terms.crash + 0.1).abs() < 1e-6);
    assert_eq!(env.observations(), &spawn_obs[..]);
    // Actions beyond [−1, 1] are clipped: −7 is the same fall.
    let mut env2 = VecEnv::time_trial(config(1));
    for _ in 0..steps {
        env2.step(&[-7.0; 4]).unwrap();
    }
    assert!(env2.dones()[0]);
}

#[test]
fn a_time_out_is_not_a_crash() {
    let mut env = VecEnv::time_trial(EnvConfig {
        episode_s: 0.1,
        ..config(2)
    });
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    for k in 1..=5 {
        env.step(&[hover; 8]).unwrap();
        assert_eq!(env.dones(), &[k == 5, k == 5]);
        assert_eq!(env.timeouts(), &[k == 5, k == 5]);
    }
    let stats = env.take_stats();
    assert_eq!((stats.timeouts, stats.crashes, stats.steps), (2, 0, 10));
}

#[test]
fn wrong_action_shapes_are_refused() {
    let mut env = VecEnv::time_trial(config(3));
    let before = env.observations().to_vec();
    let err = env.step(&[0.0; 11]).unwrap_err();
    assert_eq!((err.expected, err.got), (12, 11));
    assert_eq!(env.observations(), &before[..]);
}

/// The same seed gives the same spawns, initial lengths and rewards on 1 and 2 threads.
#[test]
fn deterministic_per_seed() {
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut env = VecEnv::time_trial(EnvConfig {
                spawn: SpawnMode::AlongTrack,
                random_initial_episode_length: true,
                spawn_speed_mps: 0.0,
                stage1_fraction: 0.0,
                seed,
                ..config(300)
            });
            let mut out = env.observations().to_vec();
            for k in 0..20 {
                let a: Vec<f32> = (0..1200)
                    .map(|i| ((i * 7 + k) % 13) as f32 / 6.0 - 1.0)
                    .collect();
                env.step(&a).unwrap();
                out.extend_from_slice(env.rewards());
            }
            out.extend_from_slice(env.observations());
            out
        })
    };
    assert_eq!(run(1, 9), run(2, 9));
    assert_ne!(run(2, 9), run(2, 10));
}

/// The baseline controller flies through the env (its rpm mapped back to actions): 45 s in
/// 3 episodes of 15 s, gates passed without a crash, each pass rewarded close to 1·dt.
#[test]
fn the_baseline_flies_through_the_env() {
    let mut env = VecEnv::time_trial(config(1));
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    let mut pilot = BaselineController::new(
        sitl::pilot::baseline_config_for(&Preset::paper()),
        Track::figure_eight(),
    );
    // The env's state is not public: fly a twin world with the same commands to feed the
    // baseline, and check the env agrees with it.
    let mut twin = [Drone::spawned(stage1_spawn())];
    let map = ActionMap::PAPER;
    for _ in 0..(45.0 / 0.02) as usize {
        let (MotorCommand { rpm }, _) = pilot.step(&twin[0].body.state);
        let a = rpm.map(|r| map.action_for_rpm(r).clamp(-1.0, 1.0));
        env.step(&a).unwrap();
        world.step(&mut twin, &[map.command(&a)]);
        if env.dones()[0] {
            twin = [Drone::spawned(stage1_spawn())];
            pilot.reset(0);
        }
    }
    let s = env.take_stats();
    assert_eq!(s.crashes, 0);
    assert_eq!(s.timeouts, 3);
    assert!(s.gates_passed >= 21, "{s:?}");
    assert!(s.terms.pass > 0.02 * 0.6 * s.gates_passed as f64, "{s:?}");
    assert!(s.terms.pass <= 0.02 * s.gates_passed as f64);
    assert!(s.terms.progress > 0.0);
    assert_eq!(s.success_rate(), 1.0);
    assert_eq!(env.observations().len(), OBS_DIM);
}

// ---- Stage 2: the race ---------------------------------------------------------------

use firmware_core::Controller;
use firmware_core::blob::AlignedBytes;
use sitl::env::{Competition, RaceConfig, dense_competition};
use sitl::world::stage2_spawn;

const OPPONENT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../policies/stage1_guarded.blob"
);

fn opponent_blob() -> Vec<u8> {
    std::fs::read(OPPONENT).expect("the shipped stage-1 policy")
}

fn race_config(num_envs: usize, competition: Competition) -> EnvConfig {
    EnvConfig {
        random_initial_episode_length: false,
        velocity_scale_mps: 3.0,
        race: Some(RaceConfig {
            opponent: OPPONENT.into(),
            competition,
            competition_weight: 0.5,
            ego_ahead_fraction: 0.0,
        }),
        seed: 11,
        ..EnvConfig::stage2(num_envs, OPPONENT)
    }
}

/// `bytes` in a file of its own under the system's temporary directory.
fn blob_file(name: &str, bytes: &[u8]) -> std::path::PathBuf {
    let path = std::env::temp_dir().join(format!("overtake-env-{}-{name}", std::process::id()));
    std::fs::write(&path, bytes).unwrap();
    path
}

/// One race step against a hand computation: the paper's stage-2 spawn (docs/DESIGN.md "Spawns"), the opponent commanded by
/// an independent firmware-core controller on the same states, the ego's action, and every
/// reward term, the dense competition term included, and the 30-value observation.
#[test]
fn one_race_step_by_hand() {
    let mut env = VecEnv::new(race_config(1, Competition::Dense)).unwrap();
    assert_eq!(env.obs_dim(), 30);
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE2);
    let spec = ObservationSpec::paper(ObservationLayout::FullOpponent30);
    // Which gate the env's spawn drew: the one whose stage-2 spawn observes the same.
    let observed = |d: &[Drone; 2], prev: &[f32; 4]| {
        spec.observe(
            &d[0].body.state,
            &world.track.gate(d[0].progress.target),
            prev,
            Some(&d[1].body.state),
        )
        .unwrap()
    };
    let gate = (0..6)
        .find(|&k| {
            let s = stage2_spawn(&world.track, k);
            let d = [Drone::spawned(s[0]), Drone::spawned(s[1])];
            observed(&d, &[0.0; 4]).as_slice() == env.observations()
        })
        .expect("the first observation is a stage-2 spawn's");
    let s = stage2_spawn(&world.track, gate);
    let mut d = [Drone::spawned(s[0]), Drone::spawned(s[1])];
    // The opponent 1 m ahead along the gate's axis, the ego facing it: (1, 0, 0) m / 12.
    let rel = &env.observations()[17..20];
    assert!(
        (rel[0] - 1.0 / 12.0).abs() < 1e-5 && rel[1].abs() < 1e-5,
        "{rel:?}"
    );

    let raw = opponent_blob();
    let bytes = AlignedBytes::new(&raw);
    let mut opponent = Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).unwrap();
    opponent.reset(gate);
    let a = [0.6f32, 0.5, 0.55, 0.45];
    let g = world.track.gate(gate).center_m;
    let before = (d[0].position_m() - g).norm();
    let opp_cmd = opponent
        .step(&d[1].body.state, Some(&d[0].body.state))
        .command;
    let result = world.step(&mut d, &[ActionMap::PAPER.command(&a), opp_cmd]);
    assert!(result.iter().all(|r| r.crash.is_none()));
    env.step(&a).unwrap();
    let t = env.take_stats().terms;

    let dt = 0.02f64;
    let progress = dt * 0.5 * f64::from(before - (d[0].position_m() - g).norm());
    let competition = dt * 0.5 * f64::from(dense_competition(&d[0].body.state, d[1].position_m()));
    assert!((t.progress - progress).abs() < 1e-9, "{t:?}");
    assert!(
        (t.competition - competition).abs() < 1e-9,
        "{t:?} vs {competition}"
    );
    // The opponent is ahead: the dense term is negative.
    assert!(t.competition < 0.0);
    assert!((f64::from(env.rewards()[0]) - t.total()).abs() < 1e-7);
    assert_eq!(env.observations(), observed(&d, &a).as_slice());
}

/// Eq. 6's sign: positive when the ego leads (the opponent behind it along its body x),
/// negative when it trails, zero beside it, and bounded by tanh.
#[test]
fn the_dense_competition_reward_pays_the_leader() {
    use firmware_core::math::{Quat, Vec3};
    use firmware_core::vehicle::VehicleState;
    let ego = VehicleState::at_rest(Vec3::new(0.0, 0.0, 1.0), Quat::from_yaw(0.5));
    let ahead = ego.attitude.rotate(Vec3::new(5.0, 0.0, 0.0));
    let side = ego.attitude.rotate(Vec3::new(0.0, 5.0, 0.0));
    let at = |v: Vec3| dense_competition(&ego, ego.position_m + v);
    assert!((at(ahead) - (-0.5f32).tanh()).abs() < 1e-6);
    assert!((at(ahead.scale(-1.0)) - 0.5f32.tanh()).abs() < 1e-6);
    assert!(at(side).abs() < 1e-6);
    assert!(at(ahead.scale(-1000.0)) <= 1.0);
}

/// The opponent flies: with the ego hovering at its spawn, the shipped stage-1 policy leaves
/// it behind (more than 4 m away after 3 s; it starts 1 m ahead). From stage-2 spawns that policy
/// crashes about once in 19 s (`sitl eval --spawn stage2`: 0.052 /s), which restarts the
/// env, so a few of the 16 may have restarted within the 3 s.
#[test]
fn the_opponent_flies_away_from_a_hovering_ego() {
    let mut env = VecEnv::new(race_config(16, Competition::Dense)).unwrap();
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    let a = vec![hover; 16 * 4];
    for _ in 0..150 {
        env.step(&a).unwrap();
    }
    let stats = env.take_stats();
    assert!(stats.opponent_crashes <= 2, "{stats:?}");
    // The opponent's crashes end the ego's episode as truncations, not as its crashes.
    assert_eq!((stats.crashes, stats.timeouts), (0, 0), "{stats:?}");
    let far = env
        .observations()
        .chunks_exact(30)
        .filter(|o| 12.0 * o[17..20].iter().map(|v| v * v).sum::<f32>().sqrt() > 4.0)
        .count();
    assert!(
        far as u64 + stats.opponent_crashes >= 16,
        "the opponent is over 4 m away after 3 s unless it crashed: {far} far, {stats:?}"
    );
}

/// A bad opponent is refused when the environment is built: a corrupt blob, and a policy that
/// itself needs an opponent.
#[test]
fn a_bad_opponent_is_refused() {
    let mut c = race_config(1, Competition::Sparse);
    let mut raw = opponent_blob();
    let last = raw.len() - 1;
    raw[last] ^= 0x40;
    c.race.as_mut().unwrap().opponent = blob_file("corrupt.blob", &raw);
    let e = VecEnv::new(c).unwrap_err();
    assert!(e.to_string().contains("opponent"), "{e}");
}

/// The `lead` competition term against the referee's own lead (an independent path through
/// `sitl::referee::Referee`): `0.5 dt tanh(0.1 lead)`, negative at the stage-2 spawn where
/// the opponent starts 1 m ahead, and the same whichever way the ego faces.
#[test]
fn the_lead_competition_term_is_the_referees_lead() {
    let mut env = VecEnv::new(race_config(1, Competition::Lead)).unwrap();
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE2);
    let spec = ObservationSpec::paper(ObservationLayout::FullOpponent30);
    let gate = (0..6)
        .find(|&k| {
            let s = stage2_spawn(&world.track, k);
            let d = [Drone::spawned(s[0]), Drone::spawned(s[1])];
            spec.observe(
                &d[0].body.state,
                &world.track.gate(d[0].progress.target),
                &[0.0; 4],
                Some(&d[1].body.state),
            )
            .unwrap()
            .as_slice()
                == env.observations()
        })
        .expect("the first observation is a stage-2 spawn's");
    let s = stage2_spawn(&world.track, gate);
    let mut d = [Drone::spawned(s[0]), Drone::spawned(s[1])];
    let mut referee = sitl::referee::Referee::new(&world.track, world.dt_s);
    referee.restart(&d);
    let raw = opponent_blob();
    let bytes = AlignedBytes::new(&raw);
    let mut opponent = Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).unwrap();
    opponent.reset(gate);
    let a = [0.6f32, 0.5, 0.55, 0.45];
    let opp_cmd = opponent
        .step(&d[1].body.state, Some(&d[0].body.state))
        .command;
    world.step(&mut d, &[ActionMap::PAPER.command(&a), opp_cmd]);
    env.step(&a).unwrap();
    let t = env.take_stats().terms;
    let lead = referee.lead_m(&d).unwrap();
    let expected = 0.02 * 0.5 * f64::from((0.1 * lead).tanh());
    assert!(lead < -0.3 && lead > -1.1, "lead {lead} m");
    assert!(
        (t.competition - expected).abs() < 1e-9,
        "{t:?} vs {expected}"
    );
    assert!(t.competition < 0.0);
    // Facing away from the opponent changes eq. 6's term, not the lead.
    let mut turned = d;
    turned[0].body.state.attitude = firmware_core::math::Quat::from_axis_angle(
        firmware_core::math::Vec3::new(0.0, 0.0, 1.0),
        3.0,
    ) * d[0].body.state.attitude;
    assert_eq!(referee.lead_m(&turned), Some(lead));
    let eq6 = |d: &[Drone; 2]| dense_competition(&d[0].body.state, d[1].position_m());
    assert!(
        eq6(&d) < 0.0 && eq6(&turned) > 0.0,
        "{} {}",
        eq6(&d),
        eq6(&turned)
    );
}

/// The per-env records of each step add up to the batch statistics, each record's terms sum to
/// its env's reward exactly as the reward is computed, and its events agree with `dones` and
/// `timeouts`: a fall ends in a crash, a hover in time-outs, a race in the opponent's crashes.
#[test]
fn step_records_add_up_to_the_stats() {
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    let mut env = VecEnv::time_trial(EnvConfig {
        episode_s: 0.5,
        ..config(4)
    });
    let mut race = VecEnv::new(race_config(8, Competition::Lead)).unwrap();
    let mut events = [0u64; 4];
    // Crashes and time-outs of the time trial, over the run.
    let mut seen = [0u64; 2];
    for k in 0..200 {
        // Envs 0 and 1 fall, 2 and 3 hover until their time-out.
        let fall = if k < 100 { -1.0 } else { hover };
        let a = [[fall; 4], [fall; 4], [hover; 4], [hover; 4]].concat();
        for (env, a) in [(&mut env, a), (&mut race, vec![hover; 32])] {
            env.step(&a).unwrap();
            let mut sum = sitl::env::RewardTerms::default();
            for (i, r) in env.records().iter().enumerate() {
                assert_eq!(env.rewards()[i], r.terms.total() as f32);
                assert_eq!(env.dones()[i], r.crashed || r.timed_out, "{r:?}");
                assert_eq!(env.timeouts()[i], r.timed_out, "{r:?}");
                assert!(!(r.crashed && r.timed_out), "{r:?}");
                assert!(r.timed_out || !r.opponent_crashed, "{r:?}");
                sum.progress += r.terms.progress;
                sum.command += r.terms.command;
                sum.smoothness += r.terms.smoothness;
                sum.pass += r.terms.pass;
                sum.crash += r.terms.crash;
                sum.competition += r.terms.competition;
                events[0] += u64::from(r.gate_passed);
                events[1] += u64::from(r.crashed);
                events[2] += u64::from(r.timed_out && !r.opponent_crashed);
                events[3] += u64::from(r.opponent_crashed);
            }
            let stats = env.take_stats();
            assert_eq!(stats.terms, sum);
            assert_eq!(
                [
                    stats.gates_passed,
                    stats.crashes,
                    stats.timeouts,
                    stats.opponent_crashes
                ],
                events
            );
            if env.obs_dim() == 17 {
                seen[0] += events[1];
                seen[1] += events[2];
            }
            events = [0; 4];
        }
    }
    assert!(seen[0] >= 2 && seen[1] >= 2, "{seen:?}");
}

/// The final observation of an episode is the state it ended in, before the respawn: for a
/// fall, firmware-core's observation of an independent world stepped to the ground.
#[test]
fn the_final_observation_is_the_crash_state() {
    let mut env = VecEnv::time_trial(config(1));
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    let mut d = [Drone::spawned(stage1_spawn())];
    let spec = ObservationSpec::paper(ObservationLayout::TimeTrial17);
    let a = [-1.0f32; 4];
    loop {
        env.step(&a).unwrap();
        world.step(&mut d, &[ActionMap::PAPER.command(&a)]);
        if env.dones()[0] {
            break;
        }
        assert_eq!(
            env.observations(),
            spec.observe(&d[0].body.state, &world.track.gate(0), &a, None)
                .unwrap()
                .as_slice()
        );
    }
    let last = spec
        .observe(&d[0].body.state, &world.track.gate(0), &a, None)
        .unwrap();
    assert!(env.records()[0].crashed);
    assert_eq!(env.final_observations(), last.as_slice());
    assert_ne!(env.final_observations(), env.observations());
}

/// RSL-RL's `init_at_random_ep_len` writes the episode-length buffer: an env set one step
/// short of the limit times out at its next step and only then; the others run on; a
/// wrong-length slice is refused and changes nothing.
#[test]
fn episode_steps_set_from_outside_move_the_time_outs() {
    let mut env = VecEnv::time_trial(config(3));
    let max = env.max_episode_steps();
    let hover = [0.5f32; 12];
    env.step(&hover).unwrap();
    assert_eq!(env.episode_steps(), vec![1, 1, 1]);
    assert!(env.set_episode_steps(&[0, 0]).is_err());
    assert_eq!(env.episode_steps(), vec![1, 1, 1]);
    env.set_episode_steps(&[max - 1, max - 2, 7]).unwrap();
    env.step(&hover).unwrap();
    assert_eq!(env.timeouts(), &[true, false, false]);
    assert_eq!(env.episode_steps(), vec![0, max - 1, 8]);
    env.step(&hover).unwrap();
    assert_eq!(env.timeouts(), &[false, true, false]);
    assert_eq!(env.episode_steps(), vec![1, 0, 9]);
}

/// `replay_fraction = 1`: after a crash the env restarts from the state it flew through
/// right after its (only) gate pass, previous action included: the observation after the
/// crash equals the one after the pass. Without a pass to replay, the spawn rule's own.
#[test]
fn a_replayed_spawn_is_the_state_after_a_gate_pass() {
    let mut env = VecEnv::time_trial(EnvConfig {
        replay_fraction: 1.0,
        ..config(1)
    });
    let mut pilot = BaselineController::new(
        sitl::pilot::baseline_config_for(&Preset::paper()),
        Track::figure_eight(),
    );
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    let mut twin = [Drone::spawned(stage1_spawn())];
    let map = ActionMap::PAPER;
    let after_pass = loop {
        let (MotorCommand { rpm }, _) = pilot.step(&twin[0].body.state);
        let a = rpm.map(|r| map.action_for_rpm(r).clamp(-1.0, 1.0));
        env.step(&a).unwrap();
        world.step(&mut twin, &[map.command(&a)]);
        assert!(!env.dones()[0], "the baseline crashed before g0");
        if env.records()[0].gate_passed {
            break env.observations().to_vec();
        }
    };
    // Motors off until the ground ends the episode; the replay restarts after g0's pass.
    let off = [-1.0f32; 4];
    let mut steps = 0;
    while !env.dones()[0] {
        env.step(&off).unwrap();
        assert!(!env.records()[0].gate_passed);
        steps += 1;
        assert!(steps < 1000, "no crash with the motors off");
    }
    assert!(env.records()[0].crashed);
    assert_eq!(env.observations(), after_pass.as_slice());

    // A fresh env has no pass: its first crash respawns at the stage-1 spawn.
    let mut fresh = VecEnv::time_trial(EnvConfig {
        replay_fraction: 1.0,
        ..config(1)
    });
    let start = fresh.observations().to_vec();
    while !fresh.dones()[0] {
        fresh.step(&off).unwrap();
    }
    assert_eq!(fresh.observations(), start.as_slice());
}

/// How many different attitudes the envs observe (observation 3..7).
fn distinct_attitudes(env: &VecEnv) -> usize {
    let mut attitudes: Vec<&[f32]> = env
        .observations()
        .chunks_exact(OBS_DIM)
        .map(|o| &o[3..7])
        .collect();
    attitudes.sort_by(|a, b| a.partial_cmp(b).unwrap());
    attitudes.dedup();
    attitudes.len()
}

/// `stage2_fraction = 1`: every time-trial spawn is the paper's stage-2 start, at rest
/// (whatever the spawn speed) 2 m (the ego's) or 1 m (the opponent's) before its target gate
/// on the gate's axis, both distances and every heading drawn; with 0 none is.
#[test]
fn stage2_spawns_start_at_rest_one_or_two_metres_before_a_gate() {
    let along = |fraction: f32| {
        VecEnv::time_trial(EnvConfig {
            spawn: SpawnMode::AlongTrack,
            spawn_speed_mps: 8.0,
            stage2_fraction: fraction,
            random_initial_episode_length: false,
            ..EnvConfig::paper_along_track(64, 5)
        })
    };
    // Observation: the gate seen from the drone / 12 m (0..3), attitude (3..7), body
    // velocity (7..10).
    let before = |o: &[f32], d: f32| {
        (o[0] - d / 12.0).abs() < 1e-5
            && o[1].abs() < 1e-5
            && o[2].abs() < 1e-5
            && o[7..10].iter().all(|v| *v == 0.0)
    };
    let count = |env: &VecEnv, d: f32| {
        env.observations()
            .chunks_exact(OBS_DIM)
            .filter(|o| before(o, d))
            .count()
    };
    let env = along(1.0);
    let (two, one) = (count(&env, 2.0), count(&env, 1.0));
    assert_eq!(two + one, 64);
    assert!(
        two > 16 && one > 16,
        "{two} ego starts, {one} opponent starts"
    );
    // The six gates have four headings (g1 and g5 share theirs, g2 and g4 theirs).
    assert_eq!(distinct_attitudes(&env), 4);
    let none = along(0.0);
    assert_eq!(count(&none, 2.0) + count(&none, 1.0), 0);
}

/// `spawn_jitter`: the ego's start moved as `sitl eval --jitter` moves it. From stage-2
/// spawns every env's first observation differs from the unjittered one, the gate stays
/// 1 or 2 m away within the position jitter, the drone drifts at most the velocity jitter
/// per axis, and the four headings become one per env; without it the serialised config
/// names no jitter, and a bad jitter text is refused by its key.
#[test]
fn a_jittered_spawn_moves_the_ego_start_within_its_bounds() {
    use sitl::perturb::JitterSpec;
    let stage2 = |jitter: Option<&str>| {
        VecEnv::time_trial(EnvConfig {
            spawn: SpawnMode::AlongTrack,
            stage2_fraction: 1.0,
            random_initial_episode_length: false,
            spawn_jitter: jitter.map(|j| JitterSpec::parse(j).unwrap()),
            ..EnvConfig::paper_along_track(64, 5)
        })
    };
    let plain = stage2(None);
    let jittered = stage2(Some(""));
    let scale = EnvConfig::paper_along_track(1, 0).velocity_scale_mps;
    let pairs = plain
        .observations()
        .chunks_exact(OBS_DIM)
        .zip(jittered.observations().chunks_exact(OBS_DIM));
    for (i, (p, j)) in pairs.enumerate() {
        assert_ne!(p, j, "env {i} was not jittered");
        let distance = |o: &[f32]| 12.0 * o[..3].iter().map(|v| v * v).sum::<f32>().sqrt();
        let moved = (distance(p) - distance(j)).abs();
        assert!(moved <= 0.05 * 3f32.sqrt() + 1e-4, "env {i}: {moved} m");
        let speed = scale * j[7..10].iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!(
            speed > 0.0 && speed <= 0.2 * 3f32.sqrt() + 1e-4,
            "env {i}: {speed} m/s"
        );
    }
    assert_eq!(distinct_attitudes(&jittered), 64);
    let text = serde_json::to_string(&EnvConfig::paper_along_track(1, 0)).unwrap();
    assert!(!text.contains("jitter"), "{text}");
    for bad in ["pos=-0.1", "att-deg=100", "wobble=1", "vel=x"] {
        let e = JitterSpec::parse(bad).unwrap_err();
        assert!(e.contains("jitter"), "{bad}: {e}");
    }
}

/// The mirror images a learner trains on (`VecEnv::mirrored_observations`), against the
/// reflection worked out by hand for the figure-8 (sitl::mirror): attitude (w, x, y, z) ↦
/// (z, −y, −x, w) (conjugated by the x = 0 reflection, then yawed by π), body velocity
/// (vx, −vy, vz), body rates (−ωx, ωy, −ωz), the previous action's motors renumbered
/// 0 ↔ 3, 1 ↔ 2, and the gate seen from the drone with x kept and exactly one
/// of y, z negated (the paper's frames of g1 and g2 are upside down, their mirrors g4 and g5
/// upright).
#[test]
fn mirrored_observations_are_the_reflection_by_hand() {
    let mut env = VecEnv::time_trial(EnvConfig::paper_along_track(64, 11));
    let mut actions = vec![0.0f32; 64 * 4];
    for (i, a) in actions.iter_mut().enumerate() {
        *a = 0.4 + 0.3 * ((i * 7 % 11) as f32 / 11.0 - 0.5);
    }
    let mut mirrored = Vec::new();
    let mut flips = [0usize; 2];
    for _ in 0..5 {
        env.step(&actions).unwrap();
        env.mirrored_observations(&mut mirrored).unwrap();
        assert_eq!(mirrored.len(), env.observations().len());
        for (o, m) in env
            .observations()
            .chunks_exact(OBS_DIM)
            .zip(mirrored.chunks_exact(OBS_DIM))
        {
            let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
            assert!(close(m[0], o[0]), "gate x: {o:?} {m:?}");
            let y_flipped = close(m[1], -o[1]) && close(m[2], o[2]);
            let z_flipped = close(m[1], o[1]) && close(m[2], -o[2]);
            assert!(y_flipped || z_flipped, "gate y, z: {o:?} {m:?}");
            flips[usize::from(z_flipped && !y_flipped)] += 1;
            let want = [
                o[6], -o[5], -o[4], o[3], // attitude
                o[7], -o[8], o[9], // body velocity
                -o[10], o[11], -o[12], // body rates
                o[16], o[15], o[14], o[13], // previous action
            ];
            for (k, (w, g)) in want.iter().zip(&m[3..]).enumerate() {
                assert!(close(*w, *g), "value {}: {w} vs {g}", k + 3);
            }
        }
    }
    // Both kinds of gate pair were seen.
    assert!(flips[0] > 0 && flips[1] > 0, "{flips:?}");
}

/// A folded env (`ObservationSpec::with_fold`, firmware_core::mirror): the same flights as a
/// plain env of the same seed when each action on the mirrored half (targets g3-g5) is given
/// as its image, and then it observes g0-g2 as the plain env does and g3-g5 as the plain
/// env's mirror images. An action not renumbered back would fly another flight, and the
/// observations would part.
#[test]
fn a_folded_env_observes_the_mirrored_half_as_its_image() {
    let plain_config = EnvConfig::paper_along_track(64, 5);
    let folded_config = EnvConfig {
        fold_mirror: true,
        ..plain_config.clone()
    };
    let mut plain = VecEnv::time_trial(plain_config);
    let mut folded = VecEnv::time_trial(folded_config);
    let mirror = plain.mirror().unwrap().clone();
    let mut mirrored = Vec::new();
    let mut seen = [0usize; 2];
    for step in 0..60 {
        plain.mirrored_observations(&mut mirrored).unwrap();
        let targets: Vec<usize> = plain.target_gates().collect();
        assert_eq!(targets, folded.target_gates().collect::<Vec<_>>());
        for (i, &t) in targets.iter().enumerate() {
            let row = i * OBS_DIM..(i + 1) * OBS_DIM;
            let want = if t >= 3 {
                &mirrored[row.clone()]
            } else {
                &plain.observations()[row.clone()]
            };
            assert_eq!(
                &folded.observations()[row],
                want,
                "step {step}, env {i}, target {t}"
            );
            seen[usize::from(t >= 3)] += 1;
        }
        let world: Vec<f32> = (0..64 * 4)
            .map(|k| 0.45 + 0.4 * (((k * 7 + step * 3) % 13) as f32 / 13.0 - 0.5))
            .collect();
        let mut given = world.clone();
        for (i, &t) in targets.iter().enumerate() {
            if t >= 3 {
                let a: [f32; 4] = world[i * 4..i * 4 + 4].try_into().unwrap();
                given[i * 4..i * 4 + 4].copy_from_slice(&mirror.motors(&a));
            }
        }
        plain.step(&world).unwrap();
        folded.step(&given).unwrap();
        assert_eq!(plain.rewards(), folded.rewards(), "step {step}");
        assert_eq!(plain.dones(), folded.dones(), "step {step}");
    }
    assert!(seen[0] > 100 && seen[1] > 100, "{seen:?}");
}

// ---- The environment's schema ---------------------------------------------------------

/// `EnvConfig` round-trips through serde (the `[env]` table; the other sections are not
/// part of it), refuses unknown fields, and its `validate` names the field out of range.
#[test]
fn the_env_config_round_trips_and_names_bad_fields() {
    let shipped = EnvConfig::stage1(512);
    let json = serde_json::to_string(&shipped).unwrap();
    let back: EnvConfig = serde_json::from_str(&json).unwrap();
    // Everything but the reward (`[reward]`, a table of its own) comes back.
    assert_eq!(
        EnvConfig {
            reward: shipped.reward,
            ..back.clone()
        },
        shipped
    );
    assert_eq!(back.observation_spec(), shipped.observation_spec());
    assert!(json.contains("\"spawn\":\"along-track\"") && json.contains("\"preset\":\"paper\""));
    assert!(serde_json::from_str::<EnvConfig>(&json.replace("num_envs", "num_env")).is_err());
    let paper = EnvConfig::paper(8);
    paper.validate().unwrap();
    let cases: [(EnvConfig, &str); 8] = [
        (
            EnvConfig {
                num_envs: 0,
                ..paper.clone()
            },
            "num_envs",
        ),
        (
            EnvConfig {
                num_envs: sitl::env::MAX_ENVS + 1,
                ..paper.clone()
            },
            "num_envs",
        ),
        (
            EnvConfig {
                episode_s: f32::NAN,
                ..paper.clone()
            },
            "episode_s",
        ),
        (
            EnvConfig {
                velocity_scale_mps: 0.0,
                ..paper.clone()
            },
            "velocity_scale_mps",
        ),
        (
            EnvConfig {
                stage1_fraction: 1.5,
                ..paper.clone()
            },
            "stage1_fraction",
        ),
        (
            EnvConfig {
                spawn_speed_mps: -1.0,
                ..paper.clone()
            },
            "spawn_speed_mps",
        ),
        (
            EnvConfig {
                reward: sitl::env::RewardWeights {
                    progress: f32::NAN,
                    ..Default::default()
                },
                ..paper.clone()
            },
            "reward.progress",
        ),
        (
            EnvConfig {
                layout: ObservationLayout::FullOpponent30,
                ..paper.clone()
            },
            "layout",
        ),
    ];
    for (config, field) in cases {
        let e = config.validate().unwrap_err();
        assert_eq!(e.field, field, "{e}");
        assert!(VecEnv::new(config).is_err());
    }
    let mut race = race_config(1, Competition::Dense);
    race.spawn = SpawnMode::AlongTrack;
    assert_eq!(race.validate().unwrap_err().field, "spawn");
}

/// An opponent that is missing, or a path that is no blob at all (endless), is refused when
/// the environment is built, with the path, and without reading without end.
#[test]
fn an_unreadable_opponent_is_refused_with_its_path() {
    let mut c = race_config(1, Competition::Dense);
    c.race.as_mut().unwrap().opponent = "/nonexistent/opponent.blob".into();
    match VecEnv::new(c.clone()).unwrap_err() {
        sitl::env::EnvError::ReadOpponent { kind, path, .. } => {
            assert_eq!(kind, std::io::ErrorKind::NotFound);
            assert_eq!(path, std::path::Path::new("/nonexistent/opponent.blob"));
        }
        e => panic!("{e}"),
    }
    if std::path::Path::new("/dev/zero").exists() {
        c.race.as_mut().unwrap().opponent = "/dev/zero".into();
        let e = VecEnv::new(c).unwrap_err().to_string();
        assert!(e.contains("/dev/zero") && e.contains("not a blob"), "{e}");
    }
}

/// A NaN or infinite action component flies as 0 (the same flight as a 0) and is counted.
#[test]
fn nonfinite_actions_fly_as_zero_and_are_counted() {
    let mut zeros = VecEnv::time_trial(config(2));
    let mut nans = VecEnv::time_trial(config(2));
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    for k in 0..20 {
        let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::NAN][k % 4];
        zeros
            .step(&[hover, 0.0, hover, hover, hover, hover, hover, hover])
            .unwrap();
        nans.step(&[hover, bad, hover, hover, hover, hover, hover, hover])
            .unwrap();
        assert_eq!(zeros.observations(), nans.observations());
    }
    assert_eq!(zeros.take_stats().nonfinite_actions, 0);
    assert_eq!(nans.take_stats().nonfinite_actions, 20);
}

/// A policy that observes otherwise than the envs (the shipped stage-1 policy, velocity
/// scale 12 and folded, in the paper's environment) is refused, naming each difference;
/// the envs built as the policy observes accept it.
#[test]
fn a_policy_that_observes_otherwise_is_refused() {
    let raw = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../policies/stage1.blob"
    ))
    .unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = firmware_core::blob::Blob::parse(bytes.as_bytes()).unwrap();
    let spec = blob.header().observation;
    let paper = EnvConfig::paper(4);
    let e = paper.check_policy(&spec).unwrap_err().to_string();
    assert!(
        e.contains("velocity_scale_mps") && e.contains("fold_mirror"),
        "{e}"
    );
    paper
        .clone()
        .observing_as(&spec)
        .check_policy(&spec)
        .unwrap();
    EnvConfig::stage1(4).check_policy(&spec).unwrap();
    let race = race_config(1, Competition::Dense);
    assert!(
        race.check_policy(&spec)
            .unwrap_err()
            .to_string()
            .contains("layout")
    );
}

/// The race env steps its opponents 16 side by side (`sitl::lanes`): the trajectories are
/// those of `Controller::step` one by one. Slot k of a 48-env race (every opponent in a
/// group of 16) flies exactly as the same slot of a (k+1)-env race, where it is in the
/// remainder stepped one by one: observations, rewards and episode ends, over 400 steps
/// with the opponent `policies/stage1.blob` and crashes and respawns on the way.
#[test]
fn opponents_stepped_side_by_side_fly_as_one_by_one() {
    let stage1 = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");
    let config = |n: usize| EnvConfig {
        random_initial_episode_length: true,
        seed: 5,
        ..EnvConfig::stage2(n, stage1)
    };
    let action = |slot: usize, t: usize| -> [f32; 4] {
        // A hover-ish command with a slot- and step-dependent wobble: some envs crash.
        core::array::from_fn(|k| (0.3 * ((slot * 7 + t * 3 + k * 5) as f32 * 0.37).sin()) - 0.05)
    };
    let dim = VecEnv::new(config(1)).unwrap().obs_dim();
    for k in [0usize, 16, 33] {
        let mut alone = VecEnv::new(config(k + 1)).unwrap();
        let mut wide_k = VecEnv::new(config(48)).unwrap();
        let mut ends = 0;
        for t in 0..400 {
            let a_wide: Vec<f32> = (0..48).flat_map(|s| action(s, t)).collect();
            let a_alone: Vec<f32> = (0..=k).flat_map(|s| action(s, t)).collect();
            wide_k.step(&a_wide).unwrap();
            alone.step(&a_alone).unwrap();
            let row = k * dim..(k + 1) * dim;
            assert_eq!(
                wide_k.observations()[row.clone()],
                alone.observations()[row],
                "slot {k}, step {t}"
            );
            assert_eq!(wide_k.rewards()[k].to_bits(), alone.rewards()[k].to_bits());
            assert_eq!(wide_k.dones()[k], alone.dones()[k]);
            ends += usize::from(alone.dones()[k]);
        }
        assert!(
            ends > 0,
            "slot {k}: no episode ended, the test saw no respawn"
        );
    }
}

/// `randomize` perturbs the ego as the referee's `--perturb` does: sensor noise changes what
/// it observes and not where it flies (the rewards, computed from the true state, are bit
/// for bit the nominal ones), an airframe change and a latency change where it flies, and
/// without `randomize` the config serialises as before (no key: shipped config hashes hold).
#[test]
fn randomize_perturbs_the_ego_as_the_referee_does() {
    use sitl::perturb::PerturbSpec;
    let with = |spec: &str| {
        VecEnv::time_trial(EnvConfig {
            randomize: Some(PerturbSpec::parse(spec).unwrap()),
            ..config(4)
        })
    };
    let fly = |mut env: VecEnv| {
        let mut rewards = Vec::new();
        let mut observations = env.observations().to_vec();
        for k in 0..30 {
            let a = vec![0.5 + 0.01 * k as f32; 16];
            env.step(&a).unwrap();
            rewards.extend_from_slice(env.rewards());
            observations.extend_from_slice(env.observations());
        }
        (rewards, observations)
    };
    let nominal = fly(VecEnv::time_trial(config(4)));
    let noisy = fly(with("noise=1"));
    assert_eq!(noisy.0, nominal.0, "noise moved the drone");
    assert_ne!(noisy.1, nominal.1, "noise did not reach the observations");
    let worst = noisy
        .1
        .iter()
        .zip(&nominal.1)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst < 0.5,
        "noise of a Crazyflie's size, not garbage: {worst}"
    );
    // Randomising never moves the spawns: the first observation with a new airframe is
    // the nominal one.
    for spec in ["latency=1", "thrust=0.9", "mass=1.1", "motor-tau-ms=30"] {
        assert_eq!(
            with(spec).observations(),
            VecEnv::time_trial(config(4)).observations()
        );
        let perturbed = fly(with(spec));
        assert_ne!(perturbed.0, nominal.0, "{spec} did not change the flight");
    }
    // The first step of a 1-step latency flies stopped motors: the ego loses height and
    // the progress reward of that step differs, where the noise-free airframe draws
    // nothing else.
    let late = fly(with("latency=1"));
    assert_ne!(late.0[0], nominal.0[0]);
    let json = serde_json::to_value(config(1)).unwrap();
    assert!(json.get("randomize").is_none(), "{json}");
    let bad: Result<EnvConfig, _> = serde_json::from_value(serde_json::json!({
        "num_envs": 1, "preset": "paper", "spawn": "stage1", "episode_s": 15.0,
        "random_initial_episode_length": false, "randomize": "mass=-1"
    }));
    let e = bad.unwrap_err().to_string();
    assert!(e.contains("mass: must lie in [0.1, 10]"), "{e}");
    let json = serde_json::to_value(EnvConfig {
        randomize: Some(PerturbSpec::parse("latency=0:1, noise=1").unwrap()),
        ..config(1)
    })
    .unwrap();
    assert_eq!(json["randomize"], "latency=0:1, noise=1");
}

/// `randomize_share`: at 0 a randomised config flies bit for bit the nominal envs through
/// their respawns (nothing drawn reaches the flight, the spawns stay); at 1 it is the plain
/// randomised config; in between some envs fly perturbed and some not; changed by
/// `set_randomize_share` from the next spawn on; a share outside [0, 1] is refused by name,
/// and a share of 1 leaves the serialised config as before.
#[test]
fn a_share_of_the_spawns_is_randomised() {
    use sitl::perturb::PerturbSpec;
    let with = |share: f32| {
        VecEnv::time_trial(EnvConfig {
            randomize: Some(PerturbSpec::parse("thrust=0.7,latency=1").unwrap()),
            randomize_share: share,
            ..config(64)
        })
    };
    // Rewards per env and step over enough steps that episodes end and respawn.
    let fly = |mut env: VecEnv, share_after: Option<f32>| {
        let mut rewards = Vec::new();
        let mut ends = 0;
        for k in 0..400 {
            if k == 200 {
                if let Some(s) = share_after {
                    env.set_randomize_share(s).unwrap();
                }
            }
            let a: Vec<f32> = (0..64 * 4)
                .map(|i| ((i * 7 + k) % 11) as f32 / 10.0)
                .collect();
            env.step(&a).unwrap();
            rewards.push(env.rewards().to_vec());
            ends += env.dones().iter().filter(|d| **d).count();
        }
        (rewards, ends)
    };
    let (nominal, ends) = fly(VecEnv::time_trial(config(64)), None);
    assert!(ends > 64, "too few respawns to test: {ends}");
    assert_eq!(fly(with(0.0), None).0, nominal);
    let full = VecEnv::time_trial(EnvConfig {
        randomize: Some(PerturbSpec::parse("thrust=0.7,latency=1").unwrap()),
        ..config(64)
    });
    assert_eq!(fly(with(1.0), None).0, fly(full, None).0);
    // Half: the first step of some envs is the nominal one, of others not.
    let half = fly(with(0.5), None).0;
    let same = (0..64).filter(|&i| half[0][i] == nominal[0][i]).count();
    assert!((10..=54).contains(&same), "{same} of 64 envs flew nominal");
    // Raised from 0 to 1 half-way: nominal until then, randomised spawns after.
    let raised = fly(with(0.0), Some(1.0)).0;
    assert_eq!(raised[..200], nominal[..200]);
    assert_ne!(raised[200..], nominal[200..]);
    let mut env = with(0.5);
    let e = env.set_randomize_share(1.5).unwrap_err().to_string();
    assert!(e.contains("randomize_share"), "{e}");
    let e = EnvConfig {
        randomize_share: -0.1,
        ..config(1)
    }
    .validate()
    .unwrap_err();
    assert_eq!(e.field, "randomize_share");
    let json = serde_json::to_value(config(1)).unwrap();
    assert!(json.get("randomize_share").is_none(), "{json}");
}

/// The privileged state: the observation without the sensor noise, then the episode's
/// draws (thrust, mass and inertia as ratios minus 1, the motor lag in 10 ms, the latency in
/// steps) and the share of its time left.
#[test]
fn the_privileged_state_is_the_true_observation_and_the_draws() {
    use sitl::env::PRIVILEGED_EXTRA;
    use sitl::perturb::PerturbSpec;
    let mut env = VecEnv::time_trial(EnvConfig {
        randomize: Some(
            PerturbSpec::parse("thrust=1.05,mass=0.9,inertia=1.2,motor-tau-ms=20,latency=1")
                .unwrap(),
        ),
        ..config(4)
    });
    let (d, p) = (env.obs_dim(), env.privileged_dim());
    assert_eq!(p, d + PRIVILEGED_EXTRA);
    let mut state = Vec::new();
    env.privileged_observations(&mut state);
    assert_eq!(state.len(), 4 * p);
    let max = env.max_episode_steps() as f32;
    for (row, obs) in state
        .chunks_exact(p)
        .zip(env.observations().chunks_exact(d))
    {
        // No sensor noise drawn: the observation itself.
        assert_eq!(&row[..d], obs);
        let extra = &row[d..];
        for (got, want) in extra.iter().zip([0.05, -0.1, 0.2, 2.0, 1.0, 1.0]) {
            assert!((got - want).abs() < 1e-5, "{extra:?}");
        }
    }
    env.step(&[0.5; 16]).unwrap();
    env.privileged_observations(&mut state);
    let left = state[p - 1];
    assert!((left - (1.0 - 1.0 / max)).abs() < 1e-6, "{left}");
    // Sensor noise: the observation is noisy, the privileged state is not.
    let noisy = VecEnv::time_trial(EnvConfig {
        randomize: Some(PerturbSpec::parse("noise=3").unwrap()),
        ..config(4)
    });
    let clean = VecEnv::time_trial(config(4));
    noisy.privileged_observations(&mut state);
    let mut nominal = Vec::new();
    clean.privileged_observations(&mut nominal);
    assert_eq!(state, nominal);
    assert_ne!(noisy.observations(), clean.observations());
    for row in nominal.chunks_exact(p) {
        assert_eq!(&row[d..d + 5], &[0.0; 5]);
    }
}

/// `race.ego_ahead_fraction` swaps the stage-2 spawn's places: at 1 every ego starts 1 m
/// ahead of its opponent (the opponent at (−1, 0, 0) m in the ego's frame), at 0 (the paper's)
/// 1 m behind, at 0.5 some of each; a share outside [0, 1] is refused with the field named.
#[test]
fn ego_ahead_spawns_swap_the_places() {
    let ahead_of_ego = |fraction: f32| -> Vec<f32> {
        let mut config = race_config(64, Competition::Lead);
        if let Some(r) = config.race.as_mut() {
            r.ego_ahead_fraction = fraction;
        }
        let env = VecEnv::new(config).unwrap();
        env.observations()
            .chunks(30)
            .map(|o| {
                assert!(o[18].abs() < 1e-5 && o[19].abs() < 1e-5, "{:?}", &o[17..20]);
                o[17] * 12.0 // the relative position is observed in units of 12 m
            })
            .collect()
    };
    assert!(ahead_of_ego(0.0).iter().all(|x| (x - 1.0).abs() < 1e-4));
    assert!(ahead_of_ego(1.0).iter().all(|x| (x + 1.0).abs() < 1e-4));
    let mixed = ahead_of_ego(0.5);
    let swapped = mixed.iter().filter(|x| **x < 0.0).count();
    assert!((16..=48).contains(&swapped), "{swapped} of 64 swapped");

    let mut bad = race_config(1, Competition::Lead);
    if let Some(r) = bad.race.as_mut() {
        r.ego_ahead_fraction = 1.5;
    }
    let Err(e) = VecEnv::new(bad) else {
        panic!("a share of 1.5 was accepted");
    };
    let e = e.to_string();
    assert!(e.contains("race.ego_ahead_fraction"), "{e}");
}

/// `set_race` (an opponent curriculum's change of opponent) gives the env that raced the new
/// opponent from the start, respawned at the same moment: step for step the same
/// observations (which carry the opponent's state) and rewards. A refused blob and a time
/// trial leave the env as it was.
#[test]
fn a_changed_opponent_races_as_one_raced_from_the_start() {
    let time_trial_config = config;
    let stage1 = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");
    let n = 8;
    let config = |opponent: &str| EnvConfig {
        seed: 21,
        ..EnvConfig::stage2(n, opponent)
    };
    let mut changed = VecEnv::new(config(OPPONENT)).unwrap();
    let mut from_start = VecEnv::new(config(stage1)).unwrap();
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    let actions = |t: usize| -> Vec<f32> {
        (0..n)
            .flat_map(|s| [hover + 0.2 * ((s * 5 + t) as f32 * 0.3).sin(); 4])
            .collect()
    };
    // Before the change the two opponents differ where they fly.
    for t in 0..50 {
        changed.step(&actions(t)).unwrap();
        from_start.step(&actions(t)).unwrap();
    }
    assert_ne!(changed.observations(), from_start.observations());

    // A corrupt blob is refused and the env keeps its opponent and its state.
    let mut raw = std::fs::read(stage1).unwrap();
    let last = raw.len() - 1;
    raw[last] ^= 0x40;
    let mut refused = changed.clone();
    let race = |opponent: std::path::PathBuf| RaceConfig {
        opponent,
        ..config(stage1).race.unwrap()
    };
    let e = refused
        .set_race(race(blob_file("curriculum-corrupt.blob", &raw)))
        .unwrap_err();
    assert!(e.to_string().contains("opponent"), "{e}");
    assert_eq!(refused.observations(), changed.observations());
    let mut twin = changed.clone();
    for t in 0..30 {
        refused.step(&actions(t)).unwrap();
        twin.step(&actions(t)).unwrap();
        assert_eq!(refused.observations(), twin.observations(), "step {t}");
    }

    changed.set_race(race(stage1.into())).unwrap();
    from_start.respawn_all();
    assert_eq!(changed.observations(), from_start.observations());
    for t in 0..300 {
        changed.step(&actions(t)).unwrap();
        from_start.step(&actions(t)).unwrap();
        assert_eq!(
            changed.observations(),
            from_start.observations(),
            "step {t}"
        );
        assert_eq!(changed.rewards(), from_start.rewards(), "step {t}");
        assert_eq!(changed.dones(), from_start.dones(), "step {t}");
    }

    let mut trial = VecEnv::time_trial(time_trial_config(n));
    let e = trial.set_race(race(stage1.into())).unwrap_err();
    assert!(e.to_string().contains("time-trial"), "{e}");
}

/// The opponent's recorded flights replay its live flight bit for bit: a race whose
/// opponents fly live from the start and one that replays them give the same observations,
/// rewards, ends and records at every step, through crashes, collisions, the opponent's own
/// crashes, swapped places, a partial group of envs, several rayon tasks recording at once, a
/// snapshot restored in the middle of replays, episodes made longer than the recordings from
/// outside, a clone, a change of opponent (new recordings) and a switch to live flight in the
/// middle of replays.
#[test]
fn replayed_opponents_fly_as_live_ones() {
    let stage1 = OPPONENT;
    let n = 300;
    let config = EnvConfig {
        random_initial_episode_length: true,
        seed: 9,
        race: Some(RaceConfig {
            ego_ahead_fraction: 0.3,
            ..EnvConfig::stage2(n, stage1).race.unwrap()
        }),
        ..EnvConfig::stage2(n, stage1)
    };
    let base_race = config.race.clone().unwrap();
    let mut live = VecEnv::new(config.clone()).unwrap();
    live.fly_opponents_live();
    let mut replayed = VecEnv::new(config).unwrap();
    // Half the egos hover with a small wobble (long episodes: the opponent flies whole
    // recorded laps and meets them again), half wobble hard (short ones).
    let hover = ActionMap::PAPER.action_for_rpm(Preset::paper().hover_rpm());
    let action = |slot: usize, t: usize| -> [f32; 4] {
        let amplitude = if slot.is_multiple_of(2) { 0.02 } else { 0.35 };
        core::array::from_fn(|k| {
            hover + amplitude * ((slot * 7 + t * 3 + k * 5) as f32 * 0.37).sin()
        })
    };
    let (mut collisions, mut opponent_crashes, mut ends) = (0, 0, 0);
    for t in 0..2600 {
        let a: Vec<f32> = (0..n).flat_map(|s| action(s, t)).collect();
        live.step(&a).unwrap();
        replayed.step(&a).unwrap();
        assert_eq!(live.observations(), replayed.observations(), "step {t}");
        assert_eq!(live.rewards(), replayed.rewards(), "step {t}");
        assert_eq!(live.dones(), replayed.dones(), "step {t}");
        assert_eq!(live.records(), replayed.records(), "step {t}");
        ends += live.dones().iter().filter(|d| **d).count();
        opponent_crashes += live.records().iter().filter(|r| r.opponent_crashed).count();
        match t {
            600 => {
                // A snapshot taken in the middle of replays, restored: flown live from there.
                let snap = replayed.snapshot();
                assert_eq!(
                    snap,
                    live.snapshot(),
                    "the snapshot records the replayed state"
                );
                replayed.restore(&snap).unwrap();
            }
            1200 => {
                // Episodes made longer than any recording: the controller takes over.
                let steps = vec![0; n];
                live.set_episode_steps(&steps).unwrap();
                replayed.set_episode_steps(&steps).unwrap();
            }
            1500 => replayed = replayed.clone(),
            1800 => {
                let race = RaceConfig {
                    opponent: concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob")
                        .into(),
                    ..base_race.clone()
                };
                live.set_race(race.clone()).unwrap();
                replayed.set_race(race).unwrap();
            }
            2200 => replayed.fly_opponents_live(),
            _ => {}
        }
        // A crash within 0.3 m of the opponent (the rules' separation is 0.2 m) is a
        // collision: the 30-value observation holds the opponent's offset / 12 m.
        collisions += live
            .records()
            .iter()
            .zip(live.final_observations().chunks_exact(30))
            .filter(|(r, o)| {
                r.crashed && 12.0 * o[17..20].iter().map(|v| v * v).sum::<f32>().sqrt() < 0.3
            })
            .count();
    }
    assert!(
        ends > 100 && opponent_crashes > 0 && collisions > 0,
        "{ends} ends, {opponent_crashes} opponent crashes, {collisions} collisions"
    );
}
