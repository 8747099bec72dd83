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
//! * An MLP head ([`Mlp2`], [`Mlp3`], [`Mlp4`]): its hidden [`Linear`] layers each followed
//!   by tanh, then a linear output layer (no activation): the Gaussian mean of the policy.

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

/// A weight matrix `[rows][cols]` viewed in its payload.
#[derive(Clone, Copy, Debug)]
pub enum Matrix<'w> {
    /// Row-major f32.
    F32(&'w [f32]),
    /// Symmetric per-row int8: row `r` is `scale[r] · q[r]`, each row of `q` padded to a
    /// whole number of little-endian words ([`i8_row_bytes`]).
    I8 {
        /// One scale per row.
        scale: &'w [f32],
        /// The int8 values, four per word.
        q: &'w [u32],
    },
}

impl Matrix<'_> {
    /// `y[r] += W[r] · x` for every row `r < y.len()`, with `x.len()` columns.
    ///
    /// f32: `dot` per row. int8: `x` is quantised once to int16 with one scale per vector
    /// (`s_x = max |x| / 32767`, round to nearest), each row's integer dot product is exact
    /// in i32 ([`dot_i8_i16`]), and `y[r] += (acc · (scale[r] · s_x))`. The integer sums
    /// are the same on every target, so host and Cortex-M compute the same bits.
    #[inline(always)]
    pub fn mul_add(&self, x: &[f32], y: &mut [f32]) {
        match *self {
            Self::F32(w) => {
                for (yo, row) in y.iter_mut().zip(w.chunks_exact(x.len().max(1))) {
                    *yo += dot(row, x);
                }
            }
            Self::I8 { scale, q } => mul_add_i8(scale, q, x, y),
        }
    }
}

/// The int8 arm of [`Matrix::mul_add`], out of line: inlined into every layer it costs
/// the M4 14 % more instructions per G step (988 k against 865 k), and the f32 arm, inlined,
/// 4 % fewer.
#[inline(never)]
fn mul_add_i8(scale: &[f32], q: &[u32], x: &[f32], y: &mut [f32]) {
    let mut xq = [0u32; MAX_I8_COLS / 2];
    let words = x.len().div_ceil(4);
    let Some(xq) = xq.get_mut(..2 * words) else {
        return;
    };
    let sx = quantize_i16(x, xq);
    for ((yo, s), row) in y.iter_mut().zip(scale).zip(q.chunks_exact(words.max(1))) {
        *yo += dot_i8_i16(row, xq) as f32 * (s * sx);
    }
}

/// Quantises `x` to int16 pairs for [`dot_i8_i16`] and returns the scale `s_x` (x ≈ s_x · q).
///
/// Layout: for each group of four values `x[4k..4k+4]`, word `2k` holds `(x[4k], x[4k+2])`
/// and word `2k + 1` holds `(x[4k+1], x[4k+3])` as (low, high) halfwords: the pairing of
/// SXTB16 on a word of four int8 weights. Missing values of the last group are zero. A
/// non-finite `x` gives a NaN scale, so the layer's output is NaN as in f32.
fn quantize_i16(x: &[f32], out: &mut [u32]) -> f32 {
    let max = x.iter().fold(0.0f32, |m, v| {
        if v.abs() > m || v.is_nan() {
            v.abs()
        } else {
            m
        }
    });
    if !max.is_finite() {
        out.fill(0);
        return f32::NAN;
    }
    if max == 0.0 {
        out.fill(0);
        return 0.0;
    }
    let inv = 32767.0 / max;
    let q = |i: usize| -> u32 {
        let v = x.get(i).map_or(0.0, |v| v * inv);
        // Round half away from zero; |v| <= 32767 so the cast cannot saturate.
        let r = (v + libm::copysignf(0.5, v)) as i32;
        u32::from(r as i16 as u16)
    };
    for (k, pair) in out.chunks_exact_mut(2).enumerate() {
        let b = 4 * k;
        if let [even, odd] = pair {
            *even = q(b) | (q(b + 2) << 16);
            *odd = q(b + 1) | (q(b + 3) << 16);
        }
    }
    max / 32767.0
}

/// The exact integer dot product of a row of int8 weights (four per word, little-endian)
/// with int16 activations, two words of pairs per weight word: for weights
/// `(w0, w1, w2, w3)`, `x[2k] = (x0, x2)` and `x[2k + 1] = (x1, x3)` as (low, high)
/// halfwords, the pairing SXTB16 produces (the layout [`Matrix::mul_add`] quantises its
/// input to).
///
/// On the Cortex-M4 (DSP extension) each word is two SXTB16 and two SMLAD (four MACs in
/// four instructions); elsewhere the same sum in portable Rust. Cannot overflow: at most
/// 64 words × 4 × 128 × 32767 < 2³¹.
#[inline]
pub fn dot_i8_i16(w: &[u32], x: &[u32]) -> i32 {
    #[cfg(overtake_dsp)]
    {
        let mut acc: i32 = 0;
        for (wk, xk) in w.iter().zip(x.chunks_exact(2)) {
            if let [x0, x1] = *xk {
                // SAFETY: pure register arithmetic (SXTB16 and SMLAD of the DSP extension,
                // present on every thumbv7em core); no memory access, no stack.
                unsafe {
                    core::arch::asm!(
                        "sxtb16 {lo}, {w}",
                        "sxtb16 {hi}, {w}, ror #8",
                        "smlad {acc}, {lo}, {x0}, {acc}",
                        "smlad {acc}, {hi}, {x1}, {acc}",
                        w = in(reg) *wk,
                        x0 = in(reg) x0,
                        x1 = in(reg) x1,
                        lo = out(reg) _,
                        hi = out(reg) _,
                        acc = inout(reg) acc,
                        options(pure, nomem, nostack),
                    );
                }
            }
        }
        acc
    }
    #[cfg(not(overtake_dsp))]
    {
        let lo = |v: u32| i32::from(v as u16 as i16);
        let hi = |v: u32| i32::from((v >> 16) as u16 as i16);
        let mut acc: i32 = 0;
        for (wk, xk) in w.iter().zip(x.chunks_exact(2)) {
            if let [x0, x1] = *xk {
                let [b0, b1, b2, b3] = wk.to_le_bytes().map(|b| i32::from(b as i8));
                acc = acc
                    .wrapping_add(b0 * lo(x0) + b2 * hi(x0))
                    .wrapping_add(b1 * lo(x1) + b3 * hi(x1));
            }
        }
        acc
    }
}

/// Dot product with eight independent accumulators, so the sum is not one long dependency
/// chain (two SSE registers on x86-64, eight FPU registers on the Cortex-M4F).
///
/// Measured on the host (`cargo bench -p firmware-core --bench controller_step`, row G, same
/// session): this form 52 µs per controller step; 16 accumulators 72 µs; `as_chunks::<8>`
/// or `::<16>` with a pairwise loop reduction 78 µs. Keep the shape unless a bench says so.
#[inline(always)]
fn dot(w: &[f32], x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let wc = w.chunks_exact(8);
    let xc = x.chunks_exact(8);
    let (wr, xr) = (wc.remainder(), xc.remainder());
    for (wk, xk) in wc.zip(xc) {
        for ((a, wi), xi) in acc.iter_mut().zip(wk).zip(xk) {
            *a += wi * xi;
        }
    }
    let mut tail = 0.0f32;
    for (wi, xi) in wr.iter().zip(xr) {
        tail += wi * xi;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// [`dot`] of `w` with each lane of `x` (`x[k][lane]`, `x.len() == w.len()`): the same
/// eight accumulators, tail and reduction order per lane, so each lane is bit for bit `dot`
/// of its own vector. Written as whole-lane operations ([`axpy_lanes`], [`add_lanes`]) so
/// that each is one vector instruction of the lanes (written as nested iterators, the
/// compiler vectorised across the accumulators instead, with gathers, at half the speed of
/// one input at a time).
#[inline(always)]
fn dot_lanes(w: &[f32], x: &[[f32; LANES]]) -> [f32; LANES] {
    let mut acc = [[0.0f32; LANES]; 8];
    let wc = w.chunks_exact(8);
    let xc = x.chunks_exact(8);
    let (wr, xr) = (wc.remainder(), xc.remainder());
    for (wk, xk) in wc.zip(xc) {
        for ((a, wi), xi) in acc.iter_mut().zip(wk).zip(xk) {
            axpy_lanes(a, *wi, xi);
        }
    }
    let mut tail = [0.0f32; LANES];
    for (wi, xi) in wr.iter().zip(xr) {
        axpy_lanes(&mut tail, *wi, xi);
    }
    let [a0, a1, a2, a3, a4, a5, a6, a7] = acc;
    let s04 = add_lanes(&a0, &a4);
    let s15 = add_lanes(&a1, &a5);
    let s26 = add_lanes(&a2, &a6);
    let s37 = add_lanes(&a3, &a7);
    let lo = add_lanes(&s04, &s15);
    let hi = add_lanes(&s26, &s37);
    add_lanes(&add_lanes(&lo, &hi), &tail)
}

/// `acc[l] += w · x[l]` in every lane (a product, then a sum: no fused multiply-add, as
/// [`dot`]).
#[inline(always)]
fn axpy_lanes(acc: &mut [f32; LANES], w: f32, x: &[f32; LANES]) {
    for (a, xl) in acc.iter_mut().zip(x) {
        *a += w * xl;
    }
}

/// `a[l] + b[l]` in every lane.
#[inline(always)]
fn add_lanes(a: &[f32; LANES], b: &[f32; LANES]) -> [f32; LANES] {
    let mut out = *a;
    for (o, bl) in out.iter_mut().zip(b) {
        *o += bl;
    }
    out
}

/// Logistic sigmoid through libm's `expf`.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + libm::expf(-x))
}

/// tanh through one libm `expf`: `1 − 2 / (1 + e^{2x})`. About 1.5× faster than
/// `libm::tanhf` on the host (12 vs 18 ns) with an absolute error below 2e-7 (the relative
/// error near 0 is larger, which no layer here cares about); saturates exactly to ±1 and
/// passes NaN through.
#[inline]
pub fn tanh(x: f32) -> f32 {
    1.0 - 2.0 / (1.0 + libm::expf(2.0 * x))
}

fn tanh_in_place(v: &mut [f32]) {
    for x in v {
        *x = tanh(*x);
    }
}

/// [`tanh`] of every value, [`LANES`] at a time through [`expf_lanes`]: the same bits.
#[inline(always)]
fn tanh_lanes(v: &mut [[f32; LANES]]) {
    for x in v.iter_mut() {
        let mut twice = [0.0f32; LANES];
        for (t, xl) in twice.iter_mut().zip(x.iter()) {
            *t = 2.0 * xl;
        }
        let e = expf_lanes(&twice);
        for (xl, el) in x.iter_mut().zip(e) {
            *xl = 1.0 - 2.0 / (1.0 + el);
        }
    }
}

/// `libm::expf` of [`LANES`] values at once, bit for bit: the arithmetic of FreeBSD's
/// `e_expf.c` as the `libm` crate (0.2) does it, each branch computed for every lane and
/// selected, so the compiler vectorises it; `scalbnf(y, k)` is its final multiply by 2^k
/// (k stays within [−126, 126] here). Lanes libm treats as special (|x| ≥ 87.34, where it
/// overflows or underflows, and NaN) are recomputed by `libm::expf` itself.
#[inline(always)]
fn expf_lanes(x: &[f32; LANES]) -> [f32; LANES] {
    let ln2_hi = f32::from_bits(0x3f31_7200);
    let ln2_lo = f32::from_bits(0x35bf_be8e);
    let inv_ln2 = f32::from_bits(0x3fb8_aa3b);
    let p1 = f32::from_bits(0x3e2a_aa8f);
    let p2 = f32::from_bits(0xbb35_5215);
    let mut y = [0.0f32; LANES];
    let mut special = false;
    for (yl, &xl) in y.iter_mut().zip(x) {
        let hx = xl.to_bits() & 0x7fff_ffff;
        let negative = xl.to_bits() >> 31 != 0;
        special |= hx >= 0x42ae_ac50;
        // Argument reduction: x = k ln2 + r, |r| <= ln2 / 2.
        let reduce = hx > 0x3eb1_7218;
        let k: i32 = if hx > 0x3f85_1592 {
            (inv_ln2 * xl + if negative { -0.5 } else { 0.5 }) as i32
        } else if reduce {
            if negative { -1 } else { 1 }
        } else {
            0
        };
        let kf = k as f32;
        let hi = if reduce { xl - kf * ln2_hi } else { xl };
        let lo = if reduce { kf * ln2_lo } else { 0.0 };
        let r = if reduce { hi - lo } else { xl };
        let rr = r * r;
        let c = r - rr * (p1 + rr * p2);
        let v = 1.0 + (r * c / (2.0 - c) - lo + hi);
        let scale = f32::from_bits(((0x7f + k.clamp(-126, 127)) as u32) << 23);
        let v = if k == 0 { v } else { v * scale };
        *yl = if hx > 0x3900_0000 { v } else { 1.0 + xl };
    }
    if special {
        for (yl, &xl) in y.iter_mut().zip(x) {
            if xl.to_bits() & 0x7fff_ffff >= 0x42ae_ac50 {
                *yl = libm::expf(xl);
            }
        }
    }
    y
}

/// Lane `l` of `x` as one vector.
#[inline(always)]
fn lane<const N: usize>(x: &Lanes<N>, l: usize) -> [f32; N] {
    let mut out = [0.0f32; N];
    for (o, xk) in out.iter_mut().zip(x) {
        *o = xk.get(l).copied().unwrap_or(0.0);
    }
    out
}

/// Sets lane `l` of `y` to `v`.
#[inline(always)]
fn set_lane<const N: usize>(y: &mut Lanes<N>, l: usize, v: &[f32; N]) {
    for (yk, vk) in y.iter_mut().zip(v) {
        if let Some(slot) = yk.get_mut(l) {
            *slot = *vk;
        }
    }
}

/// A fully connected layer `y = W x + b` viewing `[OUT][IN]` weights and `[OUT]` biases.
#[derive(Clone, Copy, Debug)]
pub struct Linear<'w, const IN: usize, const OUT: usize> {
    weight: Matrix<'w>,
    bias: &'w [f32],
}

impl<'w, const IN: usize, const OUT: usize> Linear<'w, IN, OUT> {
    /// Number of parameters.
    pub const PARAMS: usize = IN * OUT + OUT;

    /// Takes the layer's weights, then biases, from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let weight = r.take_matrix(OUT, IN)?;
        let bias = r.take(OUT)?;
        Ok(Self { weight, bias })
    }

    /// `y = W x + b`.
    #[inline]
    pub fn forward(&self, x: &[f32; IN], y: &mut [f32; OUT]) {
        y.fill(0.0);
        self.weight.mul_add(x, y);
        for (yo, b) in y.iter_mut().zip(self.bias) {
            *yo += b;
        }
    }

    /// [`Self::forward`] of [`LANES`] inputs side by side, each lane the same bits.
    #[inline(always)]
    pub fn forward_lanes(&self, x: &Lanes<IN>, y: &mut Lanes<OUT>) {
        match self.weight {
            Matrix::F32(w) => {
                for ((yo, row), b) in y.iter_mut().zip(w.chunks_exact(IN.max(1))).zip(self.bias) {
                    let d = dot_lanes(row, x);
                    for (yl, dl) in yo.iter_mut().zip(d) {
                        // `forward`'s order: 0 + W x, then + b.
                        *yl = (0.0 + dl) + b;
                    }
                }
            }
            // int8 quantises each input with its own scale: lane by lane.
            Matrix::I8 { .. } => {
                for l in 0..LANES {
                    let mut out = [0.0f32; OUT];
                    self.forward(&lane(x, l), &mut out);
                    set_lane(y, l, &out);
                }
            }
        }
    }
}

/// The hidden and cell state of one LSTM layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmLayerState<const H: usize> {
    /// Hidden state h.
    pub h: [f32; H],
    /// Cell state c.
    pub c: [f32; H],
}

impl<const H: usize> Default for LstmLayerState<H> {
    fn default() -> Self {
        Self {
            h: [0.0; H],
            c: [0.0; H],
        }
    }
}

/// One LSTM layer (PyTorch semantics, gate order i, f, g, o; see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct LstmCell<'w, const IN: usize, const H: usize> {
    weight_ih: Matrix<'w>,
    weight_hh: Matrix<'w>,
    bias: &'w [f32],
}

impl<'w, const IN: usize, const H: usize> LstmCell<'w, IN, H> {
    /// Number of parameters (with the two PyTorch biases stored as one).
    pub const PARAMS: usize = 4 * H * IN + 4 * H * H + 4 * H;

    /// Takes `weight_ih`, `weight_hh`, then the summed bias from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let weight_ih = r.take_matrix(4 * H, IN)?;
        let weight_hh = r.take_matrix(4 * H, H)?;
        let bias = r.take(4 * H)?;
        Ok(Self {
            weight_ih,
            weight_hh,
            bias,
        })
    }

    /// Advances `state` by one input `x`.
    ///
    /// Gate-major: the pre-activations of all four gates, `(W_ih x + W_hh h) + bias`, row
    /// by row over both weight matrices (f32), or as two matrix-vector products (int8),
    /// then the cell updates. On the host the gate-major form is 59 µs per G controller step against
    /// 84 µs for a unit-by-unit loop that needs only H values of scratch (same session); the
    /// 4H-value buffer (2 KB at H = 128) fits the RAM budget. Kept out of line so its
    /// scratch and the MLP head's never share a stack frame.
    #[inline(never)]
    pub fn step(&self, x: &[f32; IN], state: &mut LstmLayerState<H>) {
        // Pre-activations of the four gates, i f g o.
        let mut z = [[0.0f32; H]; 4];
        let flat = z.as_flattened_mut();
        match (self.weight_ih, self.weight_hh) {
            // f32: both weight streams in one pass per row. Two passes cost the host G step
            // 7 % (68.1 against 63.7 µs, mean of three paired runs); this form is at parity
            // with the code before int8 (61.8 against 63.5 µs, two paired runs).
            (Matrix::F32(w_ih), Matrix::F32(w_hh)) => {
                let rows = w_ih
                    .chunks_exact(IN)
                    .zip(w_hh.chunks_exact(H))
                    .zip(self.bias);
                for (zo, ((ri, rh), bo)) in flat.iter_mut().zip(rows) {
                    *zo = dot(ri, x) + dot(rh, &state.h) + bo;
                }
            }
            (w_ih, w_hh) => {
                w_ih.mul_add(x, flat);
                w_hh.mul_add(&state.h, flat);
                for (zo, b) in flat.iter_mut().zip(self.bias) {
                    *zo += b;
                }
            }
        }
        let [zi, zf, zg, zo] = &z;
        let units = state.h.iter_mut().zip(state.c.iter_mut());
        for ((((h, c), i), f), (g, o)) in units.zip(zi).zip(zf).zip(zg.iter().zip(zo)) {
            let cn = sigmoid(*f) * *c + sigmoid(*i) * tanh(*g);
            *c = cn;
            *h = sigmoid(*o) * tanh(cn);
        }
    }
}

/// A stack of `1 + DEEP` LSTM layers of width `H` on `IN` inputs.
#[derive(Clone, Copy, Debug)]
pub struct LstmStack<'w, const IN: usize, const H: usize, const DEEP: usize> {
    first: LstmCell<'w, IN, H>,
    deep: [LstmCell<'w, H, H>; DEEP],
}

/// The state of an [`LstmStack`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LstmStackState<const H: usize, const DEEP: usize> {
    /// State of the first layer.
    pub first: LstmLayerState<H>,
    /// States of the layers after it.
    pub deep: [LstmLayerState<H>; DEEP],
}

impl<const H: usize, const DEEP: usize> Default for LstmStackState<H, DEEP> {
    fn default() -> Self {
        Self {
            first: LstmLayerState::default(),
            deep: [LstmLayerState::default(); DEEP],
        }
    }
}

impl<const H: usize, const DEEP: usize> LstmStackState<H, DEEP> {
    /// The top layer's hidden state: the stack's output.
    pub fn output(&self) -> &[f32; H] {
        match self.deep.last() {
            Some(top) => &top.h,
            None => &self.first.h,
        }
    }
}

impl<'w, const IN: usize, const H: usize, const DEEP: usize> LstmStack<'w, IN, H, DEEP> {
    /// Number of parameters.
    pub const PARAMS: usize = LstmCell::<IN, H>::PARAMS + DEEP * LstmCell::<H, H>::PARAMS;

    /// Takes the layers in order from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        let first = LstmCell::load(r)?;
        let empty = LstmCell {
            weight_ih: Matrix::F32(&[]),
            weight_hh: Matrix::F32(&[]),
            bias: &[],
        };
        let mut deep = [empty; DEEP];
        for cell in &mut deep {
            *cell = LstmCell::load(r)?;
        }
        Ok(Self { first, deep })
    }

    /// Advances every layer by one input; the output is `state.output()`.
    pub fn step(&self, x: &[f32; IN], state: &mut LstmStackState<H, DEEP>) {
        self.first.step(x, &mut state.first);
        let mut below: &[f32; H] = &state.first.h;
        for (cell, s) in self.deep.iter().zip(state.deep.iter_mut()) {
            cell.step(below, s);
            let s: &LstmLayerState<H> = s;
            below = &s.h;
        }
    }
}

/// An MLP head: its forward pass from `IN` features to the [`ACTION_DIM`] outputs.
pub trait Head<'w, const IN: usize>: Sized {
    /// Number of parameters.
    const PARAMS: usize;
    /// Bytes of activations the forward pass keeps on the stack.
    const SCRATCH_BYTES: usize;
    /// Takes the layers in order from `r`.
    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError>;
    /// The output (the Gaussian mean, not yet clipped).
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM];
    /// [`Self::forward`] of [`LANES`] inputs side by side, each lane the same bits (the
    /// host's batched inference; unused on the flight controller).
    #[inline(always)]
    fn forward_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut y = [[0.0f32; LANES]; ACTION_DIM];
        for l in 0..LANES {
            set_lane(&mut y, l, &self.forward(&lane(x, l)));
        }
        y
    }
}

/// MLP head with two tanh hidden layers (Table 1 rows A, B: 2 × 128).
#[derive(Clone, Copy, Debug)]
pub struct Mlp2<'w, const IN: usize, const H1: usize, const H2: usize> {
    l1: Linear<'w, IN, H1>,
    l2: Linear<'w, H1, H2>,
    out: Linear<'w, H2, ACTION_DIM>,
}

impl<'w, const IN: usize, const H1: usize, const H2: usize> Head<'w, IN> for Mlp2<'w, IN, H1, H2> {
    const PARAMS: usize =
        Linear::<IN, H1>::PARAMS + Linear::<H1, H2>::PARAMS + Linear::<H2, ACTION_DIM>::PARAMS;
    const SCRATCH_BYTES: usize = (H1 + H2 + ACTION_DIM) * 4;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            l1: Linear::load(r)?,
            l2: Linear::load(r)?,
            out: Linear::load(r)?,
        })
    }

    #[inline(never)]
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        let mut a1 = [0.0f32; H1];
        self.l1.forward(x, &mut a1);
        tanh_in_place(&mut a1);
        let mut a2 = [0.0f32; H2];
        self.l2.forward(&a1, &mut a2);
        tanh_in_place(&mut a2);
        let mut y = [0.0f32; ACTION_DIM];
        self.out.forward(&a2, &mut y);
        y
    }

    #[inline(always)]
    fn forward_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut a1 = [[0.0f32; LANES]; H1];
        self.l1.forward_lanes(x, &mut a1);
        tanh_lanes(&mut a1);
        let mut a2 = [[0.0f32; LANES]; H2];
        self.l2.forward_lanes(&a1, &mut a2);
        tanh_lanes(&mut a2);
        let mut y = [[0.0f32; LANES]; ACTION_DIM];
        self.out.forward_lanes(&a2, &mut y);
        y
    }
}

/// MLP head with three tanh hidden layers (row F: 256, 128, 128).
#[derive(Clone, Copy, Debug)]
pub struct Mlp3<'w, const IN: usize, const H1: usize, const H2: usize, const H3: usize> {
    l1: Linear<'w, IN, H1>,
    l2: Linear<'w, H1, H2>,
    l3: Linear<'w, H2, H3>,
    out: Linear<'w, H3, ACTION_DIM>,
}

impl<'w, const IN: usize, const H1: usize, const H2: usize, const H3: usize> Head<'w, IN>
    for Mlp3<'w, IN, H1, H2, H3>
{
    const PARAMS: usize = Linear::<IN, H1>::PARAMS
        + Linear::<H1, H2>::PARAMS
        + Linear::<H2, H3>::PARAMS
        + Linear::<H3, ACTION_DIM>::PARAMS;
    const SCRATCH_BYTES: usize = (H1 + H2 + H3 + ACTION_DIM) * 4;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            l1: Linear::load(r)?,
            l2: Linear::load(r)?,
            l3: Linear::load(r)?,
            out: Linear::load(r)?,
        })
    }

    #[inline(never)]
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        let mut a1 = [0.0f32; H1];
        self.l1.forward(x, &mut a1);
        tanh_in_place(&mut a1);
        let mut a2 = [0.0f32; H2];
        self.l2.forward(&a1, &mut a2);
        tanh_in_place(&mut a2);
        let mut a3 = [0.0f32; H3];
        self.l3.forward(&a2, &mut a3);
        tanh_in_place(&mut a3);
        let mut y = [0.0f32; ACTION_DIM];
        self.out.forward(&a3, &mut y);
        y
    }
}

/// MLP head with four tanh hidden layers (rows C, D, E, G: 256, 128, 128, 64).
#[derive(Clone, Copy, Debug)]
pub struct Mlp4<
    'w,
    const IN: usize,
    const H1: usize,
    const H2: usize,
    const H3: usize,
    const H4: usize,
> {
    l1: Linear<'w, IN, H1>,
    l2: Linear<'w, H1, H2>,
    l3: Linear<'w, H2, H3>,
    l4: Linear<'w, H3, H4>,
    out: Linear<'w, H4, ACTION_DIM>,
}

impl<'w, const IN: usize, const H1: usize, const H2: usize, const H3: usize, const H4: usize>
    Head<'w, IN> for Mlp4<'w, IN, H1, H2, H3, H4>
{
    const PARAMS: usize = Linear::<IN, H1>::PARAMS
        + Linear::<H1, H2>::PARAMS
        + Linear::<H2, H3>::PARAMS
        + Linear::<H3, H4>::PARAMS
        + Linear::<H4, ACTION_DIM>::PARAMS;
    const SCRATCH_BYTES: usize = (H1 + H2 + H3 + H4 + ACTION_DIM) * 4;

    fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            l1: Linear::load(r)?,
            l2: Linear::load(r)?,
            l3: Linear::load(r)?,
            l4: Linear::load(r)?,
            out: Linear::load(r)?,
        })
    }

    #[inline(never)]
    fn forward(&self, x: &[f32; IN]) -> [f32; ACTION_DIM] {
        let mut a1 = [0.0f32; H1];
        self.l1.forward(x, &mut a1);
        tanh_in_place(&mut a1);
        let mut a2 = [0.0f32; H2];
        self.l2.forward(&a1, &mut a2);
        tanh_in_place(&mut a2);
        let mut a3 = [0.0f32; H3];
        self.l3.forward(&a2, &mut a3);
        tanh_in_place(&mut a3);
        let mut a4 = [0.0f32; H4];
        self.l4.forward(&a3, &mut a4);
        tanh_in_place(&mut a4);
        let mut y = [0.0f32; ACTION_DIM];
        self.out.forward(&a4, &mut y);
        y
    }

    #[inline(always)]
    fn forward_lanes(&self, x: &Lanes<IN>) -> Lanes<ACTION_DIM> {
        let mut a1 = [[0.0f32; LANES]; H1];
        self.l1.forward_lanes(x, &mut a1);
        tanh_lanes(&mut a1);
        let mut a2 = [[0.0f32; LANES]; H2];
        self.l2.forward_lanes(&a1, &mut a2);
        tanh_lanes(&mut a2);
        let mut a3 = [[0.0f32; LANES]; H3];
        self.l3.forward_lanes(&a2, &mut a3);
        tanh_lanes(&mut a3);
        let mut a4 = [[0.0f32; LANES]; H4];
        self.l4.forward_lanes(&a3, &mut a4);
        tanh_lanes(&mut a4);
        let mut y = [[0.0f32; LANES]; ACTION_DIM];
        self.out.forward_lanes(&a4, &mut y);
        y
    }
}

/// A feed-forward policy: an MLP head on the observation.
#[derive(Clone, Copy, Debug)]
pub struct MlpPolicy<M> {
    head: M,
}

impl<M> MlpPolicy<M> {
    /// Takes the head's weights from `r`.
    pub fn load<'w, const IN: usize>(r: &mut WeightReader<'w>) -> Result<Self, BlobError>
    where
        M: Head<'w, IN>,
    {
        Ok(Self { head: M::load(r)? })
    }

    /// The Gaussian mean for observation `obs` (unclipped).
    pub fn forward<'w, const IN: usize>(&self, obs: &[f32; IN]) -> [f32; ACTION_DIM]
    where
        M: Head<'w, IN>,
    {
        self.head.forward(obs)
    }

    /// [`Self::forward`] of [`LANES`] observations side by side, each lane the same bits.
    #[inline(always)]
    pub fn forward_lanes<'w, const IN: usize>(&self, obs: &Lanes<IN>) -> Lanes<ACTION_DIM>
    where
        M: Head<'w, IN>,
    {
        self.head.forward_lanes(obs)
    }
}

/// A recurrent policy: an LSTM stack on the observation, then an MLP head on its output.
#[derive(Clone, Copy, Debug)]
pub struct LstmPolicy<'w, const IN: usize, const H: usize, const DEEP: usize, M> {
    lstm: LstmStack<'w, IN, H, DEEP>,
    head: M,
}

impl<'w, const IN: usize, const H: usize, const DEEP: usize, M: Head<'w, H>>
    LstmPolicy<'w, IN, H, DEEP, M>
{
    /// Number of parameters.
    pub const PARAMS: usize = LstmStack::<IN, H, DEEP>::PARAMS + M::PARAMS;
    /// Bytes of activations kept on the stack by one step: the larger of the LSTM cell's gate
    /// pre-activations and the head's activations (their frames do not overlap), plus the
    /// int8 kernels' quantised input ([`I8_SCRATCH_BYTES`], reserved for either dtype).
    pub const SCRATCH_BYTES: usize = (if 4 * H * 4 > M::SCRATCH_BYTES {
        4 * H * 4
    } else {
        M::SCRATCH_BYTES
    }) + I8_SCRATCH_BYTES;

    /// Takes the LSTM layers, then the head, from `r`.
    pub fn load(r: &mut WeightReader<'w>) -> Result<Self, BlobError> {
        Ok(Self {
            lstm: LstmStack::load(r)?,
            head: M::load(r)?,
        })
    }

    /// Advances the recurrent state by `obs` and returns the Gaussian mean (unclipped).
    pub fn step(&self, obs: &[f32; IN], state: &mut LstmStackState<H, DEEP>) -> [f32; ACTION_DIM] {
        self.lstm.step(obs, state);
        self.head.forward(state.output())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tanh_through_expf_matches_libm_tanhf() {
        let mut worst = 0.0f32;
        for i in -200_000..=200_000 {
            let x = i as f32 * 1e-4;
            worst = worst.max((tanh(x) - libm::tanhf(x)).abs());
        }
        assert!(worst < 2e-7, "{worst}");
        assert_eq!((tanh(100.0), tanh(-100.0)), (1.0, -1.0));
        assert!(tanh(f32::NAN).is_nan());
    }

    /// `expf_lanes` is libm's `expf` bit for bit: every 251st bit pattern (all signs,
    /// exponents, NaNs, infinities, subnormals) and every pattern within 4,096 of a branch
    /// threshold of libm's, both signs; and `tanh_lanes` is `tanh`.
    #[test]
    fn expf_lanes_is_libms_expf_bit_for_bit() {
        let thresholds = [
            0x42ae_ac50u32,
            0x42b1_7218,
            0x42cf_f1b5,
            0x3f85_1592,
            0x3eb1_7218,
            0x3900_0000,
            0x7f80_0000,
            0,
        ];
        let near = thresholds.iter().flat_map(|&t| {
            (0..8192u32).flat_map(move |d| {
                let b = t.wrapping_add(d).wrapping_sub(4096);
                [b, b | 0x8000_0000]
            })
        });
        let bits: Vec<u32> = (0..=u32::MAX).step_by(251).chain(near).collect();
        for chunk in bits.chunks(LANES) {
            let mut x = [0.0f32; LANES];
            for (xl, &b) in x.iter_mut().zip(chunk) {
                *xl = f32::from_bits(b);
            }
            let y = expf_lanes(&x);
            let mut t = [x];
            tanh_lanes(&mut t);
            for l in 0..chunk.len() {
                let (want, got) = (libm::expf(x[l]), y[l]);
                assert!(
                    want.to_bits() == got.to_bits() || (want.is_nan() && got.is_nan()),
                    "expf({:e} = {:#010x}): libm {want:e}, lanes {got:e}",
                    x[l],
                    x[l].to_bits()
                );
                let (want, got) = (tanh(x[l]), t[0][l]);
                assert!(want.to_bits() == got.to_bits() || (want.is_nan() && got.is_nan()));
            }
        }
    }

    #[test]
    fn dot_equals_the_naive_sum() {
        for n in [0, 1, 15, 16, 17, 30, 128, 256] {
            let w: [f32; 256] = core::array::from_fn(|i| (i as f32 * 0.37).sin());
            let x: [f32; 256] = core::array::from_fn(|i| (i as f32 * 0.11).cos());
            let naive: f64 = (0..n).map(|i| f64::from(w[i]) * f64::from(x[i])).sum();
            assert!(
                (f64::from(dot(&w[..n], &x[..n])) - naive).abs() < 1e-4,
                "n = {n}"
            );
        }
    }
}
