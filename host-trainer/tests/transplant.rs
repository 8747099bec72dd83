//! `warm_start.transplant`: a feed-forward time-trial policy embedded in a larger row's
//! network flies as the policy does. The shipped stage-1 policy, transplanted into rows B,
//! C, E, F and G, gives its own actions on random observations over the pipeline's whole
//! range (every value in [-1, 1], the opponent's too) to within 1e-3 step after step, with
//! the recurrent state carried; the opponent's values change nothing at all (the transplant
//! starts blind to them); into its own row it is the policy bit for bit; pairs the
//! construction does not cover are refused.

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::observation::{Observation, ObservationLayout, ObservationSpec};
use firmware_core::policy::{Architecture, Policy, TableRow};
use host_trainer::transplant::{spec_fits, transplant};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The shipped stage-1 policy's architecture and weights.
fn stage1() -> (Architecture, Vec<f32>, ObservationSpec) {
    let raw = std::fs::read("../policies/stage1.blob").unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    (
        blob.header().architecture.clone(),
        blob.dequantized(),
        blob.header().observation,
    )
}

/// A fresh-looking payload of `arch`: every weight uniform in ±1/√128, seeded.
fn random_payload(arch: &Architecture, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let k = 1.0 / 128f32.sqrt();
    (0..arch.param_count())
        .map(|_| rng.random_range(-k..k))
        .collect()
}

/// Flies `steps` random observations through the source and the transplant (state carried)
/// and returns the largest action difference.
fn max_action_diff(row: TableRow, steps: usize, seed: u64) -> f32 {
    let (src_arch, src, _) = stage1();
    let arch = Architecture::table1(row);
    let payload = transplant(&src_arch, &src, &arch, &random_payload(&arch, seed)).unwrap();
    let source = Policy::from_payload(&src_arch, &src).unwrap();
    let target = Policy::from_payload(&arch, &payload).unwrap();
    let (mut s_state, mut t_state) = (source.initial_state(), target.initial_state());
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xabc);
    let mut worst = 0f32;
    for _ in 0..steps {
        let x: Vec<f32> = (0..usize::from(arch.obs_dim))
            .map(|_| rng.random_range(-1.0..=1.0))
            .collect();
        let a = source
            .act(&Observation::from_values(&x[..17]).unwrap(), &mut s_state)
            .unwrap();
        let b = target
            .act(&Observation::from_values(&x).unwrap(), &mut t_state)
            .unwrap();
        for (p, q) in a.iter().zip(&b) {
            // The rotor command is the action clamped to [-1, 1].
            worst = worst.max((p.clamp(-1.0, 1.0) - q.clamp(-1.0, 1.0)).abs());
        }
    }
    worst
}

#[test]
fn the_transplant_flies_the_source_s_actions_in_every_larger_row() {
    for row in [
        TableRow::G,
        TableRow::F,
        TableRow::E,
        TableRow::C,
        TableRow::B,
    ] {
        let worst = max_action_diff(row, 400, 7);
        println!("row {}: max |Δ action| {worst:.2e}", row.letter());
        assert!(worst < 1e-3, "row {}: {worst}", row.letter());
    }
}

#[test]
fn the_transplant_into_its_own_row_is_the_source_bit_for_bit() {
    let (arch, src, _) = stage1();
    let out = transplant(&arch, &src, &arch, &random_payload(&arch, 1)).unwrap();
    assert_eq!(out, src);
}

#[test]
fn the_transplant_starts_blind_to_the_opponent() {
    let (src_arch, src, _) = stage1();
    let arch = Architecture::table1(TableRow::G);
    let payload = transplant(&src_arch, &src, &arch, &random_payload(&arch, 3)).unwrap();
    let policy = Policy::from_payload(&arch, &payload).unwrap();
    let (mut s1, mut s2) = (policy.initial_state(), policy.initial_state());
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..100 {
        let mut x: Vec<f32> = (0..30).map(|_| rng.random_range(-1.0..=1.0)).collect();
        let a = policy.act(&Observation::from_values(&x).unwrap(), &mut s1);
        for v in &mut x[17..] {
            *v = rng.random_range(-1.0..=1.0);
        }
        let b = policy.act(&Observation::from_values(&x).unwrap(), &mut s2);
        assert_eq!(a, b);
    }
}

#[test]
fn the_units_the_source_does_not_use_keep_the_initialisation() {
    let (src_arch, src, _) = stage1();
    let arch = Architecture::table1(TableRow::G);
    let init = random_payload(&arch, 9);
    let out = transplant(&src_arch, &src, &arch, &init).unwrap();
    let kept = out.iter().zip(&init).filter(|(a, b)| a == b).count();
    // The source's 17 carried LSTM units, 128 + 128 head units and 4 carried outputs
    // rewrite under a tenth of the 303,940 weights.
    // The source's 51 carrying LSTM units per layer, 128 + 128 head units and 12 carrying
    // units per extra layer rewrite under half of the 303,940 weights.
    assert!(kept > arch.param_count() / 2, "{kept}");
}

#[test]
fn pairs_the_construction_does_not_cover_are_refused() {
    let (a, src, spec) = stage1();
    let g = Architecture::table1(TableRow::G);
    let g_payload = random_payload(&g, 1);
    // A recurrent source, a smaller target, a wrong payload length.
    let refused =
        |r: Result<Vec<f32>, host_trainer::transplant::TransplantError>| r.unwrap_err().to_string();
    assert!(refused(transplant(&g, &g_payload, &g, &g_payload)).contains("feed-forward"));
    assert!(
        refused(transplant(
            &Architecture::table1(TableRow::C),
            &random_payload(&Architecture::table1(TableRow::C), 2),
            &a,
            &src
        ))
        .contains("more than")
    );
    assert!(refused(transplant(&a, &src[1..], &g, &g_payload)).contains("weights"));
    // The spec: the velocity scale and the fold must be the source's.
    let mut g_spec = spec;
    g_spec.layout = ObservationLayout::FullOpponent30;
    assert!(spec_fits(&spec, &g_spec).is_ok());
    g_spec.velocity_scale_mps = 3.0;
    assert!(spec_fits(&spec, &g_spec).is_err());
    assert!(spec_fits(&spec, &spec.with_fold(!spec.is_folded())).is_err());
    assert!(
        spec_fits(
            &g_spec,
            &ObservationSpec::paper(ObservationLayout::TimeTrial17)
        )
        .is_err()
    );
}

/// The trainer's own LSTM actor (burn), loaded with the transplant, computes firmware-core's
/// means over a window: what PPO's update differentiates is what the rollout flew.
#[test]
fn the_trainer_s_network_computes_the_transplant_as_firmware_does() {
    use burn::tensor::{Device, Tensor, TensorData};
    use host_trainer::model::values;
    use host_trainer::nets::PolicyNet;
    use host_trainer::recurrent::{LstmState, RecurrentActor};
    let (src_arch, src, _) = stage1();
    let arch = Architecture::table1(TableRow::G);
    let device = Device::flex();
    let fresh = RecurrentActor::fresh(&arch, 0.1, &mut host_trainer::rng::init_rng(1), &device);
    let payload = transplant(&src_arch, &src, &arch, &fresh.net.payload()).unwrap();
    let actor = RecurrentActor::from_payload(&arch, &payload, &fresh.std(), &device).unwrap();
    let policy = Policy::from_payload(&arch, &payload).unwrap();
    let (steps, envs) = (40usize, 3usize);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let obs: Vec<f32> = (0..steps * envs * 30)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let mut states: Vec<_> = (0..envs).map(|_| policy.initial_state()).collect();
    let mut fw = Vec::new();
    for t in 0..steps {
        for (e, s) in states.iter_mut().enumerate() {
            let o = &obs[(t * envs + e) * 30..(t * envs + e + 1) * 30];
            fw.extend(
                policy
                    .act(&Observation::from_values(o).unwrap(), s)
                    .unwrap(),
            );
        }
    }
    let zeros = vec![0.0; envs * LstmState::width(2, 128)];
    let state = LstmState::from_flat(&zeros, 2, 128, &device);
    let obs_t = Tensor::<3>::from_data(TensorData::new(obs, [steps, envs, 30]), &device);
    let keep = Tensor::<2>::from_data(
        TensorData::new(vec![1.0f32; steps * envs], [steps, envs]),
        &device,
    );
    let (mean, _) = actor.net.sequence(obs_t, keep, state);
    let worst = values(mean)
        .iter()
        .zip(&fw)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    println!("burn vs firmware: max |Δ mean| {worst:e}");
    assert!(worst < 1e-4, "{worst}");
}
