//! A [`VecEnv`]'s whole state between two steps, to be written to disk and restored into a
//! `VecEnv` built from the same config: what a training checkpoint needs so that a resumed
//! run steps the very envs the uninterrupted run would have (docs/RELIABILITY.md, "Resume").
//!
//! Per env: both drones, the opponent controller's bookkeeping and recurrent state, the
//! previous action, the episode's step count, the spawn segments, both random generators'
//! positions, the statistics not yet taken, the replayed gate passes and the randomisation
//! drawn for the episode; and the observations the next action is chosen from. What the
//! config fixes (the world, the opponent's weights, the spec) is not stored: a snapshot is
//! restored into an env built from the same config, and refused, naming the misfit, where
//! the env's shape differs.

use super::flight::FlightBook;
use super::{EnvError, Slot, VecEnv};
use crate::perturb::EpisodePerturbationSnapshot;
use crate::world::Drone;
use firmware_core::controller::ControllerMemory;
use firmware_core::nn::ACTION_DIM;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Version of [`EnvSnapshot`]'s layout.
pub const ENV_SNAPSHOT_FORMAT: u32 = 1;

/// Where a ChaCha8 generator stands: its seed, stream and word position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RngSnapshot {
    seed: [u8; 32],
    stream: u64,
    word_pos: u128,
}

impl RngSnapshot {
    /// The generator's position.
    pub fn of(r: &ChaCha8Rng) -> Self {
        Self {
            seed: r.get_seed(),
            stream: r.get_stream(),
            word_pos: r.get_word_pos(),
        }
    }

    /// The generator at that position: it draws what the snapshotted one would have.
    pub fn generator(&self) -> ChaCha8Rng {
        let mut r = ChaCha8Rng::from_seed(self.seed);
        r.set_stream(self.stream);
        r.set_word_pos(self.word_pos);
        r
    }
}

/// One env's state ([`EnvSnapshot::slots`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SlotSnapshot {
    drones: [Drone; 2],
    /// The opponent controller's bookkeeping and its recurrent state (flat, empty for a
    /// feed-forward opponent).
    opponent: Option<(ControllerMemory, Vec<f32>)>,
    previous_action: [f32; ACTION_DIM],
    steps: u32,
    spawn_segment: [u64; 2],
    rng: RngSnapshot,
    perturb_rng: RngSnapshot,
    stats: super::EnvStats,
    passes: super::PassReplay,
    perturbed: Option<EpisodePerturbationSnapshot>,
}

/// Every env's state and the observations of the current step ([`VecEnv::snapshot`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnvSnapshot {
    /// [`ENV_SNAPSHOT_FORMAT`] when written.
    pub format: u32,
    /// Observation size of the env it was taken of.
    pub obs_dim: usize,
    /// The envs, in order.
    pub slots: Vec<SlotSnapshot>,
    /// The current observations, `envs × obs_dim`.
    pub observations: Vec<f32>,
}

impl VecEnv {
    /// The state of every env now ([`EnvSnapshot`]).
    pub fn snapshot(&self) -> EnvSnapshot {
        EnvSnapshot {
            format: ENV_SNAPSHOT_FORMAT,
            obs_dim: self.obs_dim,
            slots: self
                .slots
                .iter()
                .map(|slot| slot_snapshot(slot, self.flights.as_deref()))
                .collect(),
            observations: self.observations.clone(),
        }
    }

    /// Puts every env back where [`Self::snapshot`] found it: the next [`Self::step`] is
    /// the one the snapshotted env would have taken. `self` must be built from the same
    /// config; a snapshot of another shape (envs, observation size, an opponent where there
    /// is none, another randomisation) is refused and nothing is changed.
    pub fn restore(&mut self, s: &EnvSnapshot) -> Result<(), EnvError> {
        let refuse = |why: String| Err(EnvError::Snapshot(why));
        if s.format != ENV_SNAPSHOT_FORMAT {
            return refuse(format!(
                "format {} (this build reads {ENV_SNAPSHOT_FORMAT})",
                s.format
            ));
        }
        if s.slots.len() != self.slots.len() || s.obs_dim != self.obs_dim {
            return refuse(format!(
                "{} envs of {} observations, this env has {} of {}",
                s.slots.len(),
                s.obs_dim,
                self.slots.len(),
                self.obs_dim
            ));
        }
        if s.observations.len() != self.observations.len()
            || s.observations.iter().any(|v| !v.is_finite())
        {
            return refuse("its observations are not this env's size or not finite".into());
        }
        let randomize = self.config.randomize.as_ref().map(|p| *p.value());
        let mut slots = self.slots.clone();
        for (i, (slot, snap)) in slots.iter_mut().zip(&s.slots).enumerate() {
            let at = |why: &str| EnvError::Snapshot(format!("env {i}: {why}"));
            slot.drones = snap.drones;
            slot.previous_action = snap.previous_action;
            slot.steps = snap.steps;
            slot.spawn_segment = snap.spawn_segment;
            slot.rng = snap.rng.generator();
            slot.perturb_rng = snap.perturb_rng.generator();
            slot.stats = snap.stats;
            slot.passes = snap.passes.clone();
            // Flown live from the restored state to the next spawn.
            slot.replay = None;
            match (&mut slot.opponent, &snap.opponent) {
                (None, None) => {}
                (Some(c), Some((memory, state))) => {
                    if !c.restore(memory, state) {
                        return Err(at("the opponent's state does not fit its controller"));
                    }
                }
                _ => return Err(at("an opponent in one of the env and the snapshot only")),
            }
            slot.perturbed = match (&randomize, &snap.perturbed) {
                (_, None) => None,
                (Some(p), Some(e)) => Some(p.restore(&self.world.preset, e)),
                (None, Some(_)) => return Err(at("randomised, but this env is not")),
            };
        }
        self.slots = slots;
        self.observations.clone_from(&s.observations);
        Ok(())
    }
}

/// `slot`'s state; an opponent whose flight is being replayed (`super::flight`) is recorded
/// with the controller bookkeeping of its last recorded step, as if it had been flown live.
fn slot_snapshot(slot: &Slot, flights: Option<&FlightBook>) -> SlotSnapshot {
    let replayed = slot
        .replay
        .and_then(|(key, flown)| flights?.memory_after(key, flown));
    SlotSnapshot {
        drones: slot.drones,
        opponent: slot.opponent.as_ref().map(|c| {
            let mut state = vec![0.0; c.policy_state().flat_len()];
            c.policy_state().write_flat(&mut state);
            (replayed.unwrap_or_else(|| c.memory()), state)
        }),
        previous_action: slot.previous_action,
        steps: slot.steps,
        spawn_segment: slot.spawn_segment,
        rng: RngSnapshot::of(&slot.rng),
        perturb_rng: RngSnapshot::of(&slot.perturb_rng),
        stats: slot.stats,
        passes: slot.passes.clone(),
        perturbed: slot.perturbed.as_ref().map(|e| e.snapshot()),
    }
}
