//! Why an environment could not be built or stepped.

use super::EnvConfigError;

/// The environment could not be built.
#[derive(Clone, Debug, PartialEq)]
pub enum EnvError {
    /// A field of the config is out of its range.
    Config(EnvConfigError),
    /// The opponent's blob cannot be read.
    ReadOpponent {
        /// The blob's path.
        path: std::path::PathBuf,
        /// What the file system said (`NotFound` for a missing file).
        kind: std::io::ErrorKind,
        /// Its message.
        message: String,
    },
    /// The opponent's blob does not validate or cannot be flown as stage 2's opponent, or
    /// the observation is folded ([`firmware_core::mirror`]) on a track without the symmetry.
    Unflyable(String),
    /// A snapshot ([`super::VecEnv::restore`]) that is not of an env of this shape.
    Snapshot(String),
}

impl core::fmt::Display for EnvError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Config(e) => e.fmt(f),
            Self::ReadOpponent { path, message, .. } => {
                write!(f, "opponent '{}': {message}", path.display())
            }
            Self::Unflyable(m) => f.write_str(m),
            Self::Snapshot(m) => write!(f, "the env snapshot does not fit: {m}"),
        }
    }
}

impl std::error::Error for EnvError {}

impl From<EnvConfigError> for EnvError {
    fn from(e: EnvConfigError) -> Self {
        Self::Config(e)
    }
}

/// The actions given to [`super::VecEnv::step`] do not have `num_envs × 4` values.
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

/// The counts given to [`super::VecEnv::set_episode_steps`] are not one per env.
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
