//! `Policy::act_lanes`, the host's batched inference: every lane is bit for bit `act` of its
//! own observation (the training rollout flies it, the controller flies `act`, so a single
//! differing bit would make training and deployment disagree). A NaN may come out as
//! another NaN (x86 keeps the first operand's NaN, and the vectorised code may order an
//! operation's operands the other way): NaNs compare as one value here.

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::nn::{ACTION_DIM, LANES};
use firmware_core::observation::Observation;
use firmware_core::policy::{Policy, TableRow};
use firmware_core::synthetic;
use proptest::prelude::*;

/// `act` of each of the `LANES` observations in `obs` (row-major), as bits.
/// The bits of `v`, every NaN as the canonical one.
fn bits(v: f32) -> u32 {
    if v.is_nan() {
        f32::NAN.to_bits()
    } else {
        v.to_bits()
    }
}

fn one_by_one(policy: &Policy<'_>, obs: &[f32]) -> Vec<[u32; ACTION_DIM]> {
    obs.chunks_exact(policy.obs_dim())
        .map(|o| {
            let mut state = policy.initial_state();
            let o = Observation::from_values(o).expect("size");
            policy.act(&o, &mut state).expect("act").map(bits)
        })
        .collect()
}

fn side_by_side(policy: &Policy<'_>, obs: &[f32]) -> Vec<[u32; ACTION_DIM]> {
    policy
        .act_lanes(obs)
        .expect("a feed-forward policy")
        .iter()
        .map(|m| m.map(bits))
        .collect()
}

fn check(row: TableRow, int8: bool, seed: u64, obs: &[f32]) {
    let bytes = if int8 {
        synthetic::blob_i8(row, seed)
    } else {
        synthetic::blob(row, seed)
    }
    .expect("encode");
    let aligned = AlignedBytes::new(&bytes);
    let policy = Blob::parse(aligned.as_bytes())
        .and_then(|b| b.policy())
        .expect("policy");
    assert_eq!(
        side_by_side(&policy, obs),
        one_by_one(&policy, obs),
        "row {row:?}, int8 {int8}, seed {seed}"
    );
}

#[test]
fn every_lane_is_act_bit_for_bit_on_the_feed_forward_rows() {
    for row in [TableRow::A, TableRow::B, TableRow::C] {
        for int8 in [false, true] {
            for seed in 0..4 {
                let dim = row.observation_layout().dim();
                let obs: Vec<f32> = synthetic::observations(dim, LANES, seed + 100)
                    .concat()
                    .iter()
                    // Past the training range as well: the hidden layers saturate.
                    .map(|v| v * 3.0)
                    .collect();
                check(row, int8, seed, &obs);
            }
        }
    }
}

#[test]
fn recurrent_rows_and_wrong_lengths_are_refused() {
    for row in [TableRow::E, TableRow::G] {
        let bytes = synthetic::blob(row, 1).expect("encode");
        let aligned = AlignedBytes::new(&bytes);
        let policy = Blob::parse(aligned.as_bytes())
            .and_then(|b| b.policy())
            .expect("policy");
        assert!(policy.act_lanes(&vec![0.0; 30 * LANES]).is_none());
    }
    let bytes = synthetic::blob(TableRow::A, 1).expect("encode");
    let aligned = AlignedBytes::new(&bytes);
    let policy = Blob::parse(aligned.as_bytes())
        .and_then(|b| b.policy())
        .expect("policy");
    assert!(policy.act_lanes(&vec![0.0; 17 * LANES - 1]).is_none());
    assert!(policy.act_lanes(&vec![0.0; 17 * LANES]).is_some());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any observation values, non-finite ones and signed zeros included (a lane's NaN
    /// stays in its lane).
    #[test]
    fn any_inputs_give_acts_bits(
        seed in 0u64..1000,
        values in proptest::collection::vec(
            prop_oneof![
                8 => -4.0f32..4.0,
                1 => Just(0.0f32),
                1 => Just(-0.0f32),
                1 => Just(f32::NAN),
                1 => Just(f32::INFINITY),
                1 => Just(-1e30f32),
            ],
            17 * LANES,
        ),
    ) {
        check(TableRow::A, false, seed, &values);
    }
}
