//! The imitation warm start of a fresh run (`[warm_start]`, not in the paper): DAgger stages
//! ([`crate::imitation`]) turn the initial actor into a student of a teacher before PPO,
//! optionally refereeing every round's student and keeping the best
//! (`warm_start.keep_best_round`). The rounds go to `imitation.jsonl`, the student to
//! `warm_start.blob`, and a checkpoint at iteration 0 keeps a resume from redoing it.

use crate::config::{TrainConfig, WarmStart};
use crate::error::{TrainError, io};
use crate::evaluation::{referee_eval, referee_prefers};
use crate::export::{actor_blob, payload_blob};
use crate::imitation::{Imitate, ImitationRound};
use crate::metrics::{Console, IterationMetrics, lap_text};
use crate::nets::ValueNet;
use crate::ppo::Learner;
use crate::run_dir::{RunDir, RunState};
use burn::tensor::Device;
use sitl::dynamics::Preset;
use sitl::files::write_atomically;
use std::time::Instant;

/// Runs the warm start on `student` (the initial actor, or `warm_start.student`); the result
/// replaces the run's actor (its σ kept).
pub(crate) fn warm_start<A: Imitate, C: ValueNet>(
    state: &mut RunState<A, C>,
    student: A,
    config: &TrainConfig,
    warm: &WarmStart,
    dir: &RunDir,
    device: &Device,
    progress: bool,
) -> Result<(), TrainError> {
    let started = Instant::now();
    let arch = config.architecture()?;
    let teacher = match &warm.teacher_blob {
        Some(p) => p.clone(),
        None => format!("the baseline at {} m/s", warm.teacher_cruise_mps),
    };
    let stages = warm.stages();
    let rounds: u32 = stages.iter().map(|s| s.rounds).sum();
    println!("imitation warm start: {rounds} DAgger rounds of {teacher}");
    let console = Console::new(
        progress,
        u64::from(rounds),
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} rounds  {msg}",
    );
    if warm.keep_best_round {
        dir.create()?;
    }
    let mut log = RoundLog {
        config,
        dir,
        preset: config.preset(),
        select: warm.keep_best_round,
        console: &console,
        text: String::new(),
        best: None,
        failure: None,
    };
    let mut actor = student;
    // Rounds are numbered through the stages in the log.
    let mut before = 0;
    for (k, stage) in stages.iter().enumerate() {
        if k > 0 {
            console.say(format!(
                "refine stage {k}: {} rounds of {} steps, the student flying",
                stage.rounds, stage.steps_per_env
            ));
        }
        let last = before + stage.rounds;
        actor = actor
            .imitate(&arch, config, stage, device, &mut |r, payload| {
                log.record(before, last, r, payload)
            })?
            .0;
        if let Some(e) = log.failure.take() {
            return Err(e);
        }
        before = last;
    }
    if let Some((round, payload)) = log.best.take() {
        actor = A::from_payload(&arch, &payload, &actor.std(), device).ok_or_else(|| {
            TrainError::Export("warm start: the best round's weights do not load".into())
        })?;
        console.say(format!(
            "the warm start ends with round {}'s student, the referee's best",
            round.round
        ));
    }
    console.bar().finish_and_clear();
    let log_path = dir.file("imitation.jsonl");
    write_atomically(&log_path, log.text.as_bytes()).map_err(io(&log_path))?;
    let elapsed = started.elapsed().as_secs_f64();
    state.wall_s += elapsed;
    state.learner = Learner::new(
        actor,
        state.learner.critic.clone(),
        state.learner.learning_rate,
        device.clone(),
    );
    let blob = actor_blob(&state.learner.actor, config, 0)?;
    if let Some(r) = referee_eval(&blob, config.preset(), config) {
        let overtakes = if config.env.race.is_some() {
            format!(
                ", {} overtakes ({} sustained)",
                r.overtakes, r.sustained_overtakes
            )
        } else {
            String::new()
        };
        println!(
            "imitation done in {elapsed:.0} s; the student, referee: success {:.3}, crashes {:.3}/s, best lap {}{overtakes}",
            r.success_rate,
            r.crash_rate,
            lap_text(r.best_lap_s),
        );
    }
    let student = dir.file("warm_start.blob");
    write_atomically(&student, &blob).map_err(io(&student))?;
    dir.create()?;
    dir.save_checkpoint(state, config)
}

/// The rounds of a warm start as they end: the log lines, and with
/// `warm_start.keep_best_round` each round's student refereed and the best kept.
struct RoundLog<'a> {
    config: &'a TrainConfig,
    dir: &'a RunDir,
    preset: Preset,
    select: bool,
    console: &'a Console,
    /// `imitation.jsonl` so far.
    text: String,
    /// The best-refereed round so far and its student's weights.
    best: Option<(ImitationRound, Vec<f32>)>,
    /// A failure of the referee (reported when the stage returns).
    failure: Option<TrainError>,
}

impl RoundLog<'_> {
    /// Round `r` of a stage whose rounds follow `before` earlier ones and end at `last`,
    /// with its student's weights `payload`.
    fn record(&mut self, before: u32, last: u32, r: &ImitationRound, payload: &[f32]) {
        let mut r = ImitationRound {
            round: before + r.round,
            ..r.clone()
        };
        if self.select && self.failure.is_none() {
            match referee_round(&r, payload, self.config, self.dir, self.preset) {
                Ok(refereed) => r = refereed,
                Err(e) => self.failure = Some(e),
            }
            if round_prefers(&r, self.best.as_ref().map(|b| &b.0)) {
                self.best = Some((r.clone(), payload.to_vec()));
            }
        }
        let bar = self.console.bar();
        bar.inc(1);
        bar.set_message(format!("mse {:.4}", r.mse));
        match serde_json::to_string(&r) {
            Ok(line) => {
                self.text.push_str(&line);
                self.text.push('\n');
            }
            Err(e) => {
                self.failure
                    .get_or_insert(TrainError::Export(format!("imitation.jsonl: {e}")));
            }
        }
        if r.round.is_multiple_of(5) || r.round == last {
            let referee = match (r.referee_success_rate, r.referee_crash_rate) {
                (Some(s), Some(c)) => format!("  referee: success {s:.3}, crashes {c:.3}/s"),
                _ => String::new(),
            };
            self.console.say(format!(
                "round {:>3}  teacher {:.2}  {} samples  mse {:.4}  gates {:.2}/s  crashes {:.3}/s{referee}",
                r.round, r.teacher_share, r.samples, r.mse, r.gates_per_s, r.crash_rate_per_s
            ));
        }
    }
}

/// `round` with the referee's scores of its student `payload` (`run.eval_races` races on
/// `run.eval_seed`), whose blob is written to [`RunDir::warm_start_round_blob`].
fn referee_round(
    round: &ImitationRound,
    payload: &[f32],
    config: &TrainConfig,
    dir: &RunDir,
    preset: Preset,
) -> Result<ImitationRound, TrainError> {
    let blob = payload_blob(payload, config, 0)?;
    let path = dir.warm_start_round_blob(round.round);
    write_atomically(&path, &blob).map_err(io(&path))?;
    let report = referee_eval(&blob, preset, config);
    Ok(ImitationRound {
        referee_success_rate: report.as_ref().map(|r| r.success_rate),
        referee_crash_rate: report.as_ref().map(|r| r.crash_rate),
        ..round.clone()
    })
}

/// Whether the refereed round `a` is better than `b` (absent: none yet): the higher success,
/// then the fewer crashes, the earlier of equals ([`referee_prefers`]'s order).
fn round_prefers(a: &ImitationRound, b: Option<&ImitationRound>) -> bool {
    let key = |r: &ImitationRound| IterationMetrics {
        eval_success_rate: r.referee_success_rate,
        eval_crash_rate: r.referee_crash_rate,
        ..IterationMetrics::default()
    };
    a.referee_success_rate.is_some() && b.is_none_or(|b| referee_prefers(&key(a), &key(b)))
}
