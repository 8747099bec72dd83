//! Seeded synthetic policies and inputs, for tests, benchmarks, size reports and the
//! Cortex-M test image. Never for flight: the weights are random.
//!
//! The generator is SplitMix64; weights of each tensor are uniform in ±1/√fan_in (PyTorch's
//! default initialisation range), observations uniform in [-1, 1] with a unit quaternion in
//! the attitude slots.

extern crate std;
use std::vec::Vec;

use crate::blob::{BlobHeader, EncodeError, Provenance, encode};
use crate::policy::{Architecture, TableRow, TensorKind};

/// The Table 1 rows with a distinct architecture (D is C's): the golden-vector rows.
pub const GOLDEN_ROWS: [TableRow; 6] = [
    TableRow::A,
    TableRow::B,
    TableRow::C,
    TableRow::E,
    TableRow::F,
    TableRow::G,
];

/// The weight seed of row `row`'s golden vectors (`tests/golden/row_X.golden`), shared by the
/// host golden tests and the Cortex-M test image.
pub fn golden_seed(row: TableRow) -> u64 {
    0x0DD5_EED0 + row.letter() as u64
}

/// SplitMix64: a tiny, well-mixed, seedable generator.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator from `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-1, 1).
    pub fn symmetric(&mut self) -> f64 {
        // 53 random bits → [0, 1), then to [-1, 1).
        ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

/// Seeded weights for `arch`, in payload order.
pub fn weights(arch: &Architecture, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    let mut out = Vec::with_capacity(arch.param_count());
    let h = f64::from(arch.lstm_hidden).max(1.0);
    let mut fan_in = f64::from(arch.obs_dim);
    for t in arch.tensors() {
        let bound = match t.kind {
            TensorKind::LstmWeightIh(_) | TensorKind::LstmWeightHh(_) | TensorKind::LstmBias(_) => {
                1.0 / h.sqrt()
            }
            TensorKind::LinearWeight(_) => {
                fan_in = t.cols as f64;
                1.0 / fan_in.sqrt()
            }
            TensorKind::LinearBias(_) => 1.0 / fan_in.sqrt(),
        };
        out.extend((0..t.len()).map(|_| (rng.symmetric() * bound) as f32));
    }
    out
}

/// `steps` seeded observations of `dim` values each.
pub fn observations(dim: usize, steps: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut rng = SplitMix64::new(seed ^ 0x0B5E_4B47_1045);
    (0..steps)
        .map(|_| {
            let mut obs: Vec<f32> = (0..dim).map(|_| rng.symmetric() as f32).collect();
            // Attitude slots 3..7 (and 20..24 for the opponent) hold unit quaternions.
            for range in [3..7, 20..24] {
                if let Some(q) = obs.get_mut(range) {
                    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
                    q.iter_mut().for_each(|v| *v /= n);
                }
            }
            obs
        })
        .collect()
}

/// The header of a synthetic blob of row `row` (paper scales, 50 Hz).
pub fn header(row: TableRow, seed: u64) -> BlobHeader {
    let mut name = heapless::String::new();
    let _ = name.push_str("synthetic-");
    let _ = name.push(row.letter());
    let mut preset = heapless::String::new();
    let _ = preset.push_str("none");
    BlobHeader::paper(
        row,
        Provenance {
            name,
            seed,
            iterations: 0,
            preset,
            config_hash: 0,
        },
    )
}

/// A synthetic blob of row `row` with weights from `seed`.
pub fn blob(row: TableRow, seed: u64) -> Result<Vec<u8>, EncodeError> {
    let h = header(row, seed);
    encode(&h, &weights(&h.architecture, seed))
}

/// The int8 blob of [`blob`]`(row, seed)`: the same weights quantised by
/// [`crate::blob::encode_i8`].
pub fn blob_i8(row: TableRow, seed: u64) -> Result<Vec<u8>, EncodeError> {
    let h = header(row, seed);
    crate::blob::encode_i8(&h, &weights(&h.architecture, seed))
}
