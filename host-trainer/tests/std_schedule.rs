//! The falling σ ceiling (`ppo.max_std_decay`) in a run: with an entropy bonus strong enough
//! to hold σ at its ceiling, the σ every iteration ends with is the schedule's.

mod common;

use host_trainer::config::{StdDecay, TrainConfig};
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
