//! Validation of the cf2x dynamics against hand-derived answers (docs/DESIGN.md "Vehicle",
//! "Presets").

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
    // Half the force: hover at a ≈ +0.52, thrust-to-weight ≈ 1.62 at a = 1
    // (docs/DESIGN.md "Presets").
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
/// of the geometry in docs/DESIGN.md "Vehicle": τ = Σ pᵢ × fᵢ and τz = km Σ sᵢ rpmᵢ² with
/// s = (−1, +1, −1, +1).
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
