//! The run configuration: every shipped TOML parses, the presets in code equal their TOML
//! files, schedules and refine stages, and bad values are refused with the field's name.

use host_trainer::config::{ConfigError, TrainConfig};
use sitl::env::RewardWeights;
use std::path::Path;

mod renamed;

const STAGE1: &str = include_str!("../configs/stage1.toml");
/// The stage-1 recipe before the ego was randomised (`configs/stage1.toml` until 2026-12-07):
/// [`TrainConfig::ours`] and sitl's named stage-1 environment.
const STAGE1_NOMINAL: &str = include_str!("../configs/experiments/stage1_nominal.toml");
const FINETUNE: &str = include_str!("../configs/experiments/stage1_finetune.toml");
const PAPER: &str = include_str!("../configs/stage1_paper.toml");

#[test]
fn every_config_in_configs_parses() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let mut n = 0;
    for dir in [dir.clone(), dir.join("experiments")] {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                TrainConfig::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                n += 1;
            }
        }
    }
    assert!(n >= 19, "{n} configs");
}

#[test]
fn shipped_configs_parse() {
    let ours = TrainConfig::parse(STAGE1).unwrap();
    let paper = TrainConfig::parse(PAPER).unwrap();
    // The paper's settings stay reachable.
    assert_eq!(paper.env.num_envs, 8192);
    assert_eq!(paper.env.spawn, sitl::referee::SpawnMode::Stage1);
    assert_eq!(paper.ppo.steps_per_env, 100);
    assert_eq!((paper.ppo.epochs, paper.ppo.minibatches), (5, 4));
    assert_eq!(paper.ppo.learning_rate, 1e-4);
    assert_eq!(paper.ppo.entropy_coef, 0.01);
    assert_eq!(paper.env.reward, RewardWeights::default());
    assert_ne!(ours.hash(), paper.hash());
    assert_eq!(ours.hash(), TrainConfig::parse(STAGE1).unwrap().hash());
    // Ours learns from a random network too; the imitation pipeline stays reachable.
    assert!(ours.warm_start.is_none());
    assert!(TrainConfig::parse(FINETUNE).unwrap().warm_start.is_some());
}

#[test]
fn warm_start_schedules() {
    let text = include_str!("../configs/stage2_G.toml");
    let mut warm = TrainConfig::parse(text).unwrap().warm_start.unwrap();
    warm.rounds = 11;
    warm.learning_rate = 1e-3;
    warm.learning_rate_final = None;
    warm.teacher_share_start = 1.0;
    // The default: the teacher's share falls 1 -> 0 over the first half, the rate is flat.
    let shares: Vec<f64> = (0..11).map(|r| warm.teacher_share(r)).collect();
    assert_eq!(&shares[..3], &[1.0, 0.8, 0.6]);
    assert!(shares[5..].iter().all(|s| *s == 0.0), "{shares:?}");
    assert!((0..11).all(|r| warm.round_learning_rate(r) == 1e-3));
    // A refinement: no teacher, the rate geometric from 1e-3 to 1e-5 (1e-4 half-way).
    warm.teacher_share_start = 0.0;
    warm.learning_rate_final = Some(1e-5);
    assert!((0..11).all(|r| warm.teacher_share(r) == 0.0));
    let rate = |r| warm.round_learning_rate(r);
    assert!((rate(0) - 1e-3).abs() < 1e-12);
    assert!((rate(5) - 1e-4).abs() < 1e-12);
    assert!((rate(10) - 1e-5).abs() < 1e-12);
    assert!(
        (rate(99) - 1e-5).abs() < 1e-12,
        "past the last round it stays at the final rate"
    );
}

#[test]
fn refine_stages_inherit_the_teacher_and_start_with_the_student_flying() {
    let c = TrainConfig::parse(include_str!("../configs/experiments/stage2_B.toml")).unwrap();
    let warm = c.warm_start.unwrap();
    let stages = warm.stages();
    assert_eq!(stages.len(), 3);
    assert_eq!(
        stages.iter().map(|s| s.rounds).collect::<Vec<_>>(),
        [30, 12, 8]
    );
    assert_eq!(stages[0].teacher_share(0), 1.0);
    for s in &stages[1..] {
        assert_eq!(s.teacher_share(0), 0.0);
        assert_eq!(s.teacher_blob, warm.teacher_blob);
        assert_eq!(s.minibatch, warm.minibatch);
        assert_eq!(s.student_noise_std, warm.student_noise_std);
        assert!(s.refine.is_empty() && s.student.is_none());
    }
    assert_eq!(stages[2].steps_per_env, 750);
    assert!((stages[2].round_learning_rate(7) - 3e-5).abs() < 1e-12);
    // A bad refine stage is refused like a bad warm start.
    let text = include_str!("../configs/experiments/stage2_B.toml").replacen(
        "rounds = 8\nsteps_per_env = 750",
        "rounds = 8\nsteps_per_env = 0",
        1,
    );
    assert!(matches!(
        TrainConfig::parse(&text),
        Err(ConfigError::Invalid(_))
    ));
}

#[test]
fn typos_and_bad_values_are_errors() {
    let typo = STAGE1.replace("entropy_coef", "entropy_cof");
    assert!(matches!(
        TrainConfig::parse(&typo),
        Err(ConfigError::Parse(_))
    ));
    let bad = STAGE1.replace("preset = \"paper\"", "preset = \"moon\"");
    let e = TrainConfig::parse(&bad).unwrap_err().to_string();
    assert!(e.contains("moon"), "{e}");
    let stage2 = include_str!("../configs/experiments/stage2_B.toml");
    for bad in [
        "learning_rate = 1e-3\nlearning_rate_final = -1.0",
        "learning_rate = 1e-3\nteacher_share_start = 1.5",
    ] {
        let t = stage2.replacen("learning_rate = 1e-3", bad, 1);
        assert!(
            matches!(TrainConfig::parse(&t), Err(ConfigError::Invalid(_))),
            "{bad}"
        );
    }
    let bad = STAGE1.replace("stage2_fraction = 0.25", "stage2_fraction = 1.5");
    let e = TrainConfig::parse(&bad).unwrap_err().to_string();
    assert!(e.contains("stage2_fraction"), "{e}");
    let bad = STAGE1.replace("gamma = 0.99", "gamma = 1.5");
    assert!(matches!(
        TrainConfig::parse(&bad),
        Err(ConfigError::Invalid(_))
    ));
}

/// `run.name` names files under `--out`: a name that would leave the run directory (or hide
/// in it) is refused before anything runs; plain names pass.
#[test]
fn run_names_stay_inside_the_run_directory() {
    for name in [
        "../victim",
        "a/b",
        "..",
        ".hidden",
        "a\\b",
        "/etc/x",
        "sp ace",
    ] {
        let t = STAGE1.replace("name = \"stage1\"", &format!("name = \"{name}\""));
        assert_ne!(t, STAGE1, "the replacement happened");
        let e = TrainConfig::parse(&t).unwrap_err().to_string();
        assert!(e.contains("run.name"), "{name}: {e}");
    }
    for name in ["stage1", "stage2-G", "smoke_race.v2"] {
        let t = STAGE1.replace("name = \"stage1\"", &format!("name = \"{name}\""));
        assert!(TrainConfig::parse(&t).is_ok(), "{name}");
    }
}

#[test]
fn a_selection_is_checked_and_hashed() {
    let select =
        "select = { spawn = \"along-track\", episodes = 100, seed = 7, from_iteration = 2000 }";
    assert!(STAGE1.contains(select));
    let stage1 = TrainConfig::parse(STAGE1).unwrap();
    let other_seed = TrainConfig::parse(&STAGE1.replace("seed = 7", "seed = 8")).unwrap();
    assert_ne!(stage1.hash(), other_seed.hash());
    for (from, to, field) in [
        ("keep_best = true", "keep_best = false", "keep_best"),
        (
            "\"along-track\", episodes",
            "\"stage1\", episodes",
            "stage1",
        ),
        ("episodes = 100", "episodes = 0", "episodes"),
        (
            "from_iteration = 2000 }",
            "from_iteration = 4501 }",
            "from_iteration",
        ),
        ("seed = 7,", "seed = 7, lap = 1,", "lap"),
        ("seed = 7,", "seed = 7, jitter = \"pos=-1\",", "jitter"),
    ] {
        let e = TrainConfig::parse(&STAGE1.replace(from, to))
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{to}: {e}");
    }
    // The perturbations: one text or a list; one of them hashes as the text alone, a list of
    // two is another validation, and a bad text is refused by its key.
    let with = |perturb: &str| {
        STAGE1.replace(
            "from_iteration = 2000 }",
            &format!("from_iteration = 2000, perturb = {perturb} }}"),
        )
    };
    let one = TrainConfig::parse(&with("\"latency=1\"")).unwrap();
    let one_listed = TrainConfig::parse(&with("[\"latency=1\"]")).unwrap();
    let two = TrainConfig::parse(&with("[\"motor-tau-ms=20\", \"latency=1\"]")).unwrap();
    assert_eq!(one.hash(), one_listed.hash());
    assert_ne!(one.hash(), stage1.hash());
    assert_ne!(one.hash(), two.hash());
    assert_eq!(two.run.select.as_ref().unwrap().perturb.len(), 2);
    let e = TrainConfig::parse(&with("[\"latency=1\", \"lag=20\"]"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("lag"), "{e}");
    // A race (keep_best on) may rank by a selection, raced against its opponent, with a
    // referee floor within 0-1; not also by win rate.
    let race = include_str!("../configs/experiments/stage2_B.toml")
        .replace("[env]", &format!("{select}\n\n[env]"))
        .replace("from_iteration = 2000 }", "from_iteration = 40 }");
    let plain = TrainConfig::parse(&race).unwrap();
    let floored = |f: &str| {
        race.replace(
            "from_iteration = 40 }",
            &format!("from_iteration = 40, referee_floor = {f} }}"),
        )
    };
    let with_floor = TrainConfig::parse(&floored("0.9")).unwrap();
    assert_eq!(
        with_floor.run.select.as_ref().unwrap().referee_floor,
        Some(0.9)
    );
    assert_ne!(plain.hash(), with_floor.hash());
    for bad in ["1.5", "-0.1", "nan"] {
        let e = TrainConfig::parse(&floored(bad)).unwrap_err().to_string();
        assert!(e.contains("referee_floor"), "{bad}: {e}");
    }
    let by_win = race.replace(
        "keep_best = true",
        "keep_best = true\nkeep_best_by = \"win-rate\"",
    );
    let e = TrainConfig::parse(&by_win).unwrap_err().to_string();
    assert!(e.contains("two rankings"), "{e}");
    // [race]'s per-race bar: a race's, another config than without it; a time trial has
    // no races to judge and is refused by name.
    let with_bar = TrainConfig::parse(&race.replace(
        "from_iteration = 40 }",
        "from_iteration = 40, race_bar = true }",
    ))
    .unwrap();
    assert!(with_bar.run.select.as_ref().unwrap().race_bar);
    assert_ne!(plain.hash(), with_bar.hash());
    assert_eq!(
        TrainConfig::parse(&race.replace(
            "from_iteration = 40 }",
            "from_iteration = 40, race_bar = false }",
        ))
        .unwrap()
        .hash(),
        plain.hash()
    );
    let e = TrainConfig::parse(&STAGE1.replace(
        "from_iteration = 2000 }",
        "from_iteration = 2000, race_bar = true }",
    ))
    .unwrap_err()
    .to_string();
    assert!(e.contains("race_bar"), "{e}");
}

#[test]
fn ranking_by_win_rate_is_for_races_and_changes_the_hash() {
    let race = include_str!("../configs/stage2_transplant.toml");
    let by_win = race.replace(
        "keep_best = true",
        "keep_best = true\nkeep_best_by = \"win-rate\"",
    );
    assert_ne!(by_win, race);
    let a = TrainConfig::parse(race).unwrap();
    let b = TrainConfig::parse(&by_win).unwrap();
    assert_ne!(a.hash(), b.hash());
    // Without keep_best, or in a time trial, it is refused by name.
    let e = TrainConfig::parse(&by_win.replace("keep_best = true\n", ""))
        .unwrap_err()
        .to_string();
    assert!(e.contains("keep_best_by"), "{e}");
    let trial = STAGE1.replace(
        "keep_best = true",
        "keep_best = true\nkeep_best_by = \"win-rate\"",
    );
    let e = TrainConfig::parse(&trial).unwrap_err().to_string();
    assert!(e.contains("keep_best_by"), "{e}");
    let e = TrainConfig::parse(&by_win.replace("\"win-rate\"", "\"wins\""))
        .unwrap_err()
        .to_string();
    assert!(e.contains("keep_best_by") || e.contains("wins"), "{e}");
}

#[test]
fn the_presets_in_code_are_the_toml_presets() {
    assert_eq!(TrainConfig::parse(PAPER).unwrap(), TrainConfig::paper());
    assert_eq!(
        TrainConfig::parse(STAGE1_NOMINAL).unwrap(),
        TrainConfig::ours()
    );
    assert_eq!(TrainConfig::default(), TrainConfig::paper());
    // The presets are valid configs and hash as their files do (a blob's provenance).
    for (text, preset) in [
        (PAPER, TrainConfig::paper()),
        (STAGE1_NOMINAL, TrainConfig::ours()),
    ] {
        let round_trip = TrainConfig::parse(&toml::to_string(&preset).unwrap()).unwrap();
        assert_eq!(round_trip, preset);
        assert_eq!(preset.hash(), TrainConfig::parse(text).unwrap().hash());
    }
}

#[test]
fn the_sigma_ceiling_falls_linearly_between_its_iterations() {
    let decay = "max_std = 1.0\nmax_std_decay = { final_std = 0.4, from_iteration = 100, to_iteration = 400 }\ninit_std";
    let c = TrainConfig::parse(&FINETUNE.replacen("init_std", decay, 1)).unwrap();
    let at = |i| c.ppo.max_std_at(i).unwrap();
    for (i, want) in [(0, 1.0), (100, 1.0), (250, 0.7), (400, 0.4), (10_000, 0.4)] {
        assert!((at(i) - want).abs() < 1e-6, "iteration {i}: {}", at(i));
    }
    // Without a decay the ceiling is max_std throughout; without max_std there is none.
    let fixed = TrainConfig::parse(&FINETUNE.replacen("init_std", "max_std = 1.0\ninit_std", 1));
    assert_eq!(fixed.unwrap().ppo.max_std_at(5_000), Some(1.0));
    assert_eq!(
        TrainConfig::parse(FINETUNE).unwrap().ppo.max_std_at(0),
        None
    );
    for bad in [
        // No ceiling to lower.
        "max_std_decay = { final_std = 0.4, from_iteration = 1, to_iteration = 4 }\ninit_std",
        // A ceiling that rises, and one that falls backwards in time.
        "max_std = 1.0\nmax_std_decay = { final_std = 1.5, from_iteration = 1, to_iteration = 4 }\ninit_std",
        "max_std = 1.0\nmax_std_decay = { final_std = 0.4, from_iteration = 4, to_iteration = 4 }\ninit_std",
    ] {
        assert!(
            matches!(
                TrainConfig::parse(&FINETUNE.replacen("init_std", bad, 1)),
                Err(ConfigError::Invalid(_))
            ),
            "{bad}"
        );
    }
}

/// `pass_decay`: the pass weight falls linearly between its iterations, the other weights
/// stay; absent, it leaves the canonical TOML (older configs keep their hash).
#[test]
fn the_pass_weight_falls_linearly_between_its_iterations() {
    const RL: &str = include_str!("../configs/experiments/stage1_rl.toml");
    let decay = "\n[pass_decay]\nfinal_weight = 0.25\nfrom_iteration = 100\nto_iteration = 400\n";
    let c = TrainConfig::parse(&format!("{RL}{decay}")).unwrap();
    let plain = TrainConfig::parse(RL).unwrap();
    for (i, want) in [
        (0, 1.0),
        (100, 1.0),
        (250, 0.625),
        (400, 0.25),
        (10_000, 0.25),
    ] {
        let w = c.reward_at(i);
        assert!((w.pass - want).abs() < 1e-6, "iteration {i}: {}", w.pass);
        assert_eq!(
            RewardWeights {
                pass: c.env.reward.pass,
                ..w
            },
            c.env.reward
        );
    }
    assert_eq!(plain.reward_at(10_000), plain.env.reward);
    assert_ne!(c.hash(), plain.hash());
    assert!(!toml::to_string(&plain).unwrap().contains("pass_decay"));
    assert_eq!(
        TrainConfig::parse(&toml::to_string(&c).unwrap()).unwrap(),
        c
    );
    for bad in [
        "\n[pass_decay]\nfinal_weight = -1.0\nfrom_iteration = 1\nto_iteration = 4\n",
        "\n[pass_decay]\nfinal_weight = 0.0\nfrom_iteration = 4\nto_iteration = 4\n",
        "\n[pass_decay]\nfinal_weight = 0.0\nfrom_iteration = 1\nto_iteration = 4\n[guard]\nenvs = 8\nwarmup_steps = 1\nsteps = 1\n",
    ] {
        assert!(
            matches!(
                TrainConfig::parse(&format!("{RL}{bad}")),
                Err(ConfigError::Invalid(_))
            ),
            "{bad}"
        );
    }
}

/// `[randomize_ramp]`: no spawn is randomised until its first iteration, then a share rising
/// linearly to `env.randomize_share`; absent, the share is `env.randomize_share` throughout
/// and the canonical TOML has no key (older configs keep their hash). A ramp without
/// `env.randomize`, a reversed or empty span, or one past the budget is refused by name; so
/// is a share outside [0, 1].
#[test]
fn the_randomised_share_rises_between_its_iterations() {
    const ROBUST: &str = include_str!("../configs/experiments/stage1_robust.toml");
    let ramp = "\n[randomize_ramp]\nfrom_iteration = 100\nto_iteration = 500\n";
    let c = TrainConfig::parse(&format!("{ROBUST}{ramp}")).unwrap();
    let plain = TrainConfig::parse(ROBUST).unwrap();
    for (i, want) in [(0, 0.0), (100, 0.0), (300, 0.5), (500, 1.0), (10_000, 1.0)] {
        let share = c.randomize_share_at(i);
        assert!((share - want).abs() < 1e-6, "iteration {i}: {share}");
        assert_eq!(plain.randomize_share_at(i), 1.0);
    }
    let half = TrainConfig::parse(&format!(
        "{}{ramp}",
        ROBUST.replacen("randomize =", "randomize_share = 0.5\nrandomize =", 1)
    ))
    .unwrap();
    assert!((half.randomize_share_at(300) - 0.25).abs() < 1e-6);
    assert_ne!(c.hash(), plain.hash());
    let text = toml::to_string(&plain).unwrap();
    assert!(
        !text.contains("randomize_ramp") && !text.contains("randomize_share"),
        "{text}"
    );
    assert_eq!(
        TrainConfig::parse(&toml::to_string(&c).unwrap()).unwrap(),
        c
    );
    let no_draws = ROBUST
        .lines()
        .filter(|l| !l.starts_with("randomize ="))
        .collect::<Vec<_>>()
        .join("\n");
    for (text, says) in [
        (format!("{no_draws}{ramp}"), "set env.randomize"),
        (
            format!("{ROBUST}\n[randomize_ramp]\nfrom_iteration = 500\nto_iteration = 500\n"),
            "below to_iteration",
        ),
        (
            format!("{ROBUST}\n[randomize_ramp]\nfrom_iteration = 100\nto_iteration = 2500\n"),
            "below run.iterations 2500",
        ),
        (
            ROBUST.replacen("randomize =", "randomize_share = 1.5\nrandomize =", 1),
            "randomize_share",
        ),
    ] {
        match TrainConfig::parse(&text) {
            Err(e) => assert!(e.to_string().contains(says), "{says}: {e}"),
            Ok(_) => panic!("accepted, expected a refusal saying {says}"),
        }
    }
}

/// `env.fold_mirror`: read, hashed only when on (older configs keep their hash), carried
/// into the observation spec (pipeline version 2) that the env and the blob use, and
/// refused beside a warm start, whose teacher labels world motors.
#[test]
fn the_mirror_fold_is_checked_hashed_and_reaches_the_spec() {
    const RL: &str = include_str!("../configs/experiments/stage1_rl.toml");
    let plain = TrainConfig::parse(RL).unwrap();
    let on = TrainConfig::parse(&RL.replacen("[env]\n", "[env]\nfold_mirror = true\n", 1)).unwrap();
    assert!(on.env.fold_mirror && !plain.env.fold_mirror);
    assert_ne!(on.hash(), plain.hash());
    assert!(!toml::to_string(&plain).unwrap().contains("fold_mirror"));
    assert_eq!(
        TrainConfig::parse(&toml::to_string(&on).unwrap()).unwrap(),
        on
    );
    assert!(on.observation_spec().is_folded());
    assert!(!plain.observation_spec().is_folded());
    assert_eq!(
        on.observation_spec().with_fold(false),
        plain.observation_spec()
    );
    // The deleted mirror options are unknown keys now, not silently ignored.
    let old = RL.replacen("init_std", "mirror_augmentation = true\ninit_std", 1);
    let e = TrainConfig::parse(&old).unwrap_err().to_string();
    assert!(e.contains("mirror_augmentation"), "{e}");
    // stage1_finetune.toml warm-starts from the baseline, whose labels are the world's motors.
    let e = TrainConfig::parse(&FINETUNE.replacen("[env]\n", "[env]\nfold_mirror = true\n", 1))
        .unwrap_err()
        .to_string();
    assert!(e.contains("fold_mirror") && e.contains("warm start"), "{e}");
}

/// `warm_start.transplant`: it needs its teacher and no student of its own, and unlike DAgger
/// rounds it may fold (the transplant observes through the teacher's own folded pipeline).
#[test]
fn a_transplant_needs_its_teacher_alone_and_may_fold() {
    let text = include_str!("../configs/experiments/race_transplant.toml");
    let ok = TrainConfig::parse(text).unwrap();
    let warm = ok.warm_start.as_ref().unwrap();
    assert!(warm.transplant && ok.env.fold_mirror && warm.rounds == 0);
    for (bad, says) in [
        (
            text.replacen("teacher_blob = \"policies/stage1_nominal.blob\"\n", "", 1),
            "teacher_blob",
        ),
        (
            text.replacen(
                "transplant = true\n",
                "transplant = true\nstudent = \"x.blob\"\n",
                1,
            ),
            "student",
        ),
        (
            text.replacen("rounds = 0\n", "rounds = 2\n", 1),
            "fold_mirror",
        ),
        (text.replacen("transplant = true\n", "", 1), "rounds"),
        (
            text.replacen("[ppo]\n", "[ppo]\nlstm_learning_rate_scale = 0.0\n", 1),
            "lstm_learning_rate_scale",
        ),
        (
            text.replacen("[ppo]\n", "[ppo]\nlstm_learning_rate_scale = 0.1\n", 1)
                .replacen("row = \"G\"", "row = \"C\"", 1),
            "recurrent row",
        ),
    ] {
        let e = TrainConfig::parse(&bad).unwrap_err().to_string();
        assert!(e.contains(says), "{says}: {e}");
    }
}

/// Every committed config (the shipped pipelines in `configs/` and each policy's own in
/// `policies/*/config.toml`) round-trips through sitl's environment schema: parsed,
/// written back and parsed again it is the same config with the same hash, and its
/// environment validates on its own.
#[test]
fn every_committed_config_round_trips_through_the_env_schema() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut paths: Vec<_> = ["host-trainer/configs", "host-trainer/configs/experiments"]
        .into_iter()
        .flat_map(|d| std::fs::read_dir(root.join(d)).unwrap())
        .map(|e| e.unwrap().path())
        .collect();
    for entry in std::fs::read_dir(root.join("policies")).unwrap() {
        paths.push(entry.unwrap().path().join("config.toml"));
    }
    let mut n = 0;
    for path in paths
        .iter()
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e == "toml"))
    {
        let config = TrainConfig::load(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let written = toml::to_string(&config).unwrap();
        let again = TrainConfig::parse(&written).unwrap();
        assert_eq!(again, config, "{}", path.display());
        assert_eq!(again.hash(), config.hash(), "{}", path.display());
        config.env_config(0).validate().unwrap();
        n += 1;
    }
    assert!(n >= 20, "{n} configs");
}

/// The shipped pipelines' environments are sitl's named ones, which the Python binding's
/// defaults come from (`overtake.shipped_env`): stage 1's `[env]` and `[reward]` are
/// `EnvConfig::stage1`, and the row-G race's are `EnvConfig::stage2` against its opponent.
#[test]
fn the_shipped_environments_are_sitls_named_ones() {
    use sitl::env::EnvConfig;
    let nominal = TrainConfig::parse(STAGE1_NOMINAL).unwrap();
    assert_eq!(
        nominal.env,
        EnvConfig {
            seed: 1,
            ..EnvConfig::stage1(512)
        }
    );
    // The shipped stage-1 run is that environment with the ego randomised on a share of the
    // spawns (`[randomize_ramp]` raises the share during the run).
    let stage1 = TrainConfig::parse(STAGE1).unwrap();
    assert!(stage1.env.randomize.is_some() && stage1.env.randomize_share > 0.0);
    assert_eq!(
        stage1.env,
        EnvConfig {
            seed: 1,
            randomize: stage1.env.randomize.clone(),
            randomize_share: stage1.env.randomize_share,
            ..EnvConfig::stage1(512)
        }
    );
    let race = TrainConfig::parse(include_str!("../configs/stage2_G.toml")).unwrap();
    let opponent = race.env.race.as_ref().unwrap().opponent.clone();
    assert_eq!(
        race.env,
        EnvConfig {
            seed: 1,
            ..EnvConfig::stage2(128, opponent)
        }
    );
}

/// An environment field out of its range is refused with the field as the config writes
/// it, whichever of the environment's three sections it is in.
#[test]
fn environment_errors_name_the_field() {
    let race = include_str!("../configs/stage2_G.toml");
    for (text, from, to, field) in [
        (
            STAGE1,
            "velocity_scale_mps = 12.0",
            "velocity_scale_mps = -1.0",
            "env.velocity_scale_mps",
        ),
        (
            STAGE1,
            "num_envs = 512",
            "num_envs = 1000000000",
            "env.num_envs",
        ),
        (
            STAGE1,
            "episode_s = 15.0",
            "episode_s = nan",
            "env.episode_s",
        ),
        (
            STAGE1,
            "spawn_speed_mps = 8.0",
            "spawn_speed_mps = 80.0",
            "env.spawn_speed_mps",
        ),
        (
            STAGE1,
            "progress = 0.5",
            "progress = nan",
            "reward.progress",
        ),
        (STAGE1, "crash = 1.0", "crash = -1.0", "reward.crash"),
        (
            race,
            "competition_weight = 0.5",
            "competition_weight = inf",
            "race.competition_weight",
        ),
        (
            race,
            "spawn = \"stage2\"",
            "spawn = \"along-track\"",
            "env.spawn",
        ),
    ] {
        assert!(text.contains(from), "{from}");
        let e = TrainConfig::parse(&text.replace(from, to))
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{to}: {e}");
    }
}

/// The previous stage-2 path (what `sitl race` flew until `stage2.toml`):
/// `configs/stage2_transplant.toml` is, parsed, the run's own `config.toml` beside
/// `policies/stage2_transplant.blob` (whose provenance `shipped_policies.rs` checks against
/// it, by the paths its run named), and it starts from the stage-1 blob that
/// `experiments/stage1_nominal.toml` makes (`configs/stage1.toml` then).
#[test]
fn the_transplant_stage2_config_is_the_one_that_made_its_race_ego() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let blessed =
        TrainConfig::load(&root.join("host-trainer/configs/stage2_transplant.toml")).unwrap();
    let made = TrainConfig::load(&root.join("policies/stage2_transplant/config.toml")).unwrap();
    // The nominal stage-1 policy was policies/stage1.blob when the run was made.
    let renamed = renamed::as_run(&blessed);
    assert_ne!(renamed, blessed, "the rename applies");
    assert_eq!(renamed, made);
    assert_eq!(renamed.hash(), made.hash());
    let warm = blessed.warm_start.as_ref().unwrap();
    assert!(warm.transplant && warm.rounds == 0);
    assert_eq!(
        warm.teacher_blob.as_deref(),
        Some("policies/stage1_nominal.blob")
    );
    let stage1 = TrainConfig::parse(STAGE1_NOMINAL).unwrap();
    assert_eq!(stage1.run.name, "stage1");
}

/// `experiments/stage2_long.toml` (`configs/stage2.toml` until 2026-12-07) is
/// `stage2_transplant.toml` with the faster teacher and its own name and seed, and
/// `experiments/race_long.toml` (run long2) under another name and seed; the teacher is
/// `experiments/stage1_long.toml`'s blob, which is `stage1_nominal.toml` with a larger budget.
/// `experiments/stage2_robust_fast.toml` (`configs/stage2.toml` until it ranked by the race
/// bar) is that recipe with the robust teacher, opponent and draws, and
/// `experiments/stage1_robust_fast.toml` is `experiments/stage1_4500.toml` with 300 more
/// iterations under a wider draw; `stage1_4500.toml` is `configs/stage1.toml` with 1,500 more
/// iterations and nothing else. `configs/stage2.toml` (what `sitl race` flies) is
/// `stage2_robust_fast.toml` from the jittered teacher, from jittered starts, with the
/// selection that ranks by the race bar, and `experiments/stage2_robust_jitter3.toml` (the run
/// it repeats) with the race bar in place of the referee's floor.
#[test]
fn the_long_stage2_recipe_is_the_transplant_recipe_with_the_long_teacher() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let load = |p: &str| TrainConfig::load(&root.join(p)).unwrap();
    let long = load("experiments/stage2_long.toml");
    assert_eq!(long.run.seed, 2, "seed 2 of three shipped");
    let mut renamed = load("experiments/race_long.toml");
    renamed.run.name = long.run.name.clone();
    renamed.run.seed = long.run.seed;
    renamed.env.seed = long.env.seed;
    assert_eq!(renamed, long);
    let mut transplant = load("stage2_transplant.toml");
    transplant.run.name = long.run.name.clone();
    transplant.run.seed = long.run.seed;
    transplant.env.seed = long.env.seed;
    if let Some(w) = transplant.warm_start.as_mut() {
        w.teacher_blob = Some("policies/stage1_long.blob".into());
    }
    assert_eq!(transplant, long);
    let mut stage1_long = load("experiments/stage1_long.toml");
    let stage1 = TrainConfig::parse(STAGE1_NOMINAL).unwrap();
    assert_eq!(stage1_long.run.iterations, 2 * stage1.run.iterations);
    stage1_long.run.iterations = stage1.run.iterations;
    stage1_long.run.name = stage1.run.name.clone();
    assert_eq!(stage1_long, stage1);

    let robust = load("experiments/stage2_robust_fast.toml");
    let mut from_long = long.clone();
    from_long.run.name = robust.run.name.clone();
    from_long.run.seed = robust.run.seed;
    from_long.env.seed = robust.env.seed;
    from_long.env.randomize = robust.env.randomize.clone();
    from_long.env.randomize_share = robust.env.randomize_share;
    from_long.env.race.as_mut().unwrap().opponent = "policies/stage1.blob".into();
    from_long.warm_start.as_mut().unwrap().teacher_blob =
        Some("policies/stage1_robust_fast.blob".into());
    assert_eq!(from_long, robust);
    let fast = load("experiments/stage1_robust_fast.toml");
    let root_4500 = load("experiments/stage1_4500.toml");
    assert_eq!(fast.run.iterations, root_4500.run.iterations + 300);
    assert_eq!(fast.randomize_ramp, root_4500.randomize_ramp);
    assert_eq!(fast.env.randomize_share, root_4500.env.randomize_share);
    let shipped1 = TrainConfig::parse(STAGE1).unwrap();
    assert_eq!(root_4500.run.iterations, shipped1.run.iterations + 1500);
    assert!(root_4500.only_budget_differs_from(&shipped1));

    let shipped2 = load("stage2.toml");
    let mut jittered = robust.clone();
    jittered.env.spawn_jitter = shipped2.env.spawn_jitter.clone();
    jittered.run.select = shipped2.run.select.clone();
    jittered.warm_start.as_mut().unwrap().teacher_blob =
        Some("policies/stage1_robust_jitter3.blob".into());
    assert_eq!(jittered, shipped2);
    let select = shipped2.run.select.as_ref().unwrap();
    assert!(select.race_bar && select.referee_floor.is_none());
    let mut repeated = load("experiments/stage2_robust_jitter3.toml");
    let s = repeated.run.select.as_mut().unwrap();
    assert_eq!(s.referee_floor, Some(0.9));
    (s.referee_floor, s.race_bar) = (None, true);
    repeated.run.name = shipped2.run.name.clone();
    repeated.warm_start.as_mut().unwrap().teacher_blob =
        Some("policies/stage1_robust_jitter3.blob".into());
    assert_eq!(repeated, shipped2);
}

/// `experiments/race_curriculum.toml` is the shipped race recipe at the same budget with one
/// `[[opponent_curriculum]]` stage; `race_at` gives each iteration's opponent, the key is
/// hashed, and a curriculum outside a race, out of order, past the budget or beside a
/// `[guard]` is refused by name.
#[test]
fn an_opponent_curriculum_is_the_shipped_recipe_with_an_earlier_opponent() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let text = std::fs::read_to_string(root.join("experiments/race_curriculum.toml")).unwrap();
    let curriculum = TrainConfig::parse(&text).unwrap();
    // The race recipe it was run beside (configs/stage2.toml until 2026-12-07).
    let shipped = TrainConfig::load(&root.join("experiments/stage2_long.toml")).unwrap();
    let opponent = |c: &TrainConfig, i| c.race_at(i).unwrap().opponent;
    assert_eq!(
        opponent(&curriculum, 0),
        Path::new("policies/stage1_robust.blob")
    );
    assert_eq!(
        opponent(&curriculum, 99),
        Path::new("policies/stage1_robust.blob")
    );
    assert_eq!(
        opponent(&curriculum, 100),
        Path::new("policies/stage1_nominal.blob")
    );
    assert_eq!(
        opponent(&shipped, 0),
        Path::new("policies/stage1_nominal.blob")
    );
    assert_eq!(
        curriculum.race_at(100),
        shipped.race_at(0),
        "only the opponent changes"
    );
    let mut same = curriculum.clone();
    same.opponent_curriculum.clear();
    same.run.name = shipped.run.name.clone();
    assert_eq!(same, shipped);
    assert_ne!(curriculum.hash(), same.hash());

    let refused = |t: &str| TrainConfig::parse(t).unwrap_err().to_string();
    let e = refused(&text.replace("until_iteration = 100", "until_iteration = 200"));
    assert!(e.contains("opponent_curriculum[0].until_iteration"), "{e}");
    let two = format!(
        "{text}\n[[opponent_curriculum]]\nopponent = \"policies/stage1_guarded.blob\"\nuntil_iteration = 50\n"
    );
    let e = refused(&two);
    assert!(e.contains("opponent_curriculum[1].until_iteration"), "{e}");
    let e = refused(&format!(
        "{text}\n[guard]\nenvs = 8\nwarmup_steps = 10\nsteps = 10\n"
    ));
    assert!(e.contains("[guard]"), "{e}");
    let stage = &text[text.find("[[opponent_curriculum]]").unwrap()..];
    let e = refused(&format!("{STAGE1}\n{stage}"));
    assert!(e.contains("time trial"), "{e}");
    let e = refused(&text.replace("until_iteration", "until"));
    assert!(e.contains("until"), "{e}");
}
