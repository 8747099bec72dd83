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

/// Values a privileged critic sees beyond the ego's observation
/// ([`super::VecEnv::privileged_observations`]).
pub const PRIVILEGED_EXTRA: usize = 6;

/// The privileged state of `slot` for a value function that trains beside the policy and is
/// never deployed: the ego's observation of its true state (no sensor noise), then the
/// episode's draws and its clock (see [`super::VecEnv::privileged_observations`]).
pub(super) fn privileged(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &Slot,
    max_steps: u32,
    out: &mut [f32],
) {
    let (obs, extra) = out.split_at_mut(out.len() - PRIVILEGED_EXTRA);
    match ego_observation(world, spec, fold, slot, slot.opponent.is_some()) {
        Ok((o, _)) => obs.copy_from_slice(o.as_slice()),
        Err(_) => obs.fill(0.0),
    }
    let nominal = &world.preset;
    let (ego, latency) = match &slot.perturbed {
        Some(p) => (&p.ego_preset, p.latency_steps),
        None => (nominal, 0),
    };
    let ratio = |a: f32, b: f32| if b > 0.0 { a / b - 1.0 } else { 0.0 };
    let left = 1.0 - slot.steps as f32 / max_steps.max(1) as f32;
    extra.copy_from_slice(&[
        ratio(ego.thrust_scale, nominal.thrust_scale),
        ratio(ego.mass_kg, nominal.mass_kg),
        ratio(ego.inertia_kgm2[0], nominal.inertia_kgm2[0]),
        // 10 ms → 1.
        ego.motor_time_constant_s * 100.0,
        latency as f32,
        left.clamp(0.0, 1.0),
    ]);
}
