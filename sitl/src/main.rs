//! `sitl`: fly controllers in the simulated world.
//!
//! `cargo run --release -p sitl -- fly [--preset paper|nominal|realistic] [--seconds 45]
//! [--cruise MPS]` flies the classical baseline controller on the figure-8 and prints the
//! time trial's gates, crashes and laps.

use firmware_core::PAPER_CONTROL_PERIOD_NS;
use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::track::Track;
use sitl::dynamics::Preset;
use std::process::ExitCode;

const USAGE: &str =
    "usage: sitl fly [--preset paper|nominal|realistic] [--seconds S] [--cruise M_PER_S]";

fn parse(args: &[String]) -> Result<(Preset, f32, Option<f32>), String> {
    let mut it = args.iter();
    match it.next().map(String::as_str) {
        Some("fly") => {}
        Some(other) => return Err(format!("unknown command '{other}'\n{USAGE}")),
        None => return Err(USAGE.to_string()),
    }
    let (mut preset, mut seconds, mut cruise) = (Preset::paper(), 45.0f32, None);
    while let Some(flag) = it.next() {
        let mut value = || {
            it.next()
                .ok_or_else(|| format!("{flag} needs a value\n{USAGE}"))
        };
        match flag.as_str() {
            "--preset" => {
                let name = value()?;
                preset = Preset::by_name(name).ok_or_else(|| {
                    format!("unknown preset '{name}' (paper, nominal, realistic)")
                })?;
            }
            "--seconds" => {
                seconds = value()?
                    .parse()
                    .map_err(|_| "--seconds needs a number".to_string())?;
                if !(seconds > 0.0 && seconds <= 3600.0) {
                    return Err("--seconds must be in (0, 3600]".into());
                }
            }
            "--cruise" => {
                let v: f32 = value()?
                    .parse()
                    .map_err(|_| "--cruise needs a number (m/s)".to_string())?;
                if !(v > 0.0 && v <= 30.0) {
                    return Err("--cruise must be in (0, 30] m/s".into());
                }
                cruise = Some(v);
            }
            "-h" | "--help" => return Err(USAGE.to_string()),
            other => return Err(format!("unknown flag '{other}'\n{USAGE}")),
        }
    }
    Ok((preset, seconds, cruise))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (preset, seconds, cruise) = match parse(&args) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    let mut config = if preset.thrust_scale < 1.0 {
        BaselineConfig::paper()
    } else {
        BaselineConfig::nominal()
    };
    if let Some(c) = cruise {
        config.cruise_speed_mps = c;
    }
    let track = Track::figure_eight();
    let mut pilot = BaselineController::new(config, track);
    let dt = PAPER_CONTROL_PERIOD_NS as f32 * 1e-9;
    let s = sitl::time_trial::fly(&mut pilot, &track, &preset, seconds, dt);
    println!(
        "baseline controller, preset '{}', cruise {:.1} m/s, {:.0} s simulated",
        preset.name, config.cruise_speed_mps, s.sim_seconds
    );
    println!(
        "  gates passed      {} / {} encountered (success {:.3})",
        s.gates_passed,
        s.gates_encountered,
        s.success_rate()
    );
    println!(
        "  crashes           {} ({:.3} /s)",
        s.crashes,
        s.crash_rate_per_s()
    );
    let laps: Vec<String> = s.lap_times_s.iter().map(|t| format!("{t:.2}")).collect();
    println!(
        "  laps (s)          {}",
        if laps.is_empty() {
            "none".into()
        } else {
            laps.join(", ")
        }
    );
    match s.best_lap_s() {
        Some(b) => println!("  best lap          {b:.2} s"),
        None => println!("  best lap          DNF"),
    }
    ExitCode::SUCCESS
}
