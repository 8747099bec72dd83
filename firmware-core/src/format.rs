//! The words of the blob format that the parser ([`crate::blob`]) and the layers reading a
//! payload ([`crate::nn`], [`crate::policy`]) share: the format's identity ([`MAGIC`],
//! [`FORMAT_VERSION`]), how the weights are stored ([`WeightDtype`]) and every defect a blob can
//! have ([`BlobError`]).
//!
//! It sits below those three modules so that none of them imports another in a loop: `blob`
//! reads its payload through `nn` and builds a `policy`, and both report defects in these
//! words. The module is private: `crate::blob` re-exports everything here, so the format keeps
//! one public home.

use serde::{Deserialize, Serialize};

/// The four bytes every blob starts with.
pub const MAGIC: [u8; 4] = *b"OVTK";
/// The format version this crate reads and writes.
pub const FORMAT_VERSION: u16 = 1;

/// Storage type of the weights.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum WeightDtype {
    /// IEEE-754 binary32, little-endian.
    F32,
    /// Matrices in symmetric per-row int8 with f32 scales; biases in f32 (the
    /// [`crate::blob`] docs, "Payload (dtype I8)").
    I8,
}

impl WeightDtype {
    /// The name used on command lines and in reports (`f32`, `i8`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::I8 => "i8",
        }
    }

    /// The dtype called `name` on a command line (`f32`, `i8`, or `int8`).
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "f32" => Some(Self::F32),
            "i8" | "int8" => Some(Self::I8),
            _ => None,
        }
    }
}

/// The largest blob any reader accepts (bytes): far above row G in f32 (~1.2 MB), so a wrong
/// file (`/dev/zero`, a video) is refused instead of read without end.
pub const MAX_BLOB_BYTES: usize = 64 << 20;

/// The control periods a blob may record (ns): 0.1 ms (10 kHz) to 1 s (1 Hz). The paper's
/// is 20 ms.
pub const CONTROL_PERIOD_RANGE_NS: core::ops::RangeInclusive<u32> = 100_000..=1_000_000_000;

/// The observation scales (divisors, in m, m/s or rad/s) and clips a blob may record. The
/// paper's are 12 m, 3 m/s, π rad/s and 1; a value far outside (1e-40, 1e30) is a corrupt
/// header that would saturate or zero every input.
pub const OBSERVATION_SCALE_RANGE: core::ops::RangeInclusive<f32> = 1e-3..=1e4;

/// A defect in a blob.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum BlobError {
    /// The blob does not start on a 4-byte boundary, so its weights cannot be read in place.
    Misaligned {
        /// The start address modulo 4.
        offset_mod_4: usize,
    },
    /// Fewer bytes than the blob needs.
    Truncated {
        /// Bytes needed so far.
        needed: usize,
        /// Bytes available.
        available: usize,
    },
    /// The first four bytes are not [`MAGIC`].
    BadMagic,
    /// A format version this crate cannot read.
    UnsupportedVersion(u16),
    /// The header does not decode, or does not fill exactly its declared length.
    MalformedHeader,
    /// A padding byte (before the payload, or at the end of an int8 row) is not zero.
    NonZeroPadding,
    /// The stored CRC does not match the bytes.
    CrcMismatch {
        /// CRC stored in the blob.
        stored: u32,
        /// CRC computed over the bytes.
        computed: u32,
    },
    /// A weight dtype this build cannot run.
    UnsupportedDtype,
    /// The observation spec is of another pipeline version or has invalid scales.
    ObservationSpecMismatch,
    /// The architecture is not one of Table 1's, or disagrees with the observation spec.
    UnsupportedArchitecture,
    /// The action map is not finite and positive.
    InvalidActionMap,
    /// The control period is outside [`CONTROL_PERIOD_RANGE_NS`] (0.1 ms to 1 s).
    InvalidControlPeriod,
    /// An observation scale or the clip is outside
    /// [`OBSERVATION_SCALE_RANGE`] (1e-3 to 1e4): finite and positive, but no
    /// pipeline divides by it on purpose.
    ImplausibleObservationScale,
    /// The blob is larger than [`MAX_BLOB_BYTES`].
    TooLarge {
        /// Bytes offered.
        bytes: usize,
    },
    /// The int8 payload does not have exactly the architecture's size.
    PayloadLengthMismatch {
        /// Bytes the architecture needs in int8.
        expected_bytes: usize,
        /// Bytes in the payload.
        actual_bytes: usize,
    },
    /// An int8 row scale is negative, NaN or infinite.
    InvalidScale {
        /// Index of the scale's 4-byte word in the payload.
        word: usize,
    },
    /// The payload does not hold exactly the architecture's parameters.
    PayloadSizeMismatch {
        /// Parameters the architecture needs.
        expected_floats: usize,
        /// Parameters in the payload.
        actual_floats: usize,
    },
    /// A weight is NaN or infinite.
    NonFiniteWeight {
        /// Index of the weight in the payload.
        index: usize,
    },
}

impl core::fmt::Display for BlobError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Self::Misaligned { offset_mod_4 } => {
                write!(
                    f,
                    "blob starts at an address ≡ {offset_mod_4} (mod 4); it must be 4-byte aligned"
                )
            }
            Self::Truncated { needed, available } => {
                write!(f, "blob truncated: needs {needed} bytes, has {available}")
            }
            Self::BadMagic => f.write_str("not a weight blob (bad magic; expected \"OVTK\")"),
            Self::UnsupportedVersion(v) => {
                write!(
                    f,
                    "blob format version {v} is not supported (this build reads {FORMAT_VERSION})"
                )
            }
            Self::MalformedHeader => f.write_str("blob header does not decode"),
            Self::NonZeroPadding => f.write_str("blob padding bytes are not zero"),
            Self::CrcMismatch { stored, computed } => {
                write!(
                    f,
                    "blob CRC mismatch: stored {stored:#010x}, computed {computed:#010x}"
                )
            }
            Self::UnsupportedDtype => {
                f.write_str("blob weight dtype is not supported by this build")
            }
            Self::ObservationSpecMismatch => {
                f.write_str("blob observation spec does not match this observation pipeline")
            }
            Self::UnsupportedArchitecture => {
                f.write_str("blob architecture is not a supported Table 1 policy")
            }
            Self::InvalidActionMap => f.write_str("blob action map is not finite and positive"),
            Self::InvalidControlPeriod => {
                f.write_str("blob control period is outside 0.1 ms to 1 s")
            }
            Self::ImplausibleObservationScale => f.write_str(
                "blob observation scale or clip is outside 1e-3 to 1e4 (a corrupt or hand-edited header)",
            ),
            Self::TooLarge { bytes } => write!(
                f,
                "{bytes} bytes is larger than any blob ({} MiB at most)",
                MAX_BLOB_BYTES >> 20
            ),
            Self::PayloadSizeMismatch {
                expected_floats,
                actual_floats,
            } => write!(
                f,
                "blob payload holds {actual_floats} weights, the architecture needs {expected_floats}"
            ),
            Self::NonFiniteWeight { index } => write!(f, "blob weight {index} is not finite"),
            Self::PayloadLengthMismatch {
                expected_bytes,
                actual_bytes,
            } => write!(
                f,
                "int8 blob payload is {actual_bytes} bytes, the architecture needs {expected_bytes}"
            ),
            Self::InvalidScale { word } => write!(
                f,
                "int8 blob scale at payload word {word} is negative or not finite"
            ),
        }
    }
}

#[cfg(feature = "std")]
impl core::error::Error for BlobError {}
