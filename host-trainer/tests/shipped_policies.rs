//! The blobs in `policies/` are what their committed configs produce and fly as recorded:
//! the provenance names the config (hash, seed, iterations, preset), and the referee's
//! time trial from the stage-1 spawn gives the numbers in policies/README.md.

use firmware_core::blob::{AlignedBytes, Blob};
use host_trainer::config::TrainConfig;
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, report};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap()
}

#[test]
fn stage1_imitation_is_its_config_and_flies_the_track() {
    let raw = std::fs::read(root().join("policies/stage1_imitation.blob")).unwrap();
    let config =
        TrainConfig::load(&root().join("host-trainer/configs/stage1_imitation.toml")).unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    let p = &blob.header().provenance;
    assert_eq!(
        p.config_hash,
        config.hash(),
        "the blob was made with another config"
    );
    assert_eq!(p.seed, config.run.seed);
    assert_eq!(p.iterations, config.run.iterations);
    assert_eq!(p.preset.as_str(), config.env.preset);
    assert_eq!(p.name.as_str(), config.run.name);
    assert_eq!(
        blob.header().observation.velocity_scale_mps,
        config.env.velocity_scale_mps
    );

    let spec = PilotSpec::from_blob("stage1_imitation", &raw).unwrap();
    let eval = EvalConfig {
        preset: Preset::paper(),
        episodes: 1,
        seconds: 45.0,
        seed: 0,
        spawn: Some(SpawnMode::Stage1),
    };
    let r = report(&spec, None, &eval);
    println!("{}", r.table());
    assert_eq!(r.crashes, 0);
    assert!(r.success_rate >= 0.999, "{}", r.success_rate);
    let lap = r.best_lap_s.expect("a complete lap");
    assert!(
        (lap - 10.94).abs() < 0.03,
        "best lap {lap} s, recorded 10.94 s"
    );
}
