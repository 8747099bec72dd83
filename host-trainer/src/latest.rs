//! A run's latest checkpoint read back for use outside the training loop: as a learner (for
//! diagnostics on a run's networks), as an actor (for checking a resume), or as a blob with
//! the run's provenance (`host-trainer export` of a run that has not finished).

use crate::config::{CriticKind, TrainConfig};
use crate::error::TrainError;
use crate::export::actor_blob;
use crate::model::{Actor, Critic, PrivilegedCritic};
use crate::nets::{PolicyNet, ValueNet};
use crate::ppo::Learner;
use crate::recurrent::{RecurrentActor, RecurrentCritic};
use crate::run_dir::RunDir;
use burn::tensor::Device;
use firmware_core::policy::Architecture;
use std::path::Path;

/// The learner (actor, critic, Adam states, learning rate) of the latest checkpoint in `out`
/// and its iteration (for diagnostics on a run's feed-forward networks with the actor-shaped
/// critic).
pub fn checkpoint_learner(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Learner), TrainError> {
    if config.ppo.critic != CriticKind::ActorShaped {
        return Err(TrainError::Config(
            "checkpoint_learner reads runs whose critic is actor-shaped (ppo.critic)".into(),
        ));
    }
    let arch = config.architecture()?;
    let state = RunDir::new(out).load_checkpoint::<Actor, Critic>(config, &arch, device)?;
    Ok((state.iteration, state.learner))
}

/// The actor of the latest checkpoint in `out` as a blob with the run's provenance (for
/// exporting a run that has not finished), feed-forward or recurrent, and its iteration.
pub fn checkpoint_blob(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Vec<u8>), TrainError> {
    fn latest<A: PolicyNet, C: ValueNet>(
        dir: &RunDir,
        config: &TrainConfig,
        arch: &Architecture,
        device: &Device,
    ) -> Result<(u32, Vec<u8>), TrainError> {
        let s = dir.load_checkpoint::<A, C>(config, arch, device)?;
        Ok((
            s.iteration,
            actor_blob(&s.learner.actor, config, s.iteration)?,
        ))
    }
    let arch = config.architecture()?;
    let dir = RunDir::new(out);
    match (arch.is_recurrent(), config.ppo.critic) {
        (true, CriticKind::ActorShaped) => {
            latest::<RecurrentActor, RecurrentCritic>(&dir, config, &arch, device)
        }
        (true, CriticKind::PrivilegedMlp) => {
            latest::<RecurrentActor, PrivilegedCritic>(&dir, config, &arch, device)
        }
        (false, CriticKind::ActorShaped) => latest::<Actor, Critic>(&dir, config, &arch, device),
        (false, CriticKind::PrivilegedMlp) => {
            latest::<Actor, PrivilegedCritic>(&dir, config, &arch, device)
        }
    }
}

/// The feed-forward actor of the latest checkpoint in `out` (for checking a resume).
pub fn checkpoint_actor(
    config: &TrainConfig,
    out: &Path,
    device: &Device,
) -> Result<(u32, Actor), TrainError> {
    checkpoint_learner(config, out, device).map(|(iteration, learner)| (iteration, learner.actor))
}
