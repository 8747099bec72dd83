//! Real-time factor of a 45 s two-drone race over MAVLink in lockstep: a row-G LSTM
//! controller against the shipped row-A MLP, each its own `sitl fc` process on loopback UDP
//! (target: >= 100x real time, a 45 s race in <= 0.45 s). In the same run, for ratios: the
//! same race with the controllers on threads, and in-process (`sitl eval`'s path, no
//! MAVLink).
//!
//! The G blob has seeded random weights (`firmware_core::synthetic`; no trained G exists
//! yet): it computes exactly what a trained G computes per step, but flies badly, so it
//! crashes and restarts more often than a trained one would (each restart is one more
//! command round trip). Controller start-up is outside the timing.
//!
//! `cargo bench -p sitl --bench race`

use criterion::{Criterion, criterion_group, criterion_main};
use firmware_core::policy::TableRow;
use sitl::bridge::race::{Entrant, RaceConfig, Transport, race};
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, evaluate};
use sitl::pilot::PilotSpec;
use std::path::PathBuf;
use std::time::Duration;

const SECONDS: f32 = 45.0;

fn entrants() -> Vec<Entrant> {
    let dir = std::env::temp_dir().join(format!("sitl-race-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let g_path = dir.join("g_synthetic.blob");
    let g = firmware_core::synthetic::blob(TableRow::G, 7).expect("G blob encodes");
    std::fs::write(&g_path, &g).expect("G blob written");
    let a_path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../policies/stage1_imitation.blob");
    [("ego", g_path, 1u8), ("opponent", a_path, 2u8)]
        .into_iter()
        .map(|(role, path, id)| {
            let spec = path.display().to_string();
            Entrant {
                role: role.into(),
                pilot: PilotSpec::load(&spec, &Preset::paper()).expect("blob loads"),
                spec,
                system_id: id,
            }
        })
        .collect()
}

fn eval_config(seed: u64) -> EvalConfig {
    EvalConfig {
        preset: Preset::paper(),
        episodes: 1,
        seconds: SECONDS,
        seed,
        spawn: None,
        perturbation: sitl::perturb::Perturbation::NONE,
    }
}

fn bench(c: &mut Criterion) {
    let entrants = entrants();
    let mut group = c.benchmark_group("race_45s_G_vs_A");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(15));
    let transports = [
        (
            "processes",
            Transport::Processes(env!("CARGO_BIN_EXE_sitl").into()),
        ),
        ("threads", Transport::Threads),
    ];
    for (name, transport) in transports {
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for i in 0..iters {
                    let config = RaceConfig::new(eval_config(i));
                    let outcome = race(&entrants, &transport, &config).expect("race runs");
                    assert!(!outcome.has_failures(), "{}", outcome.summary());
                    total += Duration::from_secs_f64(outcome.wall_s);
                }
                total
            });
        });
    }
    group.bench_function("in_process_no_mavlink", |b| {
        let mut seed = 0;
        b.iter(|| {
            seed += 1;
            evaluate(
                &entrants[0].pilot,
                Some(&entrants[1].pilot),
                &eval_config(seed),
                false,
            )
        });
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
