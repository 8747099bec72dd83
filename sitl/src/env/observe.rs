//! The ego's observation of an env slot: through the fold of the mirrored track half, the
//! ego's sensor noise when randomised, and the opponent in a race.

use super::Slot;
use crate::world::{Drone, World};
use firmware_core::mirror::{TrackMirror, observe_folded};
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::{Observation, ObservationError, ObservationSpec};
use firmware_core::vehicle::VehicleState;

/// The ego's observation of its slot, folded by `fold` (the env's, when its spec is
/// folded), through its sensor noise when randomised; zeros when the pipeline refuses the
/// state.
pub(super) fn observe(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &mut Slot,
    out: &mut [f32],
) {
    let own = slot.drones[0].body.state;
    let own = match &mut slot.perturbed {
        Some(p) => p.sense(own),
        None => own,
    };
    match ego_observation_of(world, spec, fold, slot, &own, slot.opponent.is_some()) {
        Ok((o, _)) => out.copy_from_slice(o.as_slice()),
        // Only a diverged state fails, and a diverged state is a crash that was respawned.
        Err(_) => out.fill(0.0),
    }
}

/// The ego's observation in `slot` through `fold` (and whether it is the mirror image), with
/// the opponent in it when `racing`.
pub(super) fn ego_observation(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &Slot,
    racing: bool,
) -> Result<(Observation, bool), ObservationError> {
    ego_observation_of(world, spec, fold, slot, &slot.drones[0].body.state, racing)
}

/// [`ego_observation`] with the ego's state as `own` (its sensors' reading of it).
fn ego_observation_of(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &Slot,
    own: &VehicleState,
    racing: bool,
) -> Result<(Observation, bool), ObservationError> {
    let [d, opp] = &slot.drones;
    observe_folded(
        spec,
        fold,
        &world.track,
        own,
        d.progress.target,
        &slot.previous_action,
        racing.then_some(&opp.body.state),
    )
}

/// The ego's observation (`drones[0]`, after `previous_action`), with `drones[1]` as the
/// opponent when `racing`; zeros when the pipeline refuses the state.
pub(super) fn observe_drones(
    world: &World,
    spec: &ObservationSpec,
    drones: &[Drone; 2],
    previous_action: &[f32; ACTION_DIM],
    racing: bool,
    out: &mut [f32],
) {
    let [d, opp] = drones;
    let gate = world.track.gate(d.progress.target);
    let opponent = racing.then_some(&opp.body.state);
    match spec.observe(&d.body.state, &gate, previous_action, opponent) {
        Ok(o) => out.copy_from_slice(o.as_slice()),
        // Only a diverged state fails, and a diverged state is a crash that was respawned.
        Err(_) => out.fill(0.0),
    }
}
