//! The program of the size images: a controller on one embedded blob, stepped forever over
//! the benchmark flight. Nothing else (no semihosting, no formatting), so the ELF's sizes are
//! those of a minimal flight-controller task around the inference code.

use core::hint::black_box;
use firmware_core::{Controller, Track};

use crate::fixtures::{FLIGHT_STEPS, flight};

/// Builds a controller on `blob` and steps it forever; on a bad blob, waits forever.
pub fn run(blob: &'static [u8]) -> ! {
    // Keep the size symbols in the image for `tools size-report` (12 bytes of .rodata).
    black_box(&crate::data::OVERTAKE_CONTROLLER_BYTES);
    black_box(&crate::data::OVERTAKE_SCRATCH_A_BYTES);
    black_box(&crate::data::OVERTAKE_SCRATCH_G_BYTES);
    let Ok(mut controller) = Controller::from_bytes(black_box(blob), Track::figure_eight()) else {
        loop {
            cortex_m::asm::wfi();
        }
    };
    let mut i = 0;
    loop {
        let (own, opponent) = flight(black_box(i));
        black_box(controller.step(&own, Some(&opponent)));
        i = (i + 1) % FLIGHT_STEPS;
    }
}
