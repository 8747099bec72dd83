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
    /// The configuration cannot be trained by this trainer.
    Unsupported(String),
    /// The trained network could not be exported.
    Export(String),
}

impl core::fmt::Display for TrainError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Io(p, e) => write!(f, "{}: {e}", p.display()),
            Self::OutDir(m) | Self::Checkpoint(m) | Self::Unsupported(m) | Self::Export(m) => {
                f.write_str(m)
            }
        }
    }
}

impl std::error::Error for TrainError {}

/// Maps an I/O error on `path` to [`TrainError::Io`].
pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |e| TrainError::Io(path.to_path_buf(), e)
}
