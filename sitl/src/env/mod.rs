//! The vectorised environments every learner steps (host-trainer's PPO, or Python through
//! a binding): many independent worlds stepped in parallel with rayon, rewards per
//! docs/DESIGN.md "Rewards" with every term kept apart for the logs, and observations built
//! only by firmware-core's pipeline (the one the controller runs). Nothing here knows of a
//! learning library.
//!
//! Stage 1 (time trial): one drone per world. Each env auto-resets: after a crash or a
//! time-out its slot is respawned and the observation returned is the new episode's first.
//!
//! Stage 2 (race, [`EnvConfig::race`]): the ego and an opponent in one world, spawned as the paper's
//! stage 2 (a random gate k, the opponent 1 m and the ego 2 m before it, at rest). The
//! opponent is a frozen blob flown by firmware-core's [`Controller`], the code a flight
//! controller runs, deterministically (its Gaussian mean). Blind to the ego and spawned at one
//! of a few places, a feed-forward opponent flies the same flight from each place in every
//! episode: it is recorded once and replayed, bit for bit the live flight (`env::flight`;
//! [`VecEnv::fly_opponents_live`] flies it live instead). An episode ends as a race restarts
//! in the referee: on any crash. The ego's crash (a collision included) is a terminal step
//! with the crash penalty; the opponent crashing alone is a truncation (`timeouts`, so it is
//! bootstrapped with γ·V): the ego did nothing wrong and its future was cut short.
//!
//! **The reward** of a step, term by term, is [`reward`]'s (docs/DESIGN.md "Rewards").

use crate::mirror::{Mirror, NoMirror};
use crate::perturb::EpisodePerturbation;
use crate::referee::{SpawnMode, TrackProgress};
use crate::world::{Drone, World};
use firmware_core::Controller;
use firmware_core::baseline::BaselineController;

use firmware_core::mirror::{TrackMirror, unfold_action};
use firmware_core::nn::{ACTION_DIM, LANES};
use firmware_core::observation::ObservationSpec;
use firmware_core::policy::Policy;
use firmware_core::track::CrashRules;
use firmware_core::vehicle::{ActionMap, MotorCommand};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

mod config;
mod error;
mod flight;
mod observe;
mod opponent;
pub mod reward;
pub mod snapshot;
mod spawn;
mod stats;

pub use crate::dynamics::PresetName;
pub use config::{
    EnvConfig, EnvConfigError, MAX_ENVS, MAX_SPAWN_SPEED_MPS, PAPER_VELOCITY_SCALE_MPS, RaceConfig,
    Task,
};
pub use error::{ActionShapeError, EnvError, EpisodeStepsError};
use flight::{FlightBook, FlightStep};
pub use observe::PRIVILEGED_EXTRA;
use observe::{ego_observation, observe, observe_drones, privileged};
use opponent::Race;
pub use opponent::{MAX_BLOB_BYTES, interned, read_blob};
pub use reward::{Competition, RewardTerms, RewardWeights, dense_competition};
use reward::{Rewards, StepOutcome};
pub use snapshot::{ENV_SNAPSHOT_FORMAT, EnvSnapshot};
use spawn::{PassReplay, SpawnRule, respawn};
pub use stats::{EnvStats, StepRecord};

/// Mixed into the seed of the randomisation generators (`Slot::perturb_rng`).
const PERTURB_SEED_KEY: u64 = 0x7261_6e64_6f6d_697a; // "randomiz"

/// Envs per rayon task.
const CHUNK: usize = 128;

#[derive(Clone, Debug)]
struct Slot {
    /// The ego, then the opponent (stage 2 only; unused in a time trial).
    drones: [Drone; 2],
    /// The opponent's controller (stage 2).
    opponent: Option<Controller<'static>>,
    previous_action: [f32; ACTION_DIM],
    steps: u32,
    /// Each drone's centreline segment at its last spawn (for the `lead` reward).
    spawn_segment: [u64; 2],
    rng: ChaCha8Rng,
    /// The generator of the ego's randomisation draws (`EnvConfig::randomize`), apart from
    /// `rng`: randomising never moves where or when an env spawns.
    perturb_rng: ChaCha8Rng,
    stats: EnvStats,
    /// The ego's states after its last gate passes (for `replay_fraction`).
    passes: PassReplay,
    /// The ego's randomised airframe, latency and sensor noise this episode
    /// (`EnvConfig::randomize`).
    perturbed: Option<EpisodePerturbation>,
    /// Stage 2: the opponent's spawn place and the steps it has flown since, set at every
    /// race spawn and kept while its recorded flight is replayed (`flight`); `None` once its
    /// controller flies it live (no recording, or past it, or restored from a snapshot).
    replay: Option<(usize, u32)>,
}

/// Many stage-1 or stage-2 worlds with their observations, rewards and episode ends.
#[derive(Clone, Debug)]
pub struct VecEnv {
    world: World,
    progress: TrackProgress,
    spec: ObservationSpec,
    obs_dim: usize,
    map: ActionMap,
    config: EnvConfig,
    race: Option<Race>,
    /// Stage 2 with a feed-forward opponent: its recorded flights (`flight`).
    flights: Option<std::sync::Arc<FlightBook>>,
    max_steps: u32,
    slots: Vec<Slot>,
    observations: Vec<f32>,
    rewards: Vec<f32>,
    dones: Vec<bool>,
    timeouts: Vec<bool>,
    records: Vec<StepRecord>,
    /// Rows of the envs that were done in the last step: the observation of the state the
    /// episode ended in, before the respawn (other rows are stale).
    final_observations: Vec<f32>,
    /// The track's mirror symmetry, when it has one ([`VecEnv::mirrored_observations`]).
    mirror: Result<Mirror, NoMirror>,
    /// The mirror the observations are folded by, when the spec is folded: the mirrored
    /// half's steps are observed as their images, and their actions renumbered back.
    fold: Option<TrackMirror>,
}

/// Observation size of stage 1.
pub const OBS_DIM: usize = 17;

impl VecEnv {
    /// `config.num_envs` stage-1 envs, each spawned (at a random point of its first episode
    /// when `random_initial_episode_length`); `config.race` is dropped. For tests and
    /// benches, whose configs are written in code.
    ///
    /// # Panics
    /// When `config` does not validate ([`EnvConfig::validate`]).
    pub fn time_trial(config: EnvConfig) -> Self {
        let config = EnvConfig {
            race: None,
            ..config
        };
        match Self::new(config) {
            Ok(env) => env,
            Err(e) => panic!("VecEnv::time_trial: {e}"),
        }
    }

    /// `config.num_envs` envs of a time trial or, with `config.race`, of a race. A config
    /// that does not validate, an opponent blob that cannot be read or does not validate,
    /// or whose policy would need to see an opponent itself, is refused here.
    pub fn new(config: EnvConfig) -> Result<Self, EnvError> {
        config.validate()?;
        let rules = if config.race.is_some() {
            CrashRules::STAGE2
        } else {
            CrashRules::STAGE1
        };
        let world = World::figure_eight(config.preset(), rules);
        let race = config.race.as_ref().map(Race::load).transpose()?;
        let progress = TrackProgress::new(&world.track);
        let max_steps = ((config.episode_s / world.dt_s).round() as u32).max(1);
        let n = config.num_envs;
        let spec = config.observation_spec();
        let obs_dim = spec.dim();
        let mirror = Mirror::of_track(&world.track);
        let fold = match (&mirror, spec.is_folded()) {
            (_, false) => None,
            (Ok(m), true) => Some(*m.track_mirror()),
            (Err(e), true) => {
                return Err(EnvError::Unflyable(format!(
                    "the observation is folded by the track's mirror, but the track has {e}"
                )));
            }
        };
        let flights = race
            .as_ref()
            .and_then(|r| flight_book(r, &world, max_steps));
        let mut env = Self {
            world,
            progress,
            spec,
            obs_dim,
            map: ActionMap::PAPER,
            flights,
            race,
            max_steps,
            slots: Vec::with_capacity(n),
            observations: vec![0.0; n * obs_dim],
            rewards: vec![0.0; n],
            dones: vec![false; n],
            timeouts: vec![false; n],
            records: vec![StepRecord::default(); n],
            final_observations: vec![0.0; n * obs_dim],
            mirror,
            fold,
            config,
        };
        for i in 0..n {
            let mut rng = ChaCha8Rng::seed_from_u64(env.config.seed);
            rng.set_stream(i as u64);
            let steps = if env.config.random_initial_episode_length {
                rng.random_range(0..max_steps)
            } else {
                0
            };
            let mut slot = Slot {
                drones: [Drone::default(); 2],
                opponent: env.race.as_ref().map(|r| r.opponent.clone()),
                previous_action: [0.0; ACTION_DIM],
                steps: 0,
                spawn_segment: [0; 2],
                rng,
                perturb_rng: {
                    let mut r = ChaCha8Rng::seed_from_u64(env.config.seed ^ PERTURB_SEED_KEY);
                    r.set_stream(i as u64);
                    r
                },
                stats: EnvStats::default(),
                passes: PassReplay::default(),
                perturbed: None,
                replay: None,
            };
            respawn(
                &env.world,
                &env.progress,
                &env.map,
                &env.spawn_rule(),
                &mut slot,
            );
            slot.steps = steps;
            env.slots.push(slot);
        }
        env.observe_all();
        Ok(env)
    }

    /// Every env's observation from its current state.
    fn observe_all(&mut self) {
        for (slot, obs) in self
            .slots
            .iter_mut()
            .zip(self.observations.chunks_exact_mut(self.obs_dim))
        {
            observe(&self.world, &self.spec, self.fold.as_ref(), slot, obs);
        }
    }

    fn spawn_rule(&self) -> SpawnRule {
        SpawnRule {
            mode: if self.race.is_some() {
                SpawnMode::Stage2
            } else {
                self.config.spawn
            },
            max_speed_mps: self.config.spawn_speed_mps,
            stage1_fraction: self.config.stage1_fraction,
            stage2_fraction: self.config.stage2_fraction,
            replay_fraction: self.config.replay_fraction,
            race: self.race.is_some(),
            ego_ahead_fraction: self
                .config
                .race
                .as_ref()
                .map_or(0.0, |r| r.ego_ahead_fraction),
            randomize: self.config.randomize.as_ref().map(|p| *p.value()),
            randomize_share: self.config.randomize_share,
            jitter: self.config.spawn_jitter.as_ref().map(|j| *j.value()),
        }
    }

    /// Values per observation (17, 20 or 30: the observation spec's layout).
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Number of envs.
    pub fn num_envs(&self) -> usize {
        self.slots.len()
    }

    /// Simulated seconds of one step (the control period).
    pub fn dt_s(&self) -> f32 {
        self.world.dt_s
    }

    /// Env-steps per episode before a time-out.
    pub fn max_episode_steps(&self) -> u32 {
        self.max_steps
    }

    /// Steps each env's current episode has run (`num_envs` values; an episode times out
    /// when its count reaches [`VecEnv::max_episode_steps`]).
    pub fn episode_steps(&self) -> Vec<u32> {
        self.slots.iter().map(|s| s.steps).collect()
    }

    /// Sets how many steps each env's current episode has run, as RSL-RL's runner does to
    /// spread time-outs (`init_at_random_ep_len`): an env set to `max_episode_steps() - 1`
    /// times out at its next step, one set at or beyond the limit too. Nothing else about
    /// the episodes changes. A slice of the wrong length is refused and nothing changes.
    pub fn set_episode_steps(&mut self, steps: &[u32]) -> Result<(), EpisodeStepsError> {
        if steps.len() != self.slots.len() {
            return Err(EpisodeStepsError {
                expected: self.slots.len(),
                got: steps.len(),
            });
        }
        for (slot, &s) in self.slots.iter_mut().zip(steps) {
            slot.steps = s;
        }
        Ok(())
    }

    /// The reward's weights of the steps to come.
    pub fn reward_weights(&self) -> RewardWeights {
        self.config.reward
    }

    /// Changes the reward's weights from the next step on (a trainer's reward schedule); the
    /// worlds, episodes and observations are left as they are.
    pub fn set_reward_weights(&mut self, weights: RewardWeights) {
        self.config.reward = weights;
    }

    /// Changes the share of spawns whose ego is randomised (`EnvConfig::randomize_share`)
    /// from the next spawn on (a trainer's ramp); the episodes in flight keep their draws.
    pub fn set_randomize_share(&mut self, share: f32) -> Result<(), EnvError> {
        let changed = EnvConfig {
            randomize_share: share,
            ..self.config.clone()
        };
        changed.validate().map_err(EnvError::Config)?;
        self.config = changed;
        Ok(())
    }

    /// The observation spec every observation follows (recorded in exported blobs).
    pub fn observation_spec(&self) -> ObservationSpec {
        self.spec
    }

    /// Current observations, `num_envs × obs_dim`, row-major.
    pub fn observations(&self) -> &[f32] {
        &self.observations
    }

    /// Rewards of the last step.
    pub fn rewards(&self) -> &[f32] {
        &self.rewards
    }

    /// Whether each env's episode ended in the last step (crash or time-out); its
    /// observation is already the next episode's first.
    pub fn dones(&self) -> &[bool] {
        &self.dones
    }

    /// Whether each episode end of the last step was a time-out (to bootstrap with γ·V).
    pub fn timeouts(&self) -> &[bool] {
        &self.timeouts
    }

    /// Each env's last step, term by term and event by event (`num_envs` records).
    pub fn records(&self) -> &[StepRecord] {
        &self.records
    }

    /// `num_envs × obs_dim`, row-major: for each env whose episode ended in the last step
    /// ([`VecEnv::dones`]), the observation of the state it ended in, taken before the
    /// respawn (zeros when that state is not finite); the rows of the other envs are stale.
    /// What a learner bootstraps a truncated episode from.
    pub fn final_observations(&self) -> &[f32] {
        &self.final_observations
    }

    /// One control step of every env: `actions` is `num_envs × 4`, row-major, unclipped (the
    /// policy's samples); they are clipped to [−1, 1] before the motors and the reward. A
    /// non-finite component (NaN, ±inf) flies as 0 and is counted in
    /// [`EnvStats::nonfinite_actions`] (the flight controller is stricter: a non-finite policy
    /// output stops its motors). An action slice of the wrong length is refused and nothing
    /// moves.
    pub fn step(&mut self, actions: &[f32]) -> Result<(), ActionShapeError> {
        if actions.len() != self.slots.len() * ACTION_DIM {
            return Err(ActionShapeError {
                expected: self.slots.len() * ACTION_DIM,
                got: actions.len(),
            });
        }
        let rule = self.spawn_rule();
        let (world, spec, fold, map, max_steps, obs_dim) = (
            &self.world,
            &self.spec,
            self.fold.as_ref(),
            &self.map,
            self.max_steps,
            self.obs_dim,
        );
        let reward = Rewards {
            weights: self.config.reward,
            competition: self.race.as_ref().map(|r| (r.competition, r.weight)),
        };
        let reward = &reward;
        let progress = &self.progress;
        let opponent_policy = self.race.as_ref().map(|r| *r.opponent.policy());
        let opponent_policy = opponent_policy.as_ref();
        let flights = self.flights.as_deref();
        self.slots
            .par_chunks_mut(CHUNK)
            .zip(self.observations.par_chunks_mut(CHUNK * obs_dim))
            .zip(self.final_observations.par_chunks_mut(CHUNK * obs_dim))
            .zip(self.rewards.par_chunks_mut(CHUNK))
            .zip(self.dones.par_chunks_mut(CHUNK))
            .zip(self.timeouts.par_chunks_mut(CHUNK))
            .zip(self.records.par_chunks_mut(CHUNK))
            .zip(actions.par_chunks(CHUNK * ACTION_DIM))
            .for_each(
                |(((((((slots, obs), last), rew), done), timeout), record), act)| {
                    let replayed: Vec<Option<&FlightStep>> = slots
                        .iter_mut()
                        .map(|slot| replayed_step(flights, world, slot))
                        .collect();
                    let opponent_commands = opponent_commands(opponent_policy, slots, &replayed);
                    for (i, slot) in slots.iter_mut().enumerate() {
                        let raw: [f32; ACTION_DIM] = core::array::from_fn(|k| {
                            act.get(i * ACTION_DIM + k).copied().unwrap_or(0.0)
                        });
                        let nonfinite = raw.iter().filter(|v| !v.is_finite()).count();
                        slot.stats.nonfinite_actions += nonfinite as u64;
                        let a: [f32; ACTION_DIM] = core::array::from_fn(|k| {
                            let v = raw[k];
                            if v.is_finite() {
                                v.clamp(-1.0, 1.0)
                            } else {
                                0.0
                            }
                        });
                        // A folded observation's action is the image's: renumber it back.
                        let folded = fold.is_some_and(|m| m.folds(slot.drones[0].progress.target));
                        let a = unfold_action(fold, folded, &a);
                        let opp =
                            match (replayed.get(i).copied().flatten(), opponent_commands.get(i)) {
                                (Some(f), _) => Some(OpponentStep::Replayed(f)),
                                (None, Some(Some(c))) => Some(OpponentStep::Live(*c)),
                                (None, _) => None,
                            };
                        let rec = step_slot(world, progress, map, reward, max_steps, slot, &a, opp);
                        if let (Some((_, flown)), Some(OpponentStep::Replayed(_))) =
                            (&mut slot.replay, opp)
                        {
                            *flown += 1;
                        }
                        let ended = rec.crashed || rec.timed_out;
                        if rec.gate_passed && !ended && rule.replay_fraction > 0.0 {
                            slot.passes.record(slot.drones[0], slot.previous_action);
                        }
                        if ended {
                            let row = i * obs_dim..(i + 1) * obs_dim;
                            observe(world, spec, fold, slot, &mut last[row]);
                            respawn(world, progress, map, &rule, slot);
                        }
                        rew[i] = rec.terms.total() as f32;
                        done[i] = ended;
                        timeout[i] = rec.timed_out;
                        record[i] = rec;
                        observe(
                            world,
                            spec,
                            fold,
                            slot,
                            &mut obs[i * obs_dim..(i + 1) * obs_dim],
                        );
                    }
                },
            );
        Ok(())
    }

    /// What `teacher` would command in every env now, as actions in [−1, 1] through the
    /// inverse of the paper's action map (`num_envs × 4`, row-major): the labels of the
    /// imitation warm start. The teacher flies to each env's current target gate.
    pub fn teacher_actions(&self, teacher: &BaselineController<'static>, out: &mut [f32]) {
        let map = self.map;
        self.per_env(out, |slot| {
            let d = &slot.drones[0];
            let mut c = teacher.clone();
            c.reset(d.progress.target);
            let (cmd, _) = c.step(&d.body.state);
            cmd.rpm.map(|rpm| map.action_for_rpm(rpm).clamp(-1.0, 1.0))
        });
    }

    /// `label(slot)` of every env into `out` (`num_envs × 4`), in parallel.
    fn per_env(&self, out: &mut [f32], label: impl Fn(&Slot) -> [f32; ACTION_DIM] + Sync) {
        self.slots
            .par_chunks(CHUNK)
            .zip(out.par_chunks_mut(CHUNK * ACTION_DIM))
            .for_each(|(slots, out)| {
                for (slot, a) in slots.iter().zip(out.chunks_exact_mut(ACTION_DIM)) {
                    a.copy_from_slice(&label(slot));
                }
            });
    }

    /// What a feed-forward `policy` (a time-trial blob's, observing through `spec`) would
    /// command in every env now: its means for the ego's state, the ego's target gate and
    /// the ego's executed previous action (`num_envs × 4`, row-major), as the world's motors
    /// (a folded `spec` observes and acts through the track's mirror on its mirrored half).
    /// The labels of an imitation warm start with a learned teacher; a recurrent or
    /// opponent-observing policy gives zeros (it is refused before this is called).
    pub fn policy_actions(
        &self,
        policy: &firmware_core::policy::Policy<'_>,
        spec: &ObservationSpec,
        out: &mut [f32],
    ) {
        let world = &self.world;
        // A folded teacher flies through the track's mirror whether or not the env folds.
        let fold = match &self.mirror {
            Ok(m) if spec.is_folded() => Some(m.track_mirror()),
            _ => None,
        };
        self.per_env(out, |slot| {
            let mut state = firmware_core::policy::PolicyState::Stateless;
            ego_observation(world, spec, fold, slot, false)
                .ok()
                .and_then(|(o, folded)| {
                    let a = policy.act(&o, &mut state)?;
                    Some(unfold_action(fold, folded, &a))
                })
                .unwrap_or([0.0; ACTION_DIM])
        });
    }

    /// Starts a new episode in every env now (a fresh spawn, the opponent's controller
    /// reset): for collecting data whose recurrent state starts at zero.
    pub fn respawn_all(&mut self) {
        let rule = self.spawn_rule();
        for slot in &mut self.slots {
            respawn(&self.world, &self.progress, &self.map, &rule, slot);
        }
        self.observe_all();
    }

    /// Flies every opponent live from now on, its controller stepped in every step, instead
    /// of replaying its recorded flight (`env::flight`): for the tests and benches that compare
    /// the two. An opponent in the middle of a replay goes on from the recorded state; a later
    /// [`VecEnv::set_race`] keeps flying live.
    pub fn fly_opponents_live(&mut self) {
        let book = self.flights.take();
        for slot in &mut self.slots {
            let last = slot
                .replay
                .take()
                .and_then(|(key, flown)| book.as_deref()?.memory_after(key, flown));
            if let (Some(c), Some(memory)) = (slot.opponent.as_mut(), last) {
                c.restore(&memory, &[]);
            }
        }
    }

    /// Races `race` from now on (an opponent curriculum changes the opponent during a run):
    /// its opponent's blob read and validated as [`VecEnv::new`] does, every slot given a
    /// fresh copy of its controller, and every env respawned ([`VecEnv::respawn_all`]), so no
    /// race goes on with a changed opponent. A time-trial env, or a blob that is refused,
    /// leaves the env as it was.
    pub fn set_race(&mut self, race: RaceConfig) -> Result<(), EnvError> {
        if self.race.is_none() {
            return Err(EnvError::Unflyable(
                "a time-trial environment has no opponent to change".into(),
            ));
        }
        let loaded = Race::load(&race)?;
        if self.flights.is_some() {
            // New recordings for the new opponent (an env flying live stays live).
            self.flights = flight_book(&loaded, &self.world, self.max_steps);
        }
        for slot in &mut self.slots {
            slot.opponent = Some(loaded.opponent.clone());
        }
        self.race = Some(loaded);
        self.config.race = Some(race);
        self.respawn_all();
        Ok(())
    }

    /// Values per privileged state ([`VecEnv::privileged_observations`]): the observation's
    /// and [`PRIVILEGED_EXTRA`] more.
    pub fn privileged_dim(&self) -> usize {
        self.obs_dim + PRIVILEGED_EXTRA
    }

    /// Every env's privileged state, `num_envs × privileged_dim`, row-major, into `out`
    /// (cleared first): what an asymmetric critic learns the value from, which the deployed
    /// policy never sees. Per env:
    /// - the ego's observation of its true state: the same layout, fold and opponent as
    ///   [`VecEnv::observations`], without the randomised sensor noise (zeros when the
    ///   pipeline refuses the state);
    /// - the episode's randomised airframe (`env.randomize`) as ratios to the preset minus 1:
    ///   thrust, mass, inertia (0 when not randomised);
    /// - the ego's motor time constant (units of 10 ms), its command latency (steps);
    /// - the share of the episode's time left (1 at the start, 0 at the time-out).
    pub fn privileged_observations(&self, out: &mut Vec<f32>) {
        let dim = self.privileged_dim();
        out.clear();
        out.resize(self.slots.len() * dim, 0.0);
        for (slot, row) in self.slots.iter().zip(out.chunks_exact_mut(dim)) {
            privileged(
                &self.world,
                &self.spec,
                self.fold.as_ref(),
                slot,
                self.max_steps,
                row,
            );
        }
    }

    /// The observation of every env's current state reflected in the track's mirror plane
    /// ([`crate::mirror`]), `num_envs × obs_dim`, row-major, into `out` (cleared first): the
    /// reflected drones (and opponents) observed by the same pipeline, targeting the
    /// reflected gates, after the reflected previous actions. A learner that trains on
    /// mirror images pairs each with [`Mirror::motors`] of the action taken. A track without
    /// the symmetry is refused and `out` is left empty.
    pub fn mirrored_observations(&self, out: &mut Vec<f32>) -> Result<(), NoMirror> {
        out.clear();
        let mirror = self.mirror.as_ref().map_err(Clone::clone)?;
        out.resize(self.slots.len() * self.obs_dim, 0.0);
        for (slot, obs) in self.slots.iter().zip(out.chunks_exact_mut(self.obs_dim)) {
            observe_drones(
                &self.world,
                &self.spec,
                &slot.drones.each_ref().map(|d| mirror.drone(d)),
                &mirror.motors(&slot.previous_action),
                slot.opponent.is_some(),
                obs,
            );
        }
        Ok(())
    }

    /// The gate each env's ego must pass next (the gate its observation shows), one per env.
    pub fn target_gates(&self) -> impl ExactSizeIterator<Item = usize> + '_ {
        self.slots.iter().map(|s| s.drones[0].progress.target)
    }

    /// The track's mirror symmetry, if it has one.
    pub fn mirror(&self) -> Result<&Mirror, NoMirror> {
        self.mirror.as_ref().map_err(Clone::clone)
    }

    /// The statistics since the last call, summed over envs, and reset.
    pub fn take_stats(&mut self) -> EnvStats {
        let mut total = EnvStats::default();
        for s in &mut self.slots {
            total.add(&s.stats);
            s.stats = EnvStats::default();
        }
        total
    }
}

/// The book of the race's recorded opponent flights: one place per gate, and with the
/// places swapped; `None` for a recurrent opponent (its state is not recorded), which flies
/// live.
fn flight_book(race: &Race, world: &World, max_steps: u32) -> Option<std::sync::Arc<FlightBook>> {
    (race.opponent.policy_state().flat_len() == 0)
        .then(|| std::sync::Arc::new(FlightBook::new(2 * world.track.len(), max_steps)))
}

/// The opponent's recorded step for `slot` now, when its flight is being replayed
/// ([`flight`]); else `None`, and the slot flies its opponent live from here to its next
/// spawn (its controller given the recorded bookkeeping first, when the flight ran out of
/// recorded steps).
fn replayed_step<'b>(
    flights: Option<&'b FlightBook>,
    world: &World,
    slot: &mut Slot,
) -> Option<&'b FlightStep> {
    let (key, flown) = slot.replay?;
    let step = flights.and_then(|book| {
        let controller = slot.opponent.as_ref()?;
        let flight = if flown == 0 {
            book.flight(key, world, &slot.drones[1], controller)?
        } else {
            book.recorded(key)?
        };
        flight.step(flown)
    });
    if step.is_none() {
        // Live from here; past the recording, the controller takes over where it stopped.
        let last = flights.and_then(|book| book.memory_after(key, flown));
        if let (Some(c), Some(memory)) = (slot.opponent.as_mut(), last) {
            c.restore(&memory, &[]);
        }
        slot.replay = None;
    }
    step
}

/// The commands of the opponents of `slots` flown live (stage 2; empty in a time trial),
/// one per slot, `None` where `replayed` holds the opponent's recorded step: from the states
/// before the step (as the referee's lockstep does), their controllers stepped [`LANES`] at
/// a time through `policy`, the one all of them fly (clones of the race's controller), where
/// a whole group flies live, else one by one; bit for bit `Controller::step` either way.
fn opponent_commands(
    policy: Option<&Policy<'static>>,
    slots: &mut [Slot],
    replayed: &[Option<&FlightStep>],
) -> Vec<Option<MotorCommand>> {
    let Some(policy) = policy else {
        return Vec::new();
    };
    if replayed.iter().all(Option::is_some) {
        return vec![None; slots.len()];
    }
    let mut commands = Vec::with_capacity(slots.len());
    let mut groups = slots.chunks_exact_mut(LANES);
    let mut flags = replayed.chunks(LANES);
    for group in &mut groups {
        let replay = flags.next().unwrap_or(&[]);
        if replay.iter().any(Option::is_some) {
            commands.extend(group.iter_mut().zip(replay).map(|(slot, r)| match r {
                Some(_) => None,
                None => one_command(slot),
            }));
            continue;
        }
        let mut controllers = Vec::with_capacity(LANES);
        let mut own = Vec::with_capacity(LANES);
        let mut ego = Vec::with_capacity(LANES);
        for slot in group.iter_mut() {
            let [e, o] = &slot.drones;
            own.push(&o.body.state);
            ego.push(Some(&e.body.state));
            if let Some(c) = slot.opponent.as_mut() {
                controllers.push(c);
            }
        }
        let (Ok(controllers), Ok(own), Ok(ego)) = (
            <[_; LANES]>::try_from(controllers),
            <[_; LANES]>::try_from(own),
            <[_; LANES]>::try_from(ego),
        ) else {
            // A slot without an opponent in a race: none is built that way.
            return Vec::new();
        };
        let out = crate::lanes::controller_step_lanes(policy, controllers, own, ego);
        commands.extend(out.iter().map(|o| Some(o.command)));
    }
    let rest = replayed.get(commands.len()..).unwrap_or(&[]);
    for (slot, r) in groups.into_remainder().iter_mut().zip(rest) {
        commands.push(match r {
            Some(_) => None,
            None => one_command(slot),
        });
    }
    commands
}

/// The command of `slot`'s opponent flown live, one env alone.
fn one_command(slot: &mut Slot) -> Option<MotorCommand> {
    let [e, o] = &slot.drones;
    let c = slot.opponent.as_mut()?;
    Some(c.step(&o.body.state, Some(&e.body.state)).command)
}

/// What the opponent does in a step of its env: flown live with a command, or its recorded
/// step replayed ([`flight`]).
#[derive(Clone, Copy)]
enum OpponentStep<'a> {
    Live(MotorCommand),
    Replayed(&'a FlightStep),
}

/// Steps one env, the opponent flying or replaying `opponent` (stage 2; `None` in a time
/// trial: the ego flies alone); returns what the step
/// was made of.
#[allow(clippy::too_many_arguments)]
fn step_slot(
    world: &World,
    progress: &TrackProgress,
    map: &ActionMap,
    rewards: &Rewards,
    max_steps: u32,
    slot: &mut Slot,
    action: &[f32; ACTION_DIM],
    opponent: Option<OpponentStep<'_>>,
) -> StepRecord {
    let d = &slot.drones[0];
    let gate = world.track.gate(d.progress.target).center_m;
    let before = d.position_m();
    let (command, airframe) = match &mut slot.perturbed {
        Some(p) => (p.deliver(map.command(action)), p.ego_preset),
        None => (map.command(action), world.preset),
    };
    let (result, opponent_crashed) = match opponent {
        Some(OpponentStep::Replayed(f)) => {
            let [ego, opponent] = &mut slot.drones;
            let from = opponent.position_m();
            let [e, o] = world.step_beside(ego, &command, &airframe, from, &f.drone, f.step);
            *opponent = f.drone;
            (e, o.crash.is_some())
        }
        Some(OpponentStep::Live(opp_command)) => {
            let [e, o] = world.step_airframes(
                &mut slot.drones,
                &[command, opp_command],
                &[airframe, world.preset],
            );
            (e, o.crash.is_some())
        }
        None => {
            let [ego, _] = &mut slot.drones;
            let [e] = world.step_airframes(core::array::from_mut(ego), &[command], &[airframe]);
            (e, false)
        }
    };
    let crashed = result.crash.is_some();
    let passed = !crashed && result.passed_gate().is_some();
    let [ego, opponent] = &slot.drones;
    let terms = rewards.terms(&StepOutcome {
        dt_s: world.dt_s,
        gate_m: gate,
        before_m: before,
        action,
        previous_action: &slot.previous_action,
        crashed,
        passed,
        ego,
        opponent,
        spawn_segment: slot.spawn_segment,
        progress,
    });
    slot.stats.gates_passed += u64::from(passed);
    slot.previous_action = *action;
    slot.steps += 1;
    // The opponent crashing alone cuts the episode short without the ego's doing: a
    // truncation, bootstrapped like a time-out.
    let opponent_only = !crashed && opponent_crashed;
    let timed_out = !crashed && (slot.steps >= max_steps || opponent_only);
    slot.stats.steps += 1;
    slot.stats.crashes += u64::from(crashed);
    slot.stats.timeouts += u64::from(timed_out && !opponent_only);
    slot.stats.opponent_crashes += u64::from(opponent_only);
    slot.stats.terms.add(&terms);
    StepRecord {
        terms,
        gate_passed: passed,
        crashed,
        timed_out,
        opponent_crashed: opponent_only,
    }
}
