//! An env snapshot ([`VecEnv::snapshot`]), written as JSON and restored into an env built
//! anew from the same config, steps on exactly as the env it was taken of: observations,
//! rewards, episode ends and statistics bit for bit, through gate passes, crashes,
//! respawns (replays of recorded passes included), randomised airframes, latency and sensor
//! noise, and the race's opponent. Snapshots of another shape are refused.

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::policy::Policy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sitl::env::{Competition, EnvConfig, EnvSnapshot, RaceConfig, VecEnv};
use sitl::perturb::PerturbSpec;

const STAGE1: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage1.blob");

/// Flies `steps` steps of the shipped stage-1 policy's actions with noise (crashes happen),
/// returning everything the env reported, as bits.
fn fly(env: &mut VecEnv, steps: usize, seed: u64) -> Vec<u32> {
    let raw = std::fs::read(STAGE1).unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    let policy =
        Policy::from_payload(&blob.header().architecture, blob.weights().unwrap()).unwrap();
    let spec = blob.header().observation;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut actions = vec![0.0; env.num_envs() * 4];
    let mut out = Vec::new();
    for _ in 0..steps {
        env.policy_actions(&policy, &spec, &mut actions);
        for a in &mut actions {
            *a += rng.random_range(-0.3..0.3);
        }
        env.step(&actions).unwrap();
        out.extend(env.observations().iter().map(|v| v.to_bits()));
        out.extend(env.rewards().iter().map(|v| v.to_bits()));
        out.extend(env.dones().iter().map(|&d| u32::from(d)));
        out.extend(env.timeouts().iter().map(|&d| u32::from(d)));
    }
    let stats = env.take_stats();
    out.extend([
        stats.steps as u32,
        stats.crashes as u32,
        stats.gates_passed as u32,
    ]);
    out.push(stats.terms.total().to_bits() as u32);
    out
}

/// Steps `config` for a while, snapshots it through JSON into a new env, and checks that
/// both step on alike; returns the crashes seen (so the test knows it covered respawns).
fn resumes_bit_for_bit(config: EnvConfig) -> u64 {
    let other = EnvConfig {
        seed: config.seed ^ 1,
        ..config.clone()
    };
    let mut a = VecEnv::new(config.clone()).unwrap();
    let first = fly(&mut a, 300, 1);
    // fly ends with the statistics: steps, crashes, gates, reward.
    let crashes_before = u64::from(first[first.len() - 3]);
    let json = serde_json::to_string(&a.snapshot()).unwrap();
    let snap: EnvSnapshot = serde_json::from_str(&json).unwrap();
    assert_eq!(snap, a.snapshot(), "the snapshot round-trips through JSON");
    let mut b = VecEnv::new(config).unwrap();
    b.restore(&snap).unwrap();
    assert_eq!(a.observations(), b.observations());
    let (fa, fb) = (fly(&mut a, 400, 2), fly(&mut b, 400, 2));
    assert!(fa == fb, "the restored env steps otherwise");
    // And an env that was not restored does not (the check can fail).
    let mut c = VecEnv::new(other).unwrap();
    fly(&mut c, 300, 1);
    assert!(fly(&mut c, 400, 2) != fa);
    crashes_before
}

#[test]
fn a_restored_time_trial_steps_as_the_original() {
    // The shipped stage-1 environment: replays, stage-2 starts, the fold, random lengths;
    // randomised as stage1_robust is.
    let config = EnvConfig {
        seed: 5,
        randomize: Some(
            PerturbSpec::parse(
                "latency=0:1,motor-tau-ms=0:30,thrust=0.95:1.05,mass=0.95:1.05,noise=1",
            )
            .unwrap(),
        ),
        ..EnvConfig::stage1(32)
    };
    assert!(
        resumes_bit_for_bit(config) > 0,
        "no crash: respawns not covered"
    );
}

#[test]
fn a_restored_race_steps_as_the_original() {
    let config = EnvConfig {
        seed: 6,
        velocity_scale_mps: 12.0,
        fold_mirror: true,
        race: Some(RaceConfig {
            opponent: STAGE1.into(),
            competition: Competition::Lead,
            competition_weight: 0.5,
            ego_ahead_fraction: 0.0,
        }),
        ..EnvConfig::stage2(32, STAGE1)
    };
    assert!(
        resumes_bit_for_bit(config) > 0,
        "no crash: respawns not covered"
    );
}

#[test]
fn a_snapshot_of_another_env_is_refused() {
    let a = VecEnv::new(EnvConfig::stage1(8)).unwrap();
    let snap = a.snapshot();
    let mut fewer = VecEnv::new(EnvConfig::stage1(4)).unwrap();
    let before = fewer.observations().to_vec();
    let e = fewer.restore(&snap).unwrap_err().to_string();
    assert!(e.contains("8 envs"), "{e}");
    assert_eq!(fewer.observations(), &before[..], "nothing changed");
    let mut race = VecEnv::new(EnvConfig {
        velocity_scale_mps: 12.0,
        fold_mirror: true,
        ..EnvConfig::stage2(8, STAGE1)
    })
    .unwrap();
    let e = race.restore(&snap).unwrap_err().to_string();
    assert!(e.contains("observations"), "{e}");
    let mut bad = snap.clone();
    bad.format = 99;
    let e = VecEnv::new(EnvConfig::stage1(8))
        .unwrap()
        .restore(&bad)
        .unwrap_err()
        .to_string();
    assert!(e.contains("format 99"), "{e}");
    let mut bad = snap;
    bad.observations[3] = f32::NAN;
    assert!(
        VecEnv::new(EnvConfig::stage1(8))
            .unwrap()
            .restore(&bad)
            .is_err()
    );
}
