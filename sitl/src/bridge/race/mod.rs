//! Lockstep races over MAVLink: the simulator is the clock, each controller a MAVLink
//! endpoint (a process by default, a thread with `--in-process`), the referee the same as
//! `sitl eval`'s. Protocol in [`super`].
//!
//! | file | owns |
//! |---|---|
//! | `mod.rs` | the race's settings, entrants and errors; [`race`] |
//! | `launch.rs` | starting the controllers (processes, threads, attached addresses) |
//! | `link.rs` | [`ControllerLink`]: the simulator's end of one link, without the socket |
//! | `lockstep.rs` | the simulator's side of the race: the clock and the collected answers |
//! | `report.rs` | [`RaceOutcome`]: the result as text and JSON |

mod launch;
mod link;
mod lockstep;
mod report;

pub use link::{Answer, ControllerLink, Received};
pub use report::{ControllerReport, RaceOutcome};

use crate::eval::{EvalConfig, Report};
use crate::pilot::PilotSpec;
use crate::referee::{Episode, run_crew};
use crate::world::World;
use launch::{Endpoint, launch};
use lockstep::{Link, Lockstep};
use std::io;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// [`RaceConfig::resend_after`]'s default: 25 ms, many times a loopback round trip (tens of
/// µs) and a step's inference, short enough that 5 % loss costs a few ms per step.
pub const DEFAULT_RESEND_AFTER: Duration = Duration::from_millis(25);

/// How a race is run beyond what [`EvalConfig`] says.
#[derive(Clone, Debug)]
pub struct RaceConfig {
    /// Preset, episodes, seconds, seed, spawn: as `sitl eval`.
    pub eval: EvalConfig,
    /// A controller silent this long within a step (or a reset) is declared failed.
    pub step_timeout: Duration,
    /// A request (a step's states, a new flight) unanswered this long is sent again; the
    /// controller answers a repeated step from its cache and never steps twice.
    pub resend_after: Duration,
    /// How long a controller process may take to start.
    pub startup_timeout: Duration,
    /// MAVLink 2 signing on the controller links.
    pub signing_key: Option<[u8; 32]>,
    /// Where to stream the race for a ground station (`None`: no stream).
    pub gcs: Option<SocketAddr>,
    /// Rate of the ground station's attitude and position messages (Hz, simulated time).
    pub gcs_rate_hz: f32,
    /// Pace the race at wall-clock speed.
    pub realtime: bool,
    /// Record the ground-station stream as a telemetry log.
    pub tlog: bool,
    /// Keep each episode's trace (for plots and comparisons).
    pub record: bool,
}

impl RaceConfig {
    /// A race with `eval`'s episodes, 2 s step timeout, no ground station, no log.
    pub fn new(eval: EvalConfig) -> Self {
        Self {
            eval,
            step_timeout: Duration::from_secs(2),
            resend_after: DEFAULT_RESEND_AFTER,
            startup_timeout: Duration::from_secs(20),
            signing_key: None,
            gcs: None,
            gcs_rate_hz: 10.0,
            realtime: false,
            tlog: false,
            record: false,
        }
    }
}

/// Where the controllers run.
#[derive(Clone, Debug)]
pub enum Transport {
    /// Each controller is `EXE fc …`, its own process (EXE is the `sitl` binary).
    Processes(PathBuf),
    /// Each controller runs [`serve`](super::fc::serve) on a thread of this process.
    Threads,
    /// The controllers already run at these addresses (ego first): started by hand, on
    /// other machines, or behind a proxy.
    Attach(Vec<SocketAddr>),
}

/// A drone in the race and who flies it.
#[derive(Clone, Debug)]
pub struct Entrant {
    /// "ego" or "opponent".
    pub role: String,
    /// The pilot as given on the command line (a blob path or `baseline[:…]`): what a
    /// controller process is started with.
    pub spec: String,
    /// The pilot, loaded and validated.
    pub pilot: PilotSpec,
    /// Its MAVLink system id.
    pub system_id: u8,
}

/// Why a race could not be run (a controller failing mid-race is not an error: the result
/// reports it).
#[derive(Debug)]
pub enum RaceError {
    /// A socket could not be opened or used.
    Io(io::Error),
    /// A controller did not start.
    Launch(String),
    /// Not one or two entrants.
    Entrants(usize),
}

impl core::fmt::Display for RaceError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Io(e) => write!(f, "simulator socket: {e}"),
            Self::Launch(why) => f.write_str(why),
            Self::Entrants(n) => write!(f, "a race has one or two drones, not {n}"),
        }
    }
}

impl std::error::Error for RaceError {}

impl From<io::Error> for RaceError {
    fn from(e: io::Error) -> Self {
        Self::Io(e)
    }
}

/// Races `entrants` (the ego first, then an optional opponent) over MAVLink in lockstep:
/// starts their controllers, flies `config.eval.episodes` episodes with the referee, shuts
/// the controllers down.
pub fn race(
    entrants: &[Entrant],
    transport: &Transport,
    config: &RaceConfig,
) -> Result<RaceOutcome, RaceError> {
    if !(1..=2).contains(&entrants.len()) {
        return Err(RaceError::Entrants(entrants.len()));
    }
    let mut endpoints = entrants
        .iter()
        .enumerate()
        .map(|(i, e)| launch(i, e, transport, config))
        .collect::<Result<Vec<_>, _>>()?;
    let race_mode = entrants.len() == 2;
    let world = config.eval.world(race_mode);
    let (mut lockstep, started) = Lockstep::new(entrants, &mut endpoints, config, &world)?;
    let episodes = fly(&world, &mut lockstep, config, race_mode);
    let wall_s = started.elapsed().as_secs_f64();
    let (links, tlog) = lockstep.shut_down();
    wait_for(&mut endpoints);
    let metrics: Vec<_> = episodes.iter().map(|e| e.metrics.clone()).collect();
    let opponent = entrants.get(1).map(|e| &e.pilot);
    let report = Report::new(&entrants[0].pilot, opponent, &config.eval, &metrics);
    Ok(RaceOutcome {
        report,
        episodes,
        controllers: controller_reports(entrants, links, transport),
        wall_s,
        tlog,
    })
}

/// Flies `config.eval.episodes` episodes of one drone, or two in `race_mode`.
fn fly(
    world: &World,
    lockstep: &mut Lockstep<'_>,
    config: &RaceConfig,
    race_mode: bool,
) -> Vec<Episode> {
    let episode = config.eval.episode(race_mode);
    let mut episodes = Vec::with_capacity(config.eval.episodes as usize);
    for i in 0..config.eval.episodes {
        let e = if race_mode {
            run_crew::<2>(world, lockstep, &episode, u64::from(i), config.record)
        } else {
            run_crew::<1>(world, lockstep, &episode, u64::from(i), config.record)
        };
        episodes.push(e);
    }
    episodes
}

/// Gives each controller process a second to exit after the shutdown command (one that
/// does not go is killed when dropped) and joins the controller threads.
fn wait_for(endpoints: &mut [Endpoint]) {
    for ep in endpoints {
        if let Some(c) = &mut ep.child {
            let until = Instant::now() + Duration::from_secs(1);
            while matches!(c.try_wait(), Ok(None)) && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(5));
            }
        }
        if let Some(t) = ep.thread.take() {
            let _ = t.join();
        }
    }
}

/// Each entrant's controller as the result reports it.
fn controller_reports(
    entrants: &[Entrant],
    links: Vec<Link>,
    transport: &Transport,
) -> Vec<ControllerReport> {
    entrants
        .iter()
        .zip(links)
        .map(|(e, l)| ControllerReport {
            role: e.role.clone(),
            pilot: e.pilot.describe(),
            system_id: e.system_id,
            endpoint: l.addr.to_string(),
            runs_as: match transport {
                Transport::Processes(_) => "process".into(),
                Transport::Threads => "thread".into(),
                Transport::Attach(_) => "attached".into(),
            },
            failure: l.failure,
            link: l.end.stats(),
        })
        .collect()
}
