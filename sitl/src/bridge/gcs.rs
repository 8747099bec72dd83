//! The ground-station side of a race: each drone streamed as a vehicle would stream itself
//! to QGroundControl or MAVProxy, and the race recorded as a telemetry log.
//!
//! Per drone (its own system id, component 1): `HEARTBEAT` (type `MAV_TYPE_QUADROTOR`) and
//! `SYS_STATUS` once per simulated second; `ATTITUDE`, `LOCAL_POSITION_NED` and
//! `GLOBAL_POSITION_INT` (around [`GeoOrigin::DEFAULT`]) at the stream rate. Times are
//! simulated: with `sitl race --realtime` they are also wall-clock.
//!
//! A `.tlog` is a sequence of records, each an 8-byte big-endian timestamp (µs since the
//! UNIX epoch) followed by one raw MAVLink frame, the format MAVProxy and pymavlink write
//! and read. The race's log holds the ground-station stream, stamped with the race's start
//! time plus the simulated time.

use super::wire::Codec;
use super::{AUTOPILOT_COMPONENT_ID, local_position, vehicle_heartbeat};
use crate::frames::{GeoOrigin, NedState};
use mavlink::dialects::common::{
    ATTITUDE_DATA, GLOBAL_POSITION_INT_DATA, MavMessage, MavSysStatusSensor, SYS_STATUS_DATA,
};
use std::net::{SocketAddr, UdpSocket};

/// Streams the drones of a race to a ground station and/or a telemetry log.
#[derive(Debug)]
pub struct GroundStation {
    socket: Option<(UdpSocket, SocketAddr)>,
    codecs: Vec<Codec>,
    system_ids: Vec<u8>,
    every_steps: u32,
    steps_per_second: u64,
    origin: GeoOrigin,
    tlog: Option<Vec<u8>>,
    tlog_epoch_us: u64,
    /// Datagrams the ground-station socket could not send.
    pub send_errors: u64,
}

impl GroundStation {
    /// A stream of the vehicles `system_ids` to `to` (if any), at `rate_hz` for the fast
    /// messages given a control period of `dt_s`; with `tlog`, also recorded in memory.
    pub fn new(
        system_ids: &[u8],
        to: Option<SocketAddr>,
        rate_hz: f32,
        dt_s: f32,
        tlog: bool,
    ) -> std::io::Result<Self> {
        let socket = match to {
            Some(addr) => {
                let bind = if addr.is_ipv4() {
                    "0.0.0.0:0"
                } else {
                    "[::]:0"
                };
                Some((UdpSocket::bind(bind)?, addr))
            }
            None => None,
        };
        let tlog_epoch_us = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_micros() as u64)
            .unwrap_or(0);
        Ok(Self {
            socket,
            codecs: system_ids
                .iter()
                .map(|_| Codec::new(AUTOPILOT_COMPONENT_ID, None, 0))
                .collect(),
            system_ids: system_ids.to_vec(),
            every_steps: ((1.0 / (rate_hz.max(0.1) * dt_s)).round() as u32).max(1),
            steps_per_second: ((1.0 / dt_s).round() as u64).max(1),
            origin: GeoOrigin::DEFAULT,
            tlog: tlog.then(Vec::new),
            tlog_epoch_us,
            send_errors: 0,
        })
    }

    /// True when neither a ground station nor a log wants the stream.
    pub fn is_idle(&self) -> bool {
        self.socket.is_none() && self.tlog.is_none()
    }

    /// The messages of step `step` (simulated time `t_ms`) for the drones' `states`;
    /// `link_errors[i]` is the count of frames dropped on drone `i`'s controller link.
    pub fn publish(&mut self, step: u64, t_ms: u32, states: &[NedState], link_errors: &[u64]) {
        if self.is_idle() {
            return;
        }
        let slow = step.is_multiple_of(self.steps_per_second);
        let fast = step.is_multiple_of(u64::from(self.every_steps));
        if !(slow || fast) {
            return;
        }
        let mut datagram = Vec::with_capacity(512);
        for (i, s) in states.iter().enumerate() {
            let (Some(&id), Some(codec)) = (self.system_ids.get(i), self.codecs.get_mut(i)) else {
                continue;
            };
            datagram.clear();
            let mut messages = Vec::with_capacity(5);
            if slow {
                messages.push(vehicle_heartbeat());
                messages.push(sys_status(link_errors.get(i).copied().unwrap_or(0)));
            }
            if fast {
                messages.extend(vehicle_messages(t_ms, s, &self.origin));
            }
            for m in &messages {
                let start = datagram.len();
                codec.encode(id, m, &mut datagram);
                if let Some(log) = &mut self.tlog {
                    let stamp = self.tlog_epoch_us + u64::from(t_ms) * 1000;
                    log.extend_from_slice(&stamp.to_be_bytes());
                    log.extend_from_slice(&datagram[start..]);
                }
            }
            if let Some((socket, to)) = &self.socket {
                if socket.send_to(&datagram, to).is_err() {
                    self.send_errors += 1;
                }
            }
        }
    }

    /// The recorded telemetry log (empty without one).
    pub fn take_tlog(&mut self) -> Vec<u8> {
        self.tlog.take().unwrap_or_default()
    }
}

fn sys_status(errors_comm: u64) -> MavMessage {
    let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
        | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
        | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS
        | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS;
    MavMessage::SYS_STATUS(SYS_STATUS_DATA {
        onboard_control_sensors_present: sensors,
        onboard_control_sensors_enabled: sensors,
        onboard_control_sensors_health: sensors,
        load: 0,
        voltage_battery: u16::MAX,
        current_battery: -1,
        drop_rate_comm: 0,
        errors_comm: errors_comm.min(u64::from(u16::MAX)) as u16,
        battery_remaining: -1,
        ..Default::default()
    })
}

/// ATTITUDE, LOCAL_POSITION_NED and GLOBAL_POSITION_INT of one drone.
fn vehicle_messages(t_ms: u32, s: &NedState, origin: &GeoOrigin) -> [MavMessage; 3] {
    let [roll, pitch, yaw] = s.euler_rad();
    let (lat, lon, alt) = origin.global_int(s.position_m);
    let cm_s = |v: f32| (v * 100.0).round().clamp(-32_768.0, 32_767.0) as i16;
    let heading_cdeg = (yaw.to_degrees().rem_euclid(360.0) * 100.0).round() as u32 % 36_000;
    [
        MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: t_ms,
            roll,
            pitch,
            yaw,
            rollspeed: s.body_rates_radps.x,
            pitchspeed: s.body_rates_radps.y,
            yawspeed: s.body_rates_radps.z,
        }),
        local_position(t_ms, s),
        MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
            time_boot_ms: t_ms,
            lat,
            lon,
            alt,
            relative_alt: (-s.position_m.z * 1000.0).round() as i32,
            vx: cm_s(s.velocity_mps.x),
            vy: cm_s(s.velocity_mps.y),
            vz: cm_s(s.velocity_mps.z),
            hdg: heading_cdeg as u16,
        }),
    ]
}
