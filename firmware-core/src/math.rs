//! Small fixed-size 3-vector and quaternion types (f32), enough for frames and attitude.
//!
//! Conventions: right-handed frames, world z up; quaternions are Hamilton, stored
//! (w, x, y, z), and a unit quaternion `q` maps body-frame vectors to the world frame:
//! `v_world = q.rotate(v_body)`. All transcendental math goes through `libm` so the host
//! and the microcontroller compute the same bits.

use core::ops::{Add, AddAssign, Mul, Neg, Sub};
use serde::{Deserialize, Serialize};

/// A 3-vector of `f32` (units given where it is used).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vec3 {
    /// x component.
    pub x: f32,
    /// y component.
    pub y: f32,
    /// z component.
    pub z: f32,
}

impl Vec3 {
    /// The zero vector.
    pub const ZERO: Self = Self::new(0.0, 0.0, 0.0);
    /// Unit x.
    pub const X: Self = Self::new(1.0, 0.0, 0.0);
    /// Unit y.
    pub const Y: Self = Self::new(0.0, 1.0, 0.0);
    /// Unit z.
    pub const Z: Self = Self::new(0.0, 0.0, 1.0);

    /// Builds a vector from its components.
    pub const fn new(x: f32, y: f32, z: f32) -> Self {
        Self { x, y, z }
    }

    /// Components as an array `[x, y, z]`.
    pub const fn to_array(self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }

    /// Builds a vector from `[x, y, z]`.
    pub const fn from_array(a: [f32; 3]) -> Self {
        Self::new(a[0], a[1], a[2])
    }

    /// Dot product.
    pub fn dot(self, o: Self) -> f32 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    /// Cross product `self × o`.
    pub fn cross(self, o: Self) -> Self {
        Self::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }

    /// Euclidean norm.
    pub fn norm(self) -> f32 {
        libm::sqrtf(self.dot(self))
    }

    /// Multiplies every component by `s`.
    pub fn scale(self, s: f32) -> Self {
        Self::new(self.x * s, self.y * s, self.z * s)
    }

    /// Component-wise clamp to `[-limit, limit]`.
    pub fn clamp_abs(self, limit: f32) -> Self {
        Self::new(
            self.x.clamp(-limit, limit),
            self.y.clamp(-limit, limit),
            self.z.clamp(-limit, limit),
        )
    }

    /// The vector scaled down so its norm is at most `max_norm` (direction kept).
    pub fn limit_norm(self, max_norm: f32) -> Self {
        let n = self.norm();
        if n > max_norm && n > 0.0 {
            self.scale(max_norm / n)
        } else {
            self
        }
    }

    /// True when every component is finite.
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }

    /// Linear interpolation `self + t (o - self)`.
    pub fn lerp(self, o: Self, t: f32) -> Self {
        self + (o - self).scale(t)
    }
}

impl Add for Vec3 {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl AddAssign for Vec3 {
    fn add_assign(&mut self, o: Self) {
        *self = *self + o;
    }
}

impl Sub for Vec3 {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

impl Neg for Vec3 {
    type Output = Self;
    fn neg(self) -> Self {
        Self::new(-self.x, -self.y, -self.z)
    }
}

impl Mul<f32> for Vec3 {
    type Output = Self;
    fn mul(self, s: f32) -> Self {
        self.scale(s)
    }
}

/// A quaternion (w, x, y, z), Hamilton convention. Attitudes are unit quaternions that map
/// body-frame vectors to the world frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quat {
    /// Scalar part.
    pub w: f32,
    /// Vector part, x.
    pub x: f32,
    /// Vector part, y.
    pub y: f32,
    /// Vector part, z.
    pub z: f32,
}

impl Default for Quat {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Quat {
    /// The identity rotation.
    pub const IDENTITY: Self = Self::new(1.0, 0.0, 0.0, 0.0);

    /// Builds a quaternion from (w, x, y, z) without normalising it.
    pub const fn new(w: f32, x: f32, y: f32, z: f32) -> Self {
        Self { w, x, y, z }
    }

    /// Components as `[w, x, y, z]`.
    pub const fn to_array(self) -> [f32; 4] {
        [self.w, self.x, self.y, self.z]
    }

    /// Rotation of `angle_rad` about the unit axis `axis`.
    pub fn from_axis_angle(axis: Vec3, angle_rad: f32) -> Self {
        let (s, c) = libm::sincosf(0.5 * angle_rad);
        Self::new(c, axis.x * s, axis.y * s, axis.z * s)
    }

    /// Rotation about world z by `yaw_rad`.
    pub fn from_yaw(yaw_rad: f32) -> Self {
        Self::from_axis_angle(Vec3::Z, yaw_rad)
    }

    /// The vector part.
    pub const fn vector(self) -> Vec3 {
        Vec3::new(self.x, self.y, self.z)
    }

    /// Squared norm.
    pub fn norm_squared(self) -> f32 {
        self.w * self.w + self.x * self.x + self.y * self.y + self.z * self.z
    }

    /// The unit quaternion in the same direction; the identity if the norm is zero or not
    /// finite.
    pub fn normalized(self) -> Self {
        let n = libm::sqrtf(self.norm_squared());
        if n > 0.0 && n.is_finite() {
            Self::new(self.w / n, self.x / n, self.y / n, self.z / n)
        } else {
            Self::IDENTITY
        }
    }

    /// The conjugate, which is the inverse of a unit quaternion.
    pub const fn conjugate(self) -> Self {
        Self::new(self.w, -self.x, -self.y, -self.z)
    }

    /// Rotates `v` by this unit quaternion: body → world for an attitude (`R v`).
    pub fn rotate(self, v: Vec3) -> Vec3 {
        // v' = v + 2 u × (u × v + w v), u the vector part.
        let u = self.vector();
        let t = u.cross(v).scale(2.0);
        v + t.scale(self.w) + u.cross(t)
    }

    /// Rotates `v` by the inverse of this unit quaternion: world → body (`Rᵀ v`).
    pub fn inverse_rotate(self, v: Vec3) -> Vec3 {
        self.conjugate().rotate(v)
    }

    /// True when every component is finite.
    pub fn is_finite(self) -> bool {
        self.w.is_finite() && self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }

    /// Yaw (rotation about world z) of the body x axis, rad in (-π, π].
    pub fn heading_rad(self) -> f32 {
        let x = self.rotate(Vec3::X);
        libm::atan2f(x.y, x.x)
    }
}

impl Mul for Quat {
    type Output = Self;
    /// Hamilton product `self ⊗ o` (apply `o` first, then `self`).
    fn mul(self, o: Self) -> Self {
        Self::new(
            self.w * o.w - self.x * o.x - self.y * o.y - self.z * o.z,
            self.w * o.x + self.x * o.w + self.y * o.z - self.z * o.y,
            self.w * o.y - self.x * o.z + self.y * o.w + self.z * o.x,
            self.w * o.z + self.x * o.y - self.y * o.x + self.z * o.w,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit_quat() -> impl Strategy<Value = Quat> {
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0)
            .prop_filter("non-degenerate", |(w, x, y, z)| {
                w * w + x * x + y * y + z * z > 0.01
            })
            .prop_map(|(w, x, y, z)| Quat::new(w, x, y, z).normalized())
    }

    fn vec3() -> impl Strategy<Value = Vec3> {
        (-50.0f32..50.0, -50.0f32..50.0, -50.0f32..50.0).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
        (a - b).norm() <= tol * (1.0 + a.norm().max(b.norm()))
    }

    proptest! {
        #[test]
        fn rotate_then_inverse_is_identity(q in unit_quat(), v in vec3()) {
            prop_assert!(close(q.inverse_rotate(q.rotate(v)), v, 1e-5));
            prop_assert!(close(q.rotate(q.inverse_rotate(v)), v, 1e-5));
        }

        #[test]
        fn rotation_preserves_length(q in unit_quat(), v in vec3()) {
            prop_assert!((q.rotate(v).norm() - v.norm()).abs() <= 1e-5 * (1.0 + v.norm()));
        }

        #[test]
        fn product_composes_rotations(a in unit_quat(), b in unit_quat(), v in vec3()) {
            prop_assert!(close((a * b).rotate(v), a.rotate(b.rotate(v)), 1e-5));
        }

        #[test]
        fn conjugate_is_inverse(q in unit_quat()) {
            let p = q * q.conjugate();
            prop_assert!((p.w - 1.0).abs() < 1e-5 && p.vector().norm() < 1e-5);
        }

        #[test]
        fn q_and_minus_q_are_the_same_rotation(q in unit_quat(), v in vec3()) {
            let m = Quat::new(-q.w, -q.x, -q.y, -q.z);
            prop_assert!(close(q.rotate(v), m.rotate(v), 1e-5));
        }

        #[test]
        fn yaw_round_trips_through_heading(yaw in -3.1f32..3.1) {
            prop_assert!((Quat::from_yaw(yaw).heading_rad() - yaw).abs() < 1e-5);
        }
    }

    #[test]
    fn rotate_matches_right_hand_rule() {
        // +90° about z takes x to y.
        let q = Quat::from_axis_angle(Vec3::Z, core::f32::consts::FRAC_PI_2);
        assert!(close(q.rotate(Vec3::X), Vec3::Y, 1e-6));
    }

    #[test]
    fn normalizing_garbage_gives_identity() {
        assert_eq!(Quat::new(0.0, 0.0, 0.0, 0.0).normalized(), Quat::IDENTITY);
        assert_eq!(
            Quat::new(f32::NAN, 0.0, 0.0, 0.0).normalized(),
            Quat::IDENTITY
        );
    }
}
