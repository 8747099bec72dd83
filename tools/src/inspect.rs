//! `inspect <blob>`: decode a weight blob with firmware-core and print what its header says.

use std::fmt::Write as _;
use std::path::Path;
use std::process::ExitCode;

use firmware_core::blob::{AlignedBytes, Blob, BlobHeader, CRC_LEN, WeightDtype};
use firmware_core::policy::{Architecture, TableRow};

use crate::{Error, Result};

/// Reads `path`, decodes it and prints the header (exit 0) or the typed error (exit 1).
pub fn run(path: &Path) -> Result<ExitCode> {
    let bytes = std::fs::read(path).map_err(|e| Error::new(format!("{}: {e}", path.display())))?;
    // A heap Vec<u8> need not be 4-byte aligned: copy to an aligned buffer, as flash holds it.
    let aligned = AlignedBytes::new(&bytes);
    match Blob::parse(aligned.as_bytes()) {
        Ok(blob) => {
            print!("{}", describe(path, aligned.as_bytes(), &blob));
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => {
            eprintln!("{}: not a valid blob: {e}\n  error: {e:?}", path.display());
            Ok(ExitCode::FAILURE)
        }
    }
}

/// The Table 1 row whose architecture is `arch`, if any (D shares C's).
pub fn table_row(arch: &Architecture) -> Option<TableRow> {
    TableRow::ALL
        .into_iter()
        .find(|&row| Architecture::table1(row) == *arch)
}

/// The report of `blob`, decoded from `bytes` (the whole file).
pub fn describe(path: &Path, bytes: &[u8], blob: &Blob<'_>) -> String {
    let file_len = bytes.len();
    let h: &BlobHeader = blob.header();
    let a = &h.architecture;
    let mut s = String::new();
    let _ = writeln!(s, "{}: valid blob, {} bytes", path.display(), blob.len());
    let row = match table_row(a) {
        Some(TableRow::C) => "Table 1 row C/D".to_string(),
        Some(row) => format!("Table 1 row {}", row.letter()),
        None => "not a Table 1 row".to_string(),
    };
    let lstm = if a.lstm_layers == 0 {
        "no LSTM".to_string()
    } else {
        format!("{} x LSTM {}", a.lstm_layers, a.lstm_hidden)
    };
    let mlp: Vec<String> = a.mlp_hidden.iter().map(u16::to_string).collect();
    let _ = writeln!(
        s,
        "  architecture:   {} inputs, {}, MLP [{}] ({:?}), {} actions ({row})",
        a.obs_dim,
        lstm,
        mlp.join(", "),
        a.activation,
        a.action_dim
    );
    let o = &h.observation;
    let _ = writeln!(
        s,
        "  observation:    {:?} ({} values), pipeline version {}{}",
        o.layout,
        o.dim(),
        o.version,
        if o.is_folded() {
            " (folded: g3-g5 observed and flown as their mirror images)"
        } else {
            ""
        }
    );
    let [
        gate,
        velocity,
        rates,
        opp_position,
        opp_velocity,
        opp_rates,
        clip,
    ] = o.scales();
    let _ = writeln!(
        s,
        "                  scales: gate {} m, velocity {} m/s, rates {} rad/s; opponent {} m, {} m/s, {} rad/s; clip ±{}",
        gate, velocity, rates, opp_position, opp_velocity, opp_rates, clip
    );
    let _ = writeln!(
        s,
        "  action map:     rpm = {} x (1 + {} x a)",
        h.action_map.hover_rpm, h.action_map.gain
    );
    let period = f64::from(h.control_period_ns);
    let _ = writeln!(
        s,
        "  control period: {} ns ({} Hz)",
        h.control_period_ns,
        1e9 / period
    );
    let _ = writeln!(s, "  dtype:          {:?}", h.dtype);
    let p = &h.provenance;
    let _ = writeln!(
        s,
        "  provenance:     name {:?}, seed {}, {} iterations, preset {:?}, config hash {:#018x}",
        p.name.as_str(),
        p.seed,
        p.iterations,
        p.preset.as_str(),
        p.config_hash
    );
    let payload = match h.dtype {
        WeightDtype::F32 => "all finite",
        WeightDtype::I8 => "int8 rows with f32 scales and biases",
    };
    let _ = writeln!(
        s,
        "  payload:        {} bytes = {} weights ({payload})",
        h.payload_len,
        a.param_count()
    );
    let crc = blob
        .len()
        .checked_sub(CRC_LEN)
        .and_then(|at| bytes.get(at..blob.len()))
        .and_then(|b| <[u8; 4]>::try_from(b).ok())
        .map(|b| format!("{:#010x}", u32::from_le_bytes(b)))
        .unwrap_or_else(|| "?".into());
    let _ = writeln!(s, "  CRC-32:         ok ({crc})");
    if file_len > blob.len() {
        let _ = writeln!(s, "  trailing bytes: {} (ignored)", file_len - blob.len());
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use firmware_core::blob::BlobError;
    use firmware_core::synthetic;

    #[test]
    fn describes_a_synthetic_blob() {
        let bytes = AlignedBytes::new(&synthetic::blob(TableRow::G, 7).expect("encode"));
        let blob = Blob::parse(bytes.as_bytes()).expect("parse");
        let text = describe(Path::new("g.bin"), bytes.as_bytes(), &blob);
        for needle in [
            "Table 1 row G",
            "2 x LSTM 128",
            "FullOpponent30",
            "20000000 ns",
            "F32",
            "synthetic-G",
            "CRC-32:         ok",
        ] {
            assert!(text.contains(needle), "{needle} missing from\n{text}");
        }
    }

    #[test]
    fn a_flipped_bit_is_a_crc_error() {
        let mut bytes = AlignedBytes::new(&synthetic::blob(TableRow::A, 7).expect("encode"));
        let n = bytes.as_bytes().len();
        bytes.as_bytes_mut()[n - 8] ^= 1;
        assert!(matches!(
            Blob::parse(bytes.as_bytes()),
            Err(BlobError::CrcMismatch { .. })
        ));
    }
}
