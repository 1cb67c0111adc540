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
    /// Bytes the task read from the brick store.
    pub const READ: &str = "Nvx-Read";
    /// Bytes the task wrote to the brick store.
    pub const WRITTEN: &str = "Nvx-Written";
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
        // While this run lasts its coordinator answers on the run's subject, so that a later
        // coordinator of the same stage and parameters leaves its tasks alone.
        let mut presence = e
            .client
            .subscribe(engine::run_subject(&run))
            .await
            .map_err(|x| js("run presence", x))?;
        let responder = {
            let client = e.client.clone();
            AbortOnDrop(tokio::spawn(async move {
                while let Some(m) = presence.next().await {
                    if let Some(reply) = m.reply {
                        let _ = client.publish(reply, "alive".into()).await;
                    }
                }
            }))
        };
        let task_stream =
            e.js.get_stream(TASKS)
                .await
                .map_err(|x| js("task stream", x))?;
        purge_dead_runs(e, &task_stream, stage.name(), key).await;
        let result_stream =
            e.js.get_stream(RESULTS)
                .await
                .map_err(|x| js("result stream", x))?;
        let mut results = open_results(&result_stream, &run, 1).await?;
        // The last result read (stream sequence), to reopen the results after a server restart,
        // and how many were read.
        let mut last_result = 0u64;
        let mut results_read = 0u64;
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
        let mut task_to_seq: HashMap<u32, u64> = HashMap::new();
        let all: Vec<&Task> = tasks.iter().collect();
        let enqueue = Enqueue {
            e,
            subject: &subject,
            run: &run,
            stage: stage.name(),
            key,
            params: &params,
        };
        for (i, seq, bytes) in enqueue.send(&all, 0).await? {
            report.queue_bytes += bytes;
            seq_to_task.insert(seq, i);
            task_to_seq.insert(i, seq);
        }
        tracing::debug!(run, tasks = tasks.len(), subject, "enqueued");
        let by_index: BTreeMap<u32, &Task> = tasks.iter().map(|t| (t.index, t)).collect();
        let mut resolved: HashMap<u32, ()> = HashMap::new();
        let mut workers: HashMap<String, Instant> = HashMap::new();
        let mut last_worker = Instant::now();
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        let mut ticks = 0u64;
        // Since when the queue holds fewer tasks than have no result (and how many had one).
        let mut short: Option<(Instant, usize)> = None;
        let mut requeues = 0u32;
        // Tasks given up by the max-deliveries advisory: they stay in the queue.
        let mut lingering = 0usize;
        let params_text = params.clone();
        let dead = |d: &DeadTask| engine::DeadLetter {
            run: run.clone(),
            stage: stage.name().to_string(),
            params: params_text.clone(),
            unix: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|t| t.as_secs())
                .unwrap_or(0),
            task: d.clone(),
        };
        while resolved.len() < tasks.len() {
            tokio::select! {
                m = results.next() => match m {
                    Some(Ok(m)) => {
                        if let Ok(i) = m.info() {
                            last_result = last_result.max(i.stream_sequence);
                        }
                        results_read += 1;
                        let m: async_nats::Message = m.into();
                        report.queue_bytes += m.payload.len() as u64;
                        let Some(idx) = header(&m, h::TASK).and_then(|v| v.parse::<u32>().ok()) else { continue };
                        let worker = header(&m, h::WORKER).unwrap_or("?").to_string();
                        workers.insert(worker.clone(), Instant::now());
                        last_worker = Instant::now();
                        if !by_index.contains_key(&idx) {
                            continue;
                        }
                        if resolved.contains_key(&idx) {
                            // A late result: the task was redelivered and completed elsewhere
                            // (tasks are idempotent, so it carries the same output).
                            report.duplicates += 1;
                            tracing::debug!(task = idx, worker, "duplicate result ignored");
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
                            if let Err(x) = e.record_dead(&dead(&d)).await {
                                tracing::warn!("cannot keep the dead letter of task {idx}: {x}");
                            }
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
                        let read: u64 = header(&m, h::READ).and_then(|v| v.parse().ok()).unwrap_or(0);
                        let written: u64 = header(&m, h::WRITTEN).and_then(|v| v.parse().ok()).unwrap_or(0);
                        report.store_read_bytes += read;
                        report.store_written_bytes += written;
                        resolved.insert(idx, ());
                        report.completed += 1;
                        report.work_seconds += work;
                        report.queue_seconds += overhead;
                        report.bricks_skipped += skipped;
                        *report.per_worker.entry(worker.clone()).or_default() += 1;
                        on(Event::Done(Done { task: idx, worker, output, work_seconds: work, skipped }));
                    }
                    // The server restarted (its ephemeral consumers are gone) or the read failed:
                    // read on from the last result.
                    end => {
                        match end {
                            Some(Err(x)) => tracing::warn!("results: {x} (reopening)"),
                            _ => tracing::warn!("results: the consumer ended (reopening)"),
                        }
                        tokio::time::sleep(Duration::from_millis(250)).await;
                        match open_results(&result_stream, &run, last_result + 1).await {
                            Ok(r) => results = r,
                            Err(x) => tracing::warn!("results: {x} (retrying)"),
                        }
                    }
                },
                a = advisories.next() => {
                    let Some(a) = a else { continue };
                    let v: serde_json::Value = serde_json::from_slice(&a.payload).unwrap_or_default();
                    let seq = v["stream_seq"].as_u64().unwrap_or(0);
                    if let Some(&idx) = seq_to_task.get(&seq) {
                        if resolved.insert(idx, ()).is_none() {
                            lingering += 1;
                            let d = DeadTask {
                                task: idx,
                                bricks: by_index[&idx].bricks.clone(),
                                deliveries: v["deliveries"].as_u64().unwrap_or(0),
                                error: "no worker completed it: every delivery timed out (worker lost, or the task outlives its heartbeats)".into(),
                                worker: "-".into(),
                            };
                            if let Err(x) = e.record_dead(&dead(&d)).await {
                                tracing::warn!("cannot keep the dead letter of task {idx}: {x}");
                            }
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
                    ticks += 1;
                    // Every 2 s: does the queue still hold every task without a result?
                    // Results are stored before their task is acked, so a task that is neither
                    // queued nor answered for a while was lost: a restarted server that had not
                    // written it to disk yet, or a purge. The coordinator owns its tasks and
                    // enqueues the lost ones again (a few times; they are idempotent).
                    if ticks.is_multiple_of(8) && resolved.len() < tasks.len() {
                        let unresolved = tasks.len() - resolved.len();
                        match queued(&task_stream, &subject).await {
                            Some(n) if (n as usize).saturating_sub(lingering) < unresolved => {
                                let (since, at) = *short.get_or_insert((Instant::now(), resolved.len()));
                                if at != resolved.len() {
                                    short = Some((Instant::now(), resolved.len()));
                                } else if since.elapsed() > LOST_GRACE {
                                    short = None;
                                    // Unread results first: a reader stalled by a server restart
                                    // is reopened (those tasks were not lost).
                                    let stored = queued(&result_stream, &engine::result_subject(&run)).await;
                                    if stored.is_none_or(|n| n > results_read) {
                                        tracing::warn!("results: {} stored, {results_read} read; reopening the reader", stored.map_or("?".into(), |n| n.to_string()));
                                        match open_results(&result_stream, &run, last_result + 1).await {
                                            Ok(r) => results = r,
                                            Err(x) => tracing::warn!("results: {x} (retrying)"),
                                        }
                                        continue;
                                    }
                                    let mut lost = Vec::new();
                                    for (&i, t) in &by_index {
                                        if resolved.contains_key(&i) {
                                            continue;
                                        }
                                        let gone = match task_to_seq.get(&i) {
                                            Some(&seq) => matches!(
                                                task_stream.get_raw_message(seq).await,
                                                Err(x) if x.kind() == async_nats::jetstream::stream::LastRawMessageErrorKind::NoMessageFound
                                            ),
                                            None => true,
                                        };
                                        if gone {
                                            lost.push(*t);
                                        }
                                    }
                                    if !lost.is_empty() {
                                        requeues += 1;
                                        let which: Vec<u32> = lost.iter().map(|t| t.index).take(20).collect();
                                        if requeues > MAX_REQUEUES {
                                            return Err(js(
                                                "run",
                                                format!(
                                                    "{} of {} tasks left the queue without a result again after {MAX_REQUEUES} \
                                                     re-enqueues (tasks {which:?}): something purges them; re-run the \
                                                     command (done markers keep what completed)",
                                                    lost.len(),
                                                    tasks.len()
                                                ),
                                            ));
                                        }
                                        tracing::warn!(
                                            "{} tasks left the queue without a result (tasks {which:?}); enqueuing them again",
                                            lost.len()
                                        );
                                        report.requeued += lost.len() as u64;
                                        for (i, seq, bytes) in enqueue.send(&lost, requeues).await? {
                                            report.queue_bytes += bytes;
                                            seq_to_task.insert(seq, i);
                                            task_to_seq.insert(i, seq);
                                        }
                                    }
                                }
                            }
                            _ => short = None,
                        }
                    }
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
        drop(responder);
        report.seconds = t0.elapsed().as_secs_f64();
        Ok(report)
    }
}

/// How long the queue may hold fewer tasks than have no result, without any result arriving,
/// before the coordinator looks for lost tasks.
const LOST_GRACE: Duration = Duration::from_secs(5);

/// Re-enqueues of lost tasks before a run gives up.
const MAX_REQUEUES: u32 = 3;

/// Publishes a run's tasks.
struct Enqueue<'a> {
    e: &'a Engine,
    subject: &'a str,
    run: &'a str,
    stage: &'a str,
    key: u64,
    params: &'a str,
}

impl Enqueue<'_> {
    /// Publishes `tasks` (attempt 0 first, then re-enqueues), waits until JetStream stored
    /// them, and returns (task index, stream sequence, bytes) of each.
    async fn send(
        &self,
        tasks: &[&Task],
        attempt: u32,
    ) -> Result<Vec<(u32, u64, u64)>, ClusterError> {
        let mut acks = Vec::with_capacity(tasks.len());
        for t in tasks {
            let payload = codec::encode(&TaskMsg {
                run: self.run.to_string(),
                stage: self.stage.to_string(),
                key: self.key,
                params: self.params.to_string(),
                task: (*t).clone(),
            })?;
            let bytes = payload.len() as u64;
            let ack = self
                .e
                .js
                .send_publish(
                    self.subject.to_string(),
                    async_nats::jetstream::message::PublishMessage::build()
                        .payload(payload.into())
                        .message_id(format!("{}.{}.{attempt}", self.run, t.index)),
                )
                .await
                .map_err(|x| js("publish task", x))?;
            acks.push((t.index, ack, bytes));
        }
        let mut out = Vec::with_capacity(acks.len());
        for (i, a, bytes) in acks {
            let a = a.await.map_err(|x| js("publish task", x))?;
            out.push((i, a.sequence, bytes));
        }
        Ok(out)
    }
}

/// Aborts a spawned task when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// The results of `run` from stream sequence `from` on (an ordered consumer).
async fn open_results(
    stream: &async_nats::jetstream::stream::Stream,
    run: &str,
    from: u64,
) -> Result<consumer::pull::Ordered, ClusterError> {
    stream
        .create_consumer(consumer::pull::OrderedConfig {
            filter_subject: engine::result_subject(run),
            deliver_policy: if from <= 1 {
                consumer::DeliverPolicy::All
            } else {
                consumer::DeliverPolicy::ByStartSequence {
                    start_sequence: from,
                }
            },
            ..Default::default()
        })
        .await
        .map_err(|x| js("results consumer", x))?
        .messages()
        .await
        .map_err(|x| js("results consumer", x))
}

/// Messages of `subject` in `stream` (`None` if the server did not say).
async fn queued(stream: &async_nats::jetstream::stream::Stream, subject: &str) -> Option<u64> {
    let mut info = stream.info_with_subjects(subject).await.ok()?;
    let mut n = 0u64;
    while let Some(r) = info.next().await {
        n += r.ok()?.1 as u64;
    }
    Some(n)
}

/// Purges the queued tasks of earlier runs of the same stage and parameters whose coordinator
/// is gone (killed: this run re-plans what is not done yet). Tasks of a run whose coordinator
/// still answers stay: two identical runs at once both finish.
async fn purge_dead_runs(
    e: &Engine,
    stream: &async_nats::jetstream::stream::Stream,
    stage: &str,
    key: u64,
) {
    let filter = format!("nvx.task.{stage}.{key:016x}.>");
    let mut runs = std::collections::BTreeSet::new();
    match stream.info_with_subjects(&filter).await {
        Ok(mut info) => {
            while let Some(r) = info.next().await {
                match r {
                    Ok((subject, _)) => {
                        if let Some(run) = subject.rsplit('.').next() {
                            runs.insert(run.to_string());
                        }
                    }
                    Err(x) => {
                        tracing::warn!("cannot list queued tasks {filter}: {x}");
                        break;
                    }
                }
            }
        }
        Err(x) => tracing::warn!("cannot list queued tasks {filter}: {x}"),
    }
    for run in runs {
        if e.run_alive(&run).await {
            tracing::info!(
                run,
                "a run of the same stage and parameters is in progress: its tasks stay"
            );
            continue;
        }
        let subject = engine::task_subject(stage, key, &run);
        match stream.purge().filter(&subject).await {
            Ok(p) => tracing::info!(
                run,
                purged = p.purged,
                "purged the tasks of a run whose coordinator is gone"
            ),
            Err(x) => tracing::warn!("cannot purge stale tasks {subject}: {x}"),
        }
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
