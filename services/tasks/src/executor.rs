//! Executors: what runs a stage's tasks. The in-process one lives here; the service's actors
//! and the cluster implement the same trait.

use crate::{Result, Stage, Task, TaskCtx, TaskError};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// A task's output as it arrives.
#[derive(Debug)]
pub struct Done<O> {
    /// The task's index in its run.
    pub task: u32,
    /// Who ran it (`local`, or the worker's name).
    pub worker: String,
    /// Its output.
    pub output: O,
    /// Seconds the task's work took on the worker.
    pub work_seconds: f64,
    /// Bricks it skipped because they were already done.
    pub skipped: u64,
}

/// A task that could not be completed: the run reports it and finishes the rest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeadTask {
    /// The task's index.
    pub task: u32,
    /// Its bricks.
    pub bricks: Vec<[usize; 3]>,
    /// How often it was delivered.
    pub deliveries: u64,
    /// The last error.
    pub error: String,
    /// The worker that gave up on it.
    pub worker: String,
}

/// What an executor reports while a stage runs.
#[derive(Debug)]
pub enum Event<O> {
    /// A task finished.
    Done(Done<O>),
    /// A task was given up (dead-lettered).
    Dead(DeadTask),
}

/// Progress of a pipeline (one stream for the CLI's bars, the service's events and tests).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum RunEvent {
    /// A stage begins with `total` tasks.
    Stage {
        /// Stage name.
        name: String,
        /// Tasks in the stage.
        total: u64,
    },
    /// A task finished.
    Task {
        /// Tasks finished in the stage.
        done: u64,
        /// Tasks in the stage.
        total: u64,
        /// Who ran it.
        worker: String,
    },
    /// Something worth telling.
    Message(String),
}

/// What a stage's run did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RunReport {
    /// Stage name.
    pub stage: String,
    /// Executor (`local`, `actors`, `cluster nats://...`).
    pub executor: String,
    /// Tasks in the run.
    pub tasks: usize,
    /// Tasks completed.
    pub completed: usize,
    /// Bricks skipped inside tasks because their done marker was set.
    pub bricks_skipped: u64,
    /// Tasks completed per worker.
    pub per_worker: BTreeMap<String, u64>,
    /// Tasks given up after their last delivery.
    pub dead: Vec<DeadTask>,
    /// Deliveries beyond the first (redelivered after a lost worker, a timeout or a failure).
    pub redeliveries: u64,
    /// Wall-clock seconds of the run.
    pub seconds: f64,
    /// Seconds of task work, summed over tasks.
    pub work_seconds: f64,
    /// Queue overhead summed over tasks: enqueue to result, minus the work (cluster only).
    pub queue_seconds: f64,
    /// Bytes of task messages and results through the queue (cluster only).
    pub queue_bytes: u64,
    /// Bytes the tasks read from the brick store (wherever they ran).
    pub store_read_bytes: u64,
    /// Bytes the tasks wrote to the brick store.
    pub store_written_bytes: u64,
    /// Results of tasks already resolved that arrived again and were ignored (the late result
    /// of a worker whose task was redelivered meanwhile; cluster only).
    pub duplicates: u64,
    /// Tasks the coordinator enqueued again because they left the queue without a result (a
    /// restarted queue server that had not stored them yet, or a purge; cluster only).
    pub requeued: u64,
    /// True when the run stopped because it was cancelled.
    pub cancelled: bool,
}

impl RunReport {
    /// Adds another run's counts (e.g. the rounds of an iterative stage).
    pub fn absorb(&mut self, o: &RunReport) {
        if self.stage.is_empty() {
            self.stage = o.stage.clone();
            self.executor = o.executor.clone();
        }
        self.tasks += o.tasks;
        self.completed += o.completed;
        self.bricks_skipped += o.bricks_skipped;
        for (w, n) in &o.per_worker {
            *self.per_worker.entry(w.clone()).or_default() += n;
        }
        self.dead.extend(o.dead.iter().cloned());
        self.redeliveries += o.redeliveries;
        self.seconds += o.seconds;
        self.work_seconds += o.work_seconds;
        self.queue_seconds += o.queue_seconds;
        self.queue_bytes += o.queue_bytes;
        self.store_read_bytes += o.store_read_bytes;
        self.store_written_bytes += o.store_written_bytes;
        self.duplicates += o.duplicates;
        self.requeued += o.requeued;
        self.cancelled |= o.cancelled;
    }
}

/// Runs the tasks of a stage.
pub trait Executor: Sync {
    /// A short description (`local`, `cluster nats://...`).
    fn describe(&self) -> String;

    /// Runs `tasks` of `stage`, calling `on` as each completes or is given up (in any order).
    /// A task's error never aborts the run: it comes back as [`Event::Dead`] and in the report.
    fn execute<S: Stage>(
        &self,
        stage: &S,
        tasks: &[Task],
        on: &mut dyn FnMut(Event<S::Output>),
    ) -> Result<RunReport>;

    /// Drops blobs a finished run published that no later run needs (e.g. the model of a
    /// training round). Executors without a blob store do nothing.
    fn forget_blobs(&self, _keys: &[String]) {}
}

/// Runs `tasks` and returns their outputs in task order (`None` for a dead task), calling
/// `progress` as tasks finish.
pub fn execute_ordered<E: Executor + ?Sized, S: Stage>(
    exec: &E,
    stage: &S,
    tasks: &[Task],
    progress: &mut dyn FnMut(RunEvent),
) -> Result<(Vec<Option<S::Output>>, RunReport)> {
    let pos: BTreeMap<u32, usize> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| (t.index, i))
        .collect();
    let mut out: Vec<Option<S::Output>> = (0..tasks.len()).map(|_| None).collect();
    let total = tasks.len() as u64;
    progress(RunEvent::Stage {
        name: stage.name().to_string(),
        total,
    });
    let mut done = 0u64;
    let report = exec.execute(stage, tasks, &mut |e| match e {
        Event::Done(d) => {
            if let Some(&i) = pos.get(&d.task) {
                if out[i].is_none() {
                    done += 1;
                    progress(RunEvent::Task {
                        done,
                        total,
                        worker: d.worker.clone(),
                    });
                }
                out[i] = Some(d.output);
            }
        }
        Event::Dead(t) => progress(RunEvent::Message(format!(
            "task {} (bricks {:?}) given up after {} deliveries: {}",
            t.task, t.bricks, t.deliveries, t.error
        ))),
    })?;
    Ok((out, report))
}

/// A cancellation poll: true once the run should stop (e.g. a newer generation exists).
pub type CancelPoll = Arc<dyn Fn() -> bool + Send + Sync>;

/// The in-process executor: tasks in parallel on rayon's pool.
#[derive(Clone, Default)]
pub struct LocalExecutor {
    cancel: Arc<AtomicBool>,
    poll: Option<CancelPoll>,
    label: Option<String>,
}

impl LocalExecutor {
    /// An executor on the global rayon pool.
    pub fn new() -> Self {
        Self::default()
    }

    /// Also stops when `poll` returns true (checked before every task and between bricks).
    pub fn with_cancel(mut self, poll: CancelPoll) -> Self {
        self.poll = Some(poll);
        self
    }

    /// Names the executor in reports (e.g. `actors`).
    pub fn labelled(mut self, label: &str) -> Self {
        self.label = Some(label.to_string());
        self
    }

    /// Cancels the runs in progress.
    pub fn cancel(&self) {
        self.cancel.store(true, Ordering::SeqCst);
    }

    fn cancelled(&self) -> bool {
        if let Some(p) = &self.poll {
            if p() {
                self.cancel.store(true, Ordering::SeqCst);
            }
        }
        self.cancel.load(Ordering::SeqCst)
    }
}

impl Executor for LocalExecutor {
    fn describe(&self) -> String {
        self.label.clone().unwrap_or_else(|| "local".into())
    }

    fn execute<S: Stage>(
        &self,
        stage: &S,
        tasks: &[Task],
        on: &mut dyn FnMut(Event<S::Output>),
    ) -> Result<RunReport> {
        let t0 = Instant::now();
        let io0 = neuvolex_bricks::store_io();
        let who = self.describe();
        let mut report = RunReport {
            stage: stage.name().to_string(),
            executor: who.clone(),
            tasks: tasks.len(),
            ..Default::default()
        };
        type Msg<O> = (u32, Result<O>, f64, u64);
        let (tx, rx) = std::sync::mpsc::channel::<Msg<S::Output>>();
        std::thread::scope(|s| {
            s.spawn(move || {
                // Tasks start in their order (each thread takes the next one), so a caller
                // that lists the bricks it wants first gets them first; rayon's splitting
                // would start the second half at once.
                let next = std::sync::atomic::AtomicUsize::new(0);
                let workers = rayon::current_num_threads().clamp(1, tasks.len().max(1));
                (0..workers)
                    .into_par_iter()
                    .for_each_with(tx, |tx, _| loop {
                        let i = next.fetch_add(1, Ordering::SeqCst);
                        let Some(t) = tasks.get(i) else { break };
                        if self.cancelled() {
                            break;
                        }
                        let ctx = TaskCtx::new(&self.cancel);
                        let t1 = Instant::now();
                        let r = stage.run(t, &ctx);
                        let _ = tx.send((t.index, r, t1.elapsed().as_secs_f64(), ctx.skipped()));
                    });
            });
            for (index, r, secs, skipped) in rx {
                match r {
                    Ok(output) => {
                        report.completed += 1;
                        report.work_seconds += secs;
                        report.bricks_skipped += skipped;
                        *report.per_worker.entry(who.clone()).or_default() += 1;
                        on(Event::Done(Done {
                            task: index,
                            worker: who.clone(),
                            output,
                            work_seconds: secs,
                            skipped,
                        }));
                    }
                    Err(TaskError::Cancelled) => report.cancelled = true,
                    Err(e) => {
                        let bricks = tasks
                            .iter()
                            .find(|t| t.index == index)
                            .map(|t| t.bricks.clone())
                            .unwrap_or_default();
                        let d = DeadTask {
                            task: index,
                            bricks,
                            deliveries: 1,
                            error: e.to_string(),
                            worker: who.clone(),
                        };
                        report.dead.push(d.clone());
                        on(Event::Dead(d));
                    }
                }
            }
        });
        report.cancelled |= self.cancel.load(Ordering::SeqCst);
        report.seconds = t0.elapsed().as_secs_f64();
        // The process's store traffic during the run (the tasks', and whatever else ran in
        // this process meanwhile).
        let io = neuvolex_bricks::store_io().since(&io0);
        report.store_read_bytes = io.bytes_read;
        report.store_written_bytes = io.bytes_written;
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Sum;
    impl Stage for Sum {
        type Output = Vec<f64>;
        fn name(&self) -> &'static str {
            "sum"
        }
        fn params(&self) -> serde_json::Value {
            serde_json::Value::Null
        }
        fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> Result<Vec<f64>> {
            ctx.check()?;
            if task.bricks.contains(&[9, 9, 9]) {
                return Err(TaskError::Failed("brick [9, 9, 9] is poisoned".into()));
            }
            Ok(task.bricks.iter().map(|b| 0.1 * b[0] as f64).collect())
        }
    }

    #[test]
    fn outputs_come_back_in_task_order_and_failures_are_reported() {
        let mut bricks: Vec<[usize; 3]> = (0..100).map(|i| [i, 0, 0]).collect();
        bricks.push([9, 9, 9]);
        let tasks = crate::plan(&bricks, 7, 0);
        assert_eq!(tasks.len(), 15);
        let mut events = Vec::new();
        let (out, rep) =
            execute_ordered(&LocalExecutor::new(), &Sum, &tasks, &mut |e| events.push(e)).unwrap();
        assert_eq!(rep.completed, 14);
        assert_eq!(rep.dead.len(), 1);
        assert_eq!(rep.dead[0].bricks.last(), Some(&[9, 9, 9]));
        assert!(out[14].is_none());
        // The last task holds bricks 98, 99 and the poisoned one: all of it is reported dead.
        let flat: Vec<f64> = out.into_iter().flatten().flatten().collect();
        assert_eq!(flat, (0..98).map(|i| 0.1 * i as f64).collect::<Vec<_>>());
        assert!(events
            .iter()
            .any(|e| matches!(e, RunEvent::Message(m) if m.contains("poisoned"))));
    }

    #[test]
    fn a_cancelled_run_stops_and_says_so() {
        let bricks: Vec<[usize; 3]> = (0..50).map(|i| [i, 0, 0]).collect();
        let tasks = crate::plan(&bricks, 1, 0);
        let ex = LocalExecutor::new().with_cancel(Arc::new(|| true));
        let rep = ex.execute(&Sum, &tasks, &mut |_| {}).unwrap();
        assert!(rep.cancelled);
        assert_eq!(rep.completed, 0);
    }
}
