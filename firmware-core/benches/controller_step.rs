//! One `Controller::step` on the host for Table 1 rows A (MLP 2 × 128) and G (a 2-layer LSTM
//! and a 4-layer MLP): gate bookkeeping, observation, inference, action map. Seeded synthetic
//! weights (the cost does not depend on their values); G also in int8 (`controller_step_G_i8`,
//! the portable kernel: the host has no SMLAD).
//!
//! `cargo bench -p firmware-core --bench controller_step`

use criterion::{Criterion, criterion_group, criterion_main};
use firmware_core::Controller;
use firmware_core::blob::AlignedBytes;
use firmware_core::math::{Quat, Vec3};
use firmware_core::policy::TableRow;
use firmware_core::synthetic;
use firmware_core::track::Track;
use firmware_core::vehicle::VehicleState;
use std::hint::black_box;

fn states() -> Vec<VehicleState> {
    (0..64)
        .map(|i| {
            let t = i as f32 * 0.02;
            VehicleState {
                position_m: Vec3::new(-3.0 + 5.0 * t, 0.3 * t, 1.0),
                attitude: Quat::from_axis_angle(Vec3::new(0.6, 0.8, 0.0), 0.2 * t).normalized(),
                velocity_mps: Vec3::new(5.0, 0.3, 0.1),
                body_rates_radps: Vec3::new(0.1, -0.2, 0.05),
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let own = states();
    let opponent = VehicleState::at_rest(Vec3::new(-1.0, 0.5, 1.0), Quat::IDENTITY);
    for (row, int8) in [
        (TableRow::A, false),
        (TableRow::G, false),
        (TableRow::G, true),
    ] {
        let blob = if int8 {
            synthetic::blob_i8(row, 1)
        } else {
            synthetic::blob(row, 1)
        };
        let bytes = AlignedBytes::new(&blob.expect("encode"));
        let mut ctrl =
            Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
        let mut i = 0;
        let name = format!(
            "controller_step_{}{}",
            row.letter(),
            if int8 { "_i8" } else { "" }
        );
        c.bench_function(&name, |b| {
            b.iter(|| {
                i = (i + 1) % own.len();
                black_box(ctrl.step(black_box(&own[i]), Some(&opponent)))
            })
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
