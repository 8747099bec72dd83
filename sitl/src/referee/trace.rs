//! A recorded episode: where both drones flew, when they were respawned and where the ego
//! overtook (`sitl eval --trace`, the race plots and the overtake figure).

use firmware_core::math::Vec3;

/// The ego's and opponent's positions at every step of an episode, for plots.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trace {
    /// Control period (s).
    pub dt_s: f32,
    /// Ego position after each step (m, world).
    pub ego_m: Vec<Vec3>,
    /// Opponent position after each step (m, world); empty in a time trial.
    pub opponent_m: Vec<Vec3>,
    /// Steps after which the drones were respawned.
    pub respawns: Vec<u32>,
    /// The ego's overtakes: the step after which it was ahead, and whether it then held
    /// the lead for [`SUSTAINED_LEAD_S`](super::SUSTAINED_LEAD_S).
    pub overtakes: Vec<OvertakeMark>,
}

impl Trace {
    /// The trace as JSON: `dt_s`, `ego_m` and `opponent_m` as `[x, y, z]` rows (m, world),
    /// `respawns`, and `overtakes` as `{step, sustained}`.
    pub fn to_json(&self) -> serde_json::Value {
        let rows = |p: &[Vec3]| -> Vec<[f32; 3]> { p.iter().map(|v| [v.x, v.y, v.z]).collect() };
        serde_json::json!({
            "dt_s": self.dt_s,
            "ego_m": rows(&self.ego_m),
            "opponent_m": rows(&self.opponent_m),
            "respawns": self.respawns,
            "overtakes": self.overtakes.iter().map(|m| serde_json::json!({
                "step": m.step,
                "sustained": m.sustained,
            })).collect::<Vec<_>>(),
        })
    }

    /// A trace from [`Trace::to_json`]'s form; `None` when a field is missing or mistyped.
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
            .map(|m| {
                Some(OvertakeMark {
                    step: u32::try_from(m.get("step")?.as_u64()?).ok()?,
                    sustained: m.get("sustained")?.as_bool()?,
                })
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Self {
            dt_s: v.get("dt_s")?.as_f64()? as f32,
            ego_m: rows("ego_m")?,
            opponent_m: rows("opponent_m")?,
            respawns: u32s("respawns")?,
            overtakes,
        })
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
