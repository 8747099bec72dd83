//! CRC-32/ISO-HDLC (the zlib / IEEE 802.3 CRC): reflected polynomial 0xEDB88320, initial
//! value 0xFFFFFFFF, final xor 0xFFFFFFFF. `crc32(b"123456789") == 0xCBF4_3926`.
//!
//! A thin wrapper over the `crc` crate's catalogue entry [`crc::CRC_32_ISO_HDLC`] with one
//! 256-entry table (1 KiB of flash, built at compile time): the size and speed of the
//! hand-written table this replaced (docs/PERFORMANCE.md, "Flash and RAM").

use crc::{CRC_32_ISO_HDLC, Crc, Table};

/// The blob checksum and its byte-at-a-time table.
static CRC32: Crc<u32, Table<1>> = Crc::<u32, Table<1>>::new(&CRC_32_ISO_HDLC);

/// The CRC-32 of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_value_of_the_catalogue() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    /// The definition, one bit at a time.
    fn crc32_bitwise(bytes: &[u8]) -> u32 {
        let mut c = 0xFFFF_FFFFu32;
        for &b in bytes {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    #[test]
    fn table_equals_the_bitwise_definition() {
        let bytes: [u8; 1031] = core::array::from_fn(|i| (i * 131 + i / 7) as u8);
        for n in [0, 1, 3, 4, 15, 16, 17, 255, 1031] {
            assert_eq!(crc32(&bytes[..n]), crc32_bitwise(&bytes[..n]), "length {n}");
        }
    }
}
