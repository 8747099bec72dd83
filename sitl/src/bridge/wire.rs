//! MAVLink 2 frames on the wire: encoding, decoding with every defect counted, and message
//! signing (SHA-256/48 as in the MAVLink signing spec).
//!
//! A datagram may carry several frames back to back (the simulator sends a step's state
//! messages in one datagram); decoding walks them and stops at the first byte that cannot
//! start a frame. Nothing here panics on input: a defect is a [`Reject`] and a counter.

use mavlink::dialects::common::MavMessage;
use mavlink::{MAVLinkV2MessageRaw, MavHeader, MavlinkVersion, Message};
use serde::Serialize;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::time::{SystemTime, UNIX_EPOCH};

/// MAVLink 2 start byte.
const STX_V2: u8 = 0xFD;
/// Start byte, length, flags ×2, sequence, system, component, message id ×3.
const HEADER_LEN: usize = 10;
/// CRC-16 after the payload.
const CRC_LEN: usize = 2;
/// Link id, 48-bit timestamp, 48-bit signature.
const SIGNATURE_LEN: usize = 13;
/// Incompatibility flag: the frame is signed.
const IFLAG_SIGNED: u8 = 0x01;
/// Signing timestamps count 10 µs units since 2015-01-01 00:00:00 UTC.
const SIGNING_EPOCH_UNIX_S: u64 = 1_420_070_400;

/// Why a frame was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reject {
    /// Not a MAVLink 2 frame, cut short, or with flags this link does not speak.
    Malformed,
    /// The checksum does not match (corrupted, or a message id unknown to `common`).
    BadCrc,
    /// The payload does not decode as its message.
    BadPayload,
    /// Unsigned while this link requires signatures.
    Unsigned,
    /// The signature does not match the link's key.
    BadSignature,
    /// Signed with a timestamp not newer than the last one of its stream (a replay).
    Replayed,
}

/// Counters of one link, as the race result reports them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LinkStats {
    /// Frames sent (encoded for the link: [`Codec::frames_encoded`]).
    pub frames_sent: u64,
    /// Frames received and accepted.
    pub frames_received: u64,
    /// [`Reject::Malformed`] frames or datagram tails.
    pub malformed: u64,
    /// [`Reject::BadCrc`] frames.
    pub bad_crc: u64,
    /// [`Reject::BadPayload`] frames.
    pub bad_payload: u64,
    /// [`Reject::Unsigned`] frames.
    pub unsigned: u64,
    /// [`Reject::BadSignature`] frames.
    pub bad_signature: u64,
    /// [`Reject::Replayed`] frames.
    pub replayed: u64,
    /// Valid frames from a system this link does not belong to (or, for commands, addressed
    /// to one).
    pub wrong_system: u64,
    /// Valid frames for a step or a flight already handled (duplicates, stragglers, replays
    /// of old resets).
    pub stale: u64,
    /// Frames sent again: a controller's answer to a repeated request for the step it
    /// answered last (the first answer was lost), a simulator's request when no answer came
    /// in time (the lockstep's retransmission).
    pub resent: u64,
    /// Valid frames stamped for a step not yet asked, or acknowledging a flight not yet
    /// started: dropped, they never move the lockstep clock.
    pub future: u64,
    /// Valid frames this end takes no action on: messages it does not use, and commands it
    /// refuses (a new flight with an out-of-range field, an unsupported command).
    pub ignored: u64,
}

impl LinkStats {
    /// Counts a rejected frame.
    pub fn count(&mut self, r: Reject) {
        let c = match r {
            Reject::Malformed => &mut self.malformed,
            Reject::BadCrc => &mut self.bad_crc,
            Reject::BadPayload => &mut self.bad_payload,
            Reject::Unsigned => &mut self.unsigned,
            Reject::BadSignature => &mut self.bad_signature,
            Reject::Replayed => &mut self.replayed,
        };
        *c += 1;
    }

    /// Frames dropped as defective or foreign: everything but [`LinkStats::stale`],
    /// [`LinkStats::future`] and [`LinkStats::ignored`] (the valid frames of the peer that
    /// came at the wrong time or asked for nothing this end does).
    pub fn rejected(&self) -> u64 {
        self.malformed
            + self.bad_crc
            + self.bad_payload
            + self.unsigned
            + self.bad_signature
            + self.replayed
            + self.wrong_system
    }

    /// Frames dropped for any reason: every frame or datagram tail received and not acted
    /// on is in exactly one counter.
    pub fn dropped(&self) -> u64 {
        self.rejected() + self.stale + self.future + self.ignored
    }
}

/// A 32-byte MAVLink signing key from `--signing-key`: 64 hex digits, or any other text as a
/// passphrase hashed with SHA-256 (as MAVProxy's `signing setup` does).
pub fn signing_key(spec: &str) -> Result<[u8; 32], String> {
    if spec.is_empty() {
        return Err("the signing key is empty".into());
    }
    let hex = spec.len() == 64 && spec.bytes().all(|b| b.is_ascii_hexdigit());
    if hex {
        let mut key = [0u8; 32];
        for (i, k) in key.iter_mut().enumerate() {
            *k = u8::from_str_radix(&spec[2 * i..2 * i + 2], 16)
                .map_err(|e| format!("signing key: {e}"))?;
        }
        Ok(key)
    } else {
        Ok(Sha256::digest(spec.as_bytes()).into())
    }
}

/// Signing state of one endpoint: the key, the link id it signs with, its last outgoing
/// timestamp and the last timestamp seen per incoming stream.
#[derive(Clone, Debug)]
struct Signing {
    key: [u8; 32],
    link_id: u8,
    last_sent: u64,
    last_seen: HashMap<(u8, u8, u8), u64>,
}

fn signing_now() -> u64 {
    let since = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0);
    since.saturating_sub(SIGNING_EPOCH_UNIX_S * 1_000_000) / 10
}

/// One endpoint's encoder and decoder: sequence numbers, optional signing.
#[derive(Clone, Debug)]
pub struct Codec {
    sequence: u8,
    encoded: u64,
    component_id: u8,
    signing: Option<Signing>,
}

/// A decoded, accepted frame.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Its header (sender system and component, sequence).
    pub header: MavHeader,
    /// The message.
    pub message: MavMessage,
}

impl Codec {
    /// An endpoint sending as component `component_id`; with `key`, it signs everything it
    /// sends (link id `link_id`) and accepts only frames signed with the same key.
    pub fn new(component_id: u8, key: Option<[u8; 32]>, link_id: u8) -> Self {
        Self {
            sequence: 0,
            encoded: 0,
            component_id,
            signing: key.map(|key| Signing {
                key,
                link_id,
                last_sent: 0,
                last_seen: HashMap::new(),
            }),
        }
    }

    /// Appends `message`, sent as system `system_id`, to `out` as one frame.
    pub fn encode(&mut self, system_id: u8, message: &MavMessage, out: &mut Vec<u8>) {
        let header = MavHeader {
            system_id: u32::from(system_id),
            component_id: self.component_id,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        self.encoded += 1;
        let mut raw = MAVLinkV2MessageRaw::new();
        match &mut self.signing {
            None => raw.serialize_message(header, message),
            Some(s) => {
                raw.serialize_message_for_signing(header, message);
                s.last_sent = signing_now().max(s.last_sent + 1);
                *raw.signature_link_id_mut() = s.link_id;
                raw.signature_timestamp_bytes_mut()
                    .copy_from_slice(&s.last_sent.to_le_bytes()[..6]);
                let mut sig = [0u8; 6];
                raw.calculate_signature(&s.key, &mut sig);
                raw.signature_value_mut().copy_from_slice(&sig);
            }
        }
        out.extend_from_slice(raw.raw_bytes());
    }

    /// Frames encoded so far (a link's `frames_sent`).
    pub fn frames_encoded(&self) -> u64 {
        self.encoded
    }

    /// Decodes every frame of a datagram: accepted frames go to `accept` with their raw
    /// bytes, defects to `stats`.
    pub fn decode(
        &mut self,
        datagram: &[u8],
        stats: &mut LinkStats,
        mut accept: impl FnMut(Frame, &[u8]),
    ) {
        let mut rest = datagram;
        while !rest.is_empty() {
            match self.decode_one(rest) {
                Ok((frame, len)) => {
                    stats.frames_received += 1;
                    accept(frame, &rest[..len]);
                    rest = &rest[len..];
                }
                Err((reject, Some(len))) => {
                    stats.count(reject);
                    rest = &rest[len..];
                }
                Err((reject, None)) => {
                    // No frame boundary to resynchronise on: drop the rest of the datagram.
                    stats.count(reject);
                    return;
                }
            }
        }
    }

    /// The first frame of `bytes` and its length, or why it is rejected (with its length
    /// when the frame's extent is known).
    fn decode_one(&mut self, bytes: &[u8]) -> Result<(Frame, usize), (Reject, Option<usize>)> {
        if bytes.len() < HEADER_LEN + CRC_LEN || bytes[0] != STX_V2 {
            return Err((Reject::Malformed, None));
        }
        let payload_len = usize::from(bytes[1]);
        let flags = bytes[2];
        if flags & !IFLAG_SIGNED != 0 {
            return Err((Reject::Malformed, None));
        }
        let signed = flags & IFLAG_SIGNED != 0;
        let len = HEADER_LEN + payload_len + CRC_LEN + if signed { SIGNATURE_LEN } else { 0 };
        if bytes.len() < len {
            return Err((Reject::Malformed, None));
        }
        let mut raw = MAVLinkV2MessageRaw::new();
        raw.as_mut_slice()[..len].copy_from_slice(&bytes[..len]);
        if !raw.has_valid_crc::<MavMessage>() {
            return Err((Reject::BadCrc, Some(len)));
        }
        if let Some(s) = &mut self.signing {
            if !signed {
                return Err((Reject::Unsigned, Some(len)));
            }
            let mut sig = [0u8; 6];
            raw.calculate_signature(&s.key, &mut sig);
            if sig != raw.signature_value() {
                return Err((Reject::BadSignature, Some(len)));
            }
            let stream = (
                raw.signature_link_id(),
                bytes[5], // system id
                raw.component_id(),
            );
            let stamp = raw.signature_timestamp();
            if s.last_seen.get(&stream).is_some_and(|&last| stamp <= last) {
                return Err((Reject::Replayed, Some(len)));
            }
            s.last_seen.insert(stream, stamp);
        }
        let message = MavMessage::parse(MavlinkVersion::V2, raw.message_id(), raw.payload())
            .map_err(|_| (Reject::BadPayload, Some(len)))?;
        Ok((
            Frame {
                header: MavHeader {
                    system_id: raw.system_id(),
                    component_id: raw.component_id(),
                    sequence: raw.sequence(),
                },
                message,
            },
            len,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA};

    fn position(t: u32) -> MavMessage {
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: t,
            x: 1.5,
            y: -2.0,
            z: -3.25,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
        })
    }

    fn decode_all(c: &mut Codec, bytes: &[u8]) -> (Vec<Frame>, LinkStats) {
        let mut stats = LinkStats::default();
        let mut frames = Vec::new();
        c.decode(bytes, &mut stats, |f, _| frames.push(f));
        (frames, stats)
    }

    #[test]
    fn frames_round_trip_back_to_back_in_one_datagram() {
        let mut tx = Codec::new(1, None, 0);
        let mut buf = Vec::new();
        tx.encode(7, &position(20), &mut buf);
        tx.encode(
            7,
            &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
            &mut buf,
        );
        let (frames, stats) = decode_all(&mut Codec::new(1, None, 0), &buf);
        assert_eq!(frames.len(), 2);
        assert_eq!(frames[0].message, position(20));
        assert_eq!(frames[0].header.system_id, 7);
        assert_eq!(frames[1].header.sequence, 1);
        assert_eq!(stats.rejected(), 0);
    }

    #[test]
    fn defects_are_counted_not_fatal() {
        let mut tx = Codec::new(1, None, 0);
        let mut good = Vec::new();
        tx.encode(7, &position(20), &mut good);
        let mut rx = Codec::new(1, None, 0);
        let mut corrupt = good.clone();
        corrupt[12] ^= 0x40;
        assert_eq!(decode_all(&mut rx, &corrupt).1.bad_crc, 1);
        assert_eq!(decode_all(&mut rx, &good[..good.len() - 1]).1.malformed, 1);
        assert_eq!(decode_all(&mut rx, b"\x00garbage").1.malformed, 1);
        assert_eq!(decode_all(&mut rx, &[]).1, LinkStats::default());
        // A bad frame followed by a good one in the same datagram: the good one survives.
        let mut both = corrupt.clone();
        both.extend_from_slice(&good);
        let (frames, stats) = decode_all(&mut rx, &both);
        assert_eq!((frames.len(), stats.bad_crc), (1, 1));
    }

    #[test]
    fn signing_rejects_unsigned_wrong_key_and_replays() {
        let key = signing_key("overtake").unwrap();
        let other = signing_key(&"ab".repeat(32)).unwrap();
        let mut signed = Vec::new();
        Codec::new(1, Some(key), 3).encode(7, &position(1), &mut signed);
        let mut unsigned = Vec::new();
        Codec::new(1, None, 0).encode(7, &position(1), &mut unsigned);
        let mut wrong = Vec::new();
        Codec::new(1, Some(other), 3).encode(7, &position(1), &mut wrong);

        let mut rx = Codec::new(1, Some(key), 0);
        let (f, s) = decode_all(&mut rx, &signed);
        assert_eq!((f.len(), s.rejected()), (1, 0));
        assert_eq!(decode_all(&mut rx, &signed).1.replayed, 1);
        assert_eq!(decode_all(&mut rx, &unsigned).1.unsigned, 1);
        assert_eq!(decode_all(&mut rx, &wrong).1.bad_signature, 1);
        // A receiver without a key still reads signed frames (signing is per link).
        assert_eq!(decode_all(&mut Codec::new(1, None, 0), &signed).0.len(), 1);
    }

    #[test]
    fn consecutive_signed_frames_have_increasing_timestamps() {
        let key = signing_key("k").unwrap();
        let mut tx = Codec::new(1, Some(key), 0);
        let mut rx = Codec::new(1, Some(key), 0);
        let mut buf = Vec::new();
        for t in 0..100 {
            tx.encode(7, &position(t), &mut buf);
        }
        let (frames, stats) = decode_all(&mut rx, &buf);
        assert_eq!((frames.len(), stats.rejected()), (100, 0));
    }

    #[test]
    fn keys_from_hex_or_passphrase() {
        let hex = "00".repeat(31) + "ff";
        assert_eq!(signing_key(&hex).unwrap()[31], 0xff);
        assert_ne!(signing_key("a").unwrap(), signing_key("b").unwrap());
        assert!(signing_key("").is_err());
    }
}
