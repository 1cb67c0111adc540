//! The worker: pulls tasks from the shared consumer, runs them, publishes their outputs, acks.

use crate::engine::{Engine, EngineConfig, ALIVE, CANCEL, STOP};
use crate::executor::{h, TaskMsg};
use crate::{js, ClusterError, Result};
use async_nats::jetstream::AckKind;
use futures_util::StreamExt;
use neuvolex_tasks::{codec, Blobs, DynStage, Registry, TaskCtx, TaskError};
use std::collections::{HashMap, HashSet, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Worker settings.
#[derive(Debug, Clone, Default)]
pub struct WorkerOptions {
    /// Name shown in the coordinator's per-worker counts (default: host-pid).
    pub name: Option<String>,
    /// Stores given as relative paths resolve under this folder, and local stores outside it
    /// are refused.
    pub store_root: Option<PathBuf>,
    /// Exit after this many tasks (tests; default: serve until told to stop).
    pub max_tasks: Option<u64>,
    /// Sleep this long before every task (fault tests, to catch a worker mid-task).
    pub task_delay: Option<Duration>,
}

/// What a worker reports while it serves.
#[derive(Debug, Clone, PartialEq)]
pub enum WorkerEvent {
    /// Connected and pulling.
    Ready {
        /// The worker's name.
        name: String,
    },
    /// A task began.
    Started {
        /// Stage.
        stage: String,
        /// Task index.
        task: u32,
        /// Bricks in it.
        bricks: usize,
        /// Delivery number (1 for the first).
        delivered: i64,
    },
    /// A task ended.
    Finished {
        /// Stage.
        stage: String,
        /// Task index.
        task: u32,
        /// Seconds of work.
        seconds: f64,
        /// The error, if it failed.
        error: Option<String>,
    },
    /// Stopping (signal or `nvx.workers.stop`).
    Stopping,
}

/// What a worker did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WorkerSummary {
    /// Tasks completed per stage.
    pub done: HashMap<String, u64>,
    /// Tasks that failed (retried or dead-lettered).
    pub failed: u64,
}

struct NatsBlobs {
    engine: Engine,
    handle: tokio::runtime::Handle,
    cache: Mutex<HashMap<String, Arc<Vec<u8>>>>,
}

impl Blobs for NatsBlobs {
    fn get(&self, key: &str) -> neuvolex_tasks::Result<Arc<Vec<u8>>> {
        if let Some(b) = self
            .cache
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(key)
        {
            return Ok(b.clone());
        }
        let v = Arc::new(
            self.handle
                .block_on(self.engine.get_blob(key))
                .map_err(TaskError::from)?,
        );
        let mut c = self.cache.lock().unwrap_or_else(|p| p.into_inner());
        if c.len() >= 4 {
            c.clear();
        }
        c.insert(key.to_string(), v.clone());
        Ok(v)
    }
}

/// Points a local store of `params` into `root` (relative paths) and refuses one outside it.
fn resolve_store(params: &mut serde_json::Value, root: &Option<PathBuf>) -> Result<()> {
    let (Some(root), Some(s)) = (root, params.get("store").and_then(|v| v.as_str())) else {
        return Ok(());
    };
    if s.contains("://") {
        return Ok(());
    }
    let p = PathBuf::from(s);
    let full = if p.is_relative() { root.join(&p) } else { p };
    let canon = full.canonicalize().unwrap_or(full.clone());
    let root_c = root.canonicalize().unwrap_or(root.clone());
    if !canon.starts_with(&root_c) {
        return Err(ClusterError::Task(TaskError::Failed(format!(
            "store {} lies outside this worker's --store-root {}",
            full.display(),
            root.display()
        ))));
    }
    params["store"] = serde_json::Value::String(canon.display().to_string());
    Ok(())
}

/// The run of the task this worker executes now and its cancellation flag.
type Current = Option<(String, Arc<AtomicBool>)>;

fn default_name() -> String {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}

/// Serves tasks from the cluster until stopped (SIGINT/SIGTERM, `nvx.workers.stop`, or
/// `max_tasks`), calling `events` as tasks start and end. It keeps setting up JetStream as long
/// as a coordinator waits for workers (`no_worker_timeout`), and fails at once where the server
/// cannot be reached or refuses it.
pub fn serve(
    cfg: EngineConfig,
    registry: Registry,
    opts: WorkerOptions,
    events: &mut (dyn FnMut(WorkerEvent) + Send),
) -> Result<WorkerSummary> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| js("runtime", e))?;
    let r = rt.block_on(serve_async(cfg, registry, opts, events));
    rt.shutdown_background();
    r
}

async fn serve_async(
    mut cfg: EngineConfig,
    registry: Registry,
    opts: WorkerOptions,
    events: &mut (dyn FnMut(WorkerEvent) + Send),
) -> Result<WorkerSummary> {
    let name = opts.name.clone().unwrap_or_else(default_name);
    // A worker keeps setting up as long as a coordinator would wait for it.
    cfg.setup_timeout = cfg.setup_timeout.max(cfg.no_worker_timeout);
    let (engine, consumer) = Engine::connect_worker(cfg, &name).await?;
    let stop = Arc::new(AtomicBool::new(false));
    let cancelled: Arc<Mutex<HashSet<String>>> = Arc::default();
    let current: Arc<Mutex<Current>> = Arc::default();
    // Stop and cancel orders.
    {
        let mut sub = engine
            .client
            .subscribe(STOP)
            .await
            .map_err(|e| js("stop subscription", e))?;
        let stop1 = stop.clone();
        tokio::spawn(async move {
            if sub.next().await.is_some() {
                stop1.store(true, Ordering::SeqCst);
            }
        });
        let mut sub = engine
            .client
            .subscribe(CANCEL)
            .await
            .map_err(|e| js("cancel subscription", e))?;
        let (cancelled, current) = (cancelled.clone(), current.clone());
        tokio::spawn(async move {
            while let Some(m) = sub.next().await {
                let run = String::from_utf8_lossy(&m.payload).into_owned();
                if let Some((r, flag)) = &*current.lock().unwrap_or_else(|p| p.into_inner()) {
                    if *r == run {
                        flag.store(true, Ordering::SeqCst);
                    }
                }
                let mut c = cancelled.lock().unwrap_or_else(|p| p.into_inner());
                if c.len() > 4096 {
                    c.clear();
                }
                c.insert(run);
            }
        });
        let stop2 = stop.clone();
        tokio::spawn(async move {
            #[cfg(unix)]
            {
                use tokio::signal::unix::{signal, SignalKind};
                if let Ok(mut term) = signal(SignalKind::terminate()) {
                    tokio::select! {
                        _ = tokio::signal::ctrl_c() => {}
                        _ = term.recv() => {}
                    }
                } else {
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
            #[cfg(not(unix))]
            let _ = tokio::signal::ctrl_c().await;
            stop2.store(true, Ordering::SeqCst);
        });
        // Presence, so coordinators know workers exist.
        let (client, n) = (engine.client.clone(), name.clone());
        tokio::spawn(async move {
            loop {
                let _ = client.publish(ALIVE, n.clone().into()).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        });
    }
    events(WorkerEvent::Ready { name: name.clone() });
    let blobs = Arc::new(NatsBlobs {
        engine: engine.clone(),
        handle: tokio::runtime::Handle::current(),
        cache: Mutex::new(HashMap::new()),
    });
    let mut stages: VecDeque<(u64, Arc<dyn DynStage>)> = VecDeque::new();
    let registry = Arc::new(registry);
    let mut summary = WorkerSummary::default();
    let mut prev_pending = 0u64;
    let mut last_publish = 0.0f64;
    let max_deliver = engine.cfg.max_deliver;
    let heartbeat = engine.cfg.heartbeat();
    let mut served = 0u64;
    while !stop.load(Ordering::SeqCst) && opts.max_tasks.is_none_or(|m| served < m) {
        let t_fetch = Instant::now();
        let mut batch = match consumer
            .fetch()
            .max_messages(1)
            .expires(Duration::from_secs(1))
            .messages()
            .await
        {
            Ok(b) => b,
            Err(e) => {
                tracing::debug!("fetch: {e}");
                tokio::time::sleep(Duration::from_millis(500)).await;
                continue;
            }
        };
        let msg = match batch.next().await {
            Some(Ok(m)) => m,
            Some(Err(e)) => {
                tracing::debug!("fetch: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
            None => {
                prev_pending = 0;
                continue;
            }
        };
        let fetch = if prev_pending > 0 {
            t_fetch.elapsed().as_secs_f64()
        } else {
            0.0
        };
        let t_recv = Instant::now();
        let (delivered, pending) = msg
            .info()
            .map(|i| (i.delivered, i.pending))
            .unwrap_or((1, 0));
        prev_pending = pending;
        let tm: TaskMsg = match codec::decode(&msg.payload) {
            Ok(t) => t,
            Err(e) => {
                tracing::error!("malformed task message ({e}): terminated");
                let _ = msg.ack_with(AckKind::Term).await;
                continue;
            }
        };
        if cancelled
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(&tm.run)
        {
            let _ = msg.ack_with(AckKind::Term).await;
            continue;
        }
        events(WorkerEvent::Started {
            stage: tm.stage.clone(),
            task: tm.task.index,
            bricks: tm.task.bricks.len(),
            delivered,
        });
        let msg = Arc::new(msg);
        // Heartbeats keep the task ours while it runs.
        let hb = {
            let m = msg.clone();
            tokio::spawn(async move {
                loop {
                    tokio::time::sleep(heartbeat).await;
                    if let Err(e) = m.ack_with(AckKind::Progress).await {
                        tracing::debug!("heartbeat: {e}");
                    }
                }
            })
        };
        let flag = Arc::new(AtomicBool::new(false));
        *current.lock().unwrap_or_else(|p| p.into_inner()) = Some((tm.run.clone(), flag.clone()));
        let cached = stages
            .iter()
            .find(|(k, _)| *k == tm.key)
            .map(|s| s.1.clone());
        let (reg, bl, root, delay) = (
            registry.clone(),
            blobs.clone(),
            opts.store_root.clone(),
            opts.task_delay,
        );
        let tm2 = tm.clone();
        let t_work = Instant::now();
        let io0 = neuvolex_bricks::store_io();
        let r = tokio::task::spawn_blocking(move || {
            if let Some(d) = delay {
                std::thread::sleep(d);
            }
            let stage = match cached {
                Some(s) => s,
                None => {
                    let mut p: serde_json::Value = serde_json::from_str(&tm2.params)
                        .map_err(|e| TaskError::Codec(e.to_string()))?;
                    resolve_store(&mut p, &root).map_err(TaskError::from)?;
                    reg.build(&tm2.stage, &p, bl.as_ref())?
                }
            };
            let ctx = TaskCtx::new(&flag);
            let out = stage.run_encoded(&tm2.task, &ctx);
            Ok::<_, TaskError>((stage, out, ctx.skipped()))
        })
        .await;
        let work = t_work.elapsed().as_secs_f64();
        // One task at a time: the process's store traffic meanwhile is the task's.
        let io = neuvolex_bricks::store_io().since(&io0);
        hb.abort();
        *current.lock().unwrap_or_else(|p| p.into_inner()) = None;
        let outcome: std::result::Result<(Vec<u8>, u64), TaskError> = match r {
            Ok(Ok((stage, out, skipped))) => {
                if !stages.iter().any(|(k, _)| *k == tm.key) {
                    stages.push_front((tm.key, stage));
                    stages.truncate(4);
                }
                out.map(|b| (b, skipped))
            }
            Ok(Err(e)) => Err(e),
            Err(e) => Err(TaskError::Failed(format!("the task panicked: {e}"))),
        };
        served += 1;
        let subject = crate::engine::result_subject(&tm.run);
        let mut hdr = async_nats::HeaderMap::new();
        hdr.insert(h::TASK, tm.task.index.to_string().as_str());
        hdr.insert(h::WORKER, name.as_str());
        hdr.insert(h::DELIVERED, delivered.to_string().as_str());
        match outcome {
            Ok((bytes, skipped)) => {
                let overhead = t_recv.elapsed().as_secs_f64() - work + fetch + last_publish;
                hdr.insert(h::KIND, "done");
                hdr.insert(h::WORK, format!("{work:.6}").as_str());
                hdr.insert(h::OVERHEAD, format!("{overhead:.6}").as_str());
                hdr.insert(h::SKIPPED, skipped.to_string().as_str());
                hdr.insert(h::READ, io.bytes_read.to_string().as_str());
                hdr.insert(h::WRITTEN, io.bytes_written.to_string().as_str());
                let t_pub = Instant::now();
                let sent = if bytes.len() > crate::executor::INLINE_RESULT_MAX {
                    // Too large for a message: the result goes through the blob store.
                    let key = format!(
                        "result-{}-{}-{:016x}",
                        tm.run,
                        tm.task.index,
                        neuvolex_tasks::fingerprint(&bytes)
                    );
                    hdr.insert(crate::executor::h::BLOB, key.as_str());
                    engine.put_blob(&key, &bytes).await.map(|_| Vec::new())
                } else {
                    Ok(bytes)
                };
                let published = match sent {
                    Ok(payload) => publish_result(&engine, &subject, hdr, payload).await,
                    Err(e) => Err(e),
                };
                match published {
                    Ok(()) => {
                        if let Err(e) = msg.double_ack().await {
                            tracing::warn!("ack of task {}: {e} (it will be redelivered; its result is idempotent)", tm.task.index);
                        }
                        *summary.done.entry(tm.stage.clone()).or_default() += 1;
                        events(WorkerEvent::Finished {
                            stage: tm.stage.clone(),
                            task: tm.task.index,
                            seconds: work,
                            error: None,
                        });
                    }
                    Err(e) => {
                        tracing::warn!(
                            "result of task {} not published: {e}; it will be redelivered",
                            tm.task.index
                        );
                    }
                }
                last_publish = t_pub.elapsed().as_secs_f64();
            }
            Err(TaskError::Cancelled) => {
                let _ = msg.ack_with(AckKind::Term).await;
            }
            Err(e) => {
                summary.failed += 1;
                let err = format!(
                    "stage {} task {} (bricks {:?}) on {name}, delivery {delivered}/{max_deliver}: {e}",
                    tm.stage, tm.task.index, tm.task.bricks
                );
                tracing::warn!("{err}");
                events(WorkerEvent::Finished {
                    stage: tm.stage.clone(),
                    task: tm.task.index,
                    seconds: work,
                    error: Some(err.clone()),
                });
                if delivered >= max_deliver {
                    hdr.insert(h::KIND, "dead");
                    if publish_result(&engine, &subject, hdr, err.into_bytes())
                        .await
                        .is_ok()
                    {
                        let _ = msg.ack_with(AckKind::Term).await;
                    }
                } else {
                    let backoff = Duration::from_millis(500 * delivered.max(1) as u64);
                    let _ = msg.ack_with(AckKind::Nak(Some(backoff))).await;
                }
            }
        }
    }
    events(WorkerEvent::Stopping);
    Ok(summary)
}

/// Publishes a result and waits for JetStream to store it, retrying for about one AckWait.
async fn publish_result(
    engine: &Engine,
    subject: &str,
    hdr: async_nats::HeaderMap,
    payload: Vec<u8>,
) -> Result<()> {
    let payload: bytes::Bytes = payload.into();
    let deadline = Instant::now() + engine.cfg.ack_wait;
    let mut wait = Duration::from_millis(100);
    loop {
        let r = async {
            engine
                .js
                .publish_with_headers(subject.to_string(), hdr.clone(), payload.clone())
                .await
                .map_err(|e| js("publish result", e))?
                .await
                .map_err(|e| js("publish result", e))
        }
        .await;
        match r {
            Ok(_) => return Ok(()),
            Err(e) if Instant::now() + wait > deadline => return Err(e),
            Err(e) => {
                tracing::debug!("{e}; retrying");
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(Duration::from_secs(2));
            }
        }
    }
}
