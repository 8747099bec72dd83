//! Export of trained weights as firmware-core blobs.

use firmware_core::blob::{BlobHeader, EncodeError, Provenance, encode};
use firmware_core::policy::TableRow;

/// Encodes `weights` (payload order, see `firmware_core::blob`) as a blob of Table 1 row
/// `row` with the paper's observation scales, action map and 50 Hz control period.
pub fn export_blob(
    row: TableRow,
    provenance: Provenance,
    weights: &[f32],
) -> Result<Vec<u8>, EncodeError> {
    encode(&BlobHeader::paper(row, provenance), weights)
}
