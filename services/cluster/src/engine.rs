//! The connection to NATS and the JetStream resources every coordinator and worker shares.

use crate::{js, ClusterError, Result};
use async_nats::jetstream::{self, consumer, object_store, stream};
use std::time::Duration;

/// Stream of tasks (WorkQueue retention).
pub const TASKS: &str = "NVX_TASKS";
/// Stream of results and dead letters (limits retention).
pub const RESULTS: &str = "NVX_RESULTS";
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

/// Task subject of a run: `nvx.task.<stage>.<stage key>.<run>`.
pub fn task_subject(stage: &str, key: u64, run: &str) -> String {
    format!("nvx.task.{stage}.{key:016x}.{run}")
}

/// Result subject of a run.
pub fn result_subject(run: &str) -> String {
    format!("nvx.result.{run}")
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
    /// A coordinator gives up when no worker has been seen for this long.
    pub no_worker_timeout: Duration,
}

impl EngineConfig {
    /// Defaults: AckWait 30 s, MaxDeliver 3, 5 s to connect, 60 s without workers.
    pub fn new(url: &str) -> Self {
        EngineConfig {
            url: url.to_string(),
            ack_wait: Duration::from_secs(30),
            max_deliver: 3,
            connect_timeout: Duration::from_secs(5),
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
        let limit = e.cfg.connect_timeout * 4;
        tokio::time::timeout(limit, e.ensure())
            .await
            .map_err(|_| bad("JetStream did not answer in time".into()))??;
        Ok(e)
    }

    async fn ensure(&mut self) -> Result<()> {
        let hint = |e: &dyn std::fmt::Display| {
            let s = e.to_string();
            if s.contains("not enabled") || s.contains("503") || s.contains("no responders") {
                format!("{s}: JetStream is not enabled on this server (start nats-server with -js)")
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

    /// The blob stored under `key`.
    pub async fn get_blob(&self, key: &str) -> Result<Vec<u8>> {
        use tokio::io::AsyncReadExt;
        let b = self.blobs().await?;
        let mut o = b
            .get(key)
            .await
            .map_err(|e| js(&format!("blob '{key}'"), e))?;
        let mut v = Vec::new();
        o.read_to_end(&mut v)
            .await
            .map_err(|e| js(&format!("blob '{key}'"), e))?;
        Ok(v)
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
