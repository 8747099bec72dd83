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
//!   no flight reaches: run m1 in docs/journal/stage1.md.)
//! - body rates (a pseudo-vector): ω ↦ det(B)·B ω = (−ωx, ωy, −ωz);
//! - motors: motor i's role passes to the motor at its mirror position (x, −y), which spins
//!   the other way (so the yaw torque changes sign with the reflection, as it must).

use crate::world::Drone;
use firmware_core::mirror::TrackMirror;
use firmware_core::nn::ACTION_DIM;
use firmware_core::track::Track;
use firmware_core::vehicle::VehicleState;

/// A reflection that maps a track onto itself in racing order, with the gate and motor
/// renumbering it implies: firmware-core's [`TrackMirror`] (the one a folded controller
/// flies with), extended to the simulator's drones.
#[derive(Clone, Debug, PartialEq)]
pub struct Mirror(TrackMirror);

/// Why a track has no mirror symmetry this module can use.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NoMirror(pub String);

impl core::fmt::Display for NoMirror {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for NoMirror {}

impl Mirror {
    /// The reflection in the plane x = 0 or, failing that, y = 0 that maps `track` onto
    /// itself in racing order ([`TrackMirror::of_track`]).
    pub fn of_track(track: &Track<'_>) -> Result<Self, NoMirror> {
        TrackMirror::of_track(track)
            .map(Self)
            .map_err(|e| NoMirror(e.to_string()))
    }

    /// The firmware-core reflection.
    pub fn track_mirror(&self) -> &TrackMirror {
        &self.0
    }

    /// The gate the reflection of gate `index` lands on.
    pub fn gate(&self, index: usize) -> usize {
        self.0.gate(index)
    }

    /// The reflected vehicle state.
    pub fn state(&self, s: &VehicleState) -> VehicleState {
        self.0.state(s)
    }

    /// The motor commands (or actions, or propeller speeds) of the reflected drone: motor
    /// i's value moves to the motor at its reflected position.
    pub fn motors(&self, values: &[f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        self.0.motors(values)
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::Preset;
    use firmware_core::math::{Quat, Vec3};
    use firmware_core::observation::{ObservationLayout, ObservationSpec};
    use firmware_core::track::CrashRules;
    use firmware_core::vehicle::ActionMap;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_figure_eight_mirrors_in_x_with_the_halves_swapped() {
        let m = Mirror::of_track(&Track::figure_eight()).unwrap();
        assert_eq!(m.track_mirror().signs(), Vec3::new(-1.0, 1.0, 1.0));
        assert_eq!(
            (0..6).map(|k| m.gate(k)).collect::<Vec<_>>(),
            [3, 4, 5, 0, 1, 2]
        );
        // front-right <-> front-left, back-right <-> back-left
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
