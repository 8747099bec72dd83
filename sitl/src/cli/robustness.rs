//! `sitl robustness`: a pilot's scores under the standard perturbations, f32 and int8.

use super::{Contest, write};
use clap::Args;

/// The arguments of `sitl robustness`.
#[derive(Args)]
#[command(mut_arg("ego", |a| a.required(true).help(
    "The pilot: a policy blob (an f32 blob is also flown as its int8 conversion) or \"baseline\""
)))]
#[command(mut_arg("opponent", |a| a.help(
    "An opponent to race (a blob or \"baseline\"); without one, time trials"
)))]
pub struct RobustnessArgs {
    #[command(flatten)]
    contest: Contest,
    /// Also write the tables as Markdown to this file.
    #[arg(long)]
    markdown: Option<std::path::PathBuf>,
}

/// Runs `sitl robustness`.
pub fn run(args: RobustnessArgs) -> Result<(), String> {
    let contest = &args.contest;
    if !contest.scoring.perturbation().is_none() {
        return Err(
            "--jitter and --perturb do not apply here: the sweep flies its own levels".into(),
        );
    }
    let ego_spec = contest.required_ego()?;
    let (ego, opponent) = contest.pilots()?;
    let int8 = ego
        .int8(&format!("{ego_spec} (int8)"))
        .map_err(|e| format!("--ego {ego_spec}: {e}"))?;
    let config = contest.eval_config();
    let started = std::time::Instant::now();
    let levels = sitl::robustness::table_levels().len()
        + sitl::robustness::ladders()
            .iter()
            .map(|l| l.levels.len())
            .sum::<usize>();
    let mut done = 0;
    let result = sitl::robustness::sweep(&ego, int8.as_ref(), opponent.as_ref(), &config, |name| {
        done += 1;
        eprintln!(
            "[{done}/{levels}, {:.0} s] {name}",
            started.elapsed().as_secs_f64()
        );
    });
    let text = result.markdown();
    print!("{text}");
    if let Some(path) = &args.markdown {
        write(path, text.as_bytes())?;
    }
    if let Some(path) = &contest.scoring.json {
        let json = serde_json::to_string_pretty(&result).map_err(|e| e.to_string())?;
        write(path, json.as_bytes())?;
    }
    Ok(())
}
