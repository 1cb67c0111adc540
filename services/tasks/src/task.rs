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

/// Largest share of a task's time the queue's round trip may take in an iterative stage before
/// [`adapt_per_task`] batches more bricks per task (half the 5 % bound, for headroom).
pub const MAX_QUEUE_SHARE: f64 = 0.025;

/// Bricks per task for the next round of an iterative stage (k-means passes), from the last
/// round's report over `bricks` bricks: the smallest batch whose measured queue overhead per
/// task is at most [`MAX_QUEUE_SHARE`] of its work, but never fewer than `current` and never so
/// many that a worker seen in the last round would get fewer than two tasks. A report without
/// queue time (the in-process executor) keeps `current`. Tasks stay runs of bricks in order,
/// so outputs merged in task order are the same whatever the batch.
pub fn adapt_per_task(current: usize, last: &crate::RunReport, bricks: usize) -> usize {
    let current = current.max(1);
    if bricks == 0
        || last.completed == 0
        || !(last.queue_seconds > 0.0 && last.work_seconds > 0.0)
        || !(last.queue_seconds.is_finite() && last.work_seconds.is_finite())
    {
        return current;
    }
    let queue_per_task = last.queue_seconds / last.completed as f64;
    let work_per_brick = last.work_seconds / bricks as f64;
    let want = (queue_per_task / (MAX_QUEUE_SHARE * work_per_brick)).ceil();
    let workers = last.per_worker.len().max(1);
    let cap = bricks.div_ceil(2 * workers).max(1);
    let want = if want.is_finite() && want > 0.0 {
        (want as usize).min(cap)
    } else {
        current
    };
    current.max(want)
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

#[cfg(test)]
mod adapt_tests {
    use super::*;
    use crate::RunReport;

    fn report(tasks: usize, work: f64, queue: f64, workers: usize) -> RunReport {
        RunReport {
            completed: tasks,
            tasks,
            work_seconds: work,
            queue_seconds: queue,
            per_worker: (0..workers).map(|w| (format!("w{w}"), 1)).collect(),
            ..RunReport::default()
        }
    }

    #[test]
    fn batches_grow_until_the_queue_is_a_small_share() {
        // 512 one-brick tasks of 10 ms with a 1.2 ms round trip (12 %): 5 bricks a task bring
        // it to 2.4 %.
        let r = report(512, 5.12, 512.0 * 1.2e-3, 4);
        assert_eq!(adapt_per_task(1, &r, 512), 5);
        // Already batched enough: kept.
        assert_eq!(adapt_per_task(8, &r, 512), 8);
    }

    #[test]
    fn batches_keep_two_tasks_per_worker() {
        // 8 bricks on 2 workers: at most 2 bricks a task, whatever the overhead.
        let r = report(8, 0.08, 8.0 * 5e-3, 2);
        assert_eq!(adapt_per_task(1, &r, 8), 2);
        // One brick per worker pair or fewer: unbatched.
        let r = report(8, 0.08, 8.0 * 5e-3, 4);
        assert_eq!(adapt_per_task(1, &r, 8), 1);
    }

    #[test]
    fn in_process_and_degenerate_reports_keep_the_batch() {
        assert_eq!(adapt_per_task(3, &report(8, 1.0, 0.0, 1), 8), 3);
        assert_eq!(adapt_per_task(0, &report(0, 0.0, 0.0, 0), 8), 1);
        assert_eq!(adapt_per_task(2, &report(8, f64::NAN, 1.0, 1), 8), 2);
        assert_eq!(adapt_per_task(2, &report(8, 1.0, 1.0, 1), 0), 2);
    }
}
