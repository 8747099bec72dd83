//! The shipped policies in int8 on an STM32F405: the stage-1 (time-trial, row A) and the
//! stage-2 (race, row G) policy `policy_source.rs` picks, both in flash, each with its own
//! firmware-core `Controller`, in a minimal flight-controller task that flies the one the
//! mode selects (a flight controller reads it from a switch; here a static the optimiser
//! cannot see through), stepped over the benchmark flight. Linked against the F405's memory
//! map (`memory.x`): if the image did not fit, the link would fail with "region `FLASH'
//! overflowed"; `.ci/run` builds it, and builds the f32 variant (`--features f32`) expecting
//! exactly that failure. `cargo run -p tools -- size-report` prints its sizes;
//! `cargo run -p tools -- cortex-m icount` counts the instructions of a step of both blobs.
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
static STAGE1: &Aligned<[u8]> = &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/stage1.bin")));

#[cfg(target_os = "none")]
static STAGE2: &Aligned<[u8]> = &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/stage2.bin")));

/// The flight mode: 0 flies the stage-1 policy (time trial), anything else the stage-2 one
/// (race). Volatile-read, so both controllers stay in the image.
#[cfg(target_os = "none")]
static MODE: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(1);

/// Controllers the image holds, for `tools size-report`.
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_CONTROLLER_COUNT: u32 = 2;

/// `size_of::<Controller>()` on this target, for `tools size-report`.
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_CONTROLLER_BYTES: u32 =
    core::mem::size_of::<firmware_core::Controller<'static>>() as u32;

/// The modelled stack of one row-A step (activations plus the frame allowance).
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_SCRATCH_A_BYTES: u32 = firmware_core::controller::STEP_STACK_A_BYTES as u32;

/// The modelled stack of one row-G step (activations plus the frame allowance).
#[cfg(target_os = "none")]
#[unsafe(no_mangle)]
pub static OVERTAKE_SCRATCH_G_BYTES: u32 = firmware_core::controller::STEP_STACK_G_BYTES as u32;

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    use core::hint::black_box;
    use firmware_core::{Controller, Track};
    black_box(&OVERTAKE_CONTROLLER_BYTES);
    black_box(&OVERTAKE_SCRATCH_A_BYTES);
    black_box(&OVERTAKE_SCRATCH_G_BYTES);
    black_box(&OVERTAKE_CONTROLLER_COUNT);
    let track = Track::figure_eight();
    let (Ok(mut time_trial), Ok(mut race)) = (
        Controller::from_bytes(black_box(&STAGE1.0), track),
        Controller::from_bytes(black_box(&STAGE2.0), track),
    ) else {
        loop {
            cortex_m::asm::wfi();
        }
    };
    let mut i = 0;
    loop {
        let (own, opponent) = fixtures::flight(black_box(i));
        let out = if MODE.load(core::sync::atomic::Ordering::Relaxed) == 0 {
            time_trial.step(&own, None)
        } else {
            race.step(&own, Some(&opponent))
        };
        black_box(out);
        i = (i + 1) % fixtures::FLIGHT_STEPS;
    }
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(_: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m::asm::udf()
}
