//! Enables the int8 kernels' DSP path (SXTB16 and SMLAD, `nn::dot_i8_i16`) on Armv7E-M
//! targets: every `thumbv7em-*` core (Cortex-M4, M7) has the DSP extension. rustc does not
//! expose the `dsp` target feature to `cfg` on stable, hence the target-name test here.
fn main() {
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rustc-check-cfg=cfg(overtake_dsp)");
    let target = std::env::var("TARGET").unwrap_or_default();
    if target.starts_with("thumbv7em") {
        println!("cargo::rustc-cfg=overtake_dsp");
    }
}
