//! Errors of the feature stage.

use std::path::PathBuf;

/// Everything that can fail while training or extracting features.
#[derive(Debug, thiserror::Error)]
pub enum FeatureError {
    /// A store or volume error.
    #[error(transparent)]
    Brick(#[from] neuvolex_bricks::BrickError),
    /// A model or checkpoint file that cannot be used.
    #[error("{path}: {detail}")]
    Checkpoint {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// Settings that cannot work.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// An I/O error on `path`.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// Stopped by the caller.
    #[error("cancelled")]
    Cancelled,
}

impl From<neuvolex_formats::FormatError> for FeatureError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        FeatureError::Brick(e.into())
    }
}

/// Result alias.
pub type Result<T, E = FeatureError> = std::result::Result<T, E>;
