//! `sitl eval`: a pilot's Table-1 row over many seeded episodes, in-process.

use super::{Contest, write};
use clap::Args;
use sitl::eval::{Report, evaluate};
use sitl::pilot::PilotSpec;
use std::path::PathBuf;

/// The arguments of `sitl eval`.
#[derive(Args)]
#[command(mut_arg("ego", |a| a.required(true).help(
    "The ego: a policy blob file, or \"baseline\" for the classical controller \
     (\"baseline:CRUISE_MPS[:OFFSET_M]\" sets its cruise speed and a line offset to the left)"
)))]
#[command(mut_arg("opponent", |a| a.help(
    "An opponent to race (a blob or \"baseline[:CRUISE_MPS[:OFFSET_M]]\"); without one the \
     ego flies a time trial"
)))]
pub struct EvalArgs {
    #[command(flatten)]
    contest: Contest,
    /// Also draw the first episode from above (paths and gates) as SVG to this file.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Also write every episode as a 3-D replay to this file: one self-contained HTML page
    /// (drones, gates, a timeline of the events, speed and lead) that opens in any browser.
    #[arg(long, value_name = "FILE.html")]
    replay: Option<PathBuf>,
}

/// Runs `sitl eval`.
pub fn run(args: EvalArgs) -> Result<(), String> {
    let contest = &args.contest;
    let preset = contest.common.preset;
    let (ego, opponent) = contest.pilots()?;
    let config = contest.eval_config();
    let started = std::time::Instant::now();
    let record = args.plot.is_some() || contest.scoring.trace.is_some() || args.replay.is_some();
    let episodes = evaluate(&ego, opponent.as_ref(), &config, record);
    let pilots: Vec<String> = core::iter::once(ego.describe())
        .chain(opponent.as_ref().map(PilotSpec::describe))
        .collect();
    contest.scoring.write_traces(&pilots, &preset, &episodes)?;
    if let Some(path) = &args.replay {
        let world = config.world(opponent.is_some());
        contest
            .scoring
            .write_replay(path, &world.track, &pilots, &preset, &episodes)?;
    }
    if let (Some(path), Some(first)) = (&args.plot, episodes.first()) {
        let title = format!(
            "{}{}, episode 0 ({} preset, seed {})",
            ego.describe(),
            opponent
                .as_ref()
                .map(|o| format!(" vs {}", o.describe()))
                .unwrap_or_default(),
            preset.name,
            contest.scoring.seed
        );
        let svg = sitl::plot::top_down(
            &config.world(opponent.is_some()).track,
            &first.trace,
            &title,
        );
        write(path, svg.as_bytes())?;
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
    if let Some(path) = &contest.scoring.json {
        write(path, report.to_json().as_bytes())?;
    }
    Ok(())
}
