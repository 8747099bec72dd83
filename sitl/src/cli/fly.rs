//! `sitl fly`: one time trial from the stage-1 spawn with every lap.

use super::{Common, load};
use clap::Args;
use sitl::eval::{EvalConfig, evaluate};
use sitl::pilot::PilotSpec;
use sitl::referee::SpawnMode;

/// The arguments of `sitl fly`.
#[derive(Args)]
pub struct FlyArgs {
    /// The pilot: a policy blob file, or "baseline".
    #[arg(long, default_value = "baseline")]
    ego: String,
    #[command(flatten)]
    common: Common,
    /// Cruise speed of the baseline controller (m/s).
    #[arg(long, value_parser = parse_cruise)]
    cruise: Option<f32>,
}

fn parse_cruise(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 30.0 => Ok(v),
        _ => Err("must be a speed in (0, 30] m/s".into()),
    }
}

/// Runs `sitl fly`: one time trial and its gates, crashes and laps.
pub fn run(args: FlyArgs) -> Result<(), String> {
    let preset = args.common.preset;
    let mut ego = load(&args.ego, &preset, "--ego")?;
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
        perturbation: sitl::perturb::Perturbation::NONE,
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
