//! Which policies the STM32F405 image holds: the stage-1 (time-trial) policy and the stage-2
//! (race) policy that `sitl race` flies. Compiled into the image's build script, into
//! `tools/cortex-m-tests`' build script (its QEMU tests and instruction counts run the same
//! blobs) and, through `#[path]`, into `tools size-report`, so all of them pick the same
//! blobs. The candidates follow `sitl::shipped` (a test in `tools` keeps the picks equal).

use std::path::Path;

use firmware_core::blob::EncodeError;
use firmware_core::policy::TableRow;
use firmware_core::synthetic;

/// One policy slot of the image.
#[derive(Clone, Copy, Debug)]
pub struct ImagePolicy {
    /// What the slot flies, for messages ("stage 1", "stage 2").
    pub role: &'static str,
    /// Its Table 1 row: the synthetic fallback's architecture.
    pub row: TableRow,
    /// The blobs it holds, in order of preference (paths from the repository root).
    pub candidates: &'static [&'static str],
}

/// The time-trial policy: `sitl race`'s opponent (`sitl::shipped::OPPONENTS`).
pub const STAGE1: ImagePolicy = ImagePolicy {
    role: "stage 1",
    row: TableRow::A,
    candidates: &["policies/stage1.blob", "policies/stage1_guarded.blob"],
};

/// The race policy: `sitl race`'s ego (the row-G entries of `sitl::shipped::RACE_EGOS`).
pub const STAGE2: ImagePolicy = ImagePolicy {
    role: "stage 2",
    row: TableRow::G,
    candidates: &[
        "policies/stage2.blob",
        "policies/stage2_transplant.blob",
        "policies/stage2_G.blob",
    ],
};

/// Both slots, in the order the image holds them (the build scripts write slot `n` as
/// `stage{n}.bin`, `shipped_{n}.bin`, from 1).
pub const IMAGE_POLICIES: [ImagePolicy; 2] = [STAGE1, STAGE2];

/// The f32 blob `slot` is made from, and what it is: the first of its candidates under
/// `root` that exists, or its row's synthetic weights (an int8 blob's length depends only on
/// the architecture and a few header bytes, so the sizes stay right in a checkout without
/// the shipped blobs).
pub fn source_blob(root: &Path, slot: &ImagePolicy) -> Result<(String, Vec<u8>), EncodeError> {
    if let Some(found) = slot
        .candidates
        .iter()
        .find_map(|p| std::fs::read(root.join(p)).ok().map(|b| (p.to_string(), b)))
    {
        return Ok(found);
    }
    let bytes = synthetic::blob(slot.row, synthetic::golden_seed(slot.row))?;
    Ok((
        format!(
            "row {}'s synthetic weights (no shipped {} blob)",
            slot.row.letter(),
            slot.role
        ),
        bytes,
    ))
}
