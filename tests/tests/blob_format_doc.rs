//! The blob format's documentation is enough to write a reader in another language:
//! `tools/read_blob.py`, written from firmware-core's `blob` module docs with only Python's
//! standard library, reads a blob the same way firmware-core does.

use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::policy::TableRow;
use firmware_core::synthetic;
use std::process::Command;

#[test]
fn the_python_reader_agrees_with_firmware_core() {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../tools/read_blob.py");
    let dir = std::env::temp_dir().join(format!("overtake-blob-doc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    for (row, int8) in [
        (TableRow::A, false),
        (TableRow::G, false),
        (TableRow::A, true),
        (TableRow::G, true),
    ] {
        let bytes = if int8 {
            synthetic::blob_i8(row, 77)
        } else {
            synthetic::blob(row, 77)
        }
        .expect("encode");
        let path = dir.join(format!(
            "{}{}.blob",
            row.letter(),
            if int8 { "8" } else { "" }
        ));
        std::fs::write(&path, &bytes).expect("write blob");
        let out = Command::new("python3")
            .arg(script)
            .arg(&path)
            .output()
            .expect("python3 must be installed");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let json = String::from_utf8(out.stdout).expect("utf-8");

        let aligned = AlignedBytes::new(&bytes);
        let blob = Blob::parse(aligned.as_bytes()).expect("parse");
        let h = blob.header();
        let w = blob.dequantized();
        let widths = h
            .architecture
            .mlp_hidden
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(", ");
        for needle in [
            format!("\"obs_dim\": {}", h.architecture.obs_dim),
            format!("\"lstm_layers\": {}", h.architecture.lstm_layers),
            format!("\"mlp_hidden\": [{widths}]"),
            format!("\"control_period_ns\": {}", h.control_period_ns),
            "\"seed\": 77".to_string(),
            format!("\"name\": \"{}\"", h.provenance.name),
            format!("\"payload_len\": {}", h.payload_len),
            format!("\"count\": {}", w.len()),
            format!("\"layout\": \"{:?}\"", h.observation.layout),
            format!("\"dtype\": \"{:?}\"", h.dtype),
        ] {
            assert!(
                json.contains(&needle),
                "row {}: {needle} not in {json}",
                row.letter()
            );
        }
        // The first and last weights, printed by Python from what it read (for int8, its own
        // dequantisation), parse back to ours.
        let numbers = |key: &str| -> Vec<f32> {
            json.split(&format!("\"{key}\": ["))
                .nth(1)
                .and_then(|s| s.split(']').next())
                .expect(key)
                .split(',')
                .map(|v| v.trim().parse::<f32>().expect("number"))
                .collect()
        };
        assert_eq!(numbers("first"), w[..4]);
        assert_eq!(numbers("last"), w[w.len() - 4..]);
    }
    std::fs::remove_dir_all(&dir).expect("clean up");
}
