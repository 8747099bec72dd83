//! Validation of the cf2x dynamics against hand-derived answers (SPEC "Vehicle").

use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::{ActionMap, MotorCommand, VehicleState};
use sitl::dynamics::{Body, Preset};

fn at_rest() -> Body {
    Body::new(VehicleState::at_rest(
        Vec3::new(0.0, 0.0, 1.0),
        Quat::IDENTITY,
    ))
}

#[test]
fn hover_rpm_and_thrust_to_weight_per_preset() {
    let map = ActionMap::PAPER;
    let paper = Preset::paper();
    // Half the force: hover at a ≈ +0.52, thrust-to-weight ≈ 1.62 at a = 1 (SPEC).
    let a = map.action_for_rpm(paper.hover_rpm());
    assert!((a - 0.519).abs() < 0.002, "paper hover action {a}");
    let tw = |p: &Preset, rpm: f32| (rpm / p.hover_rpm()).powi(2);
    assert!((tw(&paper, map.rpm(1.0)) - 1.62).abs() < 0.01);
    let nominal = Preset::nominal();
    assert!((tw(&nominal, map.rpm(1.0)) - 3.24).abs() < 0.01);
    assert!(map.action_for_rpm(nominal.hover_rpm()).abs() < 0.002);
    let realistic = Preset::realistic();
    assert!((tw(&realistic, realistic.max_rpm) - 2.25).abs() < 0.01);
}

#[test]
fn hover_rpm_holds_altitude() {
    for preset in [Preset::paper(), Preset::nominal(), Preset::realistic()] {
        let mut body = at_rest();
        body.rpm = [preset.hover_rpm(); 4];
        let cmd = MotorCommand {
            rpm: [preset.hover_rpm(); 4],
        };
        for _ in 0..50 {
            body.step(&preset, &cmd, 0.02);
        }
        let p = body.state.position_m;
        assert!(
            (p - Vec3::new(0.0, 0.0, 1.0)).norm() < 1e-3,
            "{}: {p:?}",
            preset.name
        );
    }
}

#[test]
fn free_fall_is_exact() {
    let preset = Preset::paper();
    let mut body = at_rest();
    for _ in 0..25 {
        body.step(&preset, &MotorCommand::STOP, 0.02);
    }
    // RK4 integrates a constant acceleration exactly: z = 1 − g t²/2 at t = 0.5 s.
    let z = body.state.position_m.z;
    assert!((z - (1.0 - 0.5 * 9.81 * 0.25)).abs() < 1e-5, "{z}");
    assert!((body.state.velocity_mps.z + 9.81 * 0.5).abs() < 1e-5);
}

/// Differential thrust around hover, one axis at a time, must spin the body with the sign
/// of SPEC's geometry: τ = Σ pᵢ × fᵢ and τz = km Σ sᵢ rpmᵢ² with s = (−1, +1, −1, +1).
#[test]
fn torque_signs_follow_the_propeller_layout_and_spin() {
    let preset = Preset::nominal();
    let h = preset.hover_rpm();
    let spin = |rpm: [f32; 4]| {
        let mut body = at_rest();
        body.step(&preset, &MotorCommand { rpm }, 0.02);
        body.state.body_rates_radps
    };
    let d = 200.0;
    // Left propellers (p2, p3 at y > 0) faster: roll positive (left side up).
    let w = spin([h - d, h - d, h + d, h + d]);
    assert!(
        w.x > 0.0 && w.y.abs() < 1e-3 * w.x.abs() && w.z.abs() < 1e-3 * w.x.abs(),
        "{w:?}"
    );
    // Front propellers (p0, p3 at x > 0) faster: nose up, which is negative about body y.
    let w = spin([h + d, h - d, h - d, h + d]);
    assert!(w.y < 0.0 && w.x.abs() < 1e-3 * w.y.abs(), "{w:?}");
    // Propellers with s = +1 (p1, p3) faster: yaw positive (counter-clockwise from above).
    let w = spin([h - d, h + d, h - d, h + d]);
    assert!(
        w.z > 0.0 && w.x.abs() < 1e-3 * w.z.abs() && w.y.abs() < 1e-3 * w.z.abs(),
        "{w:?}"
    );
    // Magnitude of the yaw case by hand: τz = km (4 · 2 h d) approximately, α = τz / Izz.
    let expected = preset.km_nm_per_rpm2 * 4.0 * ((h + d).powi(2) - (h - d).powi(2))
        / 2.0
        / preset.inertia_kgm2[2]
        * 0.02;
    assert!(
        (w.z - expected).abs() < 0.01 * expected,
        "{} vs {expected}",
        w.z
    );
}

/// With the motors balanced about hover but gravity compensated, a spinning body keeps its
/// rotational energy and the magnitude of its angular momentum (no torque acts).
#[test]
fn torque_free_rotation_keeps_energy_and_momentum() {
    let preset = Preset {
        gravity_mps2: 0.0,
        ..Preset::nominal()
    };
    let mut body = Body::new(VehicleState {
        body_rates_radps: Vec3::new(3.0, -2.0, 5.0),
        ..VehicleState::at_rest(Vec3::ZERO, Quat::IDENTITY)
    });
    let j = preset.inertia_kgm2;
    let invariants = |b: &Body| {
        let w = b.state.body_rates_radps;
        let l = Vec3::new(j[0] * w.x, j[1] * w.y, j[2] * w.z);
        let energy = 0.5 * (j[0] * w.x * w.x + j[1] * w.y * w.y + j[2] * w.z * w.z);
        (energy, b.state.attitude.rotate(l))
    };
    let (e0, l0) = invariants(&body);
    for _ in 0..100 {
        body.step(&preset, &MotorCommand::STOP, 0.02);
    }
    let (e1, l1) = invariants(&body);
    assert!(((e1 - e0) / e0).abs() < 1e-4, "energy {e0} -> {e1}");
    assert!(
        (l1 - l0).norm() / l0.norm() < 1e-3,
        "momentum {l0:?} -> {l1:?}"
    );
    assert!((body.state.attitude.norm_squared() - 1.0).abs() < 1e-5);
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
        let r = overtake_rotation(q);
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

fn overtake_rotation(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// The f32 integrator (RK4, `substeps` per 20 ms) against the float64 reference over an
/// aggressive 2 s manoeuvre with changing commands (up to ±1,500 rpm of differential thrust:
/// rates of several rad/s). Prints the errors for the docs.
#[test]
fn integrator_error_against_a_float64_reference() {
    let preset = Preset::paper();
    let h = preset.hover_rpm();
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
    let (p_ref, q_ref) = reference_flight(&commands);
    for substeps in [1, 2, 4, 8] {
        let p = Preset {
            substeps,
            ..Preset::paper()
        };
        let mut body = at_rest();
        for c in &commands {
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
        let dq = 2.0 * (err[0] * err[0] + err[1] * err[1] + err[2] * err[2]).sqrt();
        println!(
            "{substeps} RK4 substep(s) per 20 ms, f32: position error {dp:.2e} m, attitude error {dq:.2e} rad after 2 s (travel {:.2} m)",
            (p_ref[0].powi(2) + p_ref[1].powi(2) + (p_ref[2] - 1.0).powi(2)).sqrt()
        );
        if substeps == preset.substeps {
            assert!(dp < 1e-4 && dq < 1e-4, "default preset: {dp} m, {dq} rad");
        }
    }
}
