//! A recorded episode: where both drones flew and how they were turned, when they passed
//! gates, crashed and were respawned, and where the ego overtook (`sitl eval --trace`, the
//! race plots, the overtake figure and the 3-D replay).

use firmware_core::math::{Quat, Vec3};

/// The ego's and opponent's states at every step of an episode, and its events.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trace {
    /// Control period (s).
    pub dt_s: f32,
    /// Ego position after each step (m, world).
    pub ego_m: Vec<Vec3>,
    /// Opponent position after each step (m, world); empty in a time trial.
    pub opponent_m: Vec<Vec3>,
    /// Ego attitude after each step (unit quaternion, body to world).
    pub ego_attitude: Vec<Quat>,
    /// Opponent attitude after each step; empty in a time trial.
    pub opponent_attitude: Vec<Quat>,
    /// Ego speed after each step (m/s).
    pub ego_speed_mps: Vec<f32>,
    /// Opponent speed after each step (m/s); empty in a time trial.
    pub opponent_speed_mps: Vec<f32>,
    /// The ego's lead along the track after each step (m, the referee's
    /// [`Referee::lead_m`](super::Referee::lead_m): positive ahead); `None` where the
    /// referee has none; empty in a time trial.
    pub lead_m: Vec<Option<f32>>,
    /// Gate passes and crashes of both drones, in step order.
    pub events: Vec<TraceEvent>,
    /// Steps after which the drones were respawned.
    pub respawns: Vec<u32>,
    /// The ego's overtakes: the step after which it was ahead, and whether it then held
    /// the lead for [`SUSTAINED_LEAD_S`](super::SUSTAINED_LEAD_S).
    pub overtakes: Vec<OvertakeMark>,
}

impl Trace {
    /// Steps recorded.
    pub fn steps(&self) -> usize {
        self.ego_m.len()
    }

    /// Records the drones' states after a step: `drones[0]` is the ego.
    pub fn record_states(&mut self, drones: &[crate::world::Drone]) {
        let speed = |d: &crate::world::Drone| d.body.state.velocity_mps.norm();
        if let Some(ego) = drones.first() {
            self.ego_m.push(ego.position_m());
            self.ego_attitude.push(ego.body.state.attitude);
            self.ego_speed_mps.push(speed(ego));
        }
        if let Some(o) = drones.get(1) {
            self.opponent_m.push(o.position_m());
            self.opponent_attitude.push(o.body.state.attitude);
            self.opponent_speed_mps.push(speed(o));
        }
    }

    /// Records the gate passes and crashes of step `step` (1-based), drone by drone.
    pub fn record_events(&mut self, step: u32, results: &[crate::world::DroneStep]) {
        for (drone, r) in (0u8..).zip(results) {
            let kind = match (r.crash, r.passed_gate()) {
                (Some(cause), _) => TraceEventKind::Crashed {
                    cause: cause.to_string(),
                },
                (None, Some(gate)) => TraceEventKind::GatePassed {
                    gate: u8::try_from(gate).unwrap_or(u8::MAX),
                },
                (None, None) => continue,
            };
            self.events.push(TraceEvent { step, drone, kind });
        }
    }

    /// The trace as JSON: `dt_s`; `ego_m` and `opponent_m` as `[x, y, z]` rows (m, world),
    /// `ego_attitude` and `opponent_attitude` as `[w, x, y, z]` rows, `ego_speed_mps` and
    /// `opponent_speed_mps` (m/s), `lead_m` (m, `null` where none); `respawns`; `overtakes`
    /// as `{step, sustained}`; `events` as `{step, drone, gate}` or `{step, drone, crash}`
    /// (drone 0 is the ego, `crash` the cause in words).
    pub fn to_json(&self) -> serde_json::Value {
        let rows = |p: &[Vec3]| -> Vec<[f32; 3]> { p.iter().map(|v| [v.x, v.y, v.z]).collect() };
        let quats =
            |q: &[Quat]| -> Vec<[f32; 4]> { q.iter().map(|q| [q.w, q.x, q.y, q.z]).collect() };
        serde_json::json!({
            "dt_s": self.dt_s,
            "ego_m": rows(&self.ego_m),
            "opponent_m": rows(&self.opponent_m),
            "ego_attitude": quats(&self.ego_attitude),
            "opponent_attitude": quats(&self.opponent_attitude),
            "ego_speed_mps": self.ego_speed_mps,
            "opponent_speed_mps": self.opponent_speed_mps,
            "lead_m": self.lead_m,
            "respawns": self.respawns,
            "overtakes": self.overtakes.iter().map(OvertakeMark::to_json).collect::<Vec<_>>(),
            "events": self.events.iter().map(TraceEvent::to_json).collect::<Vec<_>>(),
        })
    }

    /// A trace from [`Trace::to_json`]'s form; `None` when a field is missing or mistyped.
    /// The attitudes, speeds, leads and events may be absent (traces written before they
    /// were recorded): they are then empty.
    pub fn from_json(v: &serde_json::Value) -> Option<Self> {
        let rows = |key: &str| -> Option<Vec<Vec3>> {
            v.get(key)?
                .as_array()?
                .iter()
                .map(|r| {
                    let r = r.as_array()?;
                    let c = |i: usize| r.get(i)?.as_f64().map(|x| x as f32);
                    Some(Vec3::new(c(0)?, c(1)?, c(2)?))
                })
                .collect()
        };
        let u32s = |key: &str| -> Option<Vec<u32>> {
            v.get(key)?
                .as_array()?
                .iter()
                .map(|x| x.as_u64().and_then(|x| u32::try_from(x).ok()))
                .collect()
        };
        let overtakes = v
            .get("overtakes")?
            .as_array()?
            .iter()
            .map(OvertakeMark::from_json)
            .collect::<Option<Vec<_>>>()?;
        let optional = |key: &str| v.get(key).unwrap_or(&serde_json::Value::Null);
        let quats = |key: &str| -> Option<Vec<Quat>> {
            let Some(rows) = optional(key).as_array() else {
                return Some(Vec::new());
            };
            rows.iter()
                .map(|r| {
                    let r = r.as_array()?;
                    let c = |i: usize| r.get(i)?.as_f64().map(|x| x as f32);
                    Some(Quat {
                        w: c(0)?,
                        x: c(1)?,
                        y: c(2)?,
                        z: c(3)?,
                    })
                })
                .collect()
        };
        let f32s = |key: &str| -> Option<Vec<Option<f32>>> {
            let Some(xs) = optional(key).as_array() else {
                return Some(Vec::new());
            };
            xs.iter()
                .map(|x| match x {
                    serde_json::Value::Null => Some(None),
                    x => x.as_f64().map(|x| Some(x as f32)),
                })
                .collect()
        };
        let speeds = |key: &str| -> Option<Vec<f32>> { f32s(key)?.into_iter().collect() };
        let events = match optional("events").as_array() {
            Some(events) => events
                .iter()
                .map(TraceEvent::from_json)
                .collect::<Option<Vec<_>>>()?,
            None => Vec::new(),
        };
        Some(Self {
            dt_s: v.get("dt_s")?.as_f64()? as f32,
            ego_m: rows("ego_m")?,
            opponent_m: rows("opponent_m")?,
            ego_attitude: quats("ego_attitude")?,
            opponent_attitude: quats("opponent_attitude")?,
            ego_speed_mps: speeds("ego_speed_mps")?,
            opponent_speed_mps: speeds("opponent_speed_mps")?,
            lead_m: f32s("lead_m")?,
            events,
            respawns: u32s("respawns")?,
            overtakes,
        })
    }
}

/// A gate pass or a crash of one drone, as [`Trace::events`] holds them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TraceEvent {
    /// The step after which it happened (1-based: `step · dt` is the time).
    pub step: u32,
    /// Whose: 0 the ego, 1 the opponent.
    pub drone: u8,
    /// What happened.
    pub kind: TraceEventKind,
}

/// What a [`TraceEvent`] was.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TraceEventKind {
    /// The drone passed gate `gate` (its target).
    GatePassed {
        /// The gate's index on the track.
        gate: u8,
    },
    /// The drone crashed (the referee then respawns both).
    Crashed {
        /// The cause in words (`CrashCause`'s display).
        cause: String,
    },
}

impl TraceEvent {
    /// `{step, drone, gate}` or `{step, drone, crash}`.
    pub fn to_json(&self) -> serde_json::Value {
        match &self.kind {
            TraceEventKind::GatePassed { gate } => {
                serde_json::json!({"step": self.step, "drone": self.drone, "gate": gate})
            }
            TraceEventKind::Crashed { cause } => {
                serde_json::json!({"step": self.step, "drone": self.drone, "crash": cause})
            }
        }
    }

    /// An event from [`TraceEvent::to_json`]'s form.
    pub fn from_json(v: &serde_json::Value) -> Option<Self> {
        let step = u32::try_from(v.get("step")?.as_u64()?).ok()?;
        let drone = u8::try_from(v.get("drone")?.as_u64()?).ok()?;
        let kind = match (v.get("gate"), v.get("crash")) {
            (Some(g), None) => TraceEventKind::GatePassed {
                gate: u8::try_from(g.as_u64()?).ok()?,
            },
            (None, Some(c)) => TraceEventKind::Crashed {
                cause: c.as_str()?.to_string(),
            },
            _ => return None,
        };
        Some(Self { step, drone, kind })
    }
}

/// The `format` of a file of recorded episodes (`--trace`): `pilots`, `preset`, `seed`,
/// and `episodes`, each a [`Trace::to_json`].
pub const TRACES_FORMAT: &str = "overtake-traces/1";

/// One overtake in a [`Trace`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OvertakeMark {
    /// The step after which the ego was ahead (1-based: `step · dt` is the time).
    pub step: u32,
    /// The ego then kept the lead for [`SUSTAINED_LEAD_S`](super::SUSTAINED_LEAD_S) without a crash.
    pub sustained: bool,
}

impl OvertakeMark {
    /// `{step, sustained}`.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({"step": self.step, "sustained": self.sustained})
    }

    /// A mark from [`OvertakeMark::to_json`]'s form.
    pub fn from_json(v: &serde_json::Value) -> Option<Self> {
        Some(Self {
            step: u32::try_from(v.get("step")?.as_u64()?).ok()?,
            sustained: v.get("sustained")?.as_bool()?,
        })
    }
}
