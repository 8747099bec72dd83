//! Starting the controllers: processes, threads of this process, or addresses to attach to.

use super::super::fc::{FcConfig, FcSummary, serve};
use super::{Entrant, RaceConfig, RaceError, Transport};
use std::io::{self, BufRead, BufReader};
use std::net::{SocketAddr, UdpSocket};
use std::process::{Child, Command, Stdio};
use std::thread::JoinHandle;

/// A started controller.
pub(super) struct Endpoint {
    pub(super) addr: SocketAddr,
    pub(super) child: Option<Child>,
    pub(super) thread: Option<JoinHandle<io::Result<FcSummary>>>,
}

impl Drop for Endpoint {
    fn drop(&mut self) {
        if let Some(c) = &mut self.child {
            if matches!(c.try_wait(), Ok(None)) {
                let _ = c.kill();
            }
            let _ = c.wait();
        }
    }
}

/// Starts the controller of `e`.
pub(super) fn launch(
    index: usize,
    e: &Entrant,
    transport: &Transport,
    config: &RaceConfig,
) -> Result<Endpoint, RaceError> {
    match transport {
        Transport::Attach(addrs) => match addrs.get(index) {
            Some(&addr) => Ok(Endpoint {
                addr,
                child: None,
                thread: None,
            }),
            None => Err(RaceError::Launch(format!(
                "no address to attach the {} controller to",
                e.role
            ))),
        },
        Transport::Threads => {
            let socket = UdpSocket::bind("127.0.0.1:0")?;
            let addr = socket.local_addr()?;
            let fc = FcConfig {
                pilot: e.pilot.clone(),
                system_id: e.system_id,
                signing_key: config.signing_key,
                idle_timeout: config.startup_timeout,
            };
            let thread = std::thread::Builder::new()
                .name(format!("fc-{}", e.system_id))
                .spawn(move || serve(&socket, &fc))?;
            Ok(Endpoint {
                addr,
                child: None,
                thread: Some(thread),
            })
        }
        Transport::Processes(exe) => {
            let mut cmd = Command::new(exe);
            cmd.args(["fc", "--blob", &e.spec, "--sysid", &e.system_id.to_string()])
                .args(["--port", "0", "--preset", config.eval.preset.name])
                .args([
                    "--idle-timeout-s",
                    &config.startup_timeout.as_secs().max(1).to_string(),
                ])
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit());
            if let Some(key) = &config.signing_key {
                let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
                cmd.args(["--signing-key", &hex]);
            }
            let mut child = cmd.spawn().map_err(|err| {
                RaceError::Launch(format!("cannot start {} fc: {err}", exe.display()))
            })?;
            let mut line = String::new();
            let read = child
                .stdout
                .take()
                .map(|out| BufReader::new(out).read_line(&mut line));
            let addr = line
                .rsplit(' ')
                .next()
                .and_then(|a| a.trim().parse::<SocketAddr>().ok());
            match (read, addr) {
                (Some(Ok(_)), Some(addr)) => Ok(Endpoint {
                    addr,
                    child: Some(child),
                    thread: None,
                }),
                _ => {
                    let status = child.wait().map(|s| s.to_string()).unwrap_or_default();
                    Err(RaceError::Launch(format!(
                        "the {} controller ({}) did not start ({status})",
                        e.role, e.spec
                    )))
                }
            }
        }
    }
}
