//! Blobs renamed after the runs that name them were made, for the tests that check a
//! blob's provenance (`shipped_policies.rs`) and a run's own config copy (`config.rs`)
//! against the committed configs.

use host_trainer::config::TrainConfig;

/// Blobs renamed after runs that name them were made: (the path now, the path the runs
/// named). On 2026-12-07 the robust stage-1 policy took the name `stage1.blob` and the
/// nominal one became `stage1_nominal.blob`; the configs say where the file is now, and a
/// blob's provenance hashes its config as it was run.
pub const RENAMED: &[(&str, &str)] = &[("policies/stage1_nominal.blob", "policies/stage1.blob")];

/// `config` with the blobs it names by their paths when its runs were made ([`RENAMED`]).
pub fn as_run(config: &TrainConfig) -> TrainConfig {
    let then = |path: &str| {
        RENAMED
            .iter()
            .find(|(now, _)| *now == path)
            .map_or_else(|| path.to_string(), |(_, then)| then.to_string())
    };
    let mut c = config.clone();
    if let Some(race) = c.env.race.as_mut() {
        race.opponent = then(&race.opponent.to_string_lossy()).into();
    }
    for stage in &mut c.opponent_curriculum {
        stage.opponent = then(&stage.opponent.to_string_lossy()).into();
    }
    if let Some(w) = c.warm_start.as_mut() {
        w.teacher_blob = w.teacher_blob.as_deref().map(then);
        w.student = w.student.as_deref().map(then);
    }
    c
}
