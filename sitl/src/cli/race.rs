//! `sitl race`: the shipped policies (or any two pilots) raced over MAVLink in lockstep.

use super::{Contest, load, load_opponent, write, write_quietly};
use clap::Args;
use sitl::bridge::race::{Entrant, RaceConfig, RaceOutcome, Transport};
use sitl::dynamics::Preset;
use std::path::PathBuf;
use std::process::ExitCode;

/// The arguments of `sitl race`.
#[derive(Args)]
#[command(mut_arg("ego", |a| a.help(
    "The ego: a blob or baseline[:CRUISE_MPS[:OFFSET_M]]. Default: the shipped ego (the \
     first of policies/stage2.blob, stage2_transplant.blob, stage2_G.blob, stage1.blob, \
     stage1_guarded.blob, stage1_imitation.blob, else the baseline)"
)))]
#[command(mut_arg("opponent", |a| a.help(
    "The opponent, or \"none\" for a time trial. Default: the shipped opponent (the first of \
     policies/stage1.blob and stage1_guarded.blob that is not the ego, else the baseline)"
)))]
pub struct RaceArgs {
    #[command(flatten)]
    contest: Contest,
    /// The telemetry log of the ground-station stream.
    #[arg(long, default_value = "race.tlog")]
    tlog: PathBuf,
    /// Do not write the telemetry log.
    #[arg(long)]
    no_tlog: bool,
    /// The top-down plot of episode 0 (SVG).
    #[arg(long, default_value = "race.svg")]
    plot: PathBuf,
    /// Do not draw the plot.
    #[arg(long)]
    no_plot: bool,
    /// The 3-D replay of every episode: one self-contained HTML page (drones, gates, a
    /// timeline of the events, speed and lead) that opens in any browser.
    #[arg(long, value_name = "FILE.html", default_value = "race.html")]
    replay: PathBuf,
    /// Do not write the replay.
    #[arg(long)]
    no_replay: bool,
    /// Pace the race at wall-clock speed, for a ground station to watch.
    #[arg(long)]
    realtime: bool,
    /// Run the controllers on threads of this process instead of as processes.
    #[arg(long, conflicts_with = "attach")]
    in_process: bool,
    /// Race controllers already running (`sitl fc`) at these addresses, ego first
    /// (e.g. 127.0.0.1:14601,127.0.0.1:14602) instead of starting them.
    #[arg(long, value_delimiter = ',')]
    attach: Vec<std::net::SocketAddr>,
    /// MAVLink 2 signing on the controller links: 64 hex digits, or a passphrase (SHA-256).
    #[arg(long)]
    signing_key: Option<String>,
    /// Ground-station address the race is streamed to ("none" to not stream).
    #[arg(long, default_value = "127.0.0.1:14550")]
    gcs: String,
    /// Rate of the ground station's attitude and position messages (Hz, simulated time).
    #[arg(long, default_value_t = 10.0)]
    gcs_rate_hz: f32,
    /// A controller that has not answered a step within this long is declared failed (ms).
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(1..=600_000))]
    step_timeout_ms: u64,
}

/// Runs `sitl race`; exit code 3 when the race ran but a controller failed.
pub fn run(args: RaceArgs) -> Result<ExitCode, String> {
    let preset = args.contest.common.preset;
    let entrants = entrants(&args.contest, &preset)?;
    let config = config(&args)?;
    let transport = transport(&args)?;
    announce(&entrants, &transport, &config);
    let outcome =
        sitl::bridge::race::race(&entrants, &transport, &config).map_err(|e| e.to_string())?;
    print!("{}", outcome.report.table());
    print!("{}", outcome.summary());
    write_outputs(&args, &entrants, &config, &outcome)?;
    // 3: the race ran, but a controller failed (the result says which and why).
    Ok(if outcome.has_failures() {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    })
}

/// The first of `names` in policies/ (`sitl::shipped::find`), else `fallback`.
fn shipped(names: &[&str], fallback: &str) -> String {
    sitl::shipped::find(names).map_or_else(|| fallback.to_string(), |p| p.display().to_string())
}

/// The ego (system 1) and the opponent (system 2) unless `--opponent none`: as given, else
/// the shipped ones.
fn entrants(contest: &Contest, preset: &Preset) -> Result<Vec<Entrant>, String> {
    let ego_spec = contest
        .ego
        .clone()
        .unwrap_or_else(|| shipped(&sitl::shipped::RACE_EGOS, "baseline"));
    let opponent_spec = match contest.opponent.as_deref() {
        Some("none") => None,
        Some(o) => Some(o.to_string()),
        // The stage-1 policy a stage-2 ego was trained against; never the ego itself.
        None => {
            let candidates: Vec<&str> = sitl::shipped::OPPONENTS
                .into_iter()
                .filter(|n| !ego_spec.ends_with(n))
                .collect();
            Some(shipped(&candidates, "baseline"))
        }
    };
    let ego = load(&ego_spec, preset, "--ego")?;
    let opponent = load_opponent(opponent_spec.as_deref(), preset)?;
    if opponent.is_none() && ego.needs_opponent() {
        return Err(format!(
            "--ego {ego_spec} observes an opponent; race it against one (--opponent)"
        ));
    }
    let mut entrants = vec![Entrant {
        role: "ego".into(),
        spec: ego_spec,
        pilot: ego,
        system_id: 1,
    }];
    if let (Some(spec), Some(pilot)) = (opponent_spec, opponent) {
        entrants.push(Entrant {
            role: "opponent".into(),
            spec,
            pilot,
            system_id: 2,
        });
    }
    Ok(entrants)
}

/// The race's settings from the command line.
fn config(args: &RaceArgs) -> Result<RaceConfig, String> {
    let signing_key = args
        .signing_key
        .as_deref()
        .map(sitl::bridge::wire::signing_key)
        .transpose()?;
    let gcs = match args.gcs.as_str() {
        "none" | "" => None,
        a => Some(
            a.parse()
                .map_err(|e| format!("--gcs {a}: not an address like 127.0.0.1:14550 ({e})"))?,
        ),
    };
    let mut config = RaceConfig::new(args.contest.eval_config());
    config.signing_key = signing_key;
    config.gcs = gcs;
    config.gcs_rate_hz = args.gcs_rate_hz;
    config.realtime = args.realtime;
    config.tlog = !args.no_tlog;
    config.record = !args.no_plot || !args.no_replay || args.contest.scoring.trace.is_some();
    config.step_timeout = std::time::Duration::from_millis(args.step_timeout_ms);
    Ok(config)
}

/// Where the controllers run: attached, threads, or processes of this binary.
fn transport(args: &RaceArgs) -> Result<Transport, String> {
    Ok(if !args.attach.is_empty() {
        Transport::Attach(args.attach.clone())
    } else if args.in_process {
        Transport::Threads
    } else {
        Transport::Processes(
            std::env::current_exe().map_err(|e| format!("cannot find the sitl binary: {e}"))?,
        )
    })
}

/// Says on stderr who races how.
fn announce(entrants: &[Entrant], transport: &Transport, config: &RaceConfig) {
    eprintln!(
        "racing {} over MAVLink ({}, lockstep{}{})",
        entrants
            .iter()
            .map(|e| format!("{} {} (sysid {})", e.role, e.pilot.describe(), e.system_id))
            .collect::<Vec<_>>()
            .join(" vs "),
        match transport {
            Transport::Threads => "threads",
            Transport::Processes(_) => "one process per controller",
            Transport::Attach(_) => "attached controllers",
        },
        if config.signing_key.is_some() {
            ", signed"
        } else {
            ""
        },
        if config.realtime { ", real time" } else { "" },
    );
}

/// Writes what was asked for: the telemetry log, the traces, the plot, the JSON, the replay.
fn write_outputs(
    args: &RaceArgs,
    entrants: &[Entrant],
    config: &RaceConfig,
    outcome: &RaceOutcome,
) -> Result<(), String> {
    let (preset, scoring) = (&args.contest.common.preset, &args.contest.scoring);
    if config.tlog {
        write_quietly(&args.tlog, &outcome.tlog)?;
        eprintln!(
            "wrote {} ({} bytes)",
            args.tlog.display(),
            outcome.tlog.len()
        );
    }
    let pilots: Vec<String> = entrants.iter().map(|e| e.pilot.describe()).collect();
    scoring.write_traces(&pilots, preset, &outcome.episodes)?;
    if let (false, Some(first)) = (args.no_plot, outcome.episodes.first()) {
        let title = format!(
            "{} over MAVLink, episode 0 ({} preset, seed {})",
            pilots.join(" vs "),
            preset.name,
            scoring.seed
        );
        let svg = sitl::plot::top_down(
            &config.eval.world(entrants.len() == 2).track,
            &first.trace,
            &title,
        );
        write(&args.plot, svg.as_bytes())?;
    }
    if let Some(path) = &scoring.json {
        write(path, outcome.to_json().as_bytes())?;
    }
    // Last: the largest file, and one whose failure cannot keep the others from being written.
    if !args.no_replay {
        let world = config.eval.world(entrants.len() == 2);
        scoring.write_replay(
            &args.replay,
            &world.track,
            &pilots,
            preset,
            &outcome.episodes,
        )?;
    }
    Ok(())
}
