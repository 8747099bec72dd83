//! Stage 2 through the trainer: a race config trains, evaluates against its opponent and
//! exports a blob that firmware-core flies on the 30-value observation; a config that mixes
//! up rows, spawns and rewards, or names a missing opponent, is refused with a reason.

use burn::tensor::Device;
use firmware_core::Controller;
use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::observation::ObservationLayout;
use firmware_core::track::Track;
use host_trainer::config::TrainConfig;
use host_trainer::metrics::IterationMetrics;
use host_trainer::nets::PolicyNet;
use host_trainer::train::{RunOptions, run};
use std::path::PathBuf;

const CONFIG: &str = include_str!("../configs/smoke_race.toml");

fn config() -> TrainConfig {
    let mut c = TrainConfig::parse(CONFIG).unwrap();
    let race = c.env.race.as_mut().unwrap();
    // The config names the opponent from the repository root; the tests run in the crate.
    race.opponent = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(&race.opponent);
    c
}

mod common;
use common::read_jsonl;

fn tmp(name: &str) -> PathBuf {
    common::tmp_dir("race", name)
}

fn options(out: PathBuf) -> RunOptions {
    common::run_options(&out)
}

#[test]
fn a_race_config_trains_and_exports_a_30_value_policy() {
    let out = tmp("train");
    let summary = run(&config(), &options(out.clone())).unwrap();
    let blob_path = summary.blob.expect("the run finished");
    let raw = std::fs::read(&blob_path).unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    assert_eq!(
        blob.header().observation.layout,
        ObservationLayout::FullOpponent30
    );
    assert_eq!(blob.header().observation.velocity_scale_mps, 12.0);
    Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).unwrap();

    let metrics: Vec<IterationMetrics> = read_jsonl(&out.join("metrics.jsonl"));
    assert_eq!(metrics.len(), 2);
    for m in &metrics {
        let c = m
            .reward_competition
            .expect("a race logs its competition term");
        assert!(c.is_finite() && c.abs() <= 0.5 * 0.02 + 1e-9, "{c}");
        assert!(m.opponent_crash_rate_per_s.is_some());
    }
    let last = metrics.last().unwrap();
    // The in-training referee flew races: overtakes are counted (none expected here).
    assert!(last.eval_overtakes.is_some() && last.eval_sustained_overtakes.is_some());
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn inconsistent_race_configs_are_refused_with_a_reason() {
    let edit = |from: &str, to: &str| CONFIG.replace(from, to);
    let cases = [
        (edit("row = \"C\"", "row = \"A\""), "time-trial row"),
        (
            edit("spawn = \"stage2\"", "spawn = \"along-track\""),
            "stage-2 spawn",
        ),
        (
            edit("competition = \"dense\"", "competition = \"sparse\""),
            "row D",
        ),
        (
            edit("row = \"C\"", "row = \"D\""),
            "row D is the sparse one",
        ),
        (
            CONFIG[..CONFIG.find("[race]").unwrap()]
                .replace("spawn = \"stage2\"", "spawn = \"along-track\""),
            "needs a [race] section",
        ),
        (
            CONFIG[..CONFIG.find("[race]").unwrap()].to_string(),
            "needs a [race] section",
        ),
        (
            CONFIG.replace("competition_weight = 0.5", "competition_weight = -0.5"),
            "race.competition_weight",
        ),
    ];
    for (text, why) in cases {
        let e = TrainConfig::parse(&text).unwrap_err().to_string();
        assert!(e.contains(why), "expected '{why}' in: {e}");
    }
}

#[test]
fn a_missing_opponent_is_an_error_before_any_work() {
    let mut c = config();
    c.env.race.as_mut().unwrap().opponent = "/nonexistent/opponent.blob".into();
    let out = tmp("missing");
    let e = run(&c, &options(out.clone())).unwrap_err().to_string();
    assert!(e.contains("/nonexistent/opponent.blob"), "{e}");
    assert!(!out.join("checkpoints").exists());
}

/// Recurrent PPO end to end on row G: two iterations train, the exported blob is a row-G
/// policy that firmware-core's controller loads, and a run stopped after its first
/// iteration learned exactly what the uninterrupted run did up to there and resumes to the
/// end. (A resumed run restarts its environments and recurrent states, as the feed-forward
/// trainer restarts its environments, so the later iterations differ.)
#[test]
fn a_row_g_race_trains_exports_and_resumes() {
    let mut c = config();
    c.run.row = 'G';
    c.run.name = "smoke-race-g".into();
    let whole = tmp("g-whole");
    let summary = run(&c, &options(whole.clone())).unwrap();
    let raw = std::fs::read(summary.blob.expect("finished")).unwrap();
    let bytes = AlignedBytes::new(&raw);
    let blob = Blob::parse(bytes.as_bytes()).unwrap();
    assert_eq!(
        blob.header().architecture,
        firmware_core::policy::Architecture::table1(firmware_core::policy::TableRow::G)
    );
    Controller::from_bytes(bytes.as_bytes(), Track::figure_eight()).unwrap();

    // Stopped after the first iteration (its checkpoint), then resumed.
    let split = tmp("g-split");
    let mut first = options(split.clone());
    first.stop_after = Some(1);
    assert!(run(&c, &first).unwrap().blob.is_none());
    let read = |dir: &PathBuf| -> Vec<IterationMetrics> { read_jsonl(&dir.join("metrics.jsonl")) };
    let learned = |m: &IterationMetrics| {
        (
            m.reward_per_step,
            m.update.surrogate_loss,
            m.update.value_loss,
            m.update.kl,
            m.update.learning_rate,
        )
    };
    assert_eq!(learned(&read(&split)[0]), learned(&read(&whole)[0]));
    let mut second = options(split.clone());
    second.resume = true;
    let resumed = run(&c, &second).unwrap();
    assert!(resumed.blob.is_some());
    assert_eq!(read(&split).len(), 2);
    let _ = std::fs::remove_dir_all(&whole);
    let _ = std::fs::remove_dir_all(&split);
}

/// `run.keep_best`: the exported blob is the actor of the evaluation the referee scored best
/// (success rate, then crash rate, then the earlier iteration), not the last one, also when
/// the run was stopped and resumed in between (a resume starts fresh episodes, so its later
/// evaluations differ from an uninterrupted run's; the best is taken over its own metrics).
#[test]
fn keep_best_exports_the_referees_best_evaluation_across_a_resume() {
    let mut c = config();
    c.run.name = "smoke-race-best".into();
    c.run.iterations = 3;
    c.run.eval_every = 1;
    c.run.keep_best = true;
    c.run.eval_races = 2;
    c.run.eval_seed = 3;
    // Large fixed steps, so the evaluations differ from one iteration to the next.
    c.ppo.learning_rate = 3e-3;
    c.ppo.desired_kl = None;
    let whole = tmp("best-whole");
    let uninterrupted = run(&c, &options(whole.clone())).unwrap();
    let split = tmp("best-split");
    let mut first = options(split.clone());
    first.stop_after = Some(2);
    assert!(run(&c, &first).unwrap().blob.is_none());
    let mut second = options(split.clone());
    second.resume = true;
    let resumed = run(&c, &second).unwrap();

    let mut chosen = Vec::new();
    for (dir, summary) in [(&whole, uninterrupted), (&split, resumed)] {
        let metrics: Vec<IterationMetrics> = read_jsonl(&dir.join("metrics.jsonl"));
        assert_eq!(metrics.len(), 3);
        let score =
            |m: &IterationMetrics| (m.eval_success_rate.unwrap(), -m.eval_crash_rate.unwrap());
        let mut best = &metrics[0];
        for m in &metrics[1..] {
            if score(m) > score(best) {
                best = m;
            }
        }
        assert_eq!(
            summary.best.as_ref().map(|m| m.iteration),
            Some(best.iteration)
        );
        let exported = std::fs::read(summary.blob.unwrap()).unwrap();
        let bytes = AlignedBytes::new(&exported);
        let blob = Blob::parse(bytes.as_bytes()).unwrap();
        assert_eq!(blob.header().provenance.iterations, best.iteration);
        let candidate = dir
            .join("checkpoints")
            .join(format!("best_iter_{:06}.blob", best.iteration));
        assert!(exported == std::fs::read(candidate).unwrap());
        chosen.push((best.iteration, score(best)));
    }
    // The case this test is for: an earlier actor than the last is exported, and the
    // resumed run's is one it evaluated before it was stopped (both runs share iterations 1
    // and 2; the checkpoint it resumes from is iteration 2).
    assert!(
        chosen.iter().all(|(iteration, _)| *iteration < 3),
        "the last iteration scored best ({chosen:?}): pick other eval seeds for this test"
    );
    let _ = std::fs::remove_dir_all(&whole);
    let _ = std::fs::remove_dir_all(&split);
}

/// A small DAgger warm start on the shipped stage-1 policy: 4 rounds of 60 steps, the
/// teacher's share falling from 1.
fn teacher_warm_start() -> host_trainer::config::WarmStart {
    host_trainer::config::WarmStart {
        teacher_cruise_mps: 9.0,
        teacher_blob: Some(format!(
            "{}/../policies/stage1_guarded.blob",
            env!("CARGO_MANIFEST_DIR")
        )),
        student: None,
        transplant: false,
        rounds: 4,
        steps_per_env: 60,
        epochs: 3,
        minibatch: 160,
        max_samples: 100_000,
        learning_rate: 1e-3,
        learning_rate_final: None,
        teacher_share_start: 1.0,
        student_noise_std: 0.1,
        critic_iterations: 0,
        keep_best_round: false,
        clamp_labels: false,
        refine: Vec::new(),
    }
}

/// The recurrent warm start fits the stage-1 teacher: in every one of four small DAgger
/// rounds in the race, the LSTM student's error against the teacher's labels falls from the
/// round's first epoch to its last (each round's data is harder than the last's as the
/// student takes over the flying, so rounds are not compared with each other); and a
/// missing teacher is an error.
#[test]
fn a_recurrent_student_learns_from_the_stage1_teacher() {
    use host_trainer::imitation::imitate_recurrent;
    use host_trainer::recurrent::RecurrentActor;
    let mut c = config();
    c.run.row = 'G';
    c.env.num_envs = 16;
    c.ppo.steps_per_env = 20;
    let warm = teacher_warm_start();
    let arch = firmware_core::policy::Architecture::table1(firmware_core::policy::TableRow::G);
    let device = Device::flex().autodiff();
    let actor = RecurrentActor::fresh(&arch, 0.2, &mut host_trainer::rng::init_rng(2), &device);
    let (_, rounds) = imitate_recurrent(actor, &arch, &c, &warm, &device, &mut |_, _| {}).unwrap();
    assert_eq!(rounds.len(), 4);
    for r in &rounds {
        assert!(
            r.mse < r.mse_first_epoch,
            "round {}: mse {} -> {}",
            r.round,
            r.mse_first_epoch,
            r.mse
        );
    }

    let mut bad = warm.clone();
    bad.teacher_blob = Some("/nonexistent.blob".into());
    let actor = RecurrentActor::fresh(&arch, 0.2, &mut host_trainer::rng::init_rng(2), &device);
    let e = imitate_recurrent(actor, &arch, &c, &bad, &device, &mut |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("/nonexistent.blob"), "{e}");
}

/// `warm_start.keep_best_round`: every round's student is refereed (the scores in
/// `imitation.jsonl`, the blobs kept), and the warm start ends with the best-scored one
/// (success rate, then crash rate, then the earlier round), not the last.
#[test]
fn keep_best_round_ends_the_warm_start_with_the_referees_best_round() {
    use host_trainer::config::WarmStart;
    use host_trainer::imitation::ImitationRound;
    let mut c = config();
    c.run.name = "smoke-race-rounds".into();
    c.run.eval_races = 2;
    c.run.eval_seed = 3;
    c.warm_start = Some(WarmStart {
        rounds: 5,
        steps_per_env: 40,
        epochs: 2,
        minibatch: 320,
        learning_rate: 3e-3,
        critic_iterations: 1,
        keep_best_round: true,
        ..teacher_warm_start()
    });
    let dir = tmp("best-round");
    let mut opts = options(dir.clone());
    opts.stop_after = Some(1);
    run(&c, &opts).unwrap();
    let rounds: Vec<ImitationRound> = read_jsonl(&dir.join("imitation.jsonl"));
    assert_eq!(rounds.len(), 5);
    let score = |r: &ImitationRound| {
        (
            r.referee_success_rate.expect("refereed"),
            -r.referee_crash_rate.expect("refereed"),
        )
    };
    let mut best = &rounds[0];
    for r in &rounds[1..] {
        if score(r) > score(best) {
            best = r;
        }
    }
    let blob = |round: u32| {
        std::fs::read(
            dir.join("checkpoints")
                .join(format!("warm_start_round_{round:03}.blob")),
        )
        .unwrap()
    };
    for r in &rounds {
        assert!(!blob(r.round).is_empty());
    }
    assert!(std::fs::read(dir.join("warm_start.blob")).unwrap() == blob(best.round));
    assert!(
        best.round < 5,
        "the last round scored best ({rounds:?}): pick other eval seeds for this test"
    );

    // Refereeing the rounds only reads the student: without the option the same rounds are
    // trained, statistic for statistic, and the warm start ends with round 5's weights.
    let mut plain = c.clone();
    if let Some(w) = plain.warm_start.as_mut() {
        w.keep_best_round = false;
    }
    let plain_dir = tmp("best-round-off");
    let mut opts = options(plain_dir.clone());
    opts.stop_after = Some(1);
    run(&plain, &opts).unwrap();
    let plain_rounds: Vec<ImitationRound> = read_jsonl(&plain_dir.join("imitation.jsonl"));
    let unrefereed = |r: &ImitationRound| ImitationRound {
        referee_success_rate: None,
        referee_crash_rate: None,
        ..r.clone()
    };
    assert_eq!(
        rounds.iter().map(unrefereed).collect::<Vec<_>>(),
        plain_rounds
    );
    let payload = |raw: &[u8]| {
        let bytes = AlignedBytes::new(raw);
        Blob::parse(bytes.as_bytes())
            .unwrap()
            .payload_words()
            .to_vec()
    };
    assert_eq!(
        payload(&blob(5)),
        payload(&std::fs::read(plain_dir.join("warm_start.blob")).unwrap())
    );
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&plain_dir);
}

/// A warm start of 0 rounds from a student starts PPO from exactly the student (its blob
/// is `warm_start.blob`, byte for byte the student's weights); 0 rounds without a student
/// is refused.
#[test]
fn a_zero_round_warm_start_keeps_the_student() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let student = root.join("policies/stage2_C.blob");
    let mut c = config();
    c.run.row = 'C';
    c.env.num_envs = 16;
    c.ppo.steps_per_env = 20;
    let mut warm = teacher_warm_start();
    warm.student = Some(student.display().to_string());
    warm.rounds = 0;
    warm.critic_iterations = 1;
    c.warm_start = Some(warm.clone());
    let text = toml::to_string(&c).unwrap();
    assert!(TrainConfig::parse(&text).is_ok(), "{text}");
    let out = tmp("zero_rounds");
    let _ = std::fs::remove_dir_all(&out);
    run(
        &c,
        &RunOptions {
            stop_after: Some(0),
            ..options(out.clone())
        },
    )
    .unwrap();
    let weights = |raw: &[u8]| {
        let bytes = AlignedBytes::new(raw);
        let blob = Blob::parse(bytes.as_bytes()).unwrap();
        blob.weights().unwrap().to_vec()
    };
    let kept = std::fs::read(out.join("warm_start.blob")).unwrap();
    let given = std::fs::read(&student).unwrap();
    assert_eq!(weights(&kept), weights(&given));
    let _ = std::fs::remove_dir_all(&out);

    warm.student = None;
    c.warm_start = Some(warm);
    let e = TrainConfig::parse(&toml::to_string(&c).unwrap()).unwrap_err();
    assert!(
        e.to_string().contains("rounds may be 0 with a student"),
        "{e}"
    );
}
