//! Flash-ready weight blobs: a postcard header, a 4-byte-aligned little-endian payload and a
//! CRC-32, read in place (zero-copy) from `&[u8]`.
//!
//! ## Byte layout (format version 1)
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `b"OVTK"` (`4F 56 54 4B`) |
//! | 4 | 2 | format version, u16 little-endian (1) |
//! | 6 | 2 | header length `H` in bytes, u16 little-endian |
//! | 8 | `H` | [`BlobHeader`], postcard-encoded (see below) |
//! | 8 + `H` | `P` | zero bytes, `P` ∈ 0..=3, so the payload offset `O = 8 + H + P` is a multiple of 4 |
//! | `O` | `N` | payload: `N = header.payload_len` bytes of weights |
//! | `O + N` | 4 | CRC-32/ISO-HDLC (zlib's `crc32`) of bytes `0 .. O + N`, u32 little-endian |
//!
//! Bytes after `O + N + 4` are ignored (a flash partition may be larger than its blob). The
//! blob itself must start on a 4-byte boundary so the payload can be read as `f32` in place.
//!
//! ## Header (postcard 1.x wire format)
//! Fields in this order; integers are varints (u16/u32/u64: LEB128; there are no signed
//! fields), `f32` is 4 bytes little-endian, enums are a varint variant index, a `Vec` or
//! `String` is a varint length then its items, a struct is its fields in order.
//! 1. `architecture`: `obs_dim` u16, `lstm_layers` u8 (one raw byte), `lstm_hidden` u16,
//!    `mlp_hidden` `Vec<u16>` (≤ 6), `action_dim` u8, `activation` enum {0: Tanh}.
//! 2. `observation`: `version` u16 (1, or 2 for a folded pipeline: [`crate::mirror`]), `layout` enum {0: TimeTrial17, 1: OpponentPosition20,
//!    2: FullOpponent30}, then seven f32: gate position scale (m), velocity scale (m/s), body
//!    rate scale (rad/s), opponent position (m), velocity (m/s) and rate (rad/s) scales, clip.
//! 3. `action_map`: `hover_rpm` f32, `gain` f32 (rpm = hover · (1 + gain · a)).
//! 4. `control_period_ns` u32 (20,000,000 for 50 Hz).
//! 5. `dtype` enum {0: F32, 1: I8}.
//! 6. `provenance`: `name` String (≤ 32 bytes UTF-8), `seed` u64, `iterations` u32,
//!    `preset` String (≤ 16), `config_hash` u64.
//! 7. `payload_len` u32 (bytes).
//!
//! ## Payload (dtype F32)
//! `payload_len / 4` little-endian IEEE-754 f32, tensor after tensor in the order of
//! [`Architecture::tensors`]: for each LSTM layer `weight_ih [4H][in]`, `weight_hh [4H][H]`,
//! `bias_ih + bias_hh [4H]` (gate rows i, f, g, o); then for each MLP layer, the output layer
//! last, `weight [out][in]`, `bias [out]`. Matrices are row-major (PyTorch layout). Every
//! value must be finite.
//!
//! ## Payload (dtype I8)
//! The same tensors in the same order; biases stay f32, and each matrix `[rows][cols]` is
//! stored as symmetric per-row int8:
//! * `scale [rows]` f32 (finite, ≥ 0): row `r`'s weights are `scale[r] · q[r][c]`;
//! * `q [rows][stride]` i8 (two's complement), `stride = cols` rounded up to a multiple
//!   of 4; the padding bytes at the end of each row are zero.
//!
//! Every tensor so starts on a 4-byte boundary. The quantiser (`encode_i8`, feature `std`) sets
//! `scale[r] = max_c |w[r][c]| / 127` and `q = round(w / scale)` in -127..=127. Row G is
//! 320,288 payload bytes in int8 against 1,215,760 in f32 (3.8× smaller).
//!
//! ## Errors
//! Decoding checks, in order: alignment, length of the fixed prefix, magic, version, header,
//! total length, CRC, then the contents (dtype, observation spec, architecture, action map,
//! control period, payload size, finite weights). Every defect is a [`BlobError`]; nothing
//! panics and nothing is allocated.

use crate::crc32::crc32;
pub use crate::format::{
    BlobError, CONTROL_PERIOD_RANGE_NS, FORMAT_VERSION, MAGIC, MAX_BLOB_BYTES,
    OBSERVATION_SCALE_RANGE, WeightDtype,
};
use crate::nn::WeightReader;
use crate::observation::ObservationSpec;
use crate::policy::{Architecture, Policy};
use crate::vehicle::ActionMap;
use serde::{Deserialize, Serialize};

/// Size of the fixed prefix (magic, version, header length).
pub const PREFIX_LEN: usize = 8;
/// Size of the trailing CRC.
pub const CRC_LEN: usize = 4;

/// Where the weights came from.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Provenance {
    /// Short name, e.g. "stage1" or "golden-G".
    pub name: heapless::String<32>,
    /// Seed of the training run.
    pub seed: u64,
    /// Training iterations.
    pub iterations: u32,
    /// Simulator preset trained on ("paper", "nominal", "realistic").
    pub preset: heapless::String<16>,
    /// A hash of the training configuration (0 when unknown).
    pub config_hash: u64,
}

/// Everything a blob says about its weights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlobHeader {
    /// Network shape.
    pub architecture: Architecture,
    /// The observation contract the policy was trained with.
    pub observation: ObservationSpec,
    /// Action → rpm map (paper eq. 3).
    pub action_map: ActionMap,
    /// Control period the policy was trained at (ns).
    pub control_period_ns: u32,
    /// Weight storage type.
    pub dtype: WeightDtype,
    /// Training provenance.
    pub provenance: Provenance,
    /// Payload size (bytes).
    pub payload_len: u32,
}

impl BlobHeader {
    /// The header of a Table 1 row with the paper's observation scales (the layout its input
    /// size implies), action map (eq. 3) and 50 Hz control period; `payload_len` is set by the
    /// encoder.
    pub fn paper(row: crate::policy::TableRow, provenance: Provenance) -> Self {
        Self {
            architecture: Architecture::table1(row),
            observation: ObservationSpec::paper(row.observation_layout()),
            action_map: ActionMap::PAPER,
            control_period_ns: crate::vehicle::PAPER_CONTROL_PERIOD_NS,
            dtype: WeightDtype::F32,
            provenance,
            payload_len: 0,
        }
    }
}

#[cfg(target_endian = "big")]
compile_error!(
    "blobs store little-endian f32 and are read in place: big-endian targets are not supported"
);

/// A validated blob, borrowing its bytes.
#[derive(Clone, Debug)]
pub struct Blob<'w> {
    header: BlobHeader,
    /// The payload as little-endian words (f32 values, or int8 quads and f32 scales/biases).
    payload: &'w [u32],
    len: usize,
}

fn read_u16(bytes: &[u8], at: usize) -> Option<u16> {
    let b = bytes.get(at..at + 2)?;
    Some(u16::from_le_bytes([*b.first()?, *b.get(1)?]))
}

fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at + 4)?;
    Some(u32::from_le_bytes([
        *b.first()?,
        *b.get(1)?,
        *b.get(2)?,
        *b.get(3)?,
    ]))
}

/// Views 4-byte-aligned little-endian bytes as 32-bit words without copying.
fn as_words(bytes: &[u8]) -> Result<&[u32], BlobError> {
    let offset_mod_4 = bytes.as_ptr() as usize % 4;
    if offset_mod_4 != 0 {
        return Err(BlobError::Misaligned { offset_mod_4 });
    }
    // SAFETY: the pointer is 4-byte aligned (checked above), `len / 4` words lie within the
    // borrowed bytes, every bit pattern is a valid u32, and the target is little-endian
    // (compile_error above), so the values are the stored ones. The lifetime is the input's.
    Ok(unsafe { core::slice::from_raw_parts(bytes.as_ptr().cast::<u32>(), bytes.len() / 4) })
}

/// Checks an int8 payload's contents tensor by tensor, read as inference reads them
/// ([`WeightReader`]): finite biases, finite non-negative scales, zero row padding.
fn validate_i8(arch: &Architecture, words: &[u32]) -> Result<(), BlobError> {
    let mut r = WeightReader::new_i8(words);
    for t in arch.tensors() {
        let start = r.position();
        if t.cols == 0 {
            let bias = r.take(t.rows)?;
            if let Some(i) = bias.iter().position(|b| !b.is_finite()) {
                return Err(BlobError::NonFiniteWeight { index: start + i });
            }
            continue;
        }
        let (scales, q) = r.take_i8(t.rows, t.cols)?;
        if let Some(i) = scales
            .iter()
            .position(|s| !s.is_finite() || s.is_sign_negative())
        {
            return Err(BlobError::InvalidScale { word: start + i });
        }
        let row_words = crate::nn::i8_row_bytes(t.cols) / 4;
        let pad = row_words * 4 - t.cols;
        if pad > 0 {
            let last_word_of_rows = q.iter().skip(row_words - 1).step_by(row_words);
            // The last `pad` bytes of each row's last word (little-endian: the high bytes).
            let mask = u32::MAX << (8 * (4 - pad));
            if last_word_of_rows.into_iter().any(|w| w & mask != 0) {
                return Err(BlobError::NonZeroPadding);
            }
        }
    }
    r.finish()
}

impl<'w> Blob<'w> {
    /// Validates `bytes` as a blob (every check of the module docs) without copying the
    /// weights.
    pub fn parse(bytes: &'w [u8]) -> Result<Self, BlobError> {
        let offset_mod_4 = bytes.as_ptr() as usize % 4;
        if offset_mod_4 != 0 {
            return Err(BlobError::Misaligned { offset_mod_4 });
        }
        let truncated = |needed| BlobError::Truncated {
            needed,
            available: bytes.len(),
        };
        if bytes.len() > MAX_BLOB_BYTES {
            return Err(BlobError::TooLarge { bytes: bytes.len() });
        }
        if bytes.len() < PREFIX_LEN {
            return Err(truncated(PREFIX_LEN));
        }
        if bytes.get(..4) != Some(&MAGIC[..]) {
            return Err(BlobError::BadMagic);
        }
        let version = read_u16(bytes, 4).ok_or(truncated(PREFIX_LEN))?;
        if version != FORMAT_VERSION {
            return Err(BlobError::UnsupportedVersion(version));
        }
        let header_len = usize::from(read_u16(bytes, 6).ok_or(truncated(PREFIX_LEN))?);
        let header_end = PREFIX_LEN + header_len;
        let header_bytes = bytes
            .get(PREFIX_LEN..header_end)
            .ok_or(truncated(header_end))?;
        let (header, rest) = postcard::take_from_bytes::<BlobHeader>(header_bytes)
            .map_err(|_| BlobError::MalformedHeader)?;
        if !rest.is_empty() {
            return Err(BlobError::MalformedHeader);
        }
        let payload_offset = header_end.next_multiple_of(4);
        let payload_len = header.payload_len as usize;
        let payload_end = payload_offset
            .checked_add(payload_len)
            .ok_or(BlobError::MalformedHeader)?;
        let total = payload_end
            .checked_add(CRC_LEN)
            .ok_or(BlobError::MalformedHeader)?;
        if bytes.len() < total {
            return Err(truncated(total));
        }
        let stored = read_u32(bytes, payload_end).ok_or(truncated(total))?;
        let covered = bytes.get(..payload_end).ok_or(truncated(total))?;
        let computed = crc32(covered);
        if stored != computed {
            return Err(BlobError::CrcMismatch { stored, computed });
        }
        let padding = bytes
            .get(header_end..payload_offset)
            .ok_or(truncated(total))?;
        if padding.iter().any(|&b| b != 0) {
            return Err(BlobError::NonZeroPadding);
        }
        // Contents.
        if !header.observation.is_supported() {
            return Err(BlobError::ObservationSpecMismatch);
        }
        if usize::from(header.architecture.obs_dim) != header.observation.dim() {
            return Err(BlobError::UnsupportedArchitecture);
        }
        if !header.action_map.is_valid() {
            return Err(BlobError::InvalidActionMap);
        }
        let scales = header.observation.scales();
        if !scales.iter().all(|s| OBSERVATION_SCALE_RANGE.contains(s)) {
            return Err(BlobError::ImplausibleObservationScale);
        }
        if !CONTROL_PERIOD_RANGE_NS.contains(&header.control_period_ns) {
            return Err(BlobError::InvalidControlPeriod);
        }
        let arch = &header.architecture;
        let expected_bytes = arch.payload_bytes(header.dtype);
        let payload_words = |len: usize| {
            bytes
                .get(payload_offset..payload_offset + len)
                .ok_or(truncated(total))
                .and_then(as_words)
        };
        let payload = match header.dtype {
            WeightDtype::F32 => {
                let expected_floats = arch.param_count();
                if payload_len != expected_bytes {
                    return Err(BlobError::PayloadSizeMismatch {
                        expected_floats,
                        actual_floats: payload_len / 4,
                    });
                }
                let payload = payload_words(payload_len)?;
                if let Some(index) = payload.iter().position(|w| !f32::from_bits(*w).is_finite()) {
                    return Err(BlobError::NonFiniteWeight { index });
                }
                payload
            }
            WeightDtype::I8 => {
                if payload_len != expected_bytes {
                    return Err(BlobError::PayloadLengthMismatch {
                        expected_bytes,
                        actual_bytes: payload_len,
                    });
                }
                let payload = payload_words(payload_len)?;
                validate_i8(arch, payload)?;
                payload
            }
        };
        let blob = Self {
            header,
            payload,
            len: total,
        };
        // The architecture must be one we can run.
        blob.policy()?;
        Ok(blob)
    }

    /// The header.
    pub fn header(&self) -> &BlobHeader {
        &self.header
    }

    /// The f32 weights in payload order; `None` for an int8 blob (see `Blob::dequantized`,
    /// feature `std`, on the host).
    pub fn weights(&self) -> Option<&'w [f32]> {
        match self.header.dtype {
            WeightDtype::F32 => Some(crate::nn::words_f32(self.payload)),
            WeightDtype::I8 => None,
        }
    }

    /// The payload as little-endian 32-bit words, whatever the dtype.
    pub fn payload_words(&self) -> &'w [u32] {
        self.payload
    }

    /// Bytes the blob occupies (prefix, header, padding, payload, CRC).
    pub fn len(&self) -> usize {
        self.len
    }

    /// Always false: a valid blob has a header.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// A reader at the start of the payload, in the blob's dtype.
    fn reader(&self) -> WeightReader<'w> {
        match self.header.dtype {
            WeightDtype::F32 => WeightReader::new(crate::nn::words_f32(self.payload)),
            WeightDtype::I8 => WeightReader::new_i8(self.payload),
        }
    }

    /// The policy network viewing this blob's weights.
    pub fn policy(&self) -> Result<Policy<'w>, BlobError> {
        Policy::from_reader(&self.header.architecture, self.reader())
    }
}

#[cfg(feature = "std")]
mod encode;

#[cfg(feature = "std")]
pub use encode::{
    AlignedBytes, ConvertError, EncodeError, convert, convert_bytes, encode, encode_i8, int8_grid,
};
