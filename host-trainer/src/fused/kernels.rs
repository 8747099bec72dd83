//! The numeric kernels of the fused update: `matrixmultiply`'s sgemm with strides, and tanh
//! (forward with an exact-enough exp, backward) vectorised for the CPU at hand.

/// `c[m, n] = a[m, k] · b[k, n] + beta · c` with `a` and `b` at the given (row, column)
/// strides and `c` row-major.
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    (rsa, csa): (usize, usize),
    b: &[f32],
    (rsb, csb): (usize, usize),
    beta: f32,
    c: &mut [f32],
) {
    if m == 0 || n == 0 {
        return;
    }
    let last = |rows: usize, cols: usize, rs: usize, cs: usize| (rows - 1) * rs + (cols - 1) * cs;
    assert!(k == 0 || (last(m, k, rsa, csa) < a.len() && last(k, n, rsb, csb) < b.len()));
    assert!(m * n <= c.len());
    // SAFETY: the asserts keep every element the strides address inside the slices; `c`
    // is exclusively borrowed and does not alias `a` or `b`.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            rsa as isize,
            csa as isize,
            b.as_ptr(),
            rsb as isize,
            csb as isize,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// `exp(x)` without branches (Cephes' `expf`: range reduction by ln 2, a degree-6
/// polynomial, the power of two built in the exponent bits), so that loops over it
/// vectorise; relative error ~2e-7. Inputs are clamped to [-87, 88].
#[inline(always)]
pub(super) fn exp_approx(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    let x = x.clamp(-87.0, 88.0);
    let t = x * core::f32::consts::LOG2_E + MAGIC;
    let n = t - MAGIC;
    let ni = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    let r = x - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let p = ((((1.987_569_1e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let y = p * r * r + r + 1.0;
    y * f32::from_bits(((ni + 127) << 23) as u32)
}

/// `tanh` over a slice: `1 − 2/(e^{2x} + 1)` (absolute error ~1e-7, the same size as
/// `burn`'s `2σ(2x) − 1` of [`crate::model::fast_tanh`]). The loop is compiled for AVX-512
/// and for AVX2 besides the baseline (SSE2) and the widest the CPU has runs: the same
/// operations in every lane (no FMA contraction), so the same numbers whichever runs. It
/// was a fifth of a minibatch step on SSE2.
pub(super) fn tanh_in_place(v: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            return unsafe { tanh_avx512(v) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { tanh_avx2(v) };
        }
    }
    tanh_loop(v);
}

/// [`tanh_in_place`]'s loop, inlined into each target-feature copy.
#[inline(always)]
pub(super) fn tanh_loop(v: &mut [f32]) {
    for x in v {
        *x = 1.0 - 2.0 / (exp_approx(2.0 * *x) + 1.0);
    }
}

/// [`tanh_loop`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) fn tanh_avx512(v: &mut [f32]) {
    tanh_loop(v);
}

/// [`tanh_loop`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) fn tanh_avx2(v: &mut [f32]) {
    tanh_loop(v);
}

/// `d ← d · (1 − h²)`: the gradient through `h = tanh(z)`.
pub(super) fn tanh_backward(d: &mut [f32], h: &[f32]) {
    for (d, &h) in d.iter_mut().zip(h) {
        *d *= 1.0 - h * h;
    }
}
