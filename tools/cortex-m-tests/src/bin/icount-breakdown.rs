//! Where the instructions of a controller step go, on the emulated Cortex-M4F: the
//! observation, `Policy::act`, single layers of rows A and G, the activations, and candidate
//! dot-product kernels on the same weights, each measured on its own with SysTick under
//! `qemu-system-arm -icount shift=0` (see `icount`).
//!
//! With fat LTO the code of a layer depends on the other uses of it in the image, so these
//! pieces can be a few percent off their cost inside `Controller::step` (measured by the
//! `icount` image, which uses nothing else); they tell which part dominates, not the total.
//!
//! Run: `cargo run -p tools -- cortex-m icount --breakdown` (profile `firmware`).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "icount-breakdown is a bare-metal bench for thumbv7em-none-eabihf; it runs under QEMU with -icount shift=0:\n  {} --breakdown",
        cortex_m_tests::RUN_ICOUNT
    );
}

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    let Some(p) = cortex_m::Peripherals::take() else {
        cortex_m_semihosting::debug::exit(cortex_m_semihosting::debug::EXIT_FAILURE);
        loop {
            cortex_m::asm::bkpt();
        }
    };
    let counter = cortex_m_tests::counter::start_calibrated(p.SYST);
    bench::pieces(&counter);
    bench::kernels(&counter);
    cortex_m_semihosting::debug::exit(cortex_m_semihosting::debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::bkpt();
    }
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m_tests::exit_on_panic(info)
}

#[cfg(target_os = "none")]
mod bench {
    use core::hint::black_box;
    use cortex_m_semihosting::hprintln;
    use cortex_m_tests::counter::{Counter, Stats};
    use cortex_m_tests::data::{BLOB_A, BLOB_G};
    use cortex_m_tests::fixtures::{FLIGHT_STEPS, flight};
    use firmware_core::PolicyState;
    use firmware_core::blob::Blob;
    use firmware_core::nn::{Linear, LstmCell, LstmLayerState, WeightReader, sigmoid, tanh};
    use firmware_core::observation::{Observation, ObservationSpec};
    use firmware_core::track::Track;

    fn report(name: &str, stats: &Stats, per: u64, unit: &str) {
        let hundredths = stats.hundredths_per(per);
        hprintln!(
            "  {}: {} instructions/call (min {}, max {}) = {}.{:02} per {}",
            name,
            stats.mean_instructions(),
            stats.min_instructions(),
            stats.max_instructions(),
            hundredths / 100,
            hundredths % 100,
            unit
        );
    }

    /// The pieces of a step measured on their own: the observation and the policy per row,
    /// then each layer and activation.
    pub fn pieces(counter: &Counter) {
        hprintln!("pieces of a step ({} calls each):", FLIGHT_STEPS);
        policy_pieces(counter);
        layer_pieces(counter);
    }

    /// `ObservationSpec::observe` and `Policy::act` of rows A and G over a flight.
    fn policy_pieces(counter: &Counter) {
        for (row, blob) in [('A', BLOB_A), ('G', BLOB_G)] {
            let Ok(b) = Blob::parse(blob) else { return };
            let Ok(policy) = b.policy() else { return };
            let spec: ObservationSpec = b.header().observation;
            let gate = Track::figure_eight().gate(0);
            let (mut obs_stats, mut act_stats) = (Stats::new(), Stats::new());
            let mut state: PolicyState = policy.initial_state();
            for i in 0..FLIGHT_STEPS {
                let (own, opponent) = flight(i);
                let (own, opponent) = (black_box(own), black_box(opponent));
                let previous = [0.1, -0.2, 0.3, 0.0];
                let (ticks, obs) =
                    counter.measure(|| spec.observe(&own, &gate, &previous, Some(&opponent)));
                obs_stats.add(ticks);
                let Ok(obs) = obs else { return };
                let obs: Observation = black_box(obs);
                let (ticks, mean) = counter.measure(|| policy.act(&obs, &mut state));
                black_box(mean);
                act_stats.add(ticks);
            }
            hprintln!("row {}:", row);
            report("ObservationSpec::observe", &obs_stats, 1, "call");
            report(
                "Policy::act",
                &act_stats,
                b.header().architecture.param_count() as u64,
                "weight",
            );
        }
    }

    /// Each layer of rows A and G, and the activations, on inputs of their sizes.
    fn layer_pieces(counter: &Counter) {
        let (Ok(a), Ok(g)) = (Blob::parse(BLOB_A), Blob::parse(BLOB_G)) else {
            return;
        };
        let (Some(aw), Some(gw)) = (a.weights(), g.weights()) else {
            return;
        };
        let mut ra = WeightReader::new(aw);
        let (Ok(a1), Ok(a2), Ok(a3)) = (
            Linear::<17, 128>::load(&mut ra),
            Linear::<128, 128>::load(&mut ra),
            Linear::<128, 4>::load(&mut ra),
        ) else {
            return;
        };
        let mut r = WeightReader::new(gw);
        let (Ok(l0), Ok(l1)) = (
            LstmCell::<30, 128>::load(&mut r),
            LstmCell::<128, 128>::load(&mut r),
        ) else {
            return;
        };
        let (Ok(m1), Ok(m2)) = (
            Linear::<128, 256>::load(&mut r),
            Linear::<256, 128>::load(&mut r),
        ) else {
            return;
        };
        let x17 = black_box([0.5f32; 17]);
        let x30 = black_box([0.25f32; 30]);
        let x128 = black_box([0.125f32; 128]);
        let x256 = black_box([0.0625f32; 256]);
        // Arguments like hidden pre-activations: spread over [-3, 3).
        let mut args = [0.0f32; 128];
        for (k, v) in args.iter_mut().enumerate() {
            *v = (k as f32) * (6.0 / 128.0) - 3.0;
        }
        let args = black_box(args);
        let mut s = LstmLayerState::<128>::default();
        let mut st = [Stats::new(); 10];
        let (mut y4, mut y128, mut y256) = ([0.0f32; 4], [0.0f32; 128], [0.0f32; 256]);
        let mut out = [0.0f32; 128];
        for _ in 0..FLIGHT_STEPS {
            st[0].add(counter.measure(|| a1.forward(&x17, &mut y128)).0);
            st[1].add(counter.measure(|| a2.forward(&x128, &mut y128)).0);
            st[2].add(counter.measure(|| a3.forward(&x128, &mut y4)).0);
            st[3].add(counter.measure(|| l0.step(&x30, &mut s)).0);
            st[4].add(counter.measure(|| l1.step(&x128, &mut s)).0);
            st[5].add(counter.measure(|| m1.forward(&x128, &mut y256)).0);
            st[6].add(counter.measure(|| m2.forward(&x256, &mut y128)).0);
            black_box((&y4, &y128, &y256));
            st[7].add(
                counter
                    .measure(|| args.iter().zip(&mut out).for_each(|(x, o)| *o = tanh(*x)))
                    .0,
            );
            black_box(&out);
            st[8].add(
                counter
                    .measure(|| {
                        args.iter()
                            .zip(&mut out)
                            .for_each(|(x, o)| *o = libm::tanhf(*x))
                    })
                    .0,
            );
            black_box(&out);
            st[9].add(
                counter
                    .measure(|| {
                        args.iter()
                            .zip(&mut out)
                            .for_each(|(x, o)| *o = sigmoid(*x))
                    })
                    .0,
            );
            black_box(&out);
        }
        hprintln!("row A layers:");
        report("Linear<17, 128>::forward", &st[0], 17 * 128, "MAC");
        report("Linear<128, 128>::forward", &st[1], 128 * 128, "MAC");
        report("Linear<128, 4>::forward", &st[2], 128 * 4, "MAC");
        hprintln!("row G layers:");
        report(
            "LstmCell<30, 128>::step (512 rows of 30 + 128 MACs)",
            &st[3],
            4 * 128 * (30 + 128),
            "MAC",
        );
        report(
            "LstmCell<128, 128>::step (512 rows of 128 + 128 MACs)",
            &st[4],
            4 * 128 * 256,
            "MAC",
        );
        report("Linear<128, 256>::forward", &st[5], 128 * 256, "MAC");
        report("Linear<256, 128>::forward", &st[6], 256 * 128, "MAC");
        hprintln!("activations (128 calls on [-3, 3)):");
        report("nn::tanh (1 - 2/(1 + expf(2x)))", &st[7], 128, "call");
        report("libm::tanhf", &st[8], 128, "call");
        report("nn::sigmoid (1/(1 + expf(-x)))", &st[9], 128, "call");
    }

    // `overtake_dot8_blocks(w, x, blocks, acc)`: `acc[k] += Σ_i w[8i + k] · x[8i + k]` for k in
    // 0..8 over `blocks` >= 1 blocks of 8: eight weights and eight inputs per `vldmia`, so
    // 8 MACs take 12 instructions. `vmla.f32` rounds the product, then the sum, exactly like
    // `a += w * x`. AAPCS-VFP: r0-r3 arguments, s0-s15 scratch, s16-s31 (d8-d15) saved.
    // (global_asm! rather than a naked function: the workspace's MSRV is 1.87.)
    core::arch::global_asm!(
        ".fpu fpv4-sp-d16",
        ".section .text.overtake_dot8_blocks,\"ax\",%progbits",
        ".global overtake_dot8_blocks",
        ".type overtake_dot8_blocks,%function",
        ".thumb_func",
        "overtake_dot8_blocks:",
        "vpush {{d8-d11}}",
        "vldmia r3, {{s0-s7}}",
        "2:",
        "vldmia r0!, {{s8-s15}}",
        "vldmia r1!, {{s16-s23}}",
        "vmla.f32 s0, s8, s16",
        "vmla.f32 s1, s9, s17",
        "vmla.f32 s2, s10, s18",
        "vmla.f32 s3, s11, s19",
        "vmla.f32 s4, s12, s20",
        "vmla.f32 s5, s13, s21",
        "vmla.f32 s6, s14, s22",
        "vmla.f32 s7, s15, s23",
        "subs r2, r2, #1",
        "bne 2b",
        "vstmia r3, {{s0-s7}}",
        "vpop {{d8-d11}}",
        "bx lr",
        ".size overtake_dot8_blocks, . - overtake_dot8_blocks",
    );

    unsafe extern "C" {
        /// See the assembly above. `w` and `x` must be valid for `8 * blocks` reads, `acc`
        /// for 8 reads and writes, `blocks` >= 1.
        fn overtake_dot8_blocks(w: *const f32, x: *const f32, blocks: usize, acc: *mut f32);
    }

    /// `nn::dot` (8 accumulators, the same final sum) with its inner loop in
    /// `overtake_dot8_blocks`: the same operations in the same order, so the same bits.
    #[inline(always)]
    fn dot_vldm(w: &[f32], x: &[f32]) -> f32 {
        let n = w.len().min(x.len());
        let blocks = n / 8;
        let mut acc = [0.0f32; 8];
        if blocks > 0 {
            // SAFETY: `8 * blocks <= n` values of each slice; `acc` holds 8.
            unsafe { overtake_dot8_blocks(w.as_ptr(), x.as_ptr(), blocks, acc.as_mut_ptr()) };
        }
        let mut tail = 0.0f32;
        for (wi, xi) in w.iter().zip(x).take(n).skip(8 * blocks) {
            tail += wi * xi;
        }
        ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
    }

    /// A 16-accumulator dot (firmware-core had one for a while), for comparison.
    #[inline(always)]
    fn dot16(w: &[f32], x: &[f32]) -> f32 {
        let mut acc = [0.0f32; 16];
        let (wc, xc) = (w.chunks_exact(16), x.chunks_exact(16));
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
        let mut width = 16;
        while width > 1 {
            width /= 2;
            let (lo, hi) = acc.split_at_mut(width);
            for (l, h) in lo.iter_mut().zip(hi.iter()) {
                *l += *h;
            }
        }
        acc[0] + tail
    }

    /// `y = W x + b` with the vldmia kernel.
    #[inline(never)]
    fn linear_vldm<const IN: usize, const OUT: usize>(
        w: &[f32],
        b: &[f32],
        x: &[f32; IN],
        y: &mut [f32; OUT],
    ) {
        for ((yo, row), bo) in y.iter_mut().zip(w.chunks_exact(IN)).zip(b) {
            *yo = dot_vldm(row, x) + bo;
        }
    }

    /// `y = W x + b` with the 16-lane dot.
    #[inline(never)]
    fn linear_dot16<const IN: usize, const OUT: usize>(
        w: &[f32],
        b: &[f32],
        x: &[f32; IN],
        y: &mut [f32; OUT],
    ) {
        for ((yo, row), bo) in y.iter_mut().zip(w.chunks_exact(IN)).zip(b) {
            *yo = dot16(row, x) + bo;
        }
    }

    /// `y = W x + b`, four rows per pass over `x` (each `x[j]` loaded once for 4 MACs),
    /// portable Rust.
    #[inline(never)]
    fn linear_rows4<const IN: usize, const OUT: usize>(
        w: &[f32],
        b: &[f32],
        x: &[f32; IN],
        y: &mut [f32; OUT],
    ) {
        let blocks = y
            .chunks_exact_mut(4)
            .zip(w.chunks_exact(4 * IN))
            .zip(b.chunks_exact(4));
        for ((ys, ws), bs) in blocks {
            let mut rows: [&[f32; IN]; 4] = [&[0.0; IN]; 4];
            for (row, wr) in rows.iter_mut().zip(ws.chunks_exact(IN)) {
                if let Some(wr) = wr.first_chunk::<IN>() {
                    *row = wr;
                }
            }
            let mut acc = [0.0f32; 4];
            for (j, xj) in x.iter().enumerate() {
                for (a, row) in acc.iter_mut().zip(&rows) {
                    *a += row[j] * xj;
                }
            }
            for ((yo, a), bo) in ys.iter_mut().zip(acc).zip(bs) {
                *yo = a + bo;
            }
        }
    }

    fn identical(a: &[f32], b: &[f32]) -> usize {
        a.iter()
            .zip(b)
            .filter(|(p, q)| p.to_bits() == q.to_bits())
            .count()
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f32::max)
    }

    /// One layer: `Linear::forward` and the candidate kernels on its weights.
    fn layer<const IN: usize, const OUT: usize>(
        counter: &Counter,
        name: &str,
        weights: &[f32],
        offset: usize,
    ) {
        let (Some(w), Some(b)) = (
            weights.get(offset..offset + IN * OUT),
            weights.get(offset + IN * OUT..offset + IN * OUT + OUT),
        ) else {
            return;
        };
        let mut r = WeightReader::new(weights.get(offset..).unwrap_or(&[]));
        let Ok(linear) = Linear::<IN, OUT>::load(&mut r) else {
            return;
        };
        let mut x = [0.0f32; IN];
        for (k, v) in x.iter_mut().enumerate() {
            *v = ((k * 37 % 101) as f32) / 50.0 - 1.0;
        }
        let x = black_box(x);
        let mut y = [[0.0f32; OUT]; 4];
        let mut st = [Stats::new(); 4];
        for _ in 0..10 {
            let [y0, y1, y2, y3] = &mut y;
            st[0].add(counter.measure(|| linear.forward(&x, y0)).0);
            st[1].add(counter.measure(|| linear_dot16::<IN, OUT>(w, b, &x, y1)).0);
            st[2].add(counter.measure(|| linear_rows4::<IN, OUT>(w, b, &x, y2)).0);
            st[3].add(counter.measure(|| linear_vldm::<IN, OUT>(w, b, &x, y3)).0);
            black_box(&y);
        }
        let macs = (IN * OUT) as u64;
        hprintln!("{} (Linear<{}, {}>):", name, IN, OUT);
        report(
            "Linear::forward (nn::dot: 8 accumulators)",
            &st[0],
            macs,
            "MAC",
        );
        report("16-accumulator dot", &st[1], macs, "MAC");
        report("4 rows per pass over x, portable", &st[2], macs, "MAC");
        report("nn::dot with a vldmia inner loop", &st[3], macs, "MAC");
        hprintln!(
            "  outputs: vldmia kernel bit-identical to Linear::forward in {} of {}; 4-row kernel max |diff| {:e}, 16-lane max |diff| {:e}",
            identical(&y[0], &y[3]),
            OUT,
            max_diff(&y[0], &y[2]),
            max_diff(&y[0], &y[1])
        );
    }

    /// Candidate kernels for `Linear::forward` on the weights of row G's first two MLP
    /// layers and row A's second layer.
    pub fn kernels(counter: &Counter) {
        let (Ok(a), Ok(g)) = (Blob::parse(BLOB_A), Blob::parse(BLOB_G)) else {
            return;
        };
        let (Some(aw), Some(gw)) = (a.weights(), g.weights()) else {
            return;
        };
        hprintln!("dot-product kernels on the same weights (10 calls each):");
        let g_mlp = LstmCell::<30, 128>::PARAMS + LstmCell::<128, 128>::PARAMS;
        layer::<128, 256>(counter, "row G MLP layer 1", gw, g_mlp);
        layer::<256, 128>(
            counter,
            "row G MLP layer 2",
            gw,
            g_mlp + Linear::<128, 256>::PARAMS,
        );
        layer::<128, 128>(counter, "row A layer 2", aw, Linear::<17, 128>::PARAMS);
    }
}
