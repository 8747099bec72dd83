//! Weights leave host-trainer as a blob, firmware-core loads it in place, and the controller
//! flies it in the simulator: the deployment path end to end.

use firmware_core::blob::{AlignedBytes, Blob, Provenance};
use firmware_core::policy::{Architecture, TableRow};
use firmware_core::track::CrashRules;
use firmware_core::track::Track;
use firmware_core::{Controller, synthetic};
use host_trainer::export::export_blob;
use sitl::dynamics::Preset;
use sitl::pilot::Pilot;
use sitl::referee::{EpisodeConfig, EpisodeMetrics, run_episode};
use sitl::world::World;

fn fly(pilot: &mut dyn Pilot, seconds: f32) -> EpisodeMetrics {
    let world = World::figure_eight(Preset::paper(), CrashRules::STAGE1);
    run_episode(
        &world,
        pilot,
        None,
        &EpisodeConfig::time_trial(seconds),
        0,
        false,
    )
    .metrics
}

#[test]
fn exported_weights_load_and_fly() {
    let arch = Architecture::table1(TableRow::A);
    let weights = synthetic::weights(&arch, 42);
    let mut provenance = Provenance {
        seed: 42,
        iterations: 7,
        config_hash: 0xABCD,
        ..Default::default()
    };
    provenance.name.push_str("export-test").expect("fits");
    provenance.preset.push_str("paper").expect("fits");
    let bytes =
        AlignedBytes::new(&export_blob(TableRow::A, provenance.clone(), &weights).expect("export"));

    let blob = Blob::parse(bytes.as_bytes()).expect("parse");
    assert_eq!(blob.header().provenance, provenance);
    assert_eq!(blob.weights(), Some(&weights[..]));

    let track = Track::figure_eight();
    let mut controller = Controller::from_bytes(bytes.as_bytes(), track).expect("controller");
    let summary = fly(&mut controller, 5.0);
    // Random weights do not race, but every step ran the policy (no fail-safe) and the
    // referee's books balance.
    assert_eq!(controller.fault_count(), 0);
    assert_eq!(summary.sim_seconds, 5.0);
    assert_eq!(
        summary.gates_encountered,
        summary.gates_passed + summary.crashes
    );
}

#[test]
fn a_stage2_blob_refuses_to_fly_without_an_opponent() {
    let bytes = AlignedBytes::new(&synthetic::blob(TableRow::G, 1).expect("encode"));
    let track = Track::figure_eight();
    let mut controller = Controller::from_bytes(bytes.as_bytes(), track).expect("controller");
    let summary = fly(&mut controller, 1.0);
    // Every step is the fail-safe (motors stopped): it falls, crashes and is respawned.
    assert_eq!(controller.fault_count(), 50);
    assert!(summary.crashes >= 2);
}
