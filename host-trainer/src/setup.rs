//! What a run derives from its configuration, as methods of [`TrainConfig`]: the Table 1
//! row and its architecture, the dynamics preset, the observation spec recorded in the
//! run's blobs, the hover action, and the vectorised environment (sitl's [`VecEnv`], built
//! from [`TrainConfig::env`], sitl's own schema).

use crate::config::TrainConfig;
use crate::error::TrainError;
use firmware_core::observation::ObservationSpec;
use firmware_core::policy::{Architecture, TableRow};
use sitl::dynamics::Preset;
use sitl::env::{EnvConfig, VecEnv};

impl TrainConfig {
    /// The Table 1 row of `run.row` (A in a time trial, B to G in a race).
    pub fn table_row(&self) -> Result<TableRow, TrainError> {
        TableRow::from_letter(self.run.row).ok_or_else(|| {
            TrainError::Config(format!(
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
    pub fn preset(&self) -> Preset {
        self.env.preset()
    }

    /// The observation spec of the run: the paper's layout for its row (17 values for A, 20
    /// for B, 30 for the others) with `env.velocity_scale_mps`, folded by the track's mirror
    /// with `env.fold_mirror` ([`EnvConfig::observation_spec`]).
    pub fn observation_spec(&self) -> ObservationSpec {
        self.env_config(self.run.seed).observation_spec()
    }

    /// The action that holds hover with the run's preset and the paper's action map.
    pub fn hover_action(&self) -> f32 {
        firmware_core::vehicle::ActionMap::PAPER.action_for_rpm(self.preset().hover_rpm())
    }

    /// The environment's configuration, seeded with `seed`, its observation layout the one
    /// of `run.row` (row G's when the row is not a Table 1 row; validation refuses those).
    pub fn env_config(&self, seed: u64) -> EnvConfig {
        let layout = TableRow::from_letter(self.run.row).map_or(
            TableRow::G.observation_layout(),
            TableRow::observation_layout,
        );
        EnvConfig {
            layout,
            seed,
            ..self.env.clone()
        }
    }

    /// The environment of the run, seeded with `seed`: a time trial, or a race against
    /// `race.opponent` (read here; a blob that does not fly is refused).
    pub fn make_env(&self, seed: u64) -> Result<VecEnv, TrainError> {
        Ok(VecEnv::new(self.env_config(seed))?)
    }
}
