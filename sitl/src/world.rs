//! The racing world: N cf2x drones on a track, their gate progress, and the crash rules
//! (docs/DESIGN.md "Gate rules"). Stepping integrates every drone and then judges the step with
//! firmware-core's gate test and crash rules; nothing here re-implements them.
//!
//! **Layout.** A world's mutable state is a plain array `[Drone; N]` (one drone is 84 bytes:
//! position, attitude, velocity, rates, propeller speeds and gate progress), and a batch of
//! worlds is one contiguous slice of those arrays. The immutable parts (track, preset,
//! crash rules, control period) live once in [`World`] and are shared by every world of a
//! batch, so a step reads ~1.3 cache lines of state per drone and nothing else. The work is
//! compute-bound (four RK4 stages per substep), so [`World::par_step`] splits the slice into
//! chunks of [`PAR_CHUNK_WORLDS`] worlds for rayon; each world is independent, so the result
//! does not depend on the number of threads or their scheduling.

use crate::dynamics::{Body, Preset};
use firmware_core::math::{Quat, Vec3};
use firmware_core::track::{Centerline, CrashRules, GateEvent, GateProgress, Track};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use rayon::prelude::*;

/// Worlds per rayon task in [`World::par_step`]: large enough to amortise the task overhead
/// (~1 µs) over ~100 µs of work, small enough to balance two to sixteen cores over 4,096 worlds.
pub const PAR_CHUNK_WORLDS: usize = 256;

/// One drone of a world: its rigid body and the referee's view of its gate progress.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Drone {
    /// Rigid-body state and propeller speeds.
    pub body: Body,
    /// The gate it must pass next and how many it has passed since its spawn.
    pub progress: GateProgress,
}

impl Drone {
    /// A drone placed at `spawn`, at rest, propellers stopped.
    pub fn spawned(spawn: SpawnPoint) -> Self {
        Self {
            body: Body::new(spawn.state),
            progress: GateProgress::targeting(spawn.target_gate),
        }
    }

    /// Position (m, world).
    pub fn position_m(&self) -> Vec3 {
        self.body.state.position_m
    }
}

/// Why a drone crashed (docs/DESIGN.md "Gate rules": every cause ends in a reset).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CrashCause {
    /// Crossed the target gate's plane outside the opening.
    GateFrame {
        /// The gate that was hit.
        gate: usize,
    },
    /// Below the ground height of the crash rules (z < 0.1 m).
    Ground,
    /// A component of (target gate − drone) beyond the crash rules' limit.
    OutOfBounds,
    /// Came closer than the crash rules' separation to drone `other`.
    Collision {
        /// Index of the other drone in the world.
        other: usize,
    },
    /// The state is no longer finite (NaN or infinity): a diverged simulation.
    NonFinite,
}

impl core::fmt::Display for CrashCause {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::GateFrame { gate } => write!(f, "hit the frame of gate g{gate}"),
            Self::Ground => f.write_str("hit the ground"),
            Self::OutOfBounds => f.write_str("left the track bounds"),
            Self::Collision { other } => write!(f, "collided with drone {other}"),
            Self::NonFinite => f.write_str("state diverged (not finite)"),
        }
    }
}

/// What one drone did in one step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DroneStep {
    /// The gate event at its target gate.
    pub gate_event: GateEvent,
    /// The crash of this step, if any.
    pub crash: Option<CrashCause>,
}

impl Default for DroneStep {
    fn default() -> Self {
        Self {
            gate_event: GateEvent::None,
            crash: None,
        }
    }
}

impl DroneStep {
    /// The gate passed in this step, if any.
    pub fn passed_gate(&self) -> Option<usize> {
        match self.gate_event {
            GateEvent::Passed { gate, .. } if self.crash.is_none() => Some(gate),
            _ => None,
        }
    }
}

/// Where and towards which gate a drone starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpawnPoint {
    /// Initial state (at rest in every spawn of docs/DESIGN.md "Spawns").
    pub state: VehicleState,
    /// The first gate to pass.
    pub target_gate: usize,
}

/// The stage-1 spawn of the paper's code: (−1, −1, 1) m, level, at rest, first target g0.
pub fn stage1_spawn() -> SpawnPoint {
    SpawnPoint {
        state: VehicleState::at_rest(Vec3::new(-1.0, -1.0, 1.0), Quat::IDENTITY),
        target_gate: 0,
    }
}

/// The stage-2 spawn of the paper's code before gate `gate`: `[ego, opponent]`, the ego
/// 2.0 m and the opponent 1.0 m before the gate along its +x axis, both at rest and
/// targeting it. Both face the gate's heading, level (the frames of g1 and g2 are upside
/// down; only their heading is used).
pub fn stage2_spawn(track: &Track<'_>, gate: usize) -> [SpawnPoint; 2] {
    let g = track.gate(gate);
    let index = gate % track.len().max(1);
    let attitude = Quat::from_yaw(g.frame.heading_rad());
    let before = |d: f32| SpawnPoint {
        state: VehicleState::at_rest(g.center_m - g.forward().scale(d), attitude),
        target_gate: index,
    };
    [before(2.0), before(1.0)]
}

/// A spawn on the centreline at parameter `s` (gate k at `s = k`, see [`Centerline`]): at
/// rest, level, facing along the line, targeting the gate that ends the segment. For
/// training from everywhere on the track rather than one fixed start.
pub fn along_track_spawn(line: &Centerline, s: f32) -> SpawnPoint {
    let n = line.segments().max(1);
    let s = s.rem_euclid(n as f32);
    let tangent = line.tangent(s);
    let heading = libm::atan2f(tangent.y, tangent.x);
    SpawnPoint {
        state: VehicleState::at_rest(line.point(s), Quat::from_yaw(heading)),
        target_gate: (libm::floorf(s) as usize + 1) % n,
    }
}

/// The world's control period (ns): one [`World::step`]. The paper's 20 ms (50 Hz). A
/// recurrent blob trained at another period is refused by every pilot built here.
pub const CONTROL_PERIOD_NS: u32 = firmware_core::PAPER_CONTROL_PERIOD_NS;

/// The immutable part of a world, shared by every world of a batch: the track, the
/// dynamics preset, the crash rules and the control period.
#[derive(Clone, Copy, Debug)]
pub struct World {
    /// The track (gates and opening).
    pub track: Track<'static>,
    /// Airframe and integrator parameters.
    pub preset: Preset,
    /// Ground, bounds and separation limits.
    pub rules: CrashRules,
    /// Control period: simulated time of one [`World::step`] (s). Paper: 0.02.
    pub dt_s: f32,
}

impl World {
    /// The figure-8 with `preset`, `rules` and the paper's 50 Hz control.
    pub fn figure_eight(preset: Preset, rules: CrashRules) -> Self {
        Self {
            track: Track::figure_eight(),
            preset,
            rules,
            dt_s: CONTROL_PERIOD_NS as f32 * 1e-9,
        }
    }

    /// One control period: every drone flies its command, then [`World::judge`] scores the
    /// step. Crashed drones are left where they crashed; the caller respawns them.
    pub fn step<const N: usize>(
        &self,
        drones: &mut [Drone; N],
        commands: &[MotorCommand; N],
    ) -> [DroneStep; N] {
        self.step_airframes(drones, commands, &[self.preset; N])
    }

    /// [`World::step`] with drone `i` flying airframe `presets[i]` instead of the world's
    /// (a perturbed ego, `crate::perturb`).
    pub fn step_airframes<const N: usize>(
        &self,
        drones: &mut [Drone; N],
        commands: &[MotorCommand; N],
        presets: &[Preset; N],
    ) -> [DroneStep; N] {
        let from = drones.each_ref().map(Drone::position_m);
        for ((d, c), p) in drones.iter_mut().zip(commands).zip(presets) {
            d.body.step(p, c, self.dt_s);
        }
        self.judge(drones, &from)
    }

    /// Scores a step of every drone from `from` (m) to its current position: the segment gate
    /// test at its target (which advances the target on a pass), then the crash rules:
    /// non-finite state, gate frame, ground, bounds, and for two or more drones the closest
    /// approach of every pair during the step (both moving in straight lines).
    pub fn judge<const N: usize>(
        &self,
        drones: &mut [Drone; N],
        from: &[Vec3; N],
    ) -> [DroneStep; N] {
        let mut out = [DroneStep::default(); N];
        for ((d, o), &a) in drones.iter_mut().zip(out.iter_mut()).zip(from) {
            *o = self.judge_own(d, a);
        }
        for i in 0..N {
            for j in i + 1..N {
                let (Some(di), Some(dj)) = (drones.get(i), drones.get(j)) else {
                    continue;
                };
                let (Some(&fi), Some(&fj)) = (from.get(i), from.get(j)) else {
                    continue;
                };
                if self.collided([fi, fj], [di.position_m(), dj.position_m()]) {
                    for (me, other) in [(i, j), (j, i)] {
                        if let Some(o) = out.get_mut(me) {
                            o.crash.get_or_insert(CrashCause::Collision { other });
                        }
                    }
                }
            }
        }
        out
    }

    /// One step of `ego` (index 0) beside drone 1, whose own step is already known: it moved
    /// from `other_from` to `other` and its own rules gave `other_step` (a flight recorded
    /// alone, as the race env replays its opponent's). The ego is stepped and judged, and the
    /// pair's closest approach tested, exactly as [`World::step_airframes`] does for the two.
    pub fn step_beside(
        &self,
        ego: &mut Drone,
        command: &MotorCommand,
        airframe: &Preset,
        other_from: Vec3,
        other: &Drone,
        other_step: DroneStep,
    ) -> [DroneStep; 2] {
        let from = ego.position_m();
        ego.body.step(airframe, command, self.dt_s);
        let mut out = [self.judge_own(ego, from), other_step];
        if self.collided([from, other_from], [ego.position_m(), other.position_m()]) {
            for (o, other) in out.iter_mut().zip([1, 0]) {
                o.crash.get_or_insert(CrashCause::Collision { other });
            }
        }
        out
    }

    /// One drone's own rules for its step from `a` (m) to its current position.
    fn judge_own(&self, d: &mut Drone, a: Vec3) -> DroneStep {
        let b = d.body.state.position_m;
        if !d.body.state.is_finite() {
            return DroneStep {
                crash: Some(CrashCause::NonFinite),
                ..DroneStep::default()
            };
        }
        let gate_event = d.progress.advance(&self.track, a, b);
        let target = self.track.gate(d.progress.target).center_m;
        let crash = if let GateEvent::Collided { gate, .. } = gate_event {
            Some(CrashCause::GateFrame { gate })
        } else if self.rules.below_ground(b) {
            Some(CrashCause::Ground)
        } else if self.rules.out_of_bounds(target, b) {
            Some(CrashCause::OutOfBounds)
        } else {
            None
        };
        DroneStep { gate_event, crash }
    }

    /// Whether two drones moving in straight lines from `from` to `to` (m) come closer than
    /// the rules' separation during the step.
    fn collided(&self, from: [Vec3; 2], to: [Vec3; 2]) -> bool {
        closest_approach_m(from[0] - from[1], to[0] - to[1]) < self.rules.min_separation_m
    }

    /// Steps many independent worlds in parallel (rayon): world `i` flies `commands[i]` and
    /// its result goes to `out[i]`. Deterministic: the same inputs give the same outputs on
    /// any number of threads. The three slices must have the same length (extra elements of
    /// the longer ones are left alone).
    pub fn par_step<const N: usize>(
        &self,
        worlds: &mut [[Drone; N]],
        commands: &[[MotorCommand; N]],
        out: &mut [[DroneStep; N]],
    ) {
        worlds
            .par_chunks_mut(PAR_CHUNK_WORLDS)
            .zip(commands.par_chunks(PAR_CHUNK_WORLDS))
            .zip(out.par_chunks_mut(PAR_CHUNK_WORLDS))
            .for_each(|((w, c), o)| {
                for ((w, c), o) in w.iter_mut().zip(c).zip(o) {
                    *o = self.step(w, c);
                }
            });
    }
}

/// The smallest distance between two drones during a step (m), given their relative
/// position at its start and end, with both moving in straight lines.
fn closest_approach_m(start: Vec3, end: Vec3) -> f32 {
    let d = end - start;
    let dd = d.dot(d);
    let t = if dd > 0.0 {
        (-start.dot(d) / dd).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (start + d.scale(t)).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_approach_finds_a_pass_between_the_end_points() {
        // 1 m apart at both ends, but crossing through each other in between.
        let a = closest_approach_m(Vec3::new(-1.0, 0.05, 0.0), Vec3::new(1.0, 0.05, 0.0));
        assert!((a - 0.05).abs() < 1e-6);
        assert_eq!(
            closest_approach_m(Vec3::new(0.3, 0.0, 0.0), Vec3::new(0.3, 0.0, 0.0)),
            0.3
        );
        assert!(
            (closest_approach_m(Vec3::new(1.0, 0.0, 0.0), Vec3::new(2.0, 0.0, 0.0)) - 1.0).abs()
                < 1e-6
        );
    }

    #[test]
    fn spawns_follow_the_design() {
        let track = Track::figure_eight();
        for k in 0..6 {
            let [ego, opp] = stage2_spawn(&track, k);
            let g = track.gate(k);
            assert_eq!((ego.target_gate, opp.target_gate), (k, k));
            let e = g.to_gate_frame(ego.state.position_m);
            let o = g.to_gate_frame(opp.state.position_m);
            assert!(
                (e - Vec3::new(-2.0, 0.0, 0.0)).norm() < 1e-5,
                "g{k} ego {e:?}"
            );
            assert!(
                (o - Vec3::new(-1.0, 0.0, 0.0)).norm() < 1e-5,
                "g{k} opp {o:?}"
            );
            // Upright, facing the direction of travel.
            let up = ego.state.attitude.rotate(Vec3::Z);
            assert!((up - Vec3::Z).norm() < 1e-6);
            let fwd = ego.state.attitude.rotate(Vec3::X);
            assert!(fwd.dot(g.forward()) > 0.9999, "g{k}");
        }
        let s1 = stage1_spawn();
        assert_eq!(s1.state.position_m, Vec3::new(-1.0, -1.0, 1.0));
        assert_eq!(s1.target_gate, 0);
    }

    #[test]
    fn along_track_spawn_targets_the_end_of_its_segment() {
        let line = Centerline::new(&Track::figure_eight());
        let sp = along_track_spawn(&line, 2.5);
        assert_eq!(sp.target_gate, 3);
        assert!((sp.state.position_m - line.point(2.5)).norm() < 1e-6);
        assert_eq!(along_track_spawn(&line, 5.9).target_gate, 0);
        assert_eq!(along_track_spawn(&line, -0.5).target_gate, 0);
    }
}
