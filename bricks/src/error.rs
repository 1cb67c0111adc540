//! Typed errors for every reader, writer and store operation.
//!
//! Every variant that concerns a file names it, so a user sees *which* input is bad and *why*.

use neuvolex_formats::FormatError;
use std::path::PathBuf;

/// Result alias used throughout the crate.
pub type Result<T, E = BrickError> = std::result::Result<T, E>;

/// Everything that can go wrong reading, ingesting or accessing a volume.
#[derive(Debug, thiserror::Error)]
pub enum BrickError {
    /// An operating-system I/O error while touching `path`.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory involved.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The volume contains NaN or infinite values and the policy is to reject them.
    #[error(
        "{path}: {count} non-finite voxel value(s) (NaN/Inf), first at voxel (x={x}, y={y}, z={z}); \
         re-run with --non-finite zero to replace them by 0"
    )]
    NonFinite {
        /// The file.
        path: PathBuf,
        /// Number of non-finite values in the slab where they were found.
        count: u64,
        /// First offending voxel x.
        x: usize,
        /// First offending voxel y.
        y: usize,
        /// First offending voxel z.
        z: usize,
    },
    /// A Zarr store whose metadata is missing or malformed.
    #[error("{path}: corrupt Zarr store: {detail}")]
    CorruptStore {
        /// The store (or node inside it).
        path: PathBuf,
        /// What is broken.
        detail: String,
    },
    /// A chunk (brick) that the store's metadata says must exist is absent.
    #[error("{path}: missing chunk {key} of array '{array}' (the store is incomplete or damaged)")]
    MissingChunk {
        /// The store.
        path: PathBuf,
        /// Array path inside the store.
        array: String,
        /// Chunk key.
        key: String,
    },
    /// A store that was not completely written (interrupted ingest).
    #[error("{path}: incomplete store: {detail}")]
    Incomplete {
        /// The store.
        path: PathBuf,
        /// Details.
        detail: String,
    },
    /// The output already exists and would be overwritten.
    #[error("{path}: already exists (refusing to overwrite; pass --force to replace it)")]
    Exists {
        /// The output path.
        path: PathBuf,
    },
    /// An argument that is out of range (e.g. a box outside the grid).
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// An error reported by zarrs.
    #[error("{path}: zarr error: {detail}")]
    Zarr {
        /// The store.
        path: PathBuf,
        /// The zarrs error text.
        detail: String,
    },
    /// A volume file could not be read or written.
    #[error(transparent)]
    Format(FormatError),
    /// The operation was cancelled by the caller.
    #[error("cancelled")]
    Cancelled,
    /// A storage operation failed (file system or object store).
    #[error("{path}: storage error: {detail}")]
    Storage {
        /// The object, file or store (a URL for object stores).
        path: PathBuf,
        /// What failed, with a hint where the cause is clear.
        detail: String,
    },
    /// Another process holds the store's writer lock.
    #[error("{path}: locked by another writer: {holder}{hint}")]
    Locked {
        /// The store.
        path: PathBuf,
        /// Who holds it (host, process id, since when).
        holder: String,
        /// How to proceed (for a stale lock: how to break it).
        hint: String,
    },
    /// Done markers (or a pending output) written for a different brick layout or stage
    /// identity (model version, parameters).
    #[error("{path}: {detail}")]
    StageMismatch {
        /// The markers or array.
        path: PathBuf,
        /// What was recorded, what this run is, and how to proceed.
        detail: String,
    },
}

impl BrickError {
    /// Wraps an I/O error with the path it concerns.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        BrickError::Io {
            path: path.into(),
            source,
        }
    }

    /// A zarrs error for the store at `path`.
    pub fn zarr(path: impl Into<PathBuf>, err: impl std::fmt::Display) -> Self {
        BrickError::Zarr {
            path: path.into(),
            detail: err.to_string(),
        }
    }

    /// A [`BrickError::StageMismatch`]: `what` was written for `found`, this run is `expected`.
    pub fn stage_mismatch(
        path: impl Into<PathBuf>,
        what: &str,
        found: &str,
        expected: &str,
        hint: &str,
    ) -> Self {
        BrickError::StageMismatch {
            path: path.into(),
            detail: format!("{what}: written for {found}, but this run is {expected}; {hint}"),
        }
    }

    /// A corrupt-store error for `path`.
    pub fn corrupt(path: impl Into<PathBuf>, detail: impl Into<String>) -> Self {
        BrickError::CorruptStore {
            path: path.into(),
            detail: detail.into(),
        }
    }
}

impl From<FormatError> for BrickError {
    /// A format error; a store error that travelled through a volume source
    /// ([`FormatError::Source`]) comes back as itself.
    fn from(e: FormatError) -> Self {
        match e {
            FormatError::Source(inner) => match inner.downcast::<BrickError>() {
                Ok(b) => *b,
                Err(other) => BrickError::Format(FormatError::Source(other)),
            },
            e => BrickError::Format(e),
        }
    }
}

impl From<BrickError> for FormatError {
    /// A store error raised inside a volume source (an OME-Zarr store read as a volume), kept
    /// whole ([`BrickError::from`] recovers it).
    fn from(e: BrickError) -> Self {
        match e {
            BrickError::Format(f) => f,
            e => FormatError::Source(Box::new(e)),
        }
    }
}
