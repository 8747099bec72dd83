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
        Self { center_m, frame: frame.normalized() }
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

/// The paper's life-size figure-8 (SPEC "Track"): centres at z = 1 m, frames from the
/// authors' code (Frenet frames of a periodic cubic spline through the centres with uniform
/// knots, g0 and g3 overridden; g1 and g2 are upside down).
pub static FIGURE_EIGHT: [Gate; FIGURE_EIGHT_GATES] = [
    Gate { center_m: Vec3::new(0.0, 0.0, 1.0), frame: Quat::new(1.0, 0.0, 0.0, 0.0) },
    Gate { center_m: Vec3::new(10.0, 5.0, 1.0), frame: Quat::new(0.0, 0.9403, -0.3404, 0.0) },
    Gate { center_m: Vec3::new(10.0, -5.0, 1.0), frame: Quat::new(0.0, -0.3404, 0.9403, 0.0) },
    Gate { center_m: Vec3::new(0.0, 0.0, 1.0), frame: Quat::new(0.0, 0.0, 0.0, 1.0) },
    Gate { center_m: Vec3::new(-10.0, 5.0, 1.0), frame: Quat::new(0.3404, 0.0, 0.0, -0.9403) },
    Gate { center_m: Vec3::new(-10.0, -5.0, 1.0), frame: Quat::new(0.9403, 0.0, 0.0, -0.3404) },
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
        Self { gates: &FIGURE_EIGHT, opening_half_size_m: 0.8 }
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
        Ok(Self { gates, opening_half_size_m })
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
        self.gates.get(index % n).copied().unwrap_or(Gate::new(Vec3::ZERO, Quat::IDENTITY))
    }

    /// The index of the gate after `index`.
    pub fn next_index(&self, index: usize) -> usize {
        (index + 1) % self.gates.len().max(1)
    }

    /// The segment test of [`Gate::crossing`] against gate `index` with this track's opening.
    pub fn crossing(&self, index: usize, from_m: Vec3, to_m: Vec3) -> GateCrossing {
        self.gate(index).crossing(from_m, to_m, self.opening_half_size_m)
    }
}

/// Next-gate bookkeeping of one drone: the gate it targets and how many it has passed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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
        Self { target, gates_passed: 0 }
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

/// The crash rules of a race (SPEC "Track"), besides gate collisions.
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
    pub const STAGE1: Self = Self { ground_z_m: 0.1, max_gate_offset_m: 25.0, min_separation_m: 0.2 };
    /// Stage 2 (race): ground 0.1 m, out of bounds 15 m, separation 0.2 m.
    pub const STAGE2: Self = Self { ground_z_m: 0.1, max_gate_offset_m: 15.0, min_separation_m: 0.2 };

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
