//! The coordinator: publishes a stage's tasks to the work queue, gathers their outputs from the
//! results stream, and reports dead letters, per-worker counts and queue overhead.

use crate::engine::{self, Engine, EngineConfig, ALIVE, CANCEL, RESULTS, TASKS};
use crate::{js, ClusterError};
use async_nats::jetstream::consumer;
use futures_util::StreamExt;
use neuvolex_tasks::executor::CancelPoll;
use neuvolex_tasks::{codec, fingerprint, DeadTask, Done, Event, Executor, RunReport, Stage, Task};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What a task message carries.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct TaskMsg {
    /// The run.
    pub run: String,
    /// Stage name.
    pub stage: String,
    /// Fingerprint of the stage name and parameters (workers cache built stages by it).
    pub key: u64,
    /// The stage's parameters as JSON text.
    pub params: String,
    /// The task.
    pub task: Task,
}

/// Header names of result messages.
pub(crate) mod h {
    pub const KIND: &str = "Nvx-Kind";
    pub const TASK: &str = "Nvx-Task";
    pub const WORKER: &str = "Nvx-Worker";
    pub const WORK: &str = "Nvx-Work";
    pub const OVERHEAD: &str = "Nvx-Overhead";
    pub const SKIPPED: &str = "Nvx-Skipped";
    pub const DELIVERED: &str = "Nvx-Delivered";
    /// A result too large for one message: the key of the blob that holds it.
    pub const BLOB: &str = "Nvx-Blob";
}

/// Results larger than this go through the blob store (NATS messages are limited to 1 MiB
/// by default), the message carrying only the blob's key.
pub(crate) const INLINE_RESULT_MAX: usize = 256 * 1024;

struct Inner {
    rt: Option<tokio::runtime::Runtime>,
    engine: Engine,
}

impl Drop for Inner {
    fn drop(&mut self) {
        if let Some(rt) = self.rt.take() {
            rt.shutdown_background();
        }
    }
}

/// Runs stages on NATS workers. Clones share one connection.
#[derive(Clone)]
pub struct ClusterExecutor {
    inner: Arc<Inner>,
    poll: Option<CancelPoll>,
}

/// A fresh run id (alphanumeric, unique per process and time).
fn run_id() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static N: AtomicU64 = AtomicU64::new(0);
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    format!(
        "r{t:x}p{:x}n{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

fn header<'a>(m: &'a async_nats::Message, k: &str) -> Option<&'a str> {
    m.headers
        .as_ref()
        .and_then(|h| h.get(k))
        .map(|v| v.as_str())
}

impl std::fmt::Debug for ClusterExecutor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClusterExecutor")
            .field("url", &self.engine().cfg.url)
            .finish()
    }
}

impl ClusterExecutor {
    /// Connects to the cluster's NATS server (bounded by `cfg.connect_timeout`).
    pub fn connect(cfg: EngineConfig) -> Result<Self, ClusterError> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(|e| js("runtime", e))?;
        let engine = rt.block_on(Engine::connect(cfg, "neuvolex-coordinator"))?;
        Ok(ClusterExecutor {
            inner: Arc::new(Inner {
                rt: Some(rt),
                engine,
            }),
            poll: None,
        })
    }

    /// A clone that also stops when `poll` returns true (checked four times a second):
    /// pending tasks are purged and running ones told to stop.
    pub fn with_cancel(&self, poll: CancelPoll) -> Self {
        ClusterExecutor {
            inner: self.inner.clone(),
            poll: Some(poll),
        }
    }

    /// The engine.
    pub fn engine(&self) -> &Engine {
        &self.inner.engine
    }

    /// Runs a future on the executor's runtime.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.inner
            .rt
            .as_ref()
            .expect("runtime lives until drop")
            .block_on(f)
    }

    /// Tells every worker to finish its task and exit.
    pub fn stop_workers(&self) -> Result<(), ClusterError> {
        self.block_on(self.engine().stop_workers())
    }

    async fn run<S: Stage>(
        &self,
        stage: &S,
        tasks: &[Task],
        on: &mut dyn FnMut(Event<S::Output>),
    ) -> Result<RunReport, ClusterError> {
        let t0 = Instant::now();
        let e = self.engine();
        let mut report = RunReport {
            stage: stage.name().to_string(),
            executor: self.describe(),
            tasks: tasks.len(),
            ..Default::default()
        };
        if tasks.is_empty() {
            return Ok(report);
        }
        for b in stage.blobs() {
            e.put_blob(&b.key, &b.bytes).await?;
            report.queue_bytes += b.bytes.len() as u64;
        }
        let run = run_id();
        let params = stage.params().to_string();
        let key = fingerprint(format!("{}\n{params}", stage.name()).as_bytes());
        // Tasks of an earlier run of the same stage and parameters (a coordinator that was
        // killed) are redundant: this run re-plans what is not done yet.
        let task_stream =
            e.js.get_stream(TASKS)
                .await
                .map_err(|x| js("task stream", x))?;
        let prefix = format!("nvx.task.{}.{key:016x}.>", stage.name());
        if let Err(x) = task_stream.purge().filter(&prefix).await {
            tracing::warn!("cannot purge stale tasks {prefix}: {x}");
        }
        let result_stream =
            e.js.get_stream(RESULTS)
                .await
                .map_err(|x| js("result stream", x))?;
        let results = result_stream
            .create_consumer(consumer::pull::OrderedConfig {
                filter_subject: engine::result_subject(&run),
                deliver_policy: consumer::DeliverPolicy::All,
                ..Default::default()
            })
            .await
            .map_err(|x| js("results consumer", x))?;
        let mut results = results
            .messages()
            .await
            .map_err(|x| js("results consumer", x))?;
        let mut advisories = e
            .client
            .subscribe(format!(
                "$JS.EVENT.ADVISORY.CONSUMER.MAX_DELIVERIES.{TASKS}.{}",
                engine::CONSUMER
            ))
            .await
            .map_err(|x| js("advisories", x))?;
        let mut alive = e
            .client
            .subscribe(ALIVE)
            .await
            .map_err(|x| js("worker presence", x))?;
        let subject = engine::task_subject(stage.name(), key, &run);
        let mut seq_to_task: HashMap<u64, u32> = HashMap::new();
        let mut acks = Vec::with_capacity(tasks.len());
        for t in tasks {
            let payload = codec::encode(&TaskMsg {
                run: run.clone(),
                stage: stage.name().to_string(),
                key,
                params: params.clone(),
                task: t.clone(),
            })?;
            report.queue_bytes += payload.len() as u64;
            let ack =
                e.js.send_publish(
                    subject.clone(),
                    async_nats::jetstream::message::PublishMessage::build()
                        .payload(payload.into())
                        .message_id(format!("{run}.{}", t.index)),
                )
                .await
                .map_err(|x| js("publish task", x))?;
            acks.push((t.index, ack));
        }
        for (i, a) in acks {
            let a = a.await.map_err(|x| js("publish task", x))?;
            seq_to_task.insert(a.sequence, i);
        }
        tracing::debug!(run, tasks = tasks.len(), subject, "enqueued");
        let by_index: BTreeMap<u32, &Task> = tasks.iter().map(|t| (t.index, t)).collect();
        let mut resolved: HashMap<u32, ()> = HashMap::new();
        let mut workers: HashMap<String, Instant> = HashMap::new();
        let mut last_worker = Instant::now();
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        while resolved.len() < tasks.len() {
            tokio::select! {
                m = results.next() => match m {
                    Some(Ok(m)) => {
                        let m: async_nats::Message = m.into();
                        report.queue_bytes += m.payload.len() as u64;
                        let Some(idx) = header(&m, h::TASK).and_then(|v| v.parse::<u32>().ok()) else { continue };
                        let worker = header(&m, h::WORKER).unwrap_or("?").to_string();
                        workers.insert(worker.clone(), Instant::now());
                        last_worker = Instant::now();
                        if resolved.contains_key(&idx) || !by_index.contains_key(&idx) {
                            continue;
                        }
                        let delivered: u64 = header(&m, h::DELIVERED).and_then(|v| v.parse().ok()).unwrap_or(1);
                        report.redeliveries += delivered.saturating_sub(1);
                        if header(&m, h::KIND) == Some("dead") {
                            resolved.insert(idx, ());
                            let d = DeadTask {
                                task: idx,
                                bricks: by_index[&idx].bricks.clone(),
                                deliveries: delivered,
                                error: String::from_utf8_lossy(&m.payload).into_owned(),
                                worker,
                            };
                            report.dead.push(d.clone());
                            on(Event::Dead(d));
                            continue;
                        }
                        let output: S::Output = match header(&m, h::BLOB) {
                            Some(key) => {
                                let b = e.get_blob(key).await?;
                                report.queue_bytes += b.len() as u64;
                                e.delete_blob(key).await;
                                codec::decode(&b)?
                            }
                            None => codec::decode(&m.payload)?,
                        };
                        let work: f64 = header(&m, h::WORK).and_then(|v| v.parse().ok()).unwrap_or(0.0);
                        let overhead: f64 = header(&m, h::OVERHEAD).and_then(|v| v.parse().ok()).unwrap_or(0.0);
                        let skipped: u64 = header(&m, h::SKIPPED).and_then(|v| v.parse().ok()).unwrap_or(0);
                        resolved.insert(idx, ());
                        report.completed += 1;
                        report.work_seconds += work;
                        report.queue_seconds += overhead;
                        report.bricks_skipped += skipped;
                        *report.per_worker.entry(worker.clone()).or_default() += 1;
                        on(Event::Done(Done { task: idx, worker, output, work_seconds: work, skipped }));
                    }
                    Some(Err(x)) => tracing::warn!("results: {x} (resuming)"),
                    None => return Err(js("results", "the results consumer ended")),
                },
                a = advisories.next() => {
                    let Some(a) = a else { continue };
                    let v: serde_json::Value = serde_json::from_slice(&a.payload).unwrap_or_default();
                    let seq = v["stream_seq"].as_u64().unwrap_or(0);
                    if let Some(&idx) = seq_to_task.get(&seq) {
                        if resolved.insert(idx, ()).is_none() {
                            let d = DeadTask {
                                task: idx,
                                bricks: by_index[&idx].bricks.clone(),
                                deliveries: v["deliveries"].as_u64().unwrap_or(0),
                                error: "no worker completed it: every delivery timed out (worker lost, or the task outlives its heartbeats)".into(),
                                worker: "-".into(),
                            };
                            report.dead.push(d.clone());
                            on(Event::Dead(d));
                        }
                    }
                }
                w = alive.next() => {
                    if let Some(w) = w {
                        workers.insert(String::from_utf8_lossy(&w.payload).into_owned(), Instant::now());
                        last_worker = Instant::now();
                    }
                }
                _ = tick.tick() => {
                    if self.poll.as_ref().is_some_and(|p| p()) {
                        report.cancelled = true;
                        if let Err(x) = task_stream.purge().filter(&subject).await {
                            tracing::warn!("cannot purge cancelled tasks: {x}");
                        }
                        let _ = e.client.publish(CANCEL, run.clone().into()).await;
                        break;
                    }
                    if last_worker.elapsed() > e.cfg.no_worker_timeout {
                        let _ = task_stream.purge().filter(&subject).await;
                        return Err(ClusterError::Connect {
                            url: e.cfg.url.clone(),
                            detail: format!(
                                "no worker answered for {:.0} s ({} of {} tasks done); start workers with `neuvolex worker --nats {}`",
                                e.cfg.no_worker_timeout.as_secs_f64(),
                                resolved.len(),
                                tasks.len(),
                                e.cfg.url
                            ),
                        });
                    }
                }
            }
        }
        if let Err(x) = result_stream
            .purge()
            .filter(engine::result_subject(&run))
            .await
        {
            tracing::debug!("cannot purge results of {run}: {x}");
        }
        report.seconds = t0.elapsed().as_secs_f64();
        Ok(report)
    }
}

impl Executor for ClusterExecutor {
    fn describe(&self) -> String {
        format!("cluster {}", self.engine().cfg.url)
    }

    fn execute<S: Stage>(
        &self,
        stage: &S,
        tasks: &[Task],
        on: &mut dyn FnMut(Event<S::Output>),
    ) -> neuvolex_tasks::Result<RunReport> {
        Ok(self.block_on(self.run(stage, tasks, on))?)
    }

    fn forget_blobs(&self, keys: &[String]) {
        let e = self.engine();
        self.block_on(async {
            for k in keys {
                e.delete_blob(k).await;
            }
        });
    }
}
