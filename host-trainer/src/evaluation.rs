//! The referee inside a run: sitl's evaluation of the deterministic policy every
//! `run.eval_every` iterations (and of every warm-start round with
//! `warm_start.keep_best_round`), and the order in which `run.keep_best` ranks evaluations.

use crate::config::{KeepBestBy, RACE_SUCCESS_FLOOR, RunConfig, Selection, TrainConfig};
use crate::metrics::IterationMetrics;
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, RaceBar, RaceOutcome, Report, report};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;

/// The referee's verdict on the deterministic policy. A time trial: one 45 s episode from the
/// stage-1 spawn (the evaluation of issue "stage1"; the fixed spawn and the deterministic
/// policy make every such episode identical, so one is enough). A race: `run.eval_races`
/// 45 s races against the config's opponent from stage-2 spawns (seed `run.eval_seed`).
pub fn referee_eval(blob: &[u8], preset: Preset, config: &TrainConfig) -> Option<Report> {
    let spec = PilotSpec::from_blob("training", blob).ok()?;
    let opponent = race_opponent(preset, config)?;
    let eval = EvalConfig {
        preset,
        episodes: if opponent.is_some() {
            config.run.eval_races
        } else {
            1
        },
        seconds: 45.0,
        seed: config.run.eval_seed,
        spawn: Some(if opponent.is_some() {
            SpawnMode::Stage2
        } else {
            SpawnMode::Stage1
        }),
        perturbation: eval_perturbation(config, opponent.is_some()),
    };
    Some(report(&spec, opponent.as_ref(), &eval))
}

/// The opponent a race's evaluations fly against (`Some(None)` in a time trial); `None` if
/// its blob cannot be loaded.
pub fn race_opponent(preset: Preset, config: &TrainConfig) -> Option<Option<PilotSpec>> {
    match &config.env.race {
        None => Some(None),
        Some(r) => PilotSpec::load(&r.opponent.to_string_lossy(), &preset)
            .ok()
            .map(Some),
    }
}

/// The referee's perturbation during training: the standard start jitter for a race with
/// `run.eval_jitter`, else none (the nominal flight).
pub fn eval_perturbation(config: &TrainConfig, race: bool) -> sitl::perturb::Perturbation {
    use sitl::perturb::Perturbation;
    if race && config.run.eval_jitter {
        Perturbation::JITTERED
    } else {
        Perturbation::NONE
    }
}

/// Whether the referee scored evaluation `a` better than `b` (`run.keep_best`): the higher
/// success rate, then the lower crash rate; an exact tie keeps the earlier (`b`).
pub fn referee_prefers(a: &IterationMetrics, b: &IterationMetrics) -> bool {
    let key = |m: &IterationMetrics| score(m.eval_success_rate, m.eval_crash_rate, None);
    key(a) > key(b)
}

/// What `run.select` validates a candidate by: the means over its perturbations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Validation {
    /// The mean of the conditions' success rates.
    pub success_rate: f64,
    /// The mean of the conditions' crashes per second.
    pub crash_rate: f64,
    /// The mean of the conditions' mean laps (s), over those that flew a lap; `None` if none did.
    pub mean_lap_s: Option<f64>,
}

/// The validation of `run.select`: the deterministic policy flown `episodes` × 45 s from
/// the selection's spawns (seed `seed`, jittered with `jitter`) under each of `perturb`
/// (unperturbed when it names none), alone or racing `opponent`, averaged over them.
pub fn selection_eval(
    blob: &[u8],
    preset: Preset,
    select: &Selection,
    opponent: Option<&PilotSpec>,
) -> Option<Validation> {
    let spec = PilotSpec::from_blob("training", blob).ok()?;
    let conditions: Vec<sitl::perturb::Perturbation> = if select.perturb.is_empty() {
        vec![sitl::perturb::Perturbation::NONE]
    } else {
        select.perturb.iter().map(|p| *p.value()).collect()
    };
    let jitter = select
        .jitter
        .as_ref()
        .map(|j| *j.value())
        .unwrap_or_default();
    let reports: Vec<Report> = conditions
        .into_iter()
        .map(|perturbation| {
            let eval = EvalConfig {
                preset,
                episodes: select.episodes,
                seconds: 45.0,
                seed: select.seed,
                spawn: Some(select.spawn),
                perturbation: sitl::perturb::Perturbation {
                    jitter,
                    ..perturbation
                },
            };
            report(&spec, opponent, &eval)
        })
        .collect();
    let n = reports.len() as f64;
    let laps: Vec<f64> = reports.iter().filter_map(|r| r.mean_lap_s).collect();
    Some(Validation {
        success_rate: reports.iter().map(|r| r.success_rate).sum::<f64>() / n,
        crash_rate: reports.iter().map(|r| r.crash_rate).sum::<f64>() / n,
        mean_lap_s: (!laps.is_empty()).then(|| laps.iter().sum::<f64>() / laps.len() as f64),
    })
}

/// The key `run.keep_best` ranks by, greater is better: success, then fewer crashes, then a
/// shorter lap (absent: a DNF, the worst).
fn score(success: Option<f64>, crashes: Option<f64>, lap_s: Option<f64>) -> (f64, f64, f64) {
    (
        success.unwrap_or(f64::NEG_INFINITY),
        -crashes.unwrap_or(f64::INFINITY),
        -lap_s.unwrap_or(f64::INFINITY),
    )
}

/// `run.keep_best`'s key of evaluation `m`, `None` where it is no candidate: without
/// `run.select`, the in-training referee's success and crashes (with `run.keep_best_by =
/// "win-rate"`: whether the success reaches [`RACE_SUCCESS_FLOOR`], then the win rate, the
/// success and the crashes; below the floor the success and crashes); with it, the
/// validation's success, crashes and mean lap, from `run.select.from_iteration` on, those
/// whose referee reached `run.select.referee_floor` (and met `run.select.race_bar`) first.
fn candidate_score(m: &IterationMetrics, run: &RunConfig) -> Option<(f64, f64, f64, f64)> {
    let plain = |(a, b, c)| (0.0, a, b, c);
    match &run.select {
        None if run.keep_best_by == KeepBestBy::WinRate => {
            let success = m.eval_success_rate?;
            let (_, crashes, _) = score(None, m.eval_crash_rate, None);
            Some(if success >= RACE_SUCCESS_FLOOR {
                (1.0, m.eval_win_rate.unwrap_or(0.0), success, crashes)
            } else {
                plain(score(Some(success), m.eval_crash_rate, None))
            })
        }
        None => m
            .eval_success_rate
            .map(|_| plain(score(m.eval_success_rate, m.eval_crash_rate, None))),
        Some(s) if m.iteration >= s.from_iteration => m.select_success_rate.map(|_| {
            let (success, crashes, lap) = score(
                m.select_success_rate,
                m.select_crash_rate,
                m.select_mean_lap_s,
            );
            let below_floor = s
                .referee_floor
                .is_some_and(|f| m.eval_success_rate.unwrap_or(f64::NEG_INFINITY) < f);
            let misses_bar = s.race_bar && !meets_race_bar(m, run.eval_races);
            let tier = if below_floor || misses_bar { 0.0 } else { 1.0 };
            (tier, success, crashes, lap)
        }),
        Some(_) => None,
    }
}

/// Whether the referee's `races` races of evaluation `m` meet issue "race"'s per-race bar
/// ([`RaceBar::RACE`]); an evaluation without a referee's race does not.
fn meets_race_bar(m: &IterationMetrics, races: u32) -> bool {
    race_outcome(m, races).is_some_and(|o| RaceBar::RACE.misses(&o).is_empty())
}

/// The referee's races of evaluation `m` as [`RaceBar`] reads them (`None` where `m` has no
/// referee's race).
fn race_outcome(m: &IterationMetrics, races: u32) -> Option<RaceOutcome> {
    Some(RaceOutcome {
        episodes: races,
        success_rate: m.eval_success_rate?,
        crash_rate: m.eval_crash_rate?,
        best_lap_s: m.eval_best_lap_s,
        overtakes: m.eval_overtakes?,
        sustained_overtakes: m.eval_sustained_overtakes?,
        overtakes_by_gate: m.eval_overtakes_by_gate.clone(),
    })
}

/// Whether `m` becomes `run.keep_best`'s best over the current `best` (`None`: no candidate
/// yet); an exact tie keeps the earlier.
pub fn keep_best_prefers(
    m: &IterationMetrics,
    best: Option<&IterationMetrics>,
    run: &RunConfig,
) -> bool {
    match (
        candidate_score(m, run),
        best.and_then(|b| candidate_score(b, run)),
    ) {
        (Some(a), Some(b)) => a > b,
        (Some(_), None) => true,
        (None, _) => false,
    }
}

/// The best-scored candidate of `history` under `run.keep_best` (as [`keep_best_prefers`]
/// ranks them), the earliest of equals.
pub fn best_evaluation<'a>(
    history: &'a [IterationMetrics],
    run: &RunConfig,
) -> Option<&'a IterationMetrics> {
    history.iter().fold(None, |best, m| {
        if keep_best_prefers(m, best, run) {
            Some(m)
        } else {
            best
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_referee_prefers_success_then_fewer_crashes_then_the_earlier() {
        let eval = |iteration, success, crashes| IterationMetrics {
            iteration,
            eval_success_rate: Some(success),
            eval_crash_rate: Some(crashes),
            ..IterationMetrics::default()
        };
        let history = [
            eval(5, 0.80, 0.10),
            IterationMetrics {
                iteration: 6,
                ..IterationMetrics::default()
            },
            eval(10, 0.85, 0.20),
            eval(15, 0.85, 0.10),
            eval(20, 0.85, 0.10),
            eval(25, 0.70, 0.00),
        ];
        let run = RunConfig::default();
        assert_eq!(
            best_evaluation(&history, &run).map(|m| m.iteration),
            Some(15)
        );
        assert!(referee_prefers(&history[2], &history[0]));
        assert!(!referee_prefers(&history[4], &history[3]));
        assert!(best_evaluation(&history[1..2], &run).is_none());
    }

    #[test]
    fn eval_jitter_jitters_race_evaluations_only() {
        let mut config =
            crate::config::TrainConfig::parse(include_str!("../configs/smoke_race.toml"))
                .expect("the smoke race config");
        assert!(eval_perturbation(&config, true).is_none());
        config.run.eval_jitter = true;
        let p = eval_perturbation(&config, true);
        assert_eq!(p.jitter, sitl::perturb::StartJitter::STANDARD);
        assert!(p.validate().is_ok());
        assert!(eval_perturbation(&config, false).is_none());
    }

    #[test]
    fn with_a_selection_the_validation_ranks_from_its_first_iteration_on() {
        let eval = |iteration, stage1: f64, validation: Option<(f64, f64, Option<f64>)>| {
            IterationMetrics {
                iteration,
                eval_success_rate: Some(stage1),
                eval_crash_rate: Some(0.0),
                select_success_rate: validation.map(|v| v.0),
                select_crash_rate: validation.map(|v| v.1),
                select_mean_lap_s: validation.and_then(|v| v.2),
                ..IterationMetrics::default()
            }
        };
        let run = RunConfig {
            keep_best: true,
            select: Some(Selection {
                spawn: SpawnMode::AlongTrack,
                episodes: 10,
                seed: 7,
                from_iteration: 20,
                perturb: Vec::new(),
                jitter: None,
                referee_floor: None,
                race_bar: false,
            }),
            ..RunConfig::default()
        };
        let history = [
            // Before from_iteration: not a candidate, even validated and perfect.
            eval(10, 1.0, Some((1.0, 0.0, Some(7.0)))),
            // The stage-1 referee is not what ranks.
            eval(20, 1.0, Some((0.95, 0.01, Some(7.9)))),
            eval(30, 0.5, Some((0.97, 0.02, Some(8.0)))),
            eval(40, 0.9, Some((0.97, 0.01, Some(8.1)))),
            // Same success and crashes: the shorter mean lap wins; a DNF loses to any lap.
            eval(50, 0.9, Some((0.97, 0.01, Some(7.95)))),
            eval(60, 0.9, Some((0.97, 0.01, None))),
            // An exact tie keeps the earlier.
            eval(70, 1.0, Some((0.97, 0.01, Some(7.95)))),
            eval(80, 1.0, None),
        ];
        assert_eq!(
            best_evaluation(&history, &run).map(|m| m.iteration),
            Some(50)
        );
        assert_eq!(
            best_evaluation(&history[..2], &run).map(|m| m.iteration),
            Some(20)
        );
        assert!(best_evaluation(&history[..1], &run).is_none());
        let without = RunConfig {
            select: None,
            ..run
        };
        assert_eq!(
            best_evaluation(&history, &without).map(|m| m.iteration),
            Some(10)
        );
    }

    /// `run.select.perturb` flies the validation under the perturbation (a list: the means over
    /// it; `run.select.jitter` from jittered starts): `stage1_nominal.blob`, which
    /// one step of latency breaks, validates worse under it; absent, the validation is the
    /// unperturbed one.
    #[test]
    fn a_perturbed_selection_flies_its_perturbation() {
        let blob = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../policies/stage1_nominal.blob"
        ))
        .unwrap();
        let select = |perturb: &[&str]| Selection {
            spawn: SpawnMode::AlongTrack,
            episodes: 6,
            seed: 7,
            from_iteration: 0,
            perturb: perturb
                .iter()
                .map(|p| sitl::perturb::PerturbSpec::parse(p).unwrap())
                .collect(),
            jitter: None,
            referee_floor: None,
            race_bar: false,
        };
        let preset = sitl::dynamics::Preset::paper();
        let nominal = selection_eval(&blob, preset, &select(&[]), None).unwrap();
        let late = selection_eval(&blob, preset, &select(&["latency=1"]), None).unwrap();
        let both = selection_eval(&blob, preset, &select(&["", "latency=1"]), None).unwrap();
        let jittered = Selection {
            jitter: Some(sitl::perturb::JitterSpec::parse("").unwrap()),
            ..select(&[])
        };
        let jittered = selection_eval(&blob, preset, &jittered, None).unwrap();
        assert_ne!(jittered, nominal, "the jitter moved no start");
        assert!(nominal.success_rate > 0.9, "{}", nominal.success_rate);
        assert_eq!(
            both.success_rate,
            (nominal.success_rate + late.success_rate) / 2.0
        );
        assert_eq!(
            both.crash_rate,
            (nominal.crash_rate + late.crash_rate) / 2.0
        );
        assert!(
            late.crash_rate > nominal.crash_rate + 0.2,
            "{} against {}",
            late.crash_rate,
            nominal.crash_rate
        );
    }

    /// A race's validation races the opponent: `stage1_nominal.blob` validated from stage-2
    /// starts against itself is another flight than alone (the opponent holds the line
    /// ahead or beside it), and the same opponent gives the same validation.
    #[test]
    fn a_race_selection_races_its_opponent() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../policies/stage1_nominal.blob"
        );
        let blob = std::fs::read(path).unwrap();
        let preset = sitl::dynamics::Preset::paper();
        let opponent = PilotSpec::load(path, &preset).unwrap();
        let select = Selection {
            spawn: SpawnMode::Stage2,
            episodes: 6,
            seed: 7,
            from_iteration: 0,
            perturb: Vec::new(),
            jitter: None,
            referee_floor: Some(0.9),
            race_bar: false,
        };
        let alone = selection_eval(&blob, preset, &select, None).unwrap();
        let raced = selection_eval(&blob, preset, &select, Some(&opponent)).unwrap();
        assert_ne!(alone, raced, "the opponent changed nothing");
        assert_eq!(
            selection_eval(&blob, preset, &select, Some(&opponent)),
            Some(raced)
        );
    }

    /// A race run keeping the best of every evaluation, validated from 10 stage-2 spawns,
    /// with `referee_floor` and `race_bar` over `eval_races` referee races.
    fn ranked_by_referee(referee_floor: Option<f64>, race_bar: bool, eval_races: u32) -> RunConfig {
        RunConfig {
            keep_best: true,
            eval_races,
            select: Some(Selection {
                spawn: SpawnMode::Stage2,
                episodes: 10,
                seed: 7,
                from_iteration: 0,
                perturb: Vec::new(),
                jitter: None,
                referee_floor,
                race_bar,
            }),
            ..RunConfig::default()
        }
    }

    /// `run.select.referee_floor`: the candidates whose referee reached the floor rank first,
    /// however well the others validate; among them (and among those below) the validation
    /// ranks.
    #[test]
    fn a_referee_floor_ranks_the_candidates_that_reach_it_first() {
        let eval = |iteration, referee: f64, validation: f64| IterationMetrics {
            iteration,
            eval_success_rate: Some(referee),
            eval_crash_rate: Some(0.0),
            select_success_rate: Some(validation),
            select_crash_rate: Some(0.0),
            select_mean_lap_s: Some(7.9),
            ..IterationMetrics::default()
        };
        let run = |floor| ranked_by_referee(floor, false, 20);
        let history = [
            eval(10, 0.80, 0.99),
            eval(20, 0.95, 0.91),
            eval(30, 0.90, 0.93),
            eval(40, 1.00, 0.92),
        ];
        let best =
            |h: &[IterationMetrics], floor| best_evaluation(h, &run(floor)).map(|m| m.iteration);
        assert_eq!(best(&history, None), Some(10));
        assert_eq!(
            best(&history, Some(0.9)),
            Some(30),
            "the floor is reached at it"
        );
        assert_eq!(best(&history, Some(0.96)), Some(40));
        // None reaches it: the validation ranks them all.
        assert_eq!(best(&history[..3], Some(0.99)), Some(10));
        // A candidate the referee did not score is below the floor.
        let unscored = IterationMetrics {
            eval_success_rate: None,
            ..eval(50, 0.0, 1.0)
        };
        assert_eq!(best(&[unscored, history[1].clone()], Some(0.9)), Some(20));
    }

    /// `run.select.race_bar`: the candidates whose referee's races meet issue "race"'s
    /// per-race bar rank first, whatever they validate; the bar scales with `run.eval_races`
    /// and counts the gates the overtakes were held at, which the metrics line keeps.
    #[test]
    fn the_race_bar_ranks_the_candidates_whose_races_meet_it_first() {
        use sitl::eval::GateOvertakes;
        let gates = |held: &[u64]| -> Vec<GateOvertakes> {
            held.iter()
                .enumerate()
                .map(|(gate, &sustained)| GateOvertakes {
                    gate,
                    overtakes: 2 * sustained,
                    sustained,
                })
                .collect()
        };
        let eval = |iteration, held: &[u64], validation: f64| IterationMetrics {
            iteration,
            eval_success_rate: Some(0.97),
            eval_crash_rate: Some(0.02),
            eval_best_lap_s: Some(7.8),
            eval_overtakes: Some(2 * held.iter().sum::<u64>()),
            eval_sustained_overtakes: Some(held.iter().sum()),
            eval_overtakes_by_gate: gates(held),
            select_success_rate: Some(validation),
            select_crash_rate: Some(0.0),
            select_mean_lap_s: Some(7.9),
            ..IterationMetrics::default()
        };
        let run = |race_bar, eval_races| ranked_by_referee(None, race_bar, eval_races);
        let history = [
            eval(80, &[0, 0, 0, 0, 0, 18], 0.922),
            eval(150, &[11, 0, 10, 0, 10], 0.908),
            eval(160, &[9, 9], 0.93),
            eval(170, &[6, 6, 6], 0.91),
        ];
        let best =
            |race_bar, races| best_evaluation(&history, &run(race_bar, races)).map(|m| m.iteration);
        assert_eq!(best(false, 20), Some(160), "the validation alone");
        assert_eq!(best(true, 20), Some(170), "three gates and 16 per 20 races");
        assert_eq!(best(true, 25), Some(150), "25 races need 20 sustained");
        assert!(meets_race_bar(&history[1], 20) && !meets_race_bar(&history[0], 20));
        // An evaluation that kept no gates (a metrics line from before they were recorded)
        // does not meet the bar, and neither does one without a referee.
        let unrecorded = IterationMetrics {
            eval_overtakes_by_gate: Vec::new(),
            ..history[1].clone()
        };
        assert!(!meets_race_bar(&unrecorded, 20));
        assert!(!meets_race_bar(&IterationMetrics::default(), 20));
        // The gates round-trip through metrics.jsonl.
        let line = serde_json::to_string(&history[1]).unwrap();
        assert_eq!(
            serde_json::from_str::<IterationMetrics>(&line).unwrap(),
            history[1]
        );
    }

    #[test]
    fn a_race_ranked_by_win_rate_needs_the_success_floor_first() {
        let race = |iteration, success, crashes, win| IterationMetrics {
            iteration,
            eval_success_rate: Some(success),
            eval_crash_rate: Some(crashes),
            eval_win_rate: Some(win),
            ..IterationMetrics::default()
        };
        let run = RunConfig {
            keep_best: true,
            keep_best_by: KeepBestBy::WinRate,
            ..RunConfig::default()
        };
        let history = [
            // Below the floor: ranked by success, under every candidate above it.
            race(10, 0.89, 0.0, 0.95),
            race(20, 0.95, 0.02, 0.60),
            // Above the floor, the higher win rate wins over the higher success.
            race(30, 0.91, 0.05, 0.70),
            race(40, 0.99, 0.01, 0.65),
            // Equal win rate: the higher success.
            race(50, 0.93, 0.04, 0.70),
            // An exact tie keeps the earlier.
            race(60, 0.93, 0.04, 0.70),
        ];
        assert_eq!(
            best_evaluation(&history, &run).map(|m| m.iteration),
            Some(50)
        );
        assert_eq!(
            best_evaluation(&history[..1], &run).map(|m| m.iteration),
            Some(10)
        );
        assert_eq!(
            best_evaluation(&history[..2], &run).map(|m| m.iteration),
            Some(20)
        );
        // The default ranks by success alone.
        let by_success = RunConfig {
            keep_best_by: KeepBestBy::Success,
            ..run
        };
        assert_eq!(
            best_evaluation(&history, &by_success).map(|m| m.iteration),
            Some(40)
        );
    }
}
