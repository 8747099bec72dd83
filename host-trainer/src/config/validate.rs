//! The checks a configuration passes before a run starts, section by section; each refusal
//! names the field and the range it must be in.

use super::{ConfigError, KeepBestBy, TrainConfig, WarmStart};
use sitl::env::Competition;

fn bad(m: impl Into<String>) -> Result<(), ConfigError> {
    Err(ConfigError::Invalid(m.into()))
}

/// Every check, in the order the sections are read.
pub(super) fn validate(c: &TrainConfig) -> Result<(), ConfigError> {
    run(c)?;
    env_and_race(c)?;
    opponent_curriculum(c)?;
    warm_start(c)?;
    if let Some(g) = &c.guard {
        if g.envs == 0 || g.steps == 0 {
            return bad("guard.envs and guard.steps must be positive");
        }
    }
    if let Some(d) = &c.pass_decay {
        if !(d.final_weight >= 0.0 && d.final_weight.is_finite())
            || d.from_iteration >= d.to_iteration
        {
            return bad(
                "pass_decay: final_weight must be finite and >= 0 and from_iteration < to_iteration",
            );
        }
        if c.guard.is_some() {
            return bad(
                "pass_decay with [guard]: the guard measures returns at the undecayed weights; use one or the other",
            );
        }
    }
    if let Some(r) = &c.randomize_ramp {
        if c.env.randomize.is_none() {
            return bad(
                "randomize_ramp raises the share of env.randomize's draws; set env.randomize",
            );
        }
        if r.from_iteration >= r.to_iteration || r.to_iteration >= c.run.iterations {
            return bad(format!(
                "randomize_ramp: from_iteration {} must be below to_iteration {}, and to_iteration below run.iterations {}",
                r.from_iteration, r.to_iteration, c.run.iterations
            ));
        }
    }
    ppo(c)
}

fn run(c: &TrainConfig) -> Result<(), ConfigError> {
    if c.run.name.is_empty() || c.run.name.len() > 32 {
        return bad("run.name must be 1 to 32 bytes");
    }
    // The name becomes file names under --out (`<name>.blob`): no separators, no `..`,
    // nothing hidden, so every file stays in the run directory.
    let plain = |ch: char| ch.is_ascii_alphanumeric() || matches!(ch, '_' | '-' | '.');
    if !c.run.name.chars().all(plain) || c.run.name.starts_with('.') {
        return bad(
            "run.name may hold only letters, digits, '_', '-' and '.', and not start with '.' (it names files under --out)",
        );
    }
    if !('A'..='G').contains(&c.run.row) {
        return bad(format!("run.row '{}' is not a Table 1 row A-G", c.run.row));
    }
    if c.run.iterations == 0 || c.run.checkpoint_every == 0 || c.run.eval_every == 0 {
        return bad("run.iterations, checkpoint_every and eval_every must be positive");
    }
    if c.run.eval_races == 0 {
        return bad("run.eval_races must be positive");
    }
    if c.run.keep_best_by == KeepBestBy::WinRate && (!c.run.keep_best || c.env.race.is_none()) {
        return bad(
            "run.keep_best_by = \"win-rate\" ranks the candidates of a race's run.keep_best; set keep_best = true and a [race]",
        );
    }
    if let Some(s) = &c.run.select {
        if !c.run.keep_best {
            return bad("run.select ranks the candidates of run.keep_best; set keep_best = true");
        }
        if c.run.keep_best_by == KeepBestBy::WinRate {
            return bad(
                "run.select and run.keep_best_by = \"win-rate\" are two rankings; keep one",
            );
        }
        if let Some(f) = s.referee_floor
            && !(0.0..=1.0).contains(&f)
        {
            return bad("run.select.referee_floor is a success rate, within 0-1");
        }
        if s.race_bar && c.env.race.is_none() {
            return bad(
                "run.select.race_bar judges the referee's races; a time trial has none (add a [race] or drop it)",
            );
        }
        if s.spawn == sitl::referee::SpawnMode::Stage1 {
            return bad(
                "run.select.spawn 'stage1' (along-track, stage2; the stage-1 spawn is the referee's)",
            );
        }
        if s.episodes == 0 {
            return bad("run.select.episodes must be positive");
        }
        if s.from_iteration > c.run.iterations {
            return bad(
                "run.select.from_iteration is past run.iterations: nothing would be a candidate",
            );
        }
    }
    Ok(())
}

/// The stages of `[[opponent_curriculum]]`: a race's, their iterations rising and within the
/// run (each opponent's blob is read when the run starts).
fn opponent_curriculum(c: &TrainConfig) -> Result<(), ConfigError> {
    if c.opponent_curriculum.is_empty() {
        return Ok(());
    }
    if c.env.race.is_none() {
        return bad("[[opponent_curriculum]] changes a race's opponent; a time trial has none");
    }
    if c.guard.is_some() {
        return bad(
            "[[opponent_curriculum]] with [guard]: the guard measures returns against [race].opponent only; use one or the other",
        );
    }
    let mut from = 0;
    for (i, s) in c.opponent_curriculum.iter().enumerate() {
        if s.until_iteration <= from || s.until_iteration >= c.run.iterations {
            return bad(format!(
                "opponent_curriculum[{i}].until_iteration {} must be above {from} (the stage before it ends there) and below run.iterations {} (so [race].opponent is raced at the end)",
                s.until_iteration, c.run.iterations
            ));
        }
        from = s.until_iteration;
    }
    Ok(())
}

/// The row against the race section (row A races nobody, B-G race; row D is the sparse
/// competition reward), then the environment's own checks ([`sitl::env::EnvConfig::validate`]:
/// `[env]`, `[reward]` and `[race]`).
fn env_and_race(c: &TrainConfig) -> Result<(), ConfigError> {
    let race = c.env.race.is_some();
    if (c.run.row == 'A') == race {
        return bad(format!(
            "run.row '{}' {}",
            c.run.row,
            if race {
                "is the time-trial row; a [race] trains rows B to G"
            } else {
                "observes an opponent and needs a [race] section"
            }
        ));
    }
    if let Some(r) = &c.env.race {
        let sparse = r.competition == Competition::Sparse;
        if (c.run.row == 'D') != sparse {
            return bad(format!(
                "run.row '{}' with the {} competition reward: Table 1's row D is the sparse one, B, C and E-G the dense",
                c.run.row,
                if sparse { "sparse" } else { "dense" }
            ));
        }
    }
    c.env_config(c.run.seed).validate().map_err(|e| {
        // The [env] table's own fields are written `env.NAME` in a config; `reward.*` and
        // `race.*` are sections of their own.
        let section = if e.field.contains('.') { "" } else { "env." };
        ConfigError::Invalid(format!("{section}{e}"))
    })
}

/// The warm start and every refine stage.
fn warm_start(c: &TrainConfig) -> Result<(), ConfigError> {
    for w in c.warm_start.iter().flat_map(WarmStart::stages) {
        // No rounds: the student as given (refine stages have no student of their own).
        if (w.rounds == 0 && w.student.is_none() && !w.transplant)
            || w.steps_per_env == 0
            || w.epochs == 0
            || w.minibatch == 0
            || w.max_samples == 0
        {
            return bad(
                "warm_start.rounds, steps_per_env, epochs, minibatch and max_samples (and \
                 every refine stage's) must be positive (rounds may be 0 with a student or a \
                 transplant)",
            );
        }
        if w.transplant && (w.student.is_some() || w.teacher_blob.is_none()) {
            return bad(
                "warm_start.transplant embeds warm_start.teacher_blob as the student: it needs \
                 the teacher_blob and no warm_start.student",
            );
        }
        if !(w.learning_rate > 0.0 && w.teacher_cruise_mps > 0.0 && w.student_noise_std >= 0.0) {
            return bad("warm_start.learning_rate and teacher_cruise_mps must be positive");
        }
        if w.learning_rate_final
            .is_some_and(|l| l.is_nan() || l <= 0.0)
        {
            return bad(
                "warm_start.learning_rate_final (and every refine stage's) must be positive",
            );
        }
        if !(0.0..=1.0).contains(&w.teacher_share_start) {
            return bad("warm_start.teacher_share_start must be in [0, 1]");
        }
    }
    Ok(())
}

fn ppo(c: &TrainConfig) -> Result<(), ConfigError> {
    let p = &c.ppo;
    if p.steps_per_env == 0 || p.epochs == 0 || p.minibatches == 0 {
        return bad("ppo.steps_per_env, epochs and minibatches must be positive");
    }
    if !(c.env.num_envs * p.steps_per_env).is_multiple_of(p.minibatches) {
        return bad(format!(
            "the rollout ({} envs x {} steps) does not split into {} equal minibatches",
            c.env.num_envs, p.steps_per_env, p.minibatches
        ));
    }
    let unit = |v: f32| (0.0..=1.0).contains(&v);
    if !(unit(p.gamma) && unit(p.lambda) && p.clip > 0.0 && p.learning_rate > 0.0) {
        return bad("ppo.gamma and lambda must be in [0, 1], clip and learning_rate > 0");
    }
    if !(p.init_std.is_finite() && p.init_std > 0.0 && p.max_grad_norm > 0.0) {
        return bad("ppo.init_std and max_grad_norm must be positive and finite");
    }
    let finite_nonneg = |v: f32| v.is_finite() && v >= 0.0;
    if !(finite_nonneg(p.value_coef) && finite_nonneg(p.entropy_coef)) {
        return bad("ppo.value_coef and entropy_coef must be finite and >= 0");
    }
    if p.desired_kl.is_some_and(|k| !(k.is_finite() && k > 0.0)) {
        return bad("ppo.desired_kl must be positive");
    }
    if !(p.min_learning_rate > 0.0 && p.min_learning_rate <= p.learning_rate) {
        return bad("ppo.min_learning_rate must be in (0, learning_rate]");
    }
    if !(p.max_learning_rate >= p.learning_rate && p.max_learning_rate.is_finite()) {
        return bad("ppo.max_learning_rate must be finite and at least learning_rate");
    }
    if let Some(s) = p.max_std {
        if !(s > 0.0 && s.is_finite() && s >= p.init_std) {
            return bad("ppo.max_std must be finite, positive and at least init_std");
        }
    }
    if let Some(d) = &p.max_std_decay {
        let Some(max) = p.max_std else {
            return bad("ppo.max_std_decay lowers ppo.max_std, which is not set");
        };
        if !(d.final_std > 0.0 && d.final_std <= max && d.from_iteration < d.to_iteration) {
            return bad(
                "ppo.max_std_decay: final_std must be in (0, max_std] and from_iteration < to_iteration",
            );
        }
    }
    let imitates = c
        .warm_start
        .iter()
        .flat_map(WarmStart::stages)
        .any(|w| w.rounds > 0);
    if c.env.fold_mirror && imitates {
        return bad(
            "env.fold_mirror: a warm start's DAgger rounds label the world's motors, not the folded ones (not supported; \
             warm_start.transplant with rounds = 0 folds)",
        );
    }
    if p.critic_learning_rate
        .is_some_and(|r| !(r.is_finite() && r > 0.0))
    {
        return bad("ppo.critic_learning_rate must be positive");
    }
    if let Some(s) = p.lstm_learning_rate_scale {
        if !(s > 0.0 && s <= 1.0) {
            return bad("ppo.lstm_learning_rate_scale must be in (0, 1]");
        }
        let recurrent = matches!(c.run.row.to_ascii_uppercase(), 'E' | 'F' | 'G');
        if !recurrent || p.update != crate::config::UpdateKind::Fused {
            return bad(
                "ppo.lstm_learning_rate_scale needs a recurrent row (E, F, G) and update = \"fused\"",
            );
        }
    }
    Ok(())
}
