//! The figure-8's mirror symmetry: the track reflected in the plane x = 0 is the same track
//! in the same racing order (g0 ↔ g3, g1 ↔ g4, g2 ↔ g5), and a cf2x reflected with it is a
//! cf2x again, with its motors renumbered. So every flight has a mirror image that is a
//! flight too: the reflected state, flown with the renumbered motor commands, stays the
//! reflection of the original at every step, with the same rewards, passes and crashes.
//!
//! A learner can train on each sample's mirror image as well as the sample (symmetry data
//! augmentation, as RSL-RL's `symmetry_cfg`; Mittal et al. 2024): what the policy learns on
//! one half of the figure-8 teaches it the mirrored half. The observation of the reflected
//! state is built by firmware-core's pipeline from the reflected state and gate, so nothing
//! here re-derives the observation: the paper's gate frames are not reflections of each
//! other (g1 and g2 fly upside down, their mirrors g4 and g5 upright), so the same situation
//! on the two halves gives observations that differ by sign flips that depend on the gate.
//!
//! The reflection M = diag(m) (m = (−1, 1, 1) for the plane x = 0) acts on:
//! - positions and world velocities: p ↦ M p, v ↦ M v;
//! - the attitude: R ↦ M R B, with B = diag(1, −1, 1) the body reflected in its own
//!   x-z plane (left and right swapped, forward and up kept). That maps the cf2x's
//!   propellers onto each other and keeps a drone that flies nose first flying nose first:
//!   the image of a state the policy visits is a state it visits on the other half. (The
//!   body's y-z reflection would also be a symmetry, but its images fly tail first, states
//!   no flight reaches: run m1 in docs/TRAINING.md.)
//! - body rates (a pseudo-vector): ω ↦ det(B)·B ω = (−ωx, ωy, −ωz);
//! - motors: motor i's role passes to the motor at its mirror position (x, −y), which spins
//!   the other way (so the yaw torque changes sign with the reflection, as it must).

use crate::world::Drone;
use firmware_core::math::{Quat, Vec3};
use firmware_core::nn::ACTION_DIM;
use firmware_core::track::Track;
use firmware_core::vehicle::{Cf2x, VehicleState};

/// Largest position error (m) and direction error (cosine below 1) accepted when matching
/// a reflected gate to a gate of the track.
const MATCH_TOLERANCE: f32 = 1e-3;

/// The body's reflection B: left and right swapped (y ↦ −y), forward and up kept.
const BODY_SIGNS: Vec3 = Vec3::new(1.0, -1.0, 1.0);

/// A reflection that maps a track onto itself in racing order, with the gate and motor
/// renumbering it implies.
#[derive(Clone, Debug, PartialEq)]
pub struct Mirror {
    /// Diagonal of the reflection (one component −1, the others 1).
    signs: Vec3,
    /// M·B, the rotation that follows the attitude's conjugation by M (see [`Mirror::state`]).
    turn: Quat,
    /// `gates[k]` is the gate the reflection of gate k lands on.
    gates: Vec<usize>,
    /// `motors[i]` is the motor that takes motor i's command in the reflected drone.
    motors: [usize; ACTION_DIM],
}

/// Why a track has no mirror symmetry this module can use.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NoMirror(pub String);

impl core::fmt::Display for NoMirror {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "no mirror symmetry: {}", self.0)
    }
}

impl std::error::Error for NoMirror {}

impl Mirror {
    /// The reflection in the plane x = 0 or, failing that, y = 0 that maps `track` onto
    /// itself in racing order (each gate onto a gate with the same centre, direction of
    /// travel and opening axes up to sign, and the gate after it onto the gate after that).
    pub fn of_track(track: &Track<'_>) -> Result<Self, NoMirror> {
        let motors = motor_map()?;
        let mut why = Vec::new();
        for (plane, signs) in [
            ("x = 0", Vec3::new(-1.0, 1.0, 1.0)),
            ("y = 0", Vec3::new(1.0, -1.0, 1.0)),
        ] {
            match gate_map(track, signs) {
                Ok(gates) => {
                    return Ok(Self {
                        signs,
                        turn: half_turn(mul(signs, BODY_SIGNS)),
                        gates,
                        motors,
                    });
                }
                Err(e) => why.push(format!("plane {plane}: {e}")),
            }
        }
        Err(NoMirror(why.join("; ")))
    }

    /// The gate the reflection of gate `index` lands on.
    pub fn gate(&self, index: usize) -> usize {
        let n = self.gates.len().max(1);
        self.gates.get(index % n).copied().unwrap_or(0)
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
    /// i's value moves to the motor at its reflected position.
    pub fn motors(&self, values: &[f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        let mut out = [0.0; ACTION_DIM];
        for (i, &v) in values.iter().enumerate() {
            if let Some(o) = self.motors.get(i).and_then(|&j| out.get_mut(j)) {
                *o = v;
            }
        }
        out
    }

    /// The reflected drone: state, propeller speeds and target gate (its count of gates
    /// passed is kept).
    pub fn drone(&self, d: &Drone) -> Drone {
        let mut out = *d;
        out.body.state = self.state(&d.body.state);
        out.body.rpm = self.motors(&d.body.rpm);
        out.progress.target = self.gate(d.progress.target);
        out
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

/// Each gate's image under the reflection `signs`, checked against the track.
fn gate_map(track: &Track<'_>, signs: Vec3) -> Result<Vec<usize>, String> {
    let gates = track.gates();
    // Each gate's frame axes (travel, opening y, opening z) in the world.
    let frames: Vec<[Vec3; 3]> = gates
        .iter()
        .map(|g| [Vec3::X, Vec3::Y, Vec3::Z].map(|a| g.frame.rotate(a)))
        .collect();
    let mut map = Vec::with_capacity(gates.len());
    for (k, (g, g_axes)) in gates.iter().zip(&frames).enumerate() {
        let center = mul(signs, g.center_m);
        let axes = g_axes.map(|a| mul(signs, a));
        let image = gates.iter().zip(&frames).position(|(h, h_axes)| {
            (h.center_m - center).norm() < MATCH_TOLERANCE
                // the direction of travel is kept; the opening's axes up to their sign
                && axes[0].dot(h_axes[0]) > 1.0 - MATCH_TOLERANCE
                && axes[1].dot(h_axes[1]).abs() > 1.0 - MATCH_TOLERANCE
                && axes[2].dot(h_axes[2]).abs() > 1.0 - MATCH_TOLERANCE
        });
        match image {
            Some(j) => map.push(j),
            None => return Err(format!("gate {k}'s reflection is not a gate of the track")),
        }
    }
    let n = gates.len();
    for k in 0..n {
        if map[(k + 1) % n] != (map[k] + 1) % n {
            return Err(format!(
                "the reflection reverses the racing order (gate {k} -> {}, gate {} -> {})",
                map[k],
                (k + 1) % n,
                map[(k + 1) % n]
            ));
        }
    }
    Ok(map)
}

/// The cf2x's motor renumbering under the body's reflection B: motor i goes to the motor at
/// its mirror position with the opposite spin.
fn motor_map() -> Result<[usize; ACTION_DIM], NoMirror> {
    let pos = Cf2x::PROPELLER_POSITIONS_M;
    let spin = Cf2x::SPIN_SIGNS;
    let mut map = [0; ACTION_DIM];
    for (i, m) in map.iter_mut().enumerate() {
        *m = (0..ACTION_DIM)
            .find(|&j| {
                (pos[j][0] - BODY_SIGNS.x * pos[i][0]).abs() < 1e-6
                    && (pos[j][1] - BODY_SIGNS.y * pos[i][1]).abs() < 1e-6
                    && spin[j] == -spin[i]
            })
            .ok_or_else(|| {
                NoMirror(format!(
                    "motor {i}'s mirror position in the body is not a motor spinning the other way"
                ))
            })?;
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::Preset;
    use firmware_core::observation::{ObservationLayout, ObservationSpec};
    use firmware_core::track::CrashRules;
    use firmware_core::vehicle::ActionMap;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_figure_eight_mirrors_in_x_with_the_halves_swapped() {
        let m = Mirror::of_track(&Track::figure_eight()).unwrap();
        assert_eq!(m.signs, Vec3::new(-1.0, 1.0, 1.0));
        assert_eq!(m.gates, vec![3, 4, 5, 0, 1, 2]);
        // front-right <-> front-left, back-right <-> back-left
        assert_eq!(m.motors, [3, 2, 1, 0]);
        assert_eq!(m.motors(&[0.1, 0.2, 0.3, 0.4]), [0.4, 0.3, 0.2, 0.1]);
        // A drone flying nose first along +x, level, mirrors into one flying nose first
        // along −x (yawed by π), not tail first.
        let s = VehicleState {
            position_m: Vec3::new(2.0, 1.0, 1.0),
            attitude: Quat::IDENTITY,
            velocity_mps: Vec3::new(5.0, 0.0, 0.0),
            body_rates_radps: Vec3::ZERO,
        };
        let r = m.state(&s);
        assert_eq!(r.position_m, Vec3::new(-2.0, 1.0, 1.0));
        let nose = r.attitude.rotate(Vec3::X);
        assert!((nose - Vec3::new(-1.0, 0.0, 0.0)).norm() < 1e-6, "{nose:?}");
        assert!(r.attitude.inverse_rotate(r.velocity_mps).x > 4.99);
    }

    #[test]
    fn a_track_without_the_symmetry_is_refused_with_the_reason() {
        let gates = firmware_core::track::FIGURE_EIGHT;
        let mut moved = gates;
        moved[1].center_m.x += 0.5;
        let e = Mirror::of_track(&Track::new(&moved, 0.8).unwrap()).unwrap_err();
        assert!(e.to_string().contains("gate 1's reflection"), "{e}");
        // Racing the figure-8 backwards through the same frames is no track at all here;
        // a track whose reflection reverses the order is refused by the order check.
        let two = [gates[1], gates[2]];
        let e = Mirror::of_track(&Track::new(&two, 0.8).unwrap()).unwrap_err();
        assert!(e.to_string().contains("plane"), "{e}");
    }

    #[test]
    fn reflecting_twice_is_the_identity() {
        let m = Mirror::of_track(&Track::figure_eight()).unwrap();
        let s = VehicleState {
            position_m: Vec3::new(1.0, -2.0, 1.5),
            attitude: Quat::new(0.9, 0.1, -0.3, 0.2).normalized(),
            velocity_mps: Vec3::new(3.0, 1.0, -0.5),
            body_rates_radps: Vec3::new(0.4, -1.0, 2.0),
        };
        assert_eq!(m.state(&m.state(&s)), s);
        for k in 0..6 {
            assert_eq!(m.gate(m.gate(k)), k);
        }
        let a = [0.1, -0.2, 0.3, 0.9];
        assert_eq!(m.motors(&m.motors(&a)), a);
    }

    /// The bug this module must not have: a reflection that is not a symmetry of the
    /// simulated world. A random state and random commands, flown beside their reflections
    /// for 1 s on the `paper` preset: the reflected flight stays the reflection (positions,
    /// attitudes, rates), passes the reflected gates and gives the observation the pipeline
    /// builds from the reflected state.
    #[test]
    fn a_reflected_flight_is_the_reflection_of_the_flight() {
        let world = crate::world::World::figure_eight(Preset::paper(), CrashRules::STAGE1);
        let track = world.track;
        let m = Mirror::of_track(&track).unwrap();
        let spec = ObservationSpec::paper(ObservationLayout::TimeTrial17);
        let map = ActionMap::PAPER;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for trial in 0..20 {
            let target = trial % 6;
            let gate = track.gate(target);
            // 2-6 m before the gate, moving toward it, tilted and turning.
            let start = gate.to_world_frame(Vec3::new(
                -rng.random_range(2.0..6.0),
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.3..0.3),
            ));
            let axis = Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let state = VehicleState {
                position_m: start,
                attitude: Quat::from_axis_angle(axis.scale(1.0 / axis.norm()), 0.3).normalized(),
                velocity_mps: gate.forward().scale(rng.random_range(1.0..8.0)),
                body_rates_radps: Vec3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                ),
            };
            let mut d = [Drone::spawned(crate::world::SpawnPoint {
                state,
                target_gate: target,
            })];
            let mut r = [m.drone(&d[0])];
            let mut previous = [0.0f32; ACTION_DIM];
            for step in 0..50 {
                let a: [f32; ACTION_DIM] = core::array::from_fn(|_| rng.random_range(-0.2f32..1.0));
                let obs = spec
                    .observe(
                        &r[0].body.state,
                        &track.gate(r[0].progress.target),
                        &m.motors(&previous),
                        None,
                    )
                    .unwrap();
                let own = spec
                    .observe(
                        &m.state(&d[0].body.state),
                        &track.gate(m.gate(d[0].progress.target)),
                        &m.motors(&previous),
                        None,
                    )
                    .unwrap();
                for (x, y) in obs.as_slice().iter().zip(own.as_slice()) {
                    assert!(
                        (x - y).abs() < 2e-4,
                        "trial {trial} step {step}: {x} vs {y}"
                    );
                }
                let [e] = world.step(&mut d, &[map.command(&a)]);
                let [f] = world.step(&mut r, &[map.command(&m.motors(&a))]);
                assert_eq!(
                    e.crash.is_some(),
                    f.crash.is_some(),
                    "trial {trial} step {step}"
                );
                assert_eq!(
                    e.passed_gate().map(|g| m.gate(g)),
                    f.passed_gate(),
                    "trial {trial} step {step}"
                );
                if e.crash.is_some() {
                    break;
                }
                let want = m.drone(&d[0]);
                let (got, want) = (r[0].body.state, want.body.state);
                assert!(
                    (got.position_m - want.position_m).norm() < 1e-3,
                    "trial {trial} step {step}"
                );
                assert!(
                    (got.velocity_mps - want.velocity_mps).norm() < 1e-3,
                    "trial {trial} step {step}"
                );
                assert!(
                    (got.body_rates_radps - want.body_rates_radps).norm() < 1e-2,
                    "trial {trial} step {step}"
                );
                let dq = got
                    .attitude
                    .to_array()
                    .iter()
                    .zip(want.attitude.to_array())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                assert!(dq < 1e-4, "trial {trial} step {step}: attitude {dq}");
                assert_eq!(r[0].progress.target, m.gate(d[0].progress.target));
                previous = a;
            }
        }
    }
}
