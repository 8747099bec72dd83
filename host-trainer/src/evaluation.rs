//! The referee inside a run: sitl's evaluation of the deterministic policy every
//! `run.eval_every` iterations (and of every warm-start round with
//! `warm_start.keep_best_round`), and the order in which `run.keep_best` ranks evaluations.

use crate::config::TrainConfig;
use crate::metrics::IterationMetrics;
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, Report, report};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;

/// The referee's verdict on the deterministic policy. A time trial: one 45 s episode from the
/// stage-1 spawn (the evaluation of issue "stage1"; the fixed spawn and the deterministic
/// policy make every such episode identical, so one is enough). A race: `run.eval_races`
/// 45 s races against the config's opponent from stage-2 spawns (seed `run.eval_seed`).
pub fn referee_eval(blob: &[u8], preset: Preset, config: &TrainConfig) -> Option<Report> {
    let spec = PilotSpec::from_blob("training", blob).ok()?;
    let opponent = match &config.race {
        None => None,
        Some(r) => Some(PilotSpec::load(&r.opponent, &preset).ok()?),
    };
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
    };
    Some(report(&spec, opponent.as_ref(), &eval))
}

/// Whether the referee scored evaluation `a` better than `b` (`run.keep_best`): the higher
/// success rate, then the lower crash rate; an exact tie keeps the earlier (`b`).
pub fn referee_prefers(a: &IterationMetrics, b: &IterationMetrics) -> bool {
    let key = |m: &IterationMetrics| {
        (
            m.eval_success_rate.unwrap_or(f64::NEG_INFINITY),
            -m.eval_crash_rate.unwrap_or(f64::INFINITY),
        )
    };
    let (ka, kb) = (key(a), key(b));
    ka.0 > kb.0 || (ka.0 == kb.0 && ka.1 > kb.1)
}

/// The best-scored evaluation of `history` (`run.keep_best`): the one [`referee_prefers`]
/// to every other, the earliest of equals.
pub fn best_evaluation(history: &[IterationMetrics]) -> Option<&IterationMetrics> {
    history
        .iter()
        .filter(|m| m.eval_success_rate.is_some())
        .fold(None, |best, m| match best {
            Some(b) if !referee_prefers(m, b) => Some(b),
            _ => Some(m),
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
        assert_eq!(best_evaluation(&history).map(|m| m.iteration), Some(15));
        assert!(referee_prefers(&history[2], &history[0]));
        assert!(!referee_prefers(&history[4], &history[3]));
        assert!(best_evaluation(&history[1..2]).is_none());
    }
}
