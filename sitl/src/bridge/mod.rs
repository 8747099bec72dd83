//! The MAVLink bridge: firmware-core controllers as MAVLink endpoints, raced in lockstep by
//! the simulator. This module doc is the protocol's specification; docs/DESIGN.md
//! "SITL over MAVLink" summarises it.
//!
//! # The protocol (MAVLink 2, `common` dialect, UDP on loopback)
//!
//! Each controller ([`fc::serve`], `sitl fc`) owns a UDP port and a system id; it sends as
//! component 1 (`MAV_COMP_ID_AUTOPILOT1`). The simulator ([`race`]) is system
//! [`SIM_SYSTEM_ID`] and the clock: simulated time `t` (ms) advances 20 ms per step.
//!
//! 1. **New flight** (an episode's start, a respawn after a crash): the simulator sends each
//!    controller `COMMAND_LONG` `MAV_CMD_DO_SET_MISSION_CURRENT` with `param1` = the gate to
//!    fly to (gates are the mission items), `param2` = 1 (reset), `param3` = the flight
//!    number (1, 2, …), `param4` = the step period (ms), `param5` and `param6` = the
//!    simulated time of the flight's first step (ms) as its high and low 16 bits (an f32
//!    holds integers exactly only up to 2^24), and `param7` = the opponent's system id (0 in
//!    a time trial); [`NewFlight`] reads and writes it. The controller zeroes its recurrent
//!    state, restarts its lockstep clock at the first step, and answers `COMMAND_ACK` with
//!    `result_param2` = the flight number; the simulator waits for every acknowledgement
//!    before the flight's first step. A reset equal in every field to the current flight's
//!    or to one of the [`fc::RECENT_FLIGHTS`] before it (a duplicate, reordered or replayed
//!    one) is acknowledged again and changes nothing; one with a field out of range is
//!    refused (`MAV_RESULT_DENIED`).
//! 2. **Each step**, one datagram per controller: the other vehicles' states, then its own,
//!    each as `ATTITUDE_QUATERNION` (FRD→NED attitude, FRD rates in rad/s) and
//!    `LOCAL_POSITION_NED` (m, m/s), `time_boot_ms` = `t`, header system id = the vehicle
//!    the state belongs to ([`crate::frames`] has the conversions).
//! 3. The controller answers `HIL_ACTUATOR_CONTROLS` with `time_usec` = `t`·1000 (the
//!    step's time echoed), flag `HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP`, and
//!    `controls[0..4]` = propeller speeds of motors 0–3 in units of
//!    [`MOTOR_RPM_FULL_SCALE`] rpm (a power of two, so the round trip is exact). The
//!    simulator waits for every controller's answer for `t` before it steps the world; a
//!    controller silent past the step timeout is declared failed, its motors are stopped for
//!    the rest of the race, and the result says so.
//!
//!    **Retransmission.** UDP loses datagrams. A request (a new flight, a step) unanswered
//!    for `RaceConfig::resend_after` (25 ms) is encoded again (a signed frame needs a fresh
//!    timestamp) and sent again, until the answer comes or the step timeout passes. Answers
//!    are idempotent: a repeated reset is acknowledged again (above); a repeated request
//!    for the step the controller answered last is answered again from its cache
//!    (`HIL_ACTUATOR_CONTROLS` for the same `t`, the same command), and the pilot never
//!    steps twice. Copies the simulator no longer waits for are counted stale. Both ends
//!    count what they sent again (`LinkStats::resent`).
//! 4. At the end: `COMMAND_LONG` `MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN` (`param1` = 2), and
//!    the controller exits.
//!
//! **Sockets.** The simulator gives each link a UDP socket of its own, connected to its
//! controller's address, and a controller connects its socket to the simulator's address
//! at the first flight: the kernel then delivers each end its peer's datagrams only, so
//! another local socket cannot flood either end (its datagrams are dropped before they can
//! fill the receive buffer the answers wait in).
//!
//! With a signing key both ends sign every frame and drop unsigned or wrongly signed ones
//! ([`wire`]). A ground station link ([`gcs`]) streams the race as a vehicle would.
//!
//! # The lockstep clock against stray frames
//!
//! Each end takes a frame only when it is the one it waits for; every other frame is
//! dropped and counted in the link's [`wire::LinkStats`] (each frame in exactly one
//! counter), and none moves either end's clock:
//!
//! - The controller ([`fc::FlightController`]) expects exactly one step at a time: the
//!   flight's first step, then the step one period after the last it answered (no
//!   look-ahead: the simulator never skips a step). A state stamped earlier is `stale`,
//!   later `future`; before the first flight every state is `future`. States from systems
//!   other than its own and the flight's opponent, and commands from anyone but
//!   [`SIM_SYSTEM_ID`] or addressed to another system, are `wrong_system`. So a state
//!   stamped far ahead (replayed, or corrupted with a valid checksum) is one counted drop,
//!   and a new flight restarts the clock whatever came before: after any datagrams, a new
//!   flight and its steps are answered as by a fresh controller (`tests/link_fuzz.rs`).
//! - The simulator ([`race::ControllerLink`]) takes only the acknowledgement of the flight
//!   it started and the answer for the step it asked; an answer for an earlier step (or an
//!   earlier flight's acknowledgement) is `stale`, for a later one `future`, anything else
//!   but heartbeats `ignored`, and frames from another system id `wrong_system`.
//!
//! What this does not stop: on an unsigned link anyone on the host can forge the frame an
//! end waits for. A forged state for the step a controller expects next is taken and
//! answered; the real request for that step is then answered again from the controller's
//! cache, so the forgery costs exactly that step's command (and, for a recurrent pilot, the
//! one step of memory it fed), and the race goes on (`tests/bridge.rs`
//! `a_forged_state_costs_the_one_step_it_forged`). A forged new flight or shutdown can end
//! that controller's race. Signing stops forgeries, and the
//! signing timestamps drop replays on the stream they were first sent on (not on a stream
//! the receiver has not seen yet).

pub mod fc;
pub mod gcs;
pub mod race;
pub mod wire;

use crate::frames::NedState;
use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::MotorCommand;
use mavlink::dialects::common::{
    ATTITUDE_QUATERNION_DATA, COMMAND_ACK_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA,
    HIL_ACTUATOR_CONTROLS_DATA, HilActuatorControlsFlags, LOCAL_POSITION_NED_DATA, MavAutopilot,
    MavCmd, MavMessage, MavModeFlag, MavResult, MavState, MavType,
};

/// The simulator's own system id (commands it sends come from it).
pub const SIM_SYSTEM_ID: u8 = 250;
/// Component id of every controller: `MAV_COMP_ID_AUTOPILOT1`.
pub const AUTOPILOT_COMPONENT_ID: u8 = 1;
/// The simulator's component id (`MAV_COMP_ID_MISSIONPLANNER`-like: a ground-side tool).
pub const SIM_COMPONENT_ID: u8 = 190;
/// One unit of `HIL_ACTUATOR_CONTROLS.controls` (rpm). Commands follow paper eq. 3, which
/// tops out at 26,043 rpm, so they sit in [0, 0.8).
pub const MOTOR_RPM_FULL_SCALE: f32 = 32_768.0;

/// The two messages carrying one vehicle's state at simulated time `t_ms`.
pub fn state_messages(t_ms: u32, s: &NedState) -> [MavMessage; 2] {
    let q = s.attitude.to_array();
    [
        MavMessage::ATTITUDE_QUATERNION(ATTITUDE_QUATERNION_DATA {
            time_boot_ms: t_ms,
            q1: q[0],
            q2: q[1],
            q3: q[2],
            q4: q[3],
            rollspeed: s.body_rates_radps.x,
            pitchspeed: s.body_rates_radps.y,
            yawspeed: s.body_rates_radps.z,
            ..Default::default()
        }),
        local_position(t_ms, s),
    ]
}

/// `LOCAL_POSITION_NED` of a state at simulated time `t_ms`.
pub fn local_position(t_ms: u32, s: &NedState) -> MavMessage {
    MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
        time_boot_ms: t_ms,
        x: s.position_m.x,
        y: s.position_m.y,
        z: s.position_m.z,
        vx: s.velocity_mps.x,
        vy: s.velocity_mps.y,
        vz: s.velocity_mps.z,
    })
}

/// The simulated time (ms) of a state message; `None` for any other message.
pub fn state_time(m: &MavMessage) -> Option<u32> {
    match m {
        MavMessage::ATTITUDE_QUATERNION(a) => Some(a.time_boot_ms),
        MavMessage::LOCAL_POSITION_NED(p) => Some(p.time_boot_ms),
        _ => None,
    }
}

/// A vehicle's state assembled from its two state messages for one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PartialState {
    /// Time of the messages gathered so far (ms).
    pub t_ms: Option<u32>,
    attitude: Option<(Quat, Vec3)>,
    position: Option<(Vec3, Vec3)>,
}

impl PartialState {
    /// Takes in a state message (others are ignored); a newer time starts over.
    pub fn absorb(&mut self, m: &MavMessage) {
        let Some(t) = state_time(m) else {
            return;
        };
        if self.t_ms.is_none_or(|old| t > old) {
            *self = Self {
                t_ms: Some(t),
                ..Self::default()
            };
        } else if self.t_ms != Some(t) {
            return;
        }
        match m {
            MavMessage::ATTITUDE_QUATERNION(a) => {
                self.attitude = Some((
                    Quat::new(a.q1, a.q2, a.q3, a.q4),
                    Vec3::new(a.rollspeed, a.pitchspeed, a.yawspeed),
                ));
            }
            MavMessage::LOCAL_POSITION_NED(p) => {
                self.position = Some((Vec3::new(p.x, p.y, p.z), Vec3::new(p.vx, p.vy, p.vz)));
            }
            _ => {}
        }
    }

    /// The state at `t_ms` when both messages of that time are in.
    pub fn at(&self, t_ms: u32) -> Option<NedState> {
        match (self.t_ms, self.attitude, self.position) {
            (Some(t), Some((attitude, rates)), Some((position, velocity))) if t == t_ms => {
                Some(NedState {
                    position_m: position,
                    velocity_mps: velocity,
                    attitude,
                    body_rates_radps: rates,
                })
            }
            _ => None,
        }
    }
}

/// The controller's answer for the step at `t_ms`.
pub fn actuator_message(t_ms: u32, command: &MotorCommand) -> MavMessage {
    let mut controls = [0.0f32; 16];
    for (c, rpm) in controls.iter_mut().zip(command.rpm) {
        *c = rpm / MOTOR_RPM_FULL_SCALE;
    }
    MavMessage::HIL_ACTUATOR_CONTROLS(HIL_ACTUATOR_CONTROLS_DATA {
        time_usec: u64::from(t_ms) * 1000,
        flags: HilActuatorControlsFlags::HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP,
        controls,
        mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED
            | MavModeFlag::MAV_MODE_FLAG_HIL_ENABLED
            | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED,
    })
}

/// The motor command in an answer; a non-finite or negative value is a stopped motor.
pub fn command_from_actuators(m: &HIL_ACTUATOR_CONTROLS_DATA) -> MotorCommand {
    MotorCommand {
        rpm: core::array::from_fn(|k| {
            let rpm = m.controls[k] * MOTOR_RPM_FULL_SCALE;
            if rpm.is_finite() { rpm.max(0.0) } else { 0.0 }
        }),
    }
}

/// Largest flight number a new flight may carry: `param3` is an f32, exact for integers up
/// to 2^24 (16.7 million flights).
pub const MAX_FLIGHT_NUMBER: u32 = 1 << 24;
/// Longest step period a new flight may ask for (ms).
pub const MAX_STEP_PERIOD_MS: u32 = 1000;

/// A new flight as the simulator starts it: the fields of its reset command (protocol
/// step 1). Two resets are the same flight when every field is equal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NewFlight {
    /// The flight number (1, 2, … in a race; at most [`MAX_FLIGHT_NUMBER`]).
    pub number: u32,
    /// The gate to fly to (an index into the track's gates).
    pub gate: usize,
    /// The lockstep step period (ms, 1 to [`MAX_STEP_PERIOD_MS`]).
    pub step_period_ms: u32,
    /// The simulated time of the flight's first step (ms).
    pub first_step_ms: u32,
    /// The opponent's system id (`None` in a time trial).
    pub opponent: Option<u8>,
}

/// Why a controller refuses a reset command (it answers `MAV_RESULT_DENIED`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum FlightError {
    /// `param2` is not 1 (only resets are supported).
    NotAReset,
    /// The flight number is not an integer in 1..=[`MAX_FLIGHT_NUMBER`].
    Number,
    /// The gate is not an index into the track's gates.
    Gate,
    /// The step period is not an integer in 1..=[`MAX_STEP_PERIOD_MS`] ms.
    StepPeriod,
    /// The first step's time is not two 16-bit integers.
    FirstStep,
    /// The opponent is not a system id, or is the controller itself.
    Opponent,
}

impl core::fmt::Display for FlightError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NotAReset => "not a reset (param2 is not 1)",
            Self::Number => "flight number out of range",
            Self::Gate => "no such gate",
            Self::StepPeriod => "step period out of range",
            Self::FirstStep => "first step time not two 16-bit integers",
            Self::Opponent => "opponent is not another system id",
        })
    }
}

impl std::error::Error for FlightError {}

/// `x` when it is an integer in `0..=max` (exactly: NaN, infinities and fractions are not).
fn whole(x: f32, max: u32) -> Option<u32> {
    let x = f64::from(x);
    (x >= 0.0 && x <= f64::from(max) && x.fract() == 0.0).then_some(x as u32)
}

impl NewFlight {
    /// The simulator's reset command starting this flight on system `target`.
    pub fn command(&self, target: u8) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: self.gate as f32,
            param2: 1.0,
            param3: self.number as f32,
            param4: self.step_period_ms as f32,
            param5: (self.first_step_ms >> 16) as f32,
            param6: (self.first_step_ms & 0xffff) as f32,
            param7: f32::from(self.opponent.unwrap_or(0)),
            command: MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
            target_system: target,
            target_component: AUTOPILOT_COMPONENT_ID,
            confirmation: 0,
        })
    }

    /// The flight a `MAV_CMD_DO_SET_MISSION_CURRENT` command starts on a track of `gates`
    /// gates, or why it is refused.
    pub fn from_command(c: &COMMAND_LONG_DATA, gates: usize) -> Result<Self, FlightError> {
        if c.param2 != 1.0 {
            return Err(FlightError::NotAReset);
        }
        let number = whole(c.param3, MAX_FLIGHT_NUMBER)
            .filter(|&n| n >= 1)
            .ok_or(FlightError::Number)?;
        let gate = whole(c.param1, u32::MAX)
            .map(|g| g as usize)
            .filter(|&g| g < gates)
            .ok_or(FlightError::Gate)?;
        let step_period_ms = whole(c.param4, MAX_STEP_PERIOD_MS)
            .filter(|&p| p >= 1)
            .ok_or(FlightError::StepPeriod)?;
        let first_step_ms = match (whole(c.param5, 0xffff), whole(c.param6, 0xffff)) {
            (Some(high), Some(low)) => (high << 16) | low,
            _ => return Err(FlightError::FirstStep),
        };
        let opponent = match whole(c.param7, u32::from(u8::MAX)) {
            Some(0) => None,
            Some(id) if id != u32::from(c.target_system) => Some(id as u8),
            _ => return Err(FlightError::Opponent),
        };
        Ok(Self {
            number,
            gate,
            step_period_ms,
            first_step_ms,
            opponent,
        })
    }
}

/// The simulator's "shut down" command for system `target`.
pub fn shutdown_command(target: u8) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: 2.0,
        command: MavCmd::MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN,
        target_system: target,
        target_component: AUTOPILOT_COMPONENT_ID,
        ..Default::default()
    })
}

/// A controller's acknowledgement of `command` (with the flight number for resets).
pub fn ack(command: MavCmd, result: MavResult, flight: u32, to: (u8, u8)) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        result_param2: flight as i32,
        target_system: to.0,
        target_component: to.1,
        ..Default::default()
    })
}

/// The heartbeat of a drone: an armed quadrotor autopilot flying its mission (the gates) in
/// hardware-in-the-loop mode. Controllers send it to the simulator, the simulator to ground
/// stations on each drone's behalf.
pub fn vehicle_heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_GENERIC,
        base_mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED
            | MavModeFlag::MAV_MODE_FLAG_HIL_ENABLED
            | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED,
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motor_commands_cross_the_wire_exactly() {
        for rpm in [0.0, 1.0, 12_345.678, 14_468.43, 21_702.0] {
            let sent = MotorCommand { rpm: [rpm; 4] };
            let MavMessage::HIL_ACTUATOR_CONTROLS(m) = actuator_message(20, &sent) else {
                unreachable!()
            };
            assert_eq!(command_from_actuators(&m), sent);
            assert_eq!(m.time_usec, 20_000);
        }
    }

    fn command_data(m: MavMessage) -> COMMAND_LONG_DATA {
        match m {
            MavMessage::COMMAND_LONG(c) => c,
            other => unreachable!("{other:?}"),
        }
    }

    #[test]
    fn a_new_flight_crosses_the_wire_exactly() {
        for flight in [
            NewFlight {
                number: 1,
                gate: 0,
                step_period_ms: 20,
                first_step_ms: 0,
                opponent: Some(2),
            },
            NewFlight {
                number: MAX_FLIGHT_NUMBER,
                gate: 5,
                step_period_ms: MAX_STEP_PERIOD_MS,
                // Beyond an f32's exact integers: the two halves keep it exact.
                first_step_ms: u32::MAX - 1,
                opponent: None,
            },
        ] {
            let c = command_data(flight.command(1));
            assert_eq!(NewFlight::from_command(&c, 6), Ok(flight));
        }
    }

    #[test]
    fn a_reset_with_a_field_out_of_range_is_refused() {
        let valid = command_data(
            NewFlight {
                number: 3,
                gate: 2,
                step_period_ms: 20,
                first_step_ms: 40,
                opponent: Some(2),
            }
            .command(1),
        );
        assert!(NewFlight::from_command(&valid, 6).is_ok());
        type Edit = fn(&mut COMMAND_LONG_DATA, f32);
        let cases: [(Edit, &[f32], FlightError); 6] = [
            (
                |c, x| c.param1 = x,
                &[-1.0, 6.0, 7.0, 1e9, 2.5, f32::NAN],
                FlightError::Gate,
            ),
            (
                |c, x| c.param2 = x,
                &[0.0, f32::NAN],
                FlightError::NotAReset,
            ),
            (
                |c, x| c.param3 = x,
                &[0.0, -1.0, 1.5, 16_777_218.0, 4.3e9, f32::INFINITY, f32::NAN],
                FlightError::Number,
            ),
            (
                |c, x| c.param4 = x,
                &[0.0, 1001.0, 19.5, f32::NAN],
                FlightError::StepPeriod,
            ),
            (
                |c, x| c.param6 = x,
                &[65_536.0, -1.0, 0.5, f32::NAN],
                FlightError::FirstStep,
            ),
            (
                |c, x| c.param7 = x,
                &[1.0, 256.0, -1.0, f32::NAN],
                FlightError::Opponent,
            ),
        ];
        for (edit, values, why) in cases {
            for &x in values {
                let mut c = valid.clone();
                edit(&mut c, x);
                assert_eq!(NewFlight::from_command(&c, 6), Err(why), "{x}");
            }
        }
    }

    #[test]
    fn a_state_is_complete_only_with_both_messages_of_one_time() {
        let s = NedState {
            position_m: Vec3::new(1.0, 2.0, -3.0),
            velocity_mps: Vec3::new(4.0, 0.5, 0.0),
            attitude: Quat::IDENTITY,
            body_rates_radps: Vec3::new(0.1, 0.2, 0.3),
        };
        let [att, pos] = state_messages(40, &s);
        let [_, old_pos] = state_messages(20, &s);
        let mut p = PartialState::default();
        p.absorb(&att);
        assert_eq!(p.at(40), None);
        p.absorb(&old_pos); // a straggler from the step before is ignored
        assert_eq!(p.at(40), None);
        p.absorb(&pos);
        assert_eq!(p.at(40), Some(s));
        assert_eq!(p.at(60), None);
    }
}
