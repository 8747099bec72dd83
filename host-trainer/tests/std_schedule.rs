//! The schedules of a run: the falling σ ceiling (`ppo.max_std_decay`): with an entropy
//! bonus strong enough to hold σ at its ceiling, the σ every iteration ends with is the
//! schedule's; and the falling pass weight (`pass_decay`): the rollouts pay the pass reward
//! until the schedule reaches 0 and none after; and the falling KL target
//! (`ppo.desired_kl_decay`): the adaptive learning rate follows the lowered target.

mod common;

use host_trainer::config::{KlDecay, PassDecay, StdDecay, TrainConfig};
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

/// A KL target lowered to almost nothing after the first update: every minibatch step of
/// the later updates measures a KL above twice the target, so each divides the learning
/// rate by 1.5 (to the floor); without the decay the same run keeps a higher rate.
#[test]
fn the_learning_rate_follows_the_falling_kl_target_through_a_run() {
    let mut config = TrainConfig::parse(include_str!("../configs/smoke.toml")).unwrap();
    config.ppo.desired_kl = Some(0.01);
    config.ppo.min_learning_rate = 1e-7;
    let mut rates = Vec::new();
    for decay in [
        None,
        Some(KlDecay {
            final_kl: 1e-12,
            from_iteration: 0,
            to_iteration: 1,
        }),
    ] {
        config.ppo.desired_kl_decay = decay;
        let out = common::tmp_dir("kl-decay", "run");
        run(&config, &common::run_options(&out)).unwrap();
        let m: Vec<IterationMetrics> = common::read_jsonl(&out.join("metrics.jsonl"));
        rates.push(
            m.iter()
                .map(|m| m.update.learning_rate)
                .collect::<Vec<f64>>(),
        );
        let _ = std::fs::remove_dir_all(out);
    }
    let (plain, decayed) = (&rates[0], &rates[1]);
    let steps = (config.ppo.epochs * config.ppo.minibatches) as i32;
    // Iteration 0 (target 0.01) is the plain run's; from iteration 1 on, every step but
    // perhaps an epoch's first (whose KL can be exactly 0) divides the rate by 1.5.
    assert_eq!(decayed[0], plain[0], "{plain:?} {decayed:?}");
    for k in 1..decayed.len() {
        let most = decayed[k - 1] / 1.5f64.powi(steps - config.ppo.epochs as i32);
        assert!(
            decayed[k] <= most * (1.0 + 1e-9) || decayed[k] == 1e-7,
            "iteration {k}: {decayed:?}"
        );
        assert!(
            decayed[k] < plain[k],
            "iteration {k}: {plain:?} {decayed:?}"
        );
    }
}
