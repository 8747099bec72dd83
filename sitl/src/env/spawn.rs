//! How an env's episodes start: the spawn rule of an [`super::EnvConfig`] and the states
//! it replays (docs/DESIGN.md "Spawns").

use super::Slot;
use crate::perturb::{Perturbation, StartJitter};
use crate::referee::{SpawnMode, TrackProgress};
use crate::world::{Drone, World};
use firmware_core::math::Vec3;
use firmware_core::nn::ACTION_DIM;
use firmware_core::vehicle::{ActionMap, MotorCommand};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// States after the last [`PassReplay::LEN`] gate passes of one env, oldest overwritten.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub(super) struct PassReplay {
    states: [Option<(Drone, [f32; ACTION_DIM])>; PassReplay::LEN],
    next: usize,
}

impl PassReplay {
    const LEN: usize = 8;

    pub(super) fn record(&mut self, drone: Drone, previous_action: [f32; ACTION_DIM]) {
        self.states[self.next] = Some((drone, previous_action));
        self.next = (self.next + 1) % Self::LEN;
    }

    pub(super) fn draw(&self, rng: &mut ChaCha8Rng) -> Option<(Drone, [f32; ACTION_DIM])> {
        let filled = self.states.iter().filter(|s| s.is_some()).count();
        if filled == 0 {
            return None;
        }
        self.states[rng.random_range(0..filled)]
    }
}

/// How an env respawns.
#[derive(Clone, Copy, Debug)]
pub(super) struct SpawnRule {
    pub(super) mode: SpawnMode,
    pub(super) max_speed_mps: f32,
    pub(super) stage1_fraction: f32,
    pub(super) stage2_fraction: f32,
    pub(super) replay_fraction: f32,
    pub(super) race: bool,
    /// In a race, the share of spawns with the two drones' places swapped (the ego ahead).
    pub(super) ego_ahead_fraction: f32,
    /// The ego's domain randomisation (`EnvConfig::randomize`), drawn anew at every spawn.
    pub(super) randomize: Option<Perturbation>,
    /// The share of spawns `randomize` draws for (below 1, a draw decides; at 1, none).
    pub(super) randomize_share: f32,
    /// The jitter of the ego's start (`EnvConfig::spawn_jitter`), drawn at every spawn that
    /// is not a replay.
    pub(super) jitter: Option<StartJitter>,
}

/// A new episode in `slot`: a spawn drawn from its generator. In a race, the paper's stage-2 spawn
/// for both drones (with probability `ego_ahead_fraction` their places swapped, the ego 1 m
/// ahead), the opponent's controller reset to their gate. In a time trial, the
/// stage-1 spawn with probability `stage1_fraction`, otherwise `mode`'s, moving along its
/// heading at a speed drawn from [0, `max_speed_mps`] when that is positive. The previous
/// action zeroed. Otherwise, with probability `replay_fraction`, the state after one of the
/// env's recent gate passes, with that step's previous action; and of the spawns that are
/// neither replayed nor stage-1, a share `stage2_fraction` is the ego's or the opponent's
/// stage-2 spawn (at rest). A share of 0 draws no random number, so configs without it keep
/// their streams. With `jitter`, the ego's place (not a replay's) is then jittered.
///
/// With `randomize`, the ego's airframe and latency are then drawn (from the slot's own
/// randomisation generator: the spawns stay those of the unrandomised envs), and the
/// commands in flight are those its propellers turn at: stopped after a spawn at rest, the
/// replayed step's after a replay. Below a `randomize_share` of 1, a draw from the same
/// generator first decides whether this spawn is randomised at all.
pub(super) fn respawn(
    world: &World,
    progress: &TrackProgress,
    map: &ActionMap,
    rule: &SpawnRule,
    slot: &mut Slot,
) {
    let replayed = place(world, progress, rule, slot);
    if let Some(p) = &rule.randomize {
        if rule.randomize_share < 1.0 && slot.perturb_rng.random::<f32>() >= rule.randomize_share {
            slot.perturbed = None;
            return;
        }
        let mut drawn = p.episode(&world.preset, slot.perturb_rng.random::<u64>(), 0);
        drawn.restart_turning(if replayed {
            map.command(&slot.previous_action)
        } else {
            MotorCommand::STOP
        });
        slot.perturbed = Some(drawn);
    }
}

/// Places the drones of a new episode ([`respawn`]); true when the ego's state is a replay.
fn place(world: &World, progress: &TrackProgress, rule: &SpawnRule, slot: &mut Slot) -> bool {
    slot.replay = None;
    if !rule.race && rule.replay_fraction > 0.0 && slot.rng.random::<f32>() < rule.replay_fraction {
        if let Some((drone, previous_action)) = slot.passes.draw(&mut slot.rng) {
            slot.drones[0] = drone;
            slot.spawn_segment[0] = progress.spawn_segment(drone.progress.target);
            slot.previous_action = previous_action;
            slot.steps = 0;
            return true;
        }
    }
    let line = progress.line();
    let stage1 =
        !rule.race && rule.stage1_fraction > 0.0 && slot.rng.random::<f32>() < rule.stage1_fraction;
    let stage2 = !rule.race
        && !stage1
        && rule.stage2_fraction > 0.0
        && slot.rng.random::<f32>() < rule.stage2_fraction;
    let mode = if stage1 { SpawnMode::Stage1 } else { rule.mode };
    let [mut spawn, opponent] = if stage2 {
        let [ego, opponent] = SpawnMode::Stage2.draw(&world.track, line, &mut slot.rng);
        let s = if slot.rng.random::<bool>() {
            ego
        } else {
            opponent
        };
        [s, s]
    } else {
        let [ego, opponent] = mode.draw(&world.track, line, &mut slot.rng);
        let swap = rule.race
            && rule.ego_ahead_fraction > 0.0
            && slot.rng.random::<f32>() < rule.ego_ahead_fraction;
        // The opponent's spawn place, the key of its recorded flight (`super::flight`).
        slot.replay = rule
            .race
            .then_some((2 * opponent.target_gate + usize::from(swap), 0));
        if swap {
            [opponent, ego]
        } else {
            [ego, opponent]
        }
    };
    if rule.max_speed_mps > 0.0 && !stage1 && !stage2 && !rule.race {
        let speed = slot.rng.random_range(0.0..rule.max_speed_mps);
        let forward = spawn.state.attitude.rotate(Vec3::new(1.0, 0.0, 0.0));
        spawn.state.velocity_mps = forward.scale(speed);
    }
    if let Some(j) = &rule.jitter {
        spawn.state = j.apply(&spawn.state, &mut slot.rng);
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
    false
}
