//! `cargo run -p tools -- <subcommand>`: see `tools::cli::USAGE`.

fn main() -> std::process::ExitCode {
    tools::cli::main(std::env::args().skip(1).collect())
}
