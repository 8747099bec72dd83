//! int8 blobs: the layout, the quantiser, the kernels and the defects an int8 payload can
//! have. The Cortex-M4 image checks that its SMLAD kernel computes the host's bits
//! (`cargo run -p tools -- cortex-m test`).

use firmware_core::blob::{
    AlignedBytes, Blob, BlobError, EncodeError, WeightDtype, convert, encode_i8, int8_grid,
};
use firmware_core::crc32::crc32;
use firmware_core::nn::{dot_i8_i16, i8_row_bytes};
use firmware_core::observation::Observation;
use firmware_core::policy::{Architecture, Policy, TableRow};
use firmware_core::synthetic::{self, SplitMix64};
use proptest::prelude::*;

fn reseal(mut bytes: Vec<u8>) -> Vec<u8> {
    let n = bytes.len() - 4;
    let crc = crc32(&bytes[..n]);
    bytes[n..].copy_from_slice(&crc.to_le_bytes());
    bytes
}

fn parse(bytes: &[u8]) -> Result<(), BlobError> {
    Blob::parse(AlignedBytes::new(bytes).as_bytes()).map(|_| ())
}

/// Offset of the payload in an encoded blob.
fn payload_offset(bytes: &[u8]) -> usize {
    let header_len = usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
    (8 + header_len).next_multiple_of(4)
}

/// Means of `policy` over `steps` synthetic observations, from a zero state.
fn means(policy: &Policy<'_>, seed: u64, steps: usize) -> Vec<[f32; 4]> {
    let mut state = policy.initial_state();
    synthetic::observations(policy.obs_dim(), steps, seed)
        .iter()
        .map(|o| {
            let obs = Observation::from_values(o).expect("size");
            policy.act(&obs, &mut state).expect("act")
        })
        .collect()
}

fn max_abs_diff(a: &[[f32; 4]], b: &[[f32; 4]]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn payload_sizes_are_those_of_the_layout() {
    // G: 4 B per weight in f32; in int8 1 B per weight, rows padded to 4 B, a 4 B scale
    // per matrix row and f32 biases.
    let g = Architecture::table1(TableRow::G);
    assert_eq!(g.payload_bytes(WeightDtype::F32), 303_940 * 4);
    assert_eq!(g.payload_bytes(WeightDtype::I8), 320_288);
    let bytes = synthetic::blob_i8(TableRow::G, 1).expect("encode");
    let aligned = AlignedBytes::new(&bytes);
    let blob = Blob::parse(aligned.as_bytes()).expect("parse");
    assert_eq!(blob.header().dtype, WeightDtype::I8);
    assert_eq!(blob.header().payload_len, 320_288);
    assert_eq!(blob.weights(), None);
    // The 30-column first LSTM matrix: 32-byte rows.
    assert_eq!(i8_row_bytes(30), 32);
    assert_eq!(i8_row_bytes(128), 128);
}

#[test]
fn dequantised_weights_are_within_half_a_step_of_the_originals() {
    for row in [TableRow::A, TableRow::C, TableRow::G] {
        let h = synthetic::header(row, 9);
        let w = synthetic::weights(&h.architecture, 9);
        let bytes = AlignedBytes::new(&encode_i8(&h, &w).expect("encode"));
        let blob = Blob::parse(bytes.as_bytes()).expect("parse");
        let d = blob.dequantized();
        assert_eq!(d.len(), w.len());
        let mut at = 0;
        for t in h.architecture.tensors() {
            let (orig, deq) = (&w[at..at + t.len()], &d[at..at + t.len()]);
            at += t.len();
            if t.cols == 0 {
                assert_eq!(orig, deq, "biases stay f32");
                continue;
            }
            for (ro, rd) in orig.chunks(t.cols).zip(deq.chunks(t.cols)) {
                let step = ro.iter().fold(0.0f32, |m, v| m.max(v.abs())) / 127.0;
                for (o, q) in ro.iter().zip(rd) {
                    assert!((o - q).abs() <= 0.5 * step * 1.0001, "{o} vs {q}");
                }
            }
        }
        // int8 -> f32 -> int8 is the identity on the bytes.
        let back = convert(&blob, WeightDtype::F32).expect("to f32");
        let back = AlignedBytes::new(&back);
        let again = convert(
            &Blob::parse(back.as_bytes()).expect("parse"),
            WeightDtype::I8,
        )
        .expect("to i8");
        assert_eq!(again, bytes.as_bytes(), "row {}", row.letter());
    }
}

#[test]
fn the_int8_grid_is_what_an_int8_blob_holds_and_stays_put() {
    // A quantisation-aware trainer runs its forward pass on `int8_grid` and ends on it: the
    // int8 blob of grid weights must dequantise to exactly those weights (or the deployed
    // policy is not the trained one), and the grid of grid weights must be themselves.
    for row in [TableRow::A, TableRow::C, TableRow::G] {
        let h = synthetic::header(row, 11);
        let w = synthetic::weights(&h.architecture, 11);
        let grid = int8_grid(&h.architecture, &w).expect("grid");
        let bytes = AlignedBytes::new(&encode_i8(&h, &w).expect("encode"));
        let deq = Blob::parse(bytes.as_bytes()).expect("parse").dequantized();
        assert_eq!(grid, deq, "row {}", row.letter());
        assert_ne!(grid, w, "row {}: the grid moves the weights", row.letter());
        assert_eq!(int8_grid(&h.architecture, &grid).expect("grid"), grid);
        let again = AlignedBytes::new(&encode_i8(&h, &grid).expect("encode"));
        assert_eq!(again.as_bytes(), bytes.as_bytes(), "row {}", row.letter());
    }
    let h = synthetic::header(TableRow::A, 1);
    let w = synthetic::weights(&h.architecture, 1);
    assert!(matches!(
        int8_grid(&h.architecture, &w[1..]),
        Err(EncodeError::WrongWeightCount { .. })
    ));
    let mut bad = w.clone();
    bad[3] = f32::NAN;
    assert_eq!(
        int8_grid(&h.architecture, &bad),
        Err(EncodeError::NonFiniteWeight { index: 3 })
    );
}

#[test]
fn int8_inference_equals_f32_inference_on_the_dequantised_weights() {
    // What differs is only the int16 rounding of each layer input (1/32767 of its largest
    // value), so the two policies agree to ~1e-4 over a 200-step recurrent sequence.
    for row in synthetic::GOLDEN_ROWS {
        let bytes = AlignedBytes::new(&synthetic::blob_i8(row, 4).expect("encode"));
        let blob = Blob::parse(bytes.as_bytes()).expect("parse");
        let deq = blob.dequantized();
        let arch = &blob.header().architecture;
        let f32_policy = Policy::from_payload(arch, &deq).expect("f32 view");
        let i8_policy = blob.policy().expect("i8 view");
        let err = max_abs_diff(&means(&i8_policy, 5, 200), &means(&f32_policy, 5, 200));
        println!(
            "row {}: int8 vs dequantised f32: max |Δ| {err:.2e}",
            row.letter()
        );
        assert!(err < 1e-4, "row {}: {err}", row.letter());
        assert!(err > 0.0, "the int16 activations must round somewhere");
    }
}

#[test]
fn int8_policies_stay_close_to_their_f32_originals() {
    for row in [TableRow::A, TableRow::G] {
        let f = AlignedBytes::new(&synthetic::blob(row, 4).expect("encode"));
        let q = AlignedBytes::new(&synthetic::blob_i8(row, 4).expect("encode"));
        let (f, q) = (
            Blob::parse(f.as_bytes()).expect("f32"),
            Blob::parse(q.as_bytes()).expect("i8"),
        );
        let mf = means(&f.policy().expect("f32"), 6, 200);
        let mq = means(&q.policy().expect("i8"), 6, 200);
        let scale = mf.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
        let err = max_abs_diff(&mf, &mq);
        println!(
            "row {}: int8 vs f32 max |Δ| {err:.3e} (outputs up to {scale:.3})",
            row.letter()
        );
        assert!(err < 0.02 * scale, "row {}: {err}", row.letter());
    }
}

/// The portable kernel's contract: the exact integer sum with the interleaved layout.
fn naive_dot(w: &[i8], x: &[i16]) -> i64 {
    w.iter()
        .zip(x)
        .map(|(a, b)| i64::from(*a) * i64::from(*b))
        .sum()
}

fn pack(w: &[i8], x: &[i16]) -> (Vec<u32>, Vec<u32>) {
    let n = w.len().div_ceil(4) * 4;
    let wb: Vec<u8> = (0..n)
        .map(|i| w.get(i).copied().unwrap_or(0) as u8)
        .collect();
    let words = wb
        .chunks(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let xi = |i: usize| u32::from(x.get(i).copied().unwrap_or(0) as u16);
    let xs = (0..n / 4)
        .flat_map(|k| {
            let b = 4 * k;
            [xi(b) | (xi(b + 2) << 16), xi(b + 1) | (xi(b + 3) << 16)]
        })
        .collect();
    (words, xs)
}

proptest! {
    #[test]
    fn the_kernel_is_the_exact_integer_dot_product(
        w in proptest::collection::vec(any::<i8>(), 0..=256),
        seed in any::<u64>(),
    ) {
        let mut rng = SplitMix64::new(seed);
        let x: Vec<i16> = (0..w.len()).map(|_| (rng.next_u64() >> 48) as u16 as i16).collect();
        let (words, xs) = pack(&w, &x);
        prop_assert_eq!(i64::from(dot_i8_i16(&words, &xs)), naive_dot(&w, &x));
    }
}

#[test]
fn the_kernel_at_its_extremes() {
    let w = vec![-128i8; 256];
    let x = vec![-32768i16; 256];
    let (words, xs) = pack(&w, &x);
    assert_eq!(i64::from(dot_i8_i16(&words, &xs)), naive_dot(&w, &x));
    let w = vec![127i8; 256];
    let (words, xs) = pack(&w, &x);
    assert_eq!(i64::from(dot_i8_i16(&words, &xs)), naive_dot(&w, &x));
}

#[test]
fn int8_defects_are_typed_errors() {
    let good = synthetic::blob_i8(TableRow::A, 3).expect("encode");
    assert_eq!(parse(&good), Ok(()));
    let p = payload_offset(&good);
    // A's first matrix: 128 rows of 17 columns (20-byte rows), after its 128 scales.
    let first_row_end = p + 128 * 4 + 20;

    let mut bad = good.clone();
    bad[first_row_end - 1] = 1; // a padding byte of row 0
    assert_eq!(parse(&reseal(bad)), Err(BlobError::NonZeroPadding));

    let mut bad = good.clone();
    bad[p + 4 * 5 + 3] |= 0x80; // sign bit of scale 5
    assert_eq!(
        parse(&reseal(bad)),
        Err(BlobError::InvalidScale { word: 5 })
    );

    let mut bad = good.clone();
    bad[p..p + 4].copy_from_slice(&f32::INFINITY.to_le_bytes());
    assert_eq!(
        parse(&reseal(bad)),
        Err(BlobError::InvalidScale { word: 0 })
    );

    // The first bias (128 f32) follows the matrix.
    let bias = p + 128 * 4 + 128 * 20;
    let mut bad = good.clone();
    bad[bias + 8..bias + 12].copy_from_slice(&f32::NAN.to_le_bytes());
    let word = (bias + 8 - p) / 4;
    assert_eq!(
        parse(&reseal(bad)),
        Err(BlobError::NonFiniteWeight { index: word })
    );

    // An f32-sized payload under an int8 header is a length error that names both sizes.
    let h = synthetic::header(TableRow::A, 3);
    let mut wrong = h.clone();
    wrong.dtype = WeightDtype::I8;
    let f32_bytes =
        firmware_core::blob::encode(&h, &synthetic::weights(&h.architecture, 3)).expect("encode");
    let header_bytes = postcard::to_stdvec(&{
        let mut x = wrong.clone();
        x.payload_len = (19_332 * 4) as u32;
        x
    })
    .expect("header");
    let mut relabelled = Vec::new();
    relabelled.extend_from_slice(&f32_bytes[..6]);
    relabelled.extend_from_slice(&(header_bytes.len() as u16).to_le_bytes());
    relabelled.extend_from_slice(&header_bytes);
    relabelled.resize(relabelled.len().next_multiple_of(4), 0);
    relabelled.extend_from_slice(&f32_bytes[payload_offset(&f32_bytes)..f32_bytes.len() - 4]);
    relabelled.extend_from_slice(&[0; 4]);
    let expected = Architecture::table1(TableRow::A).payload_bytes(WeightDtype::I8);
    let err = parse(&reseal(relabelled)).expect_err("size");
    assert_eq!(
        err,
        BlobError::PayloadLengthMismatch {
            expected_bytes: expected,
            actual_bytes: 19_332 * 4
        }
    );
    assert!(err.to_string().contains(&expected.to_string()), "{err}");
}

#[test]
fn nan_inputs_give_nan_outputs_in_int8_too() {
    let bytes = AlignedBytes::new(&synthetic::blob_i8(TableRow::A, 2).expect("encode"));
    let blob = Blob::parse(bytes.as_bytes()).expect("parse");
    let policy = blob.policy().expect("policy");
    let mut values = [0.1f32; 17];
    values[3] = f32::NAN;
    let obs = Observation::from_values(&values).expect("size");
    let out = policy.act(&obs, &mut policy.initial_state()).expect("act");
    assert!(out.iter().all(|v| v.is_nan()), "{out:?}");
}
