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
//! controller runs, deterministically (its Gaussian mean). An episode ends as a race restarts
//! in the referee: on any crash. The ego's crash (a collision included) is a terminal step
//! with the crash penalty; the opponent crashing alone is a truncation (`timeouts`, so it is
//! bootstrapped with γ·V): the ego did nothing wrong and its future was cut short.
//!
//! **The reward** of a step, term by term, is [`reward`]'s (docs/DESIGN.md "Rewards").

use crate::dynamics::Preset;
use crate::mirror::{Mirror, NoMirror};
use crate::racing_line;
use crate::referee::{SpawnMode, TrackProgress};
use crate::world::{Drone, World};
use firmware_core::Controller;
use firmware_core::baseline::BaselineController;
use firmware_core::blob::AlignedBytes;
use firmware_core::math::Vec3;
use firmware_core::mirror::{TrackMirror, observe_folded, unfold_action};
use firmware_core::nn::ACTION_DIM;
use firmware_core::observation::{Observation, ObservationError, ObservationSpec};
use firmware_core::track::{CrashRules, Track};
use firmware_core::vehicle::ActionMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub mod reward;

pub use reward::{Competition, RewardTerms, RewardWeights, dense_competition};
use reward::{Rewards, StepOutcome};

/// Envs per rayon task.
const CHUNK: usize = 128;

/// How the training environment is built.
#[derive(Clone, Debug)]
pub struct EnvConfig {
    /// Number of parallel envs.
    pub num_envs: usize,
    /// Dynamics preset.
    pub preset: Preset,
    /// Where episodes start: the paper's fixed stage-1 spawn or along the track.
    pub spawn: SpawnMode,
    /// Highest initial speed (m/s) of a spawn, along its heading, drawn uniformly from
    /// [0, this]; 0 spawns at rest as the paper's spawns do. Not part of the paper: a
    /// drone already moving toward its gate sees progress reward from its first step (see
    /// docs/TRAINING.md).
    pub spawn_speed_mps: f32,
    /// Share of respawns at the paper's fixed stage-1 spawn (at rest) whatever `spawn` is:
    /// the start the referee evaluates stage 1 from. 0 for `spawn` alone.
    pub stage1_fraction: f32,
    /// Share of the time-trial respawns that are neither replayed nor stage-1 at the paper's
    /// stage-2 spawn (at rest, 2 m or 1 m before a random gate and targeting it: the ego's or
    /// the opponent's start of a race, each half the time). The stage-1 policy is stage 2's
    /// opponent and starts there; a policy trained only on moving or stage-1 starts may not
    /// lift off cleanly that close to a gate. 0 for none (the paper's stage 1).
    pub stage2_fraction: f32,
    /// Share of time-trial respawns that restart from a state the env itself flew through
    /// right after one of its recent gate passes (its position, attitude, velocity, rates,
    /// propeller speeds, next target and previous action), when it has one: Song et al.
    /// 2023's "states from successful gate passes", so the policy trains where its own
    /// flight takes it, at its own speeds. 0 for none (the paper's).
    pub replay_fraction: f32,
    /// Share of the time-trial respawns that are neither replayed nor stage-1 nor stage-2
    /// spawns placed on the `paper` preset's time-optimal lap ([`crate::racing_line`]): a random node's
    /// position, velocity, thrust-aligned attitude and target gate. Shows the policy the
    /// fast line's states (corners, climbs, dives, 7-14 m/s); the line is the `paper`
    /// preset's, so with another preset it is a slower line than that preset could fly. 0
    /// for none (the paper's).
    pub racing_line_fraction: f32,
    /// Episode length (s) before a time-out. Paper stage 1: 15.
    pub episode_s: f32,
    /// Start every env at a random point of its first episode (RSL-RL's
    /// `init_at_random_ep_len`), so that time-outs are spread over iterations.
    pub random_initial_episode_length: bool,
    /// Reward weights.
    pub reward: RewardWeights,
    /// The observation spec (layout 17; the scales are recorded in exported blobs). Paper:
    /// `ObservationSpec::paper(TimeTrial17)`.
    pub observation: ObservationSpec,
    /// Seed of the spawns and initial lengths (env i uses stream i).
    pub seed: u64,
    /// Stage 2: race an opponent (`None`: a time trial). The spawn is then the paper's stage-2
    /// spawn whatever `spawn`, `spawn_speed_mps` and `stage1_fraction` say.
    pub race: Option<RaceConfig>,
}

/// The opponent and the competition reward of a stage-2 environment.
#[derive(Clone, Debug)]
pub struct RaceConfig {
    /// The opponent's blob (a feed-forward or recurrent policy), validated when the
    /// environment is built.
    pub opponent: AlignedBytes,
    /// Which competition reward.
    pub competition: Competition,
    /// Its weight λ_c (× dt like every term). Paper 0.5.
    pub competition_weight: f32,
}

/// The environment could not be built: the opponent's blob cannot be flown, or the
/// observation is folded ([`firmware_core::mirror`]) on a track without the symmetry.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvError(pub String);

impl core::fmt::Display for EnvError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for EnvError {}

/// `bytes` for the rest of the process, one copy per distinct blob: the opponent's
/// [`Controller`] views its blob's weights in place (as in flash), so every env's controller
/// borrows one copy that must outlive the environments, which are rebuilt during a run.
pub fn interned(bytes: &AlignedBytes) -> &'static AlignedBytes {
    static BLOBS: std::sync::Mutex<Vec<&'static AlignedBytes>> = std::sync::Mutex::new(Vec::new());
    let mut blobs = BLOBS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(b) = blobs.iter().find(|b| **b == bytes) {
        return b;
    }
    let b: &'static AlignedBytes = Box::leak(Box::new(bytes.clone()));
    blobs.push(b);
    b
}

/// The built race: one controller template, cloned into every slot.
#[derive(Clone, Debug)]
struct Race {
    opponent: Controller<'static>,
    competition: Competition,
    weight: f32,
}

impl EnvConfig {
    /// `num_envs` envs with the paper's settings (preset, the paper's reward, observation spec,
    /// 15 s episodes), spawned along the track at rest with random initial episode lengths,
    /// seeded with `seed`: the base that configs and tests adjust.
    pub fn paper_along_track(num_envs: usize, seed: u64) -> Self {
        Self {
            num_envs,
            preset: Preset::paper(),
            spawn: SpawnMode::AlongTrack,
            spawn_speed_mps: 0.0,
            stage1_fraction: 0.0,
            stage2_fraction: 0.0,
            replay_fraction: 0.0,
            racing_line_fraction: 0.0,
            episode_s: 15.0,
            random_initial_episode_length: true,
            reward: RewardWeights::default(),
            observation: ObservationSpec::paper(
                firmware_core::observation::ObservationLayout::TimeTrial17,
            ),
            seed,
            race: None,
        }
    }
}

/// Per-step statistics of the whole batch, drained by [`VecEnv::take_stats`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EnvStats {
    /// Env-steps taken.
    pub steps: u64,
    /// Reward terms summed over those steps.
    pub terms: RewardTerms,
    /// Gates passed.
    pub gates_passed: u64,
    /// Crashes (episode ends that are not time-outs).
    pub crashes: u64,
    /// Episodes ended by the time limit.
    pub timeouts: u64,
    /// Stage 2: episodes ended by the opponent's crash alone (truncations).
    pub opponent_crashes: u64,
}

impl EnvStats {
    /// Gates passed / (gates passed + crashes): the success rate of docs/DESIGN.md "Metrics" over the
    /// steps counted (each crash meets one gate it did not pass).
    pub fn success_rate(&self) -> f64 {
        let met = self.gates_passed + self.crashes;
        if met == 0 {
            0.0
        } else {
            self.gates_passed as f64 / met as f64
        }
    }

    fn add(&mut self, o: &Self) {
        self.steps += o.steps;
        self.terms.add(&o.terms);
        self.gates_passed += o.gates_passed;
        self.crashes += o.crashes;
        self.timeouts += o.timeouts;
        self.opponent_crashes += o.opponent_crashes;
    }
}

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
    stats: EnvStats,
    /// The ego's states after its last gate passes (for `replay_fraction`).
    passes: PassReplay,
}

/// States after the last [`PassReplay::LEN`] gate passes of one env, oldest overwritten.
#[derive(Clone, Debug, Default)]
struct PassReplay {
    states: [Option<(Drone, [f32; ACTION_DIM])>; PassReplay::LEN],
    next: usize,
}

impl PassReplay {
    const LEN: usize = 8;

    fn record(&mut self, drone: Drone, previous_action: [f32; ACTION_DIM]) {
        self.states[self.next] = Some((drone, previous_action));
        self.next = (self.next + 1) % Self::LEN;
    }

    fn draw(&self, rng: &mut ChaCha8Rng) -> Option<(Drone, [f32; ACTION_DIM])> {
        let filled = self.states.iter().filter(|s| s.is_some()).count();
        if filled == 0 {
            return None;
        }
        self.states[rng.random_range(0..filled)]
    }
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

/// What one env's last step was made of: its reward term by term and its events. The
/// per-step counterpart of [`EnvStats`], for learners that log or filter per env.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepRecord {
    /// The reward's terms; `terms.total() as f32` is the env's reward.
    pub terms: RewardTerms,
    /// The ego passed its target gate.
    pub gate_passed: bool,
    /// The ego crashed (a terminal step).
    pub crashed: bool,
    /// The episode reached its time limit (a truncation).
    pub timed_out: bool,
    /// Stage 2: the opponent crashed while the ego did not (a truncation too).
    pub opponent_crashed: bool,
}

/// Observation size of stage 1.
pub const OBS_DIM: usize = 17;

impl VecEnv {
    /// `config.num_envs` stage-1 envs, each spawned (at a random point of its first episode
    /// when `random_initial_episode_length`); `config.race` is ignored. For a race use
    /// [`VecEnv::new`].
    pub fn time_trial(config: EnvConfig) -> Self {
        let config = EnvConfig {
            race: None,
            ..config
        };
        match Self::new(config) {
            Ok(env) => env,
            // Without a race there is no blob to refuse.
            Err(_) => unreachable!("a time trial has no opponent"),
        }
    }

    /// `config.num_envs` envs of a time trial or, with `config.race`, of a race; an opponent
    /// blob that does not validate, or whose policy would need to see an opponent itself, is
    /// refused here.
    pub fn new(config: EnvConfig) -> Result<Self, EnvError> {
        let rules = if config.race.is_some() {
            CrashRules::STAGE2
        } else {
            CrashRules::STAGE1
        };
        let world = World::figure_eight(config.preset, rules);
        let race = match &config.race {
            None => None,
            Some(r) => {
                let blob = firmware_core::blob::Blob::parse(interned(&r.opponent).as_bytes())
                    .map_err(|e| EnvError(format!("opponent blob: {e}")))?;
                let opponent = Controller::new(
                    &blob,
                    Track::figure_eight(),
                    blob.header().control_period_ns,
                )
                .map_err(|e| EnvError(format!("opponent blob: {e}")))?;
                if blob.header().observation.layout.needs_opponent() {
                    return Err(EnvError(
                        "opponent blob: the opponent's policy observes an opponent itself; stage 2 races a time-trial (17-value) policy"
                            .into(),
                    ));
                }
                Some(Race {
                    opponent,
                    competition: r.competition,
                    weight: r.competition_weight,
                })
            }
        };
        let progress = TrackProgress::new(&world.track);
        let max_steps = ((config.episode_s / world.dt_s).round() as u32).max(1);
        let n = config.num_envs;
        let obs_dim = config.observation.layout.dim();
        let mirror = Mirror::of_track(&world.track);
        let fold = match (&mirror, config.observation.is_folded()) {
            (_, false) => None,
            (Ok(m), true) => Some(*m.track_mirror()),
            (Err(e), true) => {
                return Err(EnvError(format!(
                    "the observation is folded by the track's mirror, but the track has {e}"
                )));
            }
        };
        let mut env = Self {
            world,
            progress,
            spec: config.observation,
            obs_dim,
            map: ActionMap::PAPER,
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
                stats: EnvStats::default(),
                passes: PassReplay::default(),
            };
            respawn(&env.world, &env.progress, &env.spawn_rule(), &mut slot);
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
            .iter()
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
            racing_line_fraction: self.config.racing_line_fraction,
            race: self.race.is_some(),
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
    /// policy's samples); they are clipped to [−1, 1] (a NaN to 0) before the motors and the
    /// reward. An action slice of the wrong length is refused and nothing moves.
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
                    for (i, slot) in slots.iter_mut().enumerate() {
                        let a: [f32; ACTION_DIM] = core::array::from_fn(|k| {
                            let v = act.get(i * ACTION_DIM + k).copied().unwrap_or(0.0);
                            if v.is_finite() {
                                v.clamp(-1.0, 1.0)
                            } else {
                                0.0
                            }
                        });
                        // A folded observation's action is the image's: renumber it back.
                        let folded = fold.is_some_and(|m| m.folds(slot.drones[0].progress.target));
                        let a = unfold_action(fold, folded, &a);
                        let rec = step_slot(world, progress, map, reward, max_steps, slot, &a);
                        let ended = rec.crashed || rec.timed_out;
                        if rec.gate_passed && !ended && rule.replay_fraction > 0.0 {
                            slot.passes.record(slot.drones[0], slot.previous_action);
                        }
                        if ended {
                            let row = i * obs_dim..(i + 1) * obs_dim;
                            observe(world, spec, fold, slot, &mut last[row]);
                            respawn(world, progress, &rule, slot);
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
            respawn(&self.world, &self.progress, &rule, slot);
        }
        self.observe_all();
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

/// The actions given to [`VecEnv::step`] do not have `num_envs × 4` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ActionShapeError {
    /// Values expected.
    pub expected: usize,
    /// Values given.
    pub got: usize,
}

impl core::fmt::Display for ActionShapeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "expected {} action values (envs × 4), got {}",
            self.expected, self.got
        )
    }
}

impl std::error::Error for ActionShapeError {}

/// The counts given to [`VecEnv::set_episode_steps`] are not one per env.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EpisodeStepsError {
    /// Values expected (`num_envs`).
    pub expected: usize,
    /// Values given.
    pub got: usize,
}

impl core::fmt::Display for EpisodeStepsError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "expected {} episode step counts (one per env), got {}",
            self.expected, self.got
        )
    }
}

impl std::error::Error for EpisodeStepsError {}

/// How an env respawns.
#[derive(Clone, Copy, Debug)]
struct SpawnRule {
    mode: SpawnMode,
    max_speed_mps: f32,
    stage1_fraction: f32,
    stage2_fraction: f32,
    replay_fraction: f32,
    racing_line_fraction: f32,
    race: bool,
}

/// A new episode in `slot`: a spawn drawn from its generator. In a race, the paper's stage-2 spawn
/// for both drones, the opponent's controller reset to their gate. In a time trial, the
/// stage-1 spawn with probability `stage1_fraction`, otherwise `mode`'s, moving along its
/// heading at a speed drawn from [0, `max_speed_mps`] when that is positive. The previous
/// action zeroed. Otherwise, with probability `replay_fraction`, the state after one of the
/// env's recent gate passes, with that step's previous action; and of the spawns that are
/// neither replayed nor stage-1, a share `stage2_fraction` is the ego's or the opponent's
/// stage-2 spawn (at rest), and of the rest a share `racing_line_fraction` is a random node
/// of the time-optimal lap (moving as the optimum does there). A share of 0 draws no random
/// number, so configs without it keep their streams.
fn respawn(world: &World, progress: &TrackProgress, rule: &SpawnRule, slot: &mut Slot) {
    if !rule.race && rule.replay_fraction > 0.0 && slot.rng.random::<f32>() < rule.replay_fraction {
        if let Some((drone, previous_action)) = slot.passes.draw(&mut slot.rng) {
            slot.drones[0] = drone;
            slot.spawn_segment[0] = progress.spawn_segment(drone.progress.target);
            slot.previous_action = previous_action;
            slot.steps = 0;
            return;
        }
    }
    let line = progress.line();
    let stage1 =
        !rule.race && rule.stage1_fraction > 0.0 && slot.rng.random::<f32>() < rule.stage1_fraction;
    let stage2 = !rule.race
        && !stage1
        && rule.stage2_fraction > 0.0
        && slot.rng.random::<f32>() < rule.stage2_fraction;
    let on_line = !rule.race
        && !stage1
        && !stage2
        && rule.racing_line_fraction > 0.0
        && slot.rng.random::<f32>() < rule.racing_line_fraction;
    let mode = if stage1 { SpawnMode::Stage1 } else { rule.mode };
    let [mut spawn, opponent] = if on_line {
        let s = racing_line::paper_spawn(slot.rng.random_range(0..racing_line::paper_nodes()));
        [s, s]
    } else if stage2 {
        let [ego, opponent] = SpawnMode::Stage2.draw(&world.track, line, &mut slot.rng);
        let s = if slot.rng.random::<bool>() {
            ego
        } else {
            opponent
        };
        [s, s]
    } else {
        mode.draw(&world.track, line, &mut slot.rng)
    };
    if rule.max_speed_mps > 0.0 && !stage1 && !stage2 && !on_line && !rule.race {
        let speed = slot.rng.random_range(0.0..rule.max_speed_mps);
        let forward = spawn.state.attitude.rotate(Vec3::new(1.0, 0.0, 0.0));
        spawn.state.velocity_mps = forward.scale(speed);
    }
    slot.drones = [Drone::spawned(spawn), Drone::spawned(opponent)];
    slot.spawn_segment = slot
        .drones
        .each_ref()
        .map(|d| progress.spawn_segment(d.progress.target));
    if let Some(c) = &mut slot.opponent {
        c.reset(opponent.target_gate);
    }
    slot.previous_action = [0.0; ACTION_DIM];
    slot.steps = 0;
}

/// Steps one env; returns what the step was made of.
fn step_slot(
    world: &World,
    progress: &TrackProgress,
    map: &ActionMap,
    rewards: &Rewards,
    max_steps: u32,
    slot: &mut Slot,
    action: &[f32; ACTION_DIM],
) -> StepRecord {
    let d = &slot.drones[0];
    let gate = world.track.gate(d.progress.target).center_m;
    let before = d.position_m();
    let (result, opponent_crashed) = match &mut slot.opponent {
        Some(c) => {
            let [ego, opp] = &slot.drones;
            // Both commands from the states before the step, as the referee's lockstep does.
            let opp_command = c.step(&opp.body.state, Some(&ego.body.state)).command;
            let [e, o] = world.step(&mut slot.drones, &[map.command(action), opp_command]);
            (e, o.crash.is_some())
        }
        None => {
            let [ego, _] = &mut slot.drones;
            let [e] = world.step(core::array::from_mut(ego), &[map.command(action)]);
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

/// The ego's observation of its slot, folded by `fold` (the env's, when its spec is
/// folded); zeros when the pipeline refuses the state.
fn observe(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &Slot,
    out: &mut [f32],
) {
    match ego_observation(world, spec, fold, slot, slot.opponent.is_some()) {
        Ok((o, _)) => out.copy_from_slice(o.as_slice()),
        // Only a diverged state fails, and a diverged state is a crash that was respawned.
        Err(_) => out.fill(0.0),
    }
}

/// The ego's observation in `slot` through `fold` (and whether it is the mirror image), with
/// the opponent in it when `racing`.
fn ego_observation(
    world: &World,
    spec: &ObservationSpec,
    fold: Option<&TrackMirror>,
    slot: &Slot,
    racing: bool,
) -> Result<(Observation, bool), ObservationError> {
    let [d, opp] = &slot.drones;
    observe_folded(
        spec,
        fold,
        &world.track,
        &d.body.state,
        d.progress.target,
        &slot.previous_action,
        racing.then_some(&opp.body.state),
    )
}

/// The ego's observation (`drones[0]`, after `previous_action`), with `drones[1]` as the
/// opponent when `racing`; zeros when the pipeline refuses the state.
fn observe_drones(
    world: &World,
    spec: &ObservationSpec,
    drones: &[Drone; 2],
    previous_action: &[f32; ACTION_DIM],
    racing: bool,
    out: &mut [f32],
) {
    let [d, opp] = drones;
    let gate = world.track.gate(d.progress.target);
    let opponent = racing.then_some(&opp.body.state);
    match spec.observe(&d.body.state, &gate, previous_action, opponent) {
        Ok(o) => out.copy_from_slice(o.as_slice()),
        // Only a diverged state fails, and a diverged state is a crash that was respawned.
        Err(_) => out.fill(0.0),
    }
}
