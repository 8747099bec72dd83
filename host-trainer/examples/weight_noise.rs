//! How fragile is a policy to small weight changes? Adds ±ε to every weight of a blob (the
//! shape of Adam's first steps, which move each weight by about the learning rate whatever
//! its gradient) and lets the referee fly each perturbed copy 45 s from the stage-1 spawn
//! and from 10 spawns along the track.
//!
//! `cargo run --release -p host-trainer --example weight_noise -- policies/stage1_imitation.blob`

use firmware_core::blob::{AlignedBytes, Blob, BlobHeader, encode};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, Report, report};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;

fn fly(raw: &[u8], spawn: SpawnMode, episodes: u32) -> Report {
    let spec = PilotSpec::from_blob("perturbed", raw).expect("a valid blob");
    let config = EvalConfig {
        preset: Preset::paper(),
        episodes,
        seconds: 45.0,
        seed: 0,
        spawn: Some(spawn),
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    report(&spec, None, &config)
}

fn main() {
    let path = std::env::args()
        .nth(1)
        .unwrap_or("policies/stage1_imitation.blob".into());
    let raw = std::fs::read(&path).expect("read the blob");
    let aligned = AlignedBytes::new(&raw);
    let blob = Blob::parse(aligned.as_bytes()).expect("a valid blob");
    let header: BlobHeader = blob.header().clone();
    let weights = blob.dequantized();
    println!("{path}: {} weights", weights.len());
    println!(
        "| ε per weight | seed | stage-1 spawn: success, crashes/s, best lap | along track (10): success, crashes/s |"
    );
    println!("|---|---|---|---|");
    for eps in [0.0f32, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2] {
        for seed in 0..if eps == 0.0 { 1 } else { 4 } {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let w: Vec<f32> = weights
                .iter()
                .map(|w| w + if rng.random::<bool>() { eps } else { -eps })
                .collect();
            let bytes = encode(&header, &w).expect("encode");
            let s1 = fly(&bytes, SpawnMode::Stage1, 1);
            let at = fly(&bytes, SpawnMode::AlongTrack, 10);
            println!(
                "| {eps:.0e} | {seed} | {:.3}, {:.3}, {} | {:.3}, {:.3} |",
                s1.success_rate,
                s1.crash_rate,
                s1.best_lap_s.map_or("DNF".into(), |l| format!("{l:.2} s")),
                at.success_rate,
                at.crash_rate
            );
        }
    }
}
