//! The `*_lanes` kernels: [`LANES`] inputs side by side, each lane bit for bit the
//! one-input kernel of [`super::kernels`].

use super::{LANES, Lanes};

/// [`dot`](super::kernels::dot) of `w` with each lane of `x` (`x[k][lane]`,
/// `x.len() == w.len()`): the same eight accumulators, tail and reduction order per lane,
/// so each lane is bit for bit `dot` of its own vector. Written as whole-lane operations ([`axpy_lanes`], [`add_lanes`]) so
/// that each is one vector instruction of the lanes (written as nested iterators, the
/// compiler vectorised across the accumulators instead, with gathers, at half the speed of
/// one input at a time).
#[inline(always)]
pub(super) fn dot_lanes(w: &[f32], x: &[[f32; LANES]]) -> [f32; LANES] {
    // The eight accumulators are eight variables, not an array: with a loop over them the
    // compiler vectorised across the accumulators (stride 64 bytes, with gathers and
    // scatters) instead of along the lanes, 2-4x slower than one input at a time.
    let z = [0.0f32; LANES];
    let (mut a0, mut a1, mut a2, mut a3, mut a4, mut a5, mut a6, mut a7) = (z, z, z, z, z, z, z, z);
    let wc = w.chunks_exact(8);
    let xc = x.chunks_exact(8);
    let (wr, xr) = (wc.remainder(), xc.remainder());
    for (wk, xk) in wc.zip(xc) {
        if let ([w0, w1, w2, w3, w4, w5, w6, w7], [x0, x1, x2, x3, x4, x5, x6, x7]) = (wk, xk) {
            axpy_lanes(&mut a0, *w0, x0);
            axpy_lanes(&mut a1, *w1, x1);
            axpy_lanes(&mut a2, *w2, x2);
            axpy_lanes(&mut a3, *w3, x3);
            axpy_lanes(&mut a4, *w4, x4);
            axpy_lanes(&mut a5, *w5, x5);
            axpy_lanes(&mut a6, *w6, x6);
            axpy_lanes(&mut a7, *w7, x7);
        }
    }
    let mut tail = [0.0f32; LANES];
    for (wi, xi) in wr.iter().zip(xr) {
        axpy_lanes(&mut tail, *wi, xi);
    }
    let s04 = add_lanes(&a0, &a4);
    let s15 = add_lanes(&a1, &a5);
    let s26 = add_lanes(&a2, &a6);
    let s37 = add_lanes(&a3, &a7);
    let lo = add_lanes(&s04, &s15);
    let hi = add_lanes(&s26, &s37);
    add_lanes(&add_lanes(&lo, &hi), &tail)
}

/// `acc[l] += w · x[l]` in every lane (a product, then a sum: no fused multiply-add, as
/// [`dot`](super::kernels::dot)).
#[inline(always)]
fn axpy_lanes(acc: &mut [f32; LANES], w: f32, x: &[f32; LANES]) {
    for (a, xl) in acc.iter_mut().zip(x) {
        *a += w * xl;
    }
}

/// `a[l] + b[l]` in every lane.
#[inline(always)]
pub(super) fn add_lanes(a: &[f32; LANES], b: &[f32; LANES]) -> [f32; LANES] {
    let mut out = *a;
    for (o, bl) in out.iter_mut().zip(b) {
        *o += bl;
    }
    out
}

/// [`super::tanh`] of every value, [`LANES`] at a time through [`expf_lanes`]: the same bits.
#[inline(always)]
pub(super) fn tanh_lanes(v: &mut [[f32; LANES]]) {
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
pub(super) fn expf_lanes(x: &[f32; LANES]) -> [f32; LANES] {
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
pub(super) fn lane<const N: usize>(x: &Lanes<N>, l: usize) -> [f32; N] {
    let mut out = [0.0f32; N];
    for (o, xk) in out.iter_mut().zip(x) {
        *o = xk.get(l).copied().unwrap_or(0.0);
    }
    out
}

/// Sets lane `l` of `y` to `v`.
#[inline(always)]
pub(super) fn set_lane<const N: usize>(y: &mut Lanes<N>, l: usize, v: &[f32; N]) {
    for (yk, vk) in y.iter_mut().zip(v) {
        if let Some(slot) = yk.get_mut(l) {
            *slot = *vk;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::tanh;

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
}
