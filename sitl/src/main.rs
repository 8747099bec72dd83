//! `sitl`: fly and score controllers in the simulated world.
//!
//! - `sitl eval --ego <blob|baseline> [--opponent <blob|baseline>] [--preset paper]
//!   [--episodes 20] [--seconds 45] [--seed 0] [--spawn stage1|stage2|along-track]
//!   [--json out.json] [--plot out.svg]`: the referee's Table-1 row over many seeded
//!   episodes, in-process.
//! - `sitl fly [--ego baseline] [--preset paper] [--seconds 45] [--cruise M_PER_S]`: one
//!   time trial from the stage-1 spawn with every lap time printed.

use clap::{Args, Parser, Subcommand};
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, Report, evaluate};
use sitl::pilot::PilotSpec;
use sitl::referee::{EPISODE_SECONDS, SpawnMode};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "sitl",
    version,
    about = "Fly and score drone-racing controllers in the simulated world"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Score a pilot over many seeded 45 s episodes (in-process, no MAVLink) and print its
    /// Table-1 row with 95% intervals.
    Eval(EvalArgs),
    /// Fly one time trial from the stage-1 spawn and print every lap.
    Fly(FlyArgs),
}

#[derive(Args)]
struct Common {
    /// Dynamics preset: paper (half propeller force, as the paper's simulator), nominal or
    /// realistic.
    #[arg(long, default_value = "paper", value_parser = parse_preset)]
    preset: Preset,
    /// Simulated seconds per episode.
    #[arg(long, default_value_t = EPISODE_SECONDS, value_parser = parse_seconds)]
    seconds: f32,
}

#[derive(Args)]
struct EvalArgs {
    /// The ego: a policy blob file, or "baseline" for the classical controller
    /// ("baseline:CRUISE_MPS[:OFFSET_M]" sets its cruise speed and a line offset to the left).
    #[arg(long)]
    ego: String,
    /// An opponent to race (a blob or "baseline[:CRUISE_MPS[:OFFSET_M]]"); without one the
    /// ego flies a time trial.
    #[arg(long)]
    opponent: Option<String>,
    #[command(flatten)]
    common: Common,
    /// Number of episodes.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    episodes: u32,
    /// Seed of the spawn draws; episode i uses stream i of it.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where drones start and restart: stage1 (time trials' default), stage2 (races'
    /// default), or along-track.
    #[arg(long, value_parser = parse_spawn)]
    spawn: Option<SpawnMode>,
    /// Also write the report as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also draw the first episode from above (paths and gates) as SVG to this file.
    #[arg(long)]
    plot: Option<PathBuf>,
}

#[derive(Args)]
struct FlyArgs {
    /// The pilot: a policy blob file, or "baseline".
    #[arg(long, default_value = "baseline")]
    ego: String,
    #[command(flatten)]
    common: Common,
    /// Cruise speed of the baseline controller (m/s).
    #[arg(long, value_parser = parse_cruise)]
    cruise: Option<f32>,
}

fn parse_preset(s: &str) -> Result<Preset, String> {
    Preset::by_name(s).ok_or_else(|| format!("unknown preset '{s}' (paper, nominal, realistic)"))
}

fn parse_spawn(s: &str) -> Result<SpawnMode, String> {
    SpawnMode::by_name(s)
        .ok_or_else(|| format!("unknown spawn '{s}' (stage1, stage2, along-track)"))
}

fn parse_seconds(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 3600.0 => Ok(v),
        _ => Err("must be a number of seconds in (0, 3600]".into()),
    }
}

fn parse_cruise(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 30.0 => Ok(v),
        _ => Err("must be a speed in (0, 30] m/s".into()),
    }
}

fn eval(args: EvalArgs) -> Result<(), String> {
    let preset = args.common.preset;
    let ego = PilotSpec::load(&args.ego, &preset).map_err(|e| format!("--ego: {e}"))?;
    let opponent = args
        .opponent
        .as_deref()
        .map(|o| PilotSpec::load(o, &preset).map_err(|e| format!("--opponent: {e}")))
        .transpose()?;
    if opponent.is_none() && ego.needs_opponent() {
        return Err(format!(
            "--ego {} observes an opponent; race it with --opponent <blob|baseline>",
            args.ego
        ));
    }
    let config = EvalConfig {
        preset,
        episodes: args.episodes,
        seconds: args.common.seconds,
        seed: args.seed,
        spawn: args.spawn,
    };
    let started = std::time::Instant::now();
    let episodes = evaluate(&ego, opponent.as_ref(), &config, args.plot.is_some());
    if let (Some(path), Some(first)) = (&args.plot, episodes.first()) {
        let title = format!(
            "{}{}, episode 0 ({} preset, seed {})",
            ego.describe(),
            opponent
                .as_ref()
                .map(|o| format!(" vs {}", o.describe()))
                .unwrap_or_default(),
            preset.name,
            args.seed
        );
        let svg = sitl::plot::top_down(
            &config.world(opponent.is_some()).track,
            &first.trace,
            &title,
        );
        sitl::files::write_atomically(path, svg.as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    let metrics: Vec<_> = episodes.into_iter().map(|e| e.metrics).collect();
    let report = Report::new(&ego, opponent.as_ref(), &config, &metrics);
    print!("{}", report.table());
    eprintln!(
        "({} episodes, {:.0} simulated s, in {:.2} s wall-clock)",
        report.episodes,
        report.sim_seconds,
        started.elapsed().as_secs_f64()
    );
    if let Some(path) = args.json {
        sitl::files::write_atomically(&path, report.to_json().as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

/// Writes `bytes` to a temporary file beside `path` and renames it over `path`: a reader
/// never sees half a file.
fn fly(args: FlyArgs) -> Result<(), String> {
    let preset = args.common.preset;
    let mut ego = PilotSpec::load(&args.ego, &preset).map_err(|e| format!("--ego: {e}"))?;
    if let (PilotSpec::Baseline(c), Some(v)) = (&mut ego, args.cruise) {
        c.cruise_speed_mps = v;
    } else if args.cruise.is_some() {
        return Err("--cruise applies to the baseline only".into());
    }
    if ego.needs_opponent() {
        return Err(format!(
            "--ego {} observes an opponent; race it with `sitl eval --opponent`",
            args.ego
        ));
    }
    let config = EvalConfig {
        preset,
        episodes: 1,
        seconds: args.common.seconds,
        seed: 0,
        spawn: Some(SpawnMode::Stage1),
    };
    let episodes = evaluate(&ego, None, &config, false);
    let m = episodes
        .first()
        .map(|e| e.metrics.clone())
        .unwrap_or_default();
    println!(
        "{}, preset '{}', {:.0} s simulated from the stage-1 spawn",
        ego.describe(),
        preset.name,
        m.sim_seconds
    );
    println!(
        "  gates passed      {} / {} encountered (success {:.3})",
        m.gates_passed,
        m.gates_encountered,
        m.success_rate()
    );
    println!(
        "  crashes           {} ({:.3} /s)",
        m.crashes,
        m.crash_rate_per_s()
    );
    let laps: Vec<String> = m.lap_times_s.iter().map(|t| format!("{t:.2}")).collect();
    println!(
        "  laps (s)          {}",
        if laps.is_empty() {
            "none".into()
        } else {
            laps.join(", ")
        }
    );
    match m.best_lap_s() {
        Some(b) => println!("  best lap          {b:.2} s"),
        None => println!("  best lap          DNF"),
    }
    Ok(())
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Eval(a) => eval(a),
        Command::Fly(a) => fly(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
