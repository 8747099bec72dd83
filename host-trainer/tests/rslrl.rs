//! RSL-RL interchange: a fixture written the way RSL-RL names an `ActorCriticRecurrent`
//! (names and shapes spelled out here, not taken from the code under test), imported into a
//! blob; and export → import round trips.

use firmware_core::Controller;
use firmware_core::blob::{AlignedBytes, Provenance};
use firmware_core::policy::{Architecture, TableRow};
use firmware_core::synthetic::{self, SplitMix64};
use host_trainer::export::export_blob;
use host_trainer::rslrl::{RslRlError, export_actor, import_actor};
use safetensors::tensor::{Dtype, TensorView, serialize};

fn random(rng: &mut SplitMix64, n: usize, scale: f32) -> Vec<f32> {
    (0..n).map(|_| rng.symmetric() as f32 * scale).collect()
}

fn bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Row G as RSL-RL's `ActorCriticRecurrent` state dict holds it: `memory_a.rnn` (2-layer
/// LSTM, hidden 128, input 30) with separate `bias_ih` / `bias_hh`, the `actor` Sequential
/// 128 → 256 → 128 → 128 → 64 → 4 at indices 0, 2, 4, 6, 8, `std`, and a critic that the
/// import must ignore. Returns the file and the payload a blob must hold.
fn rsl_rl_row_g(prefix: &str) -> (Vec<u8>, Vec<f32>) {
    let mut rng = SplitMix64::new(77);
    let mut named: Vec<(String, Vec<usize>, Vec<f32>)> = Vec::new();
    let mut payload = Vec::new();
    for (l, input) in [(0, 30), (1, 128)] {
        let wih = random(&mut rng, 512 * input, 0.09);
        let whh = random(&mut rng, 512 * 128, 0.09);
        let bih = random(&mut rng, 512, 0.09);
        let bhh = random(&mut rng, 512, 0.09);
        payload.extend(&wih);
        payload.extend(&whh);
        payload.extend(bih.iter().zip(&bhh).map(|(a, b)| a + b));
        named.push((
            format!("memory_a.rnn.weight_ih_l{l}"),
            vec![512, input],
            wih,
        ));
        named.push((format!("memory_a.rnn.weight_hh_l{l}"), vec![512, 128], whh));
        named.push((format!("memory_a.rnn.bias_ih_l{l}"), vec![512], bih));
        named.push((format!("memory_a.rnn.bias_hh_l{l}"), vec![512], bhh));
    }
    let dims = [128, 256, 128, 128, 64, 4];
    for (k, pair) in dims.windows(2).enumerate() {
        let (i, o) = (pair[0], pair[1]);
        let w = random(&mut rng, o * i, 1.0 / (i as f32).sqrt());
        let b = random(&mut rng, o, 0.1);
        payload.extend(&w);
        payload.extend(&b);
        named.push((format!("actor.{}.weight", 2 * k), vec![o, i], w));
        named.push((format!("actor.{}.bias", 2 * k), vec![o], b));
    }
    named.push(("std".into(), vec![4], vec![0.3; 4]));
    named.push((
        "critic.0.weight".into(),
        vec![256, 128],
        random(&mut rng, 256 * 128, 0.1),
    ));
    named.push((
        "memory_c.rnn.weight_ih_l0".into(),
        vec![512, 30],
        random(&mut rng, 512 * 30, 0.1),
    ));
    let data: Vec<(String, Vec<usize>, Vec<u8>)> = named
        .into_iter()
        .map(|(n, s, v)| (format!("{prefix}{n}"), s, bytes(&v)))
        .collect();
    let views: Vec<(String, TensorView<'_>)> = data
        .iter()
        .map(|(n, s, d)| {
            (
                n.clone(),
                TensorView::new(Dtype::F32, s.clone(), d).unwrap(),
            )
        })
        .collect();
    (serialize(views, None).unwrap(), payload)
}

#[test]
fn an_rsl_rl_actor_imports_into_a_flyable_blob() {
    let arch = Architecture::table1(TableRow::G);
    for prefix in ["", "model_state_dict."] {
        let (file, expected) = rsl_rl_row_g(prefix);
        let weights = import_actor(&file, &arch).expect("imports");
        assert_eq!(weights, expected, "prefix '{prefix}'");
        // Into a blob, and the blob flies: the controller runs the imported weights.
        let blob = AlignedBytes::new(
            &export_blob(TableRow::G, Provenance::default(), &weights).expect("encodes"),
        );
        let mut c = Controller::from_bytes(blob.as_bytes(), firmware_core::Track::figure_eight())
            .expect("loads");
        let state = firmware_core::VehicleState::at_rest(
            firmware_core::Vec3::new(-1.0, -1.0, 1.0),
            firmware_core::Quat::IDENTITY,
        );
        let out = c.step(&state, Some(&state));
        assert!(out.fault.is_none());
    }
}

#[test]
fn export_then_import_is_the_identity() {
    for row in [TableRow::A, TableRow::E, TableRow::G] {
        let arch = Architecture::table1(row);
        let weights = synthetic::weights(&arch, 5);
        let file = export_actor(&arch, &weights, Some(&[1.0; 4])).expect("exports");
        assert_eq!(
            import_actor(&file, &arch).expect("imports"),
            weights,
            "{row:?}"
        );
    }
    // Feed-forward names are RSL-RL's.
    let file = export_actor(
        &Architecture::table1(TableRow::A),
        &synthetic::weights(&Architecture::table1(TableRow::A), 1),
        None,
    )
    .unwrap();
    let st = safetensors::SafeTensors::deserialize(&file).unwrap();
    let mut names = st.names();
    names.sort();
    assert_eq!(
        names,
        [
            "actor.0.bias",
            "actor.0.weight",
            "actor.2.bias",
            "actor.2.weight",
            "actor.4.bias",
            "actor.4.weight"
        ]
    );
    assert_eq!(st.tensor("actor.0.weight").unwrap().shape(), [128, 17]);
}

#[test]
fn wrong_files_are_clear_errors() {
    let g = Architecture::table1(TableRow::G);
    let a = Architecture::table1(TableRow::A);
    assert!(matches!(
        import_actor(b"not safetensors", &g),
        Err(RslRlError::Format(_))
    ));
    // An A actor is not a G actor: the LSTM is missing.
    let file = export_actor(&a, &synthetic::weights(&a, 1), None).unwrap();
    assert_eq!(
        import_actor(&file, &g),
        Err(RslRlError::Missing("memory_a.rnn.weight_ih_l0".into()))
    );
    // A B actor (20 inputs) read as A (17): a shape error naming the tensor.
    let b = Architecture::table1(TableRow::B);
    let file = export_actor(&b, &synthetic::weights(&b, 1), None).unwrap();
    let e = import_actor(&file, &a).unwrap_err();
    assert!(e.to_string().contains("actor.0.weight"), "{e}");
    assert!(matches!(
        export_actor(&a, &[0.0; 3], None),
        Err(RslRlError::WeightCount { .. })
    ));
}
