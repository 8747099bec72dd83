//! Property-based fuzzing of both ends' datagram handling (issue 17), signed and unsigned,
//! without sockets: [`FlightController::handle`] (the controller) and
//! [`ControllerLink::handle`] (the simulator) get arbitrary bytes, mutated valid frames,
//! frames with arbitrary payloads and valid checksums, valid frames with adversarial fields
//! (times, NaN/inf, out-of-range gates and flight numbers, wrong ids), replays and
//! concatenations, interleaved with valid traffic. The properties:
//!
//! - nothing panics;
//! - every frame received is taken or in exactly one drop counter, and every whole frame
//!   of a datagram is accepted or rejected by the decoder;
//! - while the controller flies the valid simulator's flight, each valid step is answered:
//!   no stray frame wedges it (only a state forged for that very step, which it cannot tell
//!   from the real one, may answer the step first);
//! - the simulator takes nothing as an answer but the frame it awaits;
//! - after any such prefix, a valid new flight and its steps are answered exactly as by a
//!   fresh endpoint.

use firmware_core::math::{Quat, Vec3};
use firmware_core::vehicle::MotorCommand;
use mavlink::dialects::common::{
    ATTITUDE_QUATERNION_DATA, COMMAND_ACK_DATA, COMMAND_LONG_DATA, HIL_ACTUATOR_CONTROLS_DATA,
    HilActuatorControlsFlags, LOCAL_POSITION_NED_DATA, MavCmd, MavMessage, MavModeFlag, MavResult,
};
use mavlink::{MavlinkVersion, Message};
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;
use sitl::bridge::fc::{FcConfig, FlightController};
use sitl::bridge::race::{Answer, ControllerLink, Received};
use sitl::bridge::wire::{Codec, LinkStats, signing_key};
use sitl::bridge::{
    AUTOPILOT_COMPONENT_ID, NewFlight, SIM_COMPONENT_ID, SIM_SYSTEM_ID, ack, actuator_message,
    vehicle_heartbeat,
};
use sitl::dynamics::Preset;
use sitl::frames::NedState;
use sitl::pilot::PilotSpec;
use std::sync::OnceLock;
use std::time::Duration;

/// Cases of the controller's properties: each runs up to 48 datagrams of hostile and valid
/// traffic through a row-G (LSTM) controller, then a new flight of up to 4 steps on it and
/// on a fresh twin (about 30 ms a case, most of it parsing the 1.2 MB blob for each).
const CONTROLLER_CASES: u32 = 256;
/// Cases of the simulator's properties (about 1.5 ms a case).
const SIMULATOR_CASES: u32 = 2048;
const OWN: u8 = 1;
const OPPONENT: u8 = 2;
const PERIOD_MS: u32 = 20;

// ---------------------------------------------------------------------------------------
// Hostile frames

/// A system id a hostile frame claims.
fn system_id() -> impl Strategy<Value = u8> {
    prop_oneof![
        3 => Just(OWN),
        2 => Just(OPPONENT),
        2 => Just(SIM_SYSTEM_ID),
        1 => any::<u8>(),
    ]
}

/// A float field: ordinary, or one a parser or a pilot may trip on.
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        6 => -50.0f32..50.0,
        1 => Just(0.0f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
        1 => Just(1e30f32),
        1 => Just(-f32::MAX),
        1 => Just(f32::MIN_POSITIVE / 2.0),
    ]
}

fn quaternion() -> impl Strategy<Value = [f32; 4]> {
    prop_oneof![
        2 => [value(), value(), value(), value()],
        1 => Just([0.0; 4]),
        1 => Just([f32::NAN; 4]),
        1 => Just([1.0, 0.0, 0.0, 0.0]),
    ]
}

/// A time stamp, relative to the step the valid simulator asks next (ms) or absolute.
#[derive(Clone, Copy, Debug)]
enum Stamp {
    /// The step the simulator asks next, plus this (may be 0: the expected step itself).
    Near(i64),
    /// Any time.
    At(u32),
}

impl Stamp {
    fn ms(self, next_ms: u32) -> u32 {
        match self {
            Self::Near(d) => (i64::from(next_ms) + d).clamp(0, i64::from(u32::MAX)) as u32,
            Self::At(t) => t,
        }
    }
}

/// Where the valid traffic stands when a hostile frame is made.
#[derive(Clone, Copy, Debug)]
struct Now {
    /// The step the valid simulator asks next (ms).
    next_ms: u32,
    /// The step it asked last (µs, as answers echo it).
    asked_us: u64,
    /// The flight it started last.
    flight: u32,
}

/// A flight number: the valid simulator's last one plus an offset, or any.
#[derive(Clone, Copy, Debug)]
enum Number {
    Near(i64),
    Any(i32),
}

impl Number {
    fn resolve(self, now: Now) -> i32 {
        match self {
            Self::Near(d) => (i64::from(now.flight) + d) as i32,
            Self::Any(n) => n,
        }
    }
}

fn number() -> impl Strategy<Value = Number> {
    prop_oneof![
        3 => (-1i64..=2).prop_map(Number::Near),
        1 => any::<i32>().prop_map(Number::Any),
        1 => proptest::sample::select(&[0, -1, i32::MAX, i32::MIN, 1 << 24][..]).prop_map(Number::Any),
    ]
}

fn stamp() -> impl Strategy<Value = Stamp> {
    prop_oneof![
        2 => Just(Stamp::Near(0)),
        3 => (-3i64..=3).prop_map(|k| Stamp::Near(k * i64::from(PERIOD_MS))),
        1 => (-100i64..100).prop_map(Stamp::Near),
        1 => Just(Stamp::At(u32::MAX)),
        1 => Just(Stamp::At(u32::MAX - 1)),
        1 => Just(Stamp::At(1 << 31)),
        1 => any::<u32>().prop_map(Stamp::At),
    ]
}

/// A reset command's parameter: one of the values that are valid somewhere, or not.
fn reset_param(valid: &'static [f32]) -> impl Strategy<Value = f32> {
    prop_oneof![
        3 => proptest::sample::select(valid),
        1 => proptest::sample::select(&[
            -1.0f32, 0.5, 1e9, 4.3e9, 16_777_218.0, 65_536.0, 1001.0, f32::NAN,
            f32::INFINITY, -f32::INFINITY,
        ][..]),
    ]
}

/// One hostile frame: a message and the system id it claims.
#[derive(Clone, Debug)]
enum Hostile {
    Attitude {
        from: u8,
        t: Stamp,
        q: [f32; 4],
        rates: [f32; 3],
    },
    Position {
        from: u8,
        t: Stamp,
        p: [f32; 6],
    },
    /// A new flight with adversarial fields (some valid: a forged reset is a new flight).
    Reset {
        from: u8,
        target: u8,
        params: [f32; 7],
        /// The flight number (param 3) relative to the valid one instead of `params`.
        number: Option<Number>,
        /// The first step's time as a stamp (params 5 and 6) instead of `params`.
        first: Option<Stamp>,
    },
    /// A shutdown that is not the simulator's: wrong `param1`, sender or target.
    NotShutdown {
        from: u8,
        target: u8,
        param1: f32,
    },
    /// Another command.
    Command {
        from: u8,
        target: u8,
        command: MavCmd,
    },
    /// An answer or an acknowledgement, to either end.
    Answer {
        from: u8,
        time_usec: AnswerTime,
        controls: [f32; 4],
    },
    Ack {
        from: u8,
        number: Number,
        result: MavResult,
        command: MavCmd,
    },
    Heartbeat {
        from: u8,
    },
}

/// An answer's time: relative to the step asked last (steps), or any.
#[derive(Clone, Copy, Debug)]
enum AnswerTime {
    Asked(i64),
    At(u64),
}

fn hostile() -> impl Strategy<Value = Hostile> {
    prop_oneof![
        4 => (system_id(), stamp(), quaternion(), [value(), value(), value()])
            .prop_map(|(from, t, q, rates)| Hostile::Attitude { from, t, q, rates }),
        4 => (system_id(), stamp(), [value(), value(), value(), value(), value(), value()])
            .prop_map(|(from, t, p)| Hostile::Position { from, t, p }),
        4 => (
            prop_oneof![4 => Just(SIM_SYSTEM_ID), 1 => system_id()],
            prop_oneof![4 => Just(OWN), 1 => system_id()],
            (
                reset_param(&[0.0, 1.0, 3.0, 5.0, 6.0, 7.0]),
                prop_oneof![6 => Just(1.0f32), 1 => Just(0.0f32), 1 => Just(f32::NAN)],
                reset_param(&[1.0, 2.0, 3.0, 4.0, 5.0, 8.0, 16_777_216.0]),
                reset_param(&[20.0, 1.0, 1000.0]),
                reset_param(&[0.0, 1.0, 65_535.0]),
                reset_param(&[0.0, 20.0, 40.0, 65_535.0]),
                reset_param(&[0.0, 2.0, 1.0, 3.0, 255.0, 256.0]),
            ),
            proptest::option::of(number()),
            proptest::option::of(stamp()),
        )
            .prop_map(|(from, target, p, number, first)| Hostile::Reset {
                from,
                target,
                params: [p.0, p.1, p.2, p.3, p.4, p.5, p.6],
                number,
                first,
            }),
        1 => (system_id(), system_id(), prop_oneof![Just(0.0f32), Just(1.0), Just(3.0), Just(f32::NAN), Just(2.0)])
            .prop_filter("not the simulator's shutdown", |&(from, target, p)| {
                !(from == SIM_SYSTEM_ID && target == OWN && p == 2.0)
            })
            .prop_map(|(from, target, param1)| Hostile::NotShutdown { from, target, param1 }),
        1 => (system_id(), system_id(), proptest::sample::select(&[
                MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                MavCmd::MAV_CMD_NAV_LAND,
                MavCmd::MAV_CMD_MISSION_START,
            ][..]))
            .prop_map(|(from, target, command)| Hostile::Command { from, target, command }),
        3 => (
            system_id(),
            prop_oneof![
                3 => (-2i64..=2).prop_map(AnswerTime::Asked),
                1 => Just(AnswerTime::At(u64::MAX)),
                1 => any::<u64>().prop_map(AnswerTime::At),
            ],
            [value(), value(), value(), value()],
        )
            .prop_map(|(from, time_usec, controls)| Hostile::Answer { from, time_usec, controls }),
        2 => (
            system_id(),
            number(),
            proptest::sample::select(&[
                MavResult::MAV_RESULT_ACCEPTED,
                MavResult::MAV_RESULT_DENIED,
                MavResult::MAV_RESULT_FAILED,
            ][..]),
            proptest::sample::select(&[
                MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
                MavCmd::MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN,
            ][..]),
        )
            .prop_map(|(from, number, result, command)| Hostile::Ack { from, number, result, command }),
        1 => system_id().prop_map(|from| Hostile::Heartbeat { from }),
    ]
}

impl Hostile {
    /// The frame's system id and message, times and numbers relative to `now`.
    fn message(&self, now: Now) -> (u8, MavMessage) {
        let Now {
            next_ms, asked_us, ..
        } = now;
        match *self {
            Self::Attitude { from, t, q, rates } => (
                from,
                MavMessage::ATTITUDE_QUATERNION(ATTITUDE_QUATERNION_DATA {
                    time_boot_ms: t.ms(next_ms),
                    q1: q[0],
                    q2: q[1],
                    q3: q[2],
                    q4: q[3],
                    rollspeed: rates[0],
                    pitchspeed: rates[1],
                    yawspeed: rates[2],
                    ..Default::default()
                }),
            ),
            Self::Position { from, t, p } => (
                from,
                MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                    time_boot_ms: t.ms(next_ms),
                    x: p[0],
                    y: p[1],
                    z: p[2],
                    vx: p[3],
                    vy: p[4],
                    vz: p[5],
                }),
            ),
            Self::Reset {
                from,
                target,
                params,
                number,
                first,
            } => (from, reset_frame(target, params, number, first, now)),
            Self::NotShutdown {
                from,
                target,
                param1,
            } => (
                from,
                MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                    param1,
                    command: MavCmd::MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN,
                    target_system: target,
                    target_component: AUTOPILOT_COMPONENT_ID,
                    ..Default::default()
                }),
            ),
            Self::Command {
                from,
                target,
                command,
            } => (
                from,
                MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                    param1: 1.0,
                    command,
                    target_system: target,
                    target_component: AUTOPILOT_COMPONENT_ID,
                    ..Default::default()
                }),
            ),
            Self::Answer {
                from,
                time_usec,
                controls,
            } => (from, answer_frame(time_usec, controls, asked_us)),
            Self::Ack {
                from,
                number,
                result,
                command,
            } => (
                from,
                MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                    command,
                    result,
                    result_param2: number.resolve(now),
                    target_system: SIM_SYSTEM_ID,
                    target_component: SIM_COMPONENT_ID,
                    ..Default::default()
                }),
            ),
            Self::Heartbeat { from } => (from, vehicle_heartbeat()),
        }
    }
}

/// A `MAV_CMD_DO_SET_MISSION_CURRENT` (a new flight) with `params`, its flight number and
/// first step's time resolved against `now` where given.
fn reset_frame(
    target: u8,
    params: [f32; 7],
    number: Option<Number>,
    first: Option<Stamp>,
    now: Now,
) -> MavMessage {
    let p3 = number.map_or(params[2], |n| n.resolve(now) as f32);
    let (mut p5, mut p6) = (params[4], params[5]);
    if let Some(first) = first {
        let t = first.ms(now.next_ms);
        (p5, p6) = ((t >> 16) as f32, (t & 0xffff) as f32);
    }
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: params[0],
        param2: params[1],
        param3: p3,
        param4: params[3],
        param5: p5,
        param6: p6,
        param7: params[6],
        command: MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
        target_system: target,
        target_component: AUTOPILOT_COMPONENT_ID,
        confirmation: 0,
    })
}

/// A lockstep `HIL_ACTUATOR_CONTROLS` answer with `controls`, for the asked step (relative)
/// or an absolute time.
fn answer_frame(time_usec: AnswerTime, controls: [f32; 4], asked_us: u64) -> MavMessage {
    let mut all = [0.0f32; 16];
    all[..4].copy_from_slice(&controls);
    let time_usec = match time_usec {
        AnswerTime::Asked(k) => asked_us.saturating_add_signed(k * i64::from(PERIOD_MS) * 1000),
        AnswerTime::At(t) => t,
    };
    MavMessage::HIL_ACTUATOR_CONTROLS(HIL_ACTUATOR_CONTROLS_DATA {
        time_usec,
        controls: all,
        mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
        flags: HilActuatorControlsFlags::HIL_ACTUATOR_CONTROLS_FLAGS_LOCKSTEP,
    })
}

/// Who signs a hostile datagram's frames.
#[derive(Clone, Copy, Debug)]
enum Signer {
    /// Nobody.
    Unsigned,
    /// Another key.
    WrongKey,
    /// The link's key on another link id (a holder of the key, or frames captured on a
    /// stream the receiver has not seen).
    LinkKey,
}

fn signer() -> impl Strategy<Value = Signer> {
    prop_oneof![
        Just(Signer::Unsigned),
        Just(Signer::WrongKey),
        Just(Signer::LinkKey)
    ]
}

/// The encoders an attacker uses, one per [`Signer`].
struct Attacker {
    unsigned: Codec,
    wrong_key: Codec,
    link_key: Codec,
}

impl Attacker {
    fn new(key: [u8; 32]) -> Self {
        Self {
            unsigned: Codec::new(SIM_COMPONENT_ID, None, 0),
            wrong_key: Codec::new(
                SIM_COMPONENT_ID,
                Some(signing_key("not the link's").expect("key")),
                9,
            ),
            link_key: Codec::new(SIM_COMPONENT_ID, Some(key), 7),
        }
    }

    fn encode(&mut self, signer: Signer, from: u8, m: &MavMessage, out: &mut Vec<u8>) {
        let codec = match signer {
            Signer::Unsigned => &mut self.unsigned,
            Signer::WrongKey => &mut self.wrong_key,
            Signer::LinkKey => &mut self.link_key,
        };
        codec.encode(from, m, out);
    }
}

/// A datagram an attacker sends.
#[derive(Clone, Debug)]
enum Attack {
    /// Arbitrary bytes (sometimes behind a start byte, to reach the parser).
    Bytes(Vec<u8>),
    /// A valid datagram sent earlier (counted back from the latest) with bits flipped and
    /// maybe cut short.
    Mutated {
        back: usize,
        flips: Vec<(usize, u8)>,
        cut: Option<usize>,
    },
    /// Hostile frames back to back.
    Frames(Signer, Vec<Hostile>),
    /// An unsigned frame of message `id` with arbitrary payload bytes and a valid checksum
    /// (fields and enum values no encoder would write).
    Crafted { id: u32, from: u8, payload: Vec<u8> },
    /// A valid datagram sent earlier again (duplicated, reordered, replayed).
    Replay { back: usize },
}

fn attack() -> impl Strategy<Value = Attack> {
    prop_oneof![
        2 => prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..300),
            proptest::collection::vec(any::<u8>(), 0..60).prop_map(|mut v| {
                v.insert(0, 0xfd);
                v
            }),
        ]
        .prop_map(Attack::Bytes),
        3 => (
            0usize..8,
            proptest::collection::vec((any::<usize>(), 1u8..=255), 1..4),
            proptest::option::of(any::<usize>()),
        )
            .prop_map(|(back, flips, cut)| Attack::Mutated { back, flips, cut }),
        6 => (signer(), proptest::collection::vec(hostile(), 1..4))
            .prop_map(|(s, h)| Attack::Frames(s, h)),
        2 => (
            prop_oneof![
                4 => proptest::sample::select(&[0u32, 1, 31, 32, 75, 76, 77, 93][..]),
                1 => 0u32..(1 << 24),
            ],
            system_id(),
            proptest::collection::vec(any::<u8>(), 0..=255),
        )
            .prop_map(|(id, from, payload)| Attack::Crafted { id, from, payload }),
        2 => (0usize..16).prop_map(|back| Attack::Replay { back }),
    ]
}

impl Attack {
    /// The datagram and, when it is made of whole frames, how many.
    fn datagram(
        &self,
        attacker: &mut Attacker,
        sent: &[Vec<u8>],
        now: Now,
    ) -> (Vec<u8>, Option<u64>) {
        let earlier = |back: usize| sent.iter().rev().nth(back % sent.len().max(1));
        match self {
            Self::Bytes(b) => (b.clone(), None),
            Self::Mutated { back, flips, cut } => {
                let Some(mut d) = earlier(*back).cloned() else {
                    return (Vec::new(), Some(0));
                };
                for &(at, bits) in flips {
                    let n = d.len();
                    d[at % n] ^= bits;
                }
                if let Some(cut) = cut {
                    d.truncate(cut % (d.len() + 1));
                }
                (d, None)
            }
            Self::Frames(signer, frames) => {
                let mut d = Vec::new();
                for h in frames {
                    let (from, m) = h.message(now);
                    attacker.encode(*signer, from, &m, &mut d);
                }
                (d, Some(frames.len() as u64))
            }
            Self::Crafted { id, from, payload } => {
                let mut d = vec![0xfd, payload.len() as u8, 0, 0, 0, *from, SIM_COMPONENT_ID];
                d.extend_from_slice(&id.to_le_bytes()[..3]);
                d.extend_from_slice(payload);
                let crc = mavlink::calculate_crc(&d[1..], MavMessage::extra_crc(*id));
                d.extend_from_slice(&crc.to_le_bytes());
                (d, Some(1))
            }
            Self::Replay { back } => match earlier(*back) {
                Some(d) => (d.clone(), Some(frames_in(d))),
                None => (Vec::new(), Some(0)),
            },
        }
    }
}

/// Whole frames in a datagram of valid frames (MAVLink 2: a 12-byte frame plus the payload
/// length in byte 1, plus 13 bytes when signed).
fn frames_in(mut d: &[u8]) -> u64 {
    let mut n = 0;
    while d.len() >= 12 {
        let len = 12 + usize::from(d[1]) + if d[2] & 1 != 0 { 13 } else { 0 };
        d = &d[len.min(d.len())..];
        n += 1;
    }
    n
}

// ---------------------------------------------------------------------------------------
// Valid traffic

fn finite_state() -> impl Strategy<Value = NedState> {
    let v = |r: f32| (-r..r, -r..r, -r..r).prop_map(|(x, y, z)| Vec3::new(x, y, z));
    (
        v(20.0),
        v(8.0),
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0, 0.2f32..1.0),
        v(4.0),
    )
        .prop_map(
            |(position_m, velocity_mps, (x, y, z, w), body_rates_radps)| NedState {
                position_m,
                velocity_mps,
                attitude: Quat::new(w, x, y, z).normalized(),
                body_rates_radps,
            },
        )
}

fn command() -> impl Strategy<Value = MotorCommand> {
    [
        0.0f32..21_702.0,
        0.0f32..21_702.0,
        0.0f32..21_702.0,
        0.0f32..21_702.0,
    ]
    .prop_map(|rpm| MotorCommand { rpm })
}

/// One datagram in a case's prefix.
#[derive(Clone, Debug)]
enum Op {
    /// The valid simulator starts a new flight (and, in the simulator fuzz, the valid
    /// controller acknowledges it).
    Flight {
        gate: usize,
        held: bool,
    },
    /// The valid simulator's next step (the states), and in the simulator fuzz the valid
    /// controller's answer (the command); hostile frames may ride in the same datagram.
    Step {
        own: NedState,
        opponent: NedState,
        command: MotorCommand,
        riders: Option<(bool, Signer, Vec<Hostile>)>,
        held: bool,
    },
    Attack(Attack),
}

// In the simulator fuzz, `held` keeps the valid reply back until the next valid datagram,
// so that hostile ones reach the simulator while it waits.

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        1 => (0usize..6, any::<bool>()).prop_map(|(gate, held)| Op::Flight { gate, held }),
        3 => (
            finite_state(),
            finite_state(),
            command(),
            proptest::option::weighted(
                0.2,
                (any::<bool>(), signer(), proptest::collection::vec(hostile(), 1..3)),
            ),
            any::<bool>(),
        )
            .prop_map(|(own, opponent, command, riders, held)| Op::Step {
                own,
                opponent,
                command,
                riders,
                held,
            }),
        4 => attack().prop_map(Op::Attack),
    ]
}

/// The valid new flight after the prefix: its gate and its steps' states.
fn suffix() -> impl Strategy<Value = (usize, Vec<(NedState, NedState, MotorCommand)>)> {
    (
        0usize..6,
        proptest::collection::vec((finite_state(), finite_state(), command()), 1..=4),
    )
}

// ---------------------------------------------------------------------------------------
// Accounting

/// Valid frames dropped, by any counter but the decoder's.
fn dropped_valid(s: &LinkStats) -> u64 {
    s.stale + s.future + s.wrong_system + s.ignored
}

/// Frames or tails the decoder rejected.
fn defects(s: &LinkStats) -> u64 {
    s.rejected() - s.wrong_system
}

/// Checks one datagram's accounting: every frame the decoder accepted was taken or counted
/// as dropped once, and a datagram of `frames` whole frames has each one accepted or
/// rejected (any other non-empty datagram at least one).
fn check_accounting(
    before: &LinkStats,
    after: &LinkStats,
    taken: u32,
    datagram_len: usize,
    frames: Option<u64>,
) -> Result<(), TestCaseError> {
    let received = after.frames_received - before.frames_received;
    prop_assert_eq!(
        received,
        u64::from(taken) + dropped_valid(after) - dropped_valid(before),
        "accepted frames neither taken nor counted: {:?} -> {:?}",
        before,
        after
    );
    let judged = received + defects(after) - defects(before);
    match frames {
        Some(n) => prop_assert_eq!(judged, n, "{:?} -> {:?}", before, after),
        None => prop_assert!(judged >= u64::from(datagram_len > 0)),
    }
    Ok(())
}

fn key() -> [u8; 32] {
    signing_key("link-fuzz").expect("key")
}

fn stage2() -> &'static PilotSpec {
    static PILOT: OnceLock<PilotSpec> = OnceLock::new();
    PILOT.get_or_init(|| {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../policies/stage2_G.blob");
        PilotSpec::load(path, &Preset::paper()).expect("stage2_G.blob loads")
    })
}

fn fc_config(signed: bool) -> FcConfig {
    FcConfig {
        pilot: stage2().clone(),
        system_id: OWN,
        signing_key: signed.then(key),
        idle_timeout: Duration::from_secs(1),
    }
}

// ---------------------------------------------------------------------------------------
// The controller's end

/// The controller under test, the valid simulator driving it (the simulator's real end),
/// and what the case has sent.
struct ControllerCase<'c> {
    fc: FlightController<'c>,
    sim: ControllerLink,
    attacker: Attacker,
    /// Valid datagrams sent so far (for mutations and replays).
    sent: Vec<Vec<u8>>,
    next_ms: u32,
    flight: u32,
    /// Every flight a hostile reset could have started (the final one must differ).
    forged: Vec<NewFlight>,
    shut_down: bool,
    /// Frames the controller took from the last datagram.
    taken: u32,
    /// The controller flies the valid simulator's current flight (no other flight started
    /// since), so each valid step must be answered...
    in_sync: bool,
    /// ...unless a hostile state for that very step was taken first (a forgery, which the
    /// controller cannot tell from the real state; it answers the step early).
    forged_step: bool,
}

impl ControllerCase<'_> {
    /// Delivers a datagram to the controller and its reply to the simulator; checks the
    /// accounting on both ends.
    fn deliver(&mut self, d: &[u8], frames: Option<u64>) -> Result<Received, TestCaseError> {
        let before = self.fc.summary().link;
        let mut reply = Vec::new();
        let handled = self.fc.handle(d, &mut reply);
        check_accounting(
            &before,
            &self.fc.summary().link,
            handled.taken,
            d.len(),
            frames,
        )?;
        self.shut_down |= handled.shut_down;
        self.taken = handled.taken;
        let before = self.sim.stats();
        let received = self.sim.handle(&reply);
        check_accounting(
            &before,
            &self.sim.stats(),
            received.taken,
            reply.len(),
            Some(frames_in(&reply)),
        )?;
        if let Some(Answer::Command(c)) = received.answer {
            prop_assert!(c.rpm.iter().all(|r| r.is_finite() && *r >= 0.0), "{:?}", c);
        }
        Ok(received)
    }

    fn new_flight(&mut self, number: u32, gate: usize) -> (NewFlight, Vec<u8>) {
        let flight = NewFlight {
            number,
            gate,
            step_period_ms: PERIOD_MS,
            first_step_ms: self.next_ms,
            opponent: Some(OPPONENT),
        };
        let mut d = Vec::new();
        self.sim.start_flight(&flight, &mut d);
        self.flight = number;
        (flight, d)
    }

    fn step(&mut self, own: &NedState, opponent: &NedState) -> Vec<u8> {
        let mut d = Vec::new();
        self.sim
            .ask_step(self.next_ms, &[(OPPONENT, *opponent), (OWN, *own)], &mut d);
        self.next_ms += PERIOD_MS;
        d
    }

    fn run(&mut self, op: &Op) -> Result<(), TestCaseError> {
        match op {
            Op::Flight { gate, .. } => {
                let (_, d) = self.new_flight(self.flight + 1, *gate);
                let flights = self.fc.summary().flights;
                self.deliver(&d, Some(1))?;
                // A forged reset may have started this very flight before: then it is a
                // duplicate, and the flight's clock is whatever came since.
                self.in_sync = self.fc.summary().flights == flights + 1;
                self.forged_step = false;
                self.sent.push(d);
            }
            Op::Step {
                own,
                opponent,
                riders,
                ..
            } => {
                let flights = self.fc.summary().flights;
                let asked_us = u64::from(self.next_ms) * 1000;
                let next_ms = self.next_ms;
                let valid = self.step(own, opponent);
                let mut d = Vec::new();
                let mut frames = 4;
                if let Some((before, signer, hostile)) = riders {
                    let mut extra = Vec::new();
                    let now = Now {
                        next_ms,
                        asked_us,
                        flight: self.flight,
                    };
                    for h in hostile {
                        self.note_forgery(h, now);
                        let (from, m) = h.message(now);
                        self.attacker.encode(*signer, from, &m, &mut extra);
                    }
                    frames += hostile.len() as u64;
                    if *before {
                        d.extend_from_slice(&extra);
                        d.extend_from_slice(&valid);
                    } else {
                        d.extend_from_slice(&valid);
                        d.extend_from_slice(&extra);
                    }
                } else {
                    d = valid.clone();
                }
                let r = self.deliver(&d, Some(frames))?;
                // Riders can change the answer (states for this step after the valid ones)
                // but not stop it, unless they start another flight.
                self.in_sync &= self.fc.summary().flights == flights;
                if self.in_sync && !self.forged_step {
                    prop_assert!(
                        matches!(r.answer, Some(Answer::Command(_))),
                        "a valid step of the current flight was not answered: {:?}",
                        self.fc.summary()
                    );
                }
                self.forged_step = false;
                self.sent.push(valid);
            }
            Op::Attack(a) => {
                let now = self.now();
                if let Attack::Frames(_, hostile) = a {
                    for h in hostile {
                        self.note_forgery(h, now);
                    }
                }
                let (d, frames) = a.datagram(&mut self.attacker, &self.sent, now);
                let flights = self.fc.summary().flights;
                self.deliver(&d, frames)?;
                // A hostile datagram changes the controller only through what it took: a
                // new flight, or a state for the step it expects.
                self.in_sync &= self.fc.summary().flights == flights;
                self.forged_step |= self.taken > 0;
            }
        }
        Ok(())
    }

    fn now(&self) -> Now {
        Now {
            next_ms: self.next_ms,
            asked_us: u64::from(self.next_ms.saturating_sub(PERIOD_MS)) * 1000,
            flight: self.flight,
        }
    }

    /// Remembers the flight a hostile reset would start, if the controller could take it.
    fn note_forgery(&mut self, h: &Hostile, now: Now) {
        if let Hostile::Reset { .. } = h {
            if let (_, MavMessage::COMMAND_LONG(c)) = h.message(now) {
                if let Ok(f) = NewFlight::from_command(&c, 6) {
                    self.forged.push(f);
                }
            }
        }
    }
}

/// Runs `prefix` on a controller, then a valid new flight of `steps` on it and on a fresh
/// twin: both must accept the flight and give the same commands.
fn controller_property(
    signed: bool,
    prefix: &[Op],
    gate: usize,
    steps: &[(NedState, NedState, MotorCommand)],
) -> Result<(), TestCaseError> {
    let config = fc_config(signed);
    let k = signed.then(key);
    let mut case = ControllerCase {
        fc: FlightController::new(&config),
        sim: ControllerLink::new(OWN, k),
        attacker: Attacker::new(key()),
        sent: Vec::new(),
        next_ms: 0,
        flight: 0,
        forged: Vec::new(),
        shut_down: false,
        taken: 0,
        in_sync: false,
        forged_step: false,
    };
    for op in prefix {
        case.run(op)?;
        prop_assert!(
            !case.shut_down,
            "a hostile datagram shut the controller down"
        );
    }
    // The next flight, made distinct from any a hostile reset could have started.
    let mut number = case.flight + 1;
    let (flight, start) = loop {
        let (flight, start) = case.new_flight(number, gate);
        if !case.forged.contains(&flight) {
            break (flight, start);
        }
        number += 1;
    };
    let mut twin_fc = FlightController::new(&config);
    let mut twin_sim = ControllerLink::new(OWN, k);
    let mut exchange = |d: &[u8], twin: &mut ControllerLink| {
        let mut reply = Vec::new();
        twin_fc.handle(d, &mut reply);
        twin.handle(&reply)
    };
    let mut twin_start = Vec::new();
    twin_sim.start_flight(&flight, &mut twin_start);
    prop_assert_eq!(
        exchange(&twin_start, &mut twin_sim).answer,
        Some(Answer::FlightAccepted)
    );
    prop_assert_eq!(
        case.deliver(&start, Some(1))?.answer,
        Some(Answer::FlightAccepted),
        "the new flight after the prefix was not accepted"
    );
    for (i, (own, opponent, _)) in steps.iter().enumerate() {
        let t = case.next_ms;
        let d = case.step(own, opponent);
        let got = case.deliver(&d, Some(4))?;
        let mut twin_d = Vec::new();
        twin_sim.ask_step(t, &[(OPPONENT, *opponent), (OWN, *own)], &mut twin_d);
        let want = exchange(&twin_d, &mut twin_sim);
        prop_assert!(
            matches!(want.answer, Some(Answer::Command(_))),
            "the fresh twin answered step {} with {:?}",
            i,
            want
        );
        prop_assert_eq!(got.answer, want.answer, "step {} of the new flight", i);
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// The simulator's end

/// The simulator's end under test and the valid controller answering it.
struct SimulatorCase {
    link: ControllerLink,
    controller: Codec,
    attacker: Attacker,
    sent: Vec<Vec<u8>>,
    next_ms: u32,
    flight: u32,
    pending: Option<Pending>,
}

/// A valid reply held back.
struct Pending {
    /// The reply (kept for replays and mutations once delivered).
    valid: Vec<u8>,
    /// The reply with any riders.
    datagram: Vec<u8>,
    frames: u64,
    answer: Answer,
    /// The valid frame comes before any hostile one in its datagram.
    first: bool,
}

impl SimulatorCase {
    fn deliver(&mut self, d: &[u8], frames: Option<u64>) -> Result<Received, TestCaseError> {
        let before = self.link.stats();
        let awaiting = self.link.awaiting();
        let received = self.link.handle(d);
        check_accounting(&before, &self.link.stats(), received.taken, d.len(), frames)?;
        if let Some(answer) = received.answer {
            prop_assert!(awaiting, "an answer taken while nothing was awaited");
            prop_assert!(!self.link.awaiting());
            if let Answer::Command(c) = answer {
                prop_assert!(c.rpm.iter().all(|r| r.is_finite() && *r >= 0.0), "{:?}", c);
            }
        }
        Ok(received)
    }

    fn start_flight(&mut self, gate: usize) {
        self.flight += 1;
        let flight = NewFlight {
            number: self.flight,
            gate,
            step_period_ms: PERIOD_MS,
            first_step_ms: self.next_ms,
            opponent: Some(OPPONENT),
        };
        self.link.start_flight(&flight, &mut Vec::new());
    }

    /// The valid controller's acknowledgement of the current flight (after a heartbeat).
    fn acknowledgement(&mut self) -> Vec<u8> {
        let mut d = Vec::new();
        self.controller.encode(OWN, &vehicle_heartbeat(), &mut d);
        let m = ack(
            MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
            MavResult::MAV_RESULT_ACCEPTED,
            self.flight,
            (SIM_SYSTEM_ID, SIM_COMPONENT_ID),
        );
        self.controller.encode(OWN, &m, &mut d);
        d
    }

    /// Asks the next step; the valid controller's answer to it.
    fn step(&mut self, own: &NedState, opponent: &NedState, command: &MotorCommand) -> Vec<u8> {
        let t = self.next_ms;
        self.link
            .ask_step(t, &[(OPPONENT, *opponent), (OWN, *own)], &mut Vec::new());
        self.next_ms += PERIOD_MS;
        let mut d = Vec::new();
        self.controller
            .encode(OWN, &actuator_message(t, command), &mut d);
        d
    }

    /// Delivers the valid reply held back, if any: while the link still waits for it, it
    /// must be taken.
    fn flush(&mut self) -> Result<(), TestCaseError> {
        if let Some(p) = self.pending.take() {
            let awaiting = self.link.awaiting();
            let r = self.deliver(&p.datagram, Some(p.frames))?;
            if awaiting && p.first {
                prop_assert_eq!(r.answer, Some(p.answer));
            }
            self.sent.push(p.valid);
        }
        Ok(())
    }

    fn run(&mut self, op: &Op) -> Result<(), TestCaseError> {
        match op {
            Op::Flight { gate, held } => {
                self.flush()?;
                self.start_flight(*gate);
                let d = self.acknowledgement();
                self.pending = Some(Pending {
                    valid: d.clone(),
                    datagram: d,
                    frames: 2,
                    answer: Answer::FlightAccepted,
                    first: true,
                });
                if !held {
                    self.flush()?;
                }
            }
            Op::Step {
                own,
                opponent,
                command,
                riders,
                held,
            } => {
                self.flush()?;
                let asked_us = u64::from(self.next_ms) * 1000;
                let next_ms = self.next_ms;
                let valid = self.step(own, opponent, command);
                let (mut d, mut frames) = (valid.clone(), 1);
                if let Some((before, signer, hostile)) = riders {
                    let mut extra = Vec::new();
                    let now = Now {
                        next_ms,
                        asked_us,
                        flight: self.flight,
                    };
                    for h in hostile {
                        let (from, m) = h.message(now);
                        self.attacker.encode(*signer, from, &m, &mut extra);
                    }
                    frames += hostile.len() as u64;
                    if *before {
                        extra.extend_from_slice(&valid);
                        d = extra;
                    } else {
                        d.extend_from_slice(&extra);
                    }
                }
                self.pending = Some(Pending {
                    valid,
                    datagram: d,
                    frames,
                    answer: Answer::Command(*command),
                    // Riders ahead of the answer may forge it first.
                    first: !matches!(riders, Some((true, ..))),
                });
                if !held {
                    self.flush()?;
                }
            }
            Op::Attack(a) => {
                let now = Now {
                    next_ms: self.next_ms,
                    asked_us: u64::from(self.next_ms.saturating_sub(PERIOD_MS)) * 1000,
                    flight: self.flight,
                };
                let (d, frames) = a.datagram(&mut self.attacker, &self.sent, now);
                let r = self.deliver(&d, frames)?;
                // Only a frame that is exactly the awaited one (a forgery) may be taken as
                // the answer: never one for another step or flight, a replay, or a mutant.
                // A crafted frame forges when its bytes decode to the awaited message (an
                // empty HIL_ACTUATOR_CONTROLS is MAVLink 2's truncated all-zero one, the
                // awaited answer while the awaited time is 0): unsigned, nothing tells it
                // from the controller's.
                let forges = match a {
                    Attack::Frames(_, hostile) => hostile
                        .iter()
                        .any(|h| self.is_awaited(h.message(now), now.asked_us)),
                    Attack::Crafted { id, from, payload } => {
                        MavMessage::parse(MavlinkVersion::V2, *id, payload)
                            .is_ok_and(|m| self.is_awaited((*from, m), now.asked_us))
                    }
                    _ => false,
                };
                prop_assert!(r.answer.is_none() || forges, "{:?} from {:?}", r, a);
            }
        }
        Ok(())
    }

    /// True when `(from, m)` is what the link awaits if it awaits anything.
    fn is_awaited(&self, (from, m): (u8, MavMessage), asked_us: u64) -> bool {
        from == OWN
            && match m {
                MavMessage::HIL_ACTUATOR_CONTROLS(a) => a.time_usec == asked_us,
                MavMessage::COMMAND_ACK(a) => {
                    a.command == MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT
                        && a.result == MavResult::MAV_RESULT_ACCEPTED
                        && i64::from(a.result_param2) == i64::from(self.flight)
                }
                _ => false,
            }
    }
}

fn simulator_property(
    signed: bool,
    prefix: &[Op],
    gate: usize,
    steps: &[(NedState, NedState, MotorCommand)],
) -> Result<(), TestCaseError> {
    let k = signed.then(key);
    let mut case = SimulatorCase {
        link: ControllerLink::new(OWN, k),
        controller: Codec::new(AUTOPILOT_COMPONENT_ID, k, OWN),
        attacker: Attacker::new(key()),
        sent: Vec::new(),
        next_ms: 0,
        flight: 0,
        pending: None,
    };
    for op in prefix {
        case.run(op)?;
    }
    case.flush()?;
    case.start_flight(gate);
    let d = case.acknowledgement();
    prop_assert_eq!(
        case.deliver(&d, Some(2))?.answer,
        Some(Answer::FlightAccepted)
    );
    for (own, opponent, command) in steps {
        let d = case.step(own, opponent, command);
        prop_assert_eq!(
            case.deliver(&d, Some(1))?.answer,
            Some(Answer::Command(*command))
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: CONTROLLER_CASES, ..ProptestConfig::default() })]

    #[test]
    fn controller_recovers_from_any_datagrams_unsigned(
        prefix in proptest::collection::vec(op(), 0..48),
        (gate, steps) in suffix(),
    ) {
        controller_property(false, &prefix, gate, &steps)?;
    }

    #[test]
    fn controller_recovers_from_any_datagrams_signed(
        prefix in proptest::collection::vec(op(), 0..48),
        (gate, steps) in suffix(),
    ) {
        controller_property(true, &prefix, gate, &steps)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: SIMULATOR_CASES, ..ProptestConfig::default() })]

    #[test]
    fn simulator_recovers_from_any_datagrams_unsigned(
        prefix in proptest::collection::vec(op(), 0..48),
        (gate, steps) in suffix(),
    ) {
        simulator_property(false, &prefix, gate, &steps)?;
    }

    #[test]
    fn simulator_recovers_from_any_datagrams_signed(
        prefix in proptest::collection::vec(op(), 0..48),
        (gate, steps) in suffix(),
    ) {
        simulator_property(true, &prefix, gate, &steps)?;
    }
}
