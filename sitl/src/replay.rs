//! The 3-D race replay: recorded episodes written as one self-contained HTML file that any
//! browser opens offline (`sitl race` writes `race.html`; `sitl eval --replay FILE`).
//!
//! The page holds three things, nothing fetched: three.js (`assets/replay/three.min.js`,
//! the parts the viewer uses, bundled by `tools/replay/build-three.sh` and committed), the
//! viewer (`assets/replay/viewer.js` and `viewer.css`), and the episodes as JSON in a
//! `<script type="application/json" id="replay-data">` element, format [`REPLAY_FORMAT`]:
//!
//! - `track`: `gates` (`center_m` [x, y, z], `frame` [w, x, y, z] gate to world, +x the
//!   direction of travel), `opening_half_size_m`, and `centerline_m`, the referee's centre
//!   line sampled every 1/[`CENTERLINE_SAMPLES_PER_SEGMENT`] of a segment;
//! - `episodes`, each: `steps`; `ego` and `opponent` (null in a time trial) as base64 of
//!   little-endian f32, [`STATE_FLOATS`] per step: position x, y, z (m, world), attitude
//!   w, x, y, z (body to world), speed (m/s); `lead_m` the same way, one per step (NaN where
//!   the referee has no lead); `respawns`, `overtakes` and `events` as in
//!   [`Trace::to_json`]; and the episode's `metrics`.
//!
//! The f32 values are the trace's own, so the file round-trips the trajectories exactly
//! ([`read`] and [`decode_f32`] read them back). docs/DESIGN.md "Replay" says why HTML and
//! three.js rather than Rerun.

use crate::referee::{Episode, OvertakeMark, Trace, TraceEvent};
use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use firmware_core::math::Vec3;
use firmware_core::track::{Centerline, Track};

/// The `format` of the replay's JSON.
pub const REPLAY_FORMAT: &str = "overtake-replay/1";

/// f32 values per drone and step in `ego` and `opponent`: x, y, z, qw, qx, qy, qz, speed.
pub const STATE_FLOATS: usize = 8;

/// Centre-line samples per segment (gate to gate) in `track.centerline_m`.
pub const CENTERLINE_SAMPLES_PER_SEGMENT: usize = 40;

const THREE_JS: &str = include_str!("../assets/replay/three.min.js");
const VIEWER_JS: &str = include_str!("../assets/replay/viewer.js");
const VIEWER_CSS: &str = include_str!("../assets/replay/viewer.css");
const DATA_OPEN: &str = "<script type=\"application/json\" id=\"replay-data\">";
const DATA_CLOSE: &str = "</script>";

/// What the page says of the race: its title, who flew and how they were scored.
#[derive(Clone, Debug)]
pub struct ReplayInfo<'a> {
    /// The page's title.
    pub title: &'a str,
    /// The pilots, ego first.
    pub pilots: &'a [String],
    /// The dynamics preset's name.
    pub preset: &'a str,
    /// The evaluation's seed.
    pub seed: u64,
}

/// A pilot's description without the directories of its file: "/a/b/stage1.blob (stage1)"
/// becomes "stage1.blob (stage1)"; "baseline (7.0 m/s cruise)" stays as it is.
pub fn short_name(pilot: &str) -> String {
    let (file, rest) = pilot.split_once(' ').unwrap_or((pilot, ""));
    let file = file.rsplit(['/', '\\']).next().unwrap_or(file);
    if rest.is_empty() {
        file.to_string()
    } else {
        format!("{file} {rest}")
    }
}

/// The replay's JSON of `episodes` flown on `track` (each must have been recorded).
pub fn replay_json(
    track: &Track<'_>,
    info: &ReplayInfo<'_>,
    episodes: &[Episode],
) -> serde_json::Value {
    let gates: Vec<serde_json::Value> = track
        .gates()
        .iter()
        .map(|g| {
            serde_json::json!({
                "center_m": [g.center_m.x, g.center_m.y, g.center_m.z],
                "frame": [g.frame.w, g.frame.x, g.frame.y, g.frame.z],
            })
        })
        .collect();
    let line = Centerline::new(track);
    let samples = line.segments() * CENTERLINE_SAMPLES_PER_SEGMENT;
    let centerline: Vec<[f32; 3]> = (0..=samples)
        .map(|i| {
            let p = line.point(i as f32 / CENTERLINE_SAMPLES_PER_SEGMENT as f32);
            [p.x, p.y, p.z]
        })
        .collect();
    let dt_s = episodes.first().map_or(0.0, |e| e.trace.dt_s);
    serde_json::json!({
        "format": REPLAY_FORMAT,
        "title": info.title,
        "pilots": info.pilots,
        "preset": info.preset,
        "seed": info.seed,
        "dt_s": dt_s,
        "track": {
            "gates": gates,
            "opening_half_size_m": track.opening_half_size_m,
            "centerline_m": centerline,
        },
        "episodes": episodes.iter().map(episode_json).collect::<Vec<_>>(),
    })
}

/// One episode: states as base64 f32, events as the trace's JSON, the metrics.
fn episode_json(e: &Episode) -> serde_json::Value {
    let t = &e.trace;
    let race = !t.opponent_m.is_empty();
    let m = &e.metrics;
    serde_json::json!({
        "steps": t.steps(),
        "ego": encode_f32(&states(&t.ego_m, &t.ego_attitude, &t.ego_speed_mps)),
        "opponent": race.then(|| encode_f32(&states(
            &t.opponent_m,
            &t.opponent_attitude,
            &t.opponent_speed_mps,
        ))),
        "lead_m": race.then(|| encode_f32(
            &t.lead_m.iter().map(|l| l.unwrap_or(f32::NAN)).collect::<Vec<_>>(),
        )),
        "respawns": t.respawns,
        "overtakes": t.overtakes.iter().map(OvertakeMark::to_json).collect::<Vec<_>>(),
        "events": t.events.iter().map(TraceEvent::to_json).collect::<Vec<_>>(),
        "metrics": {
            "sim_seconds": m.sim_seconds,
            "lap_times_s": m.lap_times_s,
            "crashes": m.crashes,
            "opponent_crashes": m.opponent_crashes,
            "overtakes": m.overtakes,
            "sustained_overtakes": m.sustained_overtakes,
            "flights": m.flights,
            "flights_won": m.flights_won,
        },
    })
}

/// Interleaves one drone's states, [`STATE_FLOATS`] per step (missing attitude or speed,
/// from a trace recorded without them: identity and 0).
fn states(
    position_m: &[Vec3],
    attitude: &[firmware_core::math::Quat],
    speed_mps: &[f32],
) -> Vec<f32> {
    let mut out = Vec::with_capacity(position_m.len() * STATE_FLOATS);
    for (k, p) in position_m.iter().enumerate() {
        let q = attitude
            .get(k)
            .copied()
            .unwrap_or(firmware_core::math::Quat::IDENTITY);
        let v = speed_mps.get(k).copied().unwrap_or(0.0);
        out.extend_from_slice(&[p.x, p.y, p.z, q.w, q.x, q.y, q.z, v]);
    }
    out
}

/// `values` as base64 of little-endian f32.
pub fn encode_f32(values: &[f32]) -> String {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    BASE64.encode(bytes)
}

/// The f32 values of [`encode_f32`]'s form.
pub fn decode_f32(text: &str) -> Result<Vec<f32>, String> {
    let bytes = BASE64
        .decode(text)
        .map_err(|e| format!("not base64: {e}"))?;
    if bytes.len() % 4 != 0 {
        return Err(format!(
            "{} bytes is not a whole number of f32",
            bytes.len()
        ));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// The self-contained page of the replay `json` ([`replay_json`]).
pub fn html(json: &serde_json::Value) -> String {
    // JSON may carry "<" only inside strings, where \u003c means the same: no pilot name
    // can close the data element.
    let data = json.to_string().replace('<', "\\u003c");
    let title = json["title"]
        .as_str()
        .unwrap_or("race replay")
        .replace('&', "&amp;")
        .replace('<', "&lt;");
    let mut page = String::with_capacity(THREE_JS.len() + data.len() + 64 * 1024);
    page.push_str("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
    page.push_str("<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n");
    page.push_str(&format!(
        "<title>{title}</title>\n<style>\n{VIEWER_CSS}</style>\n</head>\n"
    ));
    page.push_str("<body>\n");
    page.push_str(DATA_OPEN);
    page.push_str(&data);
    page.push_str(DATA_CLOSE);
    page.push_str("\n<script>\n");
    page.push_str(THREE_JS);
    page.push_str("\n</script>\n<script>\n");
    page.push_str(VIEWER_JS);
    page.push_str("\n</script>\n</body>\n</html>\n");
    page
}

/// The replay's JSON read back from a page [`html`] wrote.
pub fn read(page: &str) -> Result<serde_json::Value, String> {
    let start = page.find(DATA_OPEN).ok_or("no replay data in this page")? + DATA_OPEN.len();
    let len = page
        .get(start..)
        .and_then(|rest| rest.find(DATA_CLOSE))
        .ok_or("the replay data is not closed")?;
    let json: serde_json::Value = serde_json::from_str(&page[start..start + len])
        .map_err(|e| format!("the replay data is not JSON: {e}"))?;
    match json["format"].as_str() {
        Some(REPLAY_FORMAT) => Ok(json),
        other => Err(format!("replay format {other:?}, expected {REPLAY_FORMAT}")),
    }
}

/// The trace of episode `index` as the replay `json` holds it (positions, attitudes,
/// speeds, leads, respawns, overtakes and events; `dt_s`).
pub fn trace(json: &serde_json::Value, index: usize) -> Result<Trace, String> {
    let e = json["episodes"]
        .get(index)
        .ok_or_else(|| format!("no episode {index}"))?;
    let drone = |key: &str| -> Result<Option<Vec<f32>>, String> {
        match &e[key] {
            serde_json::Value::Null => Ok(None),
            v => v
                .as_str()
                .ok_or_else(|| format!("{key} is not a string"))
                .and_then(decode_f32)
                .map(Some),
        }
    };
    let split = |v: &[f32]| {
        let pos = v
            .chunks_exact(STATE_FLOATS)
            .map(|s| Vec3::new(s[0], s[1], s[2]));
        let att = v
            .chunks_exact(STATE_FLOATS)
            .map(|s| firmware_core::math::Quat {
                w: s[3],
                x: s[4],
                y: s[5],
                z: s[6],
            });
        let speed = v.chunks_exact(STATE_FLOATS).map(|s| s[7]);
        (pos.collect(), att.collect(), speed.collect())
    };
    let steps = e["steps"]
        .as_u64()
        .and_then(|n| usize::try_from(n).ok())
        .ok_or_else(|| format!("episode {index} has no step count"))?;
    let states = |key: &str, required: bool| -> Result<Vec<f32>, String> {
        match drone(key)? {
            Some(v) if v.len() == steps * STATE_FLOATS => Ok(v),
            Some(v) => Err(format!(
                "episode {index}: {key} holds {} values, not {STATE_FLOATS} for each of {steps} steps",
                v.len()
            )),
            None if required => Err(format!("episode {index} has no {key} states")),
            None => Ok(Vec::new()),
        }
    };
    let (ego_m, ego_attitude, ego_speed_mps) = split(&states("ego", true)?);
    let (opponent_m, opponent_attitude, opponent_speed_mps) = split(&states("opponent", false)?);
    let lead = drone("lead_m")?.unwrap_or_default();
    if !lead.is_empty() && lead.len() != steps {
        return Err(format!(
            "episode {index}: lead_m holds {} values for {steps} steps",
            lead.len()
        ));
    }
    let lead_m = lead
        .into_iter()
        .map(|l| (!l.is_nan()).then_some(l))
        .collect();
    let dt_s = json["dt_s"]
        .as_f64()
        .ok_or("the replay has no control period (dt_s)")?;
    let unparsed = |key: &str| format!("episode {index}: its {key} do not parse");
    let list = |key: &str| e[key].as_array().ok_or_else(|| unparsed(key));
    let respawns = list("respawns")?
        .iter()
        .map(|s| s.as_u64().and_then(|s| u32::try_from(s).ok()))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| unparsed("respawns"))?;
    let overtakes = list("overtakes")?
        .iter()
        .map(OvertakeMark::from_json)
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| unparsed("overtakes"))?;
    let events = list("events")?
        .iter()
        .map(TraceEvent::from_json)
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| unparsed("events"))?;
    Ok(Trace {
        dt_s: dt_s as f32,
        ego_m,
        opponent_m,
        ego_attitude,
        opponent_attitude,
        ego_speed_mps,
        opponent_speed_mps,
        lead_m,
        events,
        respawns,
        overtakes,
    })
}
