//! Why a training run stopped early: every host-side failure of the trainer as one error
//! type with the path or the reason, never swallowed.

use std::path::{Path, PathBuf};

/// Why a run stopped early.
#[derive(Debug)]
pub enum TrainError {
    /// A file could not be read or written.
    Io(PathBuf, std::io::Error),
    /// The output directory holds a run and `--resume` was not given, or there is nothing
    /// to resume.
    OutDir(String),
    /// A checkpoint could not be used.
    Checkpoint(String),
    /// The configuration cannot be trained (a row outside Table 1).
    Config(String),
    /// The environment could not be built (sitl's reason: a field, the opponent's path).
    Env(sitl::env::EnvError),
    /// A blob the config names (`what`: a teacher, a student) cannot be used, and why.
    Blob {
        /// The config's field and the blob's path.
        what: String,
        /// Why not.
        reason: String,
    },
    /// The policy and the environment disagree while flying (observation sizes, an
    /// observation the policy cannot act on, a malformed step).
    Rollout(String),
    /// A network could not be exported or carried between its forms (blob payload, int8
    /// grid, `burn` module).
    Export(String),
}

impl core::fmt::Display for TrainError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Io(p, e) => write!(f, "{}: {e}", p.display()),
            Self::Env(e) => write!(f, "the environment: {e}"),
            Self::Blob { what, reason } => write!(f, "{what}: {reason}"),
            Self::OutDir(m)
            | Self::Checkpoint(m)
            | Self::Config(m)
            | Self::Rollout(m)
            | Self::Export(m) => f.write_str(m),
        }
    }
}

impl From<sitl::env::EnvError> for TrainError {
    fn from(e: sitl::env::EnvError) -> Self {
        Self::Env(e)
    }
}

impl std::error::Error for TrainError {}

/// Maps an I/O error on `path` to [`TrainError::Io`].
pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |e| TrainError::Io(path.to_path_buf(), e)
}
