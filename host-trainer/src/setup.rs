//! What a run derives from its configuration, as methods of [`TrainConfig`]: the Table 1
//! row and its architecture, the dynamics preset, the observation spec recorded in the
//! run's blobs, the hover action, and the vectorised environment (sitl's [`VecEnv`]).

use crate::config::TrainConfig;
use crate::error::TrainError;
use firmware_core::blob::AlignedBytes;
use firmware_core::observation::ObservationSpec;
use firmware_core::policy::{Architecture, TableRow};
use sitl::dynamics::Preset;
use sitl::env::{EnvConfig, RaceConfig, VecEnv};
use sitl::referee::SpawnMode;

impl TrainConfig {
    /// The Table 1 row of `run.row` (A in a time trial, B to G in a race).
    pub fn table_row(&self) -> Result<TableRow, TrainError> {
        TableRow::from_letter(self.run.row).ok_or_else(|| {
            TrainError::Unsupported(format!(
                "run.row '{}': Table 1 has rows A to G",
                self.run.row
            ))
        })
    }

    /// The network architecture of the run's row.
    pub fn architecture(&self) -> Result<Architecture, TrainError> {
        Ok(Architecture::table1(self.table_row()?))
    }

    /// The dynamics preset `env.preset` names.
    pub fn preset(&self) -> Result<Preset, TrainError> {
        Preset::by_name(&self.env.preset)
            .ok_or_else(|| TrainError::Unsupported(format!("preset '{}'", self.env.preset)))
    }

    /// The observation spec of the run: the paper's layout for its row (17 values for A, 20
    /// for B, 30 for the others) with `env.velocity_scale_mps`, folded by the track's mirror
    /// with `env.fold_mirror`.
    pub fn observation_spec(&self) -> ObservationSpec {
        let layout = TableRow::from_letter(self.run.row).map_or(
            TableRow::G.observation_layout(),
            TableRow::observation_layout,
        );
        let mut spec = ObservationSpec::paper(layout);
        spec.velocity_scale_mps = self.env.velocity_scale_mps;
        spec.with_fold(self.env.fold_mirror)
    }

    /// The action that holds hover with the run's preset and the paper's action map.
    pub fn hover_action(&self) -> f32 {
        let preset = self.preset().unwrap_or_else(|_| Preset::paper());
        firmware_core::vehicle::ActionMap::PAPER.action_for_rpm(preset.hover_rpm())
    }

    /// The environment's configuration, seeded with `seed`: a time trial, or a race against
    /// `race.opponent` (read here).
    pub fn env_config(&self, seed: u64) -> Result<EnvConfig, TrainError> {
        let spawn = SpawnMode::by_name(&self.env.spawn)
            .ok_or_else(|| TrainError::Unsupported(format!("spawn '{}'", self.env.spawn)))?;
        Ok(EnvConfig {
            num_envs: self.env.num_envs,
            preset: self.preset()?,
            spawn,
            episode_s: self.env.episode_s,
            random_initial_episode_length: self.env.random_initial_episode_length,
            spawn_speed_mps: self.env.spawn_speed_mps,
            stage1_fraction: self.env.stage1_fraction,
            stage2_fraction: self.env.stage2_fraction,
            replay_fraction: self.env.replay_fraction,
            racing_line_fraction: self.env.racing_line_fraction,
            reward: self.reward,
            observation: self.observation_spec(),
            seed,
            race: match &self.race {
                None => None,
                Some(r) => {
                    let raw = std::fs::read(&r.opponent).map_err(|e| {
                        TrainError::Unsupported(format!("race.opponent '{}': {e}", r.opponent))
                    })?;
                    Some(RaceConfig {
                        opponent: AlignedBytes::new(&raw),
                        competition: r.competition,
                        competition_weight: r.competition_weight,
                    })
                }
            },
        })
    }

    /// The environment of the run, seeded with `seed` (an opponent blob that does not fly is
    /// refused here).
    pub fn make_env(&self, seed: u64) -> Result<VecEnv, TrainError> {
        VecEnv::new(self.env_config(seed)?).map_err(|e| TrainError::Unsupported(e.to_string()))
    }
}
