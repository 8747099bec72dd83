//! The MAVLink bridge end to end: lockstep races over UDP give `sitl eval`'s trajectories,
//! and faults (a killed controller, malformed frames, duplicated and reordered datagrams,
//! a wrong system id, bad signatures, a state stamped far in the future) neither hang nor
//! crash the simulator nor wedge a controller, and are reported. `link_fuzz.rs` fuzzes the
//! same datagram handling without sockets.

use sitl::bridge::fc::{FcConfig, serve};
use sitl::bridge::race::{Entrant, RaceConfig, RaceOutcome, Transport, race};
use sitl::bridge::wire::{Codec, signing_key};
use sitl::bridge::{AUTOPILOT_COMPONENT_ID, actuator_message};
use sitl::dynamics::Preset;
use sitl::eval::{EvalConfig, evaluate};
use sitl::pilot::PilotSpec;
use sitl::referee::Episode;
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

fn student() -> String {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../policies/stage1_imitation.blob")
        .display()
        .to_string()
}

fn entrant(role: &str, spec: &str, system_id: u8) -> Entrant {
    Entrant {
        role: role.into(),
        spec: spec.into(),
        pilot: PilotSpec::load(spec, &Preset::paper()).expect("pilot loads"),
        system_id,
    }
}

fn eval_config(episodes: u32, seconds: f32) -> EvalConfig {
    EvalConfig {
        preset: Preset::paper(),
        episodes,
        seconds,
        seed: 7,
        spawn: None,
        perturbation: sitl::perturb::Perturbation::NONE,
    }
}

fn config(episodes: u32, seconds: f32) -> RaceConfig {
    let mut c = RaceConfig::new(eval_config(episodes, seconds));
    c.record = true;
    c
}

/// Largest position difference (m) between two sets of traces, and whether the respawns
/// agree.
fn max_deviation(a: &[Episode], b: &[Episode]) -> f32 {
    assert_eq!(a.len(), b.len());
    let mut worst = 0.0f32;
    for (x, y) in a.iter().zip(b) {
        assert_eq!(x.trace.ego_m.len(), y.trace.ego_m.len());
        assert_eq!(x.trace.respawns, y.trace.respawns, "respawn steps differ");
        let pairs = x
            .trace
            .ego_m
            .iter()
            .zip(&y.trace.ego_m)
            .chain(x.trace.opponent_m.iter().zip(&y.trace.opponent_m));
        for (p, q) in pairs {
            for d in [p.x - q.x, p.y - q.y, p.z - q.z] {
                worst = worst.max(d.abs());
            }
        }
    }
    worst
}

fn assert_clean(o: &RaceOutcome) {
    for c in &o.controllers {
        assert!(c.failure.is_none(), "{} failed: {:?}", c.role, c.failure);
        assert_eq!(c.link.rejected(), 0, "{}: {:?}", c.role, c.link);
    }
}

#[test]
fn a_lockstep_race_over_processes_flies_sitl_evals_trajectories() {
    let (ego, opp) = (student(), "baseline".to_string());
    let entrants = [entrant("ego", &ego, 1), entrant("opponent", &opp, 2)];
    let c = config(3, 45.0);
    let outcome = race(
        &entrants,
        &Transport::Processes(env!("CARGO_BIN_EXE_sitl").into()),
        &c,
    )
    .expect("race runs");
    assert_clean(&outcome);
    let reference = evaluate(&entrants[0].pilot, Some(&entrants[1].pilot), &c.eval, true);
    let worst = max_deviation(&outcome.episodes, &reference);
    println!("max position difference, processes vs in-process: {worst:e} m");
    assert!(worst <= 1e-6, "{worst} m");
    let metrics: Vec<_> = reference.into_iter().map(|e| e.metrics).collect();
    let expected = sitl::eval::Report::new(
        &entrants[0].pilot,
        Some(&entrants[1].pilot),
        &c.eval,
        &metrics,
    );
    assert_eq!(outcome.report, expected);
    // Every step was answered by each controller, and nothing else was counted.
    let steps = 3 * 2250;
    for ctl in &outcome.controllers {
        assert!(ctl.link.frames_received >= steps, "{ctl:?}");
    }
}

#[test]
fn threads_and_time_trials_match_too() {
    let entrants = [entrant("ego", &student(), 1)];
    let c = config(2, 20.0);
    let outcome = race(&entrants, &Transport::Threads, &c).expect("race runs");
    assert_clean(&outcome);
    let reference = evaluate(&entrants[0].pilot, None, &c.eval, true);
    let worst = max_deviation(&outcome.episodes, &reference);
    println!("max position difference, threads vs in-process: {worst:e} m");
    assert!(worst <= 1e-6, "{worst} m");
    assert!(outcome.report.gates_passed > 0);
}

fn start_fc(spec: &str, sysid: u8, key: Option<&str>) -> (Child, SocketAddr) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sitl"));
    cmd.args([
        "fc",
        "--blob",
        spec,
        "--sysid",
        &sysid.to_string(),
        "--port",
        "0",
    ])
    .args(["--idle-timeout-s", "10"])
    .stdout(Stdio::piped())
    .stderr(Stdio::null());
    if let Some(k) = key {
        cmd.args(["--signing-key", k]);
    }
    let mut child = cmd.spawn().expect("fc starts");
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(child.stdout.take().unwrap()),
        &mut line,
    )
    .unwrap();
    let addr = line.rsplit(' ').next().unwrap().trim().parse().unwrap();
    (child, addr)
}

#[test]
fn a_killed_controller_is_reported_and_the_race_finishes() {
    let (mut ego, ego_addr) = start_fc(&student(), 1, None);
    let (mut opp, opp_addr) = start_fc("baseline", 2, None);
    let entrants = [
        entrant("ego", &student(), 1),
        entrant("opponent", "baseline", 2),
    ];
    let mut c = config(4, 45.0);
    c.step_timeout = Duration::from_millis(300);
    c.startup_timeout = Duration::from_secs(2);
    let killer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(150));
        opp.kill().unwrap();
        opp.wait().unwrap();
    });
    let started = Instant::now();
    let outcome = race(&entrants, &Transport::Attach(vec![ego_addr, opp_addr]), &c)
        .expect("the race runs to its end");
    killer.join().unwrap();
    let _ = ego.wait();
    assert!(started.elapsed() < Duration::from_secs(20));
    assert_eq!(outcome.report.episodes, 4);
    assert!(outcome.controllers[0].failure.is_none());
    let why = outcome.controllers[1]
        .failure
        .as_deref()
        .expect("opponent failed");
    assert!(why.contains("silent"), "{why}");
    assert!(outcome.has_failures());
    assert!(outcome.to_json().contains("\"failure\": \"silent"));
}

/// A test's helper thread, told to stop and joined when dropped (or by [`Background::finish`]).
struct Background<T> {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<T>>,
}

impl<T: Send + 'static> Background<T> {
    /// Runs `work` on a thread; it should return once the flag it is given is set.
    fn spawn(work: impl FnOnce(Arc<AtomicBool>) -> T + Send + 'static) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        Self {
            stop,
            thread: Some(std::thread::spawn(move || work(flag))),
        }
    }

    /// Stops the thread and returns what it returned.
    fn finish(mut self) -> Option<T> {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.take().and_then(|t| t.join().ok())
    }
}

impl<T> Drop for Background<T> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A UDP proxy between the simulator and one controller that makes a bad network: every
/// datagram is delivered, then delivered again after the next one (duplicated and
/// reordered), with garbage and bit-flipped copies in both directions and, towards the
/// simulator, well-formed answers from a wrong system id.
struct Proxy {
    addr: SocketAddr,
    _worker: Background<()>,
}

impl Proxy {
    fn new(controller: SocketAddr) -> Self {
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        socket
            .set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        let addr = socket.local_addr().unwrap();
        let worker = Background::spawn(move |flag| {
            let mut sim: Option<SocketAddr> = None;
            let mut held: [Option<Vec<u8>>; 2] = [None, None];
            let mut impostor = Codec::new(AUTOPILOT_COMPONENT_ID, None, 0);
            let mut buf = vec![0u8; 65_536];
            let mut k = 0u64;
            while !flag.load(Ordering::Relaxed) {
                let Ok((n, from)) = socket.recv_from(&mut buf) else {
                    continue;
                };
                let to_sim = from == controller;
                if !to_sim {
                    sim = Some(from);
                }
                let Some(dest) = (if to_sim { sim } else { Some(controller) }) else {
                    continue;
                };
                let d = &buf[..n];
                k += 1;
                if k.is_multiple_of(5) {
                    let _ = socket.send_to(b"\xfd\x09garbage", dest);
                    let mut flipped = d.to_vec();
                    if let Some(b) = flipped.get_mut(14) {
                        *b ^= 0x10;
                    }
                    let _ = socket.send_to(&flipped, dest);
                }
                if to_sim && k.is_multiple_of(7) {
                    // A well-formed answer from system 99 on the controller's address: it
                    // must be counted and never taken for the controller's.
                    let mut fake = Vec::new();
                    impostor.encode(99, &actuator_message(0, &Default::default()), &mut fake);
                    let _ = socket.send_to(&fake, dest);
                }
                let _ = socket.send_to(d, dest);
                let slot = usize::from(to_sim);
                if let Some(old) = held[slot].replace(d.to_vec()) {
                    let _ = socket.send_to(&old, dest);
                }
            }
        });
        Self {
            addr,
            _worker: worker,
        }
    }
}

fn fc_thread(spec: &str, sysid: u8, key: Option<[u8; 32]>) -> SocketAddr {
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let addr = socket.local_addr().unwrap();
    let config = FcConfig {
        pilot: PilotSpec::load(spec, &Preset::paper()).unwrap(),
        system_id: sysid,
        signing_key: key,
        idle_timeout: Duration::from_secs(5),
    };
    std::thread::spawn(move || serve(&socket, &config));
    addr
}

#[test]
fn malformed_duplicated_reordered_and_impostor_frames_change_nothing() {
    let ego = fc_thread(&student(), 1, None);
    let opp = fc_thread("baseline", 2, None);
    let (p_ego, p_opp) = (Proxy::new(ego), Proxy::new(opp));
    let entrants = [
        entrant("ego", &student(), 1),
        entrant("opponent", "baseline", 2),
    ];
    let c = config(2, 20.0);
    let outcome = race(
        &entrants,
        &Transport::Attach(vec![p_ego.addr, p_opp.addr]),
        &c,
    )
    .expect("race runs");
    let reference = evaluate(&entrants[0].pilot, Some(&entrants[1].pilot), &c.eval, true);
    let worst = max_deviation(&outcome.episodes, &reference);
    assert!(worst <= 1e-6, "{worst} m");
    for ctl in &outcome.controllers {
        let l = &ctl.link;
        assert!(ctl.failure.is_none(), "{ctl:?}");
        assert!(l.malformed > 0 && l.bad_crc > 0, "{l:?}");
        assert!(l.stale > 0, "duplicates counted: {l:?}");
        assert!(l.wrong_system > 0, "impostor counted: {l:?}");
    }
    println!("{}", outcome.summary());
}

/// A UDP proxy that makes a lossy network in both directions, seeded: each datagram is
/// dropped with probability `loss`, else delivered after a delay drawn from 0-20 ms (so
/// datagrams overtake each other), and with probability `loss` delivered twice.
struct LossyProxy {
    addr: SocketAddr,
    /// The simulator's address, once it has sent.
    sim: Arc<std::sync::Mutex<Option<SocketAddr>>>,
    worker: Background<u64>,
}

impl LossyProxy {
    fn new(controller: SocketAddr, loss: f64, seed: u64) -> Self {
        use rand::{Rng, SeedableRng};
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        socket
            .set_read_timeout(Some(Duration::from_micros(500)))
            .unwrap();
        let addr = socket.local_addr().unwrap();
        let seen = Arc::new(std::sync::Mutex::new(None));
        let sim_seen = seen.clone();
        let worker = Background::spawn(move |flag| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut sim: Option<SocketAddr> = None;
            // (due, destination, datagram), delivered in order of due time.
            let mut queue: Vec<(Instant, SocketAddr, Vec<u8>)> = Vec::new();
            let mut buf = vec![0u8; 65_536];
            let mut dropped = 0u64;
            while !flag.load(Ordering::Relaxed) {
                let now = Instant::now();
                queue.sort_by_key(|q| q.0);
                while queue.first().is_some_and(|q| q.0 <= now) {
                    let (_, dest, d) = queue.remove(0);
                    let _ = socket.send_to(&d, dest);
                }
                let Ok((n, from)) = socket.recv_from(&mut buf) else {
                    continue;
                };
                let to_sim = from == controller;
                if !to_sim && sim.is_none() {
                    sim = Some(from);
                    if let Ok(mut s) = sim_seen.lock() {
                        *s = sim;
                    }
                }
                let Some(dest) = (if to_sim { sim } else { Some(controller) }) else {
                    continue;
                };
                if rng.random_bool(loss) {
                    dropped += 1;
                    continue;
                }
                let copies = if rng.random_bool(loss) { 2 } else { 1 };
                for _ in 0..copies {
                    let delay = Duration::from_micros(rng.random_range(0..20_000));
                    queue.push((Instant::now() + delay, dest, buf[..n].to_vec()));
                }
            }
            dropped
        });
        Self {
            addr,
            sim: seen,
            worker,
        }
    }

    /// The simulator's address, waiting up to 10 s for it to send.
    fn sim_addr(&self) -> Option<SocketAddr> {
        let until = Instant::now() + Duration::from_secs(10);
        while Instant::now() < until {
            if let Some(a) = self.sim.lock().ok().and_then(|s| *s) {
                return Some(a);
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        None
    }

    /// Stops the proxy and says how many datagrams it dropped.
    fn dropped(self) -> u64 {
        self.worker.finish().unwrap_or(0)
    }
}

/// Issue "faults": under 5 % loss, duplication, reordering and 0-20 ms of jitter in both
/// directions, on signed links, a race gives exactly `sitl eval`'s report and trajectories:
/// lost requests and lost answers are sent again, and a repeated step is answered from the
/// controller's cache, never stepped twice (a pilot stepped twice would advance its
/// recurrent state and the trajectories would part).
#[test]
fn a_lossy_jittery_network_gives_sitl_evals_race() {
    let key = Some(signing_key("lossy").unwrap());
    let ego = fc_thread(&student(), 1, key);
    let opp = fc_thread("baseline", 2, key);
    let (p_ego, p_opp) = (LossyProxy::new(ego, 0.05, 1), LossyProxy::new(opp, 0.05, 2));
    let entrants = [
        entrant("ego", &student(), 1),
        entrant("opponent", "baseline", 2),
    ];
    let mut c = config(2, 10.0);
    c.signing_key = key;
    let outcome = race(
        &entrants,
        &Transport::Attach(vec![p_ego.addr, p_opp.addr]),
        &c,
    )
    .expect("race runs");
    let dropped = p_ego.dropped() + p_opp.dropped();
    let reference = evaluate(&entrants[0].pilot, Some(&entrants[1].pilot), &c.eval, true);
    let worst = max_deviation(&outcome.episodes, &reference);
    assert_eq!(worst, 0.0, "{worst} m");
    let metrics: Vec<_> = reference.into_iter().map(|e| e.metrics).collect();
    let expected = sitl::eval::Report::new(
        &entrants[0].pilot,
        Some(&entrants[1].pilot),
        &c.eval,
        &metrics,
    );
    assert_eq!(outcome.report, expected);
    // 2 x 500 steps per link: 5 % of ~2,000 datagrams each way were lost and made up for.
    assert!(dropped > 100, "the proxy dropped only {dropped} datagrams");
    for ctl in &outcome.controllers {
        assert!(ctl.failure.is_none(), "{ctl:?}");
        assert!(ctl.link.resent > 20, "requests sent again: {:?}", ctl.link);
    }
    println!("{} ({dropped} datagrams dropped)", outcome.summary());
}

/// Issue "faults": another local socket floods both ends of both links as fast as it can
/// (garbage, and well-formed unsigned answers and states for every step), and the race
/// flies exactly `sitl eval`'s race: each end's socket is connected to its peer, so the
/// kernel drops the flood before it can fill the buffer the answers wait in. The proxies
/// in the path only tell the flood where the simulator's sockets are.
#[test]
fn a_local_flood_leaves_the_race_unchanged() {
    let ego = fc_thread(&student(), 1, None);
    let opp = fc_thread("baseline", 2, None);
    let (p_ego, p_opp) = (
        Arc::new(LossyProxy::new(ego, 0.0, 1)),
        Arc::new(LossyProxy::new(opp, 0.0, 2)),
    );
    let proxies = (p_ego.clone(), p_opp.clone());
    let flood = Background::spawn(move |flag| {
        // The controllers and the simulator's two sockets (not the proxies: they stand in
        // for the network, and forward whatever reaches them).
        let mut targets = vec![ego, opp];
        targets.extend(proxies.0.sim_addr());
        targets.extend(proxies.1.sim_addr());
        assert_eq!(targets.len(), 4, "the simulator never sent");
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        let mut codec = Codec::new(AUTOPILOT_COMPONENT_ID, None, 0);
        let mut sent = 0u64;
        let started = Instant::now();
        let mut t = 0u32;
        while !flag.load(Ordering::Relaxed) {
            let mut frame = Vec::new();
            codec.encode(
                1 + (t % 2) as u8,
                &actuator_message(t, &Default::default()),
                &mut frame,
            );
            let state = sitl::frames::NedState {
                position_m: firmware_core::math::Vec3::new(0.0, 0.0, -1.0),
                velocity_mps: Default::default(),
                attitude: firmware_core::math::Quat::IDENTITY,
                body_rates_radps: Default::default(),
            };
            for m in sitl::bridge::state_messages(t, &state) {
                codec.encode(1 + (t % 2) as u8, &m, &mut frame);
            }
            for to in &targets {
                for d in [&frame[..], b"\xfd\x09garbage"] {
                    if socket.send_to(d, to).is_ok() {
                        sent += 1;
                    }
                }
            }
            t = (t + 20) % 20_000;
        }
        sent as f64 / started.elapsed().as_secs_f64()
    });
    let entrants = [
        entrant("ego", &student(), 1),
        entrant("opponent", "baseline", 2),
    ];
    let c = config(1, 10.0);
    let outcome = race(
        &entrants,
        &Transport::Attach(vec![p_ego.addr, p_opp.addr]),
        &c,
    )
    .expect("race runs");
    let rate = flood.finish().unwrap();
    let reference = evaluate(&entrants[0].pilot, Some(&entrants[1].pilot), &c.eval, true);
    assert_eq!(max_deviation(&outcome.episodes, &reference), 0.0);
    for ctl in &outcome.controllers {
        assert!(ctl.failure.is_none(), "{ctl:?}");
        // Not one flood datagram reached the simulator's sockets: the kernel dropped them.
        let l = &ctl.link;
        assert_eq!((l.malformed, l.wrong_system, l.future), (0, 0, 0), "{l:?}");
    }
    println!("{}flood: {rate:.0} datagrams/s", outcome.summary());
    assert!(
        rate > 20_000.0,
        "the flood was too weak to mean anything: {rate:.0}/s"
    );
}

/// A UDP proxy between the simulator and one controller that passes everything through and,
/// right after the `at`-th datagram towards the controller, injects `extra` once.
struct Injector {
    addr: SocketAddr,
    _worker: Background<()>,
}

impl Injector {
    fn new(controller: SocketAddr, at: u64, extra: Vec<u8>) -> Self {
        let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
        socket
            .set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        let addr = socket.local_addr().unwrap();
        let worker = Background::spawn(move |flag| {
            let mut sim: Option<SocketAddr> = None;
            let mut buf = vec![0u8; 65_536];
            let mut towards_controller = 0u64;
            while !flag.load(Ordering::Relaxed) {
                let Ok((n, from)) = socket.recv_from(&mut buf) else {
                    continue;
                };
                if from == controller {
                    if let Some(sim) = sim {
                        let _ = socket.send_to(&buf[..n], sim);
                    }
                    continue;
                }
                sim = Some(from);
                let _ = socket.send_to(&buf[..n], controller);
                towards_controller += 1;
                if towards_controller == at {
                    let _ = socket.send_to(&extra, controller);
                }
            }
        });
        Self {
            addr,
            _worker: worker,
        }
    }
}

/// Issue 17: one CRC-valid state stamped far in the future (a replayed or corrupted frame,
/// which an unsigned link takes from anyone on the host) moved the controller's step clock:
/// the controller answered that state, took every later step for stale, and even a new
/// flight did not reset its clock, so the simulator declared it failed after the step
/// timeout. Now the controller takes only the step it expects and counts the frame as
/// `future`; the race flies `sitl eval`'s trajectories as if the frame had not come.
#[test]
fn future_stamped_state_does_not_wedge_the_controller() {
    let state = sitl::frames::NedState {
        position_m: firmware_core::math::Vec3::new(0.0, 0.0, -1.0),
        velocity_mps: Default::default(),
        attitude: firmware_core::math::Quat::IDENTITY,
        body_rates_radps: Default::default(),
    };
    let mut forged = Vec::new();
    let mut forger = Codec::new(sitl::bridge::SIM_COMPONENT_ID, None, 0);
    for m in sitl::bridge::state_messages(u32::MAX - 1, &state) {
        forger.encode(1, &m, &mut forged);
    }
    let ego = fc_thread(&student(), 1, None);
    // Datagram 1 starts the first flight, 101 is the step at t = 2 s.
    let injector = Injector::new(ego, 101, forged);
    let entrants = [entrant("ego", &student(), 1)];
    let mut c = config(2, 20.0);
    c.step_timeout = Duration::from_millis(300);
    let outcome = race(&entrants, &Transport::Attach(vec![injector.addr]), &c).expect("race runs");
    assert!(
        outcome.controllers[0].failure.is_none(),
        "{}",
        outcome.summary()
    );
    let reference = evaluate(&entrants[0].pilot, None, &c.eval, true);
    assert_eq!(max_deviation(&outcome.episodes, &reference), 0.0);
}

/// Issue "faults": a state forged for the step the controller expects next (on an
/// unsigned link, from anyone who can send from the simulator's address) is taken, and the
/// controller answers it early; the real request for that step is then answered again from
/// its cache, and the simulator takes whichever copy comes after its request. The forgery costs
/// exactly that one step's command (the flights agree before it and part after it) and the
/// race goes on; before retransmission the controller was declared failed.
#[test]
fn a_forged_state_costs_the_one_step_it_forged() {
    let state = sitl::frames::NedState {
        position_m: firmware_core::math::Vec3::new(0.0, 0.0, -1.0),
        velocity_mps: Default::default(),
        attitude: firmware_core::math::Quat::IDENTITY,
        body_rates_radps: Default::default(),
    };
    let mut forged = Vec::new();
    let mut forger = Codec::new(sitl::bridge::SIM_COMPONENT_ID, None, 0);
    // Datagram 1 starts the first flight, datagram n >= 2 is the step at (n - 2) * 20 ms:
    // right after datagram 101 (step 99) comes a state for step 100, t = 2,000 ms.
    for m in sitl::bridge::state_messages(2_000, &state) {
        forger.encode(1, &m, &mut forged);
    }
    let ego = fc_thread(&student(), 1, None);
    let injector = Injector::new(ego, 101, forged);
    let entrants = [entrant("ego", &student(), 1)];
    let c = config(1, 5.0);
    let outcome = race(&entrants, &Transport::Attach(vec![injector.addr]), &c).expect("race runs");
    let ctl = &outcome.controllers[0];
    assert!(ctl.failure.is_none(), "{}", outcome.summary());
    // The forged step's answer came twice (early, and again from the cache): one copy was
    // surplus, dropped as future (it came before the request) or stale (after).
    assert_eq!(ctl.link.future + ctl.link.stale, 1, "{:?}", ctl.link);
    let reference = evaluate(&entrants[0].pilot, None, &c.eval, true);
    let (flown, nominal) = (&outcome.episodes[0].trace.ego_m, &reference[0].trace.ego_m);
    assert_eq!(flown[..100], nominal[..100], "the steps before the forgery");
    assert_ne!(
        flown[100], nominal[100],
        "step 100 flew the forged state's command"
    );
}

#[test]
fn signed_links_work_and_bad_or_missing_signatures_are_rejected() {
    let key = signing_key("overtake-sitl").unwrap();
    let entrants = [entrant("ego", &student(), 1)];
    let mut c = config(1, 5.0);
    c.signing_key = Some(key);
    let ok = race(&entrants, &Transport::Threads, &c).expect("race runs");
    assert_clean(&ok);

    c.step_timeout = Duration::from_millis(200);
    c.startup_timeout = Duration::from_millis(500);
    // A controller with another key: it drops everything, so it never answers.
    let wrong = fc_thread(&student(), 1, Some(signing_key("another key").unwrap()));
    let o = race(&entrants, &Transport::Attach(vec![wrong]), &c).expect("race runs");
    assert!(o.controllers[0].failure.is_some());
    // A controller that does not sign: the simulator drops its answers.
    let unsigned = fc_thread(&student(), 1, None);
    let o = race(&entrants, &Transport::Attach(vec![unsigned]), &c).expect("race runs");
    let l = &o.controllers[0].link;
    assert!(l.unsigned > 0, "{l:?}");
    assert!(o.controllers[0].failure.is_some());
}

#[test]
fn a_controller_that_does_not_start_is_a_clear_error() {
    let entrants = [entrant("ego", &student(), 1)];
    let c = config(1, 1.0);
    let err = race(
        &entrants,
        &Transport::Processes("/nonexistent/sitl".into()),
        &c,
    )
    .unwrap_err();
    assert!(err.to_string().contains("cannot start"), "{err}");
}
