//! `sitl`: fly and score controllers in the simulated world.
//!
//! - `sitl eval --ego <blob|baseline> [--opponent <blob|baseline>] [--preset paper]
//!   [--episodes 20] [--seconds 45] [--seed 0] [--spawn stage1|stage2|along-track]
//!   [--json out.json] [--plot out.svg]`: the referee's Table-1 row over many seeded
//!   episodes, in-process.
//! - `sitl fly [--ego baseline] [--preset paper] [--seconds 45] [--cruise M_PER_S]`: one
//!   time trial from the stage-1 spawn with every lap time printed.
//! - `sitl race [--ego X] [--opponent Y|none] [--episodes 20] [--seed 0] [--json F]
//!   [--tlog race.tlog] [--plot race.svg] [--realtime] [--in-process] [--signing-key K]`:
//!   the shipped policies raced over MAVLink in lockstep, each controller its own process.
//! - `sitl fc --blob X --sysid N --port P [--signing-key K]`: one controller as a MAVLink
//!   endpoint (what `race` starts).

use clap::{Args, Parser, Subcommand};
use sitl::bridge::fc::FcConfig;
use sitl::bridge::race::{Entrant, RaceConfig, Transport};
use sitl::dynamics::Preset;
use sitl::env::PresetName;
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
    /// Race the shipped policies (or any two pilots) over MAVLink in lockstep, each
    /// controller its own process; print the Table-1 row, write race.tlog and race.svg.
    Race(RaceArgs),
    /// Run one controller as a MAVLink endpoint on a UDP port (what `race` starts).
    Fc(FcArgs),
    /// Convert an f32 blob to int8 and measure what it costs: the int8 policy's action
    /// error on the observations of races the f32 policy flies, then both blobs' Table-1
    /// rows over the same seeded episodes.
    Int8Check(Int8CheckArgs),
}

#[derive(Args)]
struct Int8CheckArgs {
    /// The f32 policy blob.
    #[arg(long)]
    ego: String,
    /// The opponent (a blob or "baseline[...]"); without one, time trials.
    #[arg(long)]
    opponent: Option<String>,
    #[command(flatten)]
    common: Common,
    #[command(flatten)]
    scoring: Scoring,
}

#[derive(Args)]
struct RaceArgs {
    /// The ego: a blob or baseline[:CRUISE_MPS[:OFFSET_M]]. Default: the shipped ego
    /// (the first of policies/stage2.blob, stage1.blob, stage1_guarded.blob,
    /// stage1_imitation.blob, else the baseline).
    #[arg(long)]
    ego: Option<String>,
    /// The opponent, or "none" for a time trial. Default: the shipped opponent (the first
    /// of policies/stage1.blob and stage1_guarded.blob that is not the ego, else the
    /// baseline).
    #[arg(long)]
    opponent: Option<String>,
    #[command(flatten)]
    common: Common,
    #[command(flatten)]
    scoring: Scoring,
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

#[derive(Args)]
struct FcArgs {
    /// The pilot: a policy blob file, or baseline[:CRUISE_MPS[:OFFSET_M]].
    #[arg(long)]
    blob: String,
    /// MAVLink system id (1-249).
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=249))]
    sysid: u8,
    /// UDP port on 127.0.0.1 (0: any free port; the first line printed names it).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Dynamics preset (tunes the baseline to the preset's thrust).
    #[arg(long, default_value = "paper", value_parser = parse_preset)]
    preset: Preset,
    /// Require and send MAVLink 2 signatures: 64 hex digits, or a passphrase (SHA-256).
    #[arg(long)]
    signing_key: Option<String>,
    /// Exit after this many seconds without a valid frame.
    #[arg(long, default_value_t = 30)]
    idle_timeout_s: u64,
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

/// The episodes a pilot is scored over, as `sitl eval` and `sitl race` share them.
#[derive(Args)]
struct Scoring {
    /// Number of episodes.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    episodes: u32,
    /// Seed of the spawn draws; episode i uses stream i of it.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where drones start and restart: stage1 (time trials' default), stage2 (races'
    /// default), or along-track.
    #[arg(long, value_parser = clap::value_parser!(SpawnMode))]
    spawn: Option<SpawnMode>,
    /// Also write the report as JSON to this file (`sitl race` adds the controllers' links).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also record every episode's positions and overtakes as JSON to this file (for
    /// `cargo run -p tools -- overtake-figure`).
    #[arg(long)]
    trace: Option<PathBuf>,
}

impl Scoring {
    /// Writes the recorded episodes to `--trace`, if given.
    fn write_traces(
        &self,
        pilots: &[String],
        preset: &Preset,
        episodes: &[sitl::referee::Episode],
    ) -> Result<(), String> {
        let Some(path) = &self.trace else {
            return Ok(());
        };
        let json = serde_json::json!({
            "format": sitl::referee::TRACES_FORMAT,
            "pilots": pilots,
            "preset": preset.name,
            "seed": self.seed,
            "episodes": episodes.iter().map(|e| e.trace.to_json()).collect::<Vec<_>>(),
        });
        sitl::files::write_atomically(path, json.to_string().as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
        Ok(())
    }
}

impl Scoring {
    fn eval_config(&self, common: &Common) -> EvalConfig {
        EvalConfig {
            preset: common.preset,
            episodes: self.episodes,
            seconds: common.seconds,
            seed: self.seed,
            spawn: self.spawn,
        }
    }
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
    #[command(flatten)]
    scoring: Scoring,
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
    s.parse::<PresetName>().map(PresetName::preset)
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
    let config = args.scoring.eval_config(&args.common);
    let started = std::time::Instant::now();
    let record = args.plot.is_some() || args.scoring.trace.is_some();
    let episodes = evaluate(&ego, opponent.as_ref(), &config, record);
    let pilots: Vec<String> = core::iter::once(ego.describe())
        .chain(opponent.as_ref().map(PilotSpec::describe))
        .collect();
    args.scoring.write_traces(&pilots, &preset, &episodes)?;
    if let (Some(path), Some(first)) = (&args.plot, episodes.first()) {
        let title = format!(
            "{}{}, episode 0 ({} preset, seed {})",
            ego.describe(),
            opponent
                .as_ref()
                .map(|o| format!(" vs {}", o.describe()))
                .unwrap_or_default(),
            preset.name,
            args.scoring.seed
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
    if let Some(path) = args.scoring.json {
        sitl::files::write_atomically(&path, report.to_json().as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

fn int8_check(args: Int8CheckArgs) -> Result<ExitCode, String> {
    let preset = args.common.preset;
    let raw = std::fs::read(&args.ego).map_err(|e| format!("--ego {}: {e}", args.ego))?;
    let opponent = args
        .opponent
        .as_deref()
        .map(|o| PilotSpec::load(o, &preset).map_err(|e| format!("--opponent: {e}")))
        .transpose()?;
    let config = args.scoring.eval_config(&args.common);
    let started = std::time::Instant::now();
    let c = sitl::quant::compare(&raw, opponent.as_ref(), &config)
        .map_err(|e| format!("--ego {}: {e}", args.ego))?;
    let e = &c.action_error;
    println!(
        "{}: f32 {} bytes -> int8 {} bytes ({:.2}x smaller)",
        args.ego,
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
    if let Some(path) = &args.scoring.json {
        let json = serde_json::to_string_pretty(&c).map_err(|e| e.to_string())?;
        sitl::files::write_atomically(path, json.as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    if e.replay_mismatches > 0 {
        return Err(format!(
            "{} steps where the replayed f32 policy disagreed with the controller: the measurement is broken",
            e.replay_mismatches
        ));
    }
    Ok(ExitCode::SUCCESS)
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

/// The first of `names` in policies/ (of the working directory, else of the repository this
/// binary was built from), else `fallback`.
fn shipped(names: &[&str], fallback: &str) -> String {
    let dirs = [
        PathBuf::from("policies"),
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../policies"),
    ];
    dirs.iter()
        .flat_map(|d| names.iter().map(move |n| d.join(n)))
        .find(|p| p.is_file())
        .map_or_else(|| fallback.to_string(), |p| p.display().to_string())
}

fn race(args: RaceArgs) -> Result<ExitCode, String> {
    let preset = args.common.preset;
    let ego_spec = args.ego.unwrap_or_else(|| {
        shipped(
            &[
                "stage2.blob",
                "stage1.blob",
                "stage1_guarded.blob",
                "stage1_imitation.blob",
            ],
            "baseline",
        )
    });
    let opponent_spec = match args.opponent.as_deref() {
        Some("none") => None,
        Some(o) => Some(o.to_string()),
        // The stage-1 policy a stage-2 ego was trained against; never the ego itself.
        None => {
            let candidates: Vec<&str> = ["stage1.blob", "stage1_guarded.blob"]
                .into_iter()
                .filter(|n| !ego_spec.ends_with(n))
                .collect();
            Some(shipped(&candidates, "baseline"))
        }
    };
    let ego = PilotSpec::load(&ego_spec, &preset).map_err(|e| format!("--ego: {e}"))?;
    let opponent = opponent_spec
        .as_deref()
        .map(|o| PilotSpec::load(o, &preset).map_err(|e| format!("--opponent: {e}")))
        .transpose()?;
    if opponent.is_none() && ego.needs_opponent() {
        return Err(format!(
            "--ego {ego_spec} observes an opponent; race it against one (--opponent)"
        ));
    }
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
    let mut config = RaceConfig::new(args.scoring.eval_config(&args.common));
    config.signing_key = signing_key;
    config.gcs = gcs;
    config.gcs_rate_hz = args.gcs_rate_hz;
    config.realtime = args.realtime;
    config.tlog = !args.no_tlog;
    config.record = !args.no_plot || args.scoring.trace.is_some();
    config.step_timeout = std::time::Duration::from_millis(args.step_timeout_ms);
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
    let transport = if !args.attach.is_empty() {
        Transport::Attach(args.attach.clone())
    } else if args.in_process {
        Transport::Threads
    } else {
        Transport::Processes(
            std::env::current_exe().map_err(|e| format!("cannot find the sitl binary: {e}"))?,
        )
    };
    eprintln!(
        "racing {} over MAVLink ({}, lockstep{}{})",
        entrants
            .iter()
            .map(|e| format!("{} {} (sysid {})", e.role, e.pilot.describe(), e.system_id))
            .collect::<Vec<_>>()
            .join(" vs "),
        match &transport {
            Transport::Threads => "threads",
            Transport::Processes(_) => "one process per controller",
            Transport::Attach(_) => "attached controllers",
        },
        if config.signing_key.is_some() {
            ", signed"
        } else {
            ""
        },
        if args.realtime { ", real time" } else { "" },
    );
    let outcome =
        sitl::bridge::race::race(&entrants, &transport, &config).map_err(|e| e.to_string())?;
    print!("{}", outcome.report.table());
    print!("{}", outcome.summary());
    if config.tlog {
        sitl::files::write_atomically(&args.tlog, &outcome.tlog)
            .map_err(|e| format!("cannot write {}: {e}", args.tlog.display()))?;
        eprintln!(
            "wrote {} ({} bytes)",
            args.tlog.display(),
            outcome.tlog.len()
        );
    }
    let pilots: Vec<String> = entrants.iter().map(|e| e.pilot.describe()).collect();
    args.scoring
        .write_traces(&pilots, &preset, &outcome.episodes)?;
    if let (false, Some(first)) = (args.no_plot, outcome.episodes.first()) {
        let title = format!(
            "{} over MAVLink, episode 0 ({} preset, seed {})",
            entrants
                .iter()
                .map(|e| e.pilot.describe())
                .collect::<Vec<_>>()
                .join(" vs "),
            preset.name,
            args.scoring.seed
        );
        let svg = sitl::plot::top_down(
            &config.eval.world(entrants.len() == 2).track,
            &first.trace,
            &title,
        );
        sitl::files::write_atomically(&args.plot, svg.as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", args.plot.display()))?;
        eprintln!("wrote {}", args.plot.display());
    }
    if let Some(path) = &args.scoring.json {
        sitl::files::write_atomically(path, outcome.to_json().as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    // 3: the race ran, but a controller failed (the result says which and why).
    Ok(if outcome.has_failures() {
        ExitCode::from(3)
    } else {
        ExitCode::SUCCESS
    })
}

fn fc(args: FcArgs) -> Result<(), String> {
    use std::io::Write;
    let pilot = PilotSpec::load(&args.blob, &args.preset).map_err(|e| format!("--blob: {e}"))?;
    let signing_key = args
        .signing_key
        .as_deref()
        .map(sitl::bridge::wire::signing_key)
        .transpose()?;
    let socket = std::net::UdpSocket::bind(("127.0.0.1", args.port))
        .map_err(|e| format!("cannot bind 127.0.0.1:{}: {e}", args.port))?;
    let addr = socket.local_addr().map_err(|e| e.to_string())?;
    // The first line names the endpoint: `sitl race` reads it.
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "sitl fc: system {} ({}) listening on {addr}",
        args.sysid,
        pilot.describe()
    )
    .and_then(|()| out.flush())
    .map_err(|e| e.to_string())?;
    drop(out);
    let config = FcConfig {
        pilot,
        system_id: args.sysid,
        signing_key,
        idle_timeout: std::time::Duration::from_secs(args.idle_timeout_s),
    };
    let summary = sitl::bridge::fc::serve(&socket, &config).map_err(|e| e.to_string())?;
    let l = summary.link;
    eprintln!(
        "sitl fc: system {} {} after {} steps, {} flights; {} frames in, {} dropped",
        args.sysid,
        if summary.shut_down {
            "shut down"
        } else {
            "idle, exiting"
        },
        summary.steps,
        summary.flights,
        l.frames_received,
        l.dropped()
    );
    Ok(())
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Eval(a) => eval(a).map(|()| ExitCode::SUCCESS),
        Command::Fly(a) => fly(a).map(|()| ExitCode::SUCCESS),
        Command::Race(a) => race(a),
        Command::Fc(a) => fc(a).map(|()| ExitCode::SUCCESS),
        Command::Int8Check(a) => int8_check(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
