//! Who flies a drone in the world: the classical baseline or a learned controller from a
//! blob, both firmware-core code, called once per control period.

use crate::dynamics::Preset;
use firmware_core::Controller;
use firmware_core::baseline::{BaselineConfig, BaselineController};
use firmware_core::blob::{AlignedBytes, Blob};
use firmware_core::track::Track;
use firmware_core::vehicle::{MotorCommand, VehicleState};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Anything that flies a drone: one motor command per control step.
pub trait Pilot {
    /// The command for the drone's current state; `opponent` is the other drone's state in a
    /// race (`None` in a time trial).
    fn command(&mut self, own: &VehicleState, opponent: Option<&VehicleState>) -> MotorCommand;
    /// A new flight from a spawn, targeting `target_gate`.
    fn reset(&mut self, target_gate: usize);
}

impl Pilot for BaselineController<'_> {
    fn command(&mut self, own: &VehicleState, _: Option<&VehicleState>) -> MotorCommand {
        self.step(own).0
    }
    fn reset(&mut self, target_gate: usize) {
        BaselineController::reset(self, target_gate);
    }
}

impl Pilot for Controller<'_> {
    fn command(&mut self, own: &VehicleState, opponent: Option<&VehicleState>) -> MotorCommand {
        self.step(own, opponent).command
    }
    fn reset(&mut self, target_gate: usize) {
        Controller::reset(self, target_gate);
    }
}

/// The baseline's tuning for a preset: its model must match the thrust the preset applies.
pub fn baseline_config_for(preset: &Preset) -> BaselineConfig {
    if preset.thrust_scale < 1.0 {
        BaselineConfig::paper()
    } else {
        BaselineConfig::nominal()
    }
}

/// Why a pilot could not be loaded.
#[derive(Debug)]
pub enum PilotError {
    /// The blob file could not be read.
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A `baseline:…` specification that does not parse.
    Baseline(String),
    /// The file is not a valid blob, or its policy cannot run here.
    Blob {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
}

impl core::fmt::Display for PilotError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Read { path, source } => write!(f, "cannot read {}: {source}", path.display()),
            Self::Baseline(why) => f.write_str(why),
            Self::Blob { path, reason } => {
                write!(
                    f,
                    "{} is not a usable policy blob: {reason}",
                    path.display()
                )
            }
        }
    }
}

impl std::error::Error for PilotError {}

/// A pilot that can be built many times (once per episode, on any thread): the baseline or a
/// validated blob held in memory.
#[derive(Clone, Debug)]
pub enum PilotSpec {
    /// The classical baseline controller with this tuning.
    Baseline(BaselineConfig),
    /// A learned policy: the blob's bytes (parsed and validated when loaded).
    Blob {
        /// Where it came from (for reports).
        name: String,
        /// The blob, 4-byte aligned.
        bytes: Arc<AlignedBytes>,
    },
}

impl PilotSpec {
    /// `"baseline"` (tuned for `preset`), `"baseline:CRUISE_MPS"` or
    /// `"baseline:CRUISE_MPS:OFFSET_M"` (cruise speed, line offset to the left), or the path
    /// of a blob file, read and validated now: a missing, corrupt or unsupported blob is an
    /// error here, not mid-race.
    pub fn load(what: &str, preset: &Preset) -> Result<Self, PilotError> {
        if let Some(rest) = what.strip_prefix("baseline") {
            if rest.is_empty() || rest.starts_with(':') {
                return parse_baseline(rest, preset).map(Self::Baseline);
            }
        }
        let path = Path::new(what);
        let raw = std::fs::read(path).map_err(|source| PilotError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_blob(what, &raw).map_err(|reason| PilotError::Blob {
            path: path.to_path_buf(),
            reason,
        })
    }

    /// A learned policy from blob bytes held in memory (e.g. a trainer's latest export),
    /// validated now; `name` labels it in reports.
    pub fn from_blob(name: &str, raw: &[u8]) -> Result<Self, String> {
        let bytes = AlignedBytes::new(raw);
        world_rate_controller(bytes.as_bytes(), Track::figure_eight())
            .map_err(|e| e.to_string())?;
        Ok(Self::Blob {
            name: name.to_string(),
            bytes: Arc::new(bytes),
        })
    }

    /// The int8 conversion of an f32 blob (`firmware_core::blob::convert_bytes`), labelled
    /// `name`; `None` for the baseline and for a blob already in int8.
    pub fn int8(&self, name: &str) -> Result<Option<Self>, String> {
        let Self::Blob { bytes, .. } = self else {
            return Ok(None);
        };
        let f32_blob = Blob::parse(bytes.as_bytes())
            .is_ok_and(|b| b.header().dtype == firmware_core::blob::WeightDtype::F32);
        if !f32_blob {
            return Ok(None);
        }
        let raw = firmware_core::blob::convert_bytes(
            bytes.as_bytes(),
            firmware_core::blob::WeightDtype::I8,
        )
        .map_err(|e| format!("int8 conversion: {e}"))?;
        Self::from_blob(name, &raw).map(Some)
    }

    /// A short name for reports: "baseline" or the blob's path and provenance name.
    pub fn describe(&self) -> String {
        match self {
            Self::Baseline(c) if c.lateral_offset_m != 0.0 => format!(
                "baseline ({:.1} m/s cruise, {:+.2} m offset)",
                c.cruise_speed_mps, c.lateral_offset_m
            ),
            Self::Baseline(c) => format!("baseline ({:.1} m/s cruise)", c.cruise_speed_mps),
            Self::Blob { name, bytes } => match Blob::parse(bytes.as_bytes()) {
                Ok(b) => format!("{name} ({})", b.header().provenance.name),
                Err(_) => name.clone(),
            },
        }
    }

    /// True when the pilot's policy observes an opponent (the 20- and 30-value layouts): it
    /// cannot fly a time trial.
    pub fn needs_opponent(&self) -> bool {
        match self {
            Self::Baseline(_) => false,
            Self::Blob { bytes, .. } => Blob::parse(bytes.as_bytes())
                .is_ok_and(|b| b.header().observation.layout.needs_opponent()),
        }
    }

    /// A fresh pilot (zeroed recurrent state) on `track`.
    pub fn build(&self, track: Track<'static>) -> Box<dyn Pilot + '_> {
        match self {
            Self::Baseline(c) => Box::new(BaselineController::new(*c, track)),
            Self::Blob { bytes, .. } => match world_rate_controller(bytes.as_bytes(), track) {
                Ok(c) => Box::new(c),
                // Validated in `load`; the bytes are immutable since.
                Err(_) => Box::new(Grounded),
            },
        }
    }
}

/// The controller of the blob `bytes` on `track`, run at the world's control period
/// ([`crate::world::CONTROL_PERIOD_NS`]): a recurrent policy trained at another period is
/// refused (its state would advance at another rate than it learned).
pub fn world_rate_controller<'w>(
    bytes: &'w [u8],
    track: Track<'w>,
) -> Result<Controller<'w>, firmware_core::controller::ControllerError> {
    let blob = Blob::parse(bytes)?;
    Controller::new(&blob, track, crate::world::CONTROL_PERIOD_NS)
}

/// The baseline's tuning from the `:CRUISE[:OFFSET]` suffix of a `baseline` pilot.
fn parse_baseline(suffix: &str, preset: &Preset) -> Result<BaselineConfig, PilotError> {
    let mut config = baseline_config_for(preset);
    let fields: Vec<&str> = suffix.split(':').skip(1).collect();
    let bad = |why: &str| {
        PilotError::Baseline(format!(
            "'baseline{suffix}': {why} (use baseline, baseline:CRUISE_MPS or baseline:CRUISE_MPS:OFFSET_M)"
        ))
    };
    if fields.len() > 2 {
        return Err(bad("too many fields"));
    }
    if let Some(v) = fields.first() {
        match v.parse::<f32>() {
            Ok(v) if v > 0.0 && v <= 30.0 => config.cruise_speed_mps = v,
            _ => return Err(bad("the cruise speed must be in (0, 30] m/s")),
        }
    }
    if let Some(v) = fields.get(1) {
        match v.parse::<f32>() {
            Ok(v) if v.abs() <= 0.6 => config.lateral_offset_m = v,
            _ => {
                return Err(bad(
                    "the line offset must be within ±0.6 m (the opening is ±0.8 m)",
                ));
            }
        }
    }
    Ok(config)
}

/// Motors off: what a controller that cannot run commands.
struct Grounded;

impl Pilot for Grounded {
    fn command(&mut self, _: &VehicleState, _: Option<&VehicleState>) -> MotorCommand {
        MotorCommand::STOP
    }
    fn reset(&mut self, _: usize) {}
}
