//! The time-optimal racing line of the `paper` preset, as states to start training episodes
//! from (issue "learn": the initial-state distribution is the recipe's to choose).
//!
//! Spawns along the centreline ([`crate::world::along_track_spawn`]) show a policy the
//! track's middle at moderate speeds; the lap that is fastest for this drone crosses the
//! hairpin gates at their inside corners, climbs in the hairpins and dives through g0/g3
//! at 14 m/s (docs/TRAINING.md "The reward keeps the line at the gates' centres"). A
//! spawn on that line puts the drone in those states and lets PPO learn what to do there.
//! Only the states are used: no action of the optimum is imitated, and the reward is the
//! environment's own.
//!
//! The line is the point-mass optimum of `tools/min_lap_time.py` (`paper.rs`, generated)
//! through the middle 1.4 m of each opening (7.149 s; through the full 1.6 m, 7.099 s, it
//! grazes the frames, and a spawn just before a gate would crash whatever the policy did):
//! at each node the position, the velocity and the specific thrust. A spawn takes a node's
//! position and velocity, an attitude whose body z points along the thrust (what the point
//! mass needs to follow the line) and whose body x points along the velocity's component
//! across it, zero body rates, and the node's target gate.

mod paper;

use crate::world::SpawnPoint;
use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::VehicleState;

/// Nodes of the `paper` preset's line (one per 1/40 of each gate-to-gate segment).
pub fn paper_nodes() -> usize {
    paper::NODES.len()
}

/// The spawn at node `index` (modulo the node count) of the `paper` preset's optimal lap.
pub fn paper_spawn(index: usize) -> SpawnPoint {
    let (target_gate, v) = paper::NODES[index % paper::NODES.len()];
    let position_m = Vec3::new(v[0], v[1], v[2]);
    let velocity_mps = Vec3::new(v[3], v[4], v[5]);
    let thrust = Vec3::new(v[6], v[7], v[8]);
    SpawnPoint {
        state: VehicleState {
            position_m,
            attitude: attitude_along(thrust, velocity_mps),
            velocity_mps,
            body_rates_radps: Vec3::ZERO,
        },
        target_gate,
    }
}

/// The attitude whose body z is `up` and whose body x is `forward` made orthogonal to it
/// (world x when `forward` is along `up` or zero; identity when `up` is zero).
pub fn attitude_along(up: Vec3, forward: Vec3) -> Quat {
    let n = up.norm();
    // Also refuses a NaN thrust (every comparison with NaN is false).
    if n.is_nan() || n <= 1e-6 {
        return Quat::IDENTITY;
    }
    let z = up.scale(1.0 / n);
    let mut x = forward - z.scale(forward.dot(z));
    if x.norm() < 1e-6 {
        x = Vec3::X - z.scale(z.x);
        if x.norm() < 1e-6 {
            x = Vec3::Y - z.scale(z.y);
        }
    }
    let x = x.scale(1.0 / x.norm());
    let y = z.cross(x);
    from_columns(x, y, z)
}

/// The unit quaternion of the rotation whose matrix has columns `x`, `y`, `z` (orthonormal,
/// right-handed), by Shepperd's method (the largest of the four candidates, for accuracy).
fn from_columns(x: Vec3, y: Vec3, z: Vec3) -> Quat {
    let (m00, m11, m22) = (x.x, y.y, z.z);
    let trace = m00 + m11 + m22;
    let q = if trace > 0.0 {
        let s = 2.0 * libm::sqrtf(1.0 + trace);
        Quat::new(0.25 * s, (y.z - z.y) / s, (z.x - x.z) / s, (x.y - y.x) / s)
    } else if m00 > m11 && m00 > m22 {
        let s = 2.0 * libm::sqrtf(1.0 + m00 - m11 - m22);
        Quat::new((y.z - z.y) / s, 0.25 * s, (y.x + x.y) / s, (z.x + x.z) / s)
    } else if m11 > m22 {
        let s = 2.0 * libm::sqrtf(1.0 + m11 - m00 - m22);
        Quat::new((z.x - x.z) / s, (y.x + x.y) / s, 0.25 * s, (z.y + y.z) / s)
    } else {
        let s = 2.0 * libm::sqrtf(1.0 + m22 - m00 - m11);
        Quat::new((x.y - y.x) / s, (z.x + x.z) / s, (z.y + y.z) / s, 0.25 * s)
    };
    q.normalized()
}

#[cfg(test)]
mod tests {
    use super::*;
    use firmware_core::track::Track;

    fn close(a: Vec3, b: Vec3, tol: f32) -> bool {
        (a - b).norm() < tol
    }

    #[test]
    fn the_attitude_points_body_z_along_the_thrust_and_body_x_along_the_velocity() {
        let cases = [
            (Vec3::new(0.0, 0.0, 9.81), Vec3::new(3.0, 4.0, 0.0)),
            (Vec3::new(-0.2, -0.4, 15.9), Vec3::new(11.3, 8.2, 0.0)),
            (Vec3::new(12.0, -3.0, 4.0), Vec3::new(-1.0, 7.0, 2.0)),
            (Vec3::new(0.0, 0.0, -9.0), Vec3::new(-5.0, -1.0, 0.5)),
            (Vec3::new(-3.0, 8.0, -1.0), Vec3::new(0.0, 0.0, 1.0)),
        ];
        for (up, fwd) in cases {
            let q = attitude_along(up, fwd);
            assert!((q.norm_squared() - 1.0).abs() < 1e-5);
            let bz = q.rotate(Vec3::Z);
            let bx = q.rotate(Vec3::X);
            assert!(
                close(bz, up.scale(1.0 / up.norm()), 1e-5),
                "{up:?} {fwd:?}: z {bz:?}"
            );
            let across = fwd - bz.scale(fwd.dot(bz));
            assert!(
                close(bx, across.scale(1.0 / across.norm()), 1e-5),
                "x {bx:?}"
            );
            // Right-handed: body y is z × x.
            assert!(close(q.rotate(Vec3::Y), bz.cross(bx), 1e-5));
        }
        // Degenerate inputs still give a unit quaternion with z along the thrust.
        let q = attitude_along(Vec3::new(0.0, 0.0, 2.0), Vec3::ZERO);
        assert!(close(q.rotate(Vec3::Z), Vec3::Z, 1e-6));
        assert_eq!(attitude_along(Vec3::ZERO, Vec3::X), Quat::IDENTITY);
    }

    #[test]
    fn the_paper_line_is_a_closed_lap_through_every_gate_in_order() {
        let track = Track::figure_eight();
        let n = paper_nodes();
        assert_eq!(n, 240);
        let dt_s = 7.099 / n as f32; // about: the segments' node spacings differ
        for i in 0..n {
            let a = paper_spawn(i);
            let b = paper_spawn(i + 1);
            // Consecutive nodes are a step of the lap apart (no jump, no reordering).
            let step = (b.state.position_m - a.state.position_m).norm();
            assert!(step < 14.5 * 2.0 * dt_s, "node {i}: {step} m to the next");
            // Above the ground rule, at most 14.5 m/s, within the thrust-to-weight limit.
            assert!(a.state.position_m.z >= 0.1 - 1e-4);
            assert!(a.state.velocity_mps.norm() < 14.5);
            assert!(a.state.attitude.is_finite());
            // The target is the gate the node flies to: the next node either still flies
            // to it or has just reached it (it is then on that gate's plane).
            assert!(b.target_gate == a.target_gate || b.target_gate == (a.target_gate + 1) % 6);
            if b.target_gate != a.target_gate {
                // On the plane, inside the opening with the line's 0.1 m margin (the gate
                // test is strict at 0.8 m: a line through the frame's edge would crash).
                let rel = track.gate(a.target_gate).to_gate_frame(b.state.position_m);
                assert!(
                    rel.x.abs() < 1e-3,
                    "node {}: off g{}'s plane",
                    i + 1,
                    a.target_gate
                );
                let inside = rel.y.abs() < 0.7 + 1e-3 && rel.z.abs() < 0.7 + 1e-3;
                assert!(inside, "node {}: crosses at {rel:?}", i + 1);
            }
        }
        // Six gate changes in a lap, starting on g0's plane flying to g1.
        let changes =
            (0..n).filter(|&i| paper_spawn(i).target_gate != paper_spawn(i + 1).target_gate);
        assert_eq!(changes.count(), 6);
        assert_eq!(paper_spawn(0).target_gate, 1);
    }
}
