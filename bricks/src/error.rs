//! Typed errors for every reader, writer and store operation.
//!
//! Every variant that concerns a file names it, so a user sees *which* input is bad and *why*.

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
    /// The file ended before the header said it would.
    #[error("{path}: truncated: expected {expected} bytes of voxel data, found {found}")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Bytes the header promised.
        expected: u64,
        /// Bytes actually present.
        found: u64,
    },
    /// The file has more or fewer bytes than its declared grid needs.
    #[error("{path}: size mismatch: {detail}")]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// What was expected and what was found.
        detail: String,
    },
    /// A header could not be parsed.
    #[error("{path}: bad header: {detail}")]
    BadHeader {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        detail: String,
    },
    /// A voxel type this project does not read.
    #[error("{path}: unsupported data type {dtype}")]
    UnknownDtype {
        /// The file.
        path: PathBuf,
        /// The type as the file names it.
        dtype: String,
    },
    /// Zero, negative, overflowing or absurd grid dimensions.
    #[error("{path}: invalid dimensions: {detail}")]
    BadDims {
        /// The file.
        path: PathBuf,
        /// Which dimension and why.
        detail: String,
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
    /// gzip data that cannot be decompressed.
    #[error("{path}: corrupt gzip stream: {detail}")]
    CorruptGzip {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        detail: String,
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
    /// Two volumes that must share a grid do not.
    #[error("{path}: grid mismatch: {detail}")]
    GridMismatch {
        /// The offending (usually label) volume.
        path: PathBuf,
        /// Which property differs.
        detail: String,
    },
    /// The output already exists and would be overwritten.
    #[error("{path}: already exists (refusing to overwrite; pass --force to replace it)")]
    Exists {
        /// The output path.
        path: PathBuf,
    },
    /// A format this project does not recognise.
    #[error("{path}: unrecognised volume format: {detail}")]
    UnknownFormat {
        /// The file.
        path: PathBuf,
        /// Hint.
        detail: String,
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

    /// A header error for `path`.
    pub fn header(path: impl Into<PathBuf>, detail: impl Into<String>) -> Self {
        BrickError::BadHeader {
            path: path.into(),
            detail: detail.into(),
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
