//! `size-report`: flash and RAM of the Cortex-M4 size images, read from their ELF files,
//! against an STM32F405: `size-a`, `size-g` of `tools/cortex-m-tests` (one f32 blob each and
//! a minimal program that steps the controller) and `tools/stm32f405-fit` (the shipped
//! stage-1 and stage-2 policies in int8, one controller each, linked against the F405's own
//! memory map: that it links at all is the fit check).
//!
//! Measured (from the ELF's section headers): flash = every allocated section with contents
//! (`.vector_table`, `.text`, `.rodata`, the load image of `.data`); static RAM = every
//! allocated section in RAM (`.data`, `.bss`, `.uninit`). cortex-m-rt reserves no stack
//! section: the stack grows down from the top of RAM. Computed (from symbols the image
//! exports, evaluated for the target): the RAM one controller step needs, that is
//! `size_of::<Controller>()` plus the activations its step keeps on the stack
//! (`SCRATCH_BYTES` of the policy). The stack high-water mark of a real step, measured
//! under QEMU, is printed by `cortex-m icount`.

use std::fmt::Write as _;
use std::path::Path;
use std::process::ExitCode;

use firmware_core::blob::{WeightDtype, convert_bytes};
use firmware_core::policy::TableRow;
use firmware_core::synthetic;
use object::{Object, ObjectSection, ObjectSymbol, SectionFlags, SectionKind};

use crate::cortex_m::{PACKAGE, build_bins, workspace_root};
use crate::{Error, Result};

/// STM32F405 flash (bytes): 1 MB.
pub const F405_FLASH_BYTES: u64 = 1_048_576;
/// STM32F405 RAM (bytes): 192 KB, of which 64 KB core-coupled (CCM, CPU only).
pub const F405_RAM_BYTES: u64 = 192 * 1024;
/// STM32F405 main SRAM (SRAM1 + SRAM2, bytes): 128 KB.
pub const F405_SRAM_BYTES: u64 = 128 * 1024;

/// Start of RAM in the images' memory map (memory.x).
pub const RAM_ORIGIN: u64 = 0x2000_0000;
/// Size of RAM in the images' memory map.
pub const RAM_LENGTH: u64 = 4 * 1024 * 1024;

/// The profile the images are built with.
pub const PROFILE: &str = "firmware";

/// One allocated section.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Section {
    /// Its name.
    pub name: String,
    /// Its size (bytes).
    pub size: u64,
    /// Its run-time address.
    pub address: u64,
    /// True when it has contents in the file (not NOBITS).
    pub has_contents: bool,
}

/// What an image's ELF says.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageSizes {
    /// The allocated sections.
    pub sections: Vec<Section>,
    /// Flash: allocated sections with contents.
    pub flash: u64,
    /// Static RAM: allocated sections in RAM.
    pub ram: u64,
    /// `OVERTAKE_CONTROLLER_BYTES`, when the image exports it.
    pub controller_bytes: Option<u32>,
    /// `OVERTAKE_SCRATCH_A_BYTES`.
    pub scratch_a_bytes: Option<u32>,
    /// `OVERTAKE_SCRATCH_G_BYTES`.
    pub scratch_g_bytes: Option<u32>,
    /// `OVERTAKE_CONTROLLER_COUNT` (controllers the image holds), when it exports it; one
    /// otherwise.
    pub controller_count: Option<u32>,
}

/// Reads the sizes of the ELF at `path`.
pub fn read_elf(path: &Path) -> Result<ImageSizes> {
    let data = std::fs::read(path).map_err(|e| Error::new(format!("{}: {e}", path.display())))?;
    let file = object::File::parse(&*data)
        .map_err(|e| Error::new(format!("{}: not an ELF file: {e}", path.display())))?;
    let mut sections = Vec::new();
    for s in file.sections() {
        let SectionFlags::Elf { sh_flags, .. } = s.flags() else {
            continue;
        };
        if !sh_flags.contains(object::elf::SHF_ALLOC) || s.size() == 0 {
            continue;
        }
        sections.push(Section {
            name: s.name().unwrap_or("?").to_string(),
            size: s.size(),
            address: s.address(),
            has_contents: s.kind() != SectionKind::UninitializedData,
        });
    }
    let flash = sections
        .iter()
        .filter(|s| s.has_contents)
        .map(|s| s.size)
        .sum();
    let ram = sections
        .iter()
        .filter(|s| (RAM_ORIGIN..RAM_ORIGIN + RAM_LENGTH).contains(&s.address))
        .map(|s| s.size)
        .sum();
    let symbol_u32 = |name: &str| -> Option<u32> {
        let sym = file.symbols().find(|s| s.name() == Ok(name))?;
        let section = file.section_by_index(sym.section_index()?).ok()?;
        let bytes = section.data_range(sym.address(), 4).ok()??;
        Some(u32::from_le_bytes(bytes.try_into().ok()?))
    };
    Ok(ImageSizes {
        sections,
        flash,
        ram,
        controller_bytes: symbol_u32("OVERTAKE_CONTROLLER_BYTES"),
        scratch_a_bytes: symbol_u32("OVERTAKE_SCRATCH_A_BYTES"),
        scratch_g_bytes: symbol_u32("OVERTAKE_SCRATCH_G_BYTES"),
        controller_count: symbol_u32("OVERTAKE_CONTROLLER_COUNT"),
    })
}

/// The package of the STM32F405 fit image.
pub const F405_PACKAGE: &str = "stm32f405-fit";

/// One row of the report.
#[derive(Clone, Debug)]
pub struct Row {
    /// The image (its bin name).
    pub image: String,
    /// Table 1 rows of the blobs it holds (one controller each).
    pub rows: Vec<TableRow>,
    /// How the blob stores its weights.
    pub dtype: WeightDtype,
    /// Bytes of the embedded blobs (regenerated here exactly as build.rs does).
    pub blob_bytes: u64,
    /// The ELF's sizes.
    pub sizes: ImageSizes,
}

impl Row {
    /// Computed RAM of one step: every controller the image holds plus the activations of
    /// the largest step (one step runs at a time).
    pub fn step_ram(&self) -> Option<u64> {
        let mut scratch = 0;
        for row in &self.rows {
            scratch = scratch.max(match row {
                TableRow::A => self.sizes.scratch_a_bytes?,
                _ => self.sizes.scratch_g_bytes?,
            });
        }
        let controllers = u64::from(self.sizes.controller_count.unwrap_or(1));
        Some(controllers * u64::from(self.sizes.controller_bytes?) + u64::from(scratch))
    }

    /// The rows it holds, e.g. "A" or "A+G".
    pub fn letters(&self) -> String {
        let letters: Vec<String> = self.rows.iter().map(|r| r.letter().to_string()).collect();
        letters.join("+")
    }
}

/// The report text for `rows`.
pub fn report(rows: &[Row]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Cortex-M4F size images (thumbv7em-none-eabihf, profile `{PROFILE}`: opt-level 3, fat LTO, 1 codegen unit, panic abort)"
    );
    let _ = writeln!(
        s,
        "each: cortex-m-rt, firmware-core's Controller (code for every Table 1 architecture and both dtypes: the blob picks at run time), one blob\n"
    );
    let _ = writeln!(
        s,
        "{:<14} {:>5} {:>10} {:>12} {:>12} {:>14} {:>14} {:>14}",
        "image", "dtype", "blob", "flash", "code+data", "static RAM", "step RAM*", "RAM total"
    );
    for r in rows {
        let step = r.step_ram();
        let _ = writeln!(
            s,
            "{:<14} {:>5} {:>10} {:>12} {:>12} {:>14} {:>14} {:>14}",
            r.image,
            r.dtype.name(),
            r.blob_bytes,
            r.sizes.flash,
            r.sizes.flash.saturating_sub(r.blob_bytes),
            r.sizes.ram,
            step.map_or("?".into(), |v| v.to_string()),
            step.map_or("?".into(), |v| (v + r.sizes.ram).to_string()),
        );
    }
    let _ = writeln!(
        s,
        "\nbytes. Measured from the ELF: flash = allocated sections with contents (.vector_table, .text, .rodata, .data load image);"
    );
    let _ = writeln!(
        s,
        "code+data = flash minus the blob; static RAM = .data + .bss + .uninit (cortex-m-rt reserves no stack section)."
    );
    let _ = writeln!(
        s,
        "* computed, not measured: size_of::<Controller>() on the target per controller held + the largest step's activations (SCRATCH_BYTES) + the frame allowance (STEP_FRAME_ALLOWANCE_BYTES)."
    );
    let _ = writeln!(
        s,
        "  The measured stack high-water mark of one step is printed by `cargo run -p tools -- cortex-m icount`.\n"
    );
    let _ = writeln!(s, "sections:");
    for r in rows {
        let list: Vec<String> = r
            .sizes
            .sections
            .iter()
            .map(|x| format!("{} {}", x.name, x.size))
            .collect();
        let _ = writeln!(s, "  {}: {}", r.image, list.join(", "));
    }
    let _ = writeln!(
        s,
        "\nSTM32F405: {F405_FLASH_BYTES} bytes flash, {F405_RAM_BYTES} bytes RAM ({F405_SRAM_BYTES} SRAM + 65536 CCM)."
    );
    for r in rows {
        let _ = writeln!(s, "{}", verdict(r));
    }
    s
}

/// The plain-sentence verdict for one image.
pub fn verdict(r: &Row) -> String {
    let name = format!("Row {} {} ({})", r.letters(), r.dtype.name(), r.image);
    let ram = r.sizes.ram + r.step_ram().unwrap_or(0);
    let flash = if r.sizes.flash <= F405_FLASH_BYTES {
        format!(
            "fits the STM32F405's flash ({} of {F405_FLASH_BYTES} bytes, {:.1} %)",
            r.sizes.flash,
            100.0 * r.sizes.flash as f64 / F405_FLASH_BYTES as f64
        )
    } else {
        format!(
            "does NOT fit the STM32F405's flash: {} bytes > {F405_FLASH_BYTES} (over by {} bytes; the {} blob alone is {} bytes)",
            r.sizes.flash,
            r.sizes.flash - F405_FLASH_BYTES,
            r.dtype.name(),
            r.blob_bytes
        )
    };
    let ram = if ram <= F405_SRAM_BYTES {
        format!(
            "its RAM ({ram} bytes with its controllers and one step's activations) fits the 128 KB main SRAM"
        )
    } else {
        format!("its RAM ({ram} bytes) does NOT fit the 128 KB main SRAM")
    };
    format!("{name} {flash}; {ram}.")
}

#[path = "../stm32f405-fit/policy_source.rs"]
mod policy_source;

/// One policy of the F405 image, made as its build script makes it (the same
/// `policy_source` picks the blob), in int8.
#[derive(Clone, Debug)]
pub struct F405Policy {
    /// "stage 1" or "stage 2".
    pub role: &'static str,
    /// Its Table 1 row.
    pub row: TableRow,
    /// What it is: the shipped path, or the synthetic fallback.
    pub what: String,
    /// The int8 blob.
    pub bytes: Vec<u8>,
}

/// The F405 image's policies, in the order it holds them.
pub fn f405_policies() -> Result<Vec<F405Policy>> {
    let root = workspace_root();
    policy_source::IMAGE_POLICIES
        .iter()
        .map(|slot| {
            let (what, source) = policy_source::source_blob(&root, slot).map_err(|e| {
                Error::new(format!("encoding the synthetic {} blob: {e}", slot.role))
            })?;
            let bytes = convert_bytes(&source, WeightDtype::I8)
                .map_err(|e| Error::new(format!("{what}: {e}")))?;
            Ok(F405Policy {
                role: slot.role,
                row: slot.row,
                what,
                bytes,
            })
        })
        .collect()
}

/// Builds the size images, reads them and prints the report.
pub fn run() -> Result<ExitCode> {
    let built = build_bins(PACKAGE, PROFILE, &["size-a", "size-g"])?;
    let mut rows = Vec::new();
    for (bin, path) in &built {
        let row = if bin == "size-a" {
            TableRow::A
        } else {
            TableRow::G
        };
        let blob = synthetic::blob(row, synthetic::golden_seed(row))
            .map_err(|e| Error::new(format!("encoding blob {}: {e}", row.letter())))?;
        rows.push(Row {
            image: bin.clone(),
            rows: vec![row],
            dtype: WeightDtype::F32,
            blob_bytes: blob.len() as u64,
            sizes: read_elf(path)?,
        });
    }
    rows.sort_by_key(Row::letters);
    let policies = f405_policies()?;
    for (bin, path) in build_bins(F405_PACKAGE, PROFILE, &[F405_PACKAGE])? {
        rows.push(Row {
            image: bin,
            rows: policies.iter().map(|p| p.row).collect(),
            dtype: WeightDtype::I8,
            blob_bytes: policies.iter().map(|p| p.bytes.len() as u64).sum(),
            sizes: read_elf(&path)?,
        });
    }
    print!("{}", report(&rows));
    let held: Vec<String> = policies
        .iter()
        .map(|p| {
            format!(
                "the {} policy {} (row {}, int8, {} bytes)",
                p.role,
                p.what,
                p.row.letter(),
                p.bytes.len()
            )
        })
        .collect();
    println!(
        "{F405_PACKAGE} holds {} and is linked against the STM32F405's memory map (tools/stm32f405-fit/memory.x): it linked, so it fits.",
        held.join(" and ")
    );
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(row: TableRow, flash: u64, ram: u64) -> Row {
        Row {
            image: "size-x".into(),
            rows: vec![row],
            dtype: WeightDtype::F32,
            blob_bytes: 1000,
            sizes: ImageSizes {
                sections: vec![],
                flash,
                ram,
                controller_bytes: Some(2000),
                scratch_a_bytes: Some(1040),
                scratch_g_bytes: Some(4880),
                controller_count: None,
            },
        }
    }

    #[test]
    fn verdicts_say_whether_it_fits() {
        assert!(verdict(&row(TableRow::A, 200_000, 0)).contains("fits the STM32F405's flash"));
        let g = verdict(&row(TableRow::G, 1_300_000, 0));
        assert!(g.contains("does NOT fit the STM32F405's flash"), "{g}");
        assert!(g.contains("over by 251424 bytes"), "{g}");
        assert_eq!(row(TableRow::G, 1, 0).step_ram(), Some(6880));
        assert_eq!(row(TableRow::A, 1, 0).step_ram(), Some(3040));
        // Two controllers, one step at a time: 2 × 2000 + the larger scratch.
        let mut both = row(TableRow::A, 1, 0);
        both.rows.push(TableRow::G);
        both.sizes.controller_count = Some(2);
        assert_eq!(both.step_ram(), Some(8880));
        assert!(
            verdict(&both).starts_with("Row A+G f32"),
            "{}",
            verdict(&both)
        );
    }

    /// The F405 image holds what `sitl race` flies: its stage-2 policy is the race's default
    /// ego and its stage-1 policy the race's default opponent.
    #[test]
    fn the_f405_image_holds_the_policies_sitl_race_flies() {
        let root = workspace_root();
        let file_of = |slot: &policy_source::ImagePolicy| {
            slot.candidates
                .iter()
                .map(|p| root.join(p))
                .find(|p| p.is_file())
                .and_then(|p| p.file_name().map(|n| n.to_owned()))
        };
        let name = |p: std::path::PathBuf| p.file_name().map(|n| n.to_owned());
        let race_ego = sitl::shipped::find(&sitl::shipped::RACE_EGOS).and_then(name);
        let race_opponent = sitl::shipped::find(&sitl::shipped::OPPONENTS).and_then(name);
        assert_eq!(file_of(&policy_source::STAGE2), race_ego);
        assert_eq!(file_of(&policy_source::STAGE1), race_opponent);
        let policies = f405_policies().expect("the image's policies");
        assert_eq!(policies.len(), 2);
        assert!(
            policies.iter().all(|p| p.what.starts_with("policies/")),
            "{policies:?}"
        );
    }

    #[test]
    fn reads_an_elf_file() {
        // The test binary itself is an ELF on Linux hosts: it has allocated sections.
        let exe = std::env::current_exe().expect("current exe");
        if let Ok(sizes) = read_elf(&exe) {
            assert!(sizes.flash > 0);
            assert!(sizes.sections.iter().any(|s| s.name == ".text"));
        }
    }
}
