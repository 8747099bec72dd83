//! The deployed controller: a blob's policy, its recurrent state, the previous action and the
//! target gate, stepped once per control period.
//!
//! A step reads in order: 10 validate the inputs (a NaN or infinity gives the fail-safe),
//! 20 advance the target gate with the segment test, 30 observe (through the track's mirror
//! on its mirrored half when the blob's pipeline is folded, [`crate::mirror`]), 40 infer,
//! 50 clip the Gaussian mean to [-1, 1] (and renumber it back to the world's motors after a
//! folded observation), 60 map to rpm (paper eq. 3).

use crate::blob::{Blob, BlobError};
use crate::math::Vec3;
use crate::mirror::{MirrorError, TrackMirror, observe_folded, unfold_action};
use crate::nn::{ACTION_DIM, LANES};
use crate::observation::{MAX_OBSERVATION_DIM, Observation, ObservationError, ObservationSpec};
use crate::policy::{Policy, PolicyState};
use crate::track::{GateEvent, GateProgress, Track};
use crate::vehicle::{ActionMap, MotorCommand, VehicleState};
use serde::{Deserialize, Serialize};

/// A step begun by `Controller::begin_step`: the observation to infer on, and what
/// `finish_step` needs besides the policy's output.
#[derive(Clone, Copy, Debug)]
struct PendingStep {
    obs: Observation,
    folded: bool,
    gate_event: GateEvent,
}

/// Why a controller cannot be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum ControllerError {
    /// The blob is defective.
    Blob(BlobError),
    /// A recurrent policy would run at another rate than it was trained at.
    RateMismatch {
        /// Control period recorded in the blob (ns).
        trained_ns: u32,
        /// Control period requested (ns).
        requested_ns: u32,
    },
    /// The blob's pipeline is folded by a mirror symmetry the track does not have.
    NoMirror(MirrorError),
}

impl From<BlobError> for ControllerError {
    fn from(e: BlobError) -> Self {
        Self::Blob(e)
    }
}

impl core::fmt::Display for ControllerError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Blob(e) => e.fmt(f),
            Self::RateMismatch {
                trained_ns,
                requested_ns,
            } => write!(
                f,
                "recurrent policy trained at a {trained_ns} ns control period cannot run at {requested_ns} ns"
            ),
            Self::NoMirror(e) => write!(
                f,
                "the blob's observations are folded, but the track has {e}"
            ),
        }
    }
}

/// A step that could not run the policy; the controller commanded the fail-safe instead.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum StepFault {
    /// The own state has a NaN or infinite value.
    NonFiniteState,
    /// The opponent state has a NaN or infinite value.
    NonFiniteOpponent,
    /// The policy observes an opponent and none was given.
    MissingOpponent,
    /// The policy produced a NaN or infinite action.
    NonFiniteAction,
}

impl core::fmt::Display for StepFault {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NonFiniteState => "own state not finite",
            Self::NonFiniteOpponent => "opponent state not finite",
            Self::MissingOpponent => "opponent state missing",
            Self::NonFiniteAction => "policy output not finite",
        })
    }
}

/// The result of one control step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepOutput {
    /// The propeller speeds to command ([`MotorCommand::STOP`] on a fault).
    pub command: MotorCommand,
    /// The clipped action behind `command` (zeros on a fault).
    pub action: [f32; ACTION_DIM],
    /// Set when the step fell back to the fail-safe.
    pub fault: Option<StepFault>,
    /// The gate event detected at the start of this step.
    pub gate_event: GateEvent,
}

/// A learned racing controller running a blob's policy.
///
/// The fail-safe is [`MotorCommand::STOP`] (all motors off, as a flight controller disarms).
/// On an input fault the recurrent state, previous action and target gate are left as they
/// were; a non-finite policy output (possible only with weights near `f32::MAX`) also zeroes
/// the recurrent state. [`Controller::fault_count`] counts the events.
#[derive(Clone, Debug)]
pub struct Controller<'w> {
    policy: Policy<'w>,
    state: PolicyState,
    observation: ObservationSpec,
    action_map: ActionMap,
    control_period_ns: u32,
    track: Track<'w>,
    /// The track's mirror, when the blob's pipeline is folded.
    fold: Option<TrackMirror>,
    progress: GateProgress,
    previous_action: [f32; ACTION_DIM],
    previous_position: Option<Vec3>,
    fault_count: u32,
}

/// Stack a step uses beyond the activations [`crate::policy::PolicyG::SCRATCH_BYTES`] models:
/// call frames, spills, the observation. Measured on the Cortex-M4: a G step's stack
/// high-water mark is 3,440 B in f32 and 4,024 B in int8 (the int8 kernel's frame nests in
/// the head's) against 2,832 B of modelled activations, so 608 B and 1,192 B; budgeted at
/// 1.5 KB, and the Cortex-M test image checks both measured marks against the model.
pub const STEP_FRAME_ALLOWANCE_BYTES: usize = 1536;

/// The modelled stack of one row-A step (bytes): its MLP's activations plus
/// [`STEP_FRAME_ALLOWANCE_BYTES`]. The Cortex-M images export it for `tools size-report`.
pub const STEP_STACK_A_BYTES: usize =
    <crate::nn::Mlp2<'static, 17, 128, 128> as crate::nn::Head<'static, 17>>::SCRATCH_BYTES
        + STEP_FRAME_ALLOWANCE_BYTES;

/// The modelled stack of one row-G step (bytes): [`crate::policy::PolicyG::SCRATCH_BYTES`]
/// plus [`STEP_FRAME_ALLOWANCE_BYTES`].
pub const STEP_STACK_G_BYTES: usize =
    crate::policy::PolicyG::SCRATCH_BYTES + STEP_FRAME_ALLOWANCE_BYTES;

/// RAM of a row-G controller (bytes): the controller itself (recurrent state, weight views,
/// bookkeeping) plus the stack one step uses (its activations and frames).
pub const CONTROLLER_G_RAM_BYTES: usize =
    core::mem::size_of::<Controller<'static>>() + STEP_STACK_G_BYTES;

// The recurrent controller's RAM budget: state plus scratch <= 8 KB.
const _: () = assert!(CONTROLLER_G_RAM_BYTES <= 8 * 1024);

impl<'w> Controller<'w> {
    /// A controller for `blob` on `track`, stepped every `control_period_ns`. A recurrent
    /// policy refuses any period but the one it was trained at.
    pub fn new(
        blob: &Blob<'w>,
        track: Track<'w>,
        control_period_ns: u32,
    ) -> Result<Self, ControllerError> {
        let header = blob.header();
        let policy = blob.policy()?;
        if policy.is_recurrent() && control_period_ns != header.control_period_ns {
            return Err(ControllerError::RateMismatch {
                trained_ns: header.control_period_ns,
                requested_ns: control_period_ns,
            });
        }
        let fold = if header.observation.is_folded() {
            Some(TrackMirror::of_track(&track).map_err(ControllerError::NoMirror)?)
        } else {
            None
        };
        Ok(Self {
            policy,
            state: policy.initial_state(),
            observation: header.observation,
            action_map: header.action_map,
            control_period_ns,
            track,
            fold,
            progress: GateProgress::targeting(0),
            previous_action: [0.0; ACTION_DIM],
            previous_position: None,
            fault_count: 0,
        })
    }

    /// Parses `bytes` as a blob and builds a controller at the blob's own control period.
    pub fn from_bytes(bytes: &'w [u8], track: Track<'w>) -> Result<Self, ControllerError> {
        let blob = Blob::parse(bytes)?;
        Self::new(&blob, track, blob.header().control_period_ns)
    }

    /// Starts a new flight targeting gate `target_gate` (after a spawn or respawn): zeroes the
    /// recurrent state and the previous action.
    pub fn reset(&mut self, target_gate: usize) {
        self.state.clear();
        self.progress = GateProgress::targeting(target_gate % self.track.len().max(1));
        self.previous_action = [0.0; ACTION_DIM];
        self.previous_position = None;
    }

    /// One control step from the own state and, for policies that observe one, the
    /// opponent's. Never panics: a bad input gives the fail-safe and a fault.
    pub fn step(&mut self, own: &VehicleState, opponent: Option<&VehicleState>) -> StepOutput {
        match self.begin_step(own, opponent) {
            Ok(pending) => {
                // 40 infer (in place: no copy of the recurrent state on the stack)
                let mean = self.policy.act(&pending.obs, &mut self.state);
                self.finish_step(&pending, mean)
            }
            Err(fail_safe) => fail_safe,
        }
    }

    /// Steps 10-30 of [`Self::step`]: the inputs validated, the target gate advanced, the
    /// observation made (or the fail-safe output, when the inputs are refused). The step
    /// ends with [`Self::finish_step`] on the policy's output for `pending.obs`.
    #[inline(always)]
    fn begin_step(
        &mut self,
        own: &VehicleState,
        opponent: Option<&VehicleState>,
    ) -> Result<PendingStep, StepOutput> {
        // 10 validate: the observation refuses non-finite inputs before any state changes.
        // 20 target gate, 30 observe
        let (progress, gate_event, obs) = self.observe_next(own, opponent);
        self.progress = progress;
        let (obs, folded) = match obs {
            Ok(obs) => obs,
            Err(e) => {
                let fault = match e {
                    ObservationError::NonFiniteOpponent => StepFault::NonFiniteOpponent,
                    ObservationError::MissingOpponent => StepFault::MissingOpponent,
                    _ => StepFault::NonFiniteState,
                };
                return Err(self.fail_safe(fault, gate_event));
            }
        };
        self.previous_position = Some(own.position_m);
        Ok(PendingStep {
            obs,
            folded,
            gate_event,
        })
    }

    /// Steps 40-60 of [`Self::step`] from the policy's output `mean` for `pending.obs`
    /// (the state already advanced): a missing or non-finite output gives the fail-safe.
    #[inline(always)]
    fn finish_step(
        &mut self,
        pending: &PendingStep,
        mean: Option<[f32; ACTION_DIM]>,
    ) -> StepOutput {
        let Some(mean) = mean.filter(|m| m.iter().all(|a| a.is_finite())) else {
            // Only weights near f32::MAX can overflow; a poisoned state would stay poisoned.
            self.state.clear();
            return self.fail_safe(StepFault::NonFiniteAction, pending.gate_event);
        };
        // 50 clip (and renumber a folded step's action), 60 map to rpm
        let action = unfold_action(
            self.fold.as_ref(),
            pending.folded,
            &mean.map(|a| a.clamp(-1.0, 1.0)),
        );
        self.previous_action = action;
        StepOutput {
            command: self.action_map.command(&action),
            action,
            fault: None,
            gate_event: pending.gate_event,
        }
    }

    /// [`Self::step`] of [`LANES`] controllers that fly the same `policy` (clones of one
    /// controller, or controllers built from one blob: the caller's contract), their
    /// policy evaluated side by side ([`Policy::step_lanes`]): each output is bit for bit
    /// what `step` gives that controller (the host's batched opponents). When a lane's
    /// inputs are refused, the other lanes step one by one.
    #[inline(always)]
    pub fn step_lanes(
        policy: &Policy<'w>,
        mut controllers: [&mut Self; LANES],
        own: [&VehicleState; LANES],
        opponent: [Option<&VehicleState>; LANES],
    ) -> [StepOutput; LANES] {
        let dim = policy.obs_dim();
        let mut obs = [0.0f32; MAX_OBSERVATION_DIM * LANES];
        let mut pending: [Option<PendingStep>; LANES] = [None; LANES];
        let mut out = [StepOutput {
            command: MotorCommand::STOP,
            action: [0.0; ACTION_DIM],
            fault: None,
            gate_event: GateEvent::None,
        }; LANES];
        let mut all = true;
        let lanes = controllers
            .iter_mut()
            .zip(own.iter().zip(&opponent))
            .zip(pending.iter_mut().zip(&mut out))
            .zip(obs.chunks_exact_mut(dim.max(1)));
        for (((c, (own, opponent)), (pending, out)), row) in lanes {
            match c.begin_step(own, *opponent) {
                Ok(p) => {
                    if let Some(values) = p.obs.as_slice().get(..row.len()) {
                        row.copy_from_slice(values);
                    }
                    *pending = Some(p);
                }
                Err(fail_safe) => {
                    *out = fail_safe;
                    all = false;
                }
            }
        }
        let means = if all {
            let states = controllers.each_mut().map(|c| &mut c.state);
            policy.step_lanes(obs.get(..dim * LANES).unwrap_or(&[]), states)
        } else {
            None
        };
        let lanes = controllers.iter_mut().zip(&pending).zip(&mut out);
        for (l, ((c, p), out)) in lanes.enumerate() {
            let Some(p) = p else { continue };
            let mean = match &means {
                Some(m) => m.get(l).copied(),
                None => c.policy.act(&p.obs, &mut c.state),
            };
            *out = c.finish_step(p, mean);
        }
        out
    }

    /// The gate bookkeeping and the observation the next [`Controller::step`] would make
    /// from these states, without changing anything.
    #[inline(always)]
    fn observe_next(
        &self,
        own: &VehicleState,
        opponent: Option<&VehicleState>,
    ) -> (
        GateProgress,
        GateEvent,
        Result<(Observation, bool), ObservationError>,
    ) {
        let mut progress = self.progress;
        let gate_event = match self.previous_position {
            Some(from) if own.position_m.is_finite() => {
                progress.advance(&self.track, from, own.position_m)
            }
            _ => GateEvent::None,
        };
        let obs = observe_folded(
            &self.observation,
            self.fold.as_ref(),
            &self.track,
            own,
            progress.target,
            &self.previous_action,
            opponent,
        );
        (progress, gate_event, obs)
    }

    /// The observation the next [`Controller::step`] on these states will feed its policy
    /// (for tools that replay a flight through another policy, e.g. the int8 accuracy
    /// check); the controller is not changed.
    pub fn peek_observation(
        &self,
        own: &VehicleState,
        opponent: Option<&VehicleState>,
    ) -> Result<Observation, ObservationError> {
        self.observe_next(own, opponent).2.map(|(obs, _)| obs)
    }

    /// [`Controller::peek_observation`] and whether that step is folded: its network output
    /// comes back with the motors renumbered by [`Controller::mirror`]
    /// ([`crate::mirror::unfold_action`]).
    pub fn peek_folded_observation(
        &self,
        own: &VehicleState,
        opponent: Option<&VehicleState>,
    ) -> Result<(Observation, bool), ObservationError> {
        self.observe_next(own, opponent).2
    }

    /// The track's mirror the controller folds by, when the blob's pipeline is folded.
    pub fn mirror(&self) -> Option<&TrackMirror> {
        self.fold.as_ref()
    }

    fn fail_safe(&mut self, fault: StepFault, gate_event: GateEvent) -> StepOutput {
        self.fault_count = self.fault_count.saturating_add(1);
        StepOutput {
            command: MotorCommand::STOP,
            action: [0.0; ACTION_DIM],
            fault: Some(fault),
            gate_event,
        }
    }

    /// The policy network.
    pub fn policy(&self) -> &Policy<'w> {
        &self.policy
    }

    /// The recurrent state (for tests and telemetry).
    pub fn policy_state(&self) -> &PolicyState {
        &self.state
    }

    /// The gate the controller flies to and the gates it has passed.
    pub fn progress(&self) -> GateProgress {
        self.progress
    }

    /// The control period this controller runs at (ns).
    pub fn control_period_ns(&self) -> u32 {
        self.control_period_ns
    }

    /// Steps that fell back to the fail-safe since construction.
    pub fn fault_count(&self) -> u32 {
        self.fault_count
    }

    /// What the controller carries from one step to the next, but the recurrent state
    /// ([`Self::policy_state`]): a simulator's snapshot, with [`Self::restore`].
    pub fn memory(&self) -> ControllerMemory {
        ControllerMemory {
            progress: self.progress,
            previous_action: self.previous_action,
            previous_position: self.previous_position,
            fault_count: self.fault_count,
        }
    }

    /// Puts back what [`Self::memory`] and [`Self::policy_state`] read, so that the next
    /// step is the one the snapshotted controller would have taken. `false`, changing
    /// nothing, when the recurrent state is not this policy's shape or the target gate is
    /// not on the track.
    pub fn restore(&mut self, memory: &ControllerMemory, policy_state: &[f32]) -> bool {
        if memory.progress.target >= self.track.len() || policy_state.len() != self.state.flat_len()
        {
            return false;
        }
        self.state.read_flat(policy_state);
        self.progress = memory.progress;
        self.previous_action = memory.previous_action;
        self.previous_position = memory.previous_position;
        self.fault_count = memory.fault_count;
        true
    }
}

/// A controller's step-to-step bookkeeping ([`Controller::memory`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControllerMemory {
    /// The gate it flies to and the gates passed.
    pub progress: GateProgress,
    /// The action of the last step (the policy's next input).
    pub previous_action: [f32; ACTION_DIM],
    /// The position of the last step (for gate crossings).
    pub previous_position: Option<Vec3>,
    /// Steps that fell back to the fail-safe.
    pub fault_count: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ram_budget_of_the_recurrent_controller() {
        println!(
            "controller {} B + step scratch {} B = {} B (budget 8192)",
            core::mem::size_of::<Controller<'static>>(),
            crate::policy::PolicyG::SCRATCH_BYTES,
            CONTROLLER_G_RAM_BYTES
        );
        // The recurrent state alone is 2 layers x (h + c) x 128 x 4 B.
        assert!(core::mem::size_of::<PolicyState>() >= 2 * 2 * 128 * 4);
        assert!(CONTROLLER_G_RAM_BYTES >= core::mem::size_of::<PolicyState>());
    }
}
