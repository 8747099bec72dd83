//! The simulator's end of one controller's link, without the socket.

use super::super::wire::{Codec, LinkStats};
use super::super::{
    NewFlight, SIM_COMPONENT_ID, SIM_SYSTEM_ID, command_from_actuators, shutdown_command,
    state_messages,
};
use crate::frames::NedState;
use firmware_core::vehicle::MotorCommand;
use mavlink::dialects::common::{MavCmd, MavMessage, MavResult};

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
/// against what it waits for ([`crate::bridge`] says which frames it takes). Nothing received
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
    /// Requests sent again ([`ControllerLink::note_resent`]).
    resent: u64,
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
            resent: 0,
        }
    }

    /// Counts a request sent again because its answer did not come in time.
    pub fn note_resent(&mut self) {
        self.resent += 1;
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
            resent: self.resent,
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
