//! The host side of the blob format (feature `std`: it allocates its output): the f32 and
//! int8 encoders, the int8 grid that quantisation-aware training runs on, the dtype
//! converter, the dequantised view of a parsed blob and [`AlignedBytes`]. What it writes is
//! what [`Blob::parse`] reads (the layout is in the module docs of [`crate::blob`]).

extern crate std;
use std::vec::Vec;

use super::{Blob, BlobError, BlobHeader, FORMAT_VERSION, MAGIC, PREFIX_LEN, WeightDtype};
use crate::crc32::crc32;
use crate::nn::i8_row_bytes;
use crate::policy::Architecture;

/// Why a blob could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum EncodeError {
    /// The header does not serialise.
    Header,
    /// The header is longer than 65,535 bytes.
    HeaderTooLong,
    /// The weights do not match the architecture's parameter count.
    WrongWeightCount {
        /// Parameters the architecture needs.
        expected: usize,
        /// Weights given.
        actual: usize,
    },
    /// A weight is NaN or infinite.
    NonFiniteWeight {
        /// Its index.
        index: usize,
    },
    /// The payload exceeds u32::MAX bytes.
    PayloadTooLarge,
}

impl core::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Self::Header => f.write_str("blob header does not serialise"),
            Self::HeaderTooLong => f.write_str("blob header is longer than 65535 bytes"),
            Self::WrongWeightCount { expected, actual } => {
                write!(f, "got {actual} weights, the architecture needs {expected}")
            }
            Self::NonFiniteWeight { index } => write!(f, "weight {index} is not finite"),
            Self::PayloadTooLarge => f.write_str("payload exceeds 4 GiB"),
        }
    }
}

impl std::error::Error for EncodeError {}

fn check_weights(arch: &Architecture, weights: &[f32]) -> Result<(), EncodeError> {
    let expected = arch.param_count();
    if weights.len() != expected {
        return Err(EncodeError::WrongWeightCount {
            expected,
            actual: weights.len(),
        });
    }
    if let Some(index) = weights.iter().position(|w| !w.is_finite()) {
        return Err(EncodeError::NonFiniteWeight { index });
    }
    Ok(())
}

/// Prefix, `header` (with `dtype` and `payload_len` set), padding, `payload` and CRC.
fn assemble(
    header: &BlobHeader,
    dtype: WeightDtype,
    payload: &[u8],
) -> Result<Vec<u8>, EncodeError> {
    let mut header = header.clone();
    header.dtype = dtype;
    header.payload_len = u32::try_from(payload.len()).map_err(|_| EncodeError::PayloadTooLarge)?;
    let head = postcard::to_stdvec(&header).map_err(|_| EncodeError::Header)?;
    let head_len = u16::try_from(head.len()).map_err(|_| EncodeError::HeaderTooLong)?;
    let mut out = Vec::with_capacity(PREFIX_LEN + head.len() + 3 + payload.len() + 4);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&head_len.to_le_bytes());
    out.extend_from_slice(&head);
    out.resize(out.len().next_multiple_of(4), 0);
    out.extend_from_slice(payload);
    let crc = crc32(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(out)
}

/// Encodes f32 `weights` (payload order) under `header` (its `payload_len` and `dtype`
/// are set here).
pub fn encode(header: &BlobHeader, weights: &[f32]) -> Result<Vec<u8>, EncodeError> {
    check_weights(&header.architecture, weights)?;
    let payload: Vec<u8> = weights.iter().flat_map(|w| w.to_le_bytes()).collect();
    assemble(header, WeightDtype::F32, &payload)
}

/// Encodes f32 `weights` (payload order) under `header` as an int8 blob: every matrix
/// row quantised symmetrically, `scale = max |w| / 127`, `q = round(w / scale)` (half
/// away from zero), biases kept in f32 (module docs, "Payload (dtype I8)"). A row of
/// zeros gets scale 0.
pub fn encode_i8(header: &BlobHeader, weights: &[f32]) -> Result<Vec<u8>, EncodeError> {
    check_weights(&header.architecture, weights)?;
    let arch = &header.architecture;
    let mut payload = Vec::with_capacity(arch.payload_bytes(WeightDtype::I8));
    let mut rest = weights;
    for t in arch.tensors() {
        let (tensor, tail) = rest.split_at(t.len());
        rest = tail;
        if t.cols == 0 {
            payload.extend(tensor.iter().flat_map(|w| w.to_le_bytes()));
            continue;
        }
        let scales: Vec<f32> = tensor.chunks_exact(t.cols).map(row_scale).collect();
        payload.extend(scales.iter().flat_map(|s| s.to_le_bytes()));
        for (row, &scale) in tensor.chunks_exact(t.cols).zip(&scales) {
            let start = payload.len();
            payload.extend(row.iter().map(|&w| quantize_weight(w, scale) as u8));
            payload.resize(start + i8_row_bytes(t.cols), 0);
        }
    }
    assemble(header, WeightDtype::I8, &payload)
}

/// `weights` (payload order for `arch`) on the int8 grid that [`encode_i8`] stores
/// them on: every matrix weight replaced by its row's `scale · q`, biases unchanged.
/// An int8 blob's [`Blob::dequantized`] weights are exactly these. Quantisation-aware
/// training runs its forward pass on them.
pub fn int8_grid(arch: &Architecture, weights: &[f32]) -> Result<Vec<f32>, EncodeError> {
    check_weights(arch, weights)?;
    let mut out = Vec::with_capacity(weights.len());
    let mut rest = weights;
    for t in arch.tensors() {
        let (tensor, tail) = rest.split_at(t.len());
        rest = tail;
        if t.cols == 0 {
            out.extend_from_slice(tensor);
            continue;
        }
        for row in tensor.chunks_exact(t.cols) {
            let scale = row_scale(row);
            out.extend(
                row.iter()
                    .map(|&w| f32::from(quantize_weight(w, scale)) * scale),
            );
        }
    }
    Ok(out)
}

/// The symmetric int8 scale of one matrix row: `max |w| / 127`.
fn row_scale(row: &[f32]) -> f32 {
    row.iter().fold(0.0f32, |m, w| m.max(w.abs())) / 127.0
}

/// One weight in int8 under its row's `scale`.
fn quantize_weight(w: f32, scale: f32) -> i8 {
    if scale == 0.0 {
        return 0;
    }
    (w / scale).round().clamp(-127.0, 127.0) as i8
}

impl Blob<'_> {
    /// The weights in payload order as f32: a copy of an f32 blob's, or an int8 blob's
    /// `scale · q` (the values its inference multiplies by, before the activations'
    /// own int16 rounding).
    pub fn dequantized(&self) -> Vec<f32> {
        if let Some(w) = self.weights() {
            return w.to_vec();
        }
        let arch = &self.header.architecture;
        let mut out = Vec::with_capacity(arch.param_count());
        // `parse` checked the payload's size against these tensors: every take succeeds.
        let mut r = self.reader();
        for t in arch.tensors() {
            if t.cols == 0 {
                out.extend_from_slice(r.take(t.rows).unwrap_or_default());
                continue;
            }
            let (scales, q) = r.take_i8(t.rows, t.cols).unwrap_or_default();
            let row_words = i8_row_bytes(t.cols) / 4;
            for (row, s) in q.chunks_exact(row_words).zip(scales) {
                let bytes = row.iter().flat_map(|w| w.to_le_bytes()).take(t.cols);
                out.extend(bytes.map(|b| f32::from(b as i8) * s));
            }
        }
        out
    }
}

/// Why a blob file could not be converted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvertError {
    /// The input is not a valid blob.
    Parse(BlobError),
    /// The output could not be encoded.
    Encode(EncodeError),
}

impl core::fmt::Display for ConvertError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Parse(e) => write!(f, "not a valid blob: {e}"),
            Self::Encode(e) => write!(f, "cannot encode the converted blob: {e}"),
        }
    }
}

impl std::error::Error for ConvertError {}

/// [`convert`] on the bytes of a blob file (any alignment: they are copied first).
pub fn convert_bytes(bytes: &[u8], dtype: WeightDtype) -> Result<Vec<u8>, ConvertError> {
    let aligned = AlignedBytes::new(bytes);
    let blob = Blob::parse(aligned.as_bytes()).map_err(ConvertError::Parse)?;
    convert(&blob, dtype).map_err(ConvertError::Encode)
}

/// Re-encodes a parsed blob in `dtype` with its header otherwise unchanged (the f32 →
/// int8 converter; int8 → f32 writes the dequantised weights).
pub fn convert(blob: &Blob<'_>, dtype: WeightDtype) -> Result<Vec<u8>, EncodeError> {
    let weights = blob.dequantized();
    match dtype {
        WeightDtype::F32 => encode(blob.header(), &weights),
        WeightDtype::I8 => encode_i8(blob.header(), &weights),
    }
}

/// Bytes held at a 4-byte-aligned address, as flash would hold a blob.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct AlignedBytes {
    words: Vec<u32>,
    len: usize,
}

impl AlignedBytes {
    /// A 4-byte-aligned copy of `bytes`.
    pub fn new(bytes: &[u8]) -> Self {
        let mut words = std::vec![0u32; bytes.len().div_ceil(4)];
        for (w, chunk) in words.iter_mut().zip(bytes.chunks(4)) {
            let mut b = [0u8; 4];
            for (dst, src) in b.iter_mut().zip(chunk) {
                *dst = *src;
            }
            *w = u32::from_ne_bytes(b);
        }
        Self {
            words,
            len: bytes.len(),
        }
    }

    /// The bytes.
    pub fn as_bytes(&self) -> &[u8] {
        // SAFETY: `words` holds at least `len` initialised bytes; u8 has no alignment or
        // validity requirement.
        unsafe { core::slice::from_raw_parts(self.words.as_ptr().cast::<u8>(), self.len) }
    }

    /// Mutable bytes (for corruption tests).
    pub fn as_bytes_mut(&mut self) -> &mut [u8] {
        // SAFETY: as in `as_bytes`, with unique access through `&mut self`.
        unsafe { core::slice::from_raw_parts_mut(self.words.as_mut_ptr().cast::<u8>(), self.len) }
    }
}
