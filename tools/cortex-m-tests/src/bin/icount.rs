//! Instructions per `Controller::step` on the emulated Cortex-M4F, for rows A and G in f32
//! and in int8 (synthetic weights), and for the shipped stage-1 and stage-2 policies the
//! STM32F405 image holds (int8), against the budget of one 50 Hz step on a 168 MHz F405.
//!
//! Runs under `qemu-system-arm ... -icount shift=0` (1 ns of virtual time per instruction)
//! and counts with SysTick (25 MHz: one tick per 40 instructions). It first calibrates on a
//! loop of known length, then steps each controller 100 times over the benchmark flight and
//! reports the mean, min and max instructions per step and the stack high-water mark of one
//! step. The image uses firmware-core only through `Controller` (as a flight controller
//! would), because with fat LTO the code generated for the inference loops depends on every
//! other use in the image; the per-layer breakdown is a separate image (`icount-breakdown`).
//! Exits with failure when the calibration is off by more than 1 % (not running under `-icount shift=0`).
//!
//! Run: `cargo run -p tools -- cortex-m icount` (profile `firmware`).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "icount is a bare-metal bench for thumbv7em-none-eabihf; it runs under QEMU with -icount shift=0:\n  {}",
        cortex_m_tests::RUN_ICOUNT
    );
}

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    bench::run()
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m_tests::exit_on_panic(info)
}

#[cfg(target_os = "none")]
mod bench {
    use core::hint::black_box;
    use cortex_m_semihosting::debug::{self, EXIT_FAILURE, EXIT_SUCCESS};
    use cortex_m_semihosting::hprintln;
    use cortex_m_tests::counter::{Counter, INSTRUCTIONS_PER_TICK, Stats, start_calibrated};
    use cortex_m_tests::data::{BLOB_A, BLOB_A_I8, BLOB_G, BLOB_G_I8, SHIPPED};
    use cortex_m_tests::fixtures::{FLIGHT_STEPS, flight};
    use cortex_m_tests::stack;
    use firmware_core::Controller;
    use firmware_core::track::Track;

    /// Targets of the issue (instructions per step).
    const TARGET_A: u64 = 90_000;
    const TARGET_G: u64 = 1_300_000;
    const TARGET_G_I8: u64 = 1_000_000;
    /// Core clock of the STM32F405 (Hz).
    const F405_CLOCK_HZ: u64 = 168_000_000;
    /// The control rate every policy runs at (Hz).
    const CONTROL_RATE_HZ: u64 = 50;
    /// Cycles in one control step: 3,360,000. An instruction takes at least one cycle on
    /// the M4 (loads, multiplies-accumulate and flash wait states add more), so the
    /// instruction count is a lower bound on the cycles a step costs.
    const STEP_BUDGET_CYCLES: u64 = F405_CLOCK_HZ / CONTROL_RATE_HZ;

    pub fn run() -> ! {
        let Some(p) = cortex_m::Peripherals::take() else {
            hprintln!("icount: peripherals already taken");
            debug::exit(EXIT_FAILURE);
            loop {
                cortex_m::asm::bkpt();
            }
        };
        let counter = start_calibrated(p.SYST);
        let a = controller_steps(&counter, "row A", BLOB_A, TARGET_A);
        let g = controller_steps(&counter, "row G", BLOB_G, TARGET_G);
        let a8 = controller_steps(&counter, "row A int8", BLOB_A_I8, TARGET_A);
        let g8 = controller_steps(&counter, "row G int8", BLOB_G_I8, TARGET_G_I8);
        let mut within_budget = true;
        for shipped in &SHIPPED {
            hprintln!("{}", shipped.what);
            let steps = controller_steps(&counter, shipped.slot, shipped.blob, STEP_BUDGET_CYCLES);
            hprintln!(
                "{}: {} instructions/step = {}.{:02} % of the {} cycles of one 50 Hz step at 168 MHz ({}x headroom at one cycle per instruction)",
                shipped.slot,
                steps,
                100 * steps / STEP_BUDGET_CYCLES,
                (10_000 * steps / STEP_BUDGET_CYCLES) % 100,
                STEP_BUDGET_CYCLES,
                STEP_BUDGET_CYCLES / steps.max(1)
            );
            within_budget &= steps <= STEP_BUDGET_CYCLES;
        }
        hprintln!(
            "icount: A {} instructions/step (target {}: {}), G {} instructions/step (target {}: {}); int8: A {}, G {} instructions/step (target {}: {})",
            a,
            TARGET_A,
            verdict(a, TARGET_A),
            g,
            TARGET_G,
            verdict(g, TARGET_G),
            a8,
            g8,
            TARGET_G_I8,
            verdict(g8, TARGET_G_I8)
        );
        debug::exit(if within_budget {
            EXIT_SUCCESS
        } else {
            EXIT_FAILURE
        });
        loop {
            cortex_m::asm::bkpt();
        }
    }

    fn verdict(value: u64, target: u64) -> &'static str {
        if value <= target { "met" } else { "MISSED" }
    }

    #[inline(never)]
    fn one_step(c: &mut Controller<'_>, i: u32) {
        let (own, opponent) = flight(i);
        black_box(c.step(black_box(&own), Some(black_box(&opponent))));
    }

    /// Mean instructions of `Controller::step` over the flight (one warm-up step first).
    fn controller_steps(counter: &Counter, row: &str, blob: &'static [u8], target: u64) -> u64 {
        let Ok(mut c) = Controller::from_bytes(blob, Track::figure_eight()) else {
            hprintln!("{}: blob does not load", row);
            debug::exit(EXIT_FAILURE);
            return 0;
        };
        let stack_bytes = stack::high_water(&mut || one_step(&mut c, 0));
        c.reset(0);
        let mut stats = Stats::new();
        for i in 0..FLIGHT_STEPS {
            let (own, opponent) = flight(i);
            let (own, opponent) = (black_box(own), black_box(opponent));
            let (ticks, out) = counter.measure(|| c.step(&own, Some(&opponent)));
            black_box(out);
            stats.add(ticks);
        }
        let mean = stats.mean_instructions();
        hprintln!(
            "{}: Controller::step: {} instructions/step mean over {} steps (min {}, max {}; +-{} quantisation), target <= {}: {}; stack high-water {} bytes; faults {}, gates passed {}",
            row,
            mean,
            stats.n,
            stats.min_instructions(),
            stats.max_instructions(),
            INSTRUCTIONS_PER_TICK,
            target,
            verdict(mean, target),
            stack_bytes,
            c.fault_count(),
            c.progress().gates_passed
        );
        mean
    }
}
