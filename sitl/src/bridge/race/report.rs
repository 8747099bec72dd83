//! What a race reports: each controller's link and fate, the Table-1 row, as text and JSON.

use super::super::wire::LinkStats;
use crate::eval::Report;
use crate::referee::Episode;
use serde::Serialize;

/// One controller as the race result reports it.
#[derive(Clone, Debug, Serialize)]
pub struct ControllerReport {
    /// "ego" or "opponent".
    pub role: String,
    /// Its pilot.
    pub pilot: String,
    /// Its MAVLink system id.
    pub system_id: u8,
    /// Its UDP endpoint.
    pub endpoint: String,
    /// "process", "thread" or "attached".
    pub runs_as: String,
    /// Why it was declared failed, if it was (its drone's motors were stopped from then on).
    pub failure: Option<String>,
    /// The simulator's counters for its link.
    pub link: LinkStats,
}

/// The result of a race.
#[derive(Clone, Debug)]
pub struct RaceOutcome {
    /// The Table-1 row, as `sitl eval` computes it.
    pub report: Report,
    /// The episodes (with traces when recorded).
    pub episodes: Vec<Episode>,
    /// Each controller's link and fate.
    pub controllers: Vec<ControllerReport>,
    /// Wall-clock seconds of the race (without starting the controllers).
    pub wall_s: f64,
    /// The telemetry log (empty unless asked for).
    pub tlog: Vec<u8>,
}

#[derive(Serialize)]
struct RaceJson<'a> {
    #[serde(flatten)]
    report: &'a Report,
    controllers: &'a [ControllerReport],
    wall_s: f64,
    realtime_factor: f64,
}

impl RaceOutcome {
    /// Simulated seconds per wall-clock second.
    pub fn realtime_factor(&self) -> f64 {
        self.report.sim_seconds / self.wall_s.max(1e-9)
    }

    /// True when any controller was declared failed.
    pub fn has_failures(&self) -> bool {
        self.controllers.iter().any(|c| c.failure.is_some())
    }

    /// The report as JSON: `sitl eval`'s keys plus `controllers`, `wall_s` and
    /// `realtime_factor`.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(&RaceJson {
            report: &self.report,
            controllers: &self.controllers,
            wall_s: self.wall_s,
            realtime_factor: self.realtime_factor(),
        })
        .unwrap_or_default()
    }

    /// A few lines on the race: time, speed, each controller's link.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "race: {} episodes, {:.0} simulated s in {:.2} s wall-clock ({:.0}x real time), {} overtakes ({} sustained)\n",
            self.report.episodes,
            self.report.sim_seconds,
            self.wall_s,
            self.realtime_factor(),
            self.report.overtakes,
            self.report.sustained_overtakes,
        );
        for c in &self.controllers {
            let l = &c.link;
            s.push_str(&format!(
                "  {:<8} sysid {} {} at {}: {} frames in, {} out, {} dropped",
                c.role,
                c.system_id,
                c.runs_as,
                c.endpoint,
                l.frames_received,
                l.frames_sent,
                l.dropped()
            ));
            if l.resent > 0 {
                s.push_str(&format!(", {} requests sent again", l.resent));
            }
            if l.dropped() > 0 {
                s.push_str(&format!(
                    " (malformed {}, bad crc {}, bad payload {}, unsigned {}, bad signature {}, replayed {}, wrong system {}, stale {}, future {}, ignored {})",
                    l.malformed,
                    l.bad_crc,
                    l.bad_payload,
                    l.unsigned,
                    l.bad_signature,
                    l.replayed,
                    l.wrong_system,
                    l.stale,
                    l.future,
                    l.ignored
                ));
            }
            match &c.failure {
                Some(why) => s.push_str(&format!("\n           FAILED: {why}\n")),
                None => s.push('\n'),
            }
        }
        s
    }
}
