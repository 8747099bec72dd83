//! Frame conversions between the simulator (ENU/FLU) and MAVLink (NED/FRD): the bridge
//! sends states in them, and the referee hands in-process pilots states through the same
//! round trip.
//!
//! The simulator and firmware-core work in **ENU/FLU**: world x east, y north, z up; body x
//! forward, y left, z up; quaternions (w, x, y, z) map body vectors to the world. MAVLink
//! works in **NED/FRD**: world x north, y east, z down; body x forward, y right, z down.
//!
//! - Vectors in the world frame: `(n, e, d) = (y, x, −z)`; the same map takes them back.
//! - Vectors in the body frame (rates): `(f, r, d) = (x, −y, −z)`; its own inverse too.
//! - Attitude: `q_ned_frd = q(ENU→NED) ⊗ q_enu_flu ⊗ q(FRD→FLU)`, with the two fixed
//!   rotations a half turn about (1, 1, 0)/√2 and a half turn about x. Written out:
//!   `q_ned = (w + z, x + y, x − y, w − z)/√2`, and back `w = (q0 + q3)/√2`,
//!   `x = (q1 + q2)/√2`, `y = (q1 − q2)/√2`, `z = (q0 − q3)/√2`.
//!
//! Vector maps are sign flips and swaps, exact in f32. The attitude map has a 1/√2 and is
//! computed in f64 and rounded once each way: a round trip moves each component of a unit
//! quaternion by at most 1e-7 (property-tested). Not bit-exact, so `sitl eval` hands its
//! pilots states through the same round trip, and the lockstep race flies exactly
//! `sitl eval`'s trajectories (`sitl/tests/bridge.rs`).

use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::VehicleState;

const FRAC_1_SQRT_2: f64 = core::f64::consts::FRAC_1_SQRT_2;

/// A world-frame vector from ENU to NED (or back: the map is its own inverse).
pub fn ned_from_enu(v: Vec3) -> Vec3 {
    Vec3::new(v.y, v.x, -v.z)
}

/// A world-frame vector from NED to ENU.
pub fn enu_from_ned(v: Vec3) -> Vec3 {
    ned_from_enu(v)
}

/// A body-frame vector from FLU to FRD (or back: the map is its own inverse).
pub fn frd_from_flu(v: Vec3) -> Vec3 {
    Vec3::new(v.x, -v.y, -v.z)
}

/// A body-frame vector from FRD to FLU.
pub fn flu_from_frd(v: Vec3) -> Vec3 {
    frd_from_flu(v)
}

/// The attitude FLU→ENU as FRD→NED (components (w, x, y, z)).
pub fn ned_attitude(q: Quat) -> Quat {
    let [w, x, y, z] = q.to_array().map(f64::from);
    let c = |v: f64| (v * FRAC_1_SQRT_2) as f32;
    Quat::new(c(w + z), c(x + y), c(x - y), c(w - z))
}

/// The attitude FRD→NED as FLU→ENU: the inverse of [`ned_attitude`].
pub fn enu_attitude(q: Quat) -> Quat {
    let [q0, q1, q2, q3] = q.to_array().map(f64::from);
    let c = |v: f64| (v * FRAC_1_SQRT_2) as f32;
    Quat::new(c(q0 + q3), c(q1 + q2), c(q1 - q2), c(q0 - q3))
}

/// A vehicle state as MAVLink carries it: NED position (m) and velocity (m/s), the FRD→NED
/// attitude, FRD body rates (rad/s).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NedState {
    /// Position (m, NED, relative to the track origin).
    pub position_m: Vec3,
    /// Velocity (m/s, NED).
    pub velocity_mps: Vec3,
    /// Attitude, body FRD to world NED.
    pub attitude: Quat,
    /// Angular velocity (rad/s, body FRD): roll, pitch, yaw speed.
    pub body_rates_radps: Vec3,
}

impl NedState {
    /// The simulator's state in MAVLink's frames.
    pub fn from_enu(s: &VehicleState) -> Self {
        Self {
            position_m: ned_from_enu(s.position_m),
            velocity_mps: ned_from_enu(s.velocity_mps),
            attitude: ned_attitude(s.attitude),
            body_rates_radps: frd_from_flu(s.body_rates_radps),
        }
    }

    /// Back to the simulator's (and firmware-core's) frames.
    pub fn to_enu(&self) -> VehicleState {
        VehicleState {
            position_m: enu_from_ned(self.position_m),
            velocity_mps: enu_from_ned(self.velocity_mps),
            attitude: enu_attitude(self.attitude),
            body_rates_radps: flu_from_frd(self.body_rates_radps),
        }
    }

    /// Roll, pitch, yaw (rad; aerospace Z-Y-X order, yaw from north towards east), as
    /// MAVLink's ATTITUDE reports them.
    pub fn euler_rad(&self) -> [f32; 3] {
        let [w, x, y, z] = self.attitude.to_array().map(f64::from);
        let roll = libm::atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y));
        let pitch = libm::asin((2.0 * (w * y - z * x)).clamp(-1.0, 1.0));
        let yaw = libm::atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z));
        [roll as f32, pitch as f32, yaw as f32]
    }
}

/// The geodetic point the track's origin is placed at for ground stations (a local
/// tangent plane: fine for a 30 m track).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeoOrigin {
    /// Latitude (degrees north).
    pub lat_deg: f64,
    /// Longitude (degrees east).
    pub lon_deg: f64,
    /// Altitude of the ground (m above mean sea level).
    pub alt_m: f64,
}

/// Equatorial radius of WGS-84 (m).
const EARTH_RADIUS_M: f64 = 6_378_137.0;

impl GeoOrigin {
    /// PX4 SITL's default home (Zürich), familiar to QGroundControl users.
    pub const DEFAULT: Self = Self {
        lat_deg: 47.397_742,
        lon_deg: 8.545_594,
        alt_m: 488.0,
    };

    /// Latitude and longitude (degrees × 1e7) and altitude above mean sea level (mm) of a
    /// NED position.
    pub fn global_int(&self, ned_m: Vec3) -> (i32, i32, i32) {
        let lat = self.lat_deg + (f64::from(ned_m.x) / EARTH_RADIUS_M).to_degrees();
        let lon = self.lon_deg
            + (f64::from(ned_m.y) / (EARTH_RADIUS_M * self.lat_deg.to_radians().cos()))
                .to_degrees();
        let alt_mm = (self.alt_m - f64::from(ned_m.z)) * 1000.0;
        (
            (lat * 1e7).round() as i32,
            (lon * 1e7).round() as i32,
            alt_mm.round() as i32,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit_quat() -> impl Strategy<Value = Quat> {
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0)
            .prop_filter("not near zero", |(w, x, y, z)| {
                w * w + x * x + y * y + z * z > 0.01
            })
            .prop_map(|(w, x, y, z)| Quat::new(w, x, y, z).normalized())
    }

    fn vec3(r: f32) -> impl Strategy<Value = Vec3> {
        (-r..r, -r..r, -r..r).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    #[test]
    fn identity_attitude_faces_east_in_ned() {
        // Body forward along ENU x (east) is a yaw of +90° in NED.
        let s = NedState::from_enu(&VehicleState::at_rest(Vec3::ZERO, Quat::IDENTITY));
        let [roll, pitch, yaw] = s.euler_rad();
        assert!(roll.abs() < 1e-6 && pitch.abs() < 1e-6, "{roll} {pitch}");
        assert!((yaw - core::f32::consts::FRAC_PI_2).abs() < 1e-6, "{yaw}");
    }

    #[test]
    fn a_point_above_the_origin_is_up_in_every_frame() {
        let s = NedState::from_enu(&VehicleState::at_rest(
            Vec3::new(1.0, 2.0, 3.0),
            Quat::IDENTITY,
        ));
        assert_eq!(s.position_m, Vec3::new(2.0, 1.0, -3.0));
        let (_, _, alt) = GeoOrigin::DEFAULT.global_int(s.position_m);
        assert_eq!(alt, 491_000);
    }

    proptest! {
        #[test]
        fn vector_maps_round_trip_exactly(v in vec3(100.0)) {
            prop_assert_eq!(enu_from_ned(ned_from_enu(v)), v);
            prop_assert_eq!(flu_from_frd(frd_from_flu(v)), v);
        }

        #[test]
        fn attitude_round_trips_within_1e7(q in unit_quat()) {
            let back = enu_attitude(ned_attitude(q));
            for (a, b) in q.to_array().into_iter().zip(back.to_array()) {
                prop_assert!((a - b).abs() <= 1e-7, "{a} vs {b}");
            }
            // A second round trip changes nothing more than the first did.
            let again = enu_attitude(ned_attitude(back));
            for (a, b) in back.to_array().into_iter().zip(again.to_array()) {
                prop_assert!((a - b).abs() <= 1e-7, "{a} vs {b}");
            }
        }

        #[test]
        fn the_ned_attitude_rotates_frd_vectors_as_the_enu_one_rotates_flu(
            q in unit_quat(),
            v in vec3(10.0),
        ) {
            let enu = q.rotate(v);
            let ned = ned_attitude(q).rotate(frd_from_flu(v));
            let expected = ned_from_enu(enu);
            prop_assert!((ned.x - expected.x).abs() < 1e-4, "{ned:?} vs {expected:?}");
            prop_assert!((ned.y - expected.y).abs() < 1e-4, "{ned:?} vs {expected:?}");
            prop_assert!((ned.z - expected.z).abs() < 1e-4, "{ned:?} vs {expected:?}");
        }

        #[test]
        fn world_rates_agree_in_both_frames(q in unit_quat(), w in vec3(20.0)) {
            let s = VehicleState {
                position_m: Vec3::ZERO,
                velocity_mps: Vec3::ZERO,
                attitude: q,
                body_rates_radps: w,
            };
            let n = NedState::from_enu(&s);
            let enu = s.world_rates_radps();
            let ned = n.attitude.rotate(n.body_rates_radps);
            let expected = ned_from_enu(enu);
            prop_assert!((ned.x - expected.x).abs() < 1e-3);
            prop_assert!((ned.y - expected.y).abs() < 1e-3);
            prop_assert!((ned.z - expected.z).abs() < 1e-3);
        }

        #[test]
        fn state_round_trip_is_exact_but_for_the_attitude(
            q in unit_quat(), p in vec3(30.0), v in vec3(20.0), w in vec3(20.0),
        ) {
            let s = VehicleState { position_m: p, velocity_mps: v, attitude: q, body_rates_radps: w };
            let back = NedState::from_enu(&s).to_enu();
            prop_assert_eq!(back.position_m, p);
            prop_assert_eq!(back.velocity_mps, v);
            prop_assert_eq!(back.body_rates_radps, w);
        }
    }
}
