//! `convert` and `synth-blob`: write weight blobs, re-encoded in another dtype or with seeded
//! random weights. Both write through a temporary file, so a failed run leaves the output as
//! it was.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Args;
use firmware_core::blob::{WeightDtype, convert_bytes};
use firmware_core::policy::TableRow;

use crate::error::{Error, Result};

/// The arguments of `convert`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct ConvertArgs {
    /// The dtype to write: f32, or i8 (also spelled int8).
    #[arg(long, value_name = "f32|i8", value_parser = dtype)]
    pub dtype: WeightDtype,
    /// The blob to read.
    #[arg(long = "in", value_name = "BLOB")]
    pub input: PathBuf,
    /// The blob to write (through a temporary file: a failed conversion leaves it as it was).
    #[arg(long, value_name = "BLOB")]
    pub out: PathBuf,
}

/// The arguments of `synth-blob`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SynthArgs {
    /// The Table 1 row, A to G (either case).
    #[arg(long, value_name = "A-G", value_parser = table_row)]
    pub row: TableRow,
    /// Seed of the random weights (a non-negative integer).
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// The blob file to write.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

/// `--dtype`: `f32`, `i8` or `int8`.
fn dtype(value: &str) -> std::result::Result<WeightDtype, String> {
    WeightDtype::from_name(value).ok_or_else(|| "expected f32 or i8 (int8)".to_string())
}

/// `--row`: one letter, A to G, either case.
fn table_row(value: &str) -> std::result::Result<TableRow, String> {
    let mut letters = value.chars();
    match (letters.next(), letters.next()) {
        (Some(c), None) => TableRow::from_letter(c),
        _ => None,
    }
    .ok_or_else(|| "expected one letter, A to G".to_string())
}

/// Writes `bytes` to `out` through a temporary file (`sitl::files::write_atomically`), so a
/// partial file never has the name.
fn write_atomically(out: &Path, bytes: &[u8]) -> Result<()> {
    sitl::files::write_atomically(out, bytes)
        .map_err(|e| Error::new(format!("writing {}: {e}", out.display())))
}

/// `convert`: re-encodes `args.input` in `args.dtype` and writes it to `args.out`.
pub fn convert(args: &ConvertArgs) -> Result<ExitCode> {
    let ConvertArgs { dtype, input, out } = args;
    let bytes =
        std::fs::read(input).map_err(|e| Error::new(format!("{}: {e}", input.display())))?;
    let converted = convert_bytes(&bytes, *dtype)
        .map_err(|e| Error::new(format!("{}: {e}", input.display())))?;
    write_atomically(out, &converted)?;
    println!(
        "{} ({} bytes) -> {} ({} bytes, {}): {:.2}x",
        input.display(),
        bytes.len(),
        out.display(),
        converted.len(),
        dtype.name(),
        bytes.len() as f64 / converted.len() as f64
    );
    Ok(ExitCode::SUCCESS)
}

/// `synth-blob`: writes a blob of `args.row` with weights drawn from `args.seed`.
pub fn synth_blob(args: &SynthArgs) -> Result<ExitCode> {
    let SynthArgs { row, seed, out } = args;
    let bytes = firmware_core::synthetic::blob(*row, *seed)
        .map_err(|e| Error::new(format!("encoding the blob: {e}")))?;
    write_atomically(out, &bytes)?;
    println!(
        "wrote {} ({} bytes): row {}, seed {seed}, synthetic random weights (never for flight)",
        out.display(),
        bytes.len(),
        row.letter()
    );
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn converts_a_blob_to_int8_and_refuses_garbage() {
        let dir = std::env::temp_dir().join(format!("overtake-convert-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let (f, q) = (dir.join("g.blob"), dir.join("g_i8.blob"));
        let bytes = firmware_core::synthetic::blob(TableRow::G, 3).expect("encode");
        std::fs::write(&f, &bytes).expect("write");
        let args = ConvertArgs {
            dtype: WeightDtype::I8,
            input: f.clone(),
            out: q.clone(),
        };
        assert_eq!(convert(&args).ok(), Some(ExitCode::SUCCESS));
        let out = std::fs::read(&q).expect("read");
        let aligned = firmware_core::blob::AlignedBytes::new(&out);
        let blob = firmware_core::Blob::parse(aligned.as_bytes()).expect("a valid blob");
        assert_eq!(blob.header().dtype, WeightDtype::I8);
        assert!(
            out.len() * 3 < bytes.len(),
            "{} vs {}",
            out.len(),
            bytes.len()
        );
        std::fs::write(&f, b"OVTK garbage").expect("write");
        let err = convert(&args).expect_err("garbage");
        assert!(err.to_string().contains("not a valid blob"), "{err}");
        // The earlier output was not touched by the failed conversion.
        assert_eq!(std::fs::read(&q).expect("read"), out);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
