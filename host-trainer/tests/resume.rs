//! Checkpoints and resume: a run stopped and resumed, even after a kill left a torn
//! checkpoint and metrics past it, ends where an uninterrupted run's learning state is at the
//! checkpoint; a directory holding a run is not overwritten; a changed config is refused,
//! except a changed budget; a fork (`--fork-from`) continues a run under a changed config; `run.select` picks the
//! exported actor across a resume.

use burn::tensor::Device;
use host_trainer::config::{Selection, TrainConfig};
use host_trainer::fused::FusedOptim;
use host_trainer::latest::{checkpoint_actor, checkpoint_blob};
use host_trainer::metrics::IterationMetrics;
use host_trainer::nets::PolicyNet;
use host_trainer::train::{RunOptions, run};
use std::path::{Path, PathBuf};

const CONFIG: &str = include_str!("../configs/smoke.toml");

mod common;

fn tmp(name: &str) -> PathBuf {
    common::tmp_dir("resume", name)
}

fn options(out: &Path, resume: bool, stop_after: Option<u32>) -> RunOptions {
    RunOptions {
        resume,
        stop_after,
        ..common::run_options(out)
    }
}

fn metrics(out: &Path) -> Vec<IterationMetrics> {
    common::read_jsonl(&out.join("metrics.jsonl"))
}

#[test]
fn a_killed_run_resumes_from_its_last_checkpoint() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    assert_eq!(config.run.checkpoint_every, 2);
    let device = Device::flex().autodiff();

    // Uninterrupted to iteration 2 (a run of 4 stopped after 2 checkpoints at 2).
    let a = tmp("a");
    let s = run(&config, &options(&a, false, Some(2))).unwrap();
    assert_eq!((s.iterations, s.blob.is_none()), (2, true));
    let (it, actor_a) = checkpoint_actor(&config, &a, &device).unwrap();
    assert_eq!(it, 2);
    // The fused update's Adam state is in the checkpoint: 2 iterations × 2 epochs × 2
    // minibatches of steps, moments of the actor's size.
    let bytes = std::fs::read(
        a.join("checkpoints")
            .join("iter_000002")
            .join("fused_adam.safetensors"),
    )
    .unwrap();
    let optim = FusedOptim::from_safetensors(&bytes).unwrap();
    assert_eq!((optim.actor.time, optim.critic.time), (8, 8));
    assert_eq!(optim.actor.moment_2.len(), actor_a.payload().len() + 4);
    assert!(optim.actor.moment_2.iter().all(|v| *v > 0.0));

    // Another run, "killed" during iteration 3's checkpoint: a torn directory, a metrics
    // line past the checkpoint.
    let b = tmp("b");
    run(&config, &options(&b, false, Some(2))).unwrap();
    let torn = b.join("checkpoints").join("iter_000003");
    std::fs::create_dir_all(&torn).unwrap();
    std::fs::write(torn.join("actor.bpk"), b"half a file").unwrap();
    let mut lines = std::fs::read_to_string(b.join("metrics.jsonl")).unwrap();
    lines.push_str("{\"iteration\":3}\n");
    std::fs::write(b.join("metrics.jsonl"), lines).unwrap();

    // Both runs are deterministic up to the checkpoint.
    let (_, actor_b) = checkpoint_actor(&config, &b, &device).unwrap();
    assert_eq!(actor_a.payload(), actor_b.payload());

    // Starting over into a directory that holds a run is refused, nothing is touched.
    let e = run(&config, &options(&b, false, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--resume"), "{e}");

    // Resume: from iteration 2 to the budget of 4, the torn iteration 3 redone.
    let before = std::fs::read(b.join("metrics.jsonl")).unwrap();
    let s = run(&config, &options(&b, true, None)).unwrap();
    // metrics.jsonl is appended to, never rewritten: the lines of iterations 1 and 2 are
    // the bytes first written (the torn line of iteration 3 is cut).
    let after = std::fs::read(b.join("metrics.jsonl")).unwrap();
    let kept = before.len() - "{\"iteration\":3}\n".len();
    assert_eq!(&after[..kept], &before[..kept]);
    assert_eq!(s.iterations, 4);
    let blob = s.blob.expect("a finished run exports its blob");
    assert!(blob.exists());
    assert!(b.join("smoke.safetensors").exists());
    assert!(b.join("learning_curves.svg").exists());
    let m = metrics(&b);
    let its: Vec<u32> = m.iter().map(|m| m.iteration).collect();
    assert_eq!(its, vec![1, 2, 3, 4]);
    assert!(m[3].samples == 4 * config.samples_per_iteration() as u64);
    assert!(
        m[3].eval_success_rate.is_some(),
        "the last iteration is evaluated"
    );

    // A changed config cannot resume this run.
    let mut other = config.clone();
    other.ppo.entropy_coef = 0.02;
    other.run.iterations = 6;
    let e = run(&other, &options(&b, true, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("config hash"), "{e}");
    // Nothing to resume in an empty directory.
    let e = run(&config, &options(&tmp("c"), true, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("nothing to resume"), "{e}");
    for d in [a, b] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// The metrics of a run without its wall-clock fields (which differ between any two runs).
fn learning_record(out: &Path) -> Vec<serde_json::Value> {
    metrics(out)
        .iter()
        .map(|m| {
            let mut v = serde_json::to_value(m).unwrap();
            for k in ["wall_s", "samples_per_s", "rollout_s", "update_s"] {
                v.as_object_mut().unwrap().remove(k);
            }
            v
        })
        .collect()
}

/// Resume is bit for bit: a run stopped after iteration 2 and resumed ends with the weights
/// and the metrics (rewards, successes, losses, KL, the referee's) of the run that was never
/// stopped, for a feed-forward time trial and a recurrent race (row G: the policy's and the
/// critic's recurrent states come back too). The envs, recurrent states and episode log come
/// from the checkpoint's `loop.json`; a checkpoint without it (an older build's) resumes with
/// respawned envs, and that run differs (so the check can fail).
#[test]
fn a_resumed_run_is_the_uninterrupted_run_bit_for_bit() {
    let ff = TrainConfig::parse(CONFIG).unwrap();
    let race = tiny_race("../policies/stage1_guarded.blob");
    for (name, config) in [("ff", ff), ("g", race)] {
        assert_eq!((config.run.iterations, config.run.checkpoint_every), (4, 2));
        let whole = tmp(&format!("bitwise-{name}-whole"));
        run(&config, &options(&whole, false, None)).unwrap();
        let stopped = tmp(&format!("bitwise-{name}-stopped"));
        run(&config, &options(&stopped, false, Some(2))).unwrap();
        assert!(stopped.join("checkpoints/iter_000002/loop.json").exists());
        run(&config, &options(&stopped, true, None)).unwrap();
        // The last checkpoint's actor as a blob, byte for byte (its weights' bits).
        let device = Device::flex().autodiff();
        let nets = |d: &Path| checkpoint_blob(&config, d, &device).unwrap().1;
        assert!(
            nets(&whole) == nets(&stopped),
            "{name}: the networks differ"
        );
        assert_eq!(learning_record(&whole), learning_record(&stopped), "{name}");

        // Without loop.json the envs are respawned: another run from iteration 3 on.
        let respawned = tmp(&format!("bitwise-{name}-respawned"));
        run(&config, &options(&respawned, false, Some(2))).unwrap();
        std::fs::remove_file(respawned.join("checkpoints/iter_000002/loop.json")).unwrap();
        // (its checksum goes with it, as an older build's checkpoint has none)
        let state = respawned.join("checkpoints/iter_000002/state.json");
        let mut json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
        json["files"].as_object_mut().unwrap().remove("loop.json");
        std::fs::write(&state, json.to_string()).unwrap();
        run(&config, &options(&respawned, true, None)).unwrap();
        assert!(
            nets(&whole) != nets(&respawned),
            "{name}: a respawn changed nothing"
        );
        for d in [whole, stopped, respawned] {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// Issue "faults": a run killed at any iteration, during the validation phase too, resumes
/// bit for bit. A time trial with `run.select` validating every iteration from the second
/// (its candidates and their validation numbers live in the checkpoints) is killed after
/// each of iterations 1-4 in turn: the kill leaves the next iteration's checkpoint torn and
/// its metrics line cut. Every resumed run exports the blob of the uninterrupted run byte for
/// byte, with the same learning record.
#[test]
fn a_run_killed_at_any_iteration_even_inside_the_validation_resumes_bit_for_bit() {
    let mut config = TrainConfig::parse(CONFIG).unwrap();
    config.run.iterations = 5;
    config.run.checkpoint_every = 1;
    config.run.eval_every = 1;
    config.run.select = Some(Selection {
        spawn: sitl::referee::SpawnMode::AlongTrack,
        episodes: 2,
        seed: 7,
        from_iteration: 2,
        perturb: Vec::new(),
        jitter: None,
        referee_floor: None,
        race_bar: false,
    });
    config.run.keep_best = true;
    TrainConfig::parse(&toml::to_string(&config).unwrap()).unwrap();
    let whole = tmp("killed-whole");
    let _ = std::fs::remove_dir_all(&whole);
    let s = run(&config, &options(&whole, false, None)).unwrap();
    let want = std::fs::read(s.blob.expect("exported")).unwrap();
    assert!(
        metrics(&whole)
            .iter()
            .filter(|m| m.select_success_rate.is_some())
            .count()
            >= 3,
        "the validation flies from iteration 2"
    );
    for killed_after in 1..=4u32 {
        let out = tmp(&format!("killed-{killed_after}"));
        run(&config, &options(&out, false, Some(killed_after))).unwrap();
        // The kill: the next iteration's checkpoint half written, its metrics line cut.
        let torn = out
            .join("checkpoints")
            .join(format!("iter_{:06}", killed_after + 1));
        std::fs::create_dir_all(&torn).unwrap();
        std::fs::write(torn.join("actor.bpk"), b"half a file").unwrap();
        let mut lines = std::fs::read_to_string(out.join("metrics.jsonl")).unwrap();
        lines.push_str(&format!("{{\"iteration\":{},\"samp", killed_after + 1));
        std::fs::write(out.join("metrics.jsonl"), lines).unwrap();
        let s = run(&config, &options(&out, true, None)).unwrap();
        let got = std::fs::read(s.blob.expect("exported")).unwrap();
        assert!(got == want, "killed after {killed_after}: another blob");
        assert_eq!(
            learning_record(&out),
            learning_record(&whole),
            "killed after {killed_after}"
        );
        let _ = std::fs::remove_dir_all(out);
    }
    let _ = std::fs::remove_dir_all(whole);
}

#[test]
fn a_resumed_run_may_raise_its_budget_and_trains_as_if_it_had_it_from_the_start() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    assert_eq!(config.run.iterations, 4);
    let device = Device::flex().autodiff();
    let mut short = config.clone();
    short.run.iterations = 2;

    // A finished run of 2 iterations, extended to 4 by a resume with the larger budget.
    let extended = tmp("extended");
    let s = run(&short, &options(&extended, false, None)).unwrap();
    assert_eq!((s.iterations, s.blob.is_some()), (2, true));
    let s = run(&config, &options(&extended, true, None)).unwrap();
    assert_eq!(s.iterations, 4);
    let (it, actor_extended) = checkpoint_actor(&config, &extended, &device).unwrap();
    assert_eq!(it, 4);

    // A run with the budget of 4 from the start, stopped and resumed at the same iteration
    // (a resume restarts the environments): the same actor and the same rollouts.
    let whole = tmp("whole");
    run(&config, &options(&whole, false, Some(2))).unwrap();
    run(&config, &options(&whole, true, None)).unwrap();
    let (_, actor_whole) = checkpoint_actor(&config, &whole, &device).unwrap();
    assert_eq!(actor_extended.payload(), actor_whole.payload());
    let rewards = |d: &Path| -> Vec<f64> { metrics(d).iter().map(|m| m.reward_per_step).collect() };
    assert_eq!(rewards(&extended), rewards(&whole));
    // The run directory now holds the extended config, so the next resume needs no note.
    let stored = TrainConfig::load(&extended.join("config.toml")).unwrap();
    assert_eq!(stored.hash(), config.hash());

    // Any other change is still refused, also together with a budget change.
    let mut other = config.clone();
    other.run.iterations = 6;
    other.ppo.clip = 0.3;
    let e = run(&other, &options(&extended, true, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("only run.iterations may change"), "{e}");
    for d in [extended, whole] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn a_fork_continues_a_run_under_a_changed_config_and_records_its_parent() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    let device = Device::flex().autodiff();
    let mut short = config.clone();
    short.run.iterations = 2;
    let parent = tmp("fork_parent");
    run(&short, &options(&parent, false, None)).unwrap();

    // Forked under the parent's own recipe with the larger budget: the same learning state as
    // resuming the parent with that budget (the same environment, so both continue the
    // parent's flights from its checkpoint's loop.json).
    let same = tmp("fork_same");
    let fork = |out: &Path| RunOptions {
        fork_from: Some(parent.clone()),
        ..options(out, false, None)
    };
    let s = run(&config, &fork(&same)).unwrap();
    assert_eq!(s.iterations, 4);
    let resumed = tmp("fork_resumed");
    run(&short, &options(&resumed, false, None)).unwrap();
    run(&config, &options(&resumed, true, None)).unwrap();
    let (_, a_same) = checkpoint_actor(&config, &same, &device).unwrap();
    let (_, a_resumed) = checkpoint_actor(&config, &resumed, &device).unwrap();
    assert_eq!(a_same.payload(), a_resumed.payload());

    // The record of the parent, and the parent's metrics as the fork's first lines.
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(same.join("forked_from.json")).unwrap())
            .unwrap();
    assert_eq!(record["iteration"], 2);
    assert_eq!(record["config_hash"], format!("{:016x}", short.hash()));
    let (m_parent, m_fork) = (metrics(&parent), metrics(&same));
    assert_eq!(m_fork.len(), 4);
    assert_eq!(
        m_fork[..2]
            .iter()
            .map(|m| m.reward_per_step)
            .collect::<Vec<_>>(),
        m_parent
            .iter()
            .map(|m| m.reward_per_step)
            .collect::<Vec<_>>()
    );

    // A changed setting (refused by --resume) is what the fork trains under.
    let mut changed = config.clone();
    changed.ppo.epochs += 1;
    let other = tmp("fork_changed");
    run(&changed, &fork(&other)).unwrap();
    let (it, a_changed) = checkpoint_actor(&changed, &other, &device).unwrap();
    assert_eq!(it, 4);
    assert_ne!(a_changed.payload(), a_same.payload());
    assert_eq!(
        TrainConfig::load(&other.join("config.toml"))
            .unwrap()
            .hash(),
        changed.hash()
    );

    // Two starting points are refused, and so is a parent without a checkpoint.
    let both = RunOptions {
        init_actor: Some(parent.join("smoke.blob")),
        ..fork(&tmp("fork_both"))
    };
    let e = run(&config, &both).unwrap_err().to_string();
    assert!(e.contains("pass one"), "{e}");
    let orphan = RunOptions {
        fork_from: Some(tmp("fork_nothing")),
        ..options(&tmp("fork_orphan"), false, None)
    };
    let e = run(&config, &orphan).unwrap_err().to_string();
    assert!(e.contains("no checkpoint"), "{e}");
    for d in [parent, same, resumed, other] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// `run.select`: from its first iteration every evaluation also flies the validation, and the
/// exported blob is the candidate with the best validation (success, then crashes, then mean
/// lap), not the referee's stage-1 favourite, also across a resume; the validation's numbers
/// are the blob's own (re-flown here).
#[test]
fn a_selection_exports_the_validations_best_across_a_resume() {
    // The shipped pipeline at a tiny budget, fine-tuning the shipped policy with large fixed
    // steps: the candidates fly, and differ from one iteration to the next.
    let mut config = TrainConfig::parse(include_str!("../configs/stage1.toml")).unwrap();
    // The draws from the first iteration: the ramp's iterations lie past this budget.
    config.randomize_ramp = None;
    config.run.iterations = 8;
    config.run.checkpoint_every = 2;
    config.run.eval_every = 1;
    let select = Selection {
        spawn: sitl::referee::SpawnMode::AlongTrack,
        episodes: 6,
        seed: 7,
        from_iteration: 3,
        perturb: Vec::new(),
        jitter: None,
        referee_floor: None,
        race_bar: false,
    };
    config.run.select = Some(select.clone());
    config.env.num_envs = 64;
    config.ppo.steps_per_env = 24;
    config.ppo.learning_rate = 3e-3;
    config.ppo.desired_kl = None;
    config.ppo.init_std = 0.1;
    TrainConfig::parse(&toml::to_string(&config).unwrap()).unwrap();
    let out = tmp("select");
    let first = RunOptions {
        init_actor: Some(format!("{}/../policies/stage1.blob", env!("CARGO_MANIFEST_DIR")).into()),
        ..options(&out, false, Some(4))
    };
    assert!(run(&config, &first).unwrap().blob.is_none());
    let summary = run(&config, &options(&out, true, None)).unwrap();

    let metrics = metrics(&out);
    assert_eq!(metrics.len(), 8);
    for m in &metrics {
        assert!(m.eval_success_rate.is_some());
        assert_eq!(
            m.select_success_rate.is_some(),
            m.iteration >= 3,
            "{}",
            m.iteration
        );
    }
    let argmax = |key: &dyn Fn(&IterationMetrics) -> (f64, f64, f64)| {
        let mut best = &metrics[2];
        for m in &metrics[3..] {
            if key(m) > key(best) {
                best = m;
            }
        }
        best.iteration
    };
    let validation_key = |m: &IterationMetrics| {
        (
            m.select_success_rate.unwrap(),
            -m.select_crash_rate.unwrap(),
            -m.select_mean_lap_s.unwrap_or(f64::INFINITY),
        )
    };
    let referee_key = |m: &IterationMetrics| {
        (
            m.eval_success_rate.unwrap(),
            -m.eval_crash_rate.unwrap(),
            -m.eval_best_lap_s.unwrap_or(f64::INFINITY),
        )
    };
    let chosen = argmax(&validation_key);
    // The case this test is for: the two verdicts disagree.
    assert_ne!(
        chosen,
        argmax(&referee_key),
        "the validation and the referee agree here: pick another validation seed"
    );
    let best = &metrics[chosen as usize - 1];
    assert_eq!(summary.best.as_ref().map(|m| m.iteration), Some(chosen));
    let exported = std::fs::read(summary.blob.unwrap()).unwrap();
    let candidate = out
        .join("checkpoints")
        .join(format!("best_iter_{chosen:06}.blob"));
    assert!(exported == std::fs::read(candidate).unwrap());
    let bytes = firmware_core::blob::AlignedBytes::new(&exported);
    let blob = firmware_core::blob::Blob::parse(bytes.as_bytes()).unwrap();
    assert_eq!(blob.header().provenance.iterations, chosen);
    let validation = sitl::eval::report(
        &sitl::pilot::PilotSpec::from_blob("exported", &exported).unwrap(),
        None,
        &sitl::eval::EvalConfig {
            preset: config.preset(),
            episodes: select.episodes,
            seconds: 45.0,
            seed: select.seed,
            spawn: Some(sitl::referee::SpawnMode::AlongTrack),
            perturbation: sitl::perturb::Perturbation::NONE,
        },
    );
    // The same episodes; the means may be summed in another order (parallel episodes).
    let close = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) => (a - b).abs() <= 1e-12 * a.abs().max(1.0),
        (a, b) => a == b,
    };
    assert!(close(
        Some(validation.success_rate),
        best.select_success_rate
    ));
    assert!(close(Some(validation.crash_rate), best.select_crash_rate));
    assert!(close(validation.mean_lap_s, best.select_mean_lap_s));
    let _ = std::fs::remove_dir_all(out);
}

/// A corrupt latest checkpoint (a flipped byte in a network file, or a `state.json` whose
/// counters were edited) is reported and the previous one is resumed from, the lost
/// iterations redone; when no checkpoint is usable, the error says why.
#[test]
fn a_corrupt_checkpoint_falls_back_to_the_previous_one() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    let device = Device::flex().autodiff();
    let flip = |p: &Path| {
        let mut bytes = std::fs::read(p).unwrap();
        let i = bytes.len() / 2;
        bytes[i] ^= 0x10;
        std::fs::write(p, bytes).unwrap();
    };
    let edit = |p: &Path, from: &str, to: &str| {
        let text = std::fs::read_to_string(p).unwrap();
        assert!(text.contains(from), "{text}");
        std::fs::write(p, text.replace(from, to)).unwrap();
    };
    // A NaN written into a file with its checksum updated to match: only the load's own
    // finiteness check can catch it.
    let nan_with_checksum = |dir: &Path, file: &str| {
        let p = dir.join(file);
        let mut bytes = std::fs::read(&p).unwrap();
        let n = bytes.len();
        bytes[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
        std::fs::write(&p, &bytes).unwrap();
        let state = dir.join("state.json");
        let mut v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
        v["files"][file] = sitl::files::sha256_hex(&bytes).into();
        std::fs::write(&state, serde_json::to_string_pretty(&v).unwrap()).unwrap();
    };
    for corruption in [
        "flipped byte",
        "iteration",
        "learning rate",
        "non-finite moment",
    ] {
        let d = tmp(&format!("corrupt_{}", corruption.replace(' ', "_")));
        // Checkpoints at iterations 2 and 3 (the stop writes one).
        run(&config, &options(&d, false, Some(3))).unwrap();
        let latest = d.join("checkpoints").join("iter_000003");
        match corruption {
            "flipped byte" => flip(&latest.join("actor.bpk")),
            "iteration" => edit(
                &latest.join("state.json"),
                "\"iteration\": 3",
                "\"iteration\": 999999",
            ),
            "learning rate" => edit(
                &latest.join("state.json"),
                "\"learning_rate\": ",
                "\"learning_rate\": -",
            ),
            _ => nan_with_checksum(&latest, "fused_adam.safetensors"),
        }
        let (it, _) = checkpoint_actor(&config, &d, &device).unwrap();
        assert_eq!(it, 2, "{corruption}: the previous checkpoint is used");
        let s = run(&config, &options(&d, true, None)).unwrap();
        assert_eq!(s.iterations, 4);
        let its: Vec<u32> = metrics(&d).iter().map(|m| m.iteration).collect();
        assert_eq!(its, vec![1, 2, 3, 4], "{corruption}");
        let _ = std::fs::remove_dir_all(&d);
    }
    // Both checkpoints damaged: nothing to fall back to.
    let d = tmp("corrupt_both");
    run(&config, &options(&d, false, Some(3))).unwrap();
    for it in ["iter_000002", "iter_000003"] {
        flip(&d.join("checkpoints").join(it).join("critic.bpk"));
    }
    let e = run(&config, &options(&d, true, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("critic.bpk does not match its checksum"), "{e}");
    let _ = std::fs::remove_dir_all(&d);
}

/// Issue "faults": a rollout that cannot fit in memory (`steps_per_env = 1e8`) is refused
/// before anything is allocated or written, with the sizes and what to lower; before, it
/// grew until the kernel killed the trainer.
#[test]
fn a_run_too_big_for_memory_is_refused_before_it_starts() {
    let out = tmp("too_big");
    let text = CONFIG.replace("steps_per_env = 24", "steps_per_env = 100000000");
    assert_ne!(text, CONFIG, "smoke.toml's steps_per_env moved");
    let config = TrainConfig::parse(&text).unwrap();
    let started = std::time::Instant::now();
    let e = run(&config, &options(&out, false, None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("GiB is available"), "{e}");
    assert!(e.contains("lower env.num_envs or ppo.steps_per_env"), "{e}");
    assert!(started.elapsed().as_secs() < 5, "refused late");
    assert!(
        !out.join("checkpoints").exists(),
        "a refused run wrote checkpoints"
    );
}

/// `train --seed N` trains the config's recipe with another seed: the run's own config.toml
/// records it (so `--resume` from that file continues the same seed) and the run differs
/// from the config's seed.
#[test]
fn another_seed_from_the_command_line_is_recorded_and_resumes() {
    let bin = env!("CARGO_BIN_EXE_host-trainer");
    let config = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/smoke.toml");
    let train = |out: &Path, extra: &[&str]| {
        let status = std::process::Command::new(bin)
            .args(["train", "--quiet", "--out"])
            .arg(out)
            .args(extra)
            .stdout(std::process::Stdio::null())
            .status()
            .unwrap();
        assert!(status.success(), "{extra:?}");
    };
    let seeded = tmp("cli_seed_5");
    train(
        &seeded,
        &["--config", config, "--seed", "5", "--stop-after", "1"],
    );
    let recorded = TrainConfig::load(&seeded.join("config.toml")).unwrap();
    assert_eq!(recorded.run.seed, 5);
    let mut expected = TrainConfig::load(std::path::Path::new(config)).unwrap();
    expected.run.seed = 5;
    expected.env = expected.env_config(5);
    assert_eq!(
        recorded, expected,
        "the recipe with seed 5, nothing else changed"
    );
    let own = seeded.join("config.toml");
    train(&seeded, &["--config", own.to_str().unwrap(), "--resume"]);
    let plain = tmp("cli_seed_default");
    train(&plain, &["--config", config, "--stop-after", "1"]);
    let (a, b) = (metrics(&seeded), metrics(&plain));
    assert_eq!(
        a.len(),
        TrainConfig::parse(CONFIG).unwrap().run.iterations as usize
    );
    assert_ne!(
        a.first().map(|m| m.episode_return),
        b.first().map(|m| m.episode_return),
        "seed 5 trains another run than the config's own seed"
    );
}

/// `config` stopped after iteration 2 and resumed (into `tmp(name)`) ends where the
/// uninterrupted run in `whole` did: the same networks, bit for bit, and learning record.
fn assert_stopped_and_resumed_is(config: &TrainConfig, whole: &Path, name: &str) {
    let stopped = tmp(name);
    run(config, &options(&stopped, false, Some(2))).unwrap();
    run(config, &options(&stopped, true, None)).unwrap();
    let device = Device::flex().autodiff();
    let nets = |d: &Path| checkpoint_blob(config, d, &device).unwrap().1;
    assert!(nets(whole) == nets(&stopped), "{name}: the networks differ");
    assert_eq!(learning_record(whole), learning_record(&stopped), "{name}");
    let _ = std::fs::remove_dir_all(stopped);
}

/// A tiny row-G race (4 iterations of 16 envs × 20 steps, checkpoints every 2) against
/// `opponent`.
fn tiny_race(opponent: &str) -> TrainConfig {
    let mut race = TrainConfig::parse(include_str!("../configs/smoke_race.toml")).unwrap();
    race.run.row = 'G';
    race.run.iterations = 4;
    race.run.checkpoint_every = 2;
    race.run.eval_every = 4;
    race.run.eval_races = 1;
    race.env.num_envs = 16;
    race.ppo.steps_per_env = 20;
    if let Some(r) = &mut race.env.race {
        r.opponent = Path::new(env!("CARGO_MANIFEST_DIR")).join(opponent);
    }
    race
}

/// `[[opponent_curriculum]]`: until its iteration the training races fly against the
/// stage's opponent (the first iterations' record is that of a run racing it throughout),
/// then against `[race].opponent` (the record parts from that run's); a run stopped at the
/// change and resumed is the uninterrupted one bit for bit.
#[test]
fn an_opponent_curriculum_changes_the_opponent_at_its_iteration_and_resumes_bit_for_bit() {
    let stage1 = Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies/stage1.blob");
    let mut curriculum = tiny_race("../policies/stage1_guarded.blob");
    curriculum.opponent_curriculum = vec![host_trainer::config::CurriculumStage {
        opponent: stage1,
        until_iteration: 2,
    }];
    TrainConfig::parse(&toml::to_string(&curriculum).unwrap()).unwrap();
    let first_opponent = tiny_race("../policies/stage1.blob");
    let whole = tmp("curriculum-whole");
    run(&curriculum, &options(&whole, false, None)).unwrap();
    let longer = tmp("curriculum-longer");
    run(&first_opponent, &options(&longer, false, None)).unwrap();
    let (a, b) = (learning_record(&whole), learning_record(&longer));
    assert_eq!(a[..2], b[..2], "the first stage races stage1.blob in both");
    assert_ne!(a[2], b[2], "the third iteration races stage1_guarded.blob");

    assert_stopped_and_resumed_is(&curriculum, &whole, "curriculum-stopped");
    for d in [whole, longer] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// A fork of a `run.keep_best` run whose best evaluation comes before the fork exports that
/// actor: the parent's candidate is carried into the fork's directory.
#[test]
fn a_fork_exports_a_best_actor_from_before_the_fork() {
    // The shipped stage-1 policy, fine-tuned at a tiny budget: it flies the referee's
    // episode perfectly from the first evaluation, so no later one can be strictly better and
    // a tie goes to the earlier iteration.
    let mut config = TrainConfig::parse(include_str!("../configs/stage1.toml")).unwrap();
    // The draws from the first iteration: the ramp's iterations lie past this budget.
    config.randomize_ramp = None;
    config.run.iterations = 4;
    config.run.checkpoint_every = 2;
    config.run.keep_best = true;
    config.run.select = None;
    config.run.eval_every = 1;
    config.env.num_envs = 64;
    config.ppo.steps_per_env = 24;
    let mut short = config.clone();
    short.run.iterations = 2;
    let parent = tmp("fork_best_parent");
    let init = RunOptions {
        init_actor: Some(format!("{}/../policies/stage1.blob", env!("CARGO_MANIFEST_DIR")).into()),
        ..options(&parent, false, None)
    };
    let s = run(&short, &init).unwrap();
    assert_eq!(s.best.unwrap().eval_success_rate, Some(1.0));
    // The fork evaluates only its last iteration.
    config.run.eval_every = 4;
    let child = tmp("fork_best_child");
    let s = run(
        &config,
        &RunOptions {
            fork_from: Some(parent.clone()),
            ..options(&child, false, None)
        },
    )
    .unwrap();
    let best = s.best.expect("keep_best has a best").iteration;
    assert!(
        best <= 2,
        "the setup needs the parent's evaluation to stay the best, got iteration {best}"
    );
    let exported = std::fs::read(s.blob.unwrap()).unwrap();
    let parents =
        std::fs::read(parent.join(format!("checkpoints/best_iter_{best:06}.blob"))).unwrap();
    assert!(exported == parents);
    for d in [parent, child] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// `[randomize_ramp]`: before its first iteration no training spawn is randomised (the
/// record is that of the run without `env.randomize`), after it the draws fly (the record
/// parts from that run's), and a run stopped inside the ramp and resumed is the
/// uninterrupted one bit for bit.
#[test]
fn a_randomisation_ramp_starts_at_its_iteration_and_resumes_bit_for_bit() {
    let plain = TrainConfig::parse(CONFIG).unwrap();
    let mut ramp = plain.clone();
    ramp.env.randomize = Some(sitl::perturb::PerturbSpec::parse("latency=1,thrust=0.8").unwrap());
    ramp.randomize_ramp = Some(host_trainer::config::RandomizeRamp {
        from_iteration: 1,
        to_iteration: 3,
    });
    let ramp = TrainConfig::parse(&toml::to_string(&ramp).unwrap()).unwrap();
    assert_eq!((ramp.run.iterations, ramp.run.checkpoint_every), (4, 2));
    let whole = tmp("ramp-whole");
    run(&ramp, &options(&whole, false, None)).unwrap();
    let nominal = tmp("ramp-nominal");
    run(&plain, &options(&nominal, false, None)).unwrap();
    let (a, b) = (learning_record(&whole), learning_record(&nominal));
    assert_eq!(a[..2], b[..2], "iterations 0 and 1 randomise nothing");
    assert_ne!(a[2], b[2], "iteration 2 randomises half the spawns");

    assert_stopped_and_resumed_is(&ramp, &whole, "ramp-stopped");
    for d in [whole, nominal] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// `[ppo] critic = "privileged-mlp"` on a row-G race (fused update, the actor's windows
/// shared between two threads): the run trains, its critic learns from the privileged state
/// (another record than the LSTM critic's run), and a run stopped and resumed is the
/// uninterrupted one bit for bit (the critic's checkpoint and Adam state round-trip).
#[test]
fn a_privileged_critic_run_resumes_bit_for_bit() {
    let mut lstm = tiny_race("../policies/stage1.blob");
    lstm.ppo.update = host_trainer::config::UpdateKind::Fused;
    let mut privileged = lstm.clone();
    privileged.ppo.critic = host_trainer::config::CriticKind::PrivilegedMlp;
    let privileged = TrainConfig::parse(&toml::to_string(&privileged).unwrap()).unwrap();
    assert_ne!(privileged.hash(), lstm.hash());
    let whole = tmp("privileged-whole");
    run(&privileged, &options(&whole, false, None)).unwrap();
    let with_lstm = tmp("privileged-lstm");
    run(&lstm, &options(&with_lstm, false, None)).unwrap();
    let (a, b) = (learning_record(&whole), learning_record(&with_lstm));
    assert_eq!(a.len(), 4);
    assert_ne!(a, b, "the critic made no difference");
    assert_stopped_and_resumed_is(&privileged, &whole, "privileged-stopped");
    for d in [whole, with_lstm] {
        let _ = std::fs::remove_dir_all(d);
    }
}

/// Issue "faults": a second trainer on a run directory that a trainer is writing (a
/// `--resume` typed while the run still goes) is refused with the holder named, and writes
/// nothing: the running trainer's metrics and checkpoints stay whole. Once the lock is
/// released (the first trainer ended or died), the resume runs.
#[test]
fn a_second_trainer_on_a_live_run_is_refused() {
    let config = TrainConfig::parse(CONFIG).unwrap();
    let out = tmp("locked");
    run(&config, &options(&out, false, Some(2))).unwrap();
    let before = std::fs::read(out.join("metrics.jsonl")).unwrap();
    let held = host_trainer::run_dir::lock(&out).unwrap();
    let e = run(&config, &options(&out, true, None))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("another trainer is writing this run (pid "),
        "{e}"
    );
    assert_eq!(std::fs::read(out.join("metrics.jsonl")).unwrap(), before);
    assert_eq!(
        std::fs::read_to_string(out.join("checkpoints/latest"))
            .unwrap()
            .trim(),
        "iter_000002"
    );
    drop(held);
    let s = run(&config, &options(&out, true, None)).unwrap();
    assert_eq!(s.iterations, 4);
    let _ = std::fs::remove_dir_all(out);
}
