//! firmware-core's observation pipeline against the formulas of docs/DESIGN.md
//! "Observations" evaluated in float64 with rotation matrices (tests/src/reference.rs), over
//! random states of both drones.

use firmware_core::math::{Quat, Vec3};
use firmware_core::observation::{ObservationLayout, ObservationSpec};
use firmware_core::track::Track;
use firmware_core::vehicle::VehicleState;
use overtake_tests::reference::{State64, observation};
use proptest::prelude::*;

fn state() -> impl Strategy<Value = VehicleState> {
    (
        (-20.0f32..20.0, -20.0f32..20.0, 0.0f32..4.0),
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0),
        (-12.0f32..12.0, -12.0f32..12.0, -5.0f32..5.0),
        (-8.0f32..8.0, -8.0f32..8.0, -8.0f32..8.0),
    )
        .prop_filter("quaternion", |(_, q, _, _)| {
            q.0 * q.0 + q.1 * q.1 + q.2 * q.2 + q.3 * q.3 > 0.05
        })
        .prop_map(|(p, q, v, w)| VehicleState {
            position_m: Vec3::new(p.0, p.1, p.2),
            attitude: Quat::new(q.0, q.1, q.2, q.3).normalized(),
            velocity_mps: Vec3::new(v.0, v.1, v.2),
            body_rates_radps: Vec3::new(w.0, w.1, w.2),
        })
}

fn to64(s: &VehicleState) -> State64 {
    let v = |a: Vec3| a.to_array().map(f64::from);
    State64 {
        p: v(s.position_m),
        q: s.attitude.to_array().map(f64::from),
        v: v(s.velocity_mps),
        w: v(s.body_rates_radps),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]
    #[test]
    fn pipeline_matches_the_float64_formulas(
        own in state(),
        opp in state(),
        gate in 0usize..6,
        action in proptest::array::uniform4(-1.0f32..1.0),
    ) {
        let g = Track::figure_eight().gate(gate);
        for layout in [ObservationLayout::TimeTrial17, ObservationLayout::OpponentPosition20, ObservationLayout::FullOpponent30] {
            let got = ObservationSpec::paper(layout).observe(&own, &g, &action, Some(&opp)).expect("observe");
            let want = observation(
                layout.dim(),
                &to64(&own),
                g.center_m.to_array().map(f64::from),
                g.frame.to_array().map(f64::from),
                action.map(f64::from),
                Some(&to64(&opp)),
            );
            prop_assert_eq!(got.dim(), layout.dim());
            for (i, (a, b)) in got.as_slice().iter().zip(&want).enumerate() {
                prop_assert!((f64::from(*a) - b).abs() <= 2e-5, "{:?} index {}: {} vs {}", layout, i, a, b);
            }
        }
    }
}

#[test]
fn hand_computed_stage1_observation() {
    // At rest at the stage-1 spawn (-1, -1, 1), level, facing g0 at (0, 0, 1).
    let own = VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY);
    let g0 = Track::figure_eight().gate(0);
    let obs = ObservationSpec::paper(ObservationLayout::TimeTrial17)
        .observe(&own, &g0, &[0.1, 0.2, 0.3, 0.4], None)
        .expect("observe");
    let want = [
        1.0 / 12.0,
        1.0 / 12.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.1,
        0.2,
        0.3,
        0.4,
    ];
    for (a, b) in obs.as_slice().iter().zip(want) {
        assert!((a - b).abs() < 1e-7, "{:?}", obs.as_slice());
    }
    // Far away and fast: the position and velocity terms saturate at ±1 (the paper's 3 m/s).
    let fast = VehicleState {
        velocity_mps: Vec3::new(10.0, 0.0, 0.0),
        ..VehicleState::at_rest(Vec3::new(-30.0, 0.0, 1.0), Quat::IDENTITY)
    };
    let obs = ObservationSpec::paper(ObservationLayout::TimeTrial17)
        .observe(&fast, &g0, &[0.0; 4], None)
        .expect("observe");
    assert_eq!(obs.as_slice()[0], 1.0);
    assert_eq!(obs.as_slice()[7], 1.0);
}
