//! A track's mirror symmetry, and the folded observation that uses it.
//!
//! The figure-8 reflected in the plane x = 0 is the same track in the same racing order
//! (g0 ↔ g3, g1 ↔ g4, g2 ↔ g5), and a cf2x reflected with it is a cf2x again with its motors
//! renumbered: every flight has a mirror image that is a flight too.
//!
//! The reflection M = diag(m) (m = (−1, 1, 1) for the plane x = 0) acts on:
//! - positions and world velocities: p ↦ M p, v ↦ M v;
//! - the attitude: R ↦ M R B, with B = diag(1, −1, 1) the body reflected in its own x-z plane
//!   (left and right swapped, forward and up kept), so a drone that flies nose first still
//!   flies nose first (the body's y-z reflection would be a symmetry too, but its images fly
//!   tail first, states no flight reaches: run m1 in docs/journal/stage1.md);
//! - body rates (a pseudo-vector): ω ↦ det(B)·B ω = (−ωx, ωy, −ωz);
//! - motors: motor i's role passes to the motor at its mirror position (x, −y), which spins
//!   the other way (so the yaw torque changes sign with the reflection, as it must).
//!
//! **Folding** (observation pipeline version [`FOLDED_PIPELINE_VERSION`]): a policy that sees
//! only one half of the track. When the target gate is on the mirrored half (its image has
//! the lower index: g3, g4, g5 on the figure-8), the step observes the reflected state flying
//! to the reflected gate after the reflected previous action, and the policy's action is
//! renumbered back before it reaches the motors. The network then learns g0-g2 only, from the
//! flights of both halves, and flies the two halves as one another's images by construction.
//!
//! [`FOLDED_PIPELINE_VERSION`]: crate::observation::FOLDED_PIPELINE_VERSION

use crate::math::{Quat, Vec3};
use crate::nn::ACTION_DIM;
use crate::observation::{Observation, ObservationError, ObservationSpec};
use crate::track::Track;
use crate::vehicle::{Cf2x, VehicleState};

/// The most gates a mirrored track may have.
pub const MAX_MIRROR_GATES: usize = 16;

/// Largest position error (m) and direction error (cosine below 1) accepted when matching
/// a reflected gate to a gate of the track.
const MATCH_TOLERANCE: f32 = 1e-3;

/// The body's reflection B: left and right swapped (y ↦ −y), forward and up kept.
const BODY_SIGNS: Vec3 = Vec3::new(1.0, -1.0, 1.0);

/// The planes tried, in order.
const PLANES: [Vec3; 2] = [Vec3::new(-1.0, 1.0, 1.0), Vec3::new(1.0, -1.0, 1.0)];

/// A reflection that maps a track onto itself in racing order, with the gate and motor
/// renumbering it implies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackMirror {
    /// Diagonal of the reflection (one component −1, the others 1).
    signs: Vec3,
    /// M·B, the rotation that follows the attitude's conjugation by M (see [`TrackMirror::state`]).
    turn: Quat,
    /// `gates[k]` is the gate the reflection of gate k lands on (first `len` used).
    gates: [u8; MAX_MIRROR_GATES],
    len: u8,
    /// `motors[i]` is the motor that takes motor i's command in the reflected drone.
    motors: [u8; ACTION_DIM],
}

/// Why a reflection in one plane is not a symmetry of the track.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlaneMismatch {
    /// This gate's reflection is not a gate of the track.
    GateNotReflected(usize),
    /// The reflection reverses the racing order at this gate.
    ReversesOrder(usize),
}

impl core::fmt::Display for PlaneMismatch {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::GateNotReflected(k) => {
                write!(f, "gate {k}'s reflection is not a gate of the track")
            }
            Self::ReversesOrder(k) => {
                write!(f, "the reflection reverses the racing order at gate {k}")
            }
        }
    }
}

/// Why a track has no mirror symmetry this module can use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum MirrorError {
    /// More gates than [`MAX_MIRROR_GATES`], or none.
    GateCount(usize),
    /// The cf2x's motor at this index has no motor at its mirror position spinning the
    /// other way.
    Motor(usize),
    /// Neither plane maps the track onto itself: why not, in x = 0 and in y = 0.
    NoPlane {
        /// The plane x = 0.
        x: PlaneMismatch,
        /// The plane y = 0.
        y: PlaneMismatch,
    },
}

impl core::fmt::Display for MirrorError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("no mirror symmetry: ")?;
        match self {
            Self::GateCount(n) => write!(f, "{n} gates (1 to {MAX_MIRROR_GATES} supported)"),
            Self::Motor(i) => write!(
                f,
                "motor {i}'s mirror position in the body is not a motor spinning the other way"
            ),
            Self::NoPlane { x, y } => write!(f, "plane x = 0: {x}; plane y = 0: {y}"),
        }
    }
}

impl TrackMirror {
    /// The reflection in the plane x = 0 or, failing that, y = 0 that maps `track` onto
    /// itself in racing order (each gate onto a gate with the same centre, direction of
    /// travel and opening axes up to sign, and the gate after it onto the gate after that).
    pub fn of_track(track: &Track<'_>) -> Result<Self, MirrorError> {
        let n = track.len();
        if n == 0 || n > MAX_MIRROR_GATES {
            return Err(MirrorError::GateCount(n));
        }
        let motors = motor_map()?;
        let mut why = [PlaneMismatch::GateNotReflected(0); 2];
        for (signs, why) in PLANES.into_iter().zip(&mut why) {
            match gate_map(track, signs) {
                Ok(gates) => {
                    return Ok(Self {
                        signs,
                        turn: half_turn(mul(signs, BODY_SIGNS)),
                        gates,
                        len: n as u8,
                        motors,
                    });
                }
                Err(e) => *why = e,
            }
        }
        let [x, y] = why;
        Err(MirrorError::NoPlane { x, y })
    }

    /// Diagonal of the reflection.
    pub fn signs(&self) -> Vec3 {
        self.signs
    }

    /// The gate the reflection of gate `index` lands on.
    pub fn gate(&self, index: usize) -> usize {
        let n = usize::from(self.len).max(1);
        self.gates.get(index % n).map_or(0, |&g| usize::from(g))
    }

    /// True when a step flying to `target` is observed through the mirror in a folded
    /// pipeline: its image has the lower index (g3, g4, g5 on the figure-8).
    pub fn folds(&self, target: usize) -> bool {
        self.gate(target) < target % usize::from(self.len).max(1)
    }

    /// The reflected vehicle state.
    pub fn state(&self, s: &VehicleState) -> VehicleState {
        let m = self.signs;
        let q = s.attitude;
        // M R B = (M R M)(M B): the rotation conjugated by M, then M B.
        let conjugated = Quat::new(q.w, -m.x * q.x, -m.y * q.y, -m.z * q.z);
        VehicleState {
            position_m: mul(m, s.position_m),
            attitude: conjugated * self.turn,
            velocity_mps: mul(m, s.velocity_mps),
            // det(B) = −1
            body_rates_radps: mul(BODY_SIGNS, s.body_rates_radps).scale(-1.0),
        }
    }

    /// The motor commands (or actions, or propeller speeds) of the reflected drone: motor
    /// i's value moves to the motor at its reflected position. Its own inverse.
    pub fn motors(&self, values: &[f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        let mut out = [0.0; ACTION_DIM];
        for (&v, &j) in values.iter().zip(&self.motors) {
            if let Some(o) = out.get_mut(usize::from(j)) {
                *o = v;
            }
        }
        out
    }
}

/// A pipeline's mirror fold: `None` observes every step as it is (pipeline version 1),
/// `Some` observes the mirrored half through the mirror ([`FOLDED_PIPELINE_VERSION`]).
///
/// [`FOLDED_PIPELINE_VERSION`]: crate::observation::FOLDED_PIPELINE_VERSION
pub type Fold = Option<TrackMirror>;

/// The observation a step flying `own` to gate `target` of `track` feeds its policy under
/// `spec`, folded by `fold`, and whether it was taken through the mirror (then the policy's
/// action goes through [`TrackMirror::motors`] before the motors: [`unfold_action`]).
/// `previous_action` and `opponent` are as flown (world motors, world state).
pub fn observe_folded(
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    track: &Track<'_>,
    own: &VehicleState,
    target: usize,
    previous_action: &[f32; ACTION_DIM],
    opponent: Option<&VehicleState>,
) -> Result<(Observation, bool), ObservationError> {
    match fold.filter(|m| m.folds(target)) {
        Some(m) => {
            let opponent = opponent.map(|o| m.state(o));
            let obs = spec.observe(
                &m.state(own),
                &track.gate(m.gate(target)),
                &m.motors(previous_action),
                opponent.as_ref(),
            )?;
            Ok((obs, true))
        }
        None => Ok((
            spec.observe(own, &track.gate(target), previous_action, opponent)?,
            false,
        )),
    }
}

/// The action to fly for a policy output `action` whose observation was `folded`
/// ([`observe_folded`]): renumbered through the mirror, or as it is.
pub fn unfold_action(
    fold: Option<&TrackMirror>,
    folded: bool,
    action: &[f32; ACTION_DIM],
) -> [f32; ACTION_DIM] {
    match fold {
        Some(m) if folded => m.motors(action),
        _ => *action,
    }
}

fn mul(a: Vec3, b: Vec3) -> Vec3 {
    Vec3::new(a.x * b.x, a.y * b.y, a.z * b.z)
}

/// The rotation diag(`d`) (a product of two reflections: all signs +1, or two of them −1),
/// as a quaternion: none, or half a turn about the one axis it keeps.
fn half_turn(d: Vec3) -> Quat {
    if d.x > 0.0 && d.y > 0.0 {
        Quat::IDENTITY
    } else if d.z > 0.0 {
        Quat::new(0.0, 0.0, 0.0, 1.0)
    } else if d.y > 0.0 {
        Quat::new(0.0, 0.0, 1.0, 0.0)
    } else {
        Quat::new(0.0, 1.0, 0.0, 0.0)
    }
}

/// A gate's frame axes (travel, opening y, opening z) in the world.
fn axes(frame: Quat) -> [Vec3; 3] {
    [Vec3::X, Vec3::Y, Vec3::Z].map(|a| frame.rotate(a))
}

/// Each gate's image under the reflection `signs`, checked against the track.
fn gate_map(track: &Track<'_>, signs: Vec3) -> Result<[u8; MAX_MIRROR_GATES], PlaneMismatch> {
    let gates = track.gates();
    let mut map = [0u8; MAX_MIRROR_GATES];
    for (k, (g, slot)) in gates.iter().zip(map.iter_mut()).enumerate() {
        let center = mul(signs, g.center_m);
        let image_axes = axes(g.frame).map(|a| mul(signs, a));
        let image = gates.iter().position(|h| {
            let h_axes = axes(h.frame);
            (h.center_m - center).norm() < MATCH_TOLERANCE
                // the direction of travel is kept; the opening's axes up to their sign
                && image_axes[0].dot(h_axes[0]) > 1.0 - MATCH_TOLERANCE
                && image_axes[1].dot(h_axes[1]).abs() > 1.0 - MATCH_TOLERANCE
                && image_axes[2].dot(h_axes[2]).abs() > 1.0 - MATCH_TOLERANCE
        });
        *slot = image.ok_or(PlaneMismatch::GateNotReflected(k))? as u8;
    }
    let n = gates.len();
    let at = |k: usize| map.get(k % n).map_or(0, |&g| usize::from(g));
    for k in 0..n {
        if at(k + 1) != (at(k) + 1) % n {
            return Err(PlaneMismatch::ReversesOrder(k));
        }
    }
    Ok(map)
}

/// The cf2x's motor renumbering under the body's reflection B: motor i goes to the motor at
/// its mirror position with the opposite spin.
fn motor_map() -> Result<[u8; ACTION_DIM], MirrorError> {
    let pos = Cf2x::PROPELLER_POSITIONS_M;
    let spin = Cf2x::SPIN_SIGNS;
    let mut map = [0u8; ACTION_DIM];
    for (i, ((m, p), s)) in map.iter_mut().zip(&pos).zip(&spin).enumerate() {
        let j = pos
            .iter()
            .zip(&spin)
            .position(|(q, t)| {
                (q[0] - BODY_SIGNS.x * p[0]).abs() < 1e-6
                    && (q[1] - BODY_SIGNS.y * p[1]).abs() < 1e-6
                    && *t == -*s
            })
            .ok_or(MirrorError::Motor(i))?;
        *m = j as u8;
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observation::ObservationLayout;

    #[test]
    fn the_figure_eight_mirrors_in_x_with_the_halves_swapped() {
        let m = TrackMirror::of_track(&Track::figure_eight()).unwrap();
        assert_eq!(m.signs(), Vec3::new(-1.0, 1.0, 1.0));
        assert_eq!(
            (0..6).map(|k| m.gate(k)).collect::<Vec<_>>(),
            [3, 4, 5, 0, 1, 2]
        );
        // front-right <-> front-left, back-right <-> back-left
        assert_eq!(m.motors(&[0.1, 0.2, 0.3, 0.4]), [0.4, 0.3, 0.2, 0.1]);
        assert_eq!(
            (0..6).map(|k| m.folds(k)).collect::<Vec<_>>(),
            [false, false, false, true, true, true]
        );
    }

    #[test]
    fn a_track_without_the_symmetry_is_refused_with_the_reason() {
        let mut moved = crate::track::FIGURE_EIGHT;
        moved[1].center_m.x += 0.5;
        let e = TrackMirror::of_track(&Track::new(&moved, 0.8).unwrap()).unwrap_err();
        assert!(matches!(e, MirrorError::NoPlane { .. }), "{e}");
        let text = std::format!("{e}");
        assert!(text.contains("gate 1's reflection"), "{text}");
    }

    /// Folding observes g3-g5 as their images and leaves g0-g2 alone, and the action comes
    /// back renumbered: a folded step of a state is the plain step of its mirror image.
    #[test]
    fn a_folded_step_is_the_plain_step_of_the_image() {
        let track = Track::figure_eight();
        let m = TrackMirror::of_track(&track).unwrap();
        let spec = ObservationSpec::paper(ObservationLayout::TimeTrial17);
        let s = VehicleState {
            position_m: Vec3::new(1.0, -2.0, 1.5),
            attitude: Quat::new(0.9, 0.1, -0.3, 0.2).normalized(),
            velocity_mps: Vec3::new(3.0, 1.0, -0.5),
            body_rates_radps: Vec3::new(0.4, -1.0, 2.0),
        };
        let prev = [0.1, -0.2, 0.3, 0.9];
        for target in 0..6 {
            let (obs, folded) =
                observe_folded(&spec, Some(&m), &track, &s, target, &prev, None).unwrap();
            let plain = spec.observe(&s, &track.gate(target), &prev, None).unwrap();
            let image = spec
                .observe(
                    &m.state(&s),
                    &track.gate(m.gate(target)),
                    &m.motors(&prev),
                    None,
                )
                .unwrap();
            assert_eq!(folded, target >= 3);
            assert_eq!(obs, if folded { image } else { plain }, "target {target}");
            let (unfolded, f) =
                observe_folded(&spec, None, &track, &s, target, &prev, None).unwrap();
            assert_eq!((unfolded, f), (plain, false));
            let a = [0.5, -1.0, 0.25, 1.0];
            let flown = unfold_action(Some(&m), folded, &a);
            assert_eq!(flown, if folded { [1.0, 0.25, -1.0, 0.5] } else { a });
            assert_eq!(unfold_action(None, true, &a), a);
        }
    }
}
