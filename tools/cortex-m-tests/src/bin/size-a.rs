//! Size image of row A: one f32 policy blob (row A's synthetic weights) and a minimal program
//! that steps the controller on it forever. Built by `cargo run -p tools -- size-report`
//! (profile `firmware`), which reads its ELF; it is not meant to be run.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "size-a is a bare-metal size image for thumbv7em-none-eabihf; see: cargo run -p tools -- size-report"
    );
}

#[cfg(target_os = "none")]
#[cortex_m_rt::entry]
fn main() -> ! {
    cortex_m_tests::size_image::run(cortex_m_tests::data::BLOB_A)
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(_: &core::panic::PanicInfo<'_>) -> ! {
    cortex_m::asm::udf()
}
