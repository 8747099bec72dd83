//! `cargo run -p tools -- <subcommand>`: `--help` lists them; see `tools::cli`.

fn main() -> std::process::ExitCode {
    tools::cli::main()
}
