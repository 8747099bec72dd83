//! The f32 cf2x integrator of `sitl` against a float64 RK4 of the same equations: the
//! integrator error that `sitl/src/dynamics.rs` documents.

use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use overtake_tests::reference::rotation;
use sitl::dynamics::{Body, Preset};

fn at_rest() -> Body {
    Body::new(VehicleState::at_rest(
        Vec3::new(0.0, 0.0, 1.0),
        Quat::IDENTITY,
    ))
}

/// A float64 RK4 of the same equations with 1,024 substeps per 20 ms: the fine reference.
fn reference_flight(commands: &[[f32; 4]]) -> ([f64; 3], [f64; 4]) {
    let p = Preset::paper();
    let (m, g) = (f64::from(p.mass_kg), f64::from(p.gravity_mps2));
    let j = p.inertia_kgm2.map(f64::from);
    let kf = f64::from(p.thrust_scale) * f64::from(p.kf_n_per_rpm2);
    let km = f64::from(p.thrust_scale) * f64::from(p.km_nm_per_rpm2);
    let arms = firmware_core::Cf2x::PROPELLER_POSITIONS_M.map(|a| a.map(f64::from));
    let spins = firmware_core::Cf2x::SPIN_SIGNS.map(f64::from);
    // state: p(3) v(3) q(4) w(3)
    type S = [f64; 13];
    let deriv = |s: &S, rpm: &[f64; 4]| -> S {
        let (q, w) = ([s[6], s[7], s[8], s[9]], [s[10], s[11], s[12]]);
        let r = rotation(q);
        let f: f64 = rpm.iter().map(|x| kf * x * x).sum();
        let mut tau = [0.0; 3];
        for i in 0..4 {
            let fi = kf * rpm[i] * rpm[i];
            tau[0] += arms[i][1] * fi;
            tau[1] -= arms[i][0] * fi;
            tau[2] += spins[i] * km * rpm[i] * rpm[i];
        }
        let jw = [j[0] * w[0], j[1] * w[1], j[2] * w[2]];
        let gyro = [
            w[1] * jw[2] - w[2] * jw[1],
            w[2] * jw[0] - w[0] * jw[2],
            w[0] * jw[1] - w[1] * jw[0],
        ];
        let qd = [
            0.5 * (-q[1] * w[0] - q[2] * w[1] - q[3] * w[2]),
            0.5 * (q[0] * w[0] + q[2] * w[2] - q[3] * w[1]),
            0.5 * (q[0] * w[1] - q[1] * w[2] + q[3] * w[0]),
            0.5 * (q[0] * w[2] + q[1] * w[1] - q[2] * w[0]),
        ];
        [
            s[3],
            s[4],
            s[5],
            r[0][2] * f / m,
            r[1][2] * f / m,
            r[2][2] * f / m - g,
            qd[0],
            qd[1],
            qd[2],
            qd[3],
            (tau[0] - gyro[0]) / j[0],
            (tau[1] - gyro[1]) / j[1],
            (tau[2] - gyro[2]) / j[2],
        ]
    };
    let mut s: S = [
        0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    ];
    let n = 1024;
    let h = 0.02 / n as f64;
    for cmd in commands {
        let rpm = cmd.map(f64::from);
        for _ in 0..n {
            let add = |a: &S, k: &S, t: f64| -> S { core::array::from_fn(|i| a[i] + t * k[i]) };
            let k1 = deriv(&s, &rpm);
            let k2 = deriv(&add(&s, &k1, 0.5 * h), &rpm);
            let k3 = deriv(&add(&s, &k2, 0.5 * h), &rpm);
            let k4 = deriv(&add(&s, &k3, h), &rpm);
            s = core::array::from_fn(|i| {
                s[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            });
            let qn = (s[6] * s[6] + s[7] * s[7] + s[8] * s[8] + s[9] * s[9]).sqrt();
            for v in &mut s[6..10] {
                *v /= qn;
            }
        }
    }
    ([s[0], s[1], s[2]], [s[6], s[7], s[8], s[9]])
}

/// Position (m) and attitude (rad) error of the f32 integrator with `substeps` against the
/// float64 reference after flying `commands` from rest.
fn errors(commands: &[[f32; 4]], p_ref: [f64; 3], q_ref: [f64; 4], substeps: u32) -> (f64, f64) {
    let p = Preset {
        substeps,
        ..Preset::paper()
    };
    let mut body = at_rest();
    for c in commands {
        body.step(&p, &MotorCommand { rpm: *c }, 0.02);
    }
    let s = body.state;
    let dp = ((f64::from(s.position_m.x) - p_ref[0]).powi(2)
        + (f64::from(s.position_m.y) - p_ref[1]).powi(2)
        + (f64::from(s.position_m.z) - p_ref[2]).powi(2))
    .sqrt();
    // Rotation angle of q⁻¹ ⊗ q_ref: twice the norm of its vector part (small angles).
    let [w, x, y, z] = s.attitude.to_array().map(f64::from);
    let [rw, rx, ry, rz] = q_ref;
    let err = [
        w * rx - x * rw - y * rz + z * ry,
        w * ry + x * rz - y * rw - z * rx,
        w * rz - x * ry + y * rx - z * rw,
    ];
    (
        dp,
        2.0 * (err[0] * err[0] + err[1] * err[1] + err[2] * err[2]).sqrt(),
    )
}

/// Largest body rate (rad/s) reached while flying `commands` from rest.
fn peak_rate(commands: &[[f32; 4]]) -> f32 {
    let p = Preset::paper();
    let mut body = at_rest();
    let mut peak = 0.0f32;
    for c in commands {
        body.step(&p, &MotorCommand { rpm: *c }, 0.02);
        peak = peak.max(body.state.body_rates_radps.norm());
    }
    peak
}

/// Checks every substep count against the reference and prints the errors for the docs;
/// the default preset must stay within `bound_m` / `bound_rad`.
fn check(name: &str, commands: &[[f32; 4]], bound_m: f64, bound_rad: f64) {
    let (p_ref, q_ref) = reference_flight(commands);
    println!(
        "{name}: {:.1} s, peak body rate {:.1} rad/s, travel {:.2} m",
        commands.len() as f32 * 0.02,
        peak_rate(commands),
        (p_ref[0].powi(2) + p_ref[1].powi(2) + (p_ref[2] - 1.0).powi(2)).sqrt()
    );
    for substeps in [1, 2, 4, 8] {
        let (dp, dq) = errors(commands, p_ref, q_ref, substeps);
        println!(
            "  {substeps} RK4 substep(s) per 20 ms, f32: position error {dp:.2e} m, attitude error {dq:.2e} rad"
        );
        if substeps == Preset::paper().substeps {
            assert!(
                dp < bound_m && dq < bound_rad,
                "default preset: {dp} m, {dq} rad"
            );
        }
    }
}

/// The f32 integrator (RK4, `substeps` per 20 ms) against the float64 reference over an
/// aggressive 2 s manoeuvre with changing commands (up to ±1,500 rpm of differential thrust:
/// rates of several rad/s).
#[test]
fn integrator_error_against_a_float64_reference() {
    let h = Preset::paper().hover_rpm();
    let commands: Vec<[f32; 4]> = (0..100)
        .map(|k| {
            let t = k as f32 * 0.02;
            let wobble = 1500.0 * libm::sinf(7.0 * t);
            [
                h + wobble,
                h - 0.5 * wobble,
                h + 0.8 * wobble,
                h - wobble + 300.0,
            ]
        })
        .collect();
    check("racing manoeuvre", &commands, 1e-4, 1e-4);
}

/// Full authority: every motor switching between the action limits (a = ±1, 2,894 to
/// 26,043 rpm) in a pseudo-random pattern for 1 s, as an untrained policy does. Rates reach
/// tens of rad/s, so the error per control period grows; the default preset must stay within
/// 1 mm and 1 mrad after 1 s (one substep would not: 1.8 mrad).
#[test]
fn integrator_error_at_full_authority() {
    let map = firmware_core::vehicle::ActionMap::PAPER;
    let mut seed = 0x9e37_79b9_u32;
    let commands: Vec<[f32; 4]> = (0..50)
        .map(|_| {
            core::array::from_fn(|_| {
                seed ^= seed << 13;
                seed ^= seed >> 17;
                seed ^= seed << 5;
                map.rpm(if seed & 1 == 0 { 1.0 } else { -1.0 })
            })
        })
        .collect();
    check("full authority", &commands, 1e-3, 1e-3);
}
