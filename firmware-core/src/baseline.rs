//! A classical, non-learned racing controller: gate guidance, cascaded position → velocity →
//! attitude → body-rate control, and a mixer to propeller speeds.
//!
//! It is the deployable fallback, the opponent before any policy is trained, and the proof
//! that the track is flyable with the simulated dynamics. One step reads in order:
//! 10 validate, 20 target gate (the same segment test as the referee), 30 guidance (pure
//! pursuit of a carrot on the track's [`Centerline`], on the segment leading to the target
//! gate), 40 velocity → acceleration, 50 thrust vector and tilt limit,
//! 60 attitude error → body-rate set-point, 70 rate loop → torques, 80 mixer → rpm.

use crate::math::{Quat, Vec3};
use crate::track::{Centerline, GateEvent, GateProgress, Track};
use crate::vehicle::{ActionMap, Cf2x, MotorCommand, VehicleState};

/// Tuning and the controller's model of the airframe. Every field has a unit; the defaults
/// are [`BaselineConfig::paper`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BaselineConfig {
    /// Vehicle mass (kg). Default 0.027 (cf2x).
    pub mass_kg: f32,
    /// Principal moments of inertia (kg·m²). Default cf2x.
    pub inertia_kgm2: [f32; 3],
    /// Effective thrust per rpm² (N/rpm²). `paper`: kf / 2 = 1.58e-10 (the paper's simulator
    /// applied half the force); `nominal`: kf = 3.16e-10.
    pub thrust_coeff_n_per_rpm2: f32,
    /// Effective yaw torque per rpm² (N·m/rpm²), scaled as the thrust. `paper`: km / 2.
    pub torque_coeff_nm_per_rpm2: f32,
    /// Arm offset of each propeller along body x and y (m). Default 0.028.
    pub arm_m: f32,
    /// The motors' range: rpm = hover · (1 + gain · a), a ∈ [-1, 1]. Default paper eq. 3.
    pub action_map: ActionMap,
    /// Speed along the racing line (m/s). Default 7.0 (11.9 s laps on `paper`; the sweep
    /// `cargo run --release -p overtake-tests --example baseline_speed_sweep` crashes at 10).
    pub cruise_speed_mps: f32,
    /// Fixed part of the carrot's distance ahead along the centreline (m). Default 1.5.
    pub lookahead_m: f32,
    /// Speed-proportional part of the carrot's distance (s): lookahead = lookahead_m +
    /// lookahead_time_s · cruise. Default 0.35.
    pub lookahead_time_s: f32,
    /// Distance to the carrot → speed gain (1/s); the speed is at most the cruise speed.
    /// Default 1.5.
    pub position_gain_per_s: f32,
    /// Velocity error → acceleration gain (1/s). Default 4.0.
    pub velocity_gain_per_s: f32,
    /// Largest commanded horizontal acceleration (m/s²). Default 8.0.
    pub max_horizontal_accel_mps2: f32,
    /// Largest tilt of the thrust vector from vertical (rad). Default 0.75.
    pub max_tilt_rad: f32,
    /// Attitude error → body-rate gain (1/s). Default 12.0.
    pub attitude_gain_per_s: f32,
    /// Yaw error → yaw-rate gain (1/s). Default 3.0.
    pub yaw_gain_per_s: f32,
    /// Body-rate error → angular acceleration gain (1/s). Default 25.0.
    pub rate_gain_per_s: f32,
    /// Heading held (rad, world yaw of body x). Default 0.
    pub yaw_setpoint_rad: f32,
    /// Offset of the flown line to the left of the centreline (m, horizontal; negative is
    /// right). Default 0. Two baselines on lines 0.5 m apart can overtake without touching.
    pub lateral_offset_m: f32,
}

impl Default for BaselineConfig {
    fn default() -> Self {
        Self::paper()
    }
}

impl BaselineConfig {
    /// Tuned for the `paper` dynamics: half of kf·rpm² (thrust-to-weight ≈ 1.62 at a = 1).
    pub fn paper() -> Self {
        Self {
            thrust_coeff_n_per_rpm2: 0.5 * Cf2x::KF_N_PER_RPM2,
            torque_coeff_nm_per_rpm2: 0.5 * Cf2x::KM_NM_PER_RPM2,
            ..Self::nominal()
        }
    }

    /// Tuned for the `nominal` dynamics: the full kf·rpm² (thrust-to-weight ≈ 3.24).
    pub fn nominal() -> Self {
        Self {
            mass_kg: Cf2x::MASS_KG,
            inertia_kgm2: Cf2x::INERTIA_KGM2,
            thrust_coeff_n_per_rpm2: Cf2x::KF_N_PER_RPM2,
            torque_coeff_nm_per_rpm2: Cf2x::KM_NM_PER_RPM2,
            arm_m: 0.028,
            action_map: ActionMap::PAPER,
            cruise_speed_mps: 7.0,
            lookahead_m: 1.5,
            lookahead_time_s: 0.35,
            position_gain_per_s: 1.5,
            velocity_gain_per_s: 4.0,
            max_horizontal_accel_mps2: 8.0,
            max_tilt_rad: 0.75,
            attitude_gain_per_s: 12.0,
            yaw_gain_per_s: 3.0,
            rate_gain_per_s: 25.0,
            yaw_setpoint_rad: 0.0,
            lateral_offset_m: 0.0,
        }
    }

    /// Propeller speed that holds the vehicle in hover (rpm).
    pub fn hover_rpm(&self) -> f32 {
        libm::sqrtf(self.mass_kg * Cf2x::GRAVITY_MPS2 / (4.0 * self.thrust_coeff_n_per_rpm2))
    }
}

/// Largest offset from a gate's centre the baseline aims its crossing at (m); the opening's
/// half-size is 0.8 m.
pub const GATE_AIM_MARGIN_M: f32 = 0.5;

/// The classical gate-racing controller.
#[derive(Clone, Debug)]
pub struct BaselineController<'t> {
    config: BaselineConfig,
    track: Track<'t>,
    centerline: Centerline,
    progress: GateProgress,
    previous_position: Option<Vec3>,
    fault_count: u32,
}

impl<'t> BaselineController<'t> {
    /// A controller flying `track` from gate 0.
    pub fn new(config: BaselineConfig, track: Track<'t>) -> Self {
        Self {
            config,
            track,
            centerline: Centerline::new(&track),
            progress: GateProgress::targeting(0),
            previous_position: None,
            fault_count: 0,
        }
    }

    /// Starts a new flight targeting `target_gate`.
    pub fn reset(&mut self, target_gate: usize) {
        self.progress = GateProgress::targeting(target_gate % self.track.len().max(1));
        self.previous_position = None;
    }

    /// The gate flown to and the gates passed.
    pub fn progress(&self) -> GateProgress {
        self.progress
    }

    /// Steps that fell back to the fail-safe (non-finite state).
    pub fn fault_count(&self) -> u32 {
        self.fault_count
    }

    /// The configuration.
    pub fn config(&self) -> &BaselineConfig {
        &self.config
    }

    /// One control step. A non-finite state gives [`MotorCommand::STOP`] and counts a fault.
    pub fn step(&mut self, own: &VehicleState) -> (MotorCommand, GateEvent) {
        let c = &self.config;
        // 10 validate
        if !own.is_finite() {
            self.fault_count = self.fault_count.saturating_add(1);
            return (MotorCommand::STOP, GateEvent::None);
        }
        // 20 target gate
        let event = match self.previous_position {
            Some(from) => self.progress.advance(&self.track, from, own.position_m),
            None => GateEvent::None,
        };
        self.previous_position = Some(own.position_m);

        // 30 guidance: pure pursuit on the centreline segment that ends at the target gate.
        let n = self.track.len();
        let segment = (self.progress.target + n - 1) % n;
        let s = self.centerline.nearest_on_segment(segment, own.position_m);
        let speed_along = self.centerline.tangent(s).norm().max(1e-3);
        let lookahead_m = c.lookahead_m + c.lookahead_time_s * c.cruise_speed_mps;
        let carrot_s = s + lookahead_m / speed_along;
        let mut carrot = self.centerline.point(carrot_s);
        if c.lateral_offset_m != 0.0 {
            let t = self.centerline.tangent(carrot_s);
            let left = Vec3::new(-t.y, t.x, 0.0);
            carrot += left.scale(c.lateral_offset_m / left.norm().max(1e-3));
        }
        // Aim through the opening: when the straight line to the carrot crosses the target
        // gate's plane more than `GATE_AIM_MARGIN_M` off centre (the drone started off the
        // line, e.g. at the stage-2 spawn before g0 or g3, whose headings differ from the
        // spline's), the carrot is moved sideways until the crossing is at that margin.
        let gate = self.track.gate(self.progress.target);
        let (a, mut b) = (
            gate.to_gate_frame(own.position_m),
            gate.to_gate_frame(carrot),
        );
        if a.x < 0.0 && b.x > 0.0 {
            let t = a.x / (a.x - b.x);
            let aim = |from: f32, to: f32| {
                let cross = from + t * (to - from);
                let clamped = cross.clamp(-GATE_AIM_MARGIN_M, GATE_AIM_MARGIN_M);
                from + (clamped - from) / t
            };
            b.y = aim(a.y, b.y);
            b.z = aim(a.z, b.z);
            carrot = gate.to_world_frame(b);
        }
        let to_carrot = carrot - own.position_m;
        let distance = to_carrot.norm().max(1e-3);
        // Cruise speed toward the carrot, slowing only when the carrot is closer than the
        // lookahead (after a respawn or near the end of a segment).
        let speed = c
            .cruise_speed_mps
            .min(c.position_gain_per_s * distance.max(lookahead_m));
        let velocity_sp = to_carrot.scale(speed / distance);

        // 40 velocity → acceleration
        let mut accel = (velocity_sp - own.velocity_mps).scale(c.velocity_gain_per_s);
        let horizontal = Vec3::new(accel.x, accel.y, 0.0).limit_norm(c.max_horizontal_accel_mps2);
        accel = Vec3::new(
            horizontal.x,
            horizontal.y,
            accel.z.clamp(-0.8 * Cf2x::GRAVITY_MPS2, 8.0),
        );

        // 50 thrust vector with a tilt limit
        let mut thrust = accel + Vec3::new(0.0, 0.0, Cf2x::GRAVITY_MPS2);
        thrust.z = thrust.z.max(0.2 * Cf2x::GRAVITY_MPS2);
        let tilt_tan = libm::tanf(c.max_tilt_rad);
        let lateral = Vec3::new(thrust.x, thrust.y, 0.0).limit_norm(thrust.z * tilt_tan);
        let thrust = Vec3::new(lateral.x, lateral.y, thrust.z);
        let thrust_norm = thrust.norm();
        let z_sp = thrust.scale(1.0 / thrust_norm);

        // 60 attitude: tilt the body z onto z_sp after yawing to the set-point.
        let tilt = shortest_arc(Vec3::Z, z_sp);
        let attitude_sp = tilt * Quat::from_yaw(c.yaw_setpoint_rad);
        let mut err = own.attitude.conjugate() * attitude_sp;
        if err.w < 0.0 {
            err = Quat::new(-err.w, -err.x, -err.y, -err.z);
        }
        let rate_sp = Vec3::new(
            2.0 * c.attitude_gain_per_s * err.x,
            2.0 * c.attitude_gain_per_s * err.y,
            2.0 * c.yaw_gain_per_s * err.z,
        );

        // 70 rate loop → torques (N·m), with the gyroscopic term.
        let w = own.body_rates_radps;
        let j = Vec3::from_array(c.inertia_kgm2);
        let alpha = (rate_sp - w).scale(c.rate_gain_per_s);
        let jw = Vec3::new(j.x * w.x, j.y * w.y, j.z * w.z);
        let torque = Vec3::new(j.x * alpha.x, j.y * alpha.y, j.z * alpha.z) + w.cross(jw);

        // Collective thrust (N) along the current body z.
        let body_z = own.attitude.rotate(Vec3::Z);
        let collective = (c.mass_kg * thrust_norm * z_sp.dot(body_z)).max(0.0);

        // 80 mixer
        (mix(c, collective, torque), event)
    }
}

/// The unit quaternion rotating unit vector `from` onto unit vector `to` by the shortest arc.
fn shortest_arc(from: Vec3, to: Vec3) -> Quat {
    let axis = from.cross(to);
    Quat::new(1.0 + from.dot(to), axis.x, axis.y, axis.z).normalized()
}

/// Propeller forces for a collective thrust (N) and body torques (N·m), as rpm within the
/// motors' range. Propellers at (±arm, ±arm) in the order of [`Cf2x::PROPELLER_POSITIONS_M`]:
/// τx = arm (−f0 − f1 + f2 + f3), τy = arm (−f0 + f1 + f2 − f3), τz = k Σ sᵢ fᵢ with
/// k = torque / thrust coefficient.
fn mix(c: &BaselineConfig, collective_n: f32, torque: Vec3) -> MotorCommand {
    let k = c.torque_coeff_nm_per_rpm2 / c.thrust_coeff_n_per_rpm2;
    let t = collective_n / 4.0;
    let x = torque.x / (4.0 * c.arm_m);
    let y = torque.y / (4.0 * c.arm_m);
    let z = torque.z / (4.0 * k);
    let forces = [t - x - y - z, t - x + y + z, t + x + y - z, t + x - y + z];
    let lo = c.action_map.rpm(-1.0);
    let hi = c.action_map.rpm(1.0);
    MotorCommand {
        rpm: forces.map(|f| libm::sqrtf(f.max(0.0) / c.thrust_coeff_n_per_rpm2).clamp(lo, hi)),
    }
}
