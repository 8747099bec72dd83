//! Building and running the Cortex-M4 images of `tools/cortex-m-tests` through cargo and QEMU.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};

use crate::{Error, Result};

/// The bare-metal target of the images (Cortex-M4F, hard float).
pub const TARGET: &str = "thumbv7em-none-eabihf";

/// The package of the images.
pub const PACKAGE: &str = "cortex-m-tests";

/// The QEMU command of `.cargo/config.toml`'s runner (the ELF path follows `-kernel`).
pub const QEMU_RUNNER: &str = "qemu-system-arm -cpu cortex-m4 -machine mps2-an386 -nographic \
                               -semihosting-config enable=on,target=native -kernel";

/// The runner for instruction counting: 1 ns of virtual time per instruction.
pub const QEMU_ICOUNT_RUNNER: &str = "qemu-system-arm -cpu cortex-m4 -machine mps2-an386 -nographic \
                                      -semihosting-config enable=on,target=native -icount shift=0 -kernel";

/// The environment variable that overrides the runner of [`TARGET`].
pub const RUNNER_ENV: &str = "CARGO_TARGET_THUMBV7EM_NONE_EABIHF_RUNNER";

/// The workspace root (this crate's parent folder).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// A `cargo` command in the workspace root (the `cargo` that runs us, when there is one).
pub fn cargo() -> Command {
    let mut c = Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()));
    c.current_dir(workspace_root());
    c
}

/// Checks that QEMU can be started, with a clear error when it cannot.
pub fn check_qemu() -> Result<()> {
    let ok = Command::new("qemu-system-arm")
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    if ok {
        Ok(())
    } else {
        Err(Error::new(
            "qemu-system-arm not found: install QEMU's Arm system emulator (Debian: qemu-system-arm)",
        ))
    }
}

fn exit_code_of(status: std::process::ExitStatus, what: &str) -> ExitCode {
    match status.code() {
        Some(0) => ExitCode::SUCCESS,
        Some(code) => {
            eprintln!("{what} failed (exit status {code})");
            ExitCode::from(u8::try_from(code).unwrap_or(1).max(1))
        }
        None => {
            eprintln!("{what} was killed by a signal");
            ExitCode::FAILURE
        }
    }
}

fn spawn(mut c: Command, what: &str) -> Result<ExitCode> {
    let status = c
        .status()
        .map_err(|e| Error::new(format!("cannot run cargo for {what}: {e}")))?;
    Ok(exit_code_of(status, what))
}

/// The test images under QEMU (runner of `.cargo/config.toml`), `release` profile: the
/// test image `cortex-m-tests` (`cargo run -p cortex-m-tests --release --target
/// thumbv7em-none-eabihf`), then `shipped` (the F405 image's int8 policies against the host);
/// the exit status is the first failing QEMU's, else success.
pub fn run_tests() -> Result<ExitCode> {
    check_qemu()?;
    for (bin, what) in [
        (PACKAGE, "the Cortex-M test image"),
        ("shipped", "the Cortex-M shipped-policy image"),
    ] {
        let mut c = cargo();
        c.args([
            "run",
            "-p",
            PACKAGE,
            "--release",
            "--target",
            TARGET,
            "--bin",
            bin,
        ]);
        let code = spawn(c, what)?;
        if code != ExitCode::SUCCESS {
            return Ok(code);
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The instruction-count bench (`icount`, or `icount-breakdown`), profile `firmware`, under
/// QEMU with `-icount shift=0` (the runner is overridden through [`RUNNER_ENV`]).
pub fn run_icount(breakdown: bool) -> Result<ExitCode> {
    check_qemu()?;
    let bin = if breakdown {
        "icount-breakdown"
    } else {
        "icount"
    };
    let mut c = cargo();
    c.env(RUNNER_ENV, QEMU_ICOUNT_RUNNER);
    c.args([
        "run",
        "-p",
        PACKAGE,
        "--profile",
        "firmware",
        "--target",
        TARGET,
        "--bin",
        bin,
    ]);
    spawn(c, "the instruction-count bench")
}

/// Builds bins of `package` for [`TARGET`] with `profile` and returns `(bin, ELF path)`
/// for each, from cargo's JSON messages.
pub fn build_bins(package: &str, profile: &str, bins: &[&str]) -> Result<Vec<(String, PathBuf)>> {
    let mut c = cargo();
    c.args([
        "build",
        "-p",
        package,
        "--profile",
        profile,
        "--target",
        TARGET,
        "--message-format=json-render-diagnostics",
    ]);
    for b in bins {
        c.args(["--bin", b]);
    }
    c.stdout(Stdio::piped()).stderr(Stdio::inherit());
    let out = c
        .output()
        .map_err(|e| Error::new(format!("cannot run cargo build: {e}")))?;
    if !out.status.success() {
        return Err(Error::new(format!(
            "cargo build of {} failed ({})",
            bins.join(", "),
            out.status
        )));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let mut found = Vec::new();
    for line in stdout
        .lines()
        .filter(|l| l.contains("\"reason\":\"compiler-artifact\""))
    {
        let Some(exe) = json_string_field(line, "executable") else {
            continue;
        };
        let path = PathBuf::from(exe);
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default()
            .to_string();
        if bins.contains(&name.as_str()) {
            found.push((name, path));
        }
    }
    for b in bins {
        if !found.iter().any(|(n, _)| n == b) {
            return Err(Error::new(format!(
                "cargo built no executable for bin `{b}`"
            )));
        }
    }
    Ok(found)
}

/// The string value of `"key":"…"` in one line of JSON (enough for cargo's messages).
pub fn json_string_field(line: &str, key: &str) -> Option<String> {
    let pattern = format!("\"{key}\":\"");
    let start = line.find(&pattern)? + pattern.len();
    let mut out = String::new();
    let mut chars = line.get(start..)?.chars();
    while let Some(c) = chars.next() {
        match c {
            '"' => return Some(out),
            '\\' => match chars.next()? {
                'n' => out.push('\n'),
                't' => out.push('\t'),
                'r' => out.push('\r'),
                'b' => out.push('\u{8}'),
                'f' => out.push('\u{c}'),
                'u' => {
                    let hex: String = chars.by_ref().take(4).collect();
                    out.push(char::from_u32(u32::from_str_radix(&hex, 16).ok()?)?);
                }
                other => out.push(other),
            },
            c => out.push(c),
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_json_string_fields() {
        let line =
            r#"{"reason":"compiler-artifact","executable":"/t/a\\b \"c\" \u00e9","fresh":true}"#;
        assert_eq!(
            json_string_field(line, "executable").as_deref(),
            Some("/t/a\\b \"c\" é")
        );
        assert_eq!(
            json_string_field(line, "reason").as_deref(),
            Some("compiler-artifact")
        );
        assert_eq!(
            json_string_field(r#"{"executable":null}"#, "executable"),
            None
        );
    }
}
