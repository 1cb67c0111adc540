//! The actors: tokio tasks with bounded mailboxes that schedule the library's pure per-brick
//! work on the blocking pool, an event hub, and a supervisor that restarts a failed actor and
//! reports the failure to clients.

use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use serde::Serialize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use tokio::sync::{broadcast, mpsc, oneshot, Mutex as AsyncMutex};

/// Mailbox size of every actor: a full mailbox answers 503 instead of queueing without bound.
pub const MAILBOX: usize = 64;

/// An event for clients (sent as Server-Sent Events).
#[derive(Debug, Clone, Serialize)]
pub struct Event {
    /// Session it concerns, if any.
    pub session: Option<String>,
    /// Event name: classified, classification, training, actor_failed, ...
    pub kind: String,
    /// Details.
    pub data: serde_json::Value,
}

/// Fans events out to every subscriber; slow subscribers lose old events, never block actors.
#[derive(Clone)]
pub struct Hub {
    tx: broadcast::Sender<Event>,
}

impl Default for Hub {
    fn default() -> Self {
        Hub {
            tx: broadcast::channel(1024).0,
        }
    }
}

impl Hub {
    /// Publishes an event.
    pub fn publish(&self, session: Option<&str>, kind: &str, data: serde_json::Value) {
        let _ = self.tx.send(Event {
            session: session.map(str::to_string),
            kind: kind.to_string(),
            data,
        });
    }

    /// A new subscription.
    pub fn subscribe(&self) -> broadcast::Receiver<Event> {
        self.tx.subscribe()
    }
}

/// Runs an actor loop under supervision: when it panics, the failure is published and the
/// actor restarts on the same mailbox; when it returns (mailbox closed), supervision ends.
fn supervise<F, Fut>(name: &'static str, hub: Hub, mut run: F)
where
    F: FnMut() -> Fut + Send + 'static,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    tokio::spawn(async move {
        loop {
            match tokio::spawn(run()).await {
                Ok(()) => break,
                Err(e) => {
                    let msg = if e.is_panic() {
                        "panicked"
                    } else {
                        "was cancelled"
                    };
                    tracing::error!(actor = name, "actor {msg}; restarting");
                    hub.publish(
                        None,
                        "actor_failed",
                        serde_json::json!({"actor": name, "error": format!("{name} {msg}"), "restarted": true}),
                    );
                }
            }
        }
    });
}

/// A request to classify a session at a stroke generation.
pub struct ClassifyJob {
    /// The session.
    pub session: Arc<Session>,
    /// Stroke generation to classify.
    pub generation: u64,
}

/// What the trainer is asked to do.
pub enum TrainCommand {
    /// Start (or resume from the checkpoint when `resume`) with a budget in epochs.
    Start {
        /// The session.
        session: Arc<Session>,
        /// Epochs.
        epochs: f64,
        /// Continue from the checkpoint.
        resume: bool,
    },
}

/// A render request with its reply slot.
pub struct RenderJob {
    /// The session.
    pub session: Arc<Session>,
    /// Frame parameters.
    pub params: neuvolex_render::RenderParams,
    /// Transfer function.
    pub tf: neuvolex_render::TfFile,
    /// PNG bytes or an error.
    pub reply: oneshot::Sender<ApiResult<Vec<u8>>>,
}

/// Handles to the actors' mailboxes.
#[derive(Clone)]
pub struct Actors {
    /// Events.
    pub hub: Hub,
    classify: mpsc::Sender<ClassifyJob>,
    train: mpsc::Sender<TrainCommand>,
    render: mpsc::Sender<RenderJob>,
}

/// Forest size of interactive classification.
pub const TREES: usize = 50;

impl Actors {
    /// Starts the classifier, trainer and renderer actors under supervision.
    pub fn start(hub: Hub) -> Actors {
        let (ctx, crx) = mpsc::channel::<ClassifyJob>(MAILBOX);
        let (ttx, trx) = mpsc::channel::<TrainCommand>(MAILBOX);
        let (rtx, rrx) = mpsc::channel::<RenderJob>(MAILBOX);
        let crx = Arc::new(AsyncMutex::new(crx));
        let trx = Arc::new(AsyncMutex::new(trx));
        let rrx = Arc::new(AsyncMutex::new(rrx));
        {
            let hub2 = hub.clone();
            supervise("classifier", hub.clone(), move || {
                classifier(crx.clone(), hub2.clone())
            });
        }
        {
            let hub2 = hub.clone();
            supervise("trainer", hub.clone(), move || {
                trainer(trx.clone(), hub2.clone())
            });
        }
        supervise("renderer", hub.clone(), move || renderer(rrx.clone()));
        Actors {
            hub,
            classify: ctx,
            train: ttx,
            render: rtx,
        }
    }

    /// Queues classification of `session` at `generation` (503 when the mailbox is full).
    pub fn classify(&self, session: Arc<Session>, generation: u64) -> ApiResult<()> {
        self.classify
            .try_send(ClassifyJob {
                session,
                generation,
            })
            .map_err(|_| ApiError::Busy("the classifier is busy; try again".into()))
    }

    /// Queues a training command.
    pub fn train(&self, cmd: TrainCommand) -> ApiResult<()> {
        self.train
            .try_send(cmd)
            .map_err(|_| ApiError::Busy("the trainer is busy; try again".into()))
    }

    /// Renders a frame.
    pub async fn render(
        &self,
        session: Arc<Session>,
        params: neuvolex_render::RenderParams,
        tf: neuvolex_render::TfFile,
    ) -> ApiResult<Vec<u8>> {
        let (reply, rx) = oneshot::channel();
        self.render
            .try_send(RenderJob {
                session,
                params,
                tf,
                reply,
            })
            .map_err(|_| ApiError::Busy("the renderer is busy; try again".into()))?;
        rx.await
            .map_err(|_| ApiError::Internal("the renderer failed (restarted)".into()))?
    }
}

async fn classifier(rx: Arc<AsyncMutex<mpsc::Receiver<ClassifyJob>>>, hub: Hub) {
    let mut rx = rx.lock().await;
    let mut pending: Vec<ClassifyJob> = Vec::new();
    loop {
        if pending.is_empty() {
            match rx.recv().await {
                Some(j) => pending.push(j),
                None => break,
            }
        }
        while let Ok(j) = rx.try_recv() {
            pending.push(j);
        }
        // Coalesce: only the newest generation of each session matters; sessions take turns
        // in the order their first pending job arrived.
        let mut latest: Vec<ClassifyJob> = Vec::new();
        for j in pending.drain(..) {
            match latest.iter_mut().find(|e| e.session.id == j.session.id) {
                Some(e) if j.generation > e.generation => *e = j,
                Some(_) => {}
                None => latest.push(j),
            }
        }
        let job = latest.remove(0);
        pending = latest;
        if !job.session.current(job.generation) {
            continue;
        }
        if let Err(e) = spawn_classify(job, hub.clone()).await {
            if e.is_panic() {
                // Fail this actor: the supervisor reports it and restarts it on the same mailbox.
                std::panic::resume_unwind(e.into_panic());
            }
        }
    }
}

fn spawn_classify(job: ClassifyJob, hub: Hub) -> tokio::task::JoinHandle<()> {
    tokio::task::spawn_blocking(move || {
        let s = job.session.clone();
        let id = s.id.clone();
        let shards = rayon::current_num_threads() * 2;
        let on_brick = |b: [usize; 3], done: usize, total: usize| {
            hub.publish(
                Some(&id),
                "classified",
                serde_json::json!({"brick": b, "done": done, "total": total, "generation": job.generation}),
            );
        };
        let r = s.classify(job.generation, TREES, shards, &on_brick);
        let status = s.status.read().unwrap_or_else(|p| p.into_inner()).clone();
        match r {
            Ok(n) => hub.publish(
                Some(&id),
                "classification",
                serde_json::json!({"bricks": n, "status": status}),
            ),
            Err(e) => {
                s.status.write().unwrap_or_else(|p| p.into_inner()).state = "failed".into();
                hub.publish(
                    Some(&id),
                    "classification",
                    serde_json::json!({"error": e.to_string(), "status": status}),
                );
            }
        }
    })
}

async fn trainer(rx: Arc<AsyncMutex<mpsc::Receiver<TrainCommand>>>, hub: Hub) {
    let mut rx = rx.lock().await;
    while let Some(cmd) = rx.recv().await {
        let TrainCommand::Start {
            session,
            epochs,
            resume,
        } = cmd;
        let cancel = Arc::new(AtomicBool::new(false));
        *session
            .train_cancel
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(cancel.clone());
        let hub2 = hub.clone();
        let r =
            tokio::task::spawn_blocking(move || train(&session, epochs, resume, &cancel, &hub2))
                .await;
        if let Ok(Err(e)) = r {
            hub.publish(
                None,
                "training",
                serde_json::json!({"error": e.to_string()}),
            );
        }
    }
}

fn train(s: &Session, epochs: f64, resume: bool, cancel: &AtomicBool, hub: &Hub) -> ApiResult<()> {
    use neuvolex_features::{checkpoint, train, Budget, InrConfig, TrainConfig, TrainEvent};
    let ckpt = neuvolex_features::train::checkpoint_path(&s.store);
    let loaded = if resume && ckpt.exists() {
        Some(checkpoint::load(&ckpt).map_err(|e| ApiError::Internal(e.to_string()))?)
    } else {
        None
    };
    let cfg = TrainConfig {
        budget: Budget {
            epochs: Some(epochs),
            ..Default::default()
        },
        ..TrainConfig::default()
    };
    let id = s.id.clone();
    let mut last = std::time::Instant::now();
    let mut on = |e: TrainEvent| match e {
        TrainEvent::Step {
            epoch, psnr, loss, ..
        } if last.elapsed().as_millis() > 250 => {
            last = std::time::Instant::now();
            hub.publish(
                Some(&id),
                "training",
                serde_json::json!({"state": "running", "epoch": epoch, "psnr": psnr, "loss": loss}),
            );
        }
        TrainEvent::Finished {
            psnr, stopped_by, ..
        } => hub.publish(
            Some(&id),
            "training",
            serde_json::json!({"state": "finished", "psnr": psnr, "stopped_by": stopped_by}),
        ),
        _ => {}
    };
    let t = train(
        &s.store,
        &InrConfig::default(),
        &cfg,
        loaded,
        Some(&ckpt),
        cancel,
        &mut on,
    )
    .map_err(|e| ApiError::Internal(e.to_string()))?;
    if !cancel.load(Ordering::SeqCst) {
        checkpoint::save(
            &neuvolex_features::train::model_path(&s.store),
            &t.model,
            None,
        )
        .map_err(|e| ApiError::Internal(e.to_string()))?;
        hub.publish(
            Some(&id),
            "training",
            serde_json::json!({"state": "model_saved", "psnr": t.psnr}),
        );
    }
    Ok(())
}

async fn renderer(rx: Arc<AsyncMutex<mpsc::Receiver<RenderJob>>>) {
    let mut rx = rx.lock().await;
    while let Some(job) = rx.recv().await {
        let RenderJob {
            session,
            params,
            tf,
            reply,
        } = job;
        let r = tokio::task::spawn_blocking(move || render(&session, &params, &tf)).await;
        let _ = reply.send(r.unwrap_or_else(|_| Err(ApiError::Internal("render panicked".into()))));
    }
}

/// Renders a session: incrementally (only the pixels the changed bricks affect) when the
/// frame, transfer function and classes are those of the last frame, from scratch otherwise.
fn render(
    s: &Arc<Session>,
    params: &neuvolex_render::RenderParams,
    tf: &neuvolex_render::TfFile,
) -> ApiResult<Vec<u8>> {
    use neuvolex_render::BrickSource;
    let mut guard = s.renderer.lock().unwrap_or_else(|p| p.into_inner());
    let st = guard.get_or_insert_with(|| crate::session::RenderState {
        renderer: neuvolex_render::Renderer::new(s.source(), 512 << 20),
        key: String::new(),
    });
    let classes = st.renderer.source().classes();
    let luts = tf.compile(&st.renderer.source().normaliser(), &classes);
    let dirty: Vec<[usize; 3]> =
        std::mem::take(&mut *s.dirty.lock().unwrap_or_else(|p| p.into_inner()))
            .into_iter()
            .collect();
    let key = format!("{params:?}|{tf:?}|{classes:?}");
    let img = if key == st.key && params.mode.needs_probs() {
        match st.renderer.update_bricks(&dirty)? {
            Some(img) => img,
            None => st.renderer.render(params, &luts)?,
        }
    } else {
        st.renderer.render(params, &luts)?
    };
    st.key = key;
    crate::imaging::png(img.width, img.height, 3, &img.to_rgb8())
}
