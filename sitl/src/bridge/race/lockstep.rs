//! The simulator's side of a lockstep race: the clock, one datagram per controller and
//! step, the answers collected within the timeouts.

use super::super::NewFlight;
use super::super::gcs::GroundStation;
use super::launch::Endpoint;
use super::link::{Answer, ControllerLink};
use super::{Entrant, RaceConfig, RaceError};
use crate::frames::NedState;
use crate::referee::Crew;
use crate::world::World;
use firmware_core::vehicle::{MotorCommand, VehicleState};
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

/// What the simulator asked a controller last, kept to ask again when no answer comes.
#[derive(Clone, Debug)]
enum Request {
    /// Start a new flight.
    Flight(NewFlight),
    /// The step at `t_ms`: the `(system id, state)` pairs, the controller's own last.
    Step(u32, Vec<(u8, NedState)>),
}

/// One controller link as the simulator holds it.
pub(super) struct Link {
    pub(super) end: ControllerLink,
    pub(super) addr: SocketAddr,
    pub(super) failure: Option<String>,
    command: MotorCommand,
    request: Option<Request>,
    sent_at: Instant,
    /// The link's own socket, connected to the controller's address (`addr`).
    socket: UdpSocket,
}

impl Link {
    /// True while the link is live and its controller owes an answer.
    fn owes(&self) -> bool {
        self.failure.is_none() && self.end.awaiting()
    }
}

/// The simulator's side of a lockstep race: a [`Crew`] whose pilots are MAVLink endpoints.
///
/// Each link has a socket of its own ([`Link`]), connected to its controller's address: the kernel
/// delivers it that controller's datagrams only, so no other local socket, however fast it
/// sends, can fill the buffer the answers wait in (issue "faults": a flood used to drop both
/// controllers' answers).
pub(super) struct Lockstep<'e> {
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
    resend_after: Duration,
    gcs: GroundStation,
    pace: Option<Instant>,
    buf: Vec<u8>,
}

impl<'e> Lockstep<'e> {
    /// The simulator's side of a race of `entrants` against their started `endpoints`, on
    /// a socket of its own; with the instant the race's wall-clock time counts from.
    pub(super) fn new(
        entrants: &[Entrant],
        endpoints: &'e mut [Endpoint],
        config: &RaceConfig,
        world: &World,
    ) -> Result<(Self, Instant), RaceError> {
        let links = entrants
            .iter()
            .zip(endpoints.iter())
            .map(|(e, ep)| {
                let socket = UdpSocket::bind("127.0.0.1:0")?;
                socket.connect(ep.addr)?;
                socket.set_nonblocking(true)?;
                Ok(Link {
                    end: ControllerLink::new(e.system_id, config.signing_key),
                    addr: ep.addr,
                    failure: None,
                    command: MotorCommand::STOP,
                    request: None,
                    sent_at: Instant::now(),
                    socket,
                })
            })
            .collect::<io::Result<Vec<_>>>()?;
        let ids: Vec<u8> = entrants.iter().map(|e| e.system_id).collect();
        let gcs = GroundStation::new(
            &ids,
            config.gcs,
            config.gcs_rate_hz,
            world.dt_s,
            config.tlog,
        )?;
        let started = Instant::now();
        let lockstep = Self {
            links,
            endpoints,
            dt_ms: (world.dt_s * 1000.0).round() as u32,
            clock_ms: 0,
            step: 0,
            flight: 0,
            // The first contact may wait for a process to load its blob.
            timeout: config.startup_timeout,
            step_timeout: config.step_timeout,
            resend_after: config.resend_after.max(Duration::from_millis(1)),
            gcs,
            pace: config.realtime.then(Instant::now),
            buf: vec![0u8; 65_536],
        };
        Ok((lockstep, started))
    }

    /// Sends each controller the shutdown command and hands back the links and the
    /// telemetry log.
    pub(super) fn shut_down(mut self) -> (Vec<Link>, Vec<u8>) {
        let mut out = Vec::new();
        for i in 0..self.links.len() {
            out.clear();
            self.links[i].end.shut_down(&mut out);
            self.send(i, &out);
        }
        let tlog = self.gcs.take_tlog();
        (self.links, tlog)
    }

    /// Reads datagrams until no live link owes an answer or the timeout passes; a link that
    /// still does is declared failed with `what` in the reason. A request unanswered for
    /// `resend_after` is sent again (lost datagrams, either way). A command answer is kept
    /// in the link's `command`.
    fn collect(&mut self, what: &str) {
        let deadline = Instant::now() + self.timeout;
        while self.links.iter().any(Link::owes) {
            let now = Instant::now();
            for i in 0..self.links.len() {
                if self.links[i].owes() && now >= self.links[i].sent_at + self.resend_after {
                    self.links[i].end.note_resent();
                    self.ask(i);
                }
            }
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
            // Wake for the deadline or the next resend, whichever is first.
            let next_resend = self
                .links
                .iter()
                .filter(|l| l.owes())
                .map(|l| (l.sent_at + self.resend_after).saturating_duration_since(now))
                .min()
                .unwrap_or(self.resend_after);
            let slice = (deadline - now)
                .min(next_resend)
                .max(Duration::from_micros(100));
            match readable(&self.links, slice) {
                Ok(ready) if ready.iter().any(|&r| r) => {
                    for (i, _) in ready.iter().enumerate().filter(|(_, r)| **r) {
                        self.drain(i);
                    }
                }
                Ok(_) => self.check_processes(),
                Err(e) => {
                    for l in self.links.iter_mut().filter(|l| l.owes()) {
                        l.failure = Some(format!("simulator socket error: {e}"));
                    }
                }
            }
        }
    }

    /// Takes every datagram waiting on link `i`'s socket; a command answer is kept in the
    /// link's `command`.
    fn drain(&mut self, i: usize) {
        loop {
            let l = &mut self.links[i];
            match l.socket.recv(&mut self.buf) {
                Ok(n) => {
                    if let Some(Answer::Command(c)) = l.end.handle(&self.buf[..n]).answer {
                        l.command = c;
                    }
                }
                // Linux reports an earlier datagram's ICMP "port unreachable" (a controller
                // not listening yet) on a connected socket: not a datagram, not fatal.
                Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => {
                    self.check_processes();
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) => {
                    if l.owes() {
                        l.failure = Some(format!("simulator socket error: {e}"));
                    }
                    return;
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

    /// Encodes link `i`'s request (anew: a signed frame carries a fresh timestamp) and
    /// sends it.
    fn ask(&mut self, i: usize) {
        let mut out = Vec::with_capacity(256);
        let l = &mut self.links[i];
        match &l.request {
            Some(Request::Flight(flight)) => l.end.start_flight(flight, &mut out),
            Some(Request::Step(t, states)) => l.end.ask_step(*t, states, &mut out),
            None => return,
        }
        l.sent_at = Instant::now();
        self.send(i, &out);
    }

    fn send(&mut self, i: usize, datagram: &[u8]) {
        let l = &mut self.links[i];
        if let Err(e) = l.socket.send(datagram) {
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
            l.request = Some(Request::Flight(flight));
            self.ask(i);
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
            l.request = Some(Request::Step(t, step));
            self.ask(i);
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

/// Which of `links`' sockets have a datagram waiting, after at most `timeout` (`poll(2)`).
#[cfg(unix)]
fn readable(links: &[Link], timeout: Duration) -> io::Result<Vec<bool>> {
    use std::os::fd::AsRawFd;
    let mut fds: Vec<libc::pollfd> = links
        .iter()
        .map(|l| libc::pollfd {
            fd: l.socket.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        })
        .collect();
    // Round up: a wait of 0 ms would spin.
    let ms = timeout.as_micros().div_ceil(1000).min(i32::MAX as u128) as i32;
    // SAFETY: `fds` is a valid, exclusively borrowed array of `fds.len()` pollfd structs
    // for the duration of the call.
    let n = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, ms) };
    if n < 0 {
        let e = io::Error::last_os_error();
        if e.kind() == io::ErrorKind::Interrupted {
            return Ok(vec![false; links.len()]);
        }
        return Err(e);
    }
    // An error condition (e.g. ICMP port unreachable) is read as a datagram would be: the
    // recv reports it.
    Ok(fds
        .iter()
        .map(|f| f.revents & (libc::POLLIN | libc::POLLERR) != 0)
        .collect())
}

/// Which of `links`' sockets have a datagram waiting, after at most `timeout`: without `poll(2)`,
/// by sleeping in slices of 100 µs between non-blocking peeks.
#[cfg(not(unix))]
fn readable(links: &[Link], timeout: Duration) -> io::Result<Vec<bool>> {
    let until = Instant::now() + timeout;
    let mut byte = [0u8; 1];
    loop {
        let ready: Vec<bool> = links
            .iter()
            .map(|l| match l.socket.peek(&mut byte) {
                Ok(_) => true,
                Err(e) => e.kind() != io::ErrorKind::WouldBlock,
            })
            .collect();
        if ready.iter().any(|&r| r) || Instant::now() >= until {
            return Ok(ready);
        }
        std::thread::sleep(Duration::from_micros(100));
    }
}
