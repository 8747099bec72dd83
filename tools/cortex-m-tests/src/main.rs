//! The Cortex-M4F test image: firmware-core on QEMU `mps2-an386`, reporting over semihosting.
//!
//! Tests: golden inference for rows A, B, C, E, F, G (weights read in place from flash);
//! blob defects on a RAM copy (CRC, truncation, magic, alignment); a 30-value observation
//! against the host's bits; the controller's fail-safe and a normal step. The last line is
//! `N passed, M failed`; QEMU exits with status 0 only when every test passed.
//!
//! Run: `cargo run -p cortex-m-tests --release --target thumbv7em-none-eabihf`.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    println!(
        "cortex-m-tests is a bare-metal image for thumbv7em-none-eabihf; it runs under QEMU \
         (mps2-an386, runner in .cargo/config.toml):\n  {}",
        cortex_m_tests::RUN_TESTS
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
    use cortex_m_tests::data::{self, Aligned, BLOB_A, BLOB_A_LEN, BLOB_G};
    use cortex_m_tests::fixtures::{flight, observation_case};
    use cortex_m_tests::golden::Golden;
    use cortex_m_tests::stack;
    use firmware_core::blob::{Blob, BlobError};
    use firmware_core::controller::{CONTROLLER_G_RAM_BYTES, Controller, StepFault};
    use firmware_core::observation::{Observation, ObservationLayout, ObservationSpec};
    use firmware_core::policy::Policy;
    use firmware_core::track::Track;
    use firmware_core::vehicle::MotorCommand;

    /// Largest error allowed between the M4's f32 inference and the float64 reference.
    const GOLDEN_TOLERANCE: f64 = 1e-5;
    /// Largest difference allowed between the M4's and the host's observation values.
    const OBSERVATION_TOLERANCE: f32 = 1e-6;

    struct Runner {
        passed: u32,
        failed: u32,
    }

    impl Runner {
        fn check(&mut self, name: &str, ok: bool) {
            if ok {
                self.passed += 1;
                hprintln!("test {} ... ok", name);
            } else {
                self.failed += 1;
                hprintln!("test {} ... FAILED", name);
            }
        }
    }

    pub fn run() -> ! {
        hprintln!(
            "cortex-m-tests: firmware-core on an emulated Cortex-M4F (mps2-an386); \
             size_of::<Controller>() = {} bytes",
            core::mem::size_of::<Controller<'static>>()
        );
        let mut r = Runner {
            passed: 0,
            failed: 0,
        };
        for &(row, blob, golden) in &data::GOLDEN {
            golden_inference(&mut r, row, blob, golden);
        }
        for &(row, blob, expected) in &data::INT8 {
            int8_inference(&mut r, row, blob, expected);
        }
        blob_defects(&mut r);
        observation(&mut r);
        controller(&mut r);
        hprintln!("{} passed, {} failed", r.passed, r.failed);
        debug::exit(if r.failed == 0 {
            EXIT_SUCCESS
        } else {
            EXIT_FAILURE
        });
        loop {
            cortex_m::asm::bkpt();
        }
    }

    /// `Blob::parse` in place from flash, `policy.act` over the golden sequence.
    fn golden_inference(r: &mut Runner, row: char, blob: &'static [u8], golden: &'static [u8]) {
        let name = match row {
            'A' => "golden_row_a",
            'B' => "golden_row_b",
            'C' => "golden_row_c",
            'E' => "golden_row_e",
            'F' => "golden_row_f",
            'G' => "golden_row_g",
            _ => "golden_row_unknown",
        };
        let (Some(golden), Ok(blob)) = (Golden::parse(golden), Blob::parse(blob)) else {
            hprintln!("  row {}: blob or golden data does not parse", row);
            return r.check(name, false);
        };
        let Ok(policy) = blob.policy() else {
            return r.check(name, false);
        };
        let in_flash = (blob.payload_words().as_ptr() as usize) < cortex_m_tests::CODE_REGION_BYTES;
        let mut max_err = 0.0f64;
        let mut finite = true;
        let replayed = replay(&policy, &golden, |got, want| {
            let err = (f64::from(got) - want).abs();
            finite &= err.is_finite();
            max_err = max_err.max(err);
        });
        let ok = in_flash && golden.steps() > 0 && replayed && finite;
        hprintln!(
            "  row {}: {} weights read in place at {:#010x}, {} steps, max |M4 f32 - f64 reference| = {:.3e} (tolerance {:.0e})",
            row,
            blob.header().architecture.param_count(),
            blob.payload_words().as_ptr() as usize,
            golden.steps(),
            max_err,
            GOLDEN_TOLERANCE
        );
        r.check(name, ok && max_err <= GOLDEN_TOLERANCE);
    }

    /// `policy.act` over `golden`'s observations from a zero state, each output given to
    /// `each` with its expected value; false when the data or the policy fails.
    fn replay(policy: &Policy<'_>, golden: &Golden<'_>, mut each: impl FnMut(f32, f64)) -> bool {
        let mut state = policy.initial_state();
        for i in 0..golden.steps() {
            let Some(step) = golden.step(i) else {
                return false;
            };
            let Some(obs) = Observation::from_values(step.obs()) else {
                return false;
            };
            let Some(mean) = policy.act(&obs, &mut state) else {
                return false;
            };
            for (got, want) in mean.iter().zip(step.mean) {
                each(*got, want);
            }
        }
        true
    }

    /// An int8 blob in flash, `policy.act` over the golden observations: every output must
    /// be the host's bit for bit (the SMLAD kernel against the portable one).
    fn int8_inference(r: &mut Runner, row: char, blob: &'static [u8], expected: &'static [u8]) {
        let name = match row {
            'A' => "int8_row_a_matches_host_bits",
            'G' => "int8_row_g_matches_host_bits",
            _ => "int8_row_unknown",
        };
        let (Some(expected), Ok(blob)) = (Golden::parse(expected), Blob::parse(blob)) else {
            hprintln!("  row {} int8: blob or expected data does not parse", row);
            return r.check(name, false);
        };
        let Ok(policy) = blob.policy() else {
            return r.check(name, false);
        };
        let (mut identical, mut total, mut max_diff) = (0u32, 0u32, 0.0f64);
        let replayed = replay(&policy, &expected, |got, want| {
            total += 1;
            identical += u32::from(f64::from(got).to_bits() == want.to_bits());
            max_diff = max_diff.max((f64::from(got) - want).abs());
        });
        if !replayed {
            return r.check(name, false);
        }
        hprintln!(
            "  row {} int8: {} payload bytes in flash, {} of {} outputs bit-identical to the host (max |diff| {:e})",
            row,
            blob.header().payload_len,
            identical,
            total,
            max_diff
        );
        r.check(name, total > 0 && identical == total);
    }

    static mut RAM_BLOB: Aligned<[u8; BLOB_A_LEN]> = Aligned([0; BLOB_A_LEN]);

    /// A fresh RAM copy of row A's blob (4-byte aligned: `Aligned`).
    fn ram_copy() -> &'static mut [u8] {
        let ptr = (&raw mut RAM_BLOB).cast::<u8>();
        // SAFETY: `RAM_BLOB` holds `BLOB_A_LEN` bytes; the image is single-threaded with no
        // interrupts, and each caller drops the previous borrow before calling again (the
        // tests below use one copy at a time).
        let buf = unsafe { core::slice::from_raw_parts_mut(ptr, BLOB_A_LEN) };
        buf.copy_from_slice(BLOB_A);
        buf
    }

    fn blob_defects(r: &mut Runner) {
        let ram = ram_copy();
        r.check("blob_ram_copy_parses", Blob::parse(ram).is_ok());

        // A payload bit: the last weight's lowest mantissa bit (still finite).
        let ram = ram_copy();
        let at = BLOB_A_LEN - 4 - 4;
        ram[at] ^= 0x01;
        let got = Blob::parse(ram);
        hprintln!("  flipped bit at byte {}: {:?}", at, got.as_ref().err());
        r.check(
            "blob_flipped_payload_bit_is_crc_mismatch",
            matches!(got, Err(BlobError::CrcMismatch { .. })),
        );

        let ram = ram_copy();
        let got = Blob::parse(&ram[..BLOB_A_LEN - 1]);
        hprintln!("  one byte short: {:?}", got.as_ref().err());
        r.check(
            "blob_truncated",
            got.err()
                == Some(BlobError::Truncated {
                    needed: BLOB_A_LEN,
                    available: BLOB_A_LEN - 1,
                }),
        );

        let ram = ram_copy();
        ram[0] = b'X';
        let got = Blob::parse(ram);
        r.check("blob_bad_magic", got.err() == Some(BlobError::BadMagic));

        let ram = ram_copy();
        let got = Blob::parse(&ram[1..]);
        r.check(
            "blob_misaligned",
            got.err() == Some(BlobError::Misaligned { offset_mod_4: 1 }),
        );
    }

    fn observation(r: &mut Runner) {
        let case = observation_case();
        let spec = ObservationSpec::paper(ObservationLayout::FullOpponent30);
        let Ok(obs) = spec.observe(
            &case.own,
            &case.gate,
            &case.previous_action,
            Some(&case.opponent),
        ) else {
            return r.check("observation_matches_host", false);
        };
        let expected = data::OBSERVATION_EXPECTED.chunks_exact(4).map(|b| {
            let mut w = [0u8; 4];
            w.copy_from_slice(b);
            f32::from_le_bytes(w)
        });
        let (mut identical, mut max_diff, mut n) = (0, 0.0f32, 0);
        for (got, want) in obs.as_slice().iter().zip(expected) {
            n += 1;
            identical += usize::from(got.to_bits() == want.to_bits());
            max_diff = max_diff.max((got - want).abs());
        }
        hprintln!(
            "  observation: {} values ({} expected), {} bit-identical to the host, max diff {:e}",
            obs.dim(),
            data::OBSERVATION_EXPECTED.len() / 4,
            identical,
            max_diff
        );
        r.check(
            "observation_matches_host",
            obs.dim() == 30 && n == 30 && max_diff <= OBSERVATION_TOLERANCE,
        );
    }

    fn controller(r: &mut Runner) {
        let Ok(mut c) = Controller::from_bytes(BLOB_G, Track::figure_eight()) else {
            return r.check("controller_from_bytes_g", false);
        };
        let Ok(mut c8) = Controller::from_bytes(data::BLOB_G_I8, Track::figure_eight()) else {
            return r.check("controller_from_bytes_g_int8", false);
        };
        let (own, opponent) = flight(0);
        let mut bad = own;
        bad.position_m.x = f32::NAN;
        let out = c.step(&bad, Some(&opponent));
        r.check(
            "controller_nan_state_gives_stop",
            out.command == MotorCommand::STOP
                && out.fault == Some(StepFault::NonFiniteState)
                && c.fault_count() == 1,
        );
        let out = c.step(&own, Some(&opponent));
        let rpm = out.command.rpm;
        hprintln!("  normal step: rpm {:?}, fault {:?}", rpm, out.fault);
        r.check(
            "controller_normal_step_is_finite",
            out.fault.is_none()
                && rpm.iter().all(|v| v.is_finite() && *v > 0.0)
                && c.fault_count() == 1,
        );
        // The compile-time RAM budget must bound what a step really uses on the target.
        let stack_bytes = stack::high_water(&mut || {
            let _ = c.step(&own, Some(&opponent));
        });
        let ram = core::mem::size_of::<Controller<'static>>() + stack_bytes;
        hprintln!(
            "  G controller RAM: {} B struct + {} B step stack = {} B (model {} B, budget 8192 B)",
            core::mem::size_of::<Controller<'static>>(),
            stack_bytes,
            ram,
            CONTROLLER_G_RAM_BYTES
        );
        r.check(
            "controller_g_ram_within_model_and_budget",
            ram <= CONTROLLER_G_RAM_BYTES && CONTROLLER_G_RAM_BYTES <= 8 * 1024,
        );
        // The int8 kernel's frame nests inside the head's: the same model must hold.
        let stack8 = stack::high_water(&mut || {
            let _ = c8.step(&own, Some(&opponent));
        });
        let ram8 = core::mem::size_of::<Controller<'static>>() + stack8;
        hprintln!(
            "  G int8 controller RAM: {} B struct + {} B step stack = {} B (model {} B, budget 8192 B)",
            core::mem::size_of::<Controller<'static>>(),
            stack8,
            ram8,
            CONTROLLER_G_RAM_BYTES
        );
        r.check(
            "controller_g_int8_ram_within_model_and_budget",
            ram8 <= CONTROLLER_G_RAM_BYTES,
        );
    }
}
