//! Which row-G policy the STM32F405 image holds. Compiled into the image's build script and,
//! through `#[path]`, into `tools size-report`, so both pick the same blob.

use std::path::Path;

use firmware_core::blob::EncodeError;
use firmware_core::policy::TableRow;
use firmware_core::synthetic;

/// The row-G blobs the image holds, in order of preference: the stage-2 policy, then the
/// first warm-start stage of row G (paths from the repository root).
pub const SHIPPED_G: [&str; 2] = ["policies/stage2.blob", "policies/stage2_G_student.blob"];

/// The f32 blob the image is made from, and what it is: the first of [`SHIPPED_G`] under
/// `root` that exists, or row G's synthetic weights (an int8 G blob's length depends only on
/// the architecture and a few header bytes).
pub fn source_blob(root: &Path) -> Result<(String, Vec<u8>), EncodeError> {
    if let Some(found) = SHIPPED_G
        .iter()
        .find_map(|p| std::fs::read(root.join(p)).ok().map(|b| (p.to_string(), b)))
    {
        return Ok(found);
    }
    let bytes = synthetic::blob(TableRow::G, synthetic::golden_seed(TableRow::G))?;
    Ok((
        "row G's synthetic weights (no shipped row-G blob)".to_string(),
        bytes,
    ))
}
