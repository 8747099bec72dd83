//! The learned controller: fail-safe on bad inputs, the trained-rate contract, gate
//! bookkeeping and resets.

use firmware_core::blob::AlignedBytes;
use firmware_core::controller::{Controller, ControllerError, StepFault};
use firmware_core::math::{Quat, Vec3};
use firmware_core::policy::{PolicyState, TableRow};
use firmware_core::synthetic;
use firmware_core::track::{GateEvent, Track};
use firmware_core::vehicle::{ActionMap, MotorCommand, VehicleState};
use firmware_core::{Blob, PAPER_CONTROL_PERIOD_NS};

fn blob(row: TableRow) -> AlignedBytes {
    AlignedBytes::new(&synthetic::blob(row, 21).expect("encode"))
}

fn hovering(x: f32) -> VehicleState {
    VehicleState::at_rest(Vec3::new(x, 0.0, 1.0), Quat::IDENTITY)
}

#[test]
fn a_normal_step_commands_rpm_within_the_action_map() {
    for row in [TableRow::A, TableRow::B, TableRow::G] {
        let bytes = blob(row);
        let mut c =
            Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
        let opp = hovering(-2.0);
        let out = c.step(&hovering(-1.0), Some(&opp));
        assert_eq!(out.fault, None);
        let (lo, hi) = (ActionMap::PAPER.rpm(-1.0), ActionMap::PAPER.rpm(1.0));
        assert!(
            out.command.rpm.iter().all(|r| (lo..=hi).contains(r)),
            "{:?}",
            out.command
        );
        assert!(out.action.iter().all(|a| (-1.0..=1.0).contains(a)));
        assert_eq!(out.command, ActionMap::PAPER.command(&out.action));
    }
}

#[test]
fn nan_or_infinite_inputs_give_the_fail_safe_and_keep_the_state() {
    let bytes = blob(TableRow::G);
    let mut c =
        Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
    let opp = hovering(-2.0);
    c.step(&hovering(-1.0), Some(&opp));
    let state_before = *c.policy_state();

    let mut bad = hovering(-1.0);
    bad.velocity_mps.y = f32::NAN;
    let out = c.step(&bad, Some(&opp));
    assert_eq!(
        (out.command, out.fault),
        (MotorCommand::STOP, Some(StepFault::NonFiniteState))
    );
    assert_eq!(*c.policy_state(), state_before);

    let mut bad_opp = opp;
    bad_opp.attitude.w = f32::INFINITY;
    let out = c.step(&hovering(-1.0), Some(&bad_opp));
    assert_eq!(
        (out.command, out.fault),
        (MotorCommand::STOP, Some(StepFault::NonFiniteOpponent))
    );

    let out = c.step(&hovering(-1.0), None);
    assert_eq!(
        (out.command, out.fault),
        (MotorCommand::STOP, Some(StepFault::MissingOpponent))
    );
    assert_eq!(c.fault_count(), 3);
    assert_eq!(*c.policy_state(), state_before);

    // It recovers as soon as the inputs are good again.
    assert_eq!(c.step(&hovering(-1.0), Some(&opp)).fault, None);
}

#[test]
fn a_time_trial_policy_ignores_the_opponent() {
    let bytes = blob(TableRow::A);
    let mut c =
        Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
    let a = c.step(&hovering(-1.0), None);
    c.reset(0);
    let b = c.step(&hovering(-1.0), Some(&hovering(3.0)));
    assert_eq!(a, b);
}

#[test]
fn a_recurrent_policy_refuses_another_rate_and_an_mlp_does_not() {
    let g = blob(TableRow::G);
    let blob_g = Blob::parse(g.as_bytes()).expect("parse");
    assert_eq!(
        Controller::new(&blob_g, Track::figure_eight(), 10_000_000).err(),
        Some(ControllerError::RateMismatch {
            trained_ns: PAPER_CONTROL_PERIOD_NS,
            requested_ns: 10_000_000
        })
    );
    let a = blob(TableRow::A);
    let blob_a = Blob::parse(a.as_bytes()).expect("parse");
    assert!(Controller::new(&blob_a, Track::figure_eight(), 10_000_000).is_ok());
}

#[test]
fn the_target_gate_advances_on_a_pass_and_reset_restarts() {
    let bytes = blob(TableRow::G);
    let mut c =
        Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
    let opp = hovering(-3.0);
    c.step(&hovering(-0.2), Some(&opp));
    let out = c.step(&hovering(0.2), Some(&opp));
    assert!(
        matches!(out.gate_event, GateEvent::Passed { gate: 0, .. }),
        "{:?}",
        out.gate_event
    );
    assert_eq!(c.progress().target, 1);
    assert_ne!(*c.policy_state(), c.policy().initial_state());

    c.reset(4);
    assert_eq!(c.progress().target, 4);
    assert_eq!(c.progress().gates_passed, 0);
    assert!(matches!(c.policy_state(), PolicyState::Lstm2(s) if *s == Default::default()));
    // No pass is detected across a reset (the first step after it has no previous position).
    let out = c.step(&hovering(0.5), Some(&opp));
    assert_eq!(out.gate_event, GateEvent::None);
}

#[test]
fn same_inputs_same_outputs() {
    let bytes = blob(TableRow::F);
    let run = || {
        let mut c =
            Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
        (0..20)
            .map(|i| {
                c.step(&hovering(-2.0 + 0.05 * i as f32), Some(&hovering(-3.0)))
                    .command
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(run(), run());
}

/// A folded blob (observation pipeline version 2): on the mirrored half (targets g3-g5) the
/// controller flies the mirror image of what the same network, unfolded, does on the
/// reflected state flying to the reflected gate; on g0-g2 it flies as the unfolded one. A
/// track without the symmetry is refused.
#[test]
fn a_folded_controller_flies_the_mirrored_half_as_the_image_of_the_other() {
    use firmware_core::mirror::TrackMirror;
    let h = synthetic::header(TableRow::A, 5);
    let w = synthetic::weights(&h.architecture, 5);
    let mut folded_header = h.clone();
    folded_header.observation = h.observation.with_fold(true);
    let plain = AlignedBytes::new(&firmware_core::blob::encode(&h, &w).expect("encode"));
    let folded =
        AlignedBytes::new(&firmware_core::blob::encode(&folded_header, &w).expect("encode"));
    let track = Track::figure_eight();
    let m = TrackMirror::of_track(&track).expect("the figure-8 mirrors");
    let s = VehicleState {
        position_m: Vec3::new(1.5, -2.0, 1.2),
        attitude: Quat::new(0.9, 0.1, -0.3, 0.2).normalized(),
        velocity_mps: Vec3::new(3.0, 1.0, -0.5),
        body_rates_radps: Vec3::new(0.4, -1.0, 2.0),
    };
    let mut seen = [false; 2];
    for target in 0..6 {
        let mut f = Controller::from_bytes(folded.as_bytes(), track).expect("controller");
        let mut p = Controller::from_bytes(plain.as_bytes(), track).expect("controller");
        f.reset(target);
        p.reset(if m.folds(target) {
            m.gate(target)
        } else {
            target
        });
        // Two steps, so the previous action is folded too.
        for step in 0..2 {
            let out = f.step(&s, None);
            assert_eq!(out.fault, None);
            if m.folds(target) {
                let img = p.step(&m.state(&s), None);
                assert_eq!(
                    out.action,
                    m.motors(&img.action),
                    "target {target}, step {step}"
                );
                // The next step's previous action is the image's, as the plain one saw it.
                if step == 0 {
                    let again_f = f.peek_observation(&s, None).expect("obs");
                    let again_p = p.peek_observation(&m.state(&s), None).expect("obs");
                    assert_eq!(again_f, again_p);
                }
                seen[1] = true;
            } else {
                assert_eq!(out, p.step(&s, None), "target {target}, step {step}");
                seen[0] = true;
            }
        }
    }
    assert_eq!(seen, [true, true]);
    // Without the symmetry the folded blob cannot fly.
    let mut moved = firmware_core::track::FIGURE_EIGHT;
    moved[1].center_m.x += 0.5;
    let e = Controller::from_bytes(folded.as_bytes(), Track::new(&moved, 0.8).expect("track"))
        .expect_err("no mirror");
    assert!(matches!(e, ControllerError::NoMirror(_)), "{e}");
    assert!(e.to_string().contains("folded"), "{e}");
}

/// `Controller::step_lanes`: 16 clones of one controller stepped side by side give, lane by
/// lane, what `step` gives each (outputs and everything the next step reads), over a flight
/// with a refused input in one lane and resets in others, for a folded MLP and row G.
#[test]
fn step_lanes_is_step_for_every_lane() {
    use firmware_core::nn::LANES;
    for (row, folded) in [
        (TableRow::A, true),
        (TableRow::G, false),
        (TableRow::E, false),
    ] {
        let mut header = synthetic::header(row, 5);
        header.observation = header.observation.with_fold(folded);
        let payload = synthetic::weights(&header.architecture, 5);
        let bytes =
            AlignedBytes::new(&firmware_core::blob::encode(&header, &payload).expect("encode"));
        let template =
            Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).expect("controller");
        let policy = *template.policy();
        let mut one: Vec<Controller<'_>> = (0..LANES).map(|_| template.clone()).collect();
        let mut side: Vec<Controller<'_>> = one.clone();
        for t in 0..40 {
            let own: Vec<VehicleState> = (0..LANES)
                .map(|l| {
                    let mut s = hovering(-1.5 + 0.05 * l as f32 + 0.03 * t as f32);
                    s.velocity_mps = Vec3::new(1.0 + 0.1 * l as f32, 0.2 * t as f32, -0.1);
                    if (l, t) == (3, 17) {
                        s.position_m.z = f32::NAN;
                    }
                    s
                })
                .collect();
            let opp: Vec<VehicleState> = (0..LANES).map(|l| hovering(0.1 * l as f32)).collect();
            for (l, (a, b)) in one.iter_mut().zip(side.iter_mut()).enumerate() {
                if (t + l) % 11 == 0 {
                    a.reset(l % 7);
                    b.reset(l % 7);
                }
            }
            let want: Vec<_> = one
                .iter_mut()
                .zip(&own)
                .zip(&opp)
                .map(|((c, o), p)| c.step(o, Some(p)))
                .collect();
            let mut refs = side.iter_mut();
            let controllers: [&mut Controller<'_>; LANES] =
                core::array::from_fn(|_| refs.next().expect("16"));
            let got = Controller::step_lanes(
                &policy,
                controllers,
                core::array::from_fn(|l| &own[l]),
                core::array::from_fn(|l| Some(&opp[l])),
            );
            assert_eq!(got.as_slice(), want.as_slice(), "row {row:?}, step {t}");
            for (a, b) in one.iter().zip(&side) {
                assert_eq!(a.policy_state(), b.policy_state());
                assert_eq!(a.progress(), b.progress());
            }
        }
    }
}
