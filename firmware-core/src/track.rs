//! The race track: gates with a centre and a frame, the paper's figure-8, next-gate
//! bookkeeping, and the gate-plane tests that decide a pass or a crash.
//!
//! This is the one track description of the project: the simulator's referee, the
//! training environments and the deployed controller all call [`GateProgress::advance`] and
//! [`Gate::crossing`].
//!
//! ## Gate frame
//! A gate's frame is a unit quaternion mapping gate-frame vectors to the world frame. Its +x
//! axis is the direction of travel; the opening is the square |y| < h, |z| < h of the gate
//! plane x = 0, with h = [`Track::opening_half_size_m`] (0.8 m: a 1.6 m opening). A drone
//! *passes* a gate when the segment between two consecutive positions crosses the plane from
//! front (x < 0) to back (x >= 0) inside the opening, and *collides* with it when it crosses
//! from front to back outside it. Crossings from back to front are not events.

use crate::math::{Quat, Vec3};

/// One gate: its centre and frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gate {
    /// Centre of the opening (m, world frame).
    pub center_m: Vec3,
    /// Unit quaternion (w, x, y, z): gate frame → world frame; +x is the direction of travel.
    pub frame: Quat,
}

/// What happened at a gate plane between two positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GateCrossing {
    /// The segment does not cross the plane front to back.
    None,
    /// Crossed inside the opening; the crossing point in the gate frame (m).
    Passed {
        /// Crossing point in the gate frame (m); x is 0.
        crossing_m: Vec3,
    },
    /// Crossed the plane outside the opening: a crash.
    Collided {
        /// Crossing point in the gate frame (m); x is 0.
        crossing_m: Vec3,
    },
}

impl Gate {
    /// A gate at `center_m` with frame `frame` (normalised here).
    pub fn new(center_m: Vec3, frame: Quat) -> Self {
        Self {
            center_m,
            frame: frame.normalized(),
        }
    }

    /// A world position expressed in the gate frame (m).
    pub fn to_gate_frame(&self, p_world_m: Vec3) -> Vec3 {
        self.frame.inverse_rotate(p_world_m - self.center_m)
    }

    /// A gate-frame position expressed in the world frame (m).
    pub fn to_world_frame(&self, p_gate_m: Vec3) -> Vec3 {
        self.center_m + self.frame.rotate(p_gate_m)
    }

    /// The direction of travel through the gate (unit, world frame).
    pub fn forward(&self) -> Vec3 {
        self.frame.rotate(Vec3::X)
    }

    /// Tests the segment `from_m → to_m` (world, m) against this gate's plane with an opening
    /// of half-size `half_size_m`: the segment test, so a crossing between two 20 ms steps
    /// is found even when neither end point is near the plane.
    pub fn crossing(&self, from_m: Vec3, to_m: Vec3, half_size_m: f32) -> GateCrossing {
        let a = self.to_gate_frame(from_m);
        let b = self.to_gate_frame(to_m);
        if !(a.x < 0.0 && b.x >= 0.0) {
            return GateCrossing::None;
        }
        // a.x < 0 <= b.x, so the denominator is strictly negative and t ∈ (0, 1].
        let t = a.x / (a.x - b.x);
        let mut p = a.lerp(b, t);
        p.x = 0.0;
        if libm::fabsf(p.y) < half_size_m && libm::fabsf(p.z) < half_size_m {
            GateCrossing::Passed { crossing_m: p }
        } else {
            GateCrossing::Collided { crossing_m: p }
        }
    }
}

/// Number of gates of the figure-8 (one lap is g0 → … → g5 → g0).
pub const FIGURE_EIGHT_GATES: usize = 6;

/// The paper's life-size figure-8 (docs/DESIGN.md "Track"): centres at z = 1 m, frames from the
/// authors' code (Frenet frames of a periodic cubic spline through the centres with uniform
/// knots, g0 and g3 overridden; g1 and g2 are upside down). They are known to four digits
/// (0.9403, 0.3404), whose norm is 1.000018; they are stored here divided by that norm,
/// so every frame is a unit quaternion to f32 precision and rotations keep lengths.
pub static FIGURE_EIGHT: [Gate; FIGURE_EIGHT_GATES] = [
    Gate {
        center_m: Vec3::new(0.0, 0.0, 1.0),
        frame: Quat::new(1.0, 0.0, 0.0, 0.0),
    },
    Gate {
        center_m: Vec3::new(10.0, 5.0, 1.0),
        frame: Quat::new(0.0, 0.940_282_96, -0.340_393_83, 0.0),
    },
    Gate {
        center_m: Vec3::new(10.0, -5.0, 1.0),
        frame: Quat::new(0.0, -0.340_393_83, 0.940_282_96, 0.0),
    },
    Gate {
        center_m: Vec3::new(0.0, 0.0, 1.0),
        frame: Quat::new(0.0, 0.0, 0.0, 1.0),
    },
    Gate {
        center_m: Vec3::new(-10.0, 5.0, 1.0),
        frame: Quat::new(0.340_393_83, 0.0, 0.0, -0.940_282_96),
    },
    Gate {
        center_m: Vec3::new(-10.0, -5.0, 1.0),
        frame: Quat::new(0.940_282_96, 0.0, 0.0, -0.340_393_83),
    },
];

/// A closed track: gates in racing order, the last followed by the first.
#[derive(Clone, Copy, Debug)]
pub struct Track<'a> {
    gates: &'a [Gate],
    /// Half the side of the square gate opening (m). Paper: 0.8.
    pub opening_half_size_m: f32,
}

/// Why a track cannot be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum TrackError {
    /// A track needs at least one gate.
    NoGates,
}

impl core::fmt::Display for TrackError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NoGates => f.write_str("a track needs at least one gate"),
        }
    }
}

impl Track<'static> {
    /// The paper's figure-8 with its 1.6 m openings.
    pub const fn figure_eight() -> Self {
        Self {
            gates: &FIGURE_EIGHT,
            opening_half_size_m: 0.8,
        }
    }
}

impl Default for Track<'static> {
    fn default() -> Self {
        Self::figure_eight()
    }
}

impl<'a> Track<'a> {
    /// A track over `gates` in racing order, with openings of half-size `opening_half_size_m`.
    pub fn new(gates: &'a [Gate], opening_half_size_m: f32) -> Result<Self, TrackError> {
        if gates.is_empty() {
            return Err(TrackError::NoGates);
        }
        Ok(Self {
            gates,
            opening_half_size_m,
        })
    }

    /// The gates in racing order.
    pub fn gates(&self) -> &'a [Gate] {
        self.gates
    }

    /// Number of gates in one lap.
    pub fn len(&self) -> usize {
        self.gates.len()
    }

    /// Always false: a track has at least one gate.
    pub fn is_empty(&self) -> bool {
        self.gates.is_empty()
    }

    /// Gate `index` modulo the number of gates (a valid gate for any index).
    pub fn gate(&self, index: usize) -> Gate {
        let n = self.gates.len().max(1);
        self.gates
            .get(index % n)
            .copied()
            .unwrap_or(Gate::new(Vec3::ZERO, Quat::IDENTITY))
    }

    /// The index of the gate after `index`.
    pub fn next_index(&self, index: usize) -> usize {
        (index + 1) % self.gates.len().max(1)
    }

    /// The segment test of [`Gate::crossing`] against gate `index` with this track's opening.
    pub fn crossing(&self, index: usize, from_m: Vec3, to_m: Vec3) -> GateCrossing {
        self.gate(index)
            .crossing(from_m, to_m, self.opening_half_size_m)
    }
}

/// Most gates a [`Centerline`] can run through.
pub const MAX_CENTERLINE_GATES: usize = 16;

/// The racing line of a track: the periodic cubic spline through the gate centres with
/// uniform knots, gate `k` at parameter `k` (the construction of the paper's code, whose
/// tangents give the gates' headings). Parameter `s ∈ [0, n)` runs once around a lap
/// of `n` gates; segment `k` joins gate `k` to gate `k + 1`.
///
/// For the figure-8 the line is 68.66 m long.
#[derive(Clone, Copy, Debug)]
pub struct Centerline {
    points: [Vec3; MAX_CENTERLINE_GATES],
    /// Second derivatives at the knots (m per parameter²).
    second: [Vec3; MAX_CENTERLINE_GATES],
    n: usize,
}

impl Centerline {
    /// The spline through `track`'s gate centres (the first [`MAX_CENTERLINE_GATES`]).
    pub fn new(track: &Track<'_>) -> Self {
        let n = track.len().min(MAX_CENTERLINE_GATES);
        let mut points = [Vec3::ZERO; MAX_CENTERLINE_GATES];
        for (p, g) in points.iter_mut().zip(track.gates()) {
            *p = g.center_m;
        }
        // Periodic natural spline, uniform knots: M[i-1] + 4 M[i] + M[i+1] = 6 (P[i+1] - 2 P[i] + P[i-1]).
        // Strictly diagonally dominant, so Gauss-Seidel converges geometrically (ratio 1/2).
        let at = |a: &[Vec3; MAX_CENTERLINE_GATES], i: usize| {
            a.get(i % n.max(1)).copied().unwrap_or(Vec3::ZERO)
        };
        let mut second = [Vec3::ZERO; MAX_CENTERLINE_GATES];
        if n >= 3 {
            for _ in 0..60 {
                for i in 0..n {
                    let rhs = (at(&points, i + 1) - at(&points, i).scale(2.0)
                        + at(&points, i + n - 1))
                    .scale(6.0);
                    let v = (rhs - at(&second, i + n - 1) - at(&second, i + 1)).scale(0.25);
                    if let Some(m) = second.get_mut(i) {
                        *m = v;
                    }
                }
            }
        }
        Self { points, second, n }
    }

    /// Number of segments (gates) in a lap.
    pub fn segments(&self) -> usize {
        self.n
    }

    fn knot(&self, i: usize) -> (Vec3, Vec3) {
        let i = i % self.n.max(1);
        (
            self.points.get(i).copied().unwrap_or(Vec3::ZERO),
            self.second.get(i).copied().unwrap_or(Vec3::ZERO),
        )
    }

    fn split(&self, s: f32) -> (usize, f32) {
        let n = self.n.max(1) as f32;
        let s = s - libm::floorf(s / n) * n;
        let k = (libm::floorf(s) as usize).min(self.n.saturating_sub(1));
        (k, s - k as f32)
    }

    /// The point at parameter `s` (m, world), any real `s` (taken modulo a lap).
    pub fn point(&self, s: f32) -> Vec3 {
        let (k, t) = self.split(s);
        let ((p0, m0), (p1, m1)) = (self.knot(k), self.knot(k + 1));
        let u = 1.0 - t;
        p0.scale(u)
            + p1.scale(t)
            + m0.scale((u * u * u - u) / 6.0)
            + m1.scale((t * t * t - t) / 6.0)
    }

    /// The derivative dP/ds at parameter `s` (m per parameter unit).
    pub fn tangent(&self, s: f32) -> Vec3 {
        let (k, t) = self.split(s);
        let ((p0, m0), (p1, m1)) = (self.knot(k), self.knot(k + 1));
        let u = 1.0 - t;
        (p1 - p0) + m0.scale(-(3.0 * u * u - 1.0) / 6.0) + m1.scale((3.0 * t * t - 1.0) / 6.0)
    }

    /// The parameter of the point of segment `segment` nearest to `p_m` (a coarse scan then
    /// a refinement; exact to about 1e-3 of a segment).
    pub fn nearest_on_segment(&self, segment: usize, p_m: Vec3) -> f32 {
        let base = (segment % self.n.max(1)) as f32;
        let dist = |s: f32| (self.point(s) - p_m).dot(self.point(s) - p_m);
        let mut best = (0.0f32, dist(base));
        for i in 1..=32 {
            let t = i as f32 / 32.0;
            let d = dist(base + t);
            if d < best.1 {
                best = (t, d);
            }
        }
        let (mut lo, mut hi) = (
            (best.0 - 1.0 / 32.0).max(0.0),
            (best.0 + 1.0 / 32.0).min(1.0),
        );
        for _ in 0..12 {
            let (a, b) = (lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0);
            if dist(base + a) < dist(base + b) {
                hi = b
            } else {
                lo = a
            }
        }
        base + 0.5 * (lo + hi)
    }

    /// Arc length of segment `segment` (m), as a 256-chord polyline (error below 1 mm).
    pub fn segment_length_m(&self, segment: usize) -> f32 {
        let base = (segment % self.n.max(1)) as f32;
        let steps = 256;
        let mut len = 0.0;
        let mut prev = self.point(base);
        for i in 1..=steps {
            let p = self.point(base + i as f32 / steps as f32);
            len += (p - prev).norm();
            prev = p;
        }
        len
    }

    /// Length of one lap (m).
    pub fn length_m(&self) -> f32 {
        (0..self.n).map(|k| self.segment_length_m(k)).sum()
    }
}

/// Samples per segment of an [`ArcLength`] table.
pub const ARC_LENGTH_SAMPLES: usize = 32;

/// Arc length along a [`Centerline`] as a function of its parameter: a table of
/// [`ARC_LENGTH_SAMPLES`] chords per segment, each integrated with 8 sub-chords and
/// interpolated linearly (error below 1 mm on the figure-8). The referee measures a drone's
/// progress along the track with it (docs/DESIGN.md "Metrics": laps·length + arc length).
#[derive(Clone, Copy, Debug)]
pub struct ArcLength {
    /// `table[k][j]`: arc length from gate 0 to parameter `k + j / ARC_LENGTH_SAMPLES` (m).
    table: [[f32; ARC_LENGTH_SAMPLES + 1]; MAX_CENTERLINE_GATES],
    n: usize,
    length_m: f32,
}

impl ArcLength {
    /// The table of `line`.
    pub fn new(line: &Centerline) -> Self {
        let n = line.segments();
        let mut table = [[0.0; ARC_LENGTH_SAMPLES + 1]; MAX_CENTERLINE_GATES];
        let mut total = 0.0f32;
        for (k, row) in table.iter_mut().enumerate().take(n) {
            let mut prev = line.point(k as f32);
            for (j, slot) in row.iter_mut().enumerate() {
                if j > 0 {
                    for i in 1..=8 {
                        let s = k as f32
                            + ((j - 1) as f32 + i as f32 / 8.0) / ARC_LENGTH_SAMPLES as f32;
                        let p = line.point(s);
                        total += (p - prev).norm();
                        prev = p;
                    }
                }
                *slot = total;
            }
        }
        Self {
            table,
            n,
            length_m: total,
        }
    }

    /// Length of one lap (m).
    pub fn length_m(&self) -> f32 {
        self.length_m
    }

    /// Arc length from gate 0 to parameter `s` (m), `s` taken modulo a lap: in
    /// `[0, length_m)`.
    pub fn at(&self, s: f32) -> f32 {
        let n = self.n.max(1) as f32;
        let s = s - libm::floorf(s / n) * n;
        let k = (libm::floorf(s) as usize).min(self.n.saturating_sub(1));
        self.along_segment(k, s - k as f32)
    }

    /// Arc length from gate 0 to the point at fraction `t ∈ [0, 1]` of segment `segment`
    /// (m): no wrap at the end of the last segment, so `along_segment(n − 1, 1.0)` is the lap
    /// length.
    pub fn along_segment(&self, segment: usize, t: f32) -> f32 {
        let Some(row) = self.table.get(segment % self.n.max(1)) else {
            return 0.0;
        };
        let x = t.clamp(0.0, 1.0) * ARC_LENGTH_SAMPLES as f32;
        let j = (libm::floorf(x) as usize).min(ARC_LENGTH_SAMPLES - 1);
        let frac = x - j as f32;
        let a = row.get(j).copied().unwrap_or(0.0);
        let b = row.get(j + 1).copied().unwrap_or(a);
        a + frac * (b - a)
    }
}

/// Next-gate bookkeeping of one drone: the gate it targets and how many it has passed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct GateProgress {
    /// Index of the gate the drone must pass next.
    pub target: usize,
    /// Gates passed since the last reset (a lap is `Track::len` gates).
    pub gates_passed: u32,
}

/// A gate event of one step, from [`GateProgress::advance`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GateEvent {
    /// Nothing happened at the target gate.
    None,
    /// The target gate `gate` was passed; the target moved to the next gate.
    Passed {
        /// The gate that was passed.
        gate: usize,
        /// Crossing point in that gate's frame (m).
        crossing_m: Vec3,
    },
    /// The target gate's plane was crossed outside the opening: a crash.
    Collided {
        /// The gate that was hit.
        gate: usize,
        /// Crossing point in that gate's frame (m).
        crossing_m: Vec3,
    },
}

impl GateProgress {
    /// Targeting gate `target`, nothing passed yet.
    pub const fn targeting(target: usize) -> Self {
        Self {
            target,
            gates_passed: 0,
        }
    }

    /// Tests the step `from_m → to_m` against the target gate and advances the target on a
    /// pass. A collision leaves the progress unchanged (the caller resets the drone).
    pub fn advance(&mut self, track: &Track<'_>, from_m: Vec3, to_m: Vec3) -> GateEvent {
        let gate = self.target;
        match track.crossing(gate, from_m, to_m) {
            GateCrossing::None => GateEvent::None,
            GateCrossing::Passed { crossing_m } => {
                self.target = track.next_index(gate);
                self.gates_passed = self.gates_passed.saturating_add(1);
                GateEvent::Passed { gate, crossing_m }
            }
            GateCrossing::Collided { crossing_m } => GateEvent::Collided { gate, crossing_m },
        }
    }
}

/// The crash rules of a race (docs/DESIGN.md "Gate rules"), besides gate collisions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CrashRules {
    /// A drone below this height has hit the ground (m). Paper: 0.1.
    pub ground_z_m: f32,
    /// A drone with any component of (target gate − drone) beyond this is out of bounds (m).
    /// Paper: 25 (stage 1), 15 (stage 2).
    pub max_gate_offset_m: f32,
    /// Two drones closer than this have collided (m). Paper: 0.2.
    pub min_separation_m: f32,
}

impl CrashRules {
    /// Stage 1 (time trial): ground 0.1 m, out of bounds 25 m.
    pub const STAGE1: Self = Self {
        ground_z_m: 0.1,
        max_gate_offset_m: 25.0,
        min_separation_m: 0.2,
    };
    /// Stage 2 (race): ground 0.1 m, out of bounds 15 m, separation 0.2 m.
    pub const STAGE2: Self = Self {
        ground_z_m: 0.1,
        max_gate_offset_m: 15.0,
        min_separation_m: 0.2,
    };

    /// True when a drone at `p_m` has hit the ground.
    pub fn below_ground(&self, p_m: Vec3) -> bool {
        p_m.z < self.ground_z_m
    }

    /// True when any component of `gate_m − p_m` is beyond the limit (or not finite).
    pub fn out_of_bounds(&self, gate_m: Vec3, p_m: Vec3) -> bool {
        let d = gate_m - p_m;
        !(libm::fabsf(d.x) <= self.max_gate_offset_m
            && libm::fabsf(d.y) <= self.max_gate_offset_m
            && libm::fabsf(d.z) <= self.max_gate_offset_m)
    }

    /// True when two drones at `a_m` and `b_m` are too close.
    pub fn too_close(&self, a_m: Vec3, b_m: Vec3) -> bool {
        (a_m - b_m).norm() < self.min_separation_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn deg(r: f32) -> f32 {
        r.to_degrees()
    }

    #[test]
    fn figure_eight_frames_are_the_design_table() {
        let t = Track::figure_eight();
        let headings = [0.0, -39.81, -140.19, 180.0, -140.19, -39.81];
        for (i, (g, h)) in t.gates().iter().zip(headings).enumerate() {
            assert!((g.frame.norm_squared() - 1.0).abs() < 1e-6, "g{i} not unit");
            let got = deg(g.frame.heading_rad());
            let diff = (got - h + 540.0) % 360.0 - 180.0;
            assert!(diff.abs() < 0.05, "g{i}: heading {got} vs {h}");
            assert!(g.forward().z.abs() < 1e-4, "g{i} forward is horizontal");
            assert_eq!(g.center_m.z, 1.0);
        }
        // g1 and g2 are upside down: their z axis points down.
        for i in [1, 2] {
            assert!(
                t.gate(i).frame.rotate(Vec3::Z).z < -0.999,
                "g{i} upside down"
            );
        }
        for i in [0, 3, 4, 5] {
            assert!(t.gate(i).frame.rotate(Vec3::Z).z > 0.999, "g{i} upright");
        }
    }

    #[test]
    fn straight_through_the_centre_passes() {
        let g = Track::figure_eight().gate(0);
        let c = g.crossing(Vec3::new(-0.5, 0.0, 1.0), Vec3::new(0.5, 0.0, 1.0), 0.8);
        assert_eq!(
            c,
            GateCrossing::Passed {
                crossing_m: Vec3::new(0.0, 0.0, 0.0)
            }
        );
    }

    #[test]
    fn crossing_outside_the_opening_is_a_collision() {
        let g = Track::figure_eight().gate(0);
        for (y, z) in [(0.9, 1.0), (0.0, 1.85), (-3.0, 1.0), (0.0, 0.15)] {
            let c = g.crossing(Vec3::new(-0.5, y, z), Vec3::new(0.5, y, z), 0.8);
            assert!(
                matches!(c, GateCrossing::Collided { .. }),
                "({y}, {z}): {c:?}"
            );
        }
    }

    #[test]
    fn back_to_front_and_parallel_moves_are_not_events() {
        let g = Track::figure_eight().gate(0);
        assert_eq!(
            g.crossing(Vec3::new(0.5, 0.0, 1.0), Vec3::new(-0.5, 0.0, 1.0), 0.8),
            GateCrossing::None
        );
        assert_eq!(
            g.crossing(Vec3::new(-0.5, 0.0, 1.0), Vec3::new(-0.5, 3.0, 1.0), 0.8),
            GateCrossing::None
        );
        assert_eq!(
            g.crossing(Vec3::new(-2.0, 0.0, 1.0), Vec3::new(-0.1, 0.0, 1.0), 0.8),
            GateCrossing::None
        );
    }

    /// Regression for the paper's end-point test: a fast drone whose position after the step
    /// lies outside the opening's square, but whose path crossed the plane inside it, passed.
    #[test]
    fn crossing_between_two_steps_is_judged_at_the_plane() {
        let g = Track::figure_eight().gate(0);
        // 20 m/s for 20 ms: 0.4 m per step, crossing at y = 0.625, ending at y = 1.0.
        let c = g.crossing(Vec3::new(-0.1, 0.5, 1.0), Vec3::new(0.3, 1.0, 1.0), 0.8);
        assert!(
            matches!(c, GateCrossing::Passed { crossing_m } if (crossing_m.y - 0.625).abs() < 1e-5)
        );
        // ... and the converse: ending inside the square after crossing outside it.
        let c = g.crossing(Vec3::new(-0.1, 1.2, 1.0), Vec3::new(0.3, 0.0, 1.0), 0.8);
        assert!(matches!(c, GateCrossing::Collided { .. }), "{c:?}");
    }

    #[test]
    fn upside_down_gate_is_passed_along_its_own_axis() {
        let t = Track::figure_eight();
        let g = t.gate(1);
        let before = g.to_world_frame(Vec3::new(-0.3, 0.2, -0.3));
        let after = g.to_world_frame(Vec3::new(0.3, 0.2, -0.3));
        assert!(matches!(
            g.crossing(before, after, 0.8),
            GateCrossing::Passed { .. }
        ));
        assert_eq!(g.crossing(after, before, 0.8), GateCrossing::None);
    }

    #[test]
    fn a_lap_through_every_gate_in_order_advances_the_target_around() {
        let t = Track::figure_eight();
        let mut p = GateProgress::targeting(0);
        for lap in 0..2 {
            for i in 0..t.len() {
                let g = t.gate(i);
                let e = p.advance(
                    &t,
                    g.to_world_frame(Vec3::new(-0.2, 0.1, 0.1)),
                    g.to_world_frame(Vec3::new(0.2, 0.1, 0.1)),
                );
                assert!(
                    matches!(e, GateEvent::Passed { gate, .. } if gate == i),
                    "lap {lap} gate {i}: {e:?}"
                );
            }
        }
        assert_eq!(
            p,
            GateProgress {
                target: 0,
                gates_passed: 12
            }
        );
    }

    #[test]
    fn passing_a_gate_that_is_not_the_target_is_no_event() {
        // g3 sits at g0's centre facing the other way: flying g0's direction while targeting
        // g3 is neither a pass nor a crash.
        let t = Track::figure_eight();
        let mut p = GateProgress::targeting(3);
        let e = p.advance(&t, Vec3::new(-0.3, 0.0, 1.0), Vec3::new(0.3, 0.0, 1.0));
        assert_eq!(e, GateEvent::None);
        assert_eq!(p.target, 3);
    }

    #[test]
    fn crash_rules() {
        let r = CrashRules::STAGE1;
        assert!(r.below_ground(Vec3::new(0.0, 0.0, 0.05)));
        assert!(!r.below_ground(Vec3::new(0.0, 0.0, 0.15)));
        assert!(r.out_of_bounds(Vec3::new(0.0, 0.0, 1.0), Vec3::new(25.5, 0.0, 1.0)));
        assert!(!r.out_of_bounds(Vec3::new(0.0, 0.0, 1.0), Vec3::new(24.5, -24.0, 1.0)));
        assert!(r.out_of_bounds(Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0)));
        assert!(CrashRules::STAGE2.out_of_bounds(Vec3::ZERO, Vec3::new(0.0, 15.5, 0.0)));
        assert!(r.too_close(Vec3::ZERO, Vec3::new(0.1, 0.1, 0.0)));
        assert!(!r.too_close(Vec3::ZERO, Vec3::new(0.2, 0.1, 0.0)));
    }

    #[test]
    fn centerline_is_the_papers_spline() {
        let t = Track::figure_eight();
        let c = Centerline::new(&t);
        // docs/DESIGN.md "Track": 68.66 m (scipy's periodic CubicSpline: 68.656).
        assert!((c.length_m() - 68.656).abs() < 0.02, "{}", c.length_m());
        for (k, g) in t.gates().iter().enumerate() {
            assert!(
                (c.point(k as f32) - g.center_m).norm() < 1e-4,
                "passes g{k}"
            );
        }
        // The spline's headings at g1, g2, g4, g5 are the gate headings (g0 and g3 overridden).
        for k in [1, 2, 4, 5] {
            let d = c.tangent(k as f32);
            let spline = libm::atan2f(d.y, d.x);
            let gate = t.gate(k).frame.heading_rad();
            assert!(
                (spline - gate).abs() < 2e-3,
                "g{k}: {} vs {}",
                deg(spline),
                deg(gate)
            );
        }
        // C1 continuity at the knots.
        for k in 0..6 {
            let s = k as f32;
            assert!((c.tangent(s - 1e-4) - c.tangent(s + 1e-4)).norm() < 1e-2);
        }
        // The nearest point of a point on the line is itself.
        let s = c.nearest_on_segment(1, c.point(1.37));
        assert!((s - 1.37).abs() < 2e-3, "{s}");
    }

    #[test]
    fn arc_length_table_matches_the_fine_polyline() {
        let c = Centerline::new(&Track::figure_eight());
        let a = ArcLength::new(&c);
        assert!((a.length_m() - c.length_m()).abs() < 1e-3);
        assert_eq!(a.at(0.0), 0.0);
        let mut before = 0.0;
        for k in 0..6 {
            before += if k > 0 {
                c.segment_length_m(k - 1)
            } else {
                0.0
            };
            assert!((a.at(k as f32) - before).abs() < 2e-3, "gate {k}");
        }
        // Mid-segment against a 4,096-chord polyline from gate 0.
        let s = 2.37f32;
        let mut fine = 0.0;
        let mut prev = c.point(0.0);
        for i in 1..=4096 {
            let p = c.point(s * i as f32 / 4096.0);
            fine += (p - prev).norm();
            prev = p;
        }
        assert!((a.at(s) - fine).abs() < 1e-3, "{} vs {fine}", a.at(s));
        // Periodic, and increasing along the lap.
        assert!((a.at(s + 6.0) - a.at(s)).abs() < 1e-4);
        assert!((a.along_segment(5, 1.0) - a.length_m()).abs() < 1e-6);
        assert!((a.along_segment(2, 0.37) - a.at(2.37)).abs() < 1e-5);
        let mut last = -1.0;
        for i in 0..600 {
            let v = a.at(i as f32 / 100.0);
            assert!(v > last);
            last = v;
        }
    }

    #[test]
    fn empty_track_is_refused() {
        assert_eq!(Track::new(&[], 0.8).err(), Some(TrackError::NoGates));
    }

    proptest! {
        #[test]
        fn gate_frame_round_trips(i in 0usize..6, x in -30.0f32..30.0, y in -30.0f32..30.0, z in -5.0f32..5.0) {
            let g = Track::figure_eight().gate(i);
            let p = Vec3::new(x, y, z);
            let back = g.to_world_frame(g.to_gate_frame(p));
            prop_assert!((back - p).norm() < 1e-4);
        }

        #[test]
        fn crossing_point_lies_on_the_segment_and_the_plane(
            i in 0usize..6,
            a in (-3.0f32..-0.01, -2.0f32..2.0, -2.0f32..2.0),
            b in (0.0f32..3.0, -2.0f32..2.0, -2.0f32..2.0),
        ) {
            let g = Track::figure_eight().gate(i);
            let from = g.to_world_frame(Vec3::new(a.0, a.1, a.2));
            let to = g.to_world_frame(Vec3::new(b.0, b.1, b.2));
            let (p, inside) = match g.crossing(from, to, 0.8) {
                GateCrossing::Passed { crossing_m } => (crossing_m, true),
                GateCrossing::Collided { crossing_m } => (crossing_m, false),
                GateCrossing::None => return Err(TestCaseError::fail("front-to-back segment not seen")),
            };
            let t = -a.0 / (b.0 - a.0);
            prop_assert!((p.y - (a.1 + t * (b.1 - a.1))).abs() < 1e-3);
            prop_assert!((p.z - (a.2 + t * (b.2 - a.2))).abs() < 1e-3);
            prop_assert_eq!(inside, p.y.abs() < 0.8 && p.z.abs() < 0.8);
        }
    }
}
