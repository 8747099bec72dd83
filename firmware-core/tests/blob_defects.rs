//! Every defect of a blob is a typed error and nothing panics: truncation at every length,
//! bit flips anywhere, and each semantic defect on its own.

use firmware_core::blob::{
    AlignedBytes, Blob, BlobError, BlobHeader, FORMAT_VERSION, MAGIC, PREFIX_LEN, encode,
};
use firmware_core::crc32::crc32;
use firmware_core::observation::FOLDED_PIPELINE_VERSION;
use firmware_core::policy::{Architecture, TableRow};
use firmware_core::synthetic::{self, SplitMix64};

fn row_a() -> Vec<u8> {
    synthetic::blob(TableRow::A, 11).expect("encode")
}

fn parse(bytes: &[u8]) -> Result<(), BlobError> {
    let aligned = AlignedBytes::new(bytes);
    Blob::parse(aligned.as_bytes()).map(|_| ())
}

/// Re-seals a modified blob with a correct CRC so the semantic check is what fails.
fn reseal(mut bytes: Vec<u8>) -> Vec<u8> {
    let n = bytes.len() - 4;
    let crc = crc32(&bytes[..n]);
    bytes[n..].copy_from_slice(&crc.to_le_bytes());
    bytes
}

fn encode_with(f: impl FnOnce(&mut BlobHeader)) -> Vec<u8> {
    let mut h = synthetic::header(TableRow::A, 3);
    f(&mut h);
    let weights = synthetic::weights(&Architecture::table1(TableRow::A), 3);
    encode(&h, &weights).expect("encode")
}

#[test]
fn a_valid_blob_round_trips_its_header_and_weights() {
    let h = synthetic::header(TableRow::G, 5);
    let w = synthetic::weights(&h.architecture, 5);
    let bytes = AlignedBytes::new(&encode(&h, &w).expect("encode"));
    let blob = Blob::parse(bytes.as_bytes()).expect("parse");
    assert_eq!(blob.header().architecture, h.architecture);
    assert_eq!(blob.header().observation, h.observation);
    assert_eq!(blob.header().provenance, h.provenance);
    assert_eq!(blob.header().payload_len as usize, w.len() * 4);
    assert_eq!(blob.weights(), Some(&w[..]));
    assert_eq!(blob.len(), bytes.as_bytes().len());
    // Zero copy: the weights are the bytes of the buffer.
    let payload_start = blob.payload_words().as_ptr() as usize;
    let buf = bytes.as_bytes().as_ptr() as usize;
    assert!(payload_start > buf && payload_start < buf + bytes.as_bytes().len());
    assert_eq!((payload_start - buf) % 4, 0);
}

#[test]
fn trailing_bytes_after_the_crc_are_ignored() {
    let mut bytes = row_a();
    let len = bytes.len();
    bytes.extend_from_slice(&[0xFF; 13]);
    let aligned = AlignedBytes::new(&bytes);
    assert_eq!(Blob::parse(aligned.as_bytes()).expect("parse").len(), len);
}

#[test]
fn truncation_at_every_length_is_an_error() {
    let bytes = row_a();
    let aligned = AlignedBytes::new(&bytes);
    for len in 0..bytes.len() {
        match Blob::parse(&aligned.as_bytes()[..len]) {
            Err(BlobError::Truncated { available, .. }) => assert_eq!(available, len),
            Err(e) if len < PREFIX_LEN + 4 => panic!("len {len}: {e:?}"),
            Err(BlobError::MalformedHeader) => {} // cut inside the header
            other => panic!("len {len}: {other:?}"),
        }
    }
}

#[test]
fn every_single_bit_flip_in_the_header_is_an_error() {
    let bytes = row_a();
    let header_end = PREFIX_LEN + usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
    for byte in 0..header_end.next_multiple_of(4) {
        for bit in 0..8 {
            let mut b = bytes.clone();
            b[byte] ^= 1 << bit;
            assert!(parse(&b).is_err(), "flip of byte {byte} bit {bit} accepted");
        }
    }
}

#[test]
fn random_bit_flips_anywhere_are_errors() {
    let bytes = row_a();
    let mut aligned = AlignedBytes::new(&bytes);
    let mut rng = SplitMix64::new(99);
    for _ in 0..3000 {
        let flips = 1 + (rng.next_u64() % 3) as usize;
        let at: Vec<(usize, u8)> = (0..flips)
            .map(|_| {
                (
                    (rng.next_u64() % bytes.len() as u64) as usize,
                    1u8 << (rng.next_u64() % 8),
                )
            })
            .collect();
        for &(i, m) in &at {
            aligned.as_bytes_mut()[i] ^= m;
        }
        let changed = aligned.as_bytes() != &bytes[..];
        let result = Blob::parse(aligned.as_bytes()).map(|_| ());
        assert!(!changed || result.is_err(), "flips {at:?} accepted");
        for &(i, m) in &at {
            aligned.as_bytes_mut()[i] ^= m;
        }
    }
}

#[test]
fn payload_flip_is_a_crc_mismatch() {
    let mut bytes = row_a();
    let n = bytes.len();
    bytes[n - 100] ^= 0x10;
    assert!(matches!(parse(&bytes), Err(BlobError::CrcMismatch { .. })));
}

#[test]
fn bad_magic_and_version() {
    let mut bytes = row_a();
    bytes[0] = b'X';
    assert_eq!(parse(&bytes), Err(BlobError::BadMagic));
    let mut bytes = row_a();
    bytes[4..6].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
    assert_eq!(
        parse(&bytes),
        Err(BlobError::UnsupportedVersion(FORMAT_VERSION + 1))
    );
    assert_eq!(
        parse(b"PK\x03\x04 not a blob at all"),
        Err(BlobError::BadMagic)
    );
    assert_eq!(&row_a()[..4], &MAGIC);
}

#[test]
fn misaligned_start_is_refused() {
    let bytes = row_a();
    let mut shifted = vec![0u8; 1];
    shifted.extend_from_slice(&bytes);
    let aligned = AlignedBytes::new(&shifted);
    assert_eq!(
        Blob::parse(&aligned.as_bytes()[1..]).err(),
        Some(BlobError::Misaligned { offset_mod_4: 1 })
    );
}

#[test]
fn non_finite_weight_is_refused() {
    let mut bytes = row_a();
    let n = bytes.len();
    // The last weight sits just before the CRC.
    bytes[n - 8..n - 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let expected = Architecture::table1(TableRow::A).param_count() - 1;
    assert_eq!(
        parse(&reseal(bytes)),
        Err(BlobError::NonFiniteWeight { index: expected })
    );
    // The encoder refuses them too.
    let h = synthetic::header(TableRow::A, 1);
    let mut w = synthetic::weights(&h.architecture, 1);
    w[5] = f32::INFINITY;
    assert!(encode(&h, &w).is_err());
}

#[test]
fn observation_spec_of_another_pipeline_is_refused() {
    let bytes = encode_with(|h| h.observation.version = FOLDED_PIPELINE_VERSION + 1);
    assert_eq!(parse(&bytes), Err(BlobError::ObservationSpecMismatch));
    let bytes = encode_with(|h| h.observation.velocity_scale_mps = 0.0);
    assert_eq!(parse(&bytes), Err(BlobError::ObservationSpecMismatch));
    // A 30-value spec on a 17-input network.
    let bytes =
        encode_with(|h| h.observation.layout = firmware_core::ObservationLayout::FullOpponent30);
    assert_eq!(parse(&bytes), Err(BlobError::UnsupportedArchitecture));
}

#[test]
fn unknown_architecture_is_refused() {
    let mut h = synthetic::header(TableRow::A, 3);
    h.architecture.mlp_hidden.clear();
    let _ = h.architecture.mlp_hidden.push(64);
    let w = vec![0.01f32; h.architecture.param_count()];
    let bytes = encode(&h, &w).expect("encode");
    assert_eq!(parse(&bytes), Err(BlobError::UnsupportedArchitecture));
}

#[test]
fn action_map_and_control_period_are_checked() {
    assert_eq!(
        parse(&encode_with(|h| h.action_map.gain = f32::NAN)),
        Err(BlobError::InvalidActionMap)
    );
    assert_eq!(
        parse(&encode_with(|h| h.action_map.hover_rpm = -1.0)),
        Err(BlobError::InvalidActionMap)
    );
    for period_ns in [0, 99_999, 1_000_000_001, u32::MAX] {
        assert_eq!(
            parse(&encode_with(|h| h.control_period_ns = period_ns)),
            Err(BlobError::InvalidControlPeriod),
            "{period_ns} ns"
        );
    }
    for period_ns in [100_000, 10_000_000, 20_000_000, 1_000_000_000] {
        assert_eq!(
            parse(&encode_with(|h| h.control_period_ns = period_ns)),
            Ok(())
        );
    }
}

/// Finite, positive, but implausible scales (a gate scale of 1e-40 divides every position
/// into saturation) are refused by the parser, so every reader refuses them.
#[test]
fn implausible_observation_scales_are_refused() {
    type Edit = fn(&mut BlobHeader, f32);
    let edits: [Edit; 4] = [
        |h, v| h.observation.gate_position_scale_m = v,
        |h, v| h.observation.velocity_scale_mps = v,
        |h, v| h.observation.opponent_rate_scale_radps = v,
        |h, v| h.observation.clip = v,
    ];
    for edit in edits {
        for v in [1e-40, 1e-4, 2e4, 1e30] {
            assert_eq!(
                parse(&encode_with(|h| edit(h, v))),
                Err(BlobError::ImplausibleObservationScale),
                "{v}"
            );
        }
        for v in [1e-3, 0.25, 12.0, 1e4] {
            assert_eq!(parse(&encode_with(|h| edit(h, v))), Ok(()), "{v}");
        }
    }
}

/// Anything above the size limit is refused before it is looked at.
#[test]
fn an_oversized_blob_is_refused() {
    let mut bytes = row_a();
    bytes.resize(firmware_core::blob::MAX_BLOB_BYTES + 4, 0);
    assert_eq!(
        parse(&bytes),
        Err(BlobError::TooLarge {
            bytes: firmware_core::blob::MAX_BLOB_BYTES + 4
        })
    );
}

#[test]
fn payload_length_must_match_the_architecture() {
    // Declare one weight fewer in the header and drop it from the payload: a consistent,
    // CRC-correct blob whose payload is too short for its architecture.
    let bytes = row_a();
    let header_len = usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
    let mut header: BlobHeader = postcard::from_bytes(&bytes[8..8 + header_len]).expect("header");
    header.payload_len -= 4;
    let head = postcard::to_stdvec(&header).expect("serialise");
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(head.len() as u16).to_le_bytes());
    out.extend_from_slice(&head);
    out.resize(out.len().next_multiple_of(4), 0);
    let payload_start = (8 + header_len).next_multiple_of(4);
    out.extend_from_slice(&bytes[payload_start..bytes.len() - 8]);
    out.extend_from_slice(&[0; 4]);
    let expected = Architecture::table1(TableRow::A).param_count();
    assert_eq!(
        parse(&reseal(out)),
        Err(BlobError::PayloadSizeMismatch {
            expected_floats: expected,
            actual_floats: expected - 1
        })
    );
}

#[test]
fn non_zero_padding_is_refused() {
    // Grow the provenance name until the header leaves padding before the payload.
    let mut tested = 0;
    for extra in 0..4 {
        let bytes = encode_with(|h| {
            for _ in 0..extra {
                let _ = h.provenance.name.push('x');
            }
        });
        let header_end = PREFIX_LEN + usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
        for pad in header_end..header_end.next_multiple_of(4) {
            let mut b = bytes.clone();
            b[pad] = 1;
            assert_eq!(parse(&reseal(b)), Err(BlobError::NonZeroPadding));
            tested += 1;
        }
    }
    // Four consecutive header lengths leave 3 + 2 + 1 + 0 padding bytes.
    assert_eq!(tested, 6);
}

#[test]
fn errors_say_what_is_wrong() {
    let msg = BlobError::Truncated {
        needed: 100,
        available: 10,
    }
    .to_string();
    assert!(msg.contains("100") && msg.contains("10"), "{msg}");
    assert!(BlobError::BadMagic.to_string().contains("OVTK"));
}
