//! # neuvolex-tasks
//!
//! One task model for every brick stage, so that a stage is written once and runs in process
//! (rayon), in the service's actors, or on cluster workers, with results that compare bit for
//! bit.
//!
//! - A [`Task`] is a run of bricks (by grid index) of one stage, with its position in the run
//!   (outputs merge in that order) and a round (the iteration of an iterative stage).
//! - A [`Stage`] is the stage's parameters (serialisable, so a worker can rebuild it through a
//!   [`Registry`]), the pure function that runs one task and returns an output (a mergeable
//!   partial, or a summary of the bricks it wrote into the store), and the large read-only
//!   objects its workers need once per run ([`Blob`], e.g. a trained forest).
//! - An [`Executor`] runs a stage's tasks and reports each output as it arrives; the caller
//!   merges them ([`execute_ordered`] gives them back in task order). [`LocalExecutor`] is the
//!   in-process executor (rayon); the service's actors and the NATS cluster implement the same
//!   trait in their own crates.
//! - Which bricks of a stage are complete is recorded by the store's done markers
//!   (`neuvolex_bricks::done`, through the resumable writers of `BrickStore::resume_vectors`),
//!   so a re-run resumes.

#![warn(missing_docs)]

pub mod codec;
pub mod executor;
pub mod registry;
pub mod task;

pub use executor::{
    execute_ordered, DeadTask, Done, Event, Executor, LocalExecutor, RunEvent, RunReport,
};
pub use registry::{Blob, Blobs, Build, NoBlobs, Registry};
pub use task::{adapt_per_task, plan, DynStage, Stage, Task, TaskCtx, MAX_QUEUE_SHARE};

/// Errors of tasks and executors.
#[derive(Debug, thiserror::Error)]
pub enum TaskError {
    /// A task failed (the message names the brick and the problem).
    #[error("{0}")]
    Failed(String),
    /// A store error.
    #[error(transparent)]
    Bricks(#[from] neuvolex_bricks::BrickError),
    /// The run was cancelled.
    #[error("cancelled")]
    Cancelled,
    /// An output or parameter could not be encoded or decoded.
    #[error("codec: {0}")]
    Codec(String),
    /// A worker was asked for a stage it does not know.
    #[error("unknown stage '{0}' (this worker knows {1})")]
    UnknownStage(String, String),
    /// The engine (queue, object store) failed.
    #[error("{0}")]
    Engine(String),
}

impl From<neuvolex_formats::FormatError> for TaskError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        TaskError::Bricks(e.into())
    }
}

impl TaskError {
    /// A failure with a message.
    pub fn failed(e: impl std::fmt::Display) -> Self {
        TaskError::Failed(e.to_string())
    }
}

/// Result with [`TaskError`].
pub type Result<T, E = TaskError> = std::result::Result<T, E>;

/// A fingerprint of a file's bytes (CRC-32 and length), to check that every worker reads the
/// file the coordinator read (e.g. a trained model). `None` when the file is absent.
pub fn file_fingerprint(path: &std::path::Path) -> Option<String> {
    let b = std::fs::read(path).ok()?;
    Some(format!("{:08x}-{}", crc32fast::hash(&b), b.len()))
}

/// A stable 64-bit fingerprint of bytes (FNV-1a), for stage identities and blob keys.
pub fn fingerprint(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}
