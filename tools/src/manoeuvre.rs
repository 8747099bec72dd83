//! The numbers of an overtake (issue "race" item 3): how fast the ego came in and went out,
//! and which line it took relative to the turn, so a pass can be called the paper's
//! wide-entry, tight-exit manoeuvre (or something else) from measurements.
//!
//! Each overtake is sampled at three moments of the recorded trace: entry (`LOOK_S` before
//! the step the ego took the lead), the pass itself, and exit (`LOOK_S` after), each clamped
//! to the flight the pass belongs to (between two respawns). At each moment:
//! - speeds (m/s) of both drones;
//! - each drone's *inside offset* (m): its horizontal distance from the centreline, positive
//!   towards the inside of the turn the centreline makes at the pass (towards its centre of
//!   curvature there), negative towards the outside; every sample of a pass uses that one
//!   side, and a pass on a straight (curvature below [`STRAIGHT_PER_M`]) counts left as
//!   inside;
//! - the ego's lead along the track (m, the referee's).
//!
//! The centreline segment a drone flies is the nearest one at the pass, then the nearest of
//! that segment and its two neighbours at entry and exit (the figure-8 crosses itself; at
//! its crossing, between g0 and g3, the nearest segment at the pass can be the other
//! branch, so a pass there may be named by the other gate).

use firmware_core::math::Vec3;
use firmware_core::track::{Centerline, Track};
use sitl::referee::Trace;

/// Seconds before and after the pass at which entry and exit are sampled.
pub const LOOK_S: f32 = 1.0;

/// Curvature (1/m) below which the centreline counts as straight.
pub const STRAIGHT_PER_M: f32 = 0.02;

/// One drone at one moment of a pass.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Speed (m/s).
    pub speed_mps: f32,
    /// Horizontal offset from the centreline (m), positive towards the inside of the turn.
    pub inside_m: f32,
}

/// Both drones at one moment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Moment {
    /// Seconds from the pass (negative before).
    pub dt_s: f32,
    /// The ego.
    pub ego: Sample,
    /// The opponent.
    pub opponent: Sample,
    /// The ego's lead along the track (m); `None` where the trace has none.
    pub lead_m: Option<f32>,
}

/// The measured manoeuvre of one overtake.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Manoeuvre {
    /// The gate the ego flew towards when it took the lead.
    pub gate: usize,
    /// Curvature of the centreline at the pass (1/m), signed: positive for a left turn.
    pub curvature_per_m: f32,
    /// Whether the lead was held for 2 s.
    pub sustained: bool,
    /// [`LOOK_S`] before the pass (or the flight's start).
    pub entry: Moment,
    /// The step the ego took the lead.
    pub pass: Moment,
    /// [`LOOK_S`] after the pass (or the flight's end).
    pub exit: Moment,
}

impl Manoeuvre {
    /// The paper's wide-entry, tight-exit pass: the ego enters outside the opponent's line
    /// and leaves inside it.
    pub fn wide_in_tight_out(&self) -> bool {
        self.entry.ego.inside_m < self.entry.opponent.inside_m
            && self.exit.ego.inside_m > self.exit.opponent.inside_m
    }

    /// How it was passed, in words: "wide in, tight out", "inside line", "outside line",
    /// or "tight in, wide out".
    pub fn kind(&self) -> &'static str {
        let inside_at_entry = self.entry.ego.inside_m >= self.entry.opponent.inside_m;
        let inside_at_exit = self.exit.ego.inside_m >= self.exit.opponent.inside_m;
        match (inside_at_entry, inside_at_exit) {
            (false, true) => "wide in, tight out",
            (true, true) => "inside line",
            (false, false) => "outside line",
            (true, false) => "tight in, wide out",
        }
    }
}

/// The centreline's geometry as the manoeuvre needs it.
pub struct Line {
    line: Centerline,
}

impl Line {
    /// The line of `track`.
    pub fn new(track: &Track<'_>) -> Self {
        Self {
            line: Centerline::new(track),
        }
    }

    fn segments(&self) -> usize {
        self.line.segments().max(1)
    }

    /// The segment and the parameter of the nearest point to `p` among `segments`.
    fn nearest(&self, p: Vec3, segments: impl Iterator<Item = usize>) -> (usize, f32) {
        let d2 = |s: f32| {
            let d = self.line.point(s) - p;
            d.dot(d)
        };
        segments
            .map(|k| (k, self.line.nearest_on_segment(k, p)))
            .fold(None, |best: Option<(usize, f32)>, (k, s)| match best {
                Some(b) if d2(b.1) <= d2(s) => Some(b),
                _ => Some((k, s)),
            })
            .unwrap_or((0, 0.0))
    }

    /// Signed horizontal curvature (1/m) at parameter `s`: positive for a left turn.
    fn curvature_per_m(&self, s: f32) -> f32 {
        let h = 0.01;
        let (a, b) = (self.line.tangent(s - h), self.line.tangent(s + h));
        let (la, lb) = (
            (a.x * a.x + a.y * a.y).sqrt(),
            (b.x * b.x + b.y * b.y).sqrt(),
        );
        if la < 1e-6 || lb < 1e-6 {
            return 0.0;
        }
        // The heading's change per metre of horizontal arc.
        let cross = (a.x * b.y - a.y * b.x) / (la * lb);
        let dot = (a.x * b.x + a.y * b.y) / (la * lb);
        cross.atan2(dot) / (0.5 * (la + lb) * 2.0 * h)
    }

    /// Offset of `p` from the point at `s` (m), horizontal, positive to the left of the
    /// line's direction there times `side` (+1: left is inside, -1: right is).
    fn offset_m(&self, s: f32, p: Vec3, side: f32) -> f32 {
        let t = self.line.tangent(s);
        let norm = (t.x * t.x + t.y * t.y).sqrt().max(1e-6);
        let left = Vec3::new(-t.y / norm, t.x / norm, 0.0);
        (p - self.line.point(s)).dot(left) * side
    }

    /// +1 where the line turns left at `s` or runs straight, -1 where it turns right.
    fn inside_side(&self, s: f32) -> f32 {
        if self.curvature_per_m(s) <= -STRAIGHT_PER_M {
            -1.0
        } else {
            1.0
        }
    }
}

/// The manoeuvre of overtake `k` of `trace`; `None` where the trace lacks the speeds or the
/// opponent (a time trial, or a file written before they were recorded).
pub fn measure(line: &Line, trace: &Trace, k: usize) -> Option<Manoeuvre> {
    let mark = *trace.overtakes.get(k)?;
    let steps = trace.ego_m.len();
    if trace.opponent_m.len() != steps
        || trace.ego_speed_mps.len() != steps
        || trace.opponent_speed_mps.len() != steps
        || mark.step == 0
        || mark.step as usize > steps
    {
        return None;
    }
    let at = mark.step as usize - 1;
    // The flight: after the last respawn at or before the pass, up to the next one.
    let first = trace
        .respawns
        .iter()
        .map(|&r| r as usize)
        .filter(|&r| r <= at)
        .max()
        .unwrap_or(0);
    let last = trace
        .respawns
        .iter()
        .map(|&r| r as usize)
        .filter(|&r| r > at)
        .min()
        .map_or(steps - 1, |r| r - 1);
    let look = (LOOK_S / trace.dt_s.max(1e-3)).round() as usize;
    let n = line.segments();
    let (segment, ego_s) = line.nearest(*trace.ego_m.get(at)?, 0..n);
    let near = [segment + n - 1, segment, segment + 1].map(|k| k % n);
    // Every sample of the pass is signed by the turn at the pass, so entry and exit compare
    // sides of one turn even where the line changes direction between them.
    let side = line.inside_side(ego_s);
    let moment = |i: usize| -> Option<Moment> {
        let sample = |p: Vec3, v: f32| Sample {
            speed_mps: v,
            inside_m: line.offset_m(line.nearest(p, near.into_iter()).1, p, side),
        };
        Some(Moment {
            dt_s: (i as f32 - at as f32) * trace.dt_s,
            ego: sample(*trace.ego_m.get(i)?, *trace.ego_speed_mps.get(i)?),
            opponent: sample(*trace.opponent_m.get(i)?, *trace.opponent_speed_mps.get(i)?),
            lead_m: trace.lead_m.get(i).copied().flatten(),
        })
    };
    Some(Manoeuvre {
        gate: (segment + 1) % n,
        curvature_per_m: line.curvature_per_m(ego_s),
        sustained: mark.sustained,
        entry: moment(at.saturating_sub(look).max(first))?,
        pass: moment(at)?,
        exit: moment((at + look).min(last))?,
    })
}

/// Every overtake of `episodes` that `measure` can read.
pub fn measure_all(line: &Line, episodes: &[Trace]) -> Vec<Manoeuvre> {
    episodes
        .iter()
        .flat_map(|t| (0..t.overtakes.len()).filter_map(move |k| measure(line, t, k)))
        .collect()
}

/// A Markdown table of the sustained overtakes' means per gate: count, how many of each
/// kind, and the ego's and the opponent's speeds and inside offsets at entry, pass and exit.
pub fn summary(manoeuvres: &[Manoeuvre]) -> String {
    let mut gates: Vec<usize> = manoeuvres
        .iter()
        .filter(|m| m.sustained)
        .map(|m| m.gate)
        .collect();
    gates.sort_unstable();
    gates.dedup();
    let mut out = String::from(
        "| gate | sustained | turn | wide in, tight out | inside line | outside line | tight in, wide out | ego speed in → pass → out (m/s) | opponent speed in → out (m/s) | ego inside offset in → pass → out (m) | opponent inside offset in → pass → out (m) |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for g in gates {
        let ms: Vec<&Manoeuvre> = manoeuvres
            .iter()
            .filter(|m| m.sustained && m.gate == g)
            .collect();
        let n = ms.len() as f32;
        let mean = |f: &dyn Fn(&Manoeuvre) -> f32| ms.iter().map(|m| f(m)).sum::<f32>() / n;
        let share = |kind: &str| ms.iter().filter(|m| m.kind() == kind).count();
        let curvature = mean(&|m| m.curvature_per_m);
        let turn = if curvature >= STRAIGHT_PER_M {
            format!("left, radius {:.1} m", 1.0 / curvature)
        } else if curvature <= -STRAIGHT_PER_M {
            format!("right, radius {:.1} m", -1.0 / curvature)
        } else {
            "straight".to_string()
        };
        out += &format!(
            "| g{g} | {} | {turn} | {} | {} | {} | {} | {:.1} → {:.1} → {:.1} | {:.1} → {:.1} | {:+.2} → {:+.2} → {:+.2} | {:+.2} → {:+.2} → {:+.2} |\n",
            ms.len(),
            share("wide in, tight out"),
            share("inside line"),
            share("outside line"),
            share("tight in, wide out"),
            mean(&|m| m.entry.ego.speed_mps),
            mean(&|m| m.pass.ego.speed_mps),
            mean(&|m| m.exit.ego.speed_mps),
            mean(&|m| m.entry.opponent.speed_mps),
            mean(&|m| m.exit.opponent.speed_mps),
            mean(&|m| m.entry.ego.inside_m),
            mean(&|m| m.pass.ego.inside_m),
            mean(&|m| m.exit.ego.inside_m),
            mean(&|m| m.entry.opponent.inside_m),
            mean(&|m| m.pass.opponent.inside_m),
            mean(&|m| m.exit.opponent.inside_m),
        );
    }
    out
}

/// One overtake's numbers in a line.
pub fn describe(m: &Manoeuvre) -> String {
    let moment = |name: &str, x: &Moment| {
        format!(
            "{name} ({:+.1} s): ego {:.1} m/s at {:+.2} m, opponent {:.1} m/s at {:+.2} m{}",
            x.dt_s,
            x.ego.speed_mps,
            x.ego.inside_m,
            x.opponent.speed_mps,
            x.opponent.inside_m,
            x.lead_m
                .map(|l| format!(", lead {l:+.2} m"))
                .unwrap_or_default()
        )
    };
    format!(
        "towards g{} ({}), {}: {}; {}; {} (offsets from the centreline, + inside)",
        m.gate,
        if m.curvature_per_m >= STRAIGHT_PER_M {
            "a left turn"
        } else if m.curvature_per_m <= -STRAIGHT_PER_M {
            "a right turn"
        } else {
            "a straight"
        },
        m.kind(),
        moment("entry", &m.entry),
        moment("pass", &m.pass),
        moment("exit", &m.exit),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use sitl::referee::OvertakeMark;

    /// A scripted pass on the figure-8's centreline, in a left and in a right turn: the
    /// opponent on the line, the ego 0.5 m outside the turn before the pass and 0.5 m
    /// inside after it, faster.
    #[test]
    fn a_scripted_wide_in_tight_out_pass_is_measured_as_one() {
        let track = Track::figure_eight();
        let line = Line::new(&track);
        // Turns found without the code under test: the sign of the z component of
        // (P(s) - P(s - h)) x (P(s + h) - P(s)), positive for a left turn seen from above.
        let c = Centerline::new(&track);
        let bend = |s: f32| {
            let h = 0.05;
            let (a, b) = (c.point(s) - c.point(s - h), c.point(s + h) - c.point(s));
            (a.x * b.y - a.y * b.x) / ((a.x * a.x + a.y * a.y) * (b.x * b.x + b.y * b.y)).sqrt()
        };
        let turn = |left: bool| {
            let s = (0..600)
                .map(|i| i as f32 / 100.0)
                .find(|&s| {
                    if left {
                        bend(s) > 0.05
                    } else {
                        bend(s) < -0.05
                    }
                })
                .expect("the figure-8 turns both ways");
            assert_eq!(
                line.curvature_per_m(s) > 0.0,
                left,
                "the turn's sign at {s}"
            );
            s
        };
        scripted_pass(&track, &line, turn(true));
        scripted_pass(&track, &line, turn(false));
    }

    fn scripted_pass(track: &Track<'_>, line: &Line, s0: f32) {
        let c = Centerline::new(track);
        // The inside is the left in a left turn: the sign of the independent bend.
        let bend = {
            let h = 0.05;
            let (a, b) = (c.point(s0) - c.point(s0 - h), c.point(s0 + h) - c.point(s0));
            a.x * b.y - a.y * b.x
        };
        let sign = bend.signum();
        let at = |s: f32, inside: f32| {
            let t = c.tangent(s);
            let norm = (t.x * t.x + t.y * t.y).sqrt();
            let left = Vec3::new(-t.y / norm, t.x / norm, 0.0);
            c.point(s) + left.scale(inside * sign)
        };
        let dt = 0.02;
        let steps = 200;
        let mut trace = Trace {
            dt_s: dt,
            ..Trace::default()
        };
        for i in 0..steps {
            let t = i as f32 * dt;
            // Over 4 s the opponent moves 0.4 of a segment, the ego 0.5 from 0.05 behind.
            let so = s0 - 0.2 + 0.1 * t;
            let se = s0 - 0.25 + 0.125 * t;
            let inside = if i < 100 { -0.5 } else { 0.5 };
            trace.ego_m.push(at(se, inside));
            trace.opponent_m.push(at(so, 0.0));
            trace.ego_speed_mps.push(9.0);
            trace.opponent_speed_mps.push(8.0);
            trace.lead_m.push(Some(se - so));
        }
        trace.overtakes.push(OvertakeMark {
            step: 101,
            sustained: true,
        });
        let m = measure(line, &trace, 0).expect("measured");
        assert!((m.entry.ego.inside_m + 0.5).abs() < 0.02, "{m:?}");
        assert!((m.exit.ego.inside_m - 0.5).abs() < 0.02, "{m:?}");
        assert!(m.entry.opponent.inside_m.abs() < 0.02, "{m:?}");
        assert!((m.entry.dt_s + LOOK_S).abs() < 1e-4 && (m.exit.dt_s - LOOK_S).abs() < 1e-4);
        assert_eq!(m.kind(), "wide in, tight out");
        assert!(m.wide_in_tight_out());
        assert_eq!(
            (m.pass.ego.speed_mps, m.pass.opponent.speed_mps),
            (9.0, 8.0)
        );
        let table = summary(&[m]);
        assert!(table.contains(&format!("| g{} | 1 |", m.gate)), "{table}");

        // The same pass mirrored (ego inside, then outside): the other kind.
        let mut mirrored = trace.clone();
        for (i, p) in mirrored.ego_m.iter_mut().enumerate() {
            let t = i as f32 * dt;
            let se = s0 - 0.25 + 0.125 * t;
            *p = at(se, if i < 100 { 0.5 } else { -0.5 });
        }
        assert_eq!(
            measure(line, &mirrored, 0).map(|m| m.kind()),
            Some("tight in, wide out")
        );
    }

    /// Entry and exit stay inside the pass's flight: a respawn half a second before the
    /// pass moves the entry to it.
    #[test]
    fn entry_and_exit_are_clamped_to_the_flight() {
        let track = Track::figure_eight();
        let line = Line::new(&track);
        let c = Centerline::new(&track);
        let mut trace = Trace {
            dt_s: 0.02,
            ..Trace::default()
        };
        for i in 0..300 {
            let s = 1.0 + i as f32 * 0.002;
            trace.ego_m.push(c.point(s + 0.01));
            trace.opponent_m.push(c.point(s));
            trace.ego_speed_mps.push(8.0);
            trace.opponent_speed_mps.push(8.0);
            trace.lead_m.push(Some(0.1));
        }
        trace.respawns = vec![125, 170];
        trace.overtakes.push(OvertakeMark {
            step: 151,
            sustained: false,
        });
        let m = measure(&line, &trace, 0).expect("measured");
        assert!(
            (m.entry.dt_s - (125.0 - 150.0) * 0.02).abs() < 1e-4,
            "{m:?}"
        );
        assert!((m.exit.dt_s - (169.0 - 150.0) * 0.02).abs() < 1e-4, "{m:?}");
        // A trace without speeds is not measured.
        trace.ego_speed_mps.clear();
        assert_eq!(measure(&line, &trace, 0), None);
    }
}
