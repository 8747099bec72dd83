//! `sitl int8-check`: what converting an f32 blob to int8 costs.

use super::{Contest, load_opponent, write};
use clap::Args;
use std::process::ExitCode;

/// The arguments of `sitl int8-check`.
#[derive(Args)]
#[command(mut_arg("ego", |a| a.required(true).help("The f32 policy blob")))]
#[command(mut_arg("opponent", |a| a.help(
    "The opponent (a blob or \"baseline[...]\"); without one, time trials"
)))]
pub struct Int8CheckArgs {
    #[command(flatten)]
    contest: Contest,
}

/// Runs `sitl int8-check`.
pub fn run(args: Int8CheckArgs) -> Result<ExitCode, String> {
    let contest = &args.contest;
    let preset = contest.common.preset;
    let ego = contest.required_ego()?;
    let raw = std::fs::read(ego).map_err(|e| format!("--ego {ego}: {e}"))?;
    let opponent = load_opponent(contest.opponent.as_deref(), &preset)?;
    let config = contest.eval_config();
    let started = std::time::Instant::now();
    let c = sitl::quant::compare(&raw, opponent.as_ref(), &config)
        .map_err(|e| format!("--ego {ego}: {e}"))?;
    let e = &c.action_error;
    println!(
        "{}: f32 {} bytes -> int8 {} bytes ({:.2}x smaller)",
        ego,
        c.blob_bytes[0],
        c.blob_bytes[1],
        c.blob_bytes[0] as f64 / c.blob_bytes[1] as f64
    );
    println!(
        "action error of int8 on the f32 policy's observations ({} episodes, {} steps x 4 actions): max {:.4}, mean {:.5} (clipped actions in [-1, 1]); unclipped means max {:.4}",
        config.episodes, e.steps, e.max_abs, e.mean_abs, e.max_abs_unclipped
    );
    println!("\nf32:\n{}", c.f32_report.table());
    println!("int8:\n{}", c.int8_report.table());
    let within = c.within_f32_intervals();
    println!(
        "int8 success rate and crash rate {} the f32 blob's 95% intervals ({:.1} s wall-clock)",
        if within {
            "lie inside"
        } else {
            "do NOT lie inside"
        },
        started.elapsed().as_secs_f64()
    );
    if let Some(path) = &contest.scoring.json {
        let json = serde_json::to_string_pretty(&c).map_err(|e| e.to_string())?;
        write(path, json.as_bytes())?;
    }
    if e.replay_mismatches > 0 {
        return Err(format!(
            "{} steps where the replayed f32 policy disagreed with the controller: the measurement is broken",
            e.replay_mismatches
        ));
    }
    Ok(ExitCode::SUCCESS)
}
