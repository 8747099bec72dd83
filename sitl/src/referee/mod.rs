//! The referee: scores evaluation episodes per docs/DESIGN.md "Metrics".
//!
//! An episode is 45 s of simulated flight. Drone 0 is the ego, drone 1 (in a race) the
//! opponent. After a crash the race restarts from a fresh spawn and the clock runs on; in a
//! race any crash (the ego's, the opponent's, or their collision) restarts both drones, the
//! paper's "episode reset". The referee counts, for the ego:
//! - gates passed, and gates encountered (passed, or the target at a crash);
//! - crash resets, and the opponent's crash resets separately;
//! - lap times: g0 → g0 with no crash inside, timed at control-step resolution (20 ms);
//! - overtakes: the ego's progress along the track (laps·length + arc length of the nearest
//!   point of the centreline segment it is flying) goes from behind the opponent's to ahead;
//!   an overtake is sustained once the ego has kept that lead for 2 s without a crash. An
//!   overtake whose lead is lost, ended by a reset, or still under 2 s old when the episode
//!   ends is not sustained;
//! - flights won (races only): a flight is the span between (re)spawns, the last one ending
//!   with the episode. The ego wins a flight that the opponent's crash alone ends, or that
//!   ends ahead along the track either at the episode's end or with both drones crashing on
//!   the same step (their collision: as in racing, the drone behind answers for running into
//!   the one ahead); dead level is a tie (half a win); anything else is a loss. The win rate
//!   is (won + tied / 2) / flights, so the ego's and the opponent's rates sum to 1 and two
//!   equal pilots from symmetric starts would score 0.5 each.
//!
//! Gate passes and crashes come from [`World::judge`], i.e. firmware-core's gate test and
//! crash rules; progress comes from firmware-core's [`Centerline`] and [`ArcLength`].

use crate::dynamics::Preset;
use crate::frames::NedState;
use crate::perturb::{EpisodePerturbation, Perturbation};
use crate::pilot::Pilot;
use crate::world::{CrashCause, Drone, DroneStep, SpawnPoint, World};
use firmware_core::math::Vec3;
use firmware_core::track::{ArcLength, Centerline, Track};
use firmware_core::vehicle::{MotorCommand, VehicleState};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod trace;
pub use trace::{OvertakeMark, TRACES_FORMAT, Trace, TraceEvent, TraceEventKind};

/// Seconds an overtaking ego must keep its lead for the overtake to be sustained.
pub const SUSTAINED_LEAD_S: f32 = 2.0;

/// Length of an evaluation episode in the paper (s).
pub const EPISODE_SECONDS: f32 = 45.0;

/// What one episode measured, for the ego.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EpisodeMetrics {
    /// Simulated time (s).
    pub sim_seconds: f32,
    /// Gates the ego passed.
    pub gates_passed: u32,
    /// Gates passed plus gates that were the ego's target when it crashed.
    pub gates_encountered: u32,
    /// The ego's crash resets.
    pub crashes: u32,
    /// The opponent's crash resets (races only).
    pub opponent_crashes: u32,
    /// Complete laps g0 → g0 without a crash inside (s, at control-step resolution), in
    /// order.
    pub lap_times_s: Vec<f64>,
    /// Times the ego went from behind to ahead of the opponent.
    pub overtakes: u32,
    /// Overtakes whose lead the ego then held for [`SUSTAINED_LEAD_S`] without a crash.
    pub sustained_overtakes: u32,
    /// The ego's crashes by cause.
    pub crash_causes: CrashCounts,
    /// Flights of a race: the spans between (re)spawns, the last ending with the episode (0
    /// in a time trial).
    pub flights: u32,
    /// Flights the ego won: ended by the opponent's crash alone, or ahead along the track at
    /// the episode's end or when both crashed on the same step.
    pub flights_won: u32,
    /// Flights that ended level (both crashing, or at the episode's end).
    pub flights_tied: u32,
    /// Where the overtakes happened: entry `g` counts `[overtakes, sustained]` taken while
    /// the ego flew towards gate `g` (as long as the highest such gate needs; empty without
    /// an overtake).
    pub overtakes_by_gate: Vec<[u32; 2]>,
}

/// Crashes counted by cause.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CrashCounts {
    /// Crossed the target gate's plane outside the opening.
    pub gate_frame: u32,
    /// Below 0.1 m.
    pub ground: u32,
    /// Too far from the target gate.
    pub out_of_bounds: u32,
    /// Closer than 0.2 m to the other drone.
    pub collision: u32,
    /// Diverged (not finite).
    pub non_finite: u32,
}

impl CrashCounts {
    /// Counts one crash of cause `cause`.
    pub fn add(&mut self, cause: CrashCause) {
        let slot = match cause {
            CrashCause::GateFrame { .. } => &mut self.gate_frame,
            CrashCause::Ground => &mut self.ground,
            CrashCause::OutOfBounds => &mut self.out_of_bounds,
            CrashCause::Collision { .. } => &mut self.collision,
            CrashCause::NonFinite => &mut self.non_finite,
        };
        *slot += 1;
    }

    /// The sum of two counts.
    pub fn plus(self, o: Self) -> Self {
        Self {
            gate_frame: self.gate_frame + o.gate_frame,
            ground: self.ground + o.ground,
            out_of_bounds: self.out_of_bounds + o.out_of_bounds,
            collision: self.collision + o.collision,
            non_finite: self.non_finite + o.non_finite,
        }
    }
}

impl EpisodeMetrics {
    /// Gates passed / gates encountered; 0 when the ego met no gate at all (it never reached
    /// one in the whole episode, which is not a success).
    pub fn success_rate(&self) -> f64 {
        if self.gates_encountered == 0 {
            0.0
        } else {
            f64::from(self.gates_passed) / f64::from(self.gates_encountered)
        }
    }

    /// Crash resets per second of simulated time.
    pub fn crash_rate_per_s(&self) -> f64 {
        if self.sim_seconds > 0.0 {
            f64::from(self.crashes) / f64::from(self.sim_seconds)
        } else {
            0.0
        }
    }

    /// The fastest lap (s), `None` for a DNF.
    pub fn best_lap_s(&self) -> Option<f64> {
        self.lap_times_s.iter().copied().reduce(f64::min)
    }

    /// (flights won + tied / 2) / flights; `None` in a time trial.
    pub fn win_rate(&self) -> Option<f64> {
        (self.flights > 0).then(|| {
            (f64::from(self.flights_won) + 0.5 * f64::from(self.flights_tied))
                / f64::from(self.flights)
        })
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Lead {
    Behind,
    /// Ahead since `since_s`, the lead taken while flying towards `gate` (`None`: at a
    /// spawn, not an overtake).
    Ahead {
        since_s: f32,
        sustained: bool,
        gate: Option<usize>,
    },
}

/// Progress along the track's centreline (m), counted on across laps: what the referee
/// measures leads and overtakes with (and the training env's `lead` competition reward).
#[derive(Clone, Debug)]
pub struct TrackProgress {
    line: Centerline,
    arc: ArcLength,
    segments: u64,
}

impl TrackProgress {
    /// The measure for `track`.
    pub fn new(track: &Track<'_>) -> Self {
        let line = Centerline::new(track);
        Self {
            arc: ArcLength::new(&line),
            segments: line.segments().max(1) as u64,
            line,
        }
    }

    /// The centreline progress is measured along.
    pub fn line(&self) -> &Centerline {
        &self.line
    }

    /// The absolute index of the centreline segment a drone (re)spawned towards
    /// `target_gate` flies: the segment that ends at its target, offset by a lap so it never
    /// goes below 0.
    pub fn spawn_segment(&self, target_gate: usize) -> u64 {
        target_gate as u64 + self.segments - 1
    }

    /// Progress (m) of a drone at `position_m` that spawned on `spawn_segment` and has passed
    /// `gates_passed` gates since: laps·length + the arc length of its nearest point on the
    /// segment it flies.
    pub fn progress_m(&self, spawn_segment: u64, gates_passed: u32, position_m: Vec3) -> f32 {
        let seg = spawn_segment + u64::from(gates_passed);
        let k = (seg % self.segments) as usize;
        let s = self.line.nearest_on_segment(k, position_m);
        let laps = (seg / self.segments) as f32;
        laps * self.arc.length_m() + self.arc.along_segment(k, s - k as f32)
    }
}

/// The referee's bookkeeping for one episode. Feed it every step with [`Referee::score`];
/// call [`Referee::restart`] after every (re)spawn.
#[derive(Clone, Debug)]
pub struct Referee {
    progress: TrackProgress,
    dt_s: f32,
    steps: u32,
    metrics: EpisodeMetrics,
    lap_start_step: Option<u32>,
    /// Absolute index of the centreline segment each drone flew at its last (re)spawn (the
    /// segment ending at its target, offset by a lap); adding the gates it has passed since
    /// gives the segment it flies now, counted on across laps.
    spawn_segment: [u64; 2],
    lead: Lead,
    /// Steps scored since the last (re)spawn.
    flight_steps: u32,
    /// The ego's lead after the last step scored without a reset (m); `None` without an
    /// opponent.
    last_lead_m: Option<f32>,
}

impl Referee {
    /// A referee for `track` at control period `dt_s` (s).
    pub fn new(track: &Track<'_>, dt_s: f32) -> Self {
        Self {
            progress: TrackProgress::new(track),
            dt_s,
            steps: 0,
            metrics: EpisodeMetrics::default(),
            lap_start_step: None,
            spawn_segment: [0; 2],
            lead: Lead::Behind,
            flight_steps: 0,
            last_lead_m: None,
        }
    }

    /// The racing line progress is measured on.
    pub fn centerline(&self) -> &Centerline {
        self.progress.line()
    }

    /// Elapsed simulated time (s).
    pub fn time_s(&self) -> f32 {
        self.steps as f32 * self.dt_s
    }

    /// The drones were just (re)spawned (no gate passed yet): progress restarts from their
    /// targets, the lap timer stops, and the lead is taken as it stands (a spawn is not an
    /// overtake).
    pub fn restart(&mut self, drones: &[Drone]) {
        for (seg, d) in self.spawn_segment.iter_mut().zip(drones) {
            *seg = self.progress.spawn_segment(d.progress.target);
        }
        self.lap_start_step = None;
        self.flight_steps = 0;
        self.last_lead_m = self.lead_m(drones);
        self.lead = match self.lead_m(drones) {
            Some(l) if l > 0.0 => Lead::Ahead {
                since_s: self.time_s(),
                sustained: true,
                gate: None,
            },
            _ => Lead::Behind,
        };
    }

    /// Progress of drone `i` along the track (m): laps·length + arc length of the nearest
    /// point of the centreline segment it flies.
    pub fn progress_m(&self, drones: &[Drone], i: usize) -> Option<f32> {
        let d = drones.get(i)?;
        Some(self.progress.progress_m(
            *self.spawn_segment.get(i)?,
            d.progress.gates_passed,
            d.position_m(),
        ))
    }

    /// The ego's lead over the opponent (m); `None` without an opponent.
    pub fn lead_m(&self, drones: &[Drone]) -> Option<f32> {
        Some(self.progress_m(drones, 0)? - self.progress_m(drones, 1)?)
    }

    /// Scores one step (after [`World::step`] or [`World::judge`]): returns true when a
    /// crash ends this run and the caller must respawn the drones and call
    /// [`Referee::restart`].
    pub fn score(&mut self, drones: &[Drone], steps: &[DroneStep]) -> bool {
        self.steps += 1;
        self.flight_steps += 1;
        let t = self.time_s();
        let ego = steps.first().copied().unwrap_or_default();
        let opponent = steps.get(1).copied();
        if let Some(cause) = ego.crash {
            self.metrics.crash_causes.add(cause);
            self.metrics.crashes += 1;
            self.metrics.gates_encountered += 1;
        } else if let Some(gate) = ego.passed_gate() {
            self.metrics.gates_passed += 1;
            self.metrics.gates_encountered += 1;
            if gate == 0 {
                if let Some(k0) = self.lap_start_step {
                    self.metrics
                        .lap_times_s
                        .push(f64::from(self.steps - k0) * f64::from(self.dt_s));
                }
                self.lap_start_step = Some(self.steps);
            }
        }
        if opponent.is_some_and(|o| o.crash.is_some()) {
            self.metrics.opponent_crashes += 1;
        }
        let opponent_crashed = opponent.is_some_and(|o| o.crash.is_some());
        let reset = ego.crash.is_some() || opponent_crashed;
        if reset {
            // This flight is over: the episode's end does not count it again.
            self.flight_steps = 0;
            if opponent.is_some() {
                self.metrics.flights += 1;
                match (ego.crash.is_some(), opponent_crashed) {
                    (true, true) => self.judge_flight(self.lead_m(drones)),
                    (false, true) => self.metrics.flights_won += 1,
                    _ => {}
                }
            }
            self.lead = Lead::Behind;
            return true;
        }
        self.last_lead_m = self.lead_m(drones);
        if let Some(lead) = self.last_lead_m {
            self.lead = match self.lead {
                Lead::Behind if lead > 0.0 => {
                    self.metrics.overtakes += 1;
                    let gate = drones.first().map(|d| d.progress.target);
                    self.count_at_gate(gate, 0);
                    Lead::Ahead {
                        since_s: t,
                        sustained: false,
                        gate,
                    }
                }
                Lead::Ahead { .. } if lead <= 0.0 => Lead::Behind,
                Lead::Ahead {
                    since_s,
                    sustained: false,
                    gate,
                } if t - since_s >= SUSTAINED_LEAD_S - 0.5 * self.dt_s => {
                    self.metrics.sustained_overtakes += 1;
                    self.count_at_gate(gate, 1);
                    Lead::Ahead {
                        since_s,
                        sustained: true,
                        gate,
                    }
                }
                other => other,
            };
        }
        false
    }

    /// The episode's metrics so far.
    pub fn metrics(&self) -> &EpisodeMetrics {
        &self.metrics
    }

    /// Ends the episode (and its last flight, if a step was scored since the last spawn).
    pub fn finish(mut self) -> EpisodeMetrics {
        self.metrics.sim_seconds = self.time_s();
        if let (Some(lead), true) = (self.last_lead_m, self.flight_steps > 0) {
            self.metrics.flights += 1;
            self.judge_flight(Some(lead));
        }
        self.metrics
    }

    /// Counts an overtake (`column` 0) or its being sustained (1) at `gate`.
    fn count_at_gate(&mut self, gate: Option<usize>, column: usize) {
        let Some(g) = gate else { return };
        let by_gate = &mut self.metrics.overtakes_by_gate;
        if by_gate.len() <= g {
            by_gate.resize(g + 1, [0; 2]);
        }
        if let Some(n) = by_gate.get_mut(g).and_then(|c| c.get_mut(column)) {
            *n += 1;
        }
    }

    /// A flight that ended with both drones in the air or both crashed: the one ahead along
    /// the track wins it, level is a tie.
    fn judge_flight(&mut self, lead_m: Option<f32>) {
        match lead_m {
            Some(l) if l > 0.0 => self.metrics.flights_won += 1,
            Some(0.0) => self.metrics.flights_tied += 1,
            _ => {}
        }
    }
}

/// Where drones start (and restart after a crash). Configs and flags write it `stage1`,
/// `stage2` or `along-track`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SpawnMode {
    /// The paper's fixed stage-1 spawn, (−1, −1, 1) targeting g0 (time trials).
    Stage1,
    /// The paper's stage-2 spawn before a random gate (races; the ego alone uses the ego's
    /// place in a time trial).
    Stage2,
    /// A random point of the centreline, at rest (time trials).
    AlongTrack,
}

impl core::str::FromStr for SpawnMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::by_name(s).ok_or_else(|| format!("unknown spawn '{s}' (stage1, stage2, along-track)"))
    }
}

impl SpawnMode {
    /// The mode called `name` ("stage1", "stage2", "along-track").
    pub fn by_name(name: &str) -> Option<Self> {
        match name {
            "stage1" => Some(Self::Stage1),
            "stage2" => Some(Self::Stage2),
            "along-track" => Some(Self::AlongTrack),
            _ => None,
        }
    }

    /// The mode's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Stage1 => "stage1",
            Self::Stage2 => "stage2",
            Self::AlongTrack => "along-track",
        }
    }

    /// Spawn points `[ego, opponent]` drawn from `rng` (the opponent's is unused alone).
    pub fn draw(self, track: &Track<'_>, line: &Centerline, rng: &mut impl Rng) -> [SpawnPoint; 2] {
        match self {
            Self::Stage1 => {
                let s = crate::world::stage1_spawn();
                [s, s]
            }
            Self::Stage2 => {
                crate::world::stage2_spawn(track, rng.random_range(0..track.len().max(1)))
            }
            Self::AlongTrack => {
                let s = crate::world::along_track_spawn(
                    line,
                    rng.random_range(0.0..line.segments().max(1) as f32),
                );
                [s, s]
            }
        }
    }
}

/// How to run one episode.
#[derive(Clone, Copy, Debug)]
pub struct EpisodeConfig {
    /// Simulated seconds. Paper: 45.
    pub seconds: f32,
    /// Where drones start and restart.
    pub spawn: SpawnMode,
    /// Seed of the spawn draws (and, on streams of their own, the perturbation's).
    pub seed: u64,
    /// What perturbs the flights ([`Perturbation::NONE`]: the nominal flight).
    pub perturbation: Perturbation,
}

impl EpisodeConfig {
    /// A time trial of `seconds` from the paper's fixed stage-1 spawn.
    pub fn time_trial(seconds: f32) -> Self {
        Self {
            seconds,
            spawn: SpawnMode::Stage1,
            seed: 0,
            perturbation: Perturbation::NONE,
        }
    }
}

/// One scored episode: the metrics and, when asked for, the trace.
#[derive(Clone, Debug, Default)]
pub struct Episode {
    /// The ego's metrics.
    pub metrics: EpisodeMetrics,
    /// Positions over time (empty unless recorded).
    pub trace: Trace,
}

/// The random generator of episode `index` of an evaluation seeded `seed`: independent
/// streams, the same on every machine and thread count.
pub fn episode_rng(seed: u64, index: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(index);
    rng
}

/// Who commands the drones of an episode, all of them each step: in-process pilots
/// ([`run_episode`]), or controllers behind the MAVLink bridge (`bridge::race`).
pub trait Crew<const N: usize> {
    /// New flights from spawns: drone `i` targets gate `targets[i]`.
    fn reset(&mut self, targets: [usize; N]);
    /// The motor commands for the drones' states at the start of a step.
    fn commands(&mut self, states: &[VehicleState; N]) -> [MotorCommand; N];
}

/// In-process pilots as a crew: each sees its own state and, in a race, the other drone's,
/// as a flight controller receives them over the MAVLink bridge: in f32 NED/FRD and back
/// ([`crate::frames`]; the attitude moves by at most 1e-7). So `sitl eval` and a
/// lockstep race over MAVLink (`sitl race`) fly identical trajectories.
struct Pilots<'a, const N: usize>([&'a mut dyn Pilot; N]);

impl<const N: usize> Crew<N> for Pilots<'_, N> {
    fn reset(&mut self, targets: [usize; N]) {
        for (p, t) in self.0.iter_mut().zip(targets) {
            p.reset(t);
        }
    }

    fn commands(&mut self, states: &[VehicleState; N]) -> [MotorCommand; N] {
        let received = states.map(|s| NedState::from_enu(&s).to_enu());
        core::array::from_fn(|i| {
            let other = if N == 2 { received.get(1 - i) } else { None };
            self.0[i].command(&received[i], other)
        })
    }
}

/// Flies one episode: `ego` alone (a time trial) or against `opponent` (a race), scored by the
/// referee. With `record`, the trace of positions is kept.
pub fn run_episode(
    world: &World,
    ego: &mut dyn Pilot,
    opponent: Option<&mut dyn Pilot>,
    config: &EpisodeConfig,
    index: u64,
    record: bool,
) -> Episode {
    match opponent {
        None => run_crew(world, &mut Pilots([ego]), config, index, record),
        Some(o) => run_crew(world, &mut Pilots([ego, o]), config, index, record),
    }
}

/// Flies episode `index` of `config` with `crew` commanding the drones (drone 0 is the ego),
/// scored by the referee: the same spawns, steps and scoring whoever flies.
pub fn run_crew<const N: usize>(
    world: &World,
    crew: &mut dyn Crew<N>,
    config: &EpisodeConfig,
    index: u64,
    record: bool,
) -> Episode {
    let rng = &mut episode_rng(config.seed, index);
    let perturbed = &mut config
        .perturbation
        .episode(&world.preset, config.seed, index);
    let airframes: [Preset; N] = core::array::from_fn(|i| {
        if i == 0 {
            perturbed.ego_preset
        } else {
            world.preset
        }
    });
    let mut referee = Referee::new(&world.track, world.dt_s);
    let line = *referee.centerline();
    let mut trace = Trace {
        dt_s: world.dt_s,
        ..Trace::default()
    };
    let spawn = |crew: &mut dyn Crew<N>, rng: &mut ChaCha8Rng, p: &mut EpisodePerturbation| {
        let points = config.spawn.draw(&world.track, &line, rng);
        let drones: [Drone; N] = core::array::from_fn(|i| {
            let mut point = points.get(i).copied().unwrap_or(points[0]);
            point.state = p.spawn(point.state);
            Drone::spawned(point)
        });
        p.restart();
        crew.reset(core::array::from_fn(|i| drones[i].progress.target));
        drones
    };
    let mut drones = spawn(crew, rng, perturbed);
    referee.restart(&drones);
    let steps = (config.seconds / world.dt_s).round() as u32;
    for k in 0..steps {
        let mut states: [VehicleState; N] = core::array::from_fn(|i| drones[i].body.state);
        if let Some(ego) = states.first_mut() {
            *ego = perturbed.sense(*ego);
        }
        let mut commands = crew.commands(&states);
        if let Some(ego) = commands.first_mut() {
            *ego = perturbed.deliver(*ego);
        }
        let results = world.step_airframes(&mut drones, &commands, &airframes);
        if record {
            trace.record_states(&drones);
            trace.record_events(k + 1, &results);
            if N == 2 {
                trace.lead_m.push(referee.lead_m(&drones));
            }
        }
        let (overtakes, sustained) = {
            let m = referee.metrics();
            (m.overtakes, m.sustained_overtakes)
        };
        let reset = referee.score(&drones, &results);
        if record {
            let m = referee.metrics();
            if m.overtakes > overtakes {
                trace.overtakes.push(OvertakeMark {
                    step: k + 1,
                    sustained: false,
                });
            }
            if m.sustained_overtakes > sustained {
                if let Some(last) = trace.overtakes.last_mut() {
                    last.sustained = true;
                }
            }
        }
        if reset {
            drones = spawn(crew, rng, perturbed);
            referee.restart(&drones);
            if record {
                trace.respawns.push(k + 1);
            }
        }
    }
    Episode {
        metrics: referee.finish(),
        trace,
    }
}
