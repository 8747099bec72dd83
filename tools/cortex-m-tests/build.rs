//! Build script of the Cortex-M4 images (runs on the host).
//!
//! * puts `memory.x` (QEMU mps2-an386) on the linker search path for cortex-m-rt's `link.x`;
//! * for a bare-metal target, writes to `OUT_DIR`, for each golden row A, B, C, E, F, G:
//!   - `blob_X.bin`: the synthetic blob exactly as the host tests build it
//!     (`firmware_core::synthetic::blob(row, 0x0DD5_EED0 + letter)`);
//!   - `golden_X.bin`: `tests/golden/row_X.golden` parsed to binary: `dim` u32, `steps` u32,
//!     then per step `dim` f32 observations and 4 f64 expected means (all little-endian);
//! * for rows A and G, `blob_X_i8.bin` (the same synthetic weights quantised to int8,
//!   `synthetic::blob_i8`) and `int8_X.bin`: the golden observations with, in place of the
//!   f64 reference, the host's own int8 outputs (f32 widened to f64), which the M4 must
//!   reproduce bit for bit;
//! * `observation_expected.bin`: the 30 f32 of `fixtures::observation_case()` observed
//!   with the host's firmware-core, for the M4 to reproduce;
//! * for the shipped policies the STM32F405 image holds (`../stm32f405-fit/policy_source.rs`:
//!   stage 1 and stage 2), `shipped_N.bin` (the blob in int8), `shipped_N.txt` (what it is)
//!   and `shipped_N_commands.bin`: the rotor commands (4 f32 rpm per step, little-endian) the
//!   host's `Controller` gives on it over `fixtures::flight`, which the M4 must reproduce.

use std::env;
use std::fs;
use std::path::{Path, PathBuf};

use firmware_core::blob::{AlignedBytes, Blob, WeightDtype, convert_bytes};
use firmware_core::controller::Controller;
use firmware_core::observation::{Observation, ObservationLayout, ObservationSpec};
use firmware_core::policy::{Architecture, TableRow};
use firmware_core::synthetic::{self, GOLDEN_ROWS, golden_seed};
use firmware_core::track::Track;

#[path = "src/fixtures.rs"]
#[allow(dead_code)]
mod fixtures;

#[path = "../stm32f405-fit/policy_source.rs"]
mod policy_source;

/// Bytes of the mps2-an386 code region (memory.x `FLASH`).
const CODE_REGION_BYTES: usize = 4 * 1024 * 1024;
/// Room left in the code region for the program itself.
const CODE_RESERVE_BYTES: usize = 256 * 1024;

fn main() {
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR"));
    let root = manifest.join("../..");
    let golden_dir = root.join("tests/golden");

    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=src/fixtures.rs");
    println!("cargo:rerun-if-changed=../stm32f405-fit/policy_source.rs");
    for slot in policy_source::IMAGE_POLICIES {
        for p in slot.candidates {
            println!("cargo:rerun-if-changed={}", root.join(p).display());
        }
    }
    println!("cargo:rerun-if-changed={}", golden_dir.display());
    for row in GOLDEN_ROWS {
        println!(
            "cargo:rerun-if-changed={}",
            golden_path(&golden_dir, row).display()
        );
    }
    println!(
        "cargo:rerun-if-changed={}",
        root.join("firmware-core/src").display()
    );
    println!(
        "cargo:rerun-if-changed={}",
        root.join("firmware-core/Cargo.toml").display()
    );

    fs::copy(manifest.join("memory.x"), out.join("memory.x")).expect("copy memory.x to OUT_DIR");
    println!("cargo:rustc-link-search={}", out.display());

    // The data is only embedded in the bare-metal images; a host check needs none of it.
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }

    let mut total = 0;
    for row in GOLDEN_ROWS {
        let blob = synthetic::blob(row, golden_seed(row)).unwrap_or_else(|e| {
            panic!(
                "row {}: encoding the synthetic blob failed: {e}",
                row.letter()
            )
        });
        total += blob.len();
        write(&out.join(format!("blob_{}.bin", row.letter())), &blob);
        let path = golden_path(&golden_dir, row);
        let text = fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let golden = parse_golden(row, &text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        if matches!(row, TableRow::A | TableRow::G) {
            let blob = synthetic::blob_i8(row, golden_seed(row))
                .unwrap_or_else(|e| panic!("row {}: int8 encoding failed: {e}", row.letter()));
            total += blob.len();
            let expected = int8_expectation(&blob, &golden)
                .unwrap_or_else(|e| panic!("row {}: int8 expectation: {e}", row.letter()));
            write(&out.join(format!("blob_{}_i8.bin", row.letter())), &blob);
            write(&out.join(format!("int8_{}.bin", row.letter())), &expected);
        }
        write(&out.join(format!("golden_{}.bin", row.letter())), &golden);
    }
    assert!(
        total + CODE_RESERVE_BYTES <= CODE_REGION_BYTES,
        "the six golden blobs take {total} bytes: with {CODE_RESERVE_BYTES} bytes for the \
         program they do not fit the {CODE_REGION_BYTES}-byte code region of mps2-an386"
    );

    // The shipped blobs live in their own image (`shipped`; `icount` holds them beside the
    // synthetic A and G blobs, less than the golden set).
    let mut shipped_total = 0;
    for (n, slot) in policy_source::IMAGE_POLICIES.iter().enumerate() {
        let n = n + 1;
        let (what, source) = policy_source::source_blob(&root, slot)
            .unwrap_or_else(|e| panic!("the {} blob: {e}", slot.role));
        let blob = convert_bytes(&source, WeightDtype::I8)
            .unwrap_or_else(|e| panic!("{what}: int8 conversion: {e}"));
        shipped_total += blob.len();
        let commands = controller_commands(&blob).unwrap_or_else(|e| panic!("{what}: {e}"));
        write(&out.join(format!("shipped_{n}.bin")), &blob);
        write(
            &out.join(format!("shipped_{n}.txt")),
            format!(
                "the {} policy {what} (row {}, int8)",
                slot.role,
                slot.row.letter()
            )
            .as_bytes(),
        );
        write(&out.join(format!("shipped_{n}_commands.bin")), &commands);
    }
    assert!(
        shipped_total + CODE_RESERVE_BYTES <= CODE_REGION_BYTES,
        "the shipped blobs take {shipped_total} bytes: with {CODE_RESERVE_BYTES} bytes for the \
         program they do not fit the {CODE_REGION_BYTES}-byte code region of mps2-an386"
    );

    let case = fixtures::observation_case();
    let obs = ObservationSpec::paper(ObservationLayout::FullOpponent30)
        .observe(
            &case.own,
            &case.gate,
            &case.previous_action,
            Some(&case.opponent),
        )
        .expect("the observation case is valid");
    let bytes: Vec<u8> = obs
        .as_slice()
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    write(&out.join("observation_expected.bin"), &bytes);
}

/// The rotor commands (4 f32 rpm per step) of the host's `Controller` on `blob` over
/// `fixtures::flight`; the opponent is given when the blob's observation has one.
fn controller_commands(blob: &[u8]) -> Result<Vec<u8>, String> {
    let aligned = AlignedBytes::new(blob);
    let observes_opponent = Blob::parse(aligned.as_bytes())
        .map_err(|e| e.to_string())?
        .header()
        .observation
        .layout
        .needs_opponent();
    let mut controller = Controller::from_bytes(aligned.as_bytes(), Track::figure_eight())
        .map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for i in 0..fixtures::FLIGHT_STEPS {
        let (own, opponent) = fixtures::flight(i);
        let opponent = observes_opponent.then_some(&opponent);
        let step = controller.step(&own, opponent);
        if let Some(fault) = step.fault {
            return Err(format!("step {i}: the controller faulted: {fault:?}"));
        }
        for rpm in step.command.rpm {
            out.extend_from_slice(&rpm.to_le_bytes());
        }
    }
    Ok(out)
}

/// The binary golden `golden` (layout above) with its means replaced by the host's int8
/// inference on `blob` over the same observations.
fn int8_expectation(blob: &[u8], golden: &[u8]) -> Result<Vec<u8>, String> {
    let aligned = AlignedBytes::new(blob);
    let blob = Blob::parse(aligned.as_bytes()).map_err(|e| e.to_string())?;
    let policy = blob.policy().map_err(|e| e.to_string())?;
    let word = |at: usize| -> usize {
        u32::from_le_bytes([golden[at], golden[at + 1], golden[at + 2], golden[at + 3]]) as usize
    };
    let (dim, steps) = (word(0), word(4));
    let mut out = golden[..8].to_vec();
    let mut state = policy.initial_state();
    let mut at = 8;
    for _ in 0..steps {
        let obs_bytes = &golden[at..at + 4 * dim];
        let values: Vec<f32> = obs_bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let obs = Observation::from_values(&values).ok_or("observation size")?;
        let mean = policy.act(&obs, &mut state).ok_or("policy.act")?;
        out.extend_from_slice(obs_bytes);
        for m in mean {
            out.extend_from_slice(&f64::from(m).to_le_bytes());
        }
        at += 4 * dim + 4 * 8;
    }
    Ok(out)
}

fn golden_path(dir: &Path, row: TableRow) -> PathBuf {
    dir.join(format!("row_{}.golden", row.letter()))
}

fn write(path: &Path, bytes: &[u8]) {
    // Leave the file (and its mtime) alone when nothing changed.
    if fs::read(path).ok().as_deref() != Some(bytes) {
        fs::write(path, bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    }
}

/// Parses a golden file (format of `tests/src/fixtures.rs`) to the binary layout above.
fn parse_golden(row: TableRow, text: &str) -> Result<Vec<u8>, String> {
    let dim = usize::from(Architecture::table1(row).obs_dim);
    let mut steps: Vec<(Vec<f32>, Vec<f64>)> = Vec::new();
    let mut pending_obs: Option<Vec<f32>> = None;
    let (mut seen_row, mut seen_seed, mut seen_dim) = (false, false, false);
    for (n, line) in text.lines().enumerate() {
        let n = n + 1;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (key, rest) = line.split_once(' ').unwrap_or((line, ""));
        match key {
            "row" => {
                if rest != row.letter().to_string() {
                    return Err(format!("line {n}: row {rest:?}, expected {}", row.letter()));
                }
                seen_row = true;
            }
            "seed" => {
                if rest.parse::<u64>().ok() != Some(golden_seed(row)) {
                    return Err(format!(
                        "line {n}: seed {rest:?}, expected {}",
                        golden_seed(row)
                    ));
                }
                seen_seed = true;
            }
            "dim" => {
                if rest.parse::<usize>().ok() != Some(dim) {
                    return Err(format!("line {n}: dim {rest:?}, expected {dim}"));
                }
                seen_dim = true;
            }
            "obs" => {
                let values = parse_values::<f32>(rest).map_err(|e| format!("line {n}: {e}"))?;
                if values.len() != dim || pending_obs.is_some() {
                    return Err(format!(
                        "line {n}: expected one obs line of {dim} values per mean line"
                    ));
                }
                pending_obs = Some(values);
            }
            "mean" => {
                let values = parse_values::<f64>(rest).map_err(|e| format!("line {n}: {e}"))?;
                let obs = pending_obs
                    .take()
                    .ok_or(format!("line {n}: mean line without obs line"))?;
                if values.len() != 4 {
                    return Err(format!(
                        "line {n}: expected 4 mean values, got {}",
                        values.len()
                    ));
                }
                steps.push((obs, values));
            }
            other => return Err(format!("line {n}: unknown key {other:?}")),
        }
    }
    if !(seen_row && seen_seed && seen_dim) || pending_obs.is_some() || steps.is_empty() {
        return Err("incomplete golden file (needs row, seed, dim and obs/mean pairs)".into());
    }
    let mut out = Vec::new();
    out.extend_from_slice(&(dim as u32).to_le_bytes());
    out.extend_from_slice(&(steps.len() as u32).to_le_bytes());
    for (obs, mean) in &steps {
        obs.iter()
            .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
        mean.iter()
            .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
    }
    Ok(out)
}

fn parse_values<T: std::str::FromStr>(s: &str) -> Result<Vec<T>, String> {
    s.split_whitespace()
        .map(|v| v.parse::<T>().map_err(|_| format!("not a number: {v:?}")))
        .collect()
}
