//! Evaluation: many seeded episodes flown in parallel, aggregated into the Table-1 row with
//! 95% intervals, printed for people and written as JSON for programs.

use crate::dynamics::Preset;
use crate::perturb::Perturbation;
use crate::pilot::PilotSpec;
use crate::referee::{CrashCounts, Episode, EpisodeConfig, EpisodeMetrics, SpawnMode, run_episode};
use crate::stats::{ci95, mean};
use crate::world::World;
use firmware_core::track::CrashRules;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// What to evaluate.
#[derive(Clone, Debug)]
pub struct EvalConfig {
    /// Dynamics preset.
    pub preset: Preset,
    /// Number of episodes.
    pub episodes: u32,
    /// Simulated seconds per episode. Paper: 45.
    pub seconds: f32,
    /// Seed of the spawn draws (episode `i` uses stream `i` of it).
    pub seed: u64,
    /// Spawn mode; `None` picks stage 2 for races and stage 1 for time trials.
    pub spawn: Option<SpawnMode>,
    /// What perturbs the flights ([`Perturbation::NONE`]: the nominal flight).
    pub perturbation: Perturbation,
}

impl EvalConfig {
    /// The spawn mode in effect: races start at the stage-2 spawn, time trials at stage 1.
    pub fn spawn_mode(&self, race: bool) -> SpawnMode {
        self.spawn.unwrap_or(if race {
            SpawnMode::Stage2
        } else {
            SpawnMode::Stage1
        })
    }

    /// The episodes' settings: length, spawn, seed.
    pub fn episode(&self, race: bool) -> EpisodeConfig {
        EpisodeConfig {
            seconds: self.seconds,
            spawn: self.spawn_mode(race),
            seed: self.seed,
            perturbation: self.perturbation,
        }
    }

    /// The world episodes are flown in: the figure-8, stage-2 crash rules in a race (15 m
    /// bounds, 0.2 m separation), stage-1 rules alone (25 m).
    pub fn world(&self, race: bool) -> World {
        World::figure_eight(
            self.preset,
            if race {
                CrashRules::STAGE2
            } else {
                CrashRules::STAGE1
            },
        )
    }
}

/// Flies the episodes of [`evaluate`] without traces and aggregates them into the Table-1
/// row.
pub fn report(ego: &PilotSpec, opponent: Option<&PilotSpec>, config: &EvalConfig) -> Report {
    let metrics: Vec<_> = evaluate(ego, opponent, config, false)
        .into_iter()
        .map(|e| e.metrics)
        .collect();
    Report::new(ego, opponent, config, &metrics)
}

/// Flies `config.episodes` episodes of `ego` (against `opponent`, if any) in parallel; the
/// result is in episode order and does not depend on the thread count. With `record`, each
/// episode keeps its trace.
pub fn evaluate(
    ego: &PilotSpec,
    opponent: Option<&PilotSpec>,
    config: &EvalConfig,
    record: bool,
) -> Vec<Episode> {
    let race = opponent.is_some();
    let world = config.world(race);
    let episode = config.episode(race);
    (0..config.episodes)
        .into_par_iter()
        .map(|i| {
            let mut e = ego.build(world.track);
            match opponent {
                Some(o) => {
                    let mut o = o.build(world.track);
                    run_episode(
                        &world,
                        &mut *e,
                        Some(&mut *o),
                        &episode,
                        u64::from(i),
                        record,
                    )
                }
                None => run_episode(&world, &mut *e, None, &episode, u64::from(i), record),
            }
        })
        .collect()
}

/// The Table-1 row over many episodes: means with Student-t 95% intervals over episodes,
/// counts summed. Serialised as `sitl eval --json` writes it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Report {
    /// The ego pilot.
    pub ego: String,
    /// The opponent pilot, `None` in a time trial.
    pub opponent: Option<String>,
    /// Dynamics preset.
    pub preset: String,
    /// Spawn mode.
    pub spawn: String,
    /// Seed of the spawn draws.
    pub seed: u64,
    /// The perturbation flown (absent: none, the nominal flight).
    #[serde(skip_serializing_if = "Perturbation::is_none")]
    pub perturbation: Perturbation,
    /// Episodes flown.
    pub episodes: u32,
    /// Simulated seconds per episode.
    pub episode_seconds: f64,
    /// Simulated seconds, all episodes.
    pub sim_seconds: f64,
    /// Gates the ego passed, all episodes.
    pub gates_passed: u64,
    /// Gates the ego encountered (passed or the target at a crash), all episodes.
    pub gates_encountered: u64,
    /// Mean over episodes of gates passed / encountered.
    pub success_rate: f64,
    /// 95% interval of `success_rate`; `None` for fewer than two episodes.
    pub success_rate_ci95: Option<[f64; 2]>,
    /// The ego's crash resets, all episodes.
    pub crashes: u64,
    /// Mean over episodes of crash resets per second (1/s).
    pub crash_rate: f64,
    /// 95% interval of `crash_rate` (1/s); `None` for fewer than two episodes.
    pub crash_rate_ci95: Option<[f64; 2]>,
    /// The fastest complete lap of any episode (s); `None` for a DNF.
    pub best_lap_s: Option<f64>,
    /// Mean of all complete laps (s); `None` without one.
    pub mean_lap_s: Option<f64>,
    /// Complete laps, all episodes.
    pub laps: u64,
    /// Overtakes by the ego, all episodes.
    pub overtakes: u64,
    /// Overtakes sustained for 2 s, all episodes.
    pub sustained_overtakes: u64,
    /// sustained_overtakes / overtakes; `None` (the paper's "Fail") without an overtake.
    pub sustained_overtake_rate: Option<f64>,
    /// The opponent's crash resets, all episodes (0 in a time trial).
    pub opponent_crashes: u64,
    /// The ego's crashes by cause, all episodes.
    pub crash_causes: CrashCounts,
    /// Races: flights (spans between (re)spawns), all episodes (docs/DESIGN.md "Metrics").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flights: Option<u64>,
    /// Races: mean over episodes of the ego's win rate, (flights won + tied / 2) / flights.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub win_rate: Option<f64>,
    /// 95% interval of `win_rate`; `None` for fewer than two episodes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub win_rate_ci95: Option<[f64; 2]>,
    /// Races: where the overtakes happened, by the gate the ego flew towards when it took
    /// the lead, gates without an overtake left out (absent without an overtake).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub overtakes_by_gate: Vec<GateOvertakes>,
}

/// The overtakes taken while the ego flew towards one gate, all episodes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct GateOvertakes {
    /// The gate's index on the track.
    pub gate: usize,
    /// Overtakes.
    pub overtakes: u64,
    /// Of them, sustained for 2 s.
    pub sustained: u64,
}

impl GateOvertakes {
    /// The gates of `by_gate` at which at least one overtake was sustained: where the ego
    /// holds its passes, issue "race"'s `min_gates_held`.
    pub fn gates_held(by_gate: &[Self]) -> usize {
        by_gate.iter().filter(|g| g.sustained > 0).count()
    }

    /// The per-gate counts of `episodes`, gates without an overtake left out.
    pub fn tally(episodes: &[EpisodeMetrics]) -> Vec<Self> {
        let gates = episodes
            .iter()
            .map(|e| e.overtakes_by_gate.len())
            .max()
            .unwrap_or(0);
        (0..gates)
            .map(|gate| {
                let count = |column: usize| {
                    episodes
                        .iter()
                        .filter_map(|e| e.overtakes_by_gate.get(gate)?.get(column))
                        .map(|&n| u64::from(n))
                        .sum()
                };
                Self {
                    gate,
                    overtakes: count(0),
                    sustained: count(1),
                }
            })
            .filter(|g| g.overtakes > 0)
            .collect()
    }
}

/// What a race report says about the ego's racing, as a [`RaceBar`] judges it: the fields
/// of the same name in [`Report`] (its JSON reads into this), or an in-training referee's.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
pub struct RaceOutcome {
    /// Races flown.
    pub episodes: u32,
    /// Gates passed / (passed + crashes), mean over races.
    pub success_rate: f64,
    /// Crashes per simulated second, mean over races.
    pub crash_rate: f64,
    /// Best lap (s); `None` without a complete lap.
    pub best_lap_s: Option<f64>,
    /// Overtakes of the opponent.
    pub overtakes: u64,
    /// Of them, held 2 s.
    pub sustained_overtakes: u64,
    /// The overtakes by gate.
    #[serde(default)]
    pub overtakes_by_gate: Vec<GateOvertakes>,
}

impl RaceOutcome {
    /// The gates at which at least one overtake was sustained.
    pub fn gates_held(&self) -> usize {
        GateOvertakes::gates_held(&self.overtakes_by_gate)
    }
}

impl From<&Report> for RaceOutcome {
    fn from(r: &Report) -> Self {
        Self {
            episodes: r.episodes,
            success_rate: r.success_rate,
            crash_rate: r.crash_rate,
            best_lap_s: r.best_lap_s,
            overtakes: r.overtakes,
            sustained_overtakes: r.sustained_overtakes,
            overtakes_by_gate: r.overtakes_by_gate.clone(),
        }
    }
}

/// A per-race bar on a set of exact races: how well the ego must fly, and how many of its
/// overtakes it must hold, and where. [`RaceBar::RACE`] is issue "race"'s, which the shipped
/// race ego meets on the races of seeds 0 and 2000 and which `run.select.race_bar` asks of a
/// candidate's in-training referee.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RaceBar {
    /// The least success rate.
    pub min_success: f64,
    /// The most crashes per simulated second.
    pub max_crash_rate_per_s: f64,
    /// The slowest best lap (s); a race set without a lap misses it.
    pub max_best_lap_s: f64,
    /// The least share of the overtakes held 2 s.
    pub min_sustained_share: f64,
    /// The least sustained overtakes per 20 races.
    pub min_sustained_per_20_races: u64,
    /// The least number of gates with a sustained overtake (one gate's passes are one
    /// manoeuvre repeated, not overtaking).
    pub min_gates_held: usize,
}

impl RaceBar {
    /// Issue "race"'s bar: success >= 0.9, crashes <= 0.1 /s, best lap <= 8.0 s, at least
    /// half of the overtakes sustained and >= 16 sustained per 20 races, at >= 3 gates.
    pub const RACE: Self = Self {
        min_success: 0.9,
        max_crash_rate_per_s: 0.1,
        max_best_lap_s: 8.0,
        min_sustained_share: 0.5,
        min_sustained_per_20_races: 16,
        min_gates_held: 3,
    };

    /// What `o` misses of the bar, one line per miss, empty when it meets it.
    pub fn misses(&self, o: &RaceOutcome) -> Vec<String> {
        let mut misses = Vec::new();
        if o.success_rate.is_nan() || o.success_rate < self.min_success {
            misses.push(format!(
                "success {:.3} < {}",
                o.success_rate, self.min_success
            ));
        }
        if o.crash_rate.is_nan() || o.crash_rate > self.max_crash_rate_per_s {
            misses.push(format!(
                "crashes {:.3} /s > {}",
                o.crash_rate, self.max_crash_rate_per_s
            ));
        }
        match o.best_lap_s {
            Some(l) if l <= self.max_best_lap_s => {}
            lap => misses.push(format!(
                "best lap {} > {} s",
                lap.map_or("DNF".to_string(), |l| format!("{l:.2} s")),
                self.max_best_lap_s
            )),
        }
        let held = o.sustained_overtakes;
        if (held as f64) < self.min_sustained_share * o.overtakes as f64 {
            misses.push(format!(
                "{held} of {} overtakes sustained < {}",
                o.overtakes, self.min_sustained_share
            ));
        }
        if held * 20 < self.min_sustained_per_20_races * u64::from(o.episodes) {
            misses.push(format!(
                "{held} sustained overtakes in {} races < {} per 20",
                o.episodes, self.min_sustained_per_20_races
            ));
        }
        if o.gates_held() < self.min_gates_held {
            misses.push(format!(
                "overtakes held at {} gates < {}",
                o.gates_held(),
                self.min_gates_held
            ));
        }
        misses
    }
}

impl Report {
    /// Aggregates `episodes`, labelled with the pilots and configuration.
    pub fn new(
        ego: &PilotSpec,
        opponent: Option<&PilotSpec>,
        config: &EvalConfig,
        episodes: &[EpisodeMetrics],
    ) -> Self {
        let sum = |f: fn(&EpisodeMetrics) -> u32| episodes.iter().map(|e| u64::from(f(e))).sum();
        let success: Vec<f64> = episodes.iter().map(EpisodeMetrics::success_rate).collect();
        let crash: Vec<f64> = episodes
            .iter()
            .map(EpisodeMetrics::crash_rate_per_s)
            .collect();
        let laps: Vec<f64> = episodes
            .iter()
            .flat_map(|e| e.lap_times_s.iter().copied())
            .collect();
        let wins: Vec<f64> = episodes
            .iter()
            .filter_map(EpisodeMetrics::win_rate)
            .collect();
        let race = opponent.is_some() && !wins.is_empty();
        let overtakes: u64 = sum(|e| e.overtakes);
        let sustained: u64 = sum(|e| e.sustained_overtakes);
        Self {
            ego: ego.describe(),
            opponent: opponent.map(PilotSpec::describe),
            preset: config.preset.name.to_string(),
            spawn: config.spawn_mode(opponent.is_some()).name().to_string(),
            seed: config.seed,
            perturbation: config.perturbation,
            episodes: episodes.len() as u32,
            episode_seconds: f64::from(config.seconds),
            sim_seconds: episodes.iter().map(|e| f64::from(e.sim_seconds)).sum(),
            gates_passed: sum(|e| e.gates_passed),
            gates_encountered: sum(|e| e.gates_encountered),
            success_rate: mean(&success).unwrap_or(0.0),
            success_rate_ci95: ci95(&success, 0.0, 1.0),
            crashes: sum(|e| e.crashes),
            crash_rate: mean(&crash).unwrap_or(0.0),
            crash_rate_ci95: ci95(&crash, 0.0, f64::INFINITY),
            best_lap_s: laps.iter().copied().reduce(f64::min),
            mean_lap_s: mean(&laps),
            laps: laps.len() as u64,
            overtakes,
            sustained_overtakes: sustained,
            sustained_overtake_rate: (overtakes > 0).then(|| sustained as f64 / overtakes as f64),
            opponent_crashes: sum(|e| e.opponent_crashes),
            crash_causes: episodes
                .iter()
                .fold(CrashCounts::default(), |a, e| a.plus(e.crash_causes)),
            flights: race.then(|| sum(|e| e.flights)),
            win_rate: if race { mean(&wins) } else { None },
            win_rate_ci95: if race { ci95(&wins, 0.0, 1.0) } else { None },
            overtakes_by_gate: GateOvertakes::tally(episodes),
        }
    }

    /// The report as pretty JSON.
    pub fn to_json(&self) -> String {
        let mut json = serde_json::to_string_pretty(self)
            .unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"));
        json.push('\n');
        json
    }

    /// The Table-1 row and a short summary, for a terminal.
    pub fn table(&self) -> String {
        let ci = |c: Option<[f64; 2]>, digits: usize| match c {
            Some([a, b]) => format!(" [{a:.digits$}, {b:.digits$}]"),
            None => String::new(),
        };
        let lap = match self.best_lap_s {
            Some(t) => format!("{t:.2} s"),
            None => "DNF".into(),
        };
        let overtake = match (self.opponent.is_some(), self.sustained_overtake_rate) {
            (false, _) => "—".to_string(),
            (true, None) => "Fail".to_string(),
            (true, Some(r)) => format!("{r:.2} ({}/{})", self.sustained_overtakes, self.overtakes),
        };
        let mut out = String::new();
        out += &format!(
            "ego {}{}; preset {}, {} spawn, {} episodes x {:.0} s, seed {}\n",
            self.ego,
            self.opponent
                .as_ref()
                .map(|o| format!(" vs opponent {o}"))
                .unwrap_or_default(),
            self.preset,
            self.spawn,
            self.episodes,
            self.episode_seconds,
            self.seed
        );
        if !self.perturbation.is_none() {
            out += &format!("perturbed: {}\n", self.perturbation.describe());
        }
        let rows = [
            (
                "success rate",
                format!("{:.3}{}", self.success_rate, ci(self.success_rate_ci95, 3)),
            ),
            (
                "crash rate (/s)",
                format!("{:.3}{}", self.crash_rate, ci(self.crash_rate_ci95, 3)),
            ),
            ("lap time", lap),
            ("sustained overtakes", overtake),
            (
                "win rate",
                match self.win_rate {
                    Some(r) => format!("{r:.3}{}", ci(self.win_rate_ci95, 3)),
                    None => "—".to_string(),
                },
            ),
        ];
        let w: Vec<usize> = rows
            .iter()
            .map(|(h, v)| h.chars().count().max(v.chars().count()))
            .collect();
        let line = |cells: Vec<&str>| {
            let mut s = String::from("|");
            for (c, w) in cells.iter().zip(&w) {
                s += &format!(" {c:<w$} |", w = *w);
            }
            s + "\n"
        };
        out += &line(rows.iter().map(|r| r.0).collect());
        out += &line(rows.iter().map(|r| r.1.as_str()).collect());
        out += &format!(
            "gates {} passed / {} encountered, {} crashes, {} laps{}",
            self.gates_passed,
            self.gates_encountered,
            self.crashes,
            self.laps,
            self.mean_lap_s
                .map(|m| format!(" (mean {m:.2} s)"))
                .unwrap_or_default()
        );
        if self.crashes > 0 {
            let c = &self.crash_causes;
            out += &format!(
                " (gate frame {}, ground {}, bounds {}, collision {}, diverged {})",
                c.gate_frame, c.ground, c.out_of_bounds, c.collision, c.non_finite
            );
        }
        if self.opponent.is_some() {
            out += &format!(", opponent crashes {}", self.opponent_crashes);
            if let Some(f) = self.flights {
                out += &format!(", {f} flights");
            }
        }
        if !self.overtakes_by_gate.is_empty() {
            let held_at = GateOvertakes::gates_held(&self.overtakes_by_gate);
            out += &format!(
                "\novertakes by the gate the ego flew towards (sustained/all): {}; sustained at {held_at} distinct gate{}",
                self.overtakes_by_gate
                    .iter()
                    .map(|g| format!("g{} {}/{}", g.gate, g.sustained, g.overtakes))
                    .collect::<Vec<_>>()
                    .join(", "),
                if held_at == 1 { "" } else { "s" }
            );
        }
        out + "\n"
    }
}
