//! The command line (clap derive) and its dispatch to the subcommands' modules.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::{blobs, cortex_m, curves, figure, inspect, size};

/// The command line: `cargo run -p tools -- <subcommand>`.
#[derive(Debug, Parser)]
#[command(
    name = "tools",
    bin_name = "cargo run -p tools --",
    version,
    about = "Overtake's command-line helpers: blob inspector and converter, overtake figure, \
             learning curves, firmware size report, Cortex-M test runner"
)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// A subcommand.
#[derive(Debug, Clone, PartialEq, Subcommand)]
pub enum Command {
    /// Decode a weight blob and print its header (exit 1 on a defect).
    ///
    /// A defective blob prints the typed error of firmware-core (bad magic, version,
    /// truncation, CRC...).
    Inspect {
        /// The blob file.
        #[arg(value_name = "BLOB")]
        blob: PathBuf,
    },
    /// Build the Cortex-M4 size images and report their flash and RAM (bytes).
    ///
    /// The images: rows A and G in f32 (synthetic weights), and the shipped stage-1 and
    /// stage-2 policies in int8 linked against the STM32F405's memory map (profile
    /// `firmware`); their flash and RAM are read from the ELF and set against an STM32F405
    /// (1 MB flash; 128 KB SRAM + 64 KB CCM).
    SizeReport,
    /// Re-encode a blob in another weight dtype.
    ///
    /// f32 -> i8 quantises every matrix row (symmetric, f32 scales; biases stay f32);
    /// i8 -> f32 writes the dequantised weights.
    Convert(blobs::ConvertArgs),
    /// Write a Table 1 row's blob with seeded random weights (never for flight).
    ///
    /// For trying the tools (inspect, convert, the Cortex-M images) without a trained policy.
    SynthBlob(blobs::SynthArgs),
    /// Draw an overtake of a recorded race from above (the paper's Fig. 3).
    ///
    /// The ego's and the opponent's paths over a window of seconds around the overtake, with
    /// the gates, the centreline and each second marked on both paths.
    OvertakeFigure(figure::FigureArgs),
    /// Draw training runs' learning curves on one page (SVG).
    ///
    /// Reads each run's `metrics.jsonl` (of `host-trainer train` or tools/train_rslrl.py):
    /// referee success and best lap (s), rollout gates and crashes per second and the
    /// policy's σ, and for races the referee's overtakes (all and sustained) and win rate,
    /// against env-steps and wall-clock (min), beside the authors' run (no gate in 410 M
    /// env-steps).
    LearningCurves(curves::CurvesArgs),
    /// Run the Cortex-M4 images of tools/cortex-m-tests under QEMU (docs/cortex-m.md).
    #[command(subcommand)]
    CortexM(CortexM),
}

/// A `cortex-m` subcommand.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Subcommand)]
pub enum CortexM {
    /// Build and run the Cortex-M4 test image under QEMU (mps2-an386); exit with its status.
    Test,
    /// Count the instructions per Controller::step on the emulated Cortex-M4.
    ///
    /// QEMU with -icount shift=0 (one instruction per virtual nanosecond), profile
    /// `firmware`; rows A and G, f32 and int8.
    Icount {
        /// Run the icount-breakdown image instead: instructions per layer and kernel.
        #[arg(long)]
        breakdown: bool,
    },
}

/// Runs `command`; the exit code is the command's, 1 after printing a tool's error.
pub fn run(command: &Command) -> ExitCode {
    let result = match command {
        Command::Inspect { blob } => inspect::run(blob),
        Command::SizeReport => size::run(),
        Command::Convert(args) => blobs::convert(args),
        Command::SynthBlob(args) => blobs::synth_blob(args),
        Command::OvertakeFigure(args) => figure::run(args),
        Command::LearningCurves(args) => curves::run(args),
        Command::CortexM(CortexM::Test) => cortex_m::run_tests(),
        Command::CortexM(CortexM::Icount { breakdown }) => cortex_m::run_icount(*breakdown),
    };
    result.unwrap_or_else(|e| {
        eprintln!("error: {e}");
        ExitCode::FAILURE
    })
}

/// Parses the process's arguments and runs them: clap prints usage errors and exits 2
/// (`--help`, `help` and `--version` exit 0).
pub fn main() -> ExitCode {
    run(&Cli::parse().command)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;
    use firmware_core::blob::WeightDtype;
    use firmware_core::policy::TableRow;

    fn parse(args: &[&str]) -> std::result::Result<Command, clap::Error> {
        Cli::try_parse_from(std::iter::once("tools").chain(args.iter().copied())).map(|c| c.command)
    }

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn parses_every_subcommand() {
        let ok = |args: &[&str]| parse(args).expect("parses");
        assert_eq!(
            ok(&["inspect", "x.bin"]),
            Command::Inspect {
                blob: "x.bin".into()
            }
        );
        assert_eq!(ok(&["size-report"]), Command::SizeReport);
        assert_eq!(ok(&["cortex-m", "test"]), Command::CortexM(CortexM::Test));
        assert_eq!(
            ok(&["cortex-m", "icount"]),
            Command::CortexM(CortexM::Icount { breakdown: false })
        );
        assert_eq!(
            ok(&["cortex-m", "icount", "--breakdown"]),
            Command::CortexM(CortexM::Icount { breakdown: true })
        );
        assert_eq!(
            ok(&[
                "learning-curves",
                "--run",
                "runs/a=ours, seed 1",
                "--run",
                "runs/b",
                "--out",
                "c.svg"
            ]),
            Command::LearningCurves(curves::CurvesArgs {
                runs: vec![
                    ("runs/a".into(), "ours, seed 1".into()),
                    ("runs/b".into(), "runs/b".into())
                ],
                out: "c.svg".into()
            })
        );
        assert_eq!(
            ok(&["synth-blob", "--row", "g", "--out", "g.blob"]),
            Command::SynthBlob(blobs::SynthArgs {
                row: TableRow::G,
                seed: 1,
                out: "g.blob".into()
            })
        );
        assert_eq!(
            ok(&[
                "convert", "--dtype", "i8", "--in", "a.blob", "--out", "b.blob"
            ]),
            Command::Convert(blobs::ConvertArgs {
                dtype: WeightDtype::I8,
                input: "a.blob".into(),
                out: "b.blob".into()
            })
        );
        assert_eq!(
            ok(&["overtake-figure", "--trace", "t.json"]),
            Command::OvertakeFigure(figure::FigureArgs {
                trace: "t.json".into(),
                episode: None,
                overtake: None,
                window_s: 8.0,
                out: "overtake.svg".into(),
                summary: false
            })
        );
        assert_eq!(
            ok(&[
                "overtake-figure",
                "--trace",
                "t.json",
                "--episode",
                "2",
                "--overtake",
                "1",
                "--window-s",
                "4",
                "--out",
                "o.svg",
                "--summary"
            ]),
            Command::OvertakeFigure(figure::FigureArgs {
                trace: "t.json".into(),
                episode: Some(2),
                overtake: Some(1),
                window_s: 4.0,
                out: "o.svg".into(),
                summary: true
            })
        );
    }

    #[test]
    fn help_and_version_exit_zero() {
        for args in [
            &["--help"][..],
            &["-h"],
            &["help"],
            &["help", "convert"],
            &["--version"],
        ] {
            let err = parse(args).expect_err("help is reported as an error");
            assert_eq!(err.exit_code(), 0, "{args:?}");
        }
    }

    #[test]
    fn refuses_bad_input_with_a_usage_error() {
        for bad in [
            &[][..],
            &["inspect"],
            &["inspect", "a", "b"],
            &["inspect", "-x"],
            &["size-report", "x"],
            &["cortex-m"],
            &["cortex-m", "run"],
            &["cortex-m", "test", "--breakdown"],
            &["frob"],
            &["synth-blob", "--row", "H", "--out", "x"],
            &["synth-blob", "--row", "AB", "--out", "x"],
            &["synth-blob", "--row", "A"],
            &["synth-blob", "--out", "x", "--seed", "-1"],
            &["convert", "--dtype", "f16", "--in", "a", "--out", "b"],
            &["convert", "--in", "a", "--out", "b"],
            &["convert", "--dtype", "i8", "--in", "a"],
            &["overtake-figure"],
            &["overtake-figure", "--trace", "t", "--window-s", "0"],
            &["overtake-figure", "--trace", "t", "--window-s", "61"],
            &["overtake-figure", "--trace", "t", "--window-s", "NaN"],
            &["overtake-figure", "--trace", "t", "--episode", "-1"],
            &["overtake-figure", "--trace", "t", "--frob", "1"],
            &["learning-curves"],
            &["learning-curves", "--run", "=x"],
            &["learning-curves", "--run", "x="],
            &["learning-curves", "--run"],
        ] {
            let err = parse(bad).expect_err(&format!("{bad:?}"));
            assert_eq!(err.exit_code(), 2, "{bad:?}: {err}");
        }
    }

    #[test]
    fn value_errors_say_what_is_expected() {
        let message = |args: &[&str]| parse(args).expect_err("bad").to_string();
        let row = message(&["synth-blob", "--row", "H", "--out", "x"]);
        assert!(row.contains("expected one letter, A to G"), "{row}");
        let dtype = message(&["convert", "--dtype", "f16", "--in", "a", "--out", "b"]);
        assert!(
            dtype.contains("'f16' for '--dtype <f32|i8>': expected f32 or i8"),
            "{dtype}"
        );
        let window = message(&["overtake-figure", "--trace", "t", "--window-s", "90"]);
        assert!(window.contains("expected seconds in (0, 60]"), "{window}");
        let run = message(&["learning-curves", "--run", "=x"]);
        assert!(run.contains("expected DIR or DIR=LABEL"), "{run}");
    }
}
