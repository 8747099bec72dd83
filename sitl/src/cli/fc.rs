//! `sitl fc`: one controller as a MAVLink endpoint on a UDP port (what `sitl race` starts).

use super::{load, parse_preset};
use clap::Args;
use sitl::bridge::fc::FcConfig;
use sitl::dynamics::Preset;

/// The arguments of `sitl fc`.
#[derive(Args)]
pub struct FcArgs {
    /// The pilot: a policy blob file, or baseline[:CRUISE_MPS[:OFFSET_M]].
    #[arg(long)]
    blob: String,
    /// MAVLink system id (1-249).
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=249))]
    sysid: u8,
    /// UDP port on 127.0.0.1 (0: any free port; the first line printed names it).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Dynamics preset (tunes the baseline to the preset's thrust).
    #[arg(long, default_value = "paper", value_parser = parse_preset)]
    preset: Preset,
    /// Require and send MAVLink 2 signatures: 64 hex digits, or a passphrase (SHA-256).
    #[arg(long)]
    signing_key: Option<String>,
    /// Exit after this many seconds without a valid frame.
    #[arg(long, default_value_t = 30)]
    idle_timeout_s: u64,
}

/// Runs `sitl fc` until the simulator shuts it down or it idles out.
pub fn run(args: FcArgs) -> Result<(), String> {
    use std::io::Write;
    let pilot = load(&args.blob, &args.preset, "--blob")?;
    let signing_key = args
        .signing_key
        .as_deref()
        .map(sitl::bridge::wire::signing_key)
        .transpose()?;
    let socket = std::net::UdpSocket::bind(("127.0.0.1", args.port))
        .map_err(|e| format!("cannot bind 127.0.0.1:{}: {e}", args.port))?;
    let addr = socket.local_addr().map_err(|e| e.to_string())?;
    // The first line names the endpoint: `sitl race` reads it.
    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "sitl fc: system {} ({}) listening on {addr}",
        args.sysid,
        pilot.describe()
    )
    .and_then(|()| out.flush())
    .map_err(|e| e.to_string())?;
    drop(out);
    let config = FcConfig {
        pilot,
        system_id: args.sysid,
        signing_key,
        idle_timeout: std::time::Duration::from_secs(args.idle_timeout_s),
    };
    let summary = sitl::bridge::fc::serve(&socket, &config).map_err(|e| e.to_string())?;
    let l = summary.link;
    eprintln!(
        "sitl fc: system {} {} after {} steps, {} flights; {} frames in, {} dropped",
        args.sysid,
        if summary.shut_down {
            "shut down"
        } else {
            "idle, exiting"
        },
        summary.steps,
        summary.flights,
        l.frames_received,
        l.dropped()
    );
    Ok(())
}
