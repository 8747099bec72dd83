//! The vehicle: its state as a controller sees it, the Crazyflie 2.x ("cf2x") airframe
//! constants, and the map from policy actions to propeller speeds (paper eq. 3).

use crate::math::{Quat, Vec3};
use serde::{Deserialize, Serialize};

/// The control period of the paper (50 Hz), in ns.
pub const PAPER_CONTROL_PERIOD_NS: u32 = 20_000_000;

/// The state of one quadrotor, as a controller receives it (world frame z up).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VehicleState {
    /// Position of the centre of mass (m, world frame).
    pub position_m: Vec3,
    /// Attitude: unit quaternion (w, x, y, z) mapping body vectors to the world frame.
    /// Body frame: x forward, y left, z up.
    pub attitude: Quat,
    /// Linear velocity (m/s, world frame).
    pub velocity_mps: Vec3,
    /// Angular velocity (rad/s, body frame).
    pub body_rates_radps: Vec3,
}

impl VehicleState {
    /// At rest at `position_m` with attitude `attitude`.
    pub fn at_rest(position_m: Vec3, attitude: Quat) -> Self {
        Self {
            position_m,
            attitude,
            velocity_mps: Vec3::ZERO,
            body_rates_radps: Vec3::ZERO,
        }
    }

    /// True when every field is finite (a NaN or infinity anywhere makes it false).
    pub fn is_finite(&self) -> bool {
        self.position_m.is_finite()
            && self.attitude.is_finite()
            && self.velocity_mps.is_finite()
            && self.body_rates_radps.is_finite()
    }

    /// Angular velocity in the world frame (rad/s).
    pub fn world_rates_radps(&self) -> Vec3 {
        self.attitude.rotate(self.body_rates_radps)
    }
}

/// Propeller speeds for motors 0..3 (rpm), in the order of [`Cf2x::PROPELLER_POSITIONS_M`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MotorCommand {
    /// Commanded propeller speed per motor (rpm, >= 0).
    pub rpm: [f32; 4],
}

impl MotorCommand {
    /// All motors stopped: the controller's fail-safe command.
    pub const STOP: Self = Self { rpm: [0.0; 4] };
}

/// The Crazyflie 2.x airframe of the paper (Genesis / gym-pybullet-drones "cf2x").
///
/// These are the nominal physical constants; the simulator's presets (in `sitl`) build on them.
pub struct Cf2x;

impl Cf2x {
    /// Mass (kg).
    pub const MASS_KG: f32 = 0.027;
    /// Principal moments of inertia (kg·m²), body x, y, z.
    pub const INERTIA_KGM2: [f32; 3] = [1.4e-5, 1.4e-5, 2.17e-5];
    /// Thrust coefficient: propeller force f = kf·rpm² (N/rpm²) along body +z.
    pub const KF_N_PER_RPM2: f32 = 3.16e-10;
    /// Yaw-torque coefficient: τz = km·Σ sᵢ·rpmᵢ² (N·m/rpm²).
    pub const KM_NM_PER_RPM2: f32 = 7.94e-12;
    /// Propeller positions (x, y) in the body frame (m): front-right, back-right, back-left,
    /// front-left.
    pub const PROPELLER_POSITIONS_M: [[f32; 2]; 4] = [
        [0.028, -0.028],
        [-0.028, -0.028],
        [-0.028, 0.028],
        [0.028, 0.028],
    ];
    /// Spin sign sᵢ of each propeller in the yaw torque.
    pub const SPIN_SIGNS: [f32; 4] = [-1.0, 1.0, -1.0, 1.0];
    /// Gravity (m/s²).
    pub const GRAVITY_MPS2: f32 = 9.81;
}

/// The affine map from a policy action a ∈ [-1, 1] to propeller speed:
/// `rpm = hover_rpm · (1 + gain · clip(a, -1, 1))` (paper eq. 3: 14468.429, 0.8).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActionMap {
    /// Propeller speed at a = 0 (rpm). Paper: 14468.429 (the name "hover" is the paper's;
    /// with the `paper` dynamics the real hover is at a ≈ +0.52).
    pub hover_rpm: f32,
    /// Relative gain of the action (dimensionless). Paper: 0.8.
    pub gain: f32,
}

impl Default for ActionMap {
    fn default() -> Self {
        Self::PAPER
    }
}

impl ActionMap {
    /// Paper eq. 3.
    pub const PAPER: Self = Self {
        hover_rpm: 14468.429,
        gain: 0.8,
    };

    /// Propeller speed (rpm) for one action component, clipped to [-1, 1] first. A NaN
    /// action maps to `hover_rpm` (a = 0), never to NaN.
    pub fn rpm(&self, action: f32) -> f32 {
        let a = if action.is_nan() {
            0.0
        } else {
            action.clamp(-1.0, 1.0)
        };
        self.hover_rpm * (1.0 + self.gain * a)
    }

    /// Maps four actions to a motor command.
    pub fn command(&self, action: &[f32; 4]) -> MotorCommand {
        MotorCommand {
            rpm: action.map(|a| self.rpm(a)),
        }
    }

    /// The action (unclipped) that gives `rpm`.
    pub fn action_for_rpm(&self, rpm: f32) -> f32 {
        (rpm / self.hover_rpm - 1.0) / self.gain
    }

    /// True when both numbers are finite and positive.
    pub fn is_valid(&self) -> bool {
        self.hover_rpm.is_finite()
            && self.hover_rpm > 0.0
            && self.gain.is_finite()
            && self.gain > 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn action_map_is_paper_eq_3_with_clipping() {
        let m = ActionMap::PAPER;
        assert_eq!(m.rpm(0.0), 14468.429);
        assert!((m.rpm(1.0) - 14468.429 * 1.8).abs() < 1e-2);
        assert!((m.rpm(-1.0) - 14468.429 * 0.2).abs() < 1e-2);
        // Out-of-range actions are clipped, a NaN action is a = 0, never a NaN rpm.
        assert_eq!(m.rpm(7.0), m.rpm(1.0));
        assert_eq!(m.rpm(-7.0), m.rpm(-1.0));
        assert_eq!(m.rpm(f32::NAN), m.hover_rpm);
        assert!((m.action_for_rpm(m.rpm(0.37)) - 0.37).abs() < 1e-6);
        assert_eq!(
            m.command(&[2.0, -2.0, 0.0, f32::NAN]).rpm,
            [m.rpm(1.0), m.rpm(-1.0), m.hover_rpm, m.hover_rpm]
        );
    }

    #[test]
    fn action_map_validity() {
        assert!(ActionMap::PAPER.is_valid());
        assert!(
            !ActionMap {
                hover_rpm: 0.0,
                gain: 0.8
            }
            .is_valid()
        );
        assert!(
            !ActionMap {
                hover_rpm: 1.0,
                gain: f32::INFINITY
            }
            .is_valid()
        );
    }

    #[test]
    fn state_finiteness_and_world_rates() {
        let mut s = VehicleState::at_rest(
            Vec3::new(1.0, 2.0, 3.0),
            Quat::from_yaw(core::f32::consts::FRAC_PI_2),
        );
        assert!(s.is_finite());
        s.body_rates_radps = Vec3::X;
        // Yawed 90°: body x is world y.
        assert!((s.world_rates_radps() - Vec3::Y).norm() < 1e-6);
        s.attitude.z = f32::NAN;
        assert!(!s.is_finite());
    }
}
