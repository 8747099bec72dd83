//! The blobs in `policies/` are what their committed configs produce and fly as recorded:
//! the provenance names the config (hash, seed, iterations, preset), and the referee's
//! time trial from the stage-1 spawn gives the numbers in policies/README.md.

use firmware_core::blob::{AlignedBytes, Blob};
use host_trainer::config::TrainConfig;
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, report};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;
use std::path::Path;

mod renamed;
use renamed::as_run;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap()
}

/// A shipped blob, its config (from the repository root) and the best lap the referee
/// recorded for it (s).
const SHIPPED: &[(&str, &str, f64)] = &[(
    "stage1_imitation",
    "host-trainer/configs/experiments/stage1_imitation.toml",
    10.94,
)];

/// `policies/stage1.blob` (Table 1 row A) is PPO from a random network with the ego
/// randomised (issue "robust"): the committed `configs/stage1.toml` and its seed, the actor its
/// validation (`run.select`) chose from the shipped metrics of the finished run, folded as it
/// was trained. It flies the referee's time trial exactly as `policies/stage1/eval.json`
/// (the nominal stage-1 spawn, one flight repeated) and `eval_jitter.json` (100 jittered
/// starts) record, and the jittered record meets issue "robust"'s item 3 (success >= 0.95,
/// crashes <= 0.05 /s, best lap <= 7.8 s); the nominal flight completes its laps without a
/// crash. Its perturbed flights are `.ci/run`'s robustness step.
#[test]
fn the_stage1_policy_is_the_shipped_config_from_scratch_and_flies_as_recorded() {
    let (raw, config, iterations) = shipped_blob("stage1", "host-trainer/configs/stage1.toml");
    assert!(config.warm_start.is_none(), "no imitation");
    assert!(config.env.randomize.is_some(), "trained randomised");
    assert!(config.run.keep_best && config.run.select.is_some());
    the_runs_choice("stage1", &config, iterations);
    assert_eq!(
        TrainConfig::load(&root().join("policies/stage1/config.toml")).unwrap(),
        config
    );
    assert!(folded(&raw));

    let (eval, r) = flies_as_recorded("stage1", &raw, &root().join("policies/stage1/eval.json"));
    assert!(eval.episodes >= 20 && eval.seconds == 45.0);
    assert!(r.crashes == 0 && r.best_lap_s.is_some(), "{}", r.table());
    let (eval, r) = flies_as_recorded(
        "stage1",
        &raw,
        &root().join("policies/stage1/eval_jitter.json"),
    );
    assert!(eval.episodes >= 100 && !eval.perturbation.is_none());
    let lap = r.best_lap_s.expect("a complete lap");
    assert!(r.success_rate >= 0.95, "success {}", r.success_rate);
    assert!(r.crash_rate <= 0.05, "crashes {} /s", r.crash_rate);
    assert!(lap <= 7.8, "best lap {lap} s");
}

/// `policies/stage1_long.blob` (`stage2_long.blob`'s teacher) is
/// `configs/experiments/stage1_long.toml`, `stage1_nominal.toml`'s recipe with twice the budget: the actor its validation chose from the
/// shipped metrics of the finished run, folded; it flies the referee's time trial as
/// `policies/stage1_long/eval.json` records, and its 100 along-track episodes as
/// `eval_along_track.json` records, faster than `stage1_nominal.blob`'s (the recipe it
/// doubles the budget of).
#[test]
fn the_long_stage1_policy_is_its_config_and_flies_as_recorded() {
    let name = "stage1_long";
    let (raw, config, iterations) =
        shipped_blob(name, "host-trainer/configs/experiments/stage1_long.toml");
    assert!(config.warm_start.is_none() && config.run.select.is_some());
    the_runs_choice(name, &config, iterations);
    assert!(folded(&raw));
    let dir = root().join("policies/stage1_long");
    let (_, r) = flies_as_recorded(name, &raw, &dir.join("eval.json"));
    assert!(r.success_rate >= 0.999 && r.crashes == 0, "{}", r.table());
    let (_, along) = flies_as_recorded(name, &raw, &dir.join("eval_along_track.json"));
    laps_faster_than(&along, "stage1_nominal", "eval_along_track.json");
}

/// `policies/stage1_robust_fast.blob` (`stage2_robust_fast.blob`'s teacher, and the fork the
/// shipped teacher continues) is `configs/experiments/stage1_robust_fast.toml` forked from
/// `experiments/stage1_4500.toml`'s run (`configs/stage1.toml` with 1,500 more iterations) at
/// its last iteration (`forked_from.json` names that run's config by its hash): the actor its
/// validation chose from the shipped metrics, folded. It flies from jittered starts as
/// `eval_jitter.json` records, faster than `stage1.blob` (the opponent) by more than 0.1 s of
/// mean lap, the pace gap row G needs.
#[test]
fn the_robust_teacher_is_a_fork_of_the_stage1_run_and_faster_than_it() {
    let name = "stage1_robust_fast";
    let (raw, config, iterations) = shipped_blob(
        name,
        "host-trainer/configs/experiments/stage1_robust_fast.toml",
    );
    forked_at_the_end_of(name, "host-trainer/configs/experiments/stage1_4500.toml");
    the_runs_choice(name, &config, iterations);
    assert!(folded(&raw));
    let dir = root().join("policies/stage1_robust_fast");
    let (_, fast) = flies_as_recorded(name, &raw, &dir.join("eval_jitter.json"));
    laps_faster_than(&fast, "stage1", "eval_jitter.json");
}

/// `policies/stage1_robust_jitter3.blob` (robust12g), the teacher of `configs/stage2.toml`'s
/// row G (`policies/stage2.blob`): `stage1_robust_fast`'s run forked at its last
/// checkpoint and trained 400 iterations more from starts jittered three times as far as the
/// robustness bar's. The committed config and seed, the validation's actor of the finished
/// run, flying the jittered time trial as recorded.
#[test]
fn the_jittered_teacher_is_a_fork_of_the_robust_teacher_and_flies_as_recorded() {
    let name = "stage1_robust_jitter3";
    let (raw, config, iterations) = shipped_blob(
        name,
        "host-trainer/configs/experiments/stage1_robust_jitter3.toml",
    );
    forked_at_the_end_of(
        name,
        "host-trainer/configs/experiments/stage1_robust_fast.toml",
    );
    the_runs_choice(name, &config, iterations);
    assert!(folded(&raw));
    flies_as_recorded(
        name,
        &raw,
        &root().join("policies/stage1_robust_jitter3/eval_jitter.json"),
    );
}

/// `policies/{name}/forked_from.json` names the last checkpoint of a run of the config at
/// `parent` (from the repository root): its hash and its final iteration.
fn forked_at_the_end_of(name: &str, parent: &str) {
    let parent = TrainConfig::load(&root().join(parent)).unwrap();
    let forked: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root().join(format!("policies/{name}/forked_from.json"))).unwrap(),
    )
    .unwrap();
    assert_eq!(
        forked["config_hash"].as_str(),
        Some(format!("{:016x}", parent.hash()).as_str()),
        "{name}"
    );
    assert_eq!(
        forked["iteration"].as_u64(),
        Some(u64::from(parent.run.iterations)),
        "{name}"
    );
}

/// `policies/stage2.blob`, what `sitl race` flies, against `stage1.blob` on the 20
/// races of seed 0 (its `eval.json`, checked race for race by
/// `shipped_race_blobs_are_their_configs_best_evaluation_and_race_as_recorded`) and the 100
/// of seed 2000 (`eval_seed2000.json`): issue "race"'s per-race bars (success >= 0.9,
/// crashes <= 0.1 /s, best lap <= 8.0 s, at least half the overtakes sustained and >= 16
/// sustained per 20 races, at >= 3 gates). From jittered starts it holds 0.49 of its passes
/// (docs/RESULTS.md), and nothing here claims more; its robustness is `.ci/run`'s step.
#[test]
fn the_race_ego_meets_the_race_bars_on_both_seeds() {
    let raw = std::fs::read(root().join("policies/stage2.blob")).unwrap();
    // The blob races as each report records (gates, crashes, overtakes, win rate, the
    // overtakes by gate), so the bars below are the blob's: `eval.json` is re-raced by
    // `shipped_race_blobs_are_their_configs_best_evaluation_and_race_as_recorded`, the 100
    // races of seed 2000 here.
    races_as_recorded_in(
        "stage2",
        &raw,
        "policies/stage1.blob",
        "policies/stage2/eval_seed2000.json",
    );
    for (file, seed, races) in [("eval.json", 0, 20), ("eval_seed2000.json", 2000, 100)] {
        let r: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(root().join("policies/stage2").join(file)).unwrap(),
        )
        .unwrap();
        assert_eq!(
            (r["episodes"].as_u64(), r["seed"].as_u64()),
            (Some(races), Some(seed))
        );
        assert!(r.get("perturbation").is_none(), "{file}: nominal races");
        assert!(
            r["opponent"]
                .as_str()
                .unwrap()
                .contains("policies/stage1.blob")
        );
        let outcome: sitl::eval::RaceOutcome = serde_json::from_value(r.clone()).unwrap();
        let misses = sitl::eval::RaceBar::RACE.misses(&outcome);
        assert!(misses.is_empty(), "{file}: {misses:?}");
    }
}

/// `policies/stage1_robust.blob` (issue "robust") is stage1.toml's recipe trained with the
/// ego's latency, motor lag, thrust, mass and sensor noise randomised
/// (`configs/experiments/stage1_robust.toml`, `env.randomize`): the committed config and
/// seed, the validation's actor of the finished run; it flies the referee's time trial as
/// `eval.json` records, and the robustness table's rows for one step of latency and for
/// all perturbations at once as `robustness.json` records them, f32 and int8, at >= 0.95
/// success (stage1.blob: 0.43 and 0.63).
#[test]
fn the_robust_stage1_policy_is_its_config_and_survives_latency_as_recorded() {
    let name = "stage1_robust";
    let (raw, config, iterations) =
        shipped_blob(name, "host-trainer/configs/experiments/stage1_robust.toml");
    assert!(config.env.randomize.is_some(), "trained randomised");
    the_runs_choice(name, &config, iterations);
    assert_eq!(
        TrainConfig::load(&root().join("policies/stage1_robust/config.toml")).unwrap(),
        config
    );
    flies_as_recorded(name, &raw, &root().join("policies/stage1_robust/eval.json"));

    let recorded: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("policies/stage1_robust/robustness.json")).unwrap(),
    )
    .unwrap();
    let f32_spec = PilotSpec::from_blob(name, &raw).unwrap();
    let int8_spec = f32_spec.int8("int8").unwrap().expect("an f32 blob");
    let levels = sitl::robustness::table_levels();
    for row in ["+ latency 1 step (20 ms)", "+ all of the above"] {
        let level = levels.iter().find(|l| l.name == row).unwrap();
        let want = recorded["table"]
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["level"]["name"] == row)
            .unwrap();
        let eval = EvalConfig {
            preset: Preset::paper(),
            episodes: recorded["episodes"].as_u64().unwrap() as u32,
            seconds: 45.0,
            seed: recorded["seed"].as_u64().unwrap(),
            spawn: None,
            perturbation: level.perturbation,
        };
        for (spec, dtype) in [(&f32_spec, "f32"), (&int8_spec, "int8")] {
            let r = report(spec, None, &eval);
            assert_eq!(
                r.gates_passed,
                want[dtype]["gates_passed"].as_u64().unwrap(),
                "{row} {dtype}"
            );
            assert_eq!(r.crashes, want[dtype]["crashes"].as_u64().unwrap());
            assert!(r.success_rate >= 0.95, "{row} {dtype}: {}", r.success_rate);
        }
    }
}

#[test]
fn shipped_blobs_are_their_configs_and_fly_as_recorded() {
    for &(blob, config, lap) in SHIPPED {
        check(blob, config, lap);
    }
}

/// The shipped `metrics.jsonl` of `policies/{name}` is a finished run, and the blob's
/// provenance iteration is the actor the run's evaluations chose there (`best_evaluation`:
/// the validation's best with `run.select`, else the referee's); returns the metrics.
fn the_runs_choice(
    name: &str,
    config: &TrainConfig,
    iterations: u32,
) -> Vec<host_trainer::metrics::IterationMetrics> {
    let metrics: Vec<host_trainer::metrics::IterationMetrics> = shipped_jsonl(name, "metrics");
    assert_eq!(
        metrics.last().map(|m| m.iteration),
        Some(config.run.iterations),
        "{name}: the run finished"
    );
    let chosen = host_trainer::evaluation::best_evaluation(&metrics, &config.run).unwrap();
    assert_eq!(
        iterations, chosen.iteration,
        "{name}: not the actor the run's evaluations chose"
    );
    metrics
}

/// `faster` (a blob's replayed report) laps more than 0.1 s faster on the mean than
/// `policies/{other}.blob` flies the same episodes, replayed from `policies/{other}/{record}`.
fn laps_faster_than(faster: &sitl::eval::Report, other: &str, record: &str) {
    let (_, slower) = flies_as_recorded(
        other,
        &std::fs::read(root().join(format!("policies/{other}.blob"))).unwrap(),
        &root().join(format!("policies/{other}/{record}")),
    );
    assert_eq!(
        (faster.episodes, faster.seed),
        (slower.episodes, slower.seed)
    );
    assert!(
        faster.mean_lap_s.unwrap() < slower.mean_lap_s.unwrap() - 0.1,
        "{} against {}",
        faster.table(),
        slower.table()
    );
}

/// Whether the blob `raw` observes folded (observation pipeline version 2).
fn folded(raw: &[u8]) -> bool {
    let bytes = AlignedBytes::new(raw);
    Blob::parse(bytes.as_bytes())
        .unwrap()
        .header()
        .observation
        .is_folded()
}

/// The blob `policies/{name}.blob` and the config at `config` (from the repository root),
/// with the provenance checked against the config (hash, seed, name, preset); returns the
/// bytes, the config and the provenance's iteration count.
fn shipped_blob(name: &str, config: &str) -> (Vec<u8>, TrainConfig, u32) {
    let raw = std::fs::read(root().join(format!("policies/{name}.blob"))).unwrap();
    let config = TrainConfig::load(&root().join(config)).unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    let p = &blob.header().provenance;
    assert_eq!(
        p.config_hash,
        as_run(&config).hash(),
        "{name} was made with another config"
    );
    assert_eq!(p.seed, config.run.seed);
    assert_eq!(p.preset.as_str(), config.env.preset.name());
    assert_eq!(p.name.as_str(), config.run.name);
    assert_eq!(
        blob.header().observation.velocity_scale_mps,
        config.env.velocity_scale_mps
    );
    let iterations = p.iterations;
    (raw, config, iterations)
}

/// The blob `raw` races `opponent` (a path from the repository root) exactly as the
/// referee's report `policies/{dir}/eval.json` records.
fn races_as_recorded(name: &str, raw: &[u8], opponent: &str, dir: &str) {
    races_as_recorded_in(name, raw, opponent, &format!("policies/{dir}/eval.json"));
}

/// The blob `raw` races `opponent` exactly as the nominal race report at `report` (a path
/// from the repository root) records: gates, crashes, overtakes, and where the report has
/// them, the win rate and the overtakes by gate.
fn races_as_recorded_in(name: &str, raw: &[u8], opponent: &str, report_path: &str) {
    let recorded: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root().join(report_path)).unwrap()).unwrap();
    assert!(
        recorded.get("perturbation").is_none(),
        "{report_path}: nominal races"
    );
    let ego = PilotSpec::from_blob(name, raw).unwrap();
    let opponent_raw = std::fs::read(root().join(opponent)).unwrap();
    let opponent = PilotSpec::from_blob("opponent", &opponent_raw).unwrap();
    let eval = EvalConfig {
        preset: Preset::paper(),
        episodes: recorded["episodes"].as_u64().unwrap() as u32,
        seconds: recorded["episode_seconds"].as_f64().unwrap() as f32,
        seed: recorded["seed"].as_u64().unwrap(),
        spawn: None,
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let r = report(&ego, Some(&opponent), &eval);
    println!("{name}: {}", r.table());
    assert_eq!(r.gates_passed, recorded["gates_passed"].as_u64().unwrap());
    assert_eq!(r.crashes, recorded["crashes"].as_u64().unwrap());
    assert_eq!(r.overtakes, recorded["overtakes"].as_u64().unwrap());
    assert_eq!(
        r.sustained_overtakes,
        recorded["sustained_overtakes"].as_u64().unwrap()
    );
    if let Some(w) = recorded.get("win_rate").and_then(|w| w.as_f64()) {
        assert!((r.win_rate.unwrap() - w).abs() < 1e-12, "{name}: win rate");
    }
    if let Some(by_gate) = recorded.get("overtakes_by_gate") {
        let replayed: Vec<[u64; 3]> = r
            .overtakes_by_gate
            .iter()
            .map(|g| [g.gate as u64, g.overtakes, g.sustained])
            .collect();
        let recorded: Vec<[u64; 3]> = by_gate
            .as_array()
            .unwrap()
            .iter()
            .map(|g| ["gate", "overtakes", "sustained"].map(|k| g[k].as_u64().unwrap()))
            .collect();
        assert_eq!(replayed, recorded, "{name}: overtakes by gate");
    }
}

fn check(name: &str, config: &str, recorded_lap_s: f64) {
    let (raw, config, iterations) = shipped_blob(name, config);
    assert_eq!(iterations, config.run.iterations);

    let spec = PilotSpec::from_blob(name, &raw).unwrap();
    let eval = EvalConfig {
        preset: Preset::paper(),
        episodes: 1,
        seconds: 45.0,
        seed: 0,
        spawn: Some(SpawnMode::Stage1),
        perturbation: sitl::perturb::Perturbation::NONE,
    };
    let r = report(&spec, None, &eval);
    println!("{}", r.table());
    assert_eq!(r.crashes, 0);
    assert!(r.success_rate >= 0.999, "{}", r.success_rate);
    let lap = r.best_lap_s.expect("a complete lap");
    assert!(
        (lap - recorded_lap_s).abs() < 0.03,
        "{name}: best lap {lap} s, recorded {recorded_lap_s} s"
    );
}

/// The stage-2 blobs: `policies/stage2.blob` (row G by PPO, what `sitl race` flies),
/// `stage2_G.blob` (row G by imitation) and the ablations that are shipped, each with the
/// config that made it (blob name, config name).
const SHIPPED_RACES: &[(&str, &str)] = &[
    ("stage2", "stage2"),
    ("stage2_G", "stage2_G"),
    ("stage2_B", "stage2_B"),
    ("stage2_C", "stage2_C"),
    ("stage2_D", "stage2_D"),
    ("stage2_E", "stage2_E"),
    ("stage2_F", "stage2_F"),
    ("stage2_transplant", "stage2_transplant"),
    ("stage2_long", "stage2_long"),
    ("stage2_robust_fast", "stage2_robust_fast"),
];

/// Every shipped stage-2 blob is its config's run (hash, seed, name, preset), its actor is
/// the evaluation `run.keep_best` chose from the shipped metrics (the provenance's iteration
/// is the one the referee scored best there), and it races the shipped opponent exactly as
/// its `eval.json` records; where the warm start kept its best round, the run's first
/// evaluation is that round's score. `policies/stage2.blob` and `stage2_G.blob` must exist;
/// an ablation not yet trained is skipped.
#[test]
fn shipped_race_blobs_are_their_configs_best_evaluation_and_race_as_recorded() {
    assert!(root().join("policies/stage2.blob").is_file());
    assert!(root().join("policies/stage2_G.blob").is_file());
    for &(name, config_name) in SHIPPED_RACES {
        let path = root().join(format!("policies/{name}.blob"));
        if path.is_file() {
            check_race(name, config_name);
        }
    }
}

/// The lines of `policies/{name}/{file}.jsonl`, the log its run wrote (`metrics`,
/// `imitation`).
fn shipped_jsonl<T: serde::de::DeserializeOwned>(name: &str, file: &str) -> Vec<T> {
    std::fs::read_to_string(root().join(format!("policies/{name}/{file}.jsonl")))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn check_race(name: &str, config_name: &str) {
    // The shipped pipeline's config, else the experiment's, else the policy's own.
    let path = ["host-trainer/configs", "host-trainer/configs/experiments"]
        .map(|d| format!("{d}/{config_name}.toml"))
        .into_iter()
        .chain([format!("policies/{config_name}/config.toml")])
        .find(|p| root().join(p).is_file())
        .unwrap_or_else(|| panic!("{config_name}: no config"));
    let (raw, config, iterations) = shipped_blob(name, &path);
    assert!(
        config.run.keep_best,
        "{config_name}: the stage-2 runs keep the best"
    );
    let metrics = the_runs_choice(name, &config, iterations);
    if config
        .warm_start
        .as_ref()
        .is_some_and(|w| w.keep_best_round)
    {
        // The warm start ended with its best-refereed round: the first evaluation (the
        // critic-only iterations leave the actor as the warm start made it) scores as that
        // round did, on the same races.
        let rounds: Vec<host_trainer::imitation::ImitationRound> = shipped_jsonl(name, "imitation");
        let score = |s: Option<f64>, c: Option<f64>| (s.expect("refereed"), -c.expect("refereed"));
        let kept = rounds
            .iter()
            .map(|r| score(r.referee_success_rate, r.referee_crash_rate))
            .fold((f64::NEG_INFINITY, f64::NEG_INFINITY), |a, b| {
                if b > a { b } else { a }
            });
        let first = metrics
            .iter()
            .find(|m| m.eval_success_rate.is_some())
            .unwrap();
        assert_eq!(
            score(first.eval_success_rate, first.eval_crash_rate),
            kept,
            "{name}: the warm start did not end with its best round"
        );
    }
    let opponent = &config.env.race.as_ref().unwrap().opponent;
    races_as_recorded(name, &raw, &opponent.to_string_lossy(), name);
}

/// `policies/stage2_G_student.blob` is the first warm-start stage of row G, made by the
/// config in its directory (provenance: that config's hash, seed and name, 0 PPO
/// iterations), and races the shipped opponent exactly as its `eval.json` records.
/// `configs/stage2_G.toml` refines it into `policies/stage2_G.blob`.
#[test]
fn the_stage2_student_is_its_configs_warm_start_and_races_as_recorded() {
    let (raw, _, iterations) =
        shipped_blob("stage2_G_student", "policies/stage2_G_student/config.toml");
    assert_eq!(iterations, 0, "the warm start, before any PPO iteration");
    let g = TrainConfig::load(&root().join("host-trainer/configs/stage2_G.toml")).unwrap();
    assert_eq!(
        g.warm_start.and_then(|w| w.student).as_deref(),
        Some("policies/stage2_G_student.blob")
    );
    races_as_recorded(
        "stage2_G_student",
        &raw,
        "policies/stage1_guarded.blob",
        "stage2_G_student",
    );
}

/// `policies/stage2_G_distil.blob` is `stage1_nominal.blob` (`stage1.blob` then) distilled
/// into row G's network, racing it (issue [race]: the warm-start row): the warm start of the config in its
/// directory (provenance: that config's hash, seed and name, 0 PPO iterations), labelled
/// with the teacher's clamped commands, and it races its teacher exactly as its
/// `eval.json` records.
#[test]
fn the_race_distillation_is_its_configs_warm_start_and_races_as_recorded() {
    let (raw, config, iterations) =
        shipped_blob("stage2_G_distil", "policies/stage2_G_distil/config.toml");
    assert_eq!(iterations, 0, "the warm start, before any PPO iteration");
    let warm = config.warm_start.expect("a warm start");
    // Its run's own config, by the path the teacher had then (`renamed::RENAMED`).
    assert_eq!(warm.teacher_blob.as_deref(), Some("policies/stage1.blob"));
    assert!(warm.clamp_labels);
    races_as_recorded(
        "stage2_G_distil",
        &raw,
        "policies/stage1_nominal.blob",
        "stage2_G_distil",
    );
}

/// `docs/runs/rslrl_stage1/policy.blob`, RSL-RL's actor on the shipped recipe (issue
/// "learn", items 1 and 5; not a shipped policy): imported folded, as it was trained, and it
/// flies the referee's time trial exactly as its `eval.json` records, the numbers
/// docs/TRAINING.md compares with ours.
#[test]
fn the_rsl_rl_reference_flies_as_recorded() {
    let dir = root().join("docs/runs/rslrl_stage1");
    let raw = std::fs::read(dir.join("policy.blob")).unwrap();
    assert!(folded(&raw));
    flies_as_recorded("rsl-rl", &raw, &dir.join("eval.json"));
}

/// `v` with every number rounded to f32, the precision the reports' values have (a report
/// writes an f32 by its shortest decimal, `serde_json::to_value` by the f64 it widens to).
fn in_f32(v: &serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match v {
        Value::Number(n) => n
            .as_f64()
            .map_or_else(|| v.clone(), |x| Value::from(f64::from(x as f32))),
        Value::Array(a) => Value::Array(a.iter().map(in_f32).collect()),
        Value::Object(o) => Value::Object(o.iter().map(|(k, x)| (k.clone(), in_f32(x))).collect()),
        _ => v.clone(),
    }
}

/// The blob `raw` flies the referee's time trial (paper preset, the recorded spawn) exactly as
/// the report at `eval_json` records: the same gates, crashes and best lap. Returns the
/// evaluation replayed and its report.
fn flies_as_recorded(name: &str, raw: &[u8], eval_json: &Path) -> (EvalConfig, sitl::eval::Report) {
    let recorded: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(eval_json).unwrap()).unwrap();
    let spawn = recorded["spawn"].as_str().and_then(SpawnMode::by_name);
    assert!(
        spawn.is_some(),
        "{}: a time trial's spawn",
        eval_json.display()
    );
    assert!(recorded["opponent"].is_null());
    // Nominal, or the referee's standard jitter (`--jitter`) and nothing else.
    let perturbation = match recorded.get("perturbation") {
        None => sitl::perturb::Perturbation::NONE,
        Some(p) => {
            let jittered = sitl::perturb::Perturbation::JITTERED;
            let want = serde_json::to_value(jittered).unwrap();
            assert_eq!(in_f32(p), in_f32(&want), "jitter only");
            jittered
        }
    };
    assert_eq!(recorded["preset"].as_str(), Some("paper"));
    let eval = EvalConfig {
        preset: Preset::paper(),
        episodes: recorded["episodes"].as_u64().unwrap() as u32,
        seconds: recorded["episode_seconds"].as_f64().unwrap() as f32,
        seed: recorded["seed"].as_u64().unwrap(),
        spawn,
        perturbation,
    };
    let r = report(&PilotSpec::from_blob(name, raw).unwrap(), None, &eval);
    println!("{name}: {}", r.table());
    assert_eq!(r.gates_passed, recorded["gates_passed"].as_u64().unwrap());
    assert_eq!(r.crashes, recorded["crashes"].as_u64().unwrap());
    let lap = r.best_lap_s.expect("a complete lap");
    assert!((lap - recorded["best_lap_s"].as_f64().unwrap()).abs() < 1e-4);
    (eval, r)
}
