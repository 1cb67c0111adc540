//! Typed errors of the file-format readers and writers.
//!
//! Every variant that concerns a file names it, so a user sees *which* input is bad and *why*.

use std::path::PathBuf;

/// Result with [`FormatError`].
pub type Result<T, E = FormatError> = std::result::Result<T, E>;

/// An error reading or writing a volume file.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// An I/O error on a named file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The file holds fewer voxel bytes than its header promises.
    #[error("{path}: truncated: expected {expected} bytes of voxel data, found {found}")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Bytes the header implies.
        expected: u64,
        /// Bytes present.
        found: u64,
    },
    /// The file is larger than its header implies, or a size field disagrees.
    #[error("{path}: size mismatch: {detail}")]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// What disagrees.
        detail: String,
    },
    /// The header cannot be parsed or holds an impossible value.
    #[error("{path}: bad header: {detail}")]
    BadHeader {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The voxel type is not supported.
    #[error("{path}: unsupported data type {dtype}")]
    UnknownDtype {
        /// The file.
        path: PathBuf,
        /// The type as the header names it.
        dtype: String,
    },
    /// Dimensions are zero, negative, overflow or are too large.
    #[error("{path}: invalid dimensions: {detail}")]
    BadDims {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// A gzip stream is corrupt.
    #[error("{path}: corrupt gzip stream: {detail}")]
    CorruptGzip {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        detail: String,
    },
    /// The file's format is not recognised.
    #[error("{path}: unrecognised volume format: {detail}")]
    UnknownFormat {
        /// The file.
        path: PathBuf,
        /// What was expected.
        detail: String,
    },
    /// Two volumes that must share a grid do not.
    #[error("{path}: grid mismatch: {detail}")]
    GridMismatch {
        /// The second volume.
        path: PathBuf,
        /// What differs.
        detail: String,
    },
    /// A caller passed an invalid argument (a slab outside the volume, ...).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A volume source outside this crate (an OME-Zarr store, a generator) failed; the error
    /// is kept whole so its owner can recover it.
    #[error(transparent)]
    Source(Box<dyn std::error::Error + Send + Sync>),
}

impl FormatError {
    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        FormatError::Io {
            path: path.into(),
            source,
        }
    }

    /// A bad header in `path`.
    pub fn header(path: impl Into<PathBuf>, detail: impl Into<String>) -> Self {
        FormatError::BadHeader {
            path: path.into(),
            detail: detail.into(),
        }
    }
}
