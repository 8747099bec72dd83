//! `Policy::act_lanes` and `Policy::step_lanes`, the host's batched inference: every lane is
//! bit for bit `act` of its own observation (and, for a recurrent row, its own state) (the training rollout flies it, the controller flies `act`, so a single
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

/// The synthetic blob of `row` (seed `seed`) in f32 or int8.
fn synthetic_blob(row: TableRow, int8: bool, seed: u64) -> AlignedBytes {
    let bytes = if int8 {
        synthetic::blob_i8(row, seed)
    } else {
        synthetic::blob(row, seed)
    };
    AlignedBytes::new(&bytes.expect("encode"))
}

fn check(row: TableRow, int8: bool, seed: u64, obs: &[f32]) {
    let aligned = synthetic_blob(row, int8, seed);
    let policy = policy_of(&aligned);
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

/// The policy of a synthetic `row` blob in `aligned`.
fn policy_of(aligned: &AlignedBytes) -> Policy<'_> {
    Blob::parse(aligned.as_bytes())
        .and_then(|b| b.policy())
        .expect("policy")
}

/// `steps` steps of `LANES` envs, each with its own observations and recurrent state, the
/// state of the envs in `resets[t]` zeroed before step `t` (an episode end): every lane of
/// `step_lanes` is `act` from that env's own state, bit for bit, at every step, and the
/// states agree too.
fn check_recurrent(row: TableRow, int8: bool, seed: u64, obs: &[f32], resets: &[u16]) {
    let aligned = synthetic_blob(row, int8, seed);
    let policy = policy_of(&aligned);
    let dim = policy.obs_dim();
    let mut one = [policy.initial_state(); LANES];
    let mut side = [policy.initial_state(); LANES];
    for (t, (o, reset)) in obs.chunks_exact(dim * LANES).zip(resets).enumerate() {
        for l in (0..LANES).filter(|l| reset & (1 << l) != 0) {
            one[l].clear();
            side[l].clear();
        }
        let want: Vec<[u32; ACTION_DIM]> = o
            .chunks_exact(dim)
            .zip(&mut one)
            .map(|(o, s)| {
                let o = Observation::from_values(o).expect("size");
                policy.act(&o, s).expect("act").map(bits)
            })
            .collect();
        let got: Vec<[u32; ACTION_DIM]> = policy
            .step_lanes(o, side.each_mut())
            .expect("its own states")
            .iter()
            .map(|m| m.map(bits))
            .collect();
        assert_eq!(got, want, "row {row:?}, int8 {int8}, seed {seed}, step {t}");
        assert_eq!(
            format!("{side:?}"),
            format!("{one:?}"),
            "states, row {row:?}, int8 {int8}, seed {seed}, step {t}"
        );
    }
}

#[test]
fn every_lane_is_act_bit_for_bit_on_the_recurrent_rows_across_resets() {
    for row in [TableRow::E, TableRow::F, TableRow::G] {
        for int8 in [false, true] {
            let steps = 12;
            let obs: Vec<f32> = synthetic::observations(30, LANES * steps, 7)
                .concat()
                .iter()
                .map(|v| v * 3.0)
                .collect();
            // Lane l resets every (l % 5 + 2) steps: some lanes mid-sequence, some often.
            let resets: Vec<u16> = (0..steps)
                .map(|t| {
                    (0..LANES)
                        .filter(|l| t % (l % 5 + 2) == 0)
                        .map(|l| 1u16 << l)
                        .sum()
                })
                .collect();
            check_recurrent(row, int8, 3, &obs, &resets);
        }
    }
}

#[test]
fn step_lanes_refuses_another_policys_states_and_touches_none() {
    let aligned = synthetic_blob(TableRow::G, false, 1);
    let policy = policy_of(&aligned);
    let obs = vec![0.5; 30 * LANES];
    let mut states = [policy.initial_state(); LANES];
    // One lane holds a one-layer state (row E's): nothing runs, nothing changes.
    let e_aligned = synthetic_blob(TableRow::E, false, 1);
    states[9] = policy_of(&e_aligned).initial_state();
    let before = states;
    assert!(policy.step_lanes(&obs, states.each_mut()).is_none());
    assert_eq!(states, before);
    assert!(policy.step_lanes(&obs[1..], states.each_mut()).is_none());
    // A feed-forward policy ignores its (stateless) states.
    let a_aligned = synthetic_blob(TableRow::A, false, 1);
    let a = policy_of(&a_aligned);
    let mut stateless = [a.initial_state(); LANES];
    assert_eq!(
        a.step_lanes(&vec![0.5; 17 * LANES], stateless.each_mut()),
        a.act_lanes(&vec![0.5; 17 * LANES])
    );
}

#[test]
fn recurrent_rows_and_wrong_lengths_are_refused() {
    for row in [TableRow::E, TableRow::G] {
        let aligned = synthetic_blob(row, false, 1);
        let policy = policy_of(&aligned);
        assert!(policy.act_lanes(&vec![0.0; 30 * LANES]).is_none());
    }
    let aligned = synthetic_blob(TableRow::A, false, 1);
    let policy = policy_of(&aligned);
    assert!(policy.act_lanes(&vec![0.0; 17 * LANES - 1]).is_none());
    assert!(policy.act_lanes(&vec![0.0; 17 * LANES]).is_some());
}

/// One observation value: mostly in the training range, often a signed zero, NaN, an
/// infinity or a huge negative.
fn observation_value() -> impl Strategy<Value = f32> {
    prop_oneof![
        8 => -4.0f32..4.0,
        1 => Just(0.0f32),
        1 => Just(-0.0f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(-1e30f32),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any observation values, non-finite ones and signed zeros included (a lane's NaN
    /// stays in its lane).
    #[test]
    fn any_inputs_give_acts_bits(
        seed in 0u64..1000,
        values in proptest::collection::vec(observation_value(), 17 * LANES),
    ) {
        check(TableRow::A, false, seed, &values);
    }

    /// Rows E, F and G, f32 and int8, over any observations and any pattern of episode
    /// resets: every lane of `step_lanes` is `act` from its own state.
    #[test]
    fn recurrent_lanes_are_act_for_any_inputs_and_resets(
        row in prop_oneof![Just(TableRow::E), Just(TableRow::F), Just(TableRow::G)],
        int8 in any::<bool>(),
        seed in 0u64..1000,
        values in proptest::collection::vec(observation_value(), 30 * LANES * 4),
        resets in proptest::collection::vec(any::<u16>(), 4),
    ) {
        check_recurrent(row, int8, seed, &values, &resets);
    }
}
