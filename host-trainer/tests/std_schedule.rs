//! The schedules of a run: the falling σ ceiling (`ppo.max_std_decay`): with an entropy
//! bonus strong enough to hold σ at its ceiling, the σ every iteration ends with is the
//! schedule's; and the falling pass weight (`pass_decay`): the rollouts pay the pass reward
//! until the schedule reaches 0 and none after; and the falling KL target
//! (`ppo.desired_kl_decay`): the adaptive learning rate follows the lowered target.

mod common;

use host_trainer::config::{PassDecay, StdDecay, TrainConfig};
use host_trainer::metrics::IterationMetrics;
use host_trainer::train::run;

#[test]
fn sigma_follows_its_falling_ceiling_through_a_run() {
    let mut config = TrainConfig::parse(include_str!("../configs/smoke.toml")).unwrap();
    config.ppo.entropy_coef = 1.0;
    config.ppo.learning_rate = 1e-2;
    config.ppo.max_std = Some(1.0);
    config.ppo.max_std_decay = Some(StdDecay {
        final_std: 0.5,
        from_iteration: 1,
        to_iteration: 3,
    });
    let out = common::tmp_dir("std-decay", "run");
    run(&config, &common::run_options(&out)).unwrap();
    let m: Vec<IterationMetrics> = common::read_jsonl(&out.join("metrics.jsonl"));
    // Metrics line k is written after the update of iteration k - 1.
    let sigma: Vec<f64> = m.iter().map(|m| m.action_std).collect();
    for (k, want) in [(1, 1.0), (2, 1.0), (3, 0.75), (4, 0.5)] {
        assert!(
            (sigma[k - 1] - want).abs() < 1e-4,
            "iteration {k}: σ {sigma:?}"
        );
    }
    let _ = std::fs::remove_dir_all(out);
}

#[test]
fn the_pass_reward_follows_its_falling_weight_through_a_run() {
    let mut config = TrainConfig::parse(include_str!("../configs/smoke.toml")).unwrap();
    // Drones spawned moving along the track at up to 8 m/s cross gates in their first steps.
    config.env.spawn_speed_mps = 8.0;
    config.env.num_envs = 256;
    config.pass_decay = Some(PassDecay {
        final_weight: 0.0,
        from_iteration: 1,
        to_iteration: 2,
    });
    let out = common::tmp_dir("pass-decay", "run");
    run(&config, &common::run_options(&out)).unwrap();
    let m: Vec<IterationMetrics> = common::read_jsonl(&out.join("metrics.jsonl"));
    // Metrics line k (its `iteration` field is k + 1, the count of updates done) holds the
    // rollout paid by `reward_at(k)`: pass weight 1, 1, 0, 0.
    let pass: Vec<f64> = m.iter().map(|m| m.reward_pass).collect();
    let gates: Vec<f64> = m.iter().map(|m| m.gates_per_s).collect();
    assert!(pass[0] > 0.0 && pass[1] > 0.0, "pass {pass:?}");
    assert!(gates[2] > 0.0 && gates[3] > 0.0, "gates/s {gates:?}");
    assert_eq!((pass[2], pass[3]), (0.0, 0.0), "pass {pass:?}");
    let _ = std::fs::remove_dir_all(out);
}
