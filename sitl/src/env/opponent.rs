//! The stage-2 opponent: its blob read from disk (with a size limit), kept for the process's
//! life, and the frozen controller every env's slot clones.

use super::reward::Competition;
use super::{EnvError, RaceConfig};
use firmware_core::Controller;
use firmware_core::blob::AlignedBytes;
use firmware_core::track::Track;

/// The largest blob an environment reads (bytes): firmware-core's limit
/// ([`firmware_core::blob::MAX_BLOB_BYTES`]), so a wrong path (`/dev/zero`) is refused
/// instead of read without end.
pub const MAX_BLOB_BYTES: u64 = firmware_core::blob::MAX_BLOB_BYTES as u64;

/// The bytes of the blob at `path`, at most [`MAX_BLOB_BYTES`].
pub fn read_blob(path: &std::path::Path) -> Result<AlignedBytes, EnvError> {
    use std::io::Read;
    let refused = |kind: std::io::ErrorKind, message: String| EnvError::ReadOpponent {
        path: path.to_path_buf(),
        kind,
        message,
    };
    let file = std::fs::File::open(path).map_err(|e| refused(e.kind(), e.to_string()))?;
    let mut raw = Vec::new();
    file.take(MAX_BLOB_BYTES + 1)
        .read_to_end(&mut raw)
        .map_err(|e| refused(e.kind(), e.to_string()))?;
    if raw.len() as u64 > MAX_BLOB_BYTES {
        return Err(refused(
            std::io::ErrorKind::InvalidData,
            format!("larger than {MAX_BLOB_BYTES} bytes: not a blob"),
        ));
    }
    Ok(AlignedBytes::new(&raw))
}

/// `bytes` for the rest of the process, one copy per distinct blob: the opponent's
/// [`Controller`] views its blob's weights in place (as in flash), so every env's controller
/// borrows one copy that must outlive the environments, which are rebuilt during a run.
pub fn interned(bytes: &AlignedBytes) -> &'static AlignedBytes {
    static BLOBS: std::sync::Mutex<Vec<&'static AlignedBytes>> = std::sync::Mutex::new(Vec::new());
    let mut blobs = BLOBS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(b) = blobs.iter().find(|b| **b == bytes) {
        return b;
    }
    let b: &'static AlignedBytes = Box::leak(Box::new(bytes.clone()));
    blobs.push(b);
    b
}

/// The built race: one controller template, cloned into every slot.
#[derive(Clone, Debug)]
pub(super) struct Race {
    pub(super) opponent: Controller<'static>,
    pub(super) competition: Competition,
    pub(super) weight: f32,
}

impl Race {
    /// The race `r` describes: its opponent's blob read, validated and loaded into a
    /// controller; a blob that cannot be read, does not validate, or whose policy would
    /// need to see an opponent itself, is refused.
    pub(super) fn load(r: &RaceConfig) -> Result<Self, EnvError> {
        let bytes = read_blob(&r.opponent)?;
        let unflyable = |e: &dyn core::fmt::Display| {
            EnvError::Unflyable(format!("opponent '{}': {e}", r.opponent.display()))
        };
        let blob = firmware_core::blob::Blob::parse(interned(&bytes).as_bytes())
            .map_err(|e| unflyable(&e))?;
        // At the world's period, as every pilot (`pilot::world_rate_controller`), from the
        // blob already parsed.
        let opponent = Controller::new(
            &blob,
            Track::figure_eight(),
            crate::world::CONTROL_PERIOD_NS,
        )
        .map_err(|e| unflyable(&e))?;
        if blob.header().observation.layout.needs_opponent() {
            return Err(unflyable(
                &"the opponent's policy observes an opponent itself; stage 2 races a time-trial (17-value) policy",
            ));
        }
        Ok(Self {
            opponent,
            competition: r.competition,
            weight: r.competition_weight,
        })
    }
}
