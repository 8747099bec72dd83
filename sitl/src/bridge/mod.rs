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
//!    fly to (gates are the mission items), `param2` = 1 (reset) and `param3` = the flight
//!    number (increasing; a repeated one is acknowledged and ignored). The controller zeroes
//!    its recurrent state and answers `COMMAND_ACK` with `result_param2` = the flight number;
//!    the simulator waits for every acknowledgement before the flight's first step.
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
//! 4. At the end: `COMMAND_LONG` `MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN` (`param1` = 2), and
//!    the controller exits.
//!
//! With a signing key both ends sign every frame and drop unsigned or wrongly signed ones
//! ([`wire`]). Frames from the wrong system id, stale steps and duplicates are dropped and
//! counted per link. A ground station link ([`gcs`]) streams the race as a vehicle would.

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

/// The simulator's "new flight to gate `gate`" command for system `target`.
pub fn reset_command(target: u8, gate: usize, flight: u32) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: gate as f32,
        param2: 1.0,
        param3: flight as f32,
        command: MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
        target_system: target,
        target_component: AUTOPILOT_COMPONENT_ID,
        ..Default::default()
    })
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
