//! The trainer's way out and back in: every blob the trainer writes gets its header from
//! [`blob_header`] (the Table 1 row's architecture, the observation spec, the paper's action
//! map and 50 Hz period, the provenance), the run's actor becomes a blob ([`actor_blob`]) and
//! RSL-RL safetensors ([`actor_safetensors`]), and a blob becomes an actor again
//! ([`actor_from_blob`], for fine-tuning and refining).

use crate::config::TrainConfig;
use crate::error::{TrainError, io};
use crate::nets::PolicyNet;
use burn::tensor::Device;
use firmware_core::blob::{BlobHeader, EncodeError, Provenance, encode};
use firmware_core::observation::ObservationSpec;
use firmware_core::policy::{Architecture, TableRow};
use std::path::Path;

/// The header of every blob the trainer writes: Table 1 row `row`'s architecture with the
/// paper's action map and 50 Hz control period, observing through `observation`.
pub fn blob_header(
    row: TableRow,
    provenance: Provenance,
    observation: ObservationSpec,
) -> BlobHeader {
    let mut header = BlobHeader::paper(row, provenance);
    header.observation = observation;
    header
}

/// Encodes `weights` (payload order, see `firmware_core::blob`) as a blob of Table 1 row
/// `row` with the paper's observation spec for the row (an imported RSL-RL actor).
pub fn export_blob(
    row: TableRow,
    provenance: Provenance,
    weights: &[f32],
) -> Result<Vec<u8>, EncodeError> {
    let observation = ObservationSpec::paper(row.observation_layout());
    encode(&blob_header(row, provenance, observation), weights)
}

/// The actor as a firmware-core blob with the run's provenance.
pub fn actor_blob<A: PolicyNet>(
    actor: &A,
    config: &TrainConfig,
    iterations: u32,
) -> Result<Vec<u8>, TrainError> {
    payload_blob(&actor.payload(), config, iterations)
}

/// The blob of the weights `payload` (firmware-core order) under the run's header, as
/// [`actor_blob`].
pub fn payload_blob(
    payload: &[f32],
    config: &TrainConfig,
    iterations: u32,
) -> Result<Vec<u8>, TrainError> {
    let row = config.table_row()?;
    let mut name = heapless::String::new();
    name.push_str(&config.run.name)
        .map_err(|_| TrainError::Export("run.name longer than 32 bytes".into()))?;
    let mut preset = heapless::String::new();
    preset
        .push_str(config.env.preset.name())
        .map_err(|_| TrainError::Export("preset name longer than 16 bytes".into()))?;
    let provenance = Provenance {
        name,
        seed: config.run.seed,
        iterations,
        preset,
        config_hash: config.hash(),
    };
    encode(
        &blob_header(row, provenance, config.observation_spec()),
        payload,
    )
    .map_err(|e| TrainError::Export(format!("blob export failed: {e:?}")))
}

/// The actor (weights and σ) as RSL-RL's safetensors, written beside every exported blob.
pub fn actor_safetensors<A: PolicyNet>(
    actor: &A,
    arch: &Architecture,
) -> Result<Vec<u8>, TrainError> {
    crate::rslrl::export_actor(arch, &actor.payload(), Some(&actor.std()))
        .map_err(|e| TrainError::Export(e.to_string()))
}

/// An actor holding the weights of the blob at `path`, which must be a row-A blob with the
/// config's observation spec; σ is the config's `init_std`.
pub fn actor_from_blob<A: PolicyNet>(
    path: &Path,
    arch: &Architecture,
    config: &TrainConfig,
    device: &Device,
) -> Result<A, TrainError> {
    let (header, weights) = read_blob(path, |e| {
        TrainError::Checkpoint(format!("{}: {e}", path.display()))
    })?;
    if header.architecture != *arch {
        return Err(TrainError::Checkpoint(format!(
            "{}: not a row-{} blob",
            path.display(),
            config.run.row
        )));
    }
    if header.observation != config.observation_spec() {
        return Err(TrainError::Checkpoint(format!(
            "{}: its observation spec differs from the config's (env.velocity_scale_mps?)",
            path.display()
        )));
    }
    let std = vec![config.ppo.init_std; usize::from(arch.action_dim)];
    A::from_payload(arch, &weights, &std, device)
        .ok_or_else(|| TrainError::Checkpoint(format!("{}: weights do not fit", path.display())))
}

/// The actor `fresh` with the feed-forward time-trial blob at `path` embedded in it
/// ([`crate::transplant`]): it flies as the blob does, observing through the config's spec,
/// whose own terms (scales, clip, fold) must be the blob's.
pub fn actor_transplanted_from<A: PolicyNet>(
    path: &Path,
    fresh: &A,
    arch: &Architecture,
    config: &TrainConfig,
    device: &Device,
) -> Result<A, TrainError> {
    let refused = |reason: String| TrainError::Blob {
        what: format!("warm_start.teacher_blob '{}'", path.display()),
        reason,
    };
    let (header, weights) = read_blob(path, refused)?;
    crate::transplant::spec_fits(&header.observation, &config.observation_spec())
        .map_err(|e| refused(e.to_string()))?;
    let payload =
        crate::transplant::transplant(&header.architecture, &weights, arch, &fresh.payload())
            .map_err(|e| refused(e.to_string()))?;
    A::from_payload(arch, &payload, &fresh.std(), device)
        .ok_or_else(|| refused("the transplanted weights do not fit".into()))
}

/// The header and the (dequantised) weights of the blob file at `path`; a blob that does
/// not parse is refused through `refused`.
fn read_blob(
    path: &Path,
    refused: impl Fn(String) -> TrainError,
) -> Result<(firmware_core::blob::BlobHeader, Vec<f32>), TrainError> {
    let raw = std::fs::read(path).map_err(io(path))?;
    let bytes = firmware_core::blob::AlignedBytes::new(&raw);
    let blob =
        firmware_core::blob::Blob::parse(bytes.as_bytes()).map_err(|e| refused(e.to_string()))?;
    Ok((blob.header().clone(), blob.dequantized()))
}
