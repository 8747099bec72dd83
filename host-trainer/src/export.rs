//! Export of trained weights as firmware-core blobs.

use firmware_core::PAPER_CONTROL_PERIOD_NS;
use firmware_core::blob::{BlobHeader, EncodeError, Provenance, WeightDtype, encode};
use firmware_core::observation::{ObservationLayout, ObservationSpec};
use firmware_core::policy::{Architecture, TableRow};
use firmware_core::vehicle::ActionMap;

/// A blob header for a Table 1 row with the paper's observation scales, action map and 50 Hz
/// control period.
pub fn paper_header(row: TableRow, provenance: Provenance) -> BlobHeader {
    let architecture = Architecture::table1(row);
    let layout = match ObservationLayout::from_dim(usize::from(architecture.obs_dim)) {
        Some(layout) => layout,
        None => ObservationLayout::FullOpponent30,
    };
    BlobHeader {
        architecture,
        observation: ObservationSpec::paper(layout),
        action_map: ActionMap::PAPER,
        control_period_ns: PAPER_CONTROL_PERIOD_NS,
        dtype: WeightDtype::F32,
        provenance,
        payload_len: 0,
    }
}

/// Encodes `weights` (payload order) as a blob of row `row`.
pub fn export_blob(
    row: TableRow,
    provenance: Provenance,
    weights: &[f32],
) -> Result<Vec<u8>, EncodeError> {
    encode(&paper_header(row, provenance), weights)
}
