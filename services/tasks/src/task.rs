//! Tasks and stages.

use crate::{codec, Result, TaskError};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// A run of bricks of one stage.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Task {
    /// Position in its run: outputs merge in this order.
    pub index: u32,
    /// Round of an iterative stage (the k-means iteration; 0 otherwise).
    pub round: u32,
    /// Bricks by grid index `[x, y, z]`, in the order the stage visits them.
    pub bricks: Vec<[usize; 3]>,
}

/// Splits `bricks` (in order) into tasks of at most `per_task` bricks each.
pub fn plan(bricks: &[[usize; 3]], per_task: usize, round: u32) -> Vec<Task> {
    bricks
        .chunks(per_task.max(1))
        .enumerate()
        .map(|(i, c)| Task {
            index: i as u32,
            round,
            bricks: c.to_vec(),
        })
        .collect()
}

/// What a running task can see: whether its run was cancelled, and a counter of bricks it
/// skipped because their done marker was set.
pub struct TaskCtx<'a> {
    cancel: &'a AtomicBool,
    skipped: AtomicU64,
}

impl<'a> TaskCtx<'a> {
    /// A context cancelled through `cancel`.
    pub fn new(cancel: &'a AtomicBool) -> Self {
        TaskCtx {
            cancel,
            skipped: AtomicU64::new(0),
        }
    }

    /// `Err(Cancelled)` once the run was cancelled (stages call it between bricks).
    pub fn check(&self) -> Result<()> {
        if self.cancel.load(Ordering::Relaxed) {
            Err(TaskError::Cancelled)
        } else {
            Ok(())
        }
    }

    /// Counts `n` bricks skipped as already done.
    pub fn skip(&self, n: u64) {
        self.skipped.fetch_add(n, Ordering::Relaxed);
    }

    /// Bricks skipped so far.
    pub fn skipped(&self) -> u64 {
        self.skipped.load(Ordering::Relaxed)
    }
}

/// A brick stage: parameters, the pure per-task function, and its output type.
///
/// `run` must be idempotent: running a task twice (a redelivery after a lost worker) writes
/// the same bytes and returns the same output.
pub trait Stage: Send + Sync {
    /// What one task returns: a mergeable partial, or a summary of what it wrote.
    type Output: Serialize + DeserializeOwned + Send + 'static;
    /// The name workers dispatch on (see [`crate::Registry`]).
    fn name(&self) -> &'static str;
    /// The parameters from which a worker rebuilds this stage.
    fn params(&self) -> serde_json::Value;
    /// Large read-only objects workers fetch once per run (e.g. the trained forest).
    fn blobs(&self) -> Vec<crate::Blob> {
        Vec::new()
    }
    /// Runs one task.
    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> Result<Self::Output>;
}

/// A stage with its output type erased: what a worker runs.
pub trait DynStage: Send + Sync {
    /// The stage's name.
    fn stage_name(&self) -> &'static str;
    /// Runs one task and encodes its output ([`codec::encode`]).
    fn run_encoded(&self, task: &Task, ctx: &TaskCtx<'_>) -> Result<Vec<u8>>;
}

impl<S: Stage> DynStage for S {
    fn stage_name(&self) -> &'static str {
        self.name()
    }

    fn run_encoded(&self, task: &Task, ctx: &TaskCtx<'_>) -> Result<Vec<u8>> {
        codec::encode(&self.run(task, ctx)?)
    }
}
