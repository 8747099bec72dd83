//! `sitl`: fly and score controllers in the simulated world.
//!
//! - `sitl eval --ego <blob|baseline> [--opponent <blob|baseline>] [--preset paper]
//!   [--episodes 20] [--seconds 45] [--seed 0] [--spawn stage1|stage2|along-track]
//!   [--json out.json] [--plot out.svg]`: the referee's Table-1 row over many seeded
//!   episodes, in-process.
//! - `sitl fly [--ego baseline] [--preset paper] [--seconds 45] [--cruise M_PER_S]`: one
//!   time trial from the stage-1 spawn with every lap time printed.
//! - `sitl race [--ego X] [--opponent Y|none] [--episodes 20] [--seed 0] [--json F]
//!   [--tlog race.tlog] [--plot race.svg] [--realtime] [--in-process] [--signing-key K]`:
//!   the shipped policies raced over MAVLink in lockstep, each controller its own process.
//! - `sitl robustness --ego <blob|baseline> [--opponent ...] [--episodes 20] [--json F]
//!   [--markdown F]`: the pilot and its int8 copy under the standard perturbations.
//! - `sitl eval ... --jitter[=SPEC] --perturb SPEC`: one eval perturbed
//!   (docs/DESIGN.md "Perturbations").
//! - `sitl fc --blob X --sysid N --port P [--signing-key K]`: one controller as a MAVLink
//!   endpoint (what `race` starts).
//!
//! Each subcommand's arguments and body are in [`cli`]'s module of its name; the arguments
//! they share ([`cli::Contest`], [`cli::Common`], [`cli::Scoring`]) in [`cli`] itself.

mod cli;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "sitl",
    version,
    about = "Fly and score drone-racing controllers in the simulated world"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Score a pilot over many seeded 45 s episodes (in-process, no MAVLink) and print its
    /// Table-1 row with 95% intervals.
    Eval(cli::eval::EvalArgs),
    /// Fly one time trial from the stage-1 spawn and print every lap.
    Fly(cli::fly::FlyArgs),
    /// Race the shipped policies (or any two pilots) over MAVLink in lockstep, each
    /// controller its own process; print the Table-1 row, write race.tlog and race.svg.
    Race(cli::race::RaceArgs),
    /// Run one controller as a MAVLink endpoint on a UDP port (what `race` starts).
    Fc(cli::fc::FcArgs),
    /// Convert an f32 blob to int8 and measure what it costs: the int8 policy's action
    /// error on the observations of races the f32 policy flies, then both blobs' Table-1
    /// rows over the same seeded episodes.
    Int8Check(cli::int8::Int8CheckArgs),
    /// Fly a pilot (f32 and its int8 conversion) under the standard perturbations: start
    /// jitter, sensor noise, thrust, mass, inertia, motor lag, latency; print the table and
    /// the largest level of each it survives (success >= 0.9).
    Robustness(cli::robustness::RobustnessArgs),
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Eval(a) => cli::eval::run(a).map(|()| ExitCode::SUCCESS),
        Command::Fly(a) => cli::fly::run(a).map(|()| ExitCode::SUCCESS),
        Command::Race(a) => cli::race::run(a),
        Command::Fc(a) => cli::fc::run(a).map(|()| ExitCode::SUCCESS),
        Command::Int8Check(a) => cli::int8::run(a),
        Command::Robustness(a) => cli::robustness::run(a).map(|()| ExitCode::SUCCESS),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
