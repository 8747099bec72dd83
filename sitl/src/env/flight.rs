//! The race opponent's recorded flights. The opponent is a frozen time-trial policy: it does
//! not observe the ego, every race spawns it at rest at one of a few places (before each
//! gate, at the opponent's or, with the places swapped, at the ego's stage-2 spawn), and a
//! contact with the ego ends the episode. So its flight from each spawn is the same in every
//! episode until the episode ends: it is flown once, alone, by the same controller, dynamics
//! and rules, and replayed step by step instead of being flown again in every env (the
//! opponent's inference was most of a race step). A replayed step is the live one bit for
//! bit (`sitl/tests/env.rs`); where a flight has no recorded step (an episode made longer
//! from outside), the env flies the opponent live again from the recorded state.

use crate::world::{Drone, DroneStep, World};
use firmware_core::Controller;
use firmware_core::controller::ControllerMemory;
use std::sync::OnceLock;

/// The most steps a flight records (2 min at 50 Hz, about 1.4 MB per flight): an episode
/// longer than that flies its opponent live from there, so an env's memory does not grow
/// with its episode length.
pub const MAX_RECORDED_STEPS: u32 = 6_000;

/// One recorded step of the opponent: its drone after the step (gate progress included),
/// what its own rules said of the step, and its controller's bookkeeping after it.
#[derive(Clone, Debug)]
pub(super) struct FlightStep {
    pub(super) drone: Drone,
    pub(super) step: DroneStep,
    pub(super) memory: ControllerMemory,
}

/// The opponent's flight from one spawn: its steps until its own crash, or at most the
/// episode's length.
#[derive(Debug)]
pub(super) struct Flight {
    /// The drone it starts as (a slot whose opponent spawned otherwise flies live).
    spawn: Drone,
    steps: Vec<FlightStep>,
}

impl Flight {
    /// The flight of `controller` (reset to its spawn) from `spawn`, `max_steps` long (at
    /// most [`MAX_RECORDED_STEPS`]) or until its own crash; each step is `VecEnv::step`'s for the opponent: the command from
    /// the state before the step, the world's preset, the world's own rules.
    fn record(
        world: &World,
        spawn: Drone,
        controller: &Controller<'static>,
        max_steps: u32,
    ) -> Self {
        let mut c = controller.clone();
        let mut drone = spawn;
        let mut steps = Vec::new();
        for _ in 0..max_steps.min(MAX_RECORDED_STEPS) {
            let command = c.step(&drone.body.state, None).command;
            let from = drone.position_m();
            drone.body.step(&world.preset, &command, world.dt_s);
            let [step] = world.judge(core::array::from_mut(&mut drone), &[from]);
            steps.push(FlightStep {
                drone,
                step,
                memory: c.memory(),
            });
            if step.crash.is_some() {
                break;
            }
        }
        Self { spawn, steps }
    }

    /// Step `k` (from 0) of the flight, if recorded.
    pub(super) fn step(&self, k: u32) -> Option<&FlightStep> {
        self.steps.get(k as usize)
    }
}

/// Every spawn's flight, each recorded the first time a race needs it.
#[derive(Debug)]
pub(super) struct FlightBook {
    flights: Vec<OnceLock<Flight>>,
    max_steps: u32,
}

impl FlightBook {
    /// A book for `spawns` spawn places and episodes of `max_steps`.
    pub(super) fn new(spawns: usize, max_steps: u32) -> Self {
        Self {
            flights: (0..spawns).map(|_| OnceLock::new()).collect(),
            max_steps,
        }
    }

    /// The flight from spawn place `key`, recorded from `opponent` and `controller` (a slot
    /// just spawned there) if it is the first; `None` for a key out of range or a slot whose
    /// opponent does not start as the recorded flight did.
    pub(super) fn flight(
        &self,
        key: usize,
        world: &World,
        opponent: &Drone,
        controller: &Controller<'static>,
    ) -> Option<&Flight> {
        let flight = self
            .flights
            .get(key)?
            .get_or_init(|| Flight::record(world, *opponent, controller, self.max_steps));
        (flight.spawn == *opponent).then_some(flight)
    }

    /// The flight from spawn place `key`, if recorded.
    pub(super) fn recorded(&self, key: usize) -> Option<&Flight> {
        self.flights.get(key)?.get()
    }

    /// The opponent controller's bookkeeping after `flown` recorded steps from spawn place
    /// `key` (`None` before the first step, or where nothing is recorded).
    pub(super) fn memory_after(&self, key: usize, flown: u32) -> Option<ControllerMemory> {
        Some(self.recorded(key)?.step(flown.checked_sub(1)?)?.memory)
    }
}
