//! The scalar kernels: a weight matrix times a vector (f32 and int8), the dot product,
//! sigmoid and tanh.

use super::MAX_I8_COLS;

/// A weight matrix `[rows][cols]` viewed in its payload.
#[derive(Clone, Copy, Debug)]
pub enum Matrix<'w> {
    /// Row-major f32.
    F32(&'w [f32]),
    /// Symmetric per-row int8: row `r` is `scale[r] · q[r]`, each row of `q` padded to a
    /// whole number of little-endian words ([`i8_row_bytes`](super::i8_row_bytes)).
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
pub(super) fn dot(w: &[f32], x: &[f32]) -> f32 {
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

pub(super) fn tanh_in_place(v: &mut [f32]) {
    for x in v {
        *x = tanh(*x);
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
