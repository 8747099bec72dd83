//! The row-G policy in int8 on an STM32F405: a minimal flight-controller task (firmware-core's
//! `Controller` stepped over the benchmark flight) with the blob in flash, linked against the
//! F405's memory map (`memory.x`). If the image did not fit, the link would fail with
//! "region `FLASH' overflowed"; `.ci/run` builds it, and builds the f32 variant
//! (`--features f32`) expecting exactly that failure. `cargo run -p tools -- size-report`
//! prints its sizes.
//!
//! Build: `cargo build -p stm32f405-fit --profile firmware --target thumbv7em-none-eabihf`.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "stm32f405-fit is a bare-metal image for thumbv7em-none-eabihf:\n  cargo build -p stm32f405-fit --profile firmware --target thumbv7em-none-eabihf"
    );
}

#[cfg(target_os = "none")]
#[path = "../../cortex-m-tests/src/fixtures.rs"]
#[allow(dead_code)]
mod fixtures;

/// Bytes at a 4-byte-aligned address, as `Blob::parse` requires.
#[cfg(target_os = "none")]
#[repr(C, align(4))]
struct Aligned<B: ?Sized>(B);

#[cfg(target_os = "none")]
static POLICY: &Aligned<[u8]> = &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/policy.bin")));

/// `size_of::<Controller>()` on this target, for `tools size-report`.
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_CONTROLLER_BYTES: u32 =
    core::mem::size_of::<firmware_core::Controller<'static>>() as u32;

/// The modelled stack of one row-G step (activations plus the frame allowance).
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_SCRATCH_G_BYTES: u32 = (firmware_core::policy::PolicyG::SCRATCH_BYTES
    + firmware_core::controller::STEP_FRAME_ALLOWANCE_BYTES)
    as u32;

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    use core::hint::black_box;
    use firmware_core::{Controller, Track};
    black_box(&OVERTAKE_CONTROLLER_BYTES);
    black_box(&OVERTAKE_SCRATCH_G_BYTES);
    let Ok(mut controller) = Controller::from_bytes(black_box(&POLICY.0), Track::figure_eight())
    else {
        loop {
            cortex_m::asm::wfi();
        }
    };
    let mut i = 0;
    loop {
        let (own, opponent) = fixtures::flight(black_box(i));
        black_box(controller.step(&own, Some(&opponent)));
        i = (i + 1) % fixtures::FLIGHT_STEPS;
    }
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(_: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m::asm::udf()
}
