//! cf2x rigid-body dynamics (docs/DESIGN.md "Vehicle" and "Presets").
//!
//! Forces act at the four propeller positions along body +z (fᵢ = thrust_scale · kf · rpmᵢ²),
//! the yaw torque is thrust_scale · km · Σ sᵢ rpmᵢ², gravity pulls along world −z. The state
//! is integrated with `substeps` classical RK4 steps per control period; the attitude
//! quaternion is re-normalised after every substep.
//!
//! **Integrator error** (`cargo test --release -p overtake-tests --test integrator_error -- --nocapture`):
//! against a float64 RK4 of the same equations with 1,024 substeps per 20 ms, this f32
//! integrator ends
//!
//! | manoeuvre | 1 substep | 2 (default) | 4 (`realistic`) | 8 |
//! |---|---|---|---|---|
//! | racing: 2 s, ±1,500 rpm differential, 9.9 rad/s peak, 11 m | 1.6e-5 m, 5.9e-6 rad | 6.4e-6 m, 2.0e-6 rad | 1.6e-5 m, 1.7e-6 rad | 3.0e-5 m, 1.4e-5 rad |
//! | full authority: 1 s of random a = ±1 per motor, 47 rad/s peak | 3.0e-4 m, 1.8e-3 rad | 2.0e-5 m, 1.3e-4 rad | 1.6e-6 m, 1.1e-5 rad | 1.5e-6 m, 4.9e-6 rad |
//!
//! At racing rates RK4's truncation error is below f32 rounding from one substep on (more
//! substeps only add rounding); at the full-authority rates of an untrained policy one
//! substep loses 2 mrad per second. Two substeps keep both cases within 2e-5 m and 1.3e-4 rad
//! at half the cost of four; `realistic` uses four because the motor speed is held over a
//! substep (5 ms against its 30 ms motor lag).
//!
//! **Cost.** The propeller forces are computed once per substep (the rpm is held over it) and
//! thrust is rotated with the third column of the attitude matrix only; see
//! `docs/PERFORMANCE.md` for the env-step rate.

use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::{Cf2x, MotorCommand, VehicleState};

/// Physical parameters of one airframe and its simulation. Every field has a unit and a
/// default ([`Preset::paper`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Preset {
    /// Name of the preset ("paper", "nominal", "realistic").
    pub name: &'static str,
    /// Mass (kg). Default 0.027.
    pub mass_kg: f32,
    /// Principal moments of inertia (kg·m²). Default (1.4e-5, 1.4e-5, 2.17e-5).
    pub inertia_kgm2: [f32; 3],
    /// Thrust coefficient kf (N/rpm²). Default 3.16e-10.
    pub kf_n_per_rpm2: f32,
    /// Yaw-torque coefficient km (N·m/rpm²). Default 7.94e-12.
    pub km_nm_per_rpm2: f32,
    /// Fraction of kf·rpm² (and km·rpm²) that acts (dimensionless). `paper`: 0.5, the
    /// paper's simulator applied the propeller force on one of its two substeps; else 1.
    pub thrust_scale: f32,
    /// Largest propeller speed (rpm); commands above are clipped. Default: no limit (∞).
    pub max_rpm: f32,
    /// First-order motor time constant (s); 0 means the commanded speed acts at once.
    /// Default 0.
    pub motor_time_constant_s: f32,
    /// Linear drag, force per velocity and mass (1/s), applied as −drag·m·v. Default 0.
    pub linear_drag_per_s: f32,
    /// Gravity (m/s²). Default 9.81.
    pub gravity_mps2: f32,
    /// RK4 substeps per control period. Default 2 (`realistic`: 4, to resolve its motor lag).
    pub substeps: u32,
}

/// The dynamics presets by name ([`Preset`] holds their parameters).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PresetName {
    /// The paper's effective dynamics (half the propeller force, as its simulator).
    #[default]
    Paper,
    /// The full propeller force, no drag, no motor lag.
    Nominal,
    /// Nominal force, limited rpm, a 30 ms motor lag and linear drag.
    Realistic,
}

impl PresetName {
    /// Every preset, in the order the docs list them.
    pub const ALL: [Self; 3] = [Self::Paper, Self::Nominal, Self::Realistic];

    /// The preset's parameters.
    pub fn preset(self) -> Preset {
        match self {
            Self::Paper => Preset::paper(),
            Self::Nominal => Preset::nominal(),
            Self::Realistic => Preset::realistic(),
        }
    }

    /// Its name as configs and flags write it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Nominal => "nominal",
            Self::Realistic => "realistic",
        }
    }
}

impl core::str::FromStr for PresetName {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("unknown preset '{s}' (paper, nominal, realistic)"))
    }
}

impl Default for Preset {
    fn default() -> Self {
        Self::paper()
    }
}

impl Preset {
    /// The paper's effective dynamics: half of kf·rpm² (hover at a ≈ +0.52, thrust-to-weight
    /// ≈ 1.62 at a = 1), no drag, no motor lag.
    pub fn paper() -> Self {
        Self {
            name: "paper",
            thrust_scale: 0.5,
            ..Self::nominal()
        }
    }

    /// The full kf·rpm² (thrust-to-weight 3.24 at a = 1), no drag, no motor lag.
    pub fn nominal() -> Self {
        Self {
            name: "nominal",
            mass_kg: Cf2x::MASS_KG,
            inertia_kgm2: Cf2x::INERTIA_KGM2,
            kf_n_per_rpm2: Cf2x::KF_N_PER_RPM2,
            km_nm_per_rpm2: Cf2x::KM_NM_PER_RPM2,
            thrust_scale: 1.0,
            max_rpm: f32::INFINITY,
            motor_time_constant_s: 0.0,
            linear_drag_per_s: 0.0,
            gravity_mps2: Cf2x::GRAVITY_MPS2,
            substeps: 2,
        }
    }

    /// Nominal force with the rpm limited to 21,702 (thrust-to-weight 2.25), a 30 ms motor
    /// lag and 0.1 /s linear drag.
    pub fn realistic() -> Self {
        Self {
            name: "realistic",
            max_rpm: 21_702.0,
            motor_time_constant_s: 0.03,
            // The motor speed is held over a substep: 5 ms against the 30 ms time constant.
            substeps: 4,
            linear_drag_per_s: 0.1,
            ..Self::nominal()
        }
    }

    /// The preset called `name` ([`PresetName`]).
    pub fn by_name(name: &str) -> Option<Self> {
        name.parse::<PresetName>().ok().map(PresetName::preset)
    }

    /// Propeller speed that holds hover (rpm).
    pub fn hover_rpm(&self) -> f32 {
        libm::sqrtf(
            self.mass_kg * self.gravity_mps2 / (4.0 * self.thrust_scale * self.kf_n_per_rpm2),
        )
    }
}

/// A simulated drone: its kinematic state and its propellers' actual speeds.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Body {
    /// Position, attitude, velocity and body rates.
    pub state: VehicleState,
    /// Actual propeller speeds (rpm); equal to the command without motor lag.
    pub rpm: [f32; 4],
}

#[derive(Clone, Copy)]
struct Derivative {
    velocity: Vec3,
    attitude: Quat,
    accel: Vec3,
    angular_accel: Vec3,
}

/// What stays fixed during one substep: the propeller forces (the rpm is held over the
/// substep) and the preset's constants, with the divisions done once.
#[derive(Clone, Copy)]
struct Forces {
    /// Total thrust over mass (m/s², along body +z).
    thrust_per_mass: f32,
    /// Propeller torque (N·m, body frame).
    torque: Vec3,
    inertia: Vec3,
    inv_inertia: Vec3,
    drag_per_s: f32,
    gravity_mps2: f32,
}

impl Forces {
    fn new(p: &Preset, rpm: &[f32; 4]) -> Self {
        let mut force_z = 0.0;
        let mut torque = Vec3::ZERO;
        let kf = p.thrust_scale * p.kf_n_per_rpm2;
        let km = p.thrust_scale * p.km_nm_per_rpm2;
        for ((r, pos), spin) in rpm
            .iter()
            .zip(Cf2x::PROPELLER_POSITIONS_M)
            .zip(Cf2x::SPIN_SIGNS)
        {
            let r2 = r * r;
            let f = kf * r2;
            force_z += f;
            // τ = p × (0, 0, f) = (y f, −x f, 0)
            torque += Vec3::new(pos[1] * f, -pos[0] * f, spin * km * r2);
        }
        let j = Vec3::from_array(p.inertia_kgm2);
        Self {
            thrust_per_mass: force_z / p.mass_kg,
            torque,
            inertia: j,
            inv_inertia: Vec3::new(1.0 / j.x, 1.0 / j.y, 1.0 / j.z),
            drag_per_s: p.linear_drag_per_s,
            gravity_mps2: p.gravity_mps2,
        }
    }
}

fn derivative(f: &Forces, s: &VehicleState) -> Derivative {
    let q = s.attitude;
    // R e_z: the third column of the rotation matrix of q.
    let body_z = Vec3::new(
        2.0 * (q.x * q.z + q.w * q.y),
        2.0 * (q.y * q.z - q.w * q.x),
        1.0 - 2.0 * (q.x * q.x + q.y * q.y),
    );
    let accel = body_z.scale(f.thrust_per_mass) - s.velocity_mps.scale(f.drag_per_s)
        + Vec3::new(0.0, 0.0, -f.gravity_mps2);
    let w = s.body_rates_radps;
    let j = f.inertia;
    let jw = Vec3::new(j.x * w.x, j.y * w.y, j.z * w.z);
    let net = f.torque - w.cross(jw);
    let ji = f.inv_inertia;
    let angular_accel = Vec3::new(net.x * ji.x, net.y * ji.y, net.z * ji.z);
    // q̇ = ½ q ⊗ (0, ω)
    let qd = q * Quat::new(0.0, w.x, w.y, w.z);
    Derivative {
        velocity: s.velocity_mps,
        attitude: Quat::new(0.5 * qd.w, 0.5 * qd.x, 0.5 * qd.y, 0.5 * qd.z),
        accel,
        angular_accel,
    }
}

fn advance(s: &VehicleState, d: &Derivative, h: f32) -> VehicleState {
    let q = s.attitude;
    VehicleState {
        position_m: s.position_m + d.velocity.scale(h),
        attitude: Quat::new(
            q.w + h * d.attitude.w,
            q.x + h * d.attitude.x,
            q.y + h * d.attitude.y,
            q.z + h * d.attitude.z,
        ),
        velocity_mps: s.velocity_mps + d.accel.scale(h),
        body_rates_radps: s.body_rates_radps + d.angular_accel.scale(h),
    }
}

impl Body {
    /// A drone at rest in `state`, propellers stopped.
    pub fn new(state: VehicleState) -> Self {
        Self {
            state,
            rpm: [0.0; 4],
        }
    }

    /// Advances by `dt_s` under `command` with `preset.substeps` RK4 substeps.
    pub fn step(&mut self, preset: &Preset, command: &MotorCommand, dt_s: f32) {
        let n = preset.substeps.max(1);
        let h = dt_s / n as f32;
        let target = command.rpm.map(|r| {
            if r.is_finite() {
                r.clamp(0.0, preset.max_rpm)
            } else {
                0.0
            }
        });
        let alpha = if preset.motor_time_constant_s > 0.0 {
            1.0 - libm::expf(-h / preset.motor_time_constant_s)
        } else {
            1.0
        };
        for _ in 0..n {
            if alpha < 1.0 {
                for (r, t) in self.rpm.iter_mut().zip(target) {
                    *r += alpha * (t - *r);
                }
            } else {
                self.rpm = target;
            }
            let s = self.state;
            let f = Forces::new(preset, &self.rpm);
            let k1 = derivative(&f, &s);
            let k2 = derivative(&f, &advance(&s, &k1, 0.5 * h));
            let k3 = derivative(&f, &advance(&s, &k2, 0.5 * h));
            let k4 = derivative(&f, &advance(&s, &k3, h));
            let sum = |f: fn(&Derivative) -> [f32; 4]| {
                let (a, b, c, d) = (f(&k1), f(&k2), f(&k3), f(&k4));
                core::array::from_fn::<f32, 4, _>(|i| (a[i] + 2.0 * b[i] + 2.0 * c[i] + d[i]) / 6.0)
            };
            let v = sum(|d| [d.velocity.x, d.velocity.y, d.velocity.z, 0.0]);
            let q = sum(|d| d.attitude.to_array());
            let a = sum(|d| [d.accel.x, d.accel.y, d.accel.z, 0.0]);
            let w = sum(|d| [d.angular_accel.x, d.angular_accel.y, d.angular_accel.z, 0.0]);
            let mean = Derivative {
                velocity: Vec3::new(v[0], v[1], v[2]),
                attitude: Quat::new(q[0], q[1], q[2], q[3]),
                accel: Vec3::new(a[0], a[1], a[2]),
                angular_accel: Vec3::new(w[0], w[1], w[2]),
            };
            let mut next = advance(&s, &mean, h);
            next.attitude = next.attitude.normalized();
            self.state = next;
        }
    }
}
