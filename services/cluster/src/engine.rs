//! The connection to NATS and the JetStream resources every coordinator and worker shares.

use crate::{js, ClusterError, Result};
use async_nats::jetstream::{self, consumer, object_store, stream};
use std::time::Duration;

/// Stream of tasks (WorkQueue retention).
pub const TASKS: &str = "NVX_TASKS";
/// Stream of results and the workers' dead-letter notices (limits retention; each run's
/// messages are purged when it ends).
pub const RESULTS: &str = "NVX_RESULTS";
/// Stream of dead-letter records (`nvx.dead.<stage>.<run>`), kept for a week after their run so
/// an operator can inspect them (`neuvolex worker --nats URL --dead-letters`).
pub const DEAD: &str = "NVX_DEAD";
/// The durable pull consumer every worker shares.
pub const CONSUMER: &str = "workers";
/// Object store of blobs (trained forests, models).
pub const BLOBS: &str = "nvx-blobs";
/// Core subject on which workers announce themselves every second.
pub const ALIVE: &str = "nvx.workers.alive";
/// Core subject on which a coordinator cancels a run (payload: the run id).
pub const CANCEL: &str = "nvx.cancel";
/// Core subject that tells every worker to finish its task and exit.
pub const STOP: &str = "nvx.workers.stop";

/// What a connection error says when the server answers without JetStream.
const NOT_ENABLED: &str = "JetStream is not enabled on this server";

/// Whether a JetStream set-up error may pass by waiting: every one but a refusal of
/// permission (the server answered and will answer the same).
fn setup_may_pass(e: &ClusterError) -> bool {
    match e {
        ClusterError::JetStream { detail, .. } => {
            let d = detail.to_ascii_lowercase();
            !["permission", "authoriz", "not allowed"]
                .iter()
                .any(|t| d.contains(t))
        }
        _ => false,
    }
}

/// Task subject of a run: `nvx.task.<stage>.<stage key>.<run>`.
pub fn task_subject(stage: &str, key: u64, run: &str) -> String {
    format!("nvx.task.{stage}.{key:016x}.{run}")
}

/// Result subject of a run.
pub fn result_subject(run: &str) -> String {
    format!("nvx.result.{run}")
}

/// Subject on which a run's coordinator answers while it runs (see [`Engine::run_alive`]).
pub fn run_subject(run: &str) -> String {
    format!("nvx.run.{run}")
}

/// Dead-letter subject of a run.
pub fn dead_subject(stage: &str, run: &str) -> String {
    format!("nvx.dead.{stage}.{run}")
}

/// A task given up, as kept in the dead-letter stream.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeadLetter {
    /// The run.
    pub run: String,
    /// The stage.
    pub stage: String,
    /// The stage's parameters (JSON text).
    pub params: String,
    /// Unix seconds when the coordinator recorded it.
    pub unix: u64,
    /// The task, its bricks, deliveries, last error and worker.
    pub task: neuvolex_tasks::DeadTask,
}

/// Engine settings shared by coordinators and workers.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineConfig {
    /// NATS server URL(s), comma-separated (`nats://host:4222`).
    pub url: String,
    /// How long a delivered task may go without an ack or heartbeat before it is redelivered.
    pub ack_wait: Duration,
    /// Deliveries of a task before it is dead-lettered.
    pub max_deliver: i64,
    /// Bound on connecting and on every JetStream request.
    pub connect_timeout: Duration,
    /// How long connecting keeps setting up the streams, consumer and blob store while the
    /// server answers but JetStream does not yet (starting, busy, or set up by another process
    /// at the same moment). A worker waits at least `no_worker_timeout`.
    pub setup_timeout: Duration,
    /// A coordinator gives up when no worker has been seen for this long.
    pub no_worker_timeout: Duration,
}

impl EngineConfig {
    /// Defaults: AckWait 30 s, MaxDeliver 3, 5 s to connect, 20 s to set up JetStream, 60 s
    /// without workers.
    pub fn new(url: &str) -> Self {
        EngineConfig {
            url: url.to_string(),
            ack_wait: Duration::from_secs(30),
            max_deliver: 3,
            connect_timeout: Duration::from_secs(5),
            setup_timeout: Duration::from_secs(20),
            no_worker_timeout: Duration::from_secs(60),
        }
    }

    /// Interval of in-progress heartbeats for a running task (a third of AckWait).
    pub fn heartbeat(&self) -> Duration {
        (self.ack_wait / 3).max(Duration::from_millis(100))
    }
}

/// A connection with the shared streams, consumer and object store in place.
#[derive(Clone)]
pub struct Engine {
    /// Settings.
    pub cfg: EngineConfig,
    /// The NATS client.
    pub client: async_nats::Client,
    /// JetStream.
    pub js: jetstream::Context,
}

impl Engine {
    /// Connects (bounded by `connect_timeout`) and makes sure the streams, the workers'
    /// consumer and the blob store exist.
    pub async fn connect(cfg: EngineConfig, name: &str) -> Result<Engine> {
        Ok(Engine::connect_with(cfg, name, false).await?.0)
    }

    /// [`Engine::connect`], then the workers' pull consumer: what a worker needs to start.
    pub async fn connect_worker(
        cfg: EngineConfig,
        name: &str,
    ) -> Result<(Engine, consumer::PullConsumer)> {
        let (e, c) = Engine::connect_with(cfg, name, true).await?;
        let c = c.ok_or_else(|| js("workers' consumer", "not looked up"))?;
        Ok((e, c))
    }

    /// Connects and sets up, then looks up the workers' consumer where `worker`; the set-up
    /// and the lookup are tried again together.
    async fn connect_with(
        cfg: EngineConfig,
        name: &str,
        worker: bool,
    ) -> Result<(Engine, Option<consumer::PullConsumer>)> {
        let url = cfg.url.clone();
        let bad = |detail: String| ClusterError::Connect {
            url: url.clone(),
            detail,
        };
        for u in cfg.url.split(',') {
            let ok = ["nats://", "tls://", "ws://", "wss://"]
                .iter()
                .any(|p| u.trim().starts_with(p));
            if !ok {
                return Err(bad(format!(
                    "'{u}' is not a NATS URL (expected nats://HOST:PORT)"
                )));
            }
        }
        let opts = async_nats::ConnectOptions::new()
            .name(name)
            .connection_timeout(cfg.connect_timeout)
            .request_timeout(Some(cfg.connect_timeout.max(Duration::from_secs(5))))
            .max_reconnects(None);
        let client = tokio::time::timeout(
            cfg.connect_timeout + Duration::from_secs(1),
            opts.connect(cfg.url.as_str()),
        )
        .await
        .map_err(|_| {
            bad(format!(
                "no answer within {:.0} s (is nats-server running there?)",
                cfg.connect_timeout.as_secs_f64()
            ))
        })?
        .map_err(|e| {
            bad(format!(
                "cannot connect: {e} (is nats-server running there?)"
            ))
        })?;
        let js = jetstream::ContextBuilder::new()
            .timeout(cfg.connect_timeout.max(Duration::from_secs(5)))
            .build(client.clone());
        let mut e = Engine { cfg, client, js };
        // A server that has just started listens a moment before JetStream answers; of
        // processes that create the streams at once, all but one are told the subjects overlap
        // (the next look finds the stream); and on a busy machine (a disk that stalls the
        // server's metadata writes) a request times out. So set-up is tried again, each attempt
        // bounded, until `setup_timeout`; only what waiting cannot change ends it early.
        let (window, t0) = (e.cfg.setup_timeout, std::time::Instant::now());
        let attempt = e.cfg.connect_timeout.max(Duration::from_secs(5)) * 4;
        let mut tries = 0u32;
        loop {
            tries += 1;
            let step = async {
                e.ensure().await?;
                if worker {
                    e.consumer().await.map(Some)
                } else {
                    Ok(None)
                }
            };
            let last = match tokio::time::timeout(attempt, step).await {
                Ok(Ok(c)) => return Ok((e, c)),
                Ok(Err(x)) if !setup_may_pass(&x) => return Err(x),
                Ok(Err(x)) => x,
                Err(_) => crate::js(
                    "set-up",
                    format!("no answer within {:.0} s", attempt.as_secs_f64()),
                ),
            };
            if t0.elapsed() >= window {
                return Err(bad(format!(
                    "JetStream set-up did not complete in {:.0} s ({tries} tries); last: {last}",
                    t0.elapsed().as_secs_f64()
                )));
            }
            tracing::debug!(tries, "JetStream set-up: {last}; trying again");
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }

    async fn ensure(&mut self) -> Result<()> {
        let hint = |e: &dyn std::fmt::Display| {
            let s = e.to_string();
            let l = s.to_ascii_lowercase();
            if ["not enabled", "503", "no responders", "unavailable"]
                .iter()
                .any(|t| l.contains(t))
            {
                format!("{s}: {NOT_ENABLED} (start nats-server with -js)")
            } else {
                s
            }
        };
        self.js
            .get_or_create_stream(stream::Config {
                name: TASKS.into(),
                subjects: vec!["nvx.task.>".into()],
                retention: stream::RetentionPolicy::WorkQueue,
                storage: stream::StorageType::File,
                duplicate_window: Duration::from_secs(120),
                max_age: Duration::from_secs(7 * 24 * 3600),
                ..Default::default()
            })
            .await
            .map_err(|e| js("task stream", hint(&e)))?;
        self.js
            .get_or_create_stream(stream::Config {
                name: RESULTS.into(),
                subjects: vec!["nvx.result.>".into()],
                retention: stream::RetentionPolicy::Limits,
                storage: stream::StorageType::File,
                duplicate_window: Duration::from_secs(120),
                max_age: Duration::from_secs(24 * 3600),
                ..Default::default()
            })
            .await
            .map_err(|e| js("result stream", hint(&e)))?;
        self.js
            .get_or_create_stream(stream::Config {
                name: DEAD.into(),
                subjects: vec!["nvx.dead.>".into()],
                retention: stream::RetentionPolicy::Limits,
                storage: stream::StorageType::File,
                max_age: Duration::from_secs(7 * 24 * 3600),
                max_messages: 100_000,
                ..Default::default()
            })
            .await
            .map_err(|e| js("dead-letter stream", hint(&e)))?;
        let want = self.consumer_config();
        let s = self
            .js
            .get_stream(TASKS)
            .await
            .map_err(|e| js("task stream", e))?;
        match s.consumer_info(CONSUMER).await {
            Ok(info) => {
                // The consumer's settings are the cluster's: heartbeats follow its AckWait.
                let c = &info.config;
                if c.ack_wait != want.ack_wait || c.max_deliver != want.max_deliver {
                    tracing::warn!(
                        "the workers' consumer has AckWait {:?} and MaxDeliver {} (asked for {:?} \
                         and {}); using the consumer's (delete stream {TASKS} to change them)",
                        c.ack_wait,
                        c.max_deliver,
                        want.ack_wait,
                        want.max_deliver
                    );
                    self.cfg.ack_wait = c.ack_wait;
                    self.cfg.max_deliver = c.max_deliver;
                }
            }
            Err(_) => {
                s.get_or_create_consumer(CONSUMER, want)
                    .await
                    .map_err(|e| js("workers' consumer", e))?;
            }
        }
        if self.js.get_object_store(BLOBS).await.is_err() {
            self.js
                .create_object_store(object_store::Config {
                    bucket: BLOBS.into(),
                    description: Some("neuvolex blobs: forests and models, by content".into()),
                    storage: stream::StorageType::File,
                    max_age: Duration::from_secs(7 * 24 * 3600),
                    ..Default::default()
                })
                .await
                .map_err(|e| js("blob store", e))?;
        }
        Ok(())
    }

    fn consumer_config(&self) -> consumer::pull::Config {
        consumer::pull::Config {
            durable_name: Some(CONSUMER.into()),
            description: Some("neuvolex workers".into()),
            ack_policy: consumer::AckPolicy::Explicit,
            ack_wait: self.cfg.ack_wait,
            max_deliver: self.cfg.max_deliver,
            filter_subject: "nvx.task.>".into(),
            max_ack_pending: 4096,
            ..Default::default()
        }
    }

    /// The workers' pull consumer.
    pub async fn consumer(&self) -> Result<consumer::PullConsumer> {
        self.js
            .get_consumer_from_stream(CONSUMER, TASKS)
            .await
            .map_err(|e| js("workers' consumer", e))
    }

    /// The blob store.
    pub async fn blobs(&self) -> Result<object_store::ObjectStore> {
        self.js
            .get_object_store(BLOBS)
            .await
            .map_err(|e| js("blob store", e))
    }

    /// Publishes `bytes` under `key` unless the blob store already holds it.
    pub async fn put_blob(&self, key: &str, bytes: &[u8]) -> Result<()> {
        let b = self.blobs().await?;
        // A deleted object keeps an info record (`deleted`): it is published again.
        if b.info(key).await.is_ok_and(|i| !i.deleted) {
            return Ok(());
        }
        let mut r = bytes;
        b.put(key, &mut r).await.map_err(|e| js("blob put", e))?;
        Ok(())
    }

    /// Deletes the blob under `key` (a result read once); a failure is only logged.
    pub async fn delete_blob(&self, key: &str) {
        let r = match self.blobs().await {
            Ok(b) => b.delete(key).await.map_err(|e| e.to_string()),
            Err(e) => Err(e.to_string()),
        };
        if let Err(e) = r {
            tracing::debug!("cannot delete blob '{key}': {e}");
        }
    }

    /// The blob stored under `key`. Publishing an object again purges the chunks of the copy
    /// it replaces, so a read that began on that copy waits for chunks that will never come, or
    /// ends early with a wrong digest: a read that fails, or has no data for a request timeout,
    /// starts again from the newest copy (3 reads at most), never a hang.
    pub async fn get_blob(&self, key: &str) -> Result<Vec<u8>> {
        use tokio::io::AsyncReadExt;
        let stall = self.cfg.connect_timeout.max(Duration::from_secs(5));
        let b = self.blobs().await?;
        let (mut last, mut buf) = (String::new(), vec![0u8; 1 << 16]);
        for _ in 0..3 {
            let mut o = b
                .get(key)
                .await
                .map_err(|e| js(&format!("blob '{key}'"), e))?;
            let mut v = Vec::new();
            loop {
                match tokio::time::timeout(stall, o.read(&mut buf)).await {
                    Ok(Ok(0)) => return Ok(v),
                    Ok(Ok(n)) => v.extend_from_slice(&buf[..n]),
                    // Chunks purged under the read end it early: "wrong digest".
                    Ok(Err(e)) => {
                        last = format!("{e} after {} bytes", v.len());
                        tracing::debug!("blob '{key}': {last}; reading again");
                        break;
                    }
                    Err(_) => {
                        last = format!(
                            "no data for {:.0} s after {} bytes (replaced while read?)",
                            stall.as_secs_f64(),
                            v.len()
                        );
                        tracing::debug!("blob '{key}': {last}; reading again");
                        break;
                    }
                }
            }
        }
        Err(js(&format!("blob '{key}'"), last))
    }

    /// True unless the coordinator of `run` is certainly gone: nobody listens on its
    /// [`run_subject`] (NATS answers "no responders" at once). A coordinator that does not
    /// answer in time counts as alive, so a slow one never loses its tasks.
    pub async fn run_alive(&self, run: &str) -> bool {
        let req = async_nats::Request::new()
            .payload("alive?".into())
            .timeout(Some(Duration::from_secs(2)));
        match self.client.send_request(run_subject(run), req).await {
            Ok(_) => true,
            Err(e) => !matches!(e.kind(), async_nats::RequestErrorKind::NoResponders),
        }
    }

    /// Records a dead letter in the retained dead-letter stream.
    pub async fn record_dead(&self, d: &DeadLetter) -> Result<()> {
        let payload = serde_json::to_vec(d).map_err(|e| js("dead letter", e))?;
        self.js
            .publish(dead_subject(&d.stage, &d.run), payload.into())
            .await
            .map_err(|e| js("dead letter", e))?
            .await
            .map_err(|e| js("dead letter", e))?;
        Ok(())
    }

    /// The dead letters kept (oldest first; at most `limit`).
    pub async fn dead_letters(&self, limit: usize) -> Result<Vec<DeadLetter>> {
        use futures_util::StreamExt;
        let s = self
            .js
            .get_stream(DEAD)
            .await
            .map_err(|e| js("dead-letter stream", e))?;
        let mut out = Vec::new();
        let n = s
            .get_info()
            .await
            .map_err(|e| js("dead-letter stream", e))?
            .state
            .messages as usize;
        if n == 0 {
            return Ok(out);
        }
        let c = s
            .create_consumer(consumer::pull::OrderedConfig {
                filter_subject: "nvx.dead.>".into(),
                deliver_policy: consumer::DeliverPolicy::All,
                ..Default::default()
            })
            .await
            .map_err(|e| js("dead-letter consumer", e))?;
        let mut msgs = c
            .messages()
            .await
            .map_err(|e| js("dead-letter consumer", e))?;
        let want = n.min(limit);
        for _ in 0..want {
            let wait = self.cfg.connect_timeout.max(Duration::from_secs(5));
            let m = tokio::time::timeout(wait, msgs.next())
                .await
                .map_err(|_| js("dead-letter consumer", "no answer in time"))?;
            match m {
                Some(Ok(m)) => match serde_json::from_slice::<DeadLetter>(&m.payload) {
                    Ok(d) => out.push(d),
                    Err(e) => tracing::warn!("a dead letter that is not a record ({e}): skipped"),
                },
                Some(Err(e)) => return Err(js("dead-letter consumer", e)),
                None => break,
            }
        }
        Ok(out)
    }

    /// Tells every worker to finish its current task and exit.
    pub async fn stop_workers(&self) -> Result<()> {
        self.client
            .publish(STOP, "stop".into())
            .await
            .map_err(|e| js("stop", e))?;
        self.client.flush().await.map_err(|e| js("stop", e))
    }
}
