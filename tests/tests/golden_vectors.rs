//! Golden vectors for every Table 1 architecture: seeded synthetic weights and inputs, the
//! expected outputs of the independent float64 reference, and firmware-core's f32 inference
//! held to them (max abs error <= 1e-5).
//!
//! The committed files in `tests/golden/` pin the fixtures: a size change means the format or
//! the step count changed, a digest change with the same size means the values changed.

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::crc32::crc32;
use firmware_core::observation::Observation;
use firmware_core::policy::{Architecture, Policy, TableRow};
use firmware_core::synthetic;
use overtake_tests::fixtures::{
    GOLDEN_ROWS, golden_dir, golden_seed, golden_sequence, golden_text,
};

const TOLERANCE: f64 = 1e-5;

fn observation(values: &[f32]) -> Observation {
    // Build an Observation through the public API: a spec of the right layout over a state
    // would recompute it, so the golden inputs go in as raw values.
    Observation::from_values(values).expect("golden observation has a valid size")
}

#[test]
fn committed_golden_files_match_the_reference() {
    let bless = std::env::var_os("OVERTAKE_BLESS").is_some();
    for row in GOLDEN_ROWS {
        let path = golden_dir().join(format!("row_{}.golden", row.letter()));
        let fresh = golden_text(row);
        if bless {
            std::fs::write(&path, &fresh).expect("write golden file");
            continue;
        }
        let committed = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (bless with OVERTAKE_BLESS=1)", path.display()));
        assert_eq!(
            (committed.len(), crc32(committed.as_bytes())),
            (fresh.len(), crc32(fresh.as_bytes())),
            "row {}: golden file (size, crc32) changed: a size change means the format or step \
             count moved, the same size with another digest means the values moved",
            row.letter()
        );
    }
}

#[test]
fn firmware_inference_matches_the_float64_reference_for_rows_a_to_g() {
    for row in TableRow::ALL {
        let bytes = AlignedBytes::new(&synthetic::blob(row, golden_seed(row)).expect("encode"));
        let blob = Blob::parse(bytes.as_bytes()).expect("parse");
        let policy = blob.policy().expect("policy");
        let expected_variant = match row {
            TableRow::A => matches!(policy, Policy::A(_)),
            TableRow::B => matches!(policy, Policy::B(_)),
            TableRow::C | TableRow::D => matches!(policy, Policy::C(_)),
            TableRow::E => matches!(policy, Policy::E(_)),
            TableRow::F => matches!(policy, Policy::F(_)),
            TableRow::G => matches!(policy, Policy::G(_)),
        };
        assert!(
            expected_variant,
            "row {} dispatched to {:?}",
            row.letter(),
            policy.obs_dim()
        );
        assert_eq!(
            blob.weights().map(<[f32]>::len),
            Some(Architecture::table1(row).param_count())
        );

        let (obs, means) = golden_sequence(row);
        let mut state = policy.initial_state();
        let mut max_err = 0.0f64;
        for (o, m) in obs.iter().zip(&means) {
            let got = policy.act(&observation(o), &mut state).expect("act");
            for (g, e) in got.iter().zip(m) {
                max_err = max_err.max((f64::from(*g) - e).abs());
            }
        }
        println!(
            "row {}: {} params, max |f32 - f64 reference| = {max_err:.3e}",
            row.letter(),
            Architecture::table1(row).param_count()
        );
        assert!(
            max_err <= TOLERANCE,
            "row {}: max abs error {max_err:e} > {TOLERANCE:e}",
            row.letter()
        );
    }
}

#[test]
fn recurrent_state_carries_across_steps() {
    // Feeding the same observation twice must give different outputs for an LSTM policy
    // (state carried) and the same outputs for an MLP policy.
    for (row, recurrent) in [(TableRow::A, false), (TableRow::G, true)] {
        let bytes = AlignedBytes::new(&synthetic::blob(row, 7).expect("encode"));
        let blob = Blob::parse(bytes.as_bytes()).expect("parse");
        let policy = blob.policy().expect("policy");
        let obs = &synthetic::observations(policy.obs_dim(), 1, 7)[0];
        let mut state = policy.initial_state();
        let first = policy.act(&observation(obs), &mut state).expect("act");
        let second = policy.act(&observation(obs), &mut state).expect("act");
        assert_eq!(first != second, recurrent, "row {}", row.letter());
    }
}
