//! The shipped policies of the STM32F405 image (`tools/stm32f405-fit/policy_source.rs`: the
//! stage-1 and the stage-2 policy) on the emulated Cortex-M4F, in int8: each flown by
//! firmware-core's `Controller` over the benchmark flight (`fixtures::flight`, 100 steps
//! through gate 0), every rotor command against the host controller's bit for bit, no step
//! faulting. Its own image because, beside the golden blobs of the test image (3.8 MB), the
//! shipped ones (0.35 MB) would overflow the 4 MB code region of mps2-an386. The last line
//! is `N passed, M failed`; QEMU exits with status 0 only when every test passed.
//!
//! Run: `cargo run -p tools -- cortex-m test` (after the test image).
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "shipped is a bare-metal test image for thumbv7em-none-eabihf; it runs under QEMU:\n  {}",
        cortex_m_tests::RUN_TESTS_TOOL
    );
}

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    image::run()
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m_tests::exit_on_panic(info)
}

#[cfg(target_os = "none")]
mod image {
    use cortex_m_semihosting::debug::{self, EXIT_FAILURE, EXIT_SUCCESS};
    use cortex_m_semihosting::hprintln;
    use cortex_m_tests::data::{SHIPPED, Shipped};
    use cortex_m_tests::fixtures::{FLIGHT_STEPS, flight};
    use firmware_core::Controller;
    use firmware_core::blob::{Blob, WeightDtype};
    use firmware_core::track::Track;

    pub fn run() -> ! {
        let (mut passed, mut failed) = (0u32, 0u32);
        for shipped in &SHIPPED {
            let ok = flies_as_on_the_host(shipped);
            if ok {
                passed += 1;
            } else {
                failed += 1;
            }
            hprintln!(
                "test shipped_{}_int8_controller_matches_host_bit_for_bit ... {}",
                shipped.slot,
                if ok { "ok" } else { "FAILED" }
            );
        }
        hprintln!("{} passed, {} failed", passed, failed);
        debug::exit(if failed == 0 {
            EXIT_SUCCESS
        } else {
            EXIT_FAILURE
        });
        loop {
            cortex_m::asm::bkpt();
        }
    }

    /// The shipped int8 policy flown by `Controller` over the benchmark flight: every rotor
    /// command equals the host's bit for bit, and no step faults.
    fn flies_as_on_the_host(shipped: &Shipped) -> bool {
        hprintln!("  {}", shipped.what);
        let Ok(header) = Blob::parse(shipped.blob).map(|b| b.header().clone()) else {
            hprintln!("  the blob does not parse");
            return false;
        };
        let int8 = header.dtype == WeightDtype::I8;
        let observes_opponent = header.observation.layout.needs_opponent();
        let Ok(mut c) = Controller::from_bytes(shipped.blob, Track::figure_eight()) else {
            hprintln!("  the blob does not load");
            return false;
        };
        let (mut steps, mut differing, mut max_diff) = (0u32, 0u32, 0.0f32);
        for (i, want) in (0..FLIGHT_STEPS).zip(shipped.commands.chunks_exact(16)) {
            let (own, opponent) = flight(i);
            let out = c.step(&own, observes_opponent.then_some(&opponent));
            for (got, want) in out.command.rpm.iter().zip(want.chunks_exact(4)) {
                let want = f32::from_le_bytes([want[0], want[1], want[2], want[3]]);
                if got.to_bits() != want.to_bits() {
                    differing += 1;
                    max_diff = max_diff.max((got - want).abs());
                }
            }
            steps += 1;
        }
        hprintln!(
            "  int8 {}; {} steps: {} of {} rotor commands differ from the host's (max {} rpm); faults {}, gates passed {}",
            int8,
            steps,
            differing,
            4 * steps,
            max_diff,
            c.fault_count(),
            c.progress().gates_passed
        );
        int8 && steps == FLIGHT_STEPS
            && shipped.commands.len() == 16 * FLIGHT_STEPS as usize
            && differing == 0
            && c.fault_count() == 0
    }
}
