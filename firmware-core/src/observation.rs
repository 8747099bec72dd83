//! The observation pipeline (docs/DESIGN.md "Observations"), shared by training and
//! deployment.
//!
//! The scales, clipping and layout are data: an [`ObservationSpec`] that every blob records,
//! so a controller refuses a policy trained for another pipeline. The pipeline reads top to
//! bottom in [`ObservationSpec::observe`]:
//!
//! | stage | indices | value |
//! |---|---|---|
//! | 10 validate | | every input finite, the opponent present when the layout needs it |
//! | 20 gate | 0..3 | clip(R_gateᵀ (p_gate − p) / gate_position_scale_m, ±clip) |
//! | 30 attitude | 3..7 | own attitude quaternion (w, x, y, z), as integrated |
//! | 40 velocity | 7..10 | clip(R_bodyᵀ v / velocity_scale_mps, ±clip) |
//! | 50 rates | 10..13 | clip(ω_body / body_rate_scale_radps, ±clip) |
//! | 60 previous action | 13..17 | the previous (clipped) action |
//! | 70 opponent position | 17..20 | clip(R_bodyᵀ (p_opp − p) / opponent_position_scale_m, ±clip) |
//! | 80 opponent attitude | 20..24 | opponent attitude quaternion (w, x, y, z) |
//! | 90 opponent velocity | 24..27 | clip(R_bodyᵀ v_opp / opponent_velocity_scale_mps, ±clip) |
//! | 100 opponent rates | 27..30 | clip(R_bodyᵀ ω_opp,world / opponent_rate_scale_radps, ±clip) |
//!
//! Layouts: [`ObservationLayout::TimeTrial17`] stops after stage 60,
//! [`ObservationLayout::OpponentPosition20`] after stage 70, [`ObservationLayout::FullOpponent30`]
//! runs them all. R_body is the ego attitude, R_gate the target gate's frame; positions in m,
//! velocities in m/s (world), rates in rad/s.

use crate::math::{Quat, Vec3};
use crate::track::Gate;
use crate::vehicle::VehicleState;
use serde::{Deserialize, Serialize};

/// Version of this pipeline's semantics. A blob whose spec names a version other than this
/// or [`FOLDED_PIPELINE_VERSION`] is refused.
pub const OBSERVATION_PIPELINE_VERSION: u16 = 1;

/// Version 1 folded by the track's mirror symmetry ([`crate::mirror`]): a step whose target
/// gate is on the mirrored half observes the reflected state, reflected gate and reflected
/// previous action, and its action is renumbered back to the world's motors. The values and
/// their scales are version 1's; only which state they are taken of differs. A controller
/// for a track without the symmetry refuses such a blob.
pub const FOLDED_PIPELINE_VERSION: u16 = 2;

/// The largest observation (stage 2).
pub const MAX_OBSERVATION_DIM: usize = 30;

/// Which terms an observation holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ObservationLayout {
    /// Stage 1 (Table 1 row A): gate, attitude, velocity, rates, previous action.
    TimeTrial17,
    /// Ablation B: the 17 plus the opponent's relative position.
    OpponentPosition20,
    /// Stage 2 (rows C–G): the 17 plus the opponent's full state.
    FullOpponent30,
}

impl ObservationLayout {
    /// Number of values.
    pub const fn dim(self) -> usize {
        match self {
            Self::TimeTrial17 => 17,
            Self::OpponentPosition20 => 20,
            Self::FullOpponent30 => 30,
        }
    }

    /// The layout with `dim` values, if any.
    pub const fn from_dim(dim: usize) -> Option<Self> {
        match dim {
            17 => Some(Self::TimeTrial17),
            20 => Some(Self::OpponentPosition20),
            30 => Some(Self::FullOpponent30),
            _ => None,
        }
    }

    /// True when the layout observes an opponent.
    pub const fn needs_opponent(self) -> bool {
        !matches!(self, Self::TimeTrial17)
    }
}

/// The observation contract: layout, scales and clipping, with the pipeline version.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObservationSpec {
    /// Pipeline version the policy was trained with ([`OBSERVATION_PIPELINE_VERSION`]).
    pub version: u16,
    /// Which terms are present.
    pub layout: ObservationLayout,
    /// Divisor of the gate-relative position (m). Paper: 12.
    pub gate_position_scale_m: f32,
    /// Divisor of the own body-frame velocity (m/s). Paper: 3.
    pub velocity_scale_mps: f32,
    /// Divisor of the own body rates (rad/s). Paper: π.
    pub body_rate_scale_radps: f32,
    /// Divisor of the opponent's relative position (m). Paper: 12.
    pub opponent_position_scale_m: f32,
    /// Divisor of the opponent's velocity in the ego body frame (m/s). Paper: 3.
    pub opponent_velocity_scale_mps: f32,
    /// Divisor of the opponent's angular velocity in the ego body frame (rad/s). Paper: π.
    pub opponent_rate_scale_radps: f32,
    /// Scaled terms are clipped to ±clip. Paper: 1.
    pub clip: f32,
}

impl Default for ObservationSpec {
    fn default() -> Self {
        Self::paper(ObservationLayout::TimeTrial17)
    }
}

/// Why no observation could be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum ObservationError {
    /// The own state has a NaN or infinite value.
    NonFiniteState,
    /// The opponent state has a NaN or infinite value.
    NonFiniteOpponent,
    /// The previous action has a NaN or infinite value.
    NonFiniteAction,
    /// The layout observes an opponent and none was given.
    MissingOpponent,
}

impl core::fmt::Display for ObservationError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NonFiniteState => "own vehicle state is not finite",
            Self::NonFiniteOpponent => "opponent state is not finite",
            Self::NonFiniteAction => "previous action is not finite",
            Self::MissingOpponent => "the observation layout needs an opponent state",
        })
    }
}

/// One observation: up to [`MAX_OBSERVATION_DIM`] values, `dim` of them used.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    values: [f32; MAX_OBSERVATION_DIM],
    dim: usize,
}

impl Observation {
    /// The used values.
    pub fn as_slice(&self) -> &[f32] {
        self.values.get(..self.dim).unwrap_or(&self.values)
    }

    /// The values as a fixed-size array, when `N` is this observation's size.
    pub fn as_array<const N: usize>(&self) -> Option<&[f32; N]> {
        if N != self.dim {
            return None;
        }
        self.values.first_chunk::<N>()
    }

    /// Number of values.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// An observation holding `values` as they are (for replaying recorded or synthetic
    /// inputs); `None` unless the length is one of the layouts' sizes.
    pub fn from_values(values: &[f32]) -> Option<Self> {
        ObservationLayout::from_dim(values.len())?;
        let mut out = [0.0; MAX_OBSERVATION_DIM];
        for (o, v) in out.iter_mut().zip(values) {
            *o = *v;
        }
        Some(Self {
            values: out,
            dim: values.len(),
        })
    }
}

impl ObservationSpec {
    /// The paper's scales for `layout`, at the current pipeline version.
    pub const fn paper(layout: ObservationLayout) -> Self {
        Self {
            version: OBSERVATION_PIPELINE_VERSION,
            layout,
            gate_position_scale_m: 12.0,
            velocity_scale_mps: 3.0,
            body_rate_scale_radps: core::f32::consts::PI,
            opponent_position_scale_m: 12.0,
            opponent_velocity_scale_mps: 3.0,
            opponent_rate_scale_radps: core::f32::consts::PI,
            clip: 1.0,
        }
    }

    /// This spec folded by the track's mirror ([`FOLDED_PIPELINE_VERSION`]) or not (version 1).
    pub const fn with_fold(self, folded: bool) -> Self {
        Self {
            version: if folded {
                FOLDED_PIPELINE_VERSION
            } else {
                OBSERVATION_PIPELINE_VERSION
            },
            ..self
        }
    }

    /// True when the spec folds the track's mirrored half onto the other
    /// ([`FOLDED_PIPELINE_VERSION`]).
    pub const fn is_folded(&self) -> bool {
        self.version == FOLDED_PIPELINE_VERSION
    }

    /// Number of values of this spec's observations.
    pub const fn dim(&self) -> usize {
        self.layout.dim()
    }

    /// The six scales and the clip, in header order: gate position (m), velocity (m/s),
    /// body rates (rad/s), opponent position (m), velocity (m/s) and rates (rad/s), clip.
    pub const fn scales(&self) -> [f32; 7] {
        [
            self.gate_position_scale_m,
            self.velocity_scale_mps,
            self.body_rate_scale_radps,
            self.opponent_position_scale_m,
            self.opponent_velocity_scale_mps,
            self.opponent_rate_scale_radps,
            self.clip,
        ]
    }

    /// True when this pipeline can build observations for the spec: same version, every
    /// scale finite and positive.
    pub fn is_supported(&self) -> bool {
        (self.version == OBSERVATION_PIPELINE_VERSION || self.version == FOLDED_PIPELINE_VERSION)
            && self.scales().iter().all(|s| s.is_finite() && *s > 0.0)
    }

    /// Builds the observation of `own` flying to `target_gate`, after `previous_action`,
    /// racing `opponent` (ignored by [`ObservationLayout::TimeTrial17`]).
    pub fn observe(
        &self,
        own: &VehicleState,
        target_gate: &Gate,
        previous_action: &[f32; 4],
        opponent: Option<&VehicleState>,
    ) -> Result<Observation, ObservationError> {
        // 10 validate
        if !own.is_finite() {
            return Err(ObservationError::NonFiniteState);
        }
        if !previous_action.iter().all(|a| a.is_finite()) {
            return Err(ObservationError::NonFiniteAction);
        }
        let opponent = if self.layout.needs_opponent() {
            let opp = opponent.ok_or(ObservationError::MissingOpponent)?;
            if !opp.is_finite() {
                return Err(ObservationError::NonFiniteOpponent);
            }
            Some(opp)
        } else {
            None
        };

        let mut w = Writer {
            values: [0.0; MAX_OBSERVATION_DIM],
            len: 0,
        };
        let body = own.attitude;
        let clip = self.clip;
        // 20 gate: the gate seen from the drone, in the gate frame.
        let to_gate = target_gate
            .frame
            .inverse_rotate(target_gate.center_m - own.position_m);
        w.vec3(
            to_gate
                .scale(1.0 / self.gate_position_scale_m)
                .clamp_abs(clip),
        );
        // 30 attitude
        w.quat(body);
        // 40 velocity, body frame
        w.vec3(
            body.inverse_rotate(own.velocity_mps)
                .scale(1.0 / self.velocity_scale_mps)
                .clamp_abs(clip),
        );
        // 50 body rates
        w.vec3(
            own.body_rates_radps
                .scale(1.0 / self.body_rate_scale_radps)
                .clamp_abs(clip),
        );
        // 60 previous action
        for &a in previous_action {
            w.push(a);
        }
        if let Some(opp) = opponent {
            // 70 opponent position, ego body frame
            let rel = body.inverse_rotate(opp.position_m - own.position_m);
            w.vec3(
                rel.scale(1.0 / self.opponent_position_scale_m)
                    .clamp_abs(clip),
            );
            if self.layout == ObservationLayout::FullOpponent30 {
                // 80 opponent attitude
                w.quat(opp.attitude);
                // 90 opponent velocity, ego body frame
                let v = body.inverse_rotate(opp.velocity_mps);
                w.vec3(
                    v.scale(1.0 / self.opponent_velocity_scale_mps)
                        .clamp_abs(clip),
                );
                // 100 opponent angular velocity (world), in the ego body frame
                let rates = body.inverse_rotate(opp.world_rates_radps());
                w.vec3(
                    rates
                        .scale(1.0 / self.opponent_rate_scale_radps)
                        .clamp_abs(clip),
                );
            }
        }
        Ok(Observation {
            values: w.values,
            dim: w.len,
        })
    }
}

struct Writer {
    values: [f32; MAX_OBSERVATION_DIM],
    len: usize,
}

impl Writer {
    fn push(&mut self, v: f32) {
        if let Some(slot) = self.values.get_mut(self.len) {
            *slot = v;
            self.len += 1;
        }
    }
    fn vec3(&mut self, v: Vec3) {
        for c in v.to_array() {
            self.push(c);
        }
    }
    fn quat(&mut self, q: Quat) {
        for c in q.to_array() {
            self.push(c);
        }
    }
}
