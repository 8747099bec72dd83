//! Lockstep races over MAVLink: the simulator is the clock, each controller a MAVLink
//! endpoint (a process by default, a thread with `--in-process`), the referee the same as
//! `sitl eval`'s. Protocol in [`super`].

use super::fc::{FcConfig, FcSummary, serve};
use super::gcs::GroundStation;
use super::wire::{Codec, LinkStats};
use super::{
    NewFlight, SIM_COMPONENT_ID, SIM_SYSTEM_ID, command_from_actuators, shutdown_command,
    state_messages,
};
use crate::eval::{EvalConfig, Report};
use crate::frames::NedState;
use crate::pilot::PilotSpec;
use crate::referee::{Crew, Episode, EpisodeConfig, run_crew};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use mavlink::dialects::common::{MavCmd, MavMessage, MavResult};
use serde::Serialize;
use std::io::{self, BufRead, BufReader};
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How a race is run beyond what [`EvalConfig`] says.
#[derive(Clone, Debug)]
pub struct RaceConfig {
    /// Preset, episodes, seconds, seed, spawn: as `sitl eval`.
    pub eval: EvalConfig,
    /// A controller silent this long within a step (or a reset) is declared failed.
    pub step_timeout: Duration,
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
    /// Each controller runs [`serve`] on a thread of this process.
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

/// One controller as the race result reports it.
#[derive(Clone, Debug, Serialize)]
pub struct ControllerReport {
    /// "ego" or "opponent".
    pub role: String,
    /// Its pilot.
    pub pilot: String,
    /// Its MAVLink system id.
    pub system_id: u8,
    /// Its UDP endpoint.
    pub endpoint: String,
    /// "process", "thread" or "attached".
    pub runs_as: String,
    /// Why it was declared failed, if it was (its drone's motors were stopped from then on).
    pub failure: Option<String>,
    /// The simulator's counters for its link.
    pub link: LinkStats,
}

/// The result of a race.
#[derive(Clone, Debug)]
pub struct RaceOutcome {
    /// The Table-1 row, as `sitl eval` computes it.
    pub report: Report,
    /// The episodes (with traces when recorded).
    pub episodes: Vec<Episode>,
    /// Each controller's link and fate.
    pub controllers: Vec<ControllerReport>,
    /// Frames from addresses that are no controller's.
    pub unknown_sender_frames: u64,
    /// Wall-clock seconds of the race (without starting the controllers).
    pub wall_s: f64,
    /// The telemetry log (empty unless asked for).
    pub tlog: Vec<u8>,
}

#[derive(Serialize)]
struct RaceJson<'a> {
    #[serde(flatten)]
    report: &'a Report,
    controllers: &'a [ControllerReport],
    unknown_sender_frames: u64,
    wall_s: f64,
    realtime_factor: f64,
}

impl RaceOutcome {
    /// Simulated seconds per wall-clock second.
    pub fn realtime_factor(&self) -> f64 {
        self.report.sim_seconds / self.wall_s.max(1e-9)
    }

    /// True when any controller was declared failed.
    pub fn has_failures(&self) -> bool {
        self.controllers.iter().any(|c| c.failure.is_some())
    }

    /// The report as JSON: `sitl eval`'s keys plus `controllers`, `unknown_sender_frames`,
    /// `wall_s` and `realtime_factor`.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(&RaceJson {
            report: &self.report,
            controllers: &self.controllers,
            unknown_sender_frames: self.unknown_sender_frames,
            wall_s: self.wall_s,
            realtime_factor: self.realtime_factor(),
        })
        .unwrap_or_default()
    }

    /// A few lines on the race: time, speed, each controller's link.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "race: {} episodes, {:.0} simulated s in {:.2} s wall-clock ({:.0}x real time), {} overtakes ({} sustained)\n",
            self.report.episodes,
            self.report.sim_seconds,
            self.wall_s,
            self.realtime_factor(),
            self.report.overtakes,
            self.report.sustained_overtakes,
        );
        for c in &self.controllers {
            let l = &c.link;
            s.push_str(&format!(
                "  {:<8} sysid {} {} at {}: {} frames in, {} out, {} dropped",
                c.role,
                c.system_id,
                c.runs_as,
                c.endpoint,
                l.frames_received,
                l.frames_sent,
                l.dropped()
            ));
            if l.dropped() > 0 {
                s.push_str(&format!(
                    " (malformed {}, bad crc {}, bad payload {}, unsigned {}, bad signature {}, replayed {}, wrong system {}, stale {}, future {}, ignored {})",
                    l.malformed,
                    l.bad_crc,
                    l.bad_payload,
                    l.unsigned,
                    l.bad_signature,
                    l.replayed,
                    l.wrong_system,
                    l.stale,
                    l.future,
                    l.ignored
                ));
            }
            match &c.failure {
                Some(why) => s.push_str(&format!("\n           FAILED: {why}\n")),
                None => s.push('\n'),
            }
        }
        if self.unknown_sender_frames > 0 {
            s.push_str(&format!(
                "  {} datagrams from unknown senders ignored\n",
                self.unknown_sender_frames
            ));
        }
        s
    }
}

/// A started controller.
struct Endpoint {
    addr: SocketAddr,
    child: Option<Child>,
    thread: Option<JoinHandle<io::Result<FcSummary>>>,
}

impl Drop for Endpoint {
    fn drop(&mut self) {
        if let Some(c) = &mut self.child {
            if matches!(c.try_wait(), Ok(None)) {
                let _ = c.kill();
            }
            let _ = c.wait();
        }
    }
}

/// Starts the controller of `e`.
fn launch(
    index: usize,
    e: &Entrant,
    transport: &Transport,
    config: &RaceConfig,
) -> Result<Endpoint, RaceError> {
    match transport {
        Transport::Attach(addrs) => match addrs.get(index) {
            Some(&addr) => Ok(Endpoint {
                addr,
                child: None,
                thread: None,
            }),
            None => Err(RaceError::Launch(format!(
                "no address to attach the {} controller to",
                e.role
            ))),
        },
        Transport::Threads => {
            let socket = UdpSocket::bind("127.0.0.1:0")?;
            let addr = socket.local_addr()?;
            let fc = FcConfig {
                pilot: e.pilot.clone(),
                system_id: e.system_id,
                signing_key: config.signing_key,
                idle_timeout: config.startup_timeout,
            };
            let thread = std::thread::Builder::new()
                .name(format!("fc-{}", e.system_id))
                .spawn(move || serve(&socket, &fc))?;
            Ok(Endpoint {
                addr,
                child: None,
                thread: Some(thread),
            })
        }
        Transport::Processes(exe) => {
            let mut cmd = Command::new(exe);
            cmd.args(["fc", "--blob", &e.spec, "--sysid", &e.system_id.to_string()])
                .args(["--port", "0", "--preset", config.eval.preset.name])
                .args([
                    "--idle-timeout-s",
                    &config.startup_timeout.as_secs().max(1).to_string(),
                ])
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit());
            if let Some(key) = &config.signing_key {
                let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
                cmd.args(["--signing-key", &hex]);
            }
            let mut child = cmd.spawn().map_err(|err| {
                RaceError::Launch(format!("cannot start {} fc: {err}", exe.display()))
            })?;
            let mut line = String::new();
            let read = child
                .stdout
                .take()
                .map(|out| BufReader::new(out).read_line(&mut line));
            let addr = line
                .rsplit(' ')
                .next()
                .and_then(|a| a.trim().parse::<SocketAddr>().ok());
            match (read, addr) {
                (Some(Ok(_)), Some(addr)) => Ok(Endpoint {
                    addr,
                    child: Some(child),
                    thread: None,
                }),
                _ => {
                    let status = child.wait().map(|s| s.to_string()).unwrap_or_default();
                    Err(RaceError::Launch(format!(
                        "the {} controller ({}) did not start ({status})",
                        e.role, e.spec
                    )))
                }
            }
        }
    }
}

/// What the simulator waits for on a link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Awaited {
    /// The acknowledgement of the flight started last.
    Acknowledgement,
    /// The answer for the step asked last.
    Answer,
}

/// What the simulator took from one datagram of a controller.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Received {
    /// Valid frames taken: the awaited one, heartbeats. Each of the datagram's other frames
    /// is in one of the link's counters.
    pub taken: u32,
    /// The awaited frame, when this datagram brought it.
    pub answer: Option<Answer>,
}

/// A frame the simulator waited for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Answer {
    /// The controller accepted the flight started last.
    FlightAccepted,
    /// The controller's motor command for the step asked last.
    Command(MotorCommand),
}

/// The simulator's end of one controller's link without the socket: it encodes what the
/// simulator sends, and [`ControllerLink::handle`] judges each datagram that comes back
/// against what it waits for ([`super`] says which frames it takes). Nothing received
/// moves the simulator's clock.
#[derive(Clone, Debug)]
pub struct ControllerLink {
    system_id: u8,
    codec: Codec,
    stats: LinkStats,
    /// The flight started last (0: none yet).
    flight: u32,
    /// The step asked last (µs, as answers echo it).
    asked_us: Option<u64>,
    awaited: Option<Awaited>,
}

impl ControllerLink {
    /// The link to the controller of system `system_id`, signed with `signing_key` if any.
    pub fn new(system_id: u8, signing_key: Option<[u8; 32]>) -> Self {
        Self {
            system_id,
            codec: Codec::new(SIM_COMPONENT_ID, signing_key, 0),
            stats: LinkStats::default(),
            flight: 0,
            asked_us: None,
            awaited: None,
        }
    }

    /// The controller's system id.
    pub fn system_id(&self) -> u8 {
        self.system_id
    }

    /// Appends the reset command starting `flight` to `out` and waits for its
    /// acknowledgement.
    pub fn start_flight(&mut self, flight: &NewFlight, out: &mut Vec<u8>) {
        self.codec
            .encode(SIM_SYSTEM_ID, &flight.command(self.system_id), out);
        self.flight = flight.number;
        self.awaited = Some(Awaited::Acknowledgement);
    }

    /// Appends the step at `t_ms` to `out` (the `(system id, state)` pairs in order, the
    /// controller's own last) and waits for its answer.
    pub fn ask_step(&mut self, t_ms: u32, states: &[(u8, NedState)], out: &mut Vec<u8>) {
        for (id, state) in states {
            for m in state_messages(t_ms, state) {
                self.codec.encode(*id, &m, out);
            }
        }
        self.asked_us = Some(u64::from(t_ms) * 1000);
        self.awaited = Some(Awaited::Answer);
    }

    /// Appends the shutdown command to `out`; nothing is awaited after it.
    pub fn shut_down(&mut self, out: &mut Vec<u8>) {
        self.codec
            .encode(SIM_SYSTEM_ID, &shutdown_command(self.system_id), out);
        self.awaited = None;
    }

    /// True while the acknowledgement or answer asked for has not come.
    pub fn awaiting(&self) -> bool {
        self.awaited.is_some()
    }

    /// The link's counters, with the frames sent.
    pub fn stats(&self) -> LinkStats {
        LinkStats {
            frames_sent: self.codec.frames_encoded(),
            ..self.stats
        }
    }

    /// Takes one datagram from the controller's address: returns the awaited frame if it
    /// came, and counts every frame it drops.
    pub fn handle(&mut self, datagram: &[u8]) -> Received {
        let mut frames = Vec::new();
        self.codec
            .decode(datagram, &mut self.stats, |f, _| frames.push(f));
        let mut received = Received::default();
        for f in frames {
            if f.header.system_id != u32::from(self.system_id) {
                self.stats.wrong_system += 1;
                continue;
            }
            let answer = match &f.message {
                // Liveness only.
                MavMessage::HEARTBEAT(_) => {
                    received.taken += 1;
                    continue;
                }
                MavMessage::COMMAND_ACK(a)
                    if a.command == MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT =>
                {
                    let (number, flight) = (i64::from(a.result_param2), i64::from(self.flight));
                    if number < flight
                        || (number == flight && !self.awaits(Awaited::Acknowledgement))
                    {
                        self.stats.stale += 1;
                        continue;
                    } else if number > flight {
                        self.stats.future += 1;
                        continue;
                    } else if a.result != MavResult::MAV_RESULT_ACCEPTED {
                        self.stats.ignored += 1;
                        continue;
                    }
                    Answer::FlightAccepted
                }
                MavMessage::HIL_ACTUATOR_CONTROLS(a) => match self.asked_us {
                    Some(asked) if a.time_usec == asked && self.awaits(Awaited::Answer) => {
                        Answer::Command(command_from_actuators(a))
                    }
                    Some(asked) if a.time_usec <= asked => {
                        self.stats.stale += 1;
                        continue;
                    }
                    _ => {
                        self.stats.future += 1;
                        continue;
                    }
                },
                _ => {
                    self.stats.ignored += 1;
                    continue;
                }
            };
            self.awaited = None;
            received.taken += 1;
            received.answer = Some(answer);
        }
        received
    }

    fn awaits(&self, what: Awaited) -> bool {
        self.awaited == Some(what)
    }
}

/// One controller link as the simulator holds it.
struct Link {
    end: ControllerLink,
    addr: SocketAddr,
    failure: Option<String>,
    command: MotorCommand,
}

impl Link {
    /// True while the link is live and its controller owes an answer.
    fn owes(&self) -> bool {
        self.failure.is_none() && self.end.awaiting()
    }
}

/// The simulator's side of a lockstep race: a [`Crew`] whose pilots are MAVLink endpoints.
struct Lockstep<'e> {
    socket: UdpSocket,
    links: Vec<Link>,
    endpoints: &'e mut [Endpoint],
    dt_ms: u32,
    clock_ms: u32,
    step: u64,
    flight: u32,
    /// The wait in force: the start-up timeout until the first flight is acknowledged, the
    /// step timeout after.
    timeout: Duration,
    step_timeout: Duration,
    gcs: GroundStation,
    pace: Option<Instant>,
    unknown_sender: u64,
    buf: Vec<u8>,
}

impl Lockstep<'_> {
    /// Reads datagrams until no live link owes an answer or the timeout passes; a link that
    /// still does is declared failed with `what` in the reason. A command answer is kept in
    /// the link's `command`.
    fn collect(&mut self, what: &str) {
        let deadline = Instant::now() + self.timeout;
        while self.links.iter().any(Link::owes) {
            let now = Instant::now();
            if now >= deadline {
                for l in self.links.iter_mut().filter(|l| l.owes()) {
                    l.failure = Some(format!(
                        "silent: no {what} within {} ms (simulated t = {:.2} s)",
                        self.timeout.as_millis(),
                        f64::from(self.clock_ms) / 1000.0
                    ));
                }
                return;
            }
            let slice = (deadline - now).min(Duration::from_millis(20));
            if self.socket.set_read_timeout(Some(slice)).is_err() {
                return;
            }
            match self.socket.recv_from(&mut self.buf) {
                Ok((n, from)) => {
                    let Some(link) = self.links.iter_mut().find(|l| l.addr == from) else {
                        self.unknown_sender += 1;
                        continue;
                    };
                    if let Some(Answer::Command(c)) = link.end.handle(&self.buf[..n]).answer {
                        link.command = c;
                    }
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock
                            | io::ErrorKind::TimedOut
                            | io::ErrorKind::ConnectionRefused
                    ) =>
                {
                    self.check_processes();
                }
                Err(e) => {
                    for l in self.links.iter_mut().filter(|l| l.owes()) {
                        l.failure = Some(format!("simulator socket error: {e}"));
                    }
                }
            }
        }
    }

    /// Declares failed, at once, the links whose controller process has exited.
    fn check_processes(&mut self) {
        for (l, e) in self.links.iter_mut().zip(self.endpoints.iter_mut()) {
            if !l.owes() {
                continue;
            }
            if let Some(Ok(Some(status))) = e.child.as_mut().map(|c| c.try_wait()) {
                l.failure = Some(format!(
                    "controller process exited ({status}) at simulated t = {:.2} s",
                    f64::from(self.clock_ms) / 1000.0
                ));
            }
        }
    }

    fn send(&mut self, i: usize, datagram: &[u8]) {
        let l = &mut self.links[i];
        if let Err(e) = self.socket.send_to(datagram, l.addr) {
            if e.kind() != io::ErrorKind::ConnectionRefused {
                l.failure = Some(format!("cannot send to {}: {e}", l.addr));
            }
        }
    }
}

impl<const N: usize> Crew<N> for Lockstep<'_> {
    fn reset(&mut self, targets: [usize; N]) {
        self.flight += 1;
        let ids: Vec<u8> = self.links.iter().map(|l| l.end.system_id()).collect();
        let mut out = Vec::with_capacity(64);
        for (i, gate) in targets.into_iter().enumerate() {
            let flight = NewFlight {
                number: self.flight,
                gate,
                step_period_ms: self.dt_ms,
                first_step_ms: self.clock_ms,
                opponent: ids
                    .iter()
                    .enumerate()
                    .find(|&(j, _)| j != i)
                    .map(|(_, &id)| id),
            };
            let Some(l) = self.links.get_mut(i).filter(|l| l.failure.is_none()) else {
                continue;
            };
            out.clear();
            l.end.start_flight(&flight, &mut out);
            self.send(i, &out);
        }
        self.collect("acknowledgement of the new flight");
        // Every controller has answered once (or failed): from now on, steps are timed.
        self.timeout = self.step_timeout;
    }

    fn commands(&mut self, states: &[VehicleState; N]) -> [MotorCommand; N] {
        let t = self.clock_ms;
        if let Some(start) = self.pace {
            let due = start + Duration::from_millis(u64::from(t));
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        let ned: Vec<NedState> = states.iter().map(NedState::from_enu).collect();
        let ids: Vec<u8> = self.links.iter().map(|l| l.end.system_id()).collect();
        let mut out = Vec::with_capacity(256);
        for i in 0..self.links.len() {
            let l = &mut self.links[i];
            l.command = MotorCommand::STOP;
            if l.failure.is_some() {
                continue;
            }
            // The other vehicles first, then the own state: one datagram per step.
            let step: Vec<(u8, NedState)> = (0..ned.len())
                .filter(|&j| j != i)
                .chain([i])
                .map(|j| (ids[j], ned[j]))
                .collect();
            out.clear();
            l.end.ask_step(t, &step, &mut out);
            self.send(i, &out);
        }
        self.collect("HIL_ACTUATOR_CONTROLS for the step");
        for l in &mut self.links {
            if l.failure.is_some() {
                l.command = MotorCommand::STOP;
            }
        }
        let errors: Vec<u64> = self
            .links
            .iter()
            .map(|l| l.end.stats().rejected())
            .collect();
        self.gcs.publish(self.step, t, &ned, &errors);
        self.clock_ms += self.dt_ms;
        self.step += 1;
        core::array::from_fn(|i| self.links.get(i).map_or(MotorCommand::STOP, |l| l.command))
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
    let socket = UdpSocket::bind("127.0.0.1:0")?;
    let links = entrants
        .iter()
        .zip(&endpoints)
        .map(|(e, ep)| Link {
            end: ControllerLink::new(e.system_id, config.signing_key),
            addr: ep.addr,
            failure: None,
            command: MotorCommand::STOP,
        })
        .collect();
    let ids: Vec<u8> = entrants.iter().map(|e| e.system_id).collect();
    let gcs = GroundStation::new(
        &ids,
        config.gcs,
        config.gcs_rate_hz,
        world.dt_s,
        config.tlog,
    )?;
    let started = Instant::now();
    let mut lockstep = Lockstep {
        socket,
        links,
        endpoints: &mut endpoints,
        dt_ms: (world.dt_s * 1000.0).round() as u32,
        clock_ms: 0,
        step: 0,
        flight: 0,
        // The first contact may wait for a process to load its blob.
        timeout: config.startup_timeout,
        step_timeout: config.step_timeout,
        gcs,
        pace: config.realtime.then(Instant::now),
        unknown_sender: 0,
        buf: vec![0u8; 65_536],
    };
    let episode = EpisodeConfig {
        seconds: config.eval.seconds,
        spawn: config.eval.spawn_mode(race_mode),
        seed: config.eval.seed,
    };
    let mut episodes = Vec::with_capacity(config.eval.episodes as usize);
    for i in 0..config.eval.episodes {
        let e = if race_mode {
            run_crew::<2>(&world, &mut lockstep, &episode, u64::from(i), config.record)
        } else {
            run_crew::<1>(&world, &mut lockstep, &episode, u64::from(i), config.record)
        };
        episodes.push(e);
    }
    let wall_s = started.elapsed().as_secs_f64();
    // Shut the controllers down; a process that does not go is killed when dropped.
    let mut out = Vec::new();
    for i in 0..lockstep.links.len() {
        out.clear();
        lockstep.links[i].end.shut_down(&mut out);
        lockstep.send(i, &out);
    }
    let tlog = lockstep.gcs.take_tlog();
    let unknown_sender_frames = lockstep.unknown_sender;
    let links = std::mem::take(&mut lockstep.links);
    drop(lockstep);
    for ep in &mut endpoints {
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
    let metrics: Vec<_> = episodes.iter().map(|e| e.metrics.clone()).collect();
    let opponent = entrants.get(1).map(|e| &e.pilot);
    let report = Report::new(&entrants[0].pilot, opponent, &config.eval, &metrics);
    let controllers = entrants
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
        .collect();
    Ok(RaceOutcome {
        report,
        episodes,
        controllers,
        unknown_sender_frames,
        wall_s,
        tlog,
    })
}
