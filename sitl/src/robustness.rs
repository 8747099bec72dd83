//! The robustness sweep (`sitl robustness`, issue "robust"): a pilot flown under the
//! standard perturbations of [`crate::perturb`], f32 and its int8 conversion, and for each
//! kind of perturbation the largest level it survives.
//!
//! Every level except the first includes the standard start jitter
//! ([`StartJitter::STANDARD`](crate::perturb::StartJitter::STANDARD)), so that no row is one deterministic flight repeated.
//! "Survives" means a success rate of at least [`SURVIVAL_SUCCESS`] at that level and every
//! smaller one of its ladder.

use crate::eval::{EvalConfig, Report, report};
use crate::perturb::Perturbation;
use crate::pilot::PilotSpec;
use serde::Serialize;

/// The success rate a level must reach to count as survived.
pub const SURVIVAL_SUCCESS: f64 = 0.9;

/// One named perturbation level.
#[derive(Clone, Debug, Serialize)]
pub struct Level {
    /// Its name in tables ("jitter", "thrust ±5 %", ...).
    pub name: String,
    /// What is flown.
    pub perturbation: Perturbation,
}

fn level(name: &str, spec: &str) -> Level {
    let jittered = Perturbation::JITTERED;
    Level {
        name: name.to_string(),
        // The specs below are constants of this module; `rows_parse` tests them.
        perturbation: jittered.parse_onto(spec).unwrap_or(jittered),
    }
}

/// The rows of the robustness table: nominal, jitter, then each kind at a level a real
/// Crazyflie shows, then all of them at once.
pub fn table_levels() -> Vec<Level> {
    vec![
        Level {
            name: "nominal (one flight)".into(),
            perturbation: Perturbation::NONE,
        },
        level("jitter 5 cm, 5°, 0.2 m/s", ""),
        level("+ sensor noise ×1", "noise=1"),
        level("+ thrust ±5 %", "thrust=0.95:1.05"),
        level("+ mass ±5 %", "mass=0.95:1.05"),
        level("+ inertia ±10 %", "inertia=0.9:1.1"),
        level("+ motor lag 0-30 ms", "motor-tau-ms=0:30"),
        level("+ latency 1 step (20 ms)", "latency=1"),
        level(
            "+ all of the above",
            "noise=1,thrust=0.95:1.05,mass=0.95:1.05,inertia=0.9:1.1,motor-tau-ms=0:30,latency=0:1",
        ),
    ]
}

/// A ladder: one kind of perturbation at growing levels.
#[derive(Clone, Debug, Serialize)]
pub struct Ladder {
    /// The kind ("thrust", "latency", ...).
    pub kind: String,
    /// Its levels, smallest first.
    pub levels: Vec<Level>,
}

/// The ladders whose largest survived level the table reports.
pub fn ladders() -> Vec<Ladder> {
    let ladder = |kind: &str, levels: &[(&str, &str)]| Ladder {
        kind: kind.to_string(),
        levels: levels.iter().map(|(n, s)| level(n, s)).collect(),
    };
    vec![
        ladder(
            "thrust",
            &[
                ("±2.5 %", "thrust=0.975:1.025"),
                ("±5 %", "thrust=0.95:1.05"),
                ("±10 %", "thrust=0.9:1.1"),
                ("±20 %", "thrust=0.8:1.2"),
            ],
        ),
        ladder(
            "mass",
            &[
                ("±2.5 %", "mass=0.975:1.025"),
                ("±5 %", "mass=0.95:1.05"),
                ("±10 %", "mass=0.9:1.1"),
                ("±20 %", "mass=0.8:1.2"),
            ],
        ),
        ladder(
            "inertia",
            &[
                ("±10 %", "inertia=0.9:1.1"),
                ("±20 %", "inertia=0.8:1.2"),
                ("±40 %", "inertia=0.6:1.4"),
            ],
        ),
        ladder(
            "motor lag",
            &[
                ("10 ms", "motor-tau-ms=10"),
                ("20 ms", "motor-tau-ms=20"),
                ("30 ms", "motor-tau-ms=30"),
                ("50 ms", "motor-tau-ms=50"),
            ],
        ),
        ladder(
            "latency",
            &[
                ("1 step", "latency=1"),
                ("2 steps", "latency=2"),
                ("3 steps", "latency=3"),
            ],
        ),
        ladder(
            "sensor noise",
            &[
                ("×1", "noise=1"),
                ("×2", "noise=2"),
                ("×4", "noise=4"),
                ("×8", "noise=8"),
            ],
        ),
    ]
}

/// One pilot's scores at one level: f32 and, for a blob, its int8 conversion.
#[derive(Clone, Debug, Serialize)]
pub struct Scored {
    /// The level.
    pub level: Level,
    /// The pilot as given.
    pub f32: Report,
    /// Its int8 conversion; `None` for the baseline or an int8 blob.
    pub int8: Option<Report>,
}

/// The largest level of a ladder survived, by dtype.
#[derive(Clone, Debug, Serialize)]
pub struct Survived {
    /// The ladder's kind.
    pub kind: String,
    /// The largest level survived by the pilot as given (`None`: not even the smallest).
    pub f32: Option<String>,
    /// The same for its int8 conversion.
    pub int8: Option<String>,
    /// Every level flown.
    pub scored: Vec<Scored>,
}

/// The sweep's result.
#[derive(Clone, Debug, Serialize)]
pub struct Robustness {
    /// The pilot.
    pub ego: String,
    /// The opponent, if a race.
    pub opponent: Option<String>,
    /// Episodes per level.
    pub episodes: u32,
    /// Seed of every level's draws.
    pub seed: u64,
    /// The rows of the table.
    pub table: Vec<Scored>,
    /// The largest level survived per kind.
    pub survived: Vec<Survived>,
}

fn score(
    ego: &PilotSpec,
    int8: Option<&PilotSpec>,
    opponent: Option<&PilotSpec>,
    base: &EvalConfig,
    level: &Level,
) -> Scored {
    let config = EvalConfig {
        perturbation: level.perturbation,
        ..base.clone()
    };
    Scored {
        level: level.clone(),
        f32: report(ego, opponent, &config),
        int8: int8.map(|q| report(q, opponent, &config)),
    }
}

/// Flies `ego` (and `int8`, its conversion, if given) at every level of [`table_levels`]
/// and [`ladders`], with `base`'s episodes, seed, spawn and preset; `progress` is called
/// with the name of each level as it starts.
pub fn sweep(
    ego: &PilotSpec,
    int8: Option<&PilotSpec>,
    opponent: Option<&PilotSpec>,
    base: &EvalConfig,
    mut progress: impl FnMut(&str),
) -> Robustness {
    let table = table_levels()
        .iter()
        .map(|l| {
            progress(&l.name);
            score(ego, int8, opponent, base, l)
        })
        .collect();
    let survived = ladders()
        .into_iter()
        .map(|ladder| {
            let scored: Vec<Scored> = ladder
                .levels
                .iter()
                .map(|l| {
                    progress(&format!("{} {}", ladder.kind, l.name));
                    score(ego, int8, opponent, base, l)
                })
                .collect();
            let largest = |pick: fn(&Scored) -> Option<&Report>| {
                scored
                    .iter()
                    .take_while(|s| pick(s).is_some_and(|r| r.success_rate >= SURVIVAL_SUCCESS))
                    .last()
                    .map(|s| s.level.name.clone())
            };
            Survived {
                kind: ladder.kind,
                f32: largest(|s| Some(&s.f32)),
                int8: largest(|s| s.int8.as_ref()),
                scored,
            }
        })
        .collect();
    Robustness {
        ego: ego.describe(),
        opponent: opponent.map(PilotSpec::describe),
        episodes: base.episodes,
        seed: base.seed,
        table,
        survived,
    }
}

impl Robustness {
    /// The two tables as Markdown: the levels (success, crashes/s, best lap; f32 and int8)
    /// and the largest level survived per kind.
    pub fn markdown(&self) -> String {
        let cell = |r: Option<&Report>| match r {
            None => "—".to_string(),
            Some(r) => format!(
                "{:.3}, {:.3}, {}",
                r.success_rate,
                r.crash_rate,
                r.best_lap_s
                    .map_or("DNF".to_string(), |l| format!("{l:.2} s"))
            ),
        };
        let mut out = format!(
            "{}{}: {} episodes per level, seed {}\n\n",
            self.ego,
            self.opponent
                .as_ref()
                .map(|o| format!(" vs {o}"))
                .unwrap_or_default(),
            self.episodes,
            self.seed
        );
        out +=
            "| level | f32: success, crashes/s, best lap | int8: success, crashes/s, best lap |\n";
        out += "|---|---|---|\n";
        for s in &self.table {
            out += &format!(
                "| {} | {} | {} |\n",
                s.level.name,
                cell(Some(&s.f32)),
                cell(s.int8.as_ref())
            );
        }
        out += &format!(
            "\nLargest level survived (success ≥ {SURVIVAL_SUCCESS} there and below, with the jitter):\n\n"
        );
        out += "| perturbation | f32 | int8 | levels flown (f32 success) |\n|---|---|---|---|\n";
        for s in &self.survived {
            let name = |n: &Option<String>| n.clone().unwrap_or_else(|| "none".into());
            let flown: Vec<String> = s
                .scored
                .iter()
                .map(|x| format!("{} {:.2}", x.level.name, x.f32.success_rate))
                .collect();
            out += &format!(
                "| {} | {} | {} | {} |\n",
                s.kind,
                name(&s.f32),
                if self.table.first().is_some_and(|t| t.int8.is_some()) {
                    name(&s.int8)
                } else {
                    "—".into()
                },
                flown.join("; ")
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::perturb::StartJitter;

    #[test]
    fn rows_parse() {
        let jittered = Perturbation {
            jitter: StartJitter::STANDARD,
            ..Perturbation::NONE
        };
        let levels = table_levels()
            .into_iter()
            .chain(ladders().into_iter().flat_map(|l| l.levels));
        for (i, l) in levels.enumerate() {
            // Every level but the nominal one is jittered and, past the second, more than that.
            if i == 0 {
                assert!(l.perturbation.is_none());
            } else {
                assert_eq!(l.perturbation.jitter, StartJitter::STANDARD, "{}", l.name);
                if i > 1 {
                    assert_ne!(l.perturbation, jittered, "{} did not parse", l.name);
                }
            }
        }
    }
}
