//! Fixed-size neural-network inference over weights borrowed from a blob.
//!
//! Every layer is a *view*: it holds `&'w [f32]` slices into the blob's payload (flash on a
//! microcontroller) and never copies them. Sizes are const generics; activations live on the
//! stack and the recurrent state is a separate value owned by the caller (the controller).
//!
//! ## Layer formats (the payload order of [`crate::blob`])
//! * [`Linear<IN, OUT>`]: `weight` row-major `[OUT][IN]` (PyTorch `nn.Linear.weight`), then
//!   `bias[OUT]`; `y = W x + b`.
//! * [`LstmCell<IN, H>`]: `weight_ih` row-major `[4H][IN]`, `weight_hh` row-major `[4H][H]`,
//!   then `bias[4H]`. Rows are in PyTorch's gate order **i, f, g, o**. PyTorch keeps two bias
//!   vectors, `bias_ih` and `bias_hh`, that are only ever added together; the blob stores
//!   their sum, `bias = bias_ih + bias_hh` (an exporter adds them in f32).
//!   With `z = W_ih x + W_hh h + bias`: `i = σ(z_i)`, `f = σ(z_f)`, `g = tanh(z_g)`,
//!   `o = σ(z_o)`, `c' = f c + i g`, `h' = o tanh(c')`.
//! * An MLP head ([`Mlp`]; Table 1's are [`Mlp2`], [`Mlp3`], [`Mlp4`]): its hidden
//!   [`Linear`] layers each followed by tanh, then a linear output layer (no activation): the
//!   Gaussian mean of the policy.
//!
//! Submodules: the scalar kernels (`kernels`), their [`LANES`]-wide forms (`lanes`), the
//! MLP heads (`mlp`) and the LSTM layers (`lstm`); everything public is re-exported here.

mod kernels;
mod lanes;
mod lstm;
mod mlp;

pub use kernels::{Matrix, dot_i8_i16, sigmoid, tanh};
pub use lstm::{
    LstmCell, LstmLayerLanes, LstmLayerState, LstmPolicy, LstmStack, LstmStackLanes, LstmStackState,
};
pub use mlp::{Head, Hidden, Layers, Linear, Mlp, Mlp2, Mlp3, Mlp4, MlpPolicy};

use crate::format::{BlobError, WeightDtype};

/// Actions of a quadrotor policy: one per motor.
pub const ACTION_DIM: usize = 4;

/// Inputs evaluated side by side by the `*_lanes` forward passes (the host's batched
/// inference: one AVX-512 register of f32, four SSE ones). Each lane computes exactly the
/// operations of the one-input pass in the same order, so its output is the same bits.
pub const LANES: usize = 16;

/// `N` values of each of [`LANES`] inputs, value-major: `v[k][lane]`.
pub type Lanes<const N: usize> = [[f32; LANES]; N];

/// Bytes of one int8 matrix row of `cols` values in a payload: rows are padded with zero
/// bytes to a multiple of 4, so every row starts on a word.
pub const fn i8_row_bytes(cols: usize) -> usize {
    cols.div_ceil(4) * 4
}

/// Most columns an int8 matrix may have (the widest layer input of Table 1 is 256): the
/// quantised input vector lives in a stack buffer of this size.
pub const MAX_I8_COLS: usize = 256;

/// Bytes of stack the int8 kernels add to a layer's frame (the quantised input vector).
pub const I8_SCRATCH_BYTES: usize = MAX_I8_COLS * 2;

/// Views f32 words as their bit patterns (same size and alignment; every pattern is a u32).
fn f32_words(v: &[f32]) -> &[u32] {
    // SAFETY: f32 and u32 have the same size and alignment and every bit pattern is a valid
    // u32; the length and lifetime are the input's.
    unsafe { core::slice::from_raw_parts(v.as_ptr().cast::<u32>(), v.len()) }
}

/// Views 32-bit words as f32 (every bit pattern is a valid f32).
pub(crate) fn words_f32(v: &[u32]) -> &[f32] {
    // SAFETY: as in `f32_words`, the other way round.
    unsafe { core::slice::from_raw_parts(v.as_ptr().cast::<f32>(), v.len()) }
}

/// Reads consecutive tensors out of a payload, in the order of
/// [`crate::policy::Architecture::tensors`].
#[derive(Debug)]
pub struct WeightReader<'w> {
    rest: &'w [u32],
    taken: usize,
    storage: WeightDtype,
}

impl<'w> WeightReader<'w> {
    /// A reader at the start of an f32 `payload`.
    pub fn new(payload: &'w [f32]) -> Self {
        Self {
            rest: f32_words(payload),
            taken: 0,
            storage: WeightDtype::F32,
        }
    }

    /// A reader at the start of an int8 payload, as little-endian 32-bit words.
    pub fn new_i8(payload: &'w [u32]) -> Self {
        Self {
            rest: payload,
            taken: 0,
            storage: WeightDtype::I8,
        }
    }

    fn words(&mut self, n: usize) -> Result<&'w [u32], BlobError> {
        if n > self.rest.len() {
            return Err(self.mismatch(self.taken + n));
        }
        let (head, tail) = self.rest.split_at(n);
        self.rest = tail;
        self.taken += n;
        Ok(head)
    }

    fn mismatch(&self, expected_words: usize) -> BlobError {
        let actual_words = self.taken + self.rest.len();
        match self.storage {
            WeightDtype::F32 => BlobError::PayloadSizeMismatch {
                expected_floats: expected_words,
                actual_floats: actual_words,
            },
            WeightDtype::I8 => BlobError::PayloadLengthMismatch {
                expected_bytes: expected_words * 4,
                actual_bytes: actual_words * 4,
            },
        }
    }

    /// The next `n` f32 values (a bias vector, or any tensor of an f32 payload).
    pub fn take(&mut self, n: usize) -> Result<&'w [f32], BlobError> {
        self.words(n).map(words_f32)
    }

    /// Words of the payload read so far (where the next tensor starts).
    pub fn position(&self) -> usize {
        self.taken
    }

    /// The next `[rows][cols]` weight matrix, in the payload's storage.
    pub fn take_matrix(&mut self, rows: usize, cols: usize) -> Result<Matrix<'w>, BlobError> {
        match self.storage {
            WeightDtype::F32 => self.take(rows * cols).map(Matrix::F32),
            WeightDtype::I8 => {
                if cols > MAX_I8_COLS {
                    return Err(BlobError::UnsupportedArchitecture);
                }
                let (scale, q) = self.take_i8(rows, cols)?;
                Ok(Matrix::I8 { scale, q })
            }
        }
    }

    /// The next int8 matrix `[rows][cols]` as stored: its `rows` f32 scales, then its rows
    /// of int8 values, each padded to [`i8_row_bytes`] (the layout of `crate::blob`).
    pub fn take_i8(
        &mut self,
        rows: usize,
        cols: usize,
    ) -> Result<(&'w [f32], &'w [u32]), BlobError> {
        let scale = self.take(rows)?;
        let q = self.words(rows * i8_row_bytes(cols) / 4)?;
        Ok((scale, q))
    }

    /// Checks that every value was consumed.
    pub fn finish(self) -> Result<(), BlobError> {
        if self.rest.is_empty() {
            Ok(())
        } else {
            Err(self.mismatch(self.taken))
        }
    }
}
