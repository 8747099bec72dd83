//! One controller as a MAVLink endpoint, the way a flight controller runs in SITL: it
//! receives states, runs its firmware-core pilot once per step, and answers motor commands
//! (protocol in [`super`]). `sitl fc` runs it as its own process; `sitl race --in-process`
//! runs it on a thread.

use super::wire::{Codec, LinkStats};
use super::{
    AUTOPILOT_COMPONENT_ID, PartialState, ack, actuator_message, state_time, vehicle_heartbeat,
};
use crate::pilot::PilotSpec;
use firmware_core::track::Track;
use mavlink::dialects::common::{MavCmd, MavMessage, MavResult};
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

/// What a controller endpoint runs.
#[derive(Clone, Debug)]
pub struct FcConfig {
    /// The pilot: a blob or the baseline.
    pub pilot: PilotSpec,
    /// Its MAVLink system id (1–249).
    pub system_id: u8,
    /// Sign everything sent and require signatures on everything received.
    pub signing_key: Option<[u8; 32]>,
    /// Exit after this long without a valid frame (an orphaned process ends by itself).
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

/// Serves `config` on `socket` until the simulator's shutdown command or the idle timeout.
/// Errors are socket errors only; bad frames are counted in the summary.
pub fn serve(socket: &UdpSocket, config: &FcConfig) -> io::Result<FcSummary> {
    let own = config.system_id;
    let needs_opponent = config.pilot.needs_opponent();
    let mut pilot = config.pilot.build(Track::figure_eight());
    let mut codec = Codec::new(AUTOPILOT_COMPONENT_ID, config.signing_key, own);
    let mut summary = FcSummary::default();
    let mut sim: Option<SocketAddr> = None;
    let mut own_state = PartialState::default();
    let mut opponent = PartialState::default();
    let mut answered: Option<u32> = None;
    let mut flight = 0u32;
    let mut last_valid = Instant::now();
    let mut last_heartbeat: Option<Instant> = None;
    let mut buf = vec![0u8; 65_536];
    let mut out = Vec::with_capacity(512);
    socket.set_read_timeout(Some(Duration::from_millis(100)))?;
    // Runs until the simulator says shut down (true) or goes silent (false).
    summary.shut_down = 'serve: loop {
        // A heartbeat once a second to whoever drives us, as an autopilot does.
        if let Some(peer) = sim {
            if last_heartbeat.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                out.clear();
                codec.encode(own, &vehicle_heartbeat(), &mut out);
                socket.send_to(&out, peer)?;
                last_heartbeat = Some(Instant::now());
            }
        }
        let (n, from) = match socket.recv_from(&mut buf) {
            Ok(r) => r,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                if last_valid.elapsed() > config.idle_timeout {
                    break 'serve false;
                }
                continue;
            }
            // Linux reports an earlier datagram's ICMP "port unreachable" here: not ours.
            Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => continue,
            Err(e) => return Err(e),
        };
        let mut frames = Vec::new();
        codec.decode(&buf[..n], &mut summary.link, |f, _| frames.push(f));
        if frames.is_empty() {
            continue;
        }
        last_valid = Instant::now();
        sim = Some(from);
        out.clear();
        for f in frames {
            let sender = f.header.system_id as u8;
            match &f.message {
                MavMessage::COMMAND_LONG(c) if c.target_system == own => {
                    let to = (sender, f.header.component_id);
                    match c.command {
                        MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT => {
                            let number = c.param3 as u32;
                            if number > flight && c.param1 >= 0.0 {
                                flight = number;
                                summary.flights += 1;
                                pilot.reset(c.param1 as usize);
                                own_state = PartialState::default();
                                opponent = PartialState::default();
                            }
                            let reply = ack(c.command, MavResult::MAV_RESULT_ACCEPTED, number, to);
                            codec.encode(own, &reply, &mut out);
                        }
                        MavCmd::MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN if c.param1 == 2.0 => {
                            let reply = ack(c.command, MavResult::MAV_RESULT_ACCEPTED, 0, to);
                            codec.encode(own, &reply, &mut out);
                            socket.send_to(&out, from)?;
                            break 'serve true;
                        }
                        other => {
                            let reply = ack(other, MavResult::MAV_RESULT_UNSUPPORTED, 0, to);
                            codec.encode(own, &reply, &mut out);
                        }
                    }
                }
                m => match state_time(m) {
                    Some(t) if answered.is_some_and(|a| t <= a) => {
                        summary.link.stale += 1;
                    }
                    Some(_) if sender == own => own_state.absorb(m),
                    Some(_) => opponent.absorb(m),
                    None => {}
                },
            }
        }
        // Step once both the own state and (if observed) the opponent's are in for a time.
        if let Some(t) = own_state.t_ms.filter(|&t| answered.is_none_or(|a| t > a)) {
            let other = opponent.at(t).map(|s| s.to_enu());
            if let Some(me) = own_state.at(t) {
                if !needs_opponent || other.is_some() {
                    let command = pilot.command(&me.to_enu(), other.as_ref());
                    codec.encode(own, &actuator_message(t, &command), &mut out);
                    answered = Some(t);
                    summary.steps += 1;
                }
            }
        }
        if !out.is_empty() {
            socket.send_to(&out, from)?;
        }
    };
    summary.link.frames_sent = codec.frames_encoded();
    Ok(summary)
}
