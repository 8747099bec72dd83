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

/// Defines `$name`, which runs `$body` compiled for AVX-512, AVX2 or the baseline (SSE2),
/// the widest the CPU has (checked per call: `is_x86_feature_detected!` caches its answer).
/// The bodies are elementwise loops with the same operations in every lane (no FMA
/// contraction), so every variant gives the same numbers.
macro_rules! multiversion {
    ($(#[$doc:meta])* fn $name:ident($($arg:ident: $ty:ty),*) $body:block) => {
        $(#[$doc])*
        pub(super) fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                fn avx512($($arg: $ty),*) $body
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) $body
                if std::arch::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU has AVX-512F (checked just above).
                    return unsafe { avx512($($arg),*) };
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2 (checked just above).
                    return unsafe { avx2($($arg),*) };
                }
            }
            $body
        }
    };
}

/// `tanh(x) = 1 − 2/(e^{2x} + 1)` (absolute error ~1e-7, the same size as `burn`'s
/// `2σ(2x) − 1` of [`crate::model::fast_tanh`]).
#[inline(always)]
pub(super) fn tanh_approx(x: f32) -> f32 {
    1.0 - 2.0 / (exp_approx(2.0 * x) + 1.0)
}

/// `σ(x) = 1/(1 + e^{−x})`.
#[inline(always)]
pub(super) fn sigmoid_approx(x: f32) -> f32 {
    1.0 / (1.0 + exp_approx(-x))
}

multiversion! {
    /// [`tanh_approx`] over a slice, vectorised (it was a fifth of a minibatch step on
    /// SSE2).
    fn tanh_in_place(v: &mut [f32]) {
        tanh_loop(v);
    }
}

/// [`tanh_in_place`]'s loop, inlined into each target-feature copy.
#[inline(always)]
pub(super) fn tanh_loop(v: &mut [f32]) {
    for x in v {
        *x = tanh_approx(*x);
    }
}

multiversion! {
    /// One LSTM step for `c.len() / hidden` rows (row-major, PyTorch's gate blocks i, f, g,
    /// o): `gates` `[rows, 4H]` holds the pre-activations on entry and σ(i), σ(f), tanh(g),
    /// σ(o) on return; with the (masked) previous cell `c_prev` it writes
    /// `c = f·c_prev + i·g`, `tc = tanh(c)` and `h = o·tc`, each `[rows, H]`.
    fn lstm_cell_forward(
        gates: &mut [f32],
        c_prev: &[f32],
        c: &mut [f32],
        tc: &mut [f32],
        h: &mut [f32],
        hidden: usize
    ) {
        let rows = gates
            .chunks_exact_mut(4 * hidden)
            .zip(c_prev.chunks_exact(hidden))
            .zip(c.chunks_exact_mut(hidden))
            .zip(tc.chunks_exact_mut(hidden))
            .zip(h.chunks_exact_mut(hidden));
        for ((((z, c_prev), c), tc), h) in rows {
            let (ifg, o) = z.split_at_mut(3 * hidden);
            let (i_f, g) = ifg.split_at_mut(2 * hidden);
            // Separate loops: a chained iterator does not vectorise.
            for x in i_f.iter_mut() {
                *x = sigmoid_approx(*x);
            }
            for x in o.iter_mut() {
                *x = sigmoid_approx(*x);
            }
            for x in g.iter_mut() {
                *x = tanh_approx(*x);
            }
            let (i, f) = i_f.split_at(hidden);
            let cells = i.iter().zip(f).zip(g.iter()).zip(c_prev).zip(c.iter_mut());
            for ((((&i, &f), &g), &cp), c) in cells {
                *c = f * cp + i * g;
            }
            for (t, &c) in tc.iter_mut().zip(c.iter()) {
                *t = tanh_approx(c);
            }
            for ((h, &o), &t) in h.iter_mut().zip(o.iter()).zip(tc.iter()) {
                *h = o * t;
            }
        }
    }
}

multiversion! {
    /// The gradient through [`lstm_cell_forward`] for the same rows: `gates` its
    /// activations, `c_prev` and `tc` its inputs and outputs; `dh` and `dc` hold
    /// d loss / d h and the gradient reaching `c` from the next step. Writes the
    /// pre-activations' gradient into `dz` `[rows, 4H]` and leaves d loss / d c_prev (before
    /// the mask) in `dc`.
    fn lstm_cell_backward(
        gates: &[f32],
        c_prev: &[f32],
        tc: &[f32],
        dh: &[f32],
        dc: &mut [f32],
        dz: &mut [f32],
        hidden: usize
    ) {
        let rows = gates
            .chunks_exact(4 * hidden)
            .zip(c_prev.chunks_exact(hidden))
            .zip(tc.chunks_exact(hidden))
            .zip(dh.chunks_exact(hidden))
            .zip(dc.chunks_exact_mut(hidden))
            .zip(dz.chunks_exact_mut(4 * hidden));
        for (((((z, c_prev), tc), dh), dc), dz) in rows {
            let (i, rest) = z.split_at(hidden);
            let (f, rest) = rest.split_at(hidden);
            let (g, o) = rest.split_at(hidden);
            let (dz_i, rest) = dz.split_at_mut(hidden);
            let (dz_f, rest) = rest.split_at_mut(hidden);
            let (dz_g, dz_o) = rest.split_at_mut(hidden);
            // Re-sliced to `hidden` so that the loop runs without bounds checks.
            let (i, f, g, o) = (&i[..hidden], &f[..hidden], &g[..hidden], &o[..hidden]);
            let (c_prev, tc, dh, dc) = (&c_prev[..hidden], &tc[..hidden], &dh[..hidden], &mut dc[..hidden]);
            let (dz_i, dz_f, dz_g) = (&mut dz_i[..hidden], &mut dz_f[..hidden], &mut dz_g[..hidden]);
            let dz_o = &mut dz_o[..hidden];
            for k in 0..hidden {
                let (i, f, g, o, t, dh) = (i[k], f[k], g[k], o[k], tc[k], dh[k]);
                let d_c = dc[k] + dh * o * (1.0 - t * t);
                dz_i[k] = d_c * g * (i * (1.0 - i));
                dz_f[k] = d_c * c_prev[k] * (f * (1.0 - f));
                dz_g[k] = d_c * i * (1.0 - g * g);
                dz_o[k] = dh * t * (o * (1.0 - o));
                dc[k] = d_c * f;
            }
        }
    }
}

/// `d ← d · (1 − h²)`: the gradient through `h = tanh(z)`.
pub(super) fn tanh_backward(d: &mut [f32], h: &[f32]) {
    for (d, &h) in d.iter_mut().zip(h) {
        *d *= 1.0 - h * h;
    }
}
