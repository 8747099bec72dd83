//! Stack high-water mark of a call: paint the free stack below the current stack pointer,
//! run the call, find the lowest word that changed.

/// Bytes painted below the stack pointer (the RAM is 4 MB; the images use little of it).
pub const PAINT_BYTES: usize = 64 * 1024;
const PATTERN: u32 = 0xDEAD_BEEF;

/// Bytes of stack below this function's frame that `f` touched (its own frames, spills and
/// locals: for a `Controller::step`, the activations and gate pre-activations).
#[inline(never)]
pub fn high_water(f: &mut dyn FnMut()) -> usize {
    let sp = cortex_m::register::msp::read() as usize & !3;
    let bottom = sp - PAINT_BYTES;
    let mut addr = bottom;
    while addr < sp {
        // SAFETY: [bottom, sp) is free stack below the live frames (no interrupts are
        // enabled, so nothing else uses it); 4-byte aligned.
        unsafe { core::ptr::write_volatile(addr as *mut u32, PATTERN) };
        addr += 4;
    }
    f();
    let mut addr = bottom;
    // SAFETY: as above, reading back the painted words.
    while addr < sp && unsafe { core::ptr::read_volatile(addr as *const u32) } == PATTERN {
        addr += 4;
    }
    sp - addr
}
