//! # neuvolex-cluster
//!
//! Brick stages on an existing distributed engine, NATS JetStream, over a shared brick store
//! (a shared POSIX path or an object store): no home-made scheduler.
//!
//! - **Queue.** Tasks go to a stream with WorkQueue retention (`NVX_TASKS`); every worker pulls
//!   from one durable pull consumer (`workers`) with explicit acks, an AckWait that running
//!   tasks extend with in-progress heartbeats, and MaxDeliver. A task that fails on its last
//!   delivery is terminated and a dead-letter record names it; a task whose worker vanished on
//!   every delivery is caught from JetStream's max-deliveries advisory. Either way the run
//!   reports it and finishes the rest.
//! - **Results.** A worker publishes a task's output (the stage's mergeable partial, encoded
//!   with [`neuvolex_tasks::codec`]) to the results stream (`NVX_RESULTS`) and only then acks
//!   the task, so no result is lost; a redelivered task publishes an identical duplicate that
//!   the coordinator ignores (tasks are idempotent).
//! - **Blobs.** Large read-only inputs (the trained forest) are published once per run to a
//!   JetStream object store (`nvx-blobs`) and fetched once per worker.
//! - [`ClusterExecutor`] is the coordinator side of [`neuvolex_tasks::Executor`]; [`worker`]
//!   serves tasks until told to stop; [`registry`] lists the stages a worker can run.

#![warn(missing_docs)]

pub mod engine;
pub mod executor;
pub mod registry;
pub mod worker;

pub use engine::{Engine, EngineConfig};
pub use executor::ClusterExecutor;
pub use registry::standard_registry;
pub use worker::{serve, WorkerEvent, WorkerOptions};

/// Errors of the cluster engine.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    /// The NATS server cannot be reached or refused us.
    #[error("NATS at {url}: {detail}")]
    Connect {
        /// The server URL.
        url: String,
        /// What went wrong.
        detail: String,
    },
    /// A JetStream operation failed.
    #[error("NATS JetStream ({what}): {detail}")]
    JetStream {
        /// Which operation.
        what: String,
        /// What went wrong.
        detail: String,
    },
    /// A task error.
    #[error(transparent)]
    Task(#[from] neuvolex_tasks::TaskError),
}

impl From<ClusterError> for neuvolex_tasks::TaskError {
    fn from(e: ClusterError) -> Self {
        match e {
            ClusterError::Task(t) => t,
            o => neuvolex_tasks::TaskError::Engine(o.to_string()),
        }
    }
}

/// Result with [`ClusterError`].
pub type Result<T, E = ClusterError> = std::result::Result<T, E>;

/// A JetStream error while doing `what`.
pub(crate) fn js(what: &str, e: impl std::fmt::Display) -> ClusterError {
    ClusterError::JetStream {
        what: what.to_string(),
        detail: e.to_string(),
    }
}
