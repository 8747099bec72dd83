//! Argument parsing and dispatch (plain `std`, no parser crate).

use std::path::PathBuf;
use std::process::ExitCode;

use firmware_core::blob::{WeightDtype, convert_bytes};
use firmware_core::policy::TableRow;

use crate::{cortex_m, curves, figure, inspect, size};

fn parse_figure(args: &[&str]) -> Result<Command, String> {
    let (mut trace, mut episode, mut overtake, mut window_s, mut out) =
        (None, None, None, 8.0f32, PathBuf::from("overtake.svg"));
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        let index = |v: &str| {
            v.parse::<usize>()
                .map_err(|_| format!("{flag} takes a non-negative integer, not `{v}`"))
        };
        match *flag {
            "--trace" => trace = Some(PathBuf::from(value)),
            "--episode" => episode = Some(index(value)?),
            "--overtake" => overtake = Some(index(value)?),
            "--window-s" => {
                window_s = match value.parse::<f32>() {
                    Ok(v) if v > 0.0 && v <= 60.0 => v,
                    _ => {
                        return Err(format!(
                            "--window-s takes seconds in (0, 60], not `{value}`"
                        ));
                    }
                }
            }
            "--out" => out = PathBuf::from(value),
            other => return Err(format!("overtake-figure: unknown flag `{other}`")),
        }
    }
    Ok(Command::OvertakeFigure(figure::FigureArgs {
        trace: trace.ok_or("overtake-figure needs --trace FILE (from `sitl race --trace FILE`)")?,
        episode,
        overtake,
        window_s,
        out,
    }))
}

fn parse_curves(args: &[&str]) -> Result<Command, String> {
    let (mut runs, mut out) = (Vec::new(), PathBuf::from("learning_curves.svg"));
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match *flag {
            "--run" => {
                let (dir, label) = match value.split_once('=') {
                    Some((d, l)) if !d.is_empty() && !l.is_empty() => (d, l.to_string()),
                    Some(_) => return Err(format!("--run takes DIR or DIR=LABEL, not `{value}`")),
                    None => (*value, value.to_string()),
                };
                runs.push((PathBuf::from(dir), label));
            }
            "--out" => out = PathBuf::from(value),
            other => return Err(format!("learning-curves: unknown flag `{other}`")),
        }
    }
    if runs.is_empty() {
        return Err("learning-curves needs at least one --run DIR[=LABEL]".into());
    }
    Ok(Command::LearningCurves(curves::CurvesArgs { runs, out }))
}

fn parse_synth(args: &[&str]) -> Result<Command, String> {
    let (mut row, mut seed, mut out) = (None, 1u64, None);
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match *flag {
            "--row" => {
                let mut letters = value.chars();
                row = Some(
                    match (letters.next(), letters.next()) {
                        (Some(c), None) => TableRow::from_letter(c),
                        _ => None,
                    }
                    .ok_or_else(|| format!("--row takes A to G, not `{value}`"))?,
                )
            }
            "--seed" => {
                seed = value
                    .parse()
                    .map_err(|_| format!("--seed takes an integer, not `{value}`"))?
            }
            "--out" => out = Some(PathBuf::from(value)),
            other => return Err(format!("synth-blob: unknown flag `{other}`")),
        }
    }
    Ok(Command::SynthBlob {
        row: row.ok_or("synth-blob needs --row")?,
        seed,
        out: out.ok_or("synth-blob needs --out FILE")?,
    })
}

fn parse_convert(args: &[&str]) -> Result<Command, String> {
    let (mut dtype, mut input, mut out) = (None, None, None);
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match *flag {
            "--dtype" => {
                dtype = Some(
                    WeightDtype::from_name(value)
                        .ok_or_else(|| format!("--dtype takes f32 or i8, not `{value}`"))?,
                )
            }
            "--in" => input = Some(PathBuf::from(value)),
            "--out" => out = Some(PathBuf::from(value)),
            other => return Err(format!("convert: unknown flag `{other}`")),
        }
    }
    Ok(Command::Convert {
        dtype: dtype.ok_or("convert needs --dtype f32|i8")?,
        input: input.ok_or("convert needs --in BLOB")?,
        out: out.ok_or("convert needs --out BLOB")?,
    })
}

/// Writes `bytes` to `out` through a temporary file (`sitl::files::write_atomically`), so a
/// partial file never has the name.
fn write_atomically(out: &std::path::Path, bytes: &[u8]) -> crate::error::Result<()> {
    sitl::files::write_atomically(out, bytes)
        .map_err(|e| crate::error::Error::new(format!("writing {}: {e}", out.display())))
}

fn convert(
    dtype: WeightDtype,
    input: &std::path::Path,
    out: &std::path::Path,
) -> crate::error::Result<ExitCode> {
    let bytes = std::fs::read(input)
        .map_err(|e| crate::error::Error::new(format!("{}: {e}", input.display())))?;
    let converted = convert_bytes(&bytes, dtype)
        .map_err(|e| crate::error::Error::new(format!("{}: {e}", input.display())))?;
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

fn synth_blob(row: TableRow, seed: u64, out: &std::path::Path) -> crate::error::Result<ExitCode> {
    let bytes = firmware_core::synthetic::blob(row, seed)
        .map_err(|e| crate::error::Error::new(format!("encoding the blob: {e}")))?;
    write_atomically(out, &bytes)?;
    println!(
        "wrote {} ({} bytes): row {}, seed {seed}, synthetic random weights (never for flight)",
        out.display(),
        bytes.len(),
        row.letter()
    );
    Ok(ExitCode::SUCCESS)
}

/// The help text.
pub const USAGE: &str = "\
usage: cargo run -p tools -- <subcommand>

subcommands:
  inspect <blob>            decode a weight blob and print its header (exit 1 on a defect)
  size-report               build the Cortex-M4 size images (rows A and G in f32, G in
                            int8 linked for the STM32F405; profile `firmware`) and report
                            flash and RAM against an STM32F405
  convert --dtype f32|i8 --in BLOB --out BLOB
                            re-encode a blob: f32 -> i8 quantises every matrix row
                            (symmetric, f32 scales); i8 -> f32 writes the dequantised weights
  synth-blob --row X [--seed N] --out FILE
                            write a blob of Table 1 row X (A-G) with seeded random
                            weights: for trying the tools, never for flight
  overtake-figure --trace FILE [--episode N] [--overtake K] [--window-s S] [--out F.svg]
                            draw an overtake of a recorded race from above (the paper's
                            Fig. 3): the ego's and opponent's paths over S seconds (8)
                            around it; FILE from `sitl race --trace` or `sitl eval --trace`
  learning-curves --run DIR[=LABEL] ... [--out F.svg]
                            training runs on one page (metrics.jsonl of `host-trainer
                            train` or tools/train_rslrl.py): referee success and lap,
                            rollout gates and crashes, σ against samples and wall-clock,
                            beside the authors' run (no gate in 410 M samples)
  cortex-m test             build and run the Cortex-M4 test image under QEMU
  cortex-m icount           instructions per Controller::step on the emulated Cortex-M4
                            (QEMU -icount shift=0); --breakdown: per layer and kernel
  help                      print this text";

/// A parsed command line.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Print the usage.
    Help,
    /// Inspect a blob file.
    Inspect(PathBuf),
    /// The size report.
    SizeReport,
    /// Write a synthetic blob.
    SynthBlob {
        /// Table 1 row.
        row: TableRow,
        /// Weight seed.
        seed: u64,
        /// Output file.
        out: PathBuf,
    },
    /// Re-encode a blob in another dtype.
    Convert {
        /// The output dtype.
        dtype: WeightDtype,
        /// Input blob.
        input: PathBuf,
        /// Output blob.
        out: PathBuf,
    },
    /// Draw an overtake from a recorded race.
    OvertakeFigure(figure::FigureArgs),
    /// Draw training runs' learning curves on one page.
    LearningCurves(curves::CurvesArgs),
    /// Run the QEMU test image.
    CortexMTest,
    /// Run the instruction-count bench (`breakdown`: the per-layer image).
    CortexMIcount {
        /// Run `icount-breakdown` instead of `icount`.
        breakdown: bool,
    },
}

/// Parses the arguments after the program name.
pub fn parse(args: &[String]) -> Result<Command, String> {
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    match args.as_slice() {
        [] => Err("no subcommand given".into()),
        ["help" | "-h" | "--help"] => Ok(Command::Help),
        ["inspect", path] if !path.starts_with('-') => Ok(Command::Inspect(PathBuf::from(path))),
        ["inspect", ..] => Err("inspect takes exactly one blob file".into()),
        ["size-report"] => Ok(Command::SizeReport),
        ["size-report", ..] => Err("size-report takes no arguments".into()),
        ["synth-blob", rest @ ..] => parse_synth(rest),
        ["convert", rest @ ..] => parse_convert(rest),
        ["overtake-figure", rest @ ..] => parse_figure(rest),
        ["learning-curves", rest @ ..] => parse_curves(rest),
        ["cortex-m", "test"] => Ok(Command::CortexMTest),
        ["cortex-m", "icount"] => Ok(Command::CortexMIcount { breakdown: false }),
        ["cortex-m", "icount", "--breakdown"] => Ok(Command::CortexMIcount { breakdown: true }),
        ["cortex-m", ..] => Err("cortex-m takes `test`, `icount` or `icount --breakdown`".into()),
        [other, ..] => Err(format!("unknown subcommand `{other}`")),
    }
}

/// Runs the command line; the exit code is the command's (2 for a usage error).
pub fn main(args: Vec<String>) -> ExitCode {
    let command = match parse(&args) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}\n\n{USAGE}");
            return ExitCode::from(2);
        }
    };
    let result = match command {
        Command::Help => {
            println!("{USAGE}");
            Ok(ExitCode::SUCCESS)
        }
        Command::Inspect(path) => inspect::run(&path),
        Command::SizeReport => size::run(),
        Command::SynthBlob { row, seed, out } => synth_blob(row, seed, &out),
        Command::Convert { dtype, input, out } => convert(dtype, &input, &out),
        Command::OvertakeFigure(args) => figure::run(&args),
        Command::LearningCurves(args) => curves::run(&args),
        Command::CortexMTest => cortex_m::run_tests(),
        Command::CortexMIcount { breakdown } => cortex_m::run_icount(breakdown),
    };
    result.unwrap_or_else(|e| {
        eprintln!("error: {e}");
        ExitCode::FAILURE
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &[&str]) -> Vec<String> {
        s.iter().map(|a| a.to_string()).collect()
    }

    #[test]
    fn parses_every_subcommand() {
        assert_eq!(
            parse(&args(&["inspect", "x.bin"])),
            Ok(Command::Inspect("x.bin".into()))
        );
        assert_eq!(parse(&args(&["size-report"])), Ok(Command::SizeReport));
        assert_eq!(
            parse(&args(&["cortex-m", "test"])),
            Ok(Command::CortexMTest)
        );
        assert_eq!(
            parse(&args(&["cortex-m", "icount"])),
            Ok(Command::CortexMIcount { breakdown: false })
        );
        assert_eq!(
            parse(&args(&["cortex-m", "icount", "--breakdown"])),
            Ok(Command::CortexMIcount { breakdown: true })
        );
        assert_eq!(parse(&args(&["--help"])), Ok(Command::Help));
        assert_eq!(
            parse(&args(&[
                "learning-curves",
                "--run",
                "runs/a=ours, seed 1",
                "--run",
                "runs/b",
                "--out",
                "c.svg"
            ])),
            Ok(Command::LearningCurves(curves::CurvesArgs {
                runs: vec![
                    ("runs/a".into(), "ours, seed 1".into()),
                    ("runs/b".into(), "runs/b".into())
                ],
                out: "c.svg".into()
            }))
        );
        assert!(parse(&args(&["learning-curves"])).is_err());
        assert!(parse(&args(&["learning-curves", "--run", "=x"])).is_err());
        assert_eq!(
            parse(&args(&["synth-blob", "--row", "g", "--out", "g.blob"])),
            Ok(Command::SynthBlob {
                row: TableRow::G,
                seed: 1,
                out: "g.blob".into()
            })
        );
        assert_eq!(
            parse(&args(&[
                "convert", "--dtype", "i8", "--in", "a.blob", "--out", "b.blob"
            ])),
            Ok(Command::Convert {
                dtype: WeightDtype::I8,
                input: "a.blob".into(),
                out: "b.blob".into()
            })
        );
    }

    #[test]
    fn converts_a_blob_to_int8_and_refuses_garbage() {
        let dir = std::env::temp_dir().join(format!("overtake-convert-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let (f, q) = (dir.join("g.blob"), dir.join("g_i8.blob"));
        let bytes = firmware_core::synthetic::blob(TableRow::G, 3).expect("encode");
        std::fs::write(&f, &bytes).expect("write");
        assert_eq!(
            convert(WeightDtype::I8, &f, &q).ok(),
            Some(ExitCode::SUCCESS)
        );
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
        let err = convert(WeightDtype::I8, &f, &q).expect_err("garbage");
        assert!(err.to_string().contains("not a valid blob"), "{err}");
        // The earlier output was not touched by the failed conversion.
        assert_eq!(std::fs::read(&q).expect("read"), out);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn refuses_bad_input() {
        for bad in [
            &[][..],
            &["inspect"],
            &["inspect", "a", "b"],
            &["cortex-m"],
            &["cortex-m", "run"],
            &["frob"],
            &["synth-blob", "--row", "H", "--out", "x"],
            &["synth-blob", "--row", "A"],
            &["synth-blob", "--out", "x", "--seed", "-1"],
            &["convert", "--dtype", "f16", "--in", "a", "--out", "b"],
            &["convert", "--in", "a", "--out", "b"],
            &["convert", "--dtype", "i8", "--in", "a"],
        ] {
            assert!(parse(&args(bad)).is_err(), "{bad:?}");
        }
    }
}
