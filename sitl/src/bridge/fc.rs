//! One controller as a MAVLink endpoint, the way a flight controller runs in SITL: it
//! receives states, runs its firmware-core pilot once per step, and answers motor commands
//! (protocol in [`super`]). `sitl fc` runs it as its own process; `sitl race --in-process`
//! runs it on a thread.
//!
//! [`FlightController`] is the endpoint without its socket: [`FlightController::handle`]
//! takes one datagram and appends the reply, so every datagram's effect can be tested (and
//! fuzzed) without a network; [`serve`] runs it on a UDP socket.

use super::wire::{Codec, LinkStats};
use super::{
    AUTOPILOT_COMPONENT_ID, NewFlight, PartialState, SIM_SYSTEM_ID, ack, actuator_message,
    state_time, vehicle_heartbeat,
};
use crate::pilot::{Pilot, PilotSpec};
use firmware_core::track::Track;
use firmware_core::vehicle::MotorCommand;
use mavlink::dialects::common::{COMMAND_LONG_DATA, MavCmd, MavMessage, MavResult};
use std::collections::VecDeque;
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

/// How many flights before the current one a controller remembers, so that a duplicated,
/// reordered or replayed reset of one of them is acknowledged and changes nothing.
pub const RECENT_FLIGHTS: usize = 8;

/// What a controller endpoint runs.
#[derive(Clone, Debug)]
pub struct FcConfig {
    /// The pilot: a blob or the baseline.
    pub pilot: PilotSpec,
    /// Its MAVLink system id (1–249).
    pub system_id: u8,
    /// Sign everything sent and require signatures on everything received.
    pub signing_key: Option<[u8; 32]>,
    /// Exit after this long without a frame it could use (an orphaned process ends by
    /// itself).
    pub idle_timeout: Duration,
}

/// How a controller endpoint's session went.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FcSummary {
    /// Steps answered.
    pub steps: u64,
    /// New flights started.
    pub flights: u32,
    /// The link's counters.
    pub link: LinkStats,
    /// True when it ended on the simulator's shutdown command (false: idle timeout).
    pub shut_down: bool,
}

/// What one datagram did to a [`FlightController`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Handled {
    /// Valid frames acted on: a state for the expected step taken in, a new flight started,
    /// the shutdown. Each of the datagram's other frames is in one of the link's counters.
    pub taken: u32,
    /// A new flight started: its sender is the simulator, where replies go from now on.
    pub new_flight: bool,
    /// The simulator's shutdown command came: the endpoint stops.
    pub shut_down: bool,
}

/// The current flight and its lockstep clock.
#[derive(Clone, Copy, Debug)]
struct Flight {
    started: NewFlight,
    /// The simulated time of the one step taken next (ms; past `u32::MAX` once the clock
    /// has run out, when no state matches).
    next_ms: u64,
    /// The step answered last and its answer: a repeated request for it (the simulator
    /// retransmits when the answer is lost) is answered again from here, never stepped
    /// twice.
    answered: Option<(u32, MotorCommand)>,
}

/// A controller endpoint without its socket: the pilot, the link's codec and counters, and
/// the lockstep clock ([`super`] says which frames it takes).
pub struct FlightController<'p> {
    own: u8,
    needs_opponent: bool,
    gates: usize,
    pilot: Box<dyn Pilot + 'p>,
    codec: Codec,
    stats: LinkStats,
    flight: Option<Flight>,
    /// The flights before the current one, oldest first (at most [`RECENT_FLIGHTS`]).
    recent: VecDeque<NewFlight>,
    own_state: PartialState,
    opponent: PartialState,
    steps: u64,
    flights: u32,
    shut_down: bool,
    /// The datagram being handled repeats the request of the step answered last.
    repeated: bool,
}

impl<'p> FlightController<'p> {
    /// A controller for `config`, before its first flight.
    pub fn new(config: &'p FcConfig) -> Self {
        let track = Track::figure_eight();
        Self {
            own: config.system_id,
            needs_opponent: config.pilot.needs_opponent(),
            gates: track.len(),
            pilot: config.pilot.build(track),
            codec: Codec::new(AUTOPILOT_COMPONENT_ID, config.signing_key, config.system_id),
            stats: LinkStats::default(),
            flight: None,
            recent: VecDeque::with_capacity(RECENT_FLIGHTS),
            own_state: PartialState::default(),
            opponent: PartialState::default(),
            steps: 0,
            flights: 0,
            shut_down: false,
            repeated: false,
        }
    }

    /// Takes one datagram: appends the replies (acknowledgements, the step's answer) to
    /// `out`, counts every frame it drops, and says what it took.
    pub fn handle(&mut self, datagram: &[u8], out: &mut Vec<u8>) -> Handled {
        let mut frames = Vec::new();
        self.codec
            .decode(datagram, &mut self.stats, |f, _| frames.push(f));
        let flights = self.flights;
        let steps = self.steps;
        self.repeated = false;
        let mut handled = Handled::default();
        for f in frames {
            let sender = f.header.system_id;
            let taken = if self.shut_down {
                // Frames after the shutdown in its datagram: nothing is done any more.
                self.stats.ignored += 1;
                false
            } else if let MavMessage::COMMAND_LONG(c) = &f.message {
                self.command(sender, f.header.component_id, c, out)
            } else {
                self.state(sender, &f.message)
            };
            handled.taken += u32::from(taken);
        }
        if !self.shut_down {
            self.step(out);
        }
        if self.repeated && self.steps == steps && !self.shut_down {
            // A retransmitted request for the step answered last: its answer was lost, so
            // it goes again, once per datagram; the pilot does not step again.
            if let Some((t, command)) = self.flight.and_then(|f| f.answered) {
                self.codec
                    .encode(self.own, &actuator_message(t, &command), out);
                self.stats.resent += 1;
            }
        }
        handled.new_flight = self.flights != flights;
        handled.shut_down = self.shut_down;
        handled
    }

    /// Appends the controller's heartbeat to `out`.
    pub fn heartbeat(&mut self, out: &mut Vec<u8>) {
        self.codec.encode(self.own, &vehicle_heartbeat(), out);
    }

    /// The session so far.
    pub fn summary(&self) -> FcSummary {
        FcSummary {
            steps: self.steps,
            flights: self.flights,
            link: LinkStats {
                frames_sent: self.codec.frames_encoded(),
                ..self.stats
            },
            shut_down: self.shut_down,
        }
    }

    /// A command: taken when it starts a new flight or shuts down.
    fn command(
        &mut self,
        sender: u32,
        component: u8,
        c: &COMMAND_LONG_DATA,
        out: &mut Vec<u8>,
    ) -> bool {
        if c.target_system != self.own || sender != u32::from(SIM_SYSTEM_ID) {
            self.stats.wrong_system += 1;
            return false;
        }
        let to = (SIM_SYSTEM_ID, component);
        let (result, number, taken) = match c.command {
            MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT => {
                match NewFlight::from_command(c, self.gates) {
                    Ok(flight) if self.knows(&flight) => {
                        // A duplicate: acknowledged again (the first answer may be lost).
                        self.stats.stale += 1;
                        (MavResult::MAV_RESULT_ACCEPTED, flight.number, false)
                    }
                    Ok(flight) => {
                        self.start(flight);
                        (MavResult::MAV_RESULT_ACCEPTED, flight.number, true)
                    }
                    Err(_) => {
                        self.stats.ignored += 1;
                        (MavResult::MAV_RESULT_DENIED, c.param3 as u32, false)
                    }
                }
            }
            MavCmd::MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN if c.param1 == 2.0 => {
                self.shut_down = true;
                (MavResult::MAV_RESULT_ACCEPTED, 0, true)
            }
            _ => {
                self.stats.ignored += 1;
                (MavResult::MAV_RESULT_UNSUPPORTED, 0, false)
            }
        };
        self.codec
            .encode(self.own, &ack(c.command, result, number, to), out);
        taken
    }

    /// True when `flight` is the current flight or one of the [`RECENT_FLIGHTS`] before.
    fn knows(&self, flight: &NewFlight) -> bool {
        self.flight.is_some_and(|f| f.started == *flight) || self.recent.contains(flight)
    }

    /// Starts `flight`: the pilot's recurrent state zeroed, the clock at its first step.
    fn start(&mut self, flight: NewFlight) {
        if let Some(previous) = self.flight.take() {
            if self.recent.len() == RECENT_FLIGHTS {
                self.recent.pop_front();
            }
            self.recent.push_back(previous.started);
        }
        self.flight = Some(Flight {
            started: flight,
            next_ms: u64::from(flight.first_step_ms),
            answered: None,
        });
        self.flights += 1;
        self.pilot.reset(flight.gate);
        self.own_state = PartialState::default();
        self.opponent = PartialState::default();
    }

    /// Any message but a command: taken when it is a state of the own vehicle or the
    /// flight's opponent for the step expected.
    fn state(&mut self, sender: u32, m: &MavMessage) -> bool {
        let Some(t) = state_time(m) else {
            self.stats.ignored += 1;
            return false;
        };
        let Some(flight) = &self.flight else {
            // No flight, no step asked yet.
            self.stats.future += 1;
            return false;
        };
        let own = sender == u32::from(self.own);
        let opponent = flight
            .started
            .opponent
            .is_some_and(|o| sender == u32::from(o));
        let t_ms = u64::from(t);
        if !own && !opponent {
            self.stats.wrong_system += 1;
        } else if t_ms < flight.next_ms {
            self.stats.stale += 1;
            if own && flight.answered.is_some_and(|(a, _)| u64::from(a) == t_ms) {
                self.repeated = true;
            }
        } else if t_ms > flight.next_ms {
            self.stats.future += 1;
        } else {
            if own {
                self.own_state.absorb(m);
            } else {
                self.opponent.absorb(m);
            }
            return true;
        }
        false
    }

    /// Answers the expected step once its own state (and the opponent's, when the pilot
    /// observes one) is complete, and moves the clock one period on.
    fn step(&mut self, out: &mut Vec<u8>) {
        let Some(flight) = &mut self.flight else {
            return;
        };
        let Ok(t) = u32::try_from(flight.next_ms) else {
            return;
        };
        let Some(me) = self.own_state.at(t) else {
            return;
        };
        let other = self.opponent.at(t).map(|s| s.to_enu());
        if self.needs_opponent && other.is_none() {
            return;
        }
        let command = self.pilot.command(&me.to_enu(), other.as_ref());
        self.codec
            .encode(self.own, &actuator_message(t, &command), out);
        flight.answered = Some((t, command));
        flight.next_ms += u64::from(flight.started.step_period_ms);
        self.steps += 1;
    }
}

/// Serves `config` on `socket` until the simulator's shutdown command or the idle timeout.
/// Errors are socket errors only; dropped frames are counted in the summary.
pub fn serve(socket: &UdpSocket, config: &FcConfig) -> io::Result<FcSummary> {
    let mut fc = FlightController::new(config);
    // Where the first flight came from. The socket is then connected to it: replies go
    // there, and the kernel delivers that address's datagrams only, so no other local
    // socket can flood the controller off the race (issue "faults").
    let mut sim: Option<SocketAddr> = None;
    let mut last_taken = Instant::now();
    let mut last_heartbeat: Option<Instant> = None;
    let mut buf = vec![0u8; 65_536];
    let mut out = Vec::with_capacity(512);
    socket.set_read_timeout(Some(Duration::from_millis(100)))?;
    loop {
        // A heartbeat once a second to whoever drives us, as an autopilot does.
        if sim.is_some() && last_heartbeat.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
            out.clear();
            fc.heartbeat(&mut out);
            send(socket, &out)?;
            last_heartbeat = Some(Instant::now());
        }
        let (n, from) = match socket.recv_from(&mut buf) {
            Ok(r) => r,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                if last_taken.elapsed() > config.idle_timeout {
                    break;
                }
                continue;
            }
            // Linux reports an earlier datagram's ICMP "port unreachable" here: not ours.
            Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => continue,
            Err(e) => return Err(e),
        };
        out.clear();
        let handled = fc.handle(&buf[..n], &mut out);
        if handled.taken > 0 {
            last_taken = Instant::now();
        }
        if handled.new_flight && sim.is_none() {
            socket.connect(from)?;
            sim = Some(from);
        }
        if !out.is_empty() {
            if sim.is_some() {
                send(socket, &out)?;
            } else {
                socket.send_to(&out, from)?;
            }
        }
        if handled.shut_down {
            break;
        }
    }
    Ok(fc.summary())
}

/// Sends on the connected socket; a peer not listening (an ICMP error from an earlier
/// datagram) is not an error here: the simulator retransmits or has gone.
fn send(socket: &UdpSocket, datagram: &[u8]) -> io::Result<()> {
    match socket.send(datagram) {
        Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => Ok(()),
        r => r.map(|_| ()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bridge::race::{Answer, ControllerLink, Received};
    use crate::bridge::state_messages;
    use crate::dynamics::Preset;
    use crate::frames::NedState;
    use firmware_core::math::{Quat, Vec3};

    fn state(x: f32) -> NedState {
        NedState {
            position_m: Vec3::new(x, 0.0, -1.0),
            velocity_mps: Vec3::new(1.0, 0.0, 0.0),
            attitude: Quat::IDENTITY,
            body_rates_radps: Vec3::ZERO,
        }
    }

    fn flight(number: u32, first_step_ms: u32) -> NewFlight {
        NewFlight {
            number,
            gate: 1,
            step_period_ms: 20,
            first_step_ms,
            opponent: None,
        }
    }

    /// Delivers `datagram` to the controller and its reply to the simulator's end.
    fn exchange(fc: &mut FlightController, sim: &mut ControllerLink, datagram: &[u8]) -> Received {
        let mut reply = Vec::new();
        fc.handle(datagram, &mut reply);
        sim.handle(&reply)
    }

    #[test]
    fn only_the_expected_step_is_taken_and_a_new_flight_restarts_the_clock() {
        let config = FcConfig {
            pilot: PilotSpec::load("baseline", &Preset::paper()).unwrap(),
            system_id: 1,
            signing_key: None,
            idle_timeout: Duration::from_secs(1),
        };
        let mut fc = FlightController::new(&config);
        let mut sim = ControllerLink::new(1, None);
        let mut forger = Codec::new(AUTOPILOT_COMPONENT_ID, None, 0);
        let mut out = Vec::new();
        let ask = |sim: &mut ControllerLink, t: u32, out: &mut Vec<u8>| {
            out.clear();
            sim.ask_step(t, &[(1, state(t as f32 / 1000.0))], out);
        };
        sim.start_flight(&flight(1, 0), &mut out);
        let r = exchange(&mut fc, &mut sim, &out);
        assert_eq!(r.answer, Some(Answer::FlightAccepted));
        ask(&mut sim, 0, &mut out);
        assert!(matches!(
            exchange(&mut fc, &mut sim, &out).answer,
            Some(Answer::Command(_))
        ));

        // A complete state stamped far ahead: counted, not answered, the clock stays.
        let mut forged = Vec::new();
        for m in state_messages(u32::MAX - 1, &state(9.0)) {
            forger.encode(1, &m, &mut forged);
        }
        let mut reply = Vec::new();
        assert_eq!(fc.handle(&forged, &mut reply).taken, 0);
        assert!(reply.is_empty());
        assert_eq!(fc.summary().link.future, 2);
        ask(&mut sim, 20, &mut out);
        let Some(Answer::Command(first)) = exchange(&mut fc, &mut sim, &out).answer else {
            panic!("step 20 was not answered");
        };
        // The same step again (a retransmission after a lost answer, or a duplicate): the
        // cached answer goes again, the pilot does not step; a simulator that already has
        // the answer counts the copy stale, one still waiting takes it.
        let steps = fc.summary().steps;
        let mut reply = Vec::new();
        fc.handle(&out, &mut reply);
        assert_eq!(sim.handle(&reply), Received::default());
        let mut waiting = ControllerLink::new(1, None);
        waiting.ask_step(20, &[(1, state(0.02))], &mut Vec::new());
        assert_eq!(
            waiting.handle(&reply).answer,
            Some(Answer::Command(first)),
            "the repeated answer is the first"
        );
        let s = fc.summary();
        assert_eq!((s.steps, s.link.stale, s.link.resent), (steps, 2, 1));

        // A new flight that starts behind the controller's clock (one a replayed or
        // forged reset had moved ahead) is taken, and its steps are answered.
        out.clear();
        sim.start_flight(&flight(2, 20), &mut out);
        assert_eq!(
            exchange(&mut fc, &mut sim, &out).answer,
            Some(Answer::FlightAccepted)
        );
        ask(&mut sim, 20, &mut out);
        assert!(matches!(
            exchange(&mut fc, &mut sim, &out).answer,
            Some(Answer::Command(_))
        ));
        // The first flight's reset again: a duplicate, acknowledged, nothing else.
        let mut old = Vec::new();
        ControllerLink::new(1, None).start_flight(&flight(1, 0), &mut old);
        reply.clear();
        assert_eq!(fc.handle(&old, &mut reply).taken, 0);
        let s = fc.summary();
        assert_eq!((s.steps, s.flights, s.link.stale), (3, 2, 3));
        // Every frame was taken (two resets, three steps of two messages) or counted.
        assert_eq!(s.link.frames_received, 8 + s.link.dropped());
    }
}
