//! `host-trainer`: train racing policies and export them as flash blobs.
//!
//! ```text
//! cargo run --release -p host-trainer -- train --config host-trainer/configs/stage1.toml --out runs/stage1
//! cargo run --release -p host-trainer -- train --config runs/stage1/config.toml --out runs/stage1 --resume
//! cargo run --release -p host-trainer -- import-rslrl --safetensors actor.safetensors --row A --out a.blob
//! ```

use clap::{Parser, Subcommand, ValueEnum};
use firmware_core::blob::{Provenance, WeightDtype, convert_bytes};
use firmware_core::observation::ObservationSpec;
use firmware_core::policy::{Architecture, TableRow};
use host_trainer::config::TrainConfig;
use host_trainer::metrics::lap_text;
use host_trainer::train::{RunOptions, run};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "host-trainer",
    about = "Train Overtake racing policies and export them as blobs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Where the PPO update runs.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum Backend {
    /// burn's pure-Rust CPU backend (default).
    Flex,
    /// NVIDIA GPU (build with `--features cuda`).
    Cuda,
    /// Any GPU through wgpu (build with `--features wgpu`).
    Wgpu,
}

#[derive(Subcommand)]
enum Command {
    /// Train a policy with PPO (a progress bar, metrics.jsonl, checkpoints, curves, a blob).
    Train {
        /// The run's TOML configuration (host-trainer/configs/*.toml).
        #[arg(long)]
        config: PathBuf,
        /// Output directory (created; a directory holding a run needs --resume).
        #[arg(long)]
        out: PathBuf,
        /// Continue the run in --out from its latest checkpoint.
        #[arg(long)]
        resume: bool,
        /// Backend of the update.
        #[arg(long, value_enum, default_value = "flex")]
        device: Backend,
        /// No progress bar; one line per referee evaluation instead.
        #[arg(long)]
        quiet: bool,
        /// Stop after this many iterations of this invocation (a checkpoint is written).
        #[arg(long)]
        stop_after: Option<u32>,
        /// Train with this seed instead of the config's `run.seed` (another seed of the same
        /// recipe; the run's own config.toml records it, so `--resume` from it needs none).
        #[arg(long)]
        seed: Option<u64>,
        /// Start the actor from this row-A blob (fine-tuning) instead of a random
        /// initialisation and the config's warm start.
        #[arg(long)]
        init_actor: Option<PathBuf>,
        /// Start from the latest checkpoint of the run in this directory (networks, σ, Adam,
        /// iteration, metrics) and train on under --config, which may change anything but
        /// the networks: a fork, recorded in --out/forked_from.json.
        #[arg(long)]
        fork_from: Option<PathBuf>,
    },
    /// Export the actor of a run's latest checkpoint as a blob (a run still going, or
    /// stopped before its budget).
    Export {
        /// The run's config (its `config.toml`).
        #[arg(long)]
        config: PathBuf,
        /// The run's output directory.
        #[arg(long)]
        out: PathBuf,
        /// The blob to write.
        #[arg(long)]
        blob: PathBuf,
        /// Weight storage of the blob: f32, or i8 (every matrix row quantised to int8 with
        /// an f32 scale: 3.8x smaller, for 1 MB-flash boards; see docs/RESULTS.md for what
        /// it costs in accuracy).
        #[arg(long, default_value = "f32", value_parser = parse_dtype)]
        dtype: WeightDtype,
    },
    /// Convert an RSL-RL actor (safetensors with RSL-RL's parameter names) into a blob.
    ImportRslrl {
        /// The safetensors file (e.g. converted from rsl_rl's model_*.pt state dict).
        #[arg(long)]
        safetensors: PathBuf,
        /// Table 1 row of the actor (A-G).
        #[arg(long)]
        row: char,
        /// The blob to write.
        #[arg(long)]
        out: PathBuf,
        /// Name recorded in the blob's provenance.
        #[arg(long, default_value = "rsl-rl import")]
        name: String,
        /// The own-velocity scale (m/s) of the observations the actor was trained on
        /// (`make_vec_env(velocity_scale_mps=...)`; the paper's is 3), recorded in the blob so
        /// the controller observes as training did.
        #[arg(long, default_value_t = 3.0)]
        velocity_scale_mps: f32,
        /// The actor was trained on observations folded by the track's mirror
        /// (`make_vec_env(fold_mirror=True)`, host-trainer's `env.fold_mirror`); the blob records
        /// it so the controller folds as training did.
        #[arg(long)]
        fold_mirror: bool,
    },
    /// Write a blob's actor as an RSL-RL safetensors file (RSL-RL's parameter names), to
    /// start an RSL-RL run from it; the inverse of import-rslrl.
    ExportRslrl {
        /// The blob (f32 or int8; int8 weights are dequantised).
        #[arg(long)]
        blob: PathBuf,
        /// The safetensors file to write.
        #[arg(long)]
        out: PathBuf,
        /// The action noise σ written as `std` (a blob has none).
        #[arg(long, default_value_t = 1.0)]
        std: f32,
    },
}

fn device(b: Backend) -> Result<burn::tensor::Device, String> {
    match b {
        Backend::Flex => Ok(burn::tensor::Device::flex().autodiff()),
        #[cfg(feature = "cuda")]
        Backend::Cuda => Ok(burn::tensor::Device::cuda(0).autodiff()),
        #[cfg(feature = "wgpu")]
        Backend::Wgpu => {
            Ok(burn::tensor::Device::wgpu(burn::tensor::DeviceKind::DiscreteGpu(0)).autodiff())
        }
        #[allow(unreachable_patterns)]
        other => Err(format!(
            "--device {other:?}: this binary was built without that backend; rebuild with `--features {}`",
            format!("{other:?}").to_lowercase()
        )),
    }
}

fn parse_dtype(s: &str) -> Result<WeightDtype, String> {
    WeightDtype::from_name(s).ok_or_else(|| format!("`{s}`: the dtypes are f32 and i8"))
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Train {
            config,
            out,
            resume,
            device: backend,
            quiet,
            stop_after,
            seed,
            init_actor,
            fork_from,
        } => device(backend).and_then(|device| {
            train(
                &config,
                seed,
                RunOptions {
                    out,
                    resume,
                    device,
                    progress: !quiet,
                    stop_after,
                    init_actor,
                    fork_from,
                },
            )
        }),
        Command::Export {
            config,
            out,
            blob,
            dtype,
        } => export(&config, &out, &blob, dtype),
        Command::ImportRslrl {
            safetensors,
            row,
            out,
            name,
            velocity_scale_mps,
            fold_mirror,
        } => import_rslrl(
            &safetensors,
            row,
            &out,
            &name,
            velocity_scale_mps,
            fold_mirror,
        ),
        Command::ExportRslrl { blob, out, std } => export_rslrl(&blob, &out, std),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// `train`: runs (or resumes) the run of `config` (with `seed` instead of its own, if given)
/// and prints where it ended.
fn train(config: &Path, seed: Option<u64>, options: RunOptions) -> Result<(), String> {
    let mut cfg = TrainConfig::load(config).map_err(|e| format!("{}: {e}", config.display()))?;
    if let Some(seed) = seed {
        cfg.run.seed = seed;
        cfg.env = cfg.env_config(seed);
    }
    println!(
        "training '{}' (row {}, seed {}, {} envs x {} steps = {} samples per iteration, {} iterations, config hash {:016x}) into {}",
        cfg.run.name,
        cfg.run.row,
        cfg.run.seed,
        cfg.env.num_envs,
        cfg.ppo.steps_per_env,
        cfg.samples_per_iteration(),
        cfg.run.iterations,
        cfg.hash(),
        options.out.display()
    );
    let s = run(&cfg, &options).map_err(|e| e.to_string())?;
    let m = &s.last;
    println!(
        "{} iterations, {:.0} s of training ({:.1} min), {} samples",
        s.iterations,
        s.wall_s,
        s.wall_s / 60.0,
        m.samples
    );
    let m = match &s.best {
        Some(b) => {
            match (&cfg.run.select, b.select_success_rate) {
                (Some(sel), Some(sr)) => println!(
                    "exported the actor of iteration {} (run.keep_best: the best of iterations {}-{} on {} {} {}{}, seed {}{}: success {sr:.3}, crashes {:.3} /s, mean lap {})",
                    b.iteration,
                    sel.from_iteration,
                    s.iterations,
                    sel.episodes,
                    sel.spawn.name(),
                    if cfg.env.race.is_some() {
                        "races"
                    } else {
                        "spawns"
                    },
                    match sel.perturb.len() {
                        0 => String::new(),
                        1 => " under its perturbation".to_string(),
                        n => format!(" under each of {n} perturbations"),
                    },
                    sel.seed,
                    match (sel.referee_floor, sel.race_bar) {
                        (Some(f), true) => format!(
                            ", the referee at {f} or more and its races meeting issue race's bar first"
                        ),
                        (Some(f), false) => format!(", the referee at {f} or more first"),
                        (None, true) => {
                            ", the referee's races meeting issue race's bar first".to_string()
                        }
                        (None, false) => String::new(),
                    },
                    b.select_crash_rate.unwrap_or(0.0),
                    lap_text(b.select_mean_lap_s)
                ),
                _ => println!(
                    "exported the actor of iteration {} (run.keep_best: the referee's best)",
                    b.iteration
                ),
            }
            b
        }
        None => m,
    };
    if let Some(sr) = m.eval_success_rate {
        let what = match &cfg.env.race {
            None => "45 s from the stage-1 spawn".to_string(),
            Some(r) => format!(
                "{} races of 45 s against {}, seed {}",
                cfg.run.eval_races,
                r.opponent.display(),
                cfg.run.eval_seed
            ),
        };
        let overtakes = match (m.eval_overtakes, m.eval_sustained_overtakes) {
            (Some(o), Some(s)) => format!(
                ", {o} overtakes ({s} sustained{}){}",
                match sitl::eval::GateOvertakes::gates_held(&m.eval_overtakes_by_gate) {
                    0 => String::new(),
                    n => format!(" at {n} gates"),
                },
                m.eval_win_rate
                    .map(|w| format!(", win rate {w:.3}"))
                    .unwrap_or_default()
            ),
            _ => String::new(),
        };
        println!(
            "referee ({what}): success {:.3}, crashes {:.3} /s, best lap {}{overtakes}",
            sr,
            m.eval_crash_rate.unwrap_or(0.0),
            lap_text(m.eval_best_lap_s)
        );
    }
    match &s.blob {
        Some(p) => println!("policy: {}", p.display()),
        None => println!(
            "stopped after iteration {} of {}: wrote a checkpoint ({}) and no blob; continue with --resume",
            s.iterations,
            cfg.run.iterations,
            options.out.join("checkpoints").display()
        ),
    }
    Ok(())
}

/// `export-rslrl`: the blob's actor under RSL-RL's names.
fn export_rslrl(blob: &Path, out: &Path, std: f32) -> Result<(), String> {
    let raw = std::fs::read(blob).map_err(|e| format!("{}: {e}", blob.display()))?;
    let bytes = firmware_core::blob::AlignedBytes::new(&raw);
    let parsed = firmware_core::blob::Blob::parse(bytes.as_bytes())
        .map_err(|e| format!("{}: {e}", blob.display()))?;
    let arch = &parsed.header().architecture;
    let weights = parsed.dequantized();
    let std = vec![std; usize::from(arch.action_dim)];
    let file = host_trainer::rslrl::export_actor(arch, &weights, Some(&std))
        .map_err(|e| format!("{}: {e}", blob.display()))?;
    sitl::files::write_atomically(out, &file).map_err(|e| format!("{}: {e}", out.display()))?;
    println!(
        "{}: {} weights -> {} (RSL-RL names)",
        blob.display(),
        weights.len(),
        out.display()
    );
    Ok(())
}

/// `export`: the actor of the latest checkpoint of the run in `out` as a blob.
fn export(config: &Path, out: &Path, blob: &Path, dtype: WeightDtype) -> Result<(), String> {
    let cfg = TrainConfig::load(config).map_err(|e| format!("{}: {e}", config.display()))?;
    let device = burn::tensor::Device::flex().autodiff();
    let (iteration, bytes) =
        host_trainer::latest::checkpoint_blob(&cfg, out, &device).map_err(|e| e.to_string())?;
    let bytes = match dtype {
        WeightDtype::F32 => bytes,
        WeightDtype::I8 => convert_bytes(&bytes, dtype).map_err(|e| e.to_string())?,
    };
    sitl::files::write_atomically(blob, &bytes).map_err(|e| format!("{}: {e}", blob.display()))?;
    println!(
        "{}: the actor of iteration {iteration} -> {} ({} bytes, {})",
        out.display(),
        blob.display(),
        bytes.len(),
        dtype.name()
    );
    Ok(())
}

/// `import-rslrl`: an RSL-RL actor as a blob of Table 1 row `r`.
fn import_rslrl(
    safetensors: &Path,
    r: char,
    out: &Path,
    name: &str,
    velocity_scale_mps: f32,
    fold_mirror: bool,
) -> Result<(), String> {
    let row =
        TableRow::from_letter(r).ok_or_else(|| format!("--row {r}: not a Table 1 row A-G"))?;
    if !(velocity_scale_mps.is_finite() && velocity_scale_mps > 0.0) {
        return Err(format!(
            "--velocity-scale-mps {velocity_scale_mps}: expected a positive speed"
        ));
    }
    let mut observation = ObservationSpec::paper(row.observation_layout()).with_fold(fold_mirror);
    observation.velocity_scale_mps = velocity_scale_mps;
    let arch = Architecture::table1(row);
    let bytes =
        std::fs::read(safetensors).map_err(|e| format!("{}: {e}", safetensors.display()))?;
    let weights = host_trainer::rslrl::import_actor(&bytes, &arch)
        .map_err(|e| format!("{}: {e}", safetensors.display()))?;
    let mut provenance = Provenance::default();
    provenance
        .name
        .push_str(name)
        .map_err(|_| "--name: at most 32 bytes".to_string())?;
    let header = host_trainer::export::blob_header(row, provenance, observation);
    let blob =
        firmware_core::blob::encode(&header, &weights).map_err(|e| format!("export: {e:?}"))?;
    sitl::files::write_atomically(out, &blob).map_err(|e| format!("{}: {e}", out.display()))?;
    println!(
        "{}: row {r} actor, {} weights -> {} ({} bytes)",
        safetensors.display(),
        weights.len(),
        out.display(),
        blob.len()
    );
    Ok(())
}
