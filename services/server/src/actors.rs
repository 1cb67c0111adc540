//! The actors: tokio tasks with bounded mailboxes that schedule the library's pure per-brick
//! work on the blocking pool, an event hub, and a supervisor that restarts a failed actor and
//! reports the failure to clients.

use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use neuvolex_bricks::BrickStore;
use neuvolex_cluster::ClusterExecutor;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
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

/// What an actor's mailbox carries: work, or (fault injection, for tests of the supervisor)
/// an order to fail.
pub enum Mail<T> {
    /// A unit of work.
    Work(T),
    /// Panic: the supervisor must report it and restart the actor on the same mailbox.
    Crash,
}

/// A reserved place in the classifier's mailbox ([`Actors::reserve_classify`]).
pub struct ClassifyPermit(mpsc::OwnedPermit<Mail<ClassifyJob>>);

impl ClassifyPermit {
    /// Queues classification of `session` at `generation` (cannot fail: the place is held).
    pub fn send(self, session: Arc<Session>, generation: u64) {
        self.0.send(Mail::Work(ClassifyJob {
            session,
            generation,
        }));
    }
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
        /// Stops this training (also installed as the session's `train_cancel`).
        cancel: Arc<AtomicBool>,
        /// Its place among the concurrent trainings the server allows.
        slot: TrainingSlot,
        /// The store's writer lock, held while the training writes its checkpoint and model.
        lock: neuvolex_bricks::WriterLock,
    },
}

/// A place among the concurrent trainings the server allows ([`TrainingSlot::take`]); freed
/// when dropped, that is when the training ends however it ends.
pub struct TrainingSlot {
    running: Arc<AtomicUsize>,
}

impl TrainingSlot {
    /// A slot if fewer than `max` trainings hold one (`running` counts them).
    pub fn take(running: &Arc<AtomicUsize>, max: usize) -> Option<TrainingSlot> {
        running
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| TrainingSlot {
                running: running.clone(),
            })
    }
}

impl Drop for TrainingSlot {
    fn drop(&mut self) {
        self.running.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A render request with its reply slot.
pub struct RenderJob {
    /// The session.
    pub session: Arc<Session>,
    /// Frame parameters.
    pub params: neuvolex_render::RenderParams,
    /// Transfer function.
    pub tf: neuvolex_render::TfFile,
    /// Draw the current labels (class colours over a faint intensity context) rather than
    /// what `params.mode` draws.
    pub labels: bool,
    /// PNG bytes or an error.
    pub reply: oneshot::Sender<ApiResult<Vec<u8>>>,
    /// Set when the requester went away (its request timed out or its client left): the
    /// frame stops at its next batch of bricks.
    pub cancel: Arc<AtomicBool>,
    /// Counts the render in flight (classification yields to it) until the job ends.
    pub ticket: crate::memory::RenderTicket,
}

/// Sets its flag when dropped: a request's future dropped before its answer (timeout, client
/// gone) cancels the work it queued.
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::SeqCst);
    }
}

/// A volume file to ingest into a brick store (once: an existing store is reused).
pub struct IngestJob {
    /// The file.
    pub source: PathBuf,
    /// The store to create.
    pub dest: PathBuf,
    /// Name shown in progress events.
    pub name: String,
    /// The folder every byte read must come from (a detached NRRD header may name a data file
    /// elsewhere: that is refused).
    pub root: PathBuf,
    /// The opened store or an error.
    pub reply: oneshot::Sender<ApiResult<BrickStore>>,
}

/// A viewpoint recommendation with its reply slot.
pub struct ViewJob {
    /// The session.
    pub session: Arc<Session>,
    /// Clusters.
    pub k: usize,
    /// Candidate views.
    pub views: usize,
    /// How many distinct views to pick, and how far apart.
    pub pick: neuvolex_viewpoints::PickConfig,
    /// The result as JSON, or an error.
    pub reply: oneshot::Sender<ApiResult<serde_json::Value>>,
}

/// Handles to the actors' mailboxes.
#[derive(Clone)]
pub struct Actors {
    /// Events.
    pub hub: Hub,
    ingest: mpsc::Sender<Mail<IngestJob>>,
    classify: mpsc::Sender<Mail<ClassifyJob>>,
    train: mpsc::Sender<Mail<TrainCommand>>,
    render: mpsc::Sender<Mail<RenderJob>>,
    views: mpsc::Sender<Mail<ViewJob>>,
    compute: Arc<crate::compute::Compute>,
    /// Set once the server stops: renders in flight end at their next batch of bricks.
    stopping: Arc<AtomicBool>,
}

pub use crate::session::{trees_for, MIN_TREES, ROUND_TREE_VOXELS, TREES};

/// The actors' names, as [`Actors::crash`] and `actor_failed` events use them.
pub const ACTORS: [&str; 5] = ["ingest", "classifier", "trainer", "renderer", "viewpoints"];

type Inbox<T> = Arc<AsyncMutex<mpsc::Receiver<Mail<T>>>>;

fn mailbox<T>() -> (mpsc::Sender<Mail<T>>, Inbox<T>) {
    let (tx, rx) = mpsc::channel(MAILBOX);
    (tx, Arc::new(AsyncMutex::new(rx)))
}

fn busy<T>(what: &str) -> impl FnOnce(mpsc::error::TrySendError<T>) -> ApiError + '_ {
    move |_| ApiError::Busy(format!("the {what} is busy; try again"))
}

impl Actors {
    /// Starts the ingest, classifier, trainer, renderer and viewpoint actors under supervision,
    /// on the CPU engines.
    pub fn start(hub: Hub) -> Actors {
        Actors::start_with(hub, crate::compute::Compute::cpu(), None)
    }

    /// The engines the trainer and renderer run on.
    pub fn compute(&self) -> &crate::compute::ComputeInfo {
        &self.compute.info
    }

    /// Where sessions' rounds predict ([`crate::compute::Compute::accel`]).
    pub fn accelerator(&self) -> Option<Arc<dyn neuvolex_classify::accel::Accelerator>> {
        self.compute.accel.clone()
    }

    /// [`Actors::start`] with the trainer and renderer on `compute`'s engines, and
    /// classification and viewpoints on `cluster`'s workers when one is given.
    pub fn start_with(
        hub: Hub,
        compute: crate::compute::Compute,
        cluster: Option<ClusterExecutor>,
    ) -> Actors {
        let compute = Arc::new(compute);
        let (itx, irx) = mailbox::<IngestJob>();
        let (ctx, crx) = mailbox::<ClassifyJob>();
        let (ttx, trx) = mailbox::<TrainCommand>();
        let (rtx, rrx) = mailbox::<RenderJob>();
        let (vtx, vrx) = mailbox::<ViewJob>();
        let h = hub.clone();
        supervise("ingest", hub.clone(), move || {
            ingester(irx.clone(), h.clone())
        });
        // Classification, training and rendering each run on threads of their own, so none
        // starves the others of the shared pool (a long classification task queued ahead of a
        // training step's work, say); the processor is shared by the OS, and classification
        // and training yield to renders (see `Memory::yield_to_renders`).
        let pool = |name: &'static str| {
            Arc::new(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(rayon::current_num_threads())
                    .thread_name(move |i| format!("{name}-{i}"))
                    .build()
                    .unwrap_or_else(|e| panic!("cannot start the {name} threads: {e}")),
            )
        };
        let (h, cl, p) = (hub.clone(), cluster.clone(), pool("classify"));
        supervise("classifier", hub.clone(), move || {
            classifier(crx.clone(), h.clone(), cl.clone(), p.clone())
        });
        let (h, c, e, p) = (hub.clone(), ctx.clone(), compute.clone(), pool("train"));
        supervise("trainer", hub.clone(), move || {
            trainer(trx.clone(), h.clone(), c.clone(), e.clone(), p.clone())
        });
        let e = compute.clone();
        let stopping = Arc::new(AtomicBool::new(false));
        let pool = pool("render");
        let stop = stopping.clone();
        supervise("renderer", hub.clone(), move || {
            renderer(rrx.clone(), e.clone(), pool.clone(), stop.clone())
        });
        let (h, cl) = (hub.clone(), cluster);
        supervise("viewpoints", hub.clone(), move || {
            recommender(vrx.clone(), h.clone(), cl.clone())
        });
        Actors {
            hub,
            ingest: itx,
            classify: ctx,
            train: ttx,
            render: rtx,
            compute,
            views: vtx,
            stopping,
        }
    }

    /// The server is stopping: renders in flight and queued end at once (503).
    pub fn stop(&self) {
        self.stopping.store(true, Ordering::SeqCst);
    }

    /// Ingests `source` into the store `dest` (reused when it exists), publishing progress;
    /// every file read must lie under `root`.
    pub async fn ingest(
        &self,
        source: PathBuf,
        dest: PathBuf,
        name: String,
        root: PathBuf,
    ) -> ApiResult<BrickStore> {
        let (reply, rx) = oneshot::channel();
        self.ingest
            .try_send(Mail::Work(IngestJob {
                source,
                dest,
                name,
                root,
                reply,
            }))
            .map_err(busy("ingester"))?;
        rx.await
            .map_err(|_| ApiError::Internal("the ingester failed (restarted)".into()))?
    }

    /// Queues classification of `session` at `generation` (503 when the mailbox is full).
    pub fn classify(&self, session: Arc<Session>, generation: u64) -> ApiResult<()> {
        self.classify
            .try_send(Mail::Work(ClassifyJob {
                session,
                generation,
            }))
            .map_err(busy("classifier"))
    }

    /// Reserves a place in the classifier's mailbox before a change that needs classifying
    /// is made, so a full mailbox answers 503 with nothing changed (never "changed, but 503").
    pub fn reserve_classify(&self) -> ApiResult<ClassifyPermit> {
        self.classify
            .clone()
            .try_reserve_owned()
            .map(ClassifyPermit)
            .map_err(|_| ApiError::Busy("the classifier is busy; try again".into()))
    }

    /// Queues a training command.
    pub fn train(&self, cmd: TrainCommand) -> ApiResult<()> {
        self.train
            .try_send(Mail::Work(cmd))
            .map_err(busy("trainer"))
    }

    /// Renders a frame. Dropping the future before its answer (a request timeout, a client
    /// gone) cancels the frame.
    pub async fn render(
        &self,
        session: Arc<Session>,
        params: neuvolex_render::RenderParams,
        tf: neuvolex_render::TfFile,
        labels: bool,
    ) -> ApiResult<Vec<u8>> {
        let (reply, rx) = oneshot::channel();
        let cancel = Arc::new(AtomicBool::new(false));
        let _cancel_on_drop = CancelOnDrop(cancel.clone());
        let ticket = session.memory.render_started();
        self.render
            .try_send(Mail::Work(RenderJob {
                session,
                params,
                tf,
                labels,
                reply,
                cancel,
                ticket,
            }))
            .map_err(busy("renderer"))?;
        rx.await
            .map_err(|_| ApiError::Internal("the renderer failed (restarted)".into()))?
    }

    /// Recommends `pick.count` distinct viewpoints (each with its reason) from `views`
    /// candidates scored over `k` feature clusters, publishing progressive snapshots while
    /// bricks aggregate.
    pub async fn viewpoints(
        &self,
        session: Arc<Session>,
        k: usize,
        views: usize,
        pick: neuvolex_viewpoints::PickConfig,
    ) -> ApiResult<serde_json::Value> {
        let (reply, rx) = oneshot::channel();
        self.views
            .try_send(Mail::Work(ViewJob {
                session,
                k,
                views,
                pick,
                reply,
            }))
            .map_err(busy("viewpoint recommender"))?;
        rx.await.map_err(|_| {
            ApiError::Internal("the viewpoint recommender failed (restarted)".into())
        })?
    }

    /// Makes `actor` panic (fault injection for supervisor tests; the HTTP route exists only
    /// when [`crate::ServerConfig::fault_injection`] is set).
    pub fn crash(&self, actor: &str) -> ApiResult<()> {
        let r = match actor {
            "ingest" => self.ingest.try_send(Mail::Crash).is_ok(),
            "classifier" => self.classify.try_send(Mail::Crash).is_ok(),
            "trainer" => self.train.try_send(Mail::Crash).is_ok(),
            "renderer" => self.render.try_send(Mail::Crash).is_ok(),
            "viewpoints" => self.views.try_send(Mail::Crash).is_ok(),
            o => {
                return Err(ApiError::NotFound(format!(
                    "no actor '{}' (have {})",
                    o.escape_debug(),
                    ACTORS.join(", ")
                )))
            }
        };
        if r {
            Ok(())
        } else {
            Err(ApiError::Busy(format!("the {actor} mailbox is full")))
        }
    }
}

fn crash(actor: &str) -> ! {
    panic!("fault injection: {actor} ordered to fail")
}

async fn ingester(rx: Inbox<IngestJob>, hub: Hub) {
    let mut rx = rx.lock().await;
    while let Some(m) = rx.recv().await {
        let job = match m {
            Mail::Work(j) => j,
            Mail::Crash => crash("ingest"),
        };
        let IngestJob {
            source,
            dest,
            name,
            root,
            reply,
        } = job;
        let h = hub.clone();
        let r =
            tokio::task::spawn_blocking(move || ingest_one(&source, &dest, &name, &root, &h)).await;
        let _ = reply.send(r.unwrap_or_else(|_| Err(ApiError::Internal("ingest panicked".into()))));
    }
}

/// Ingests one file (the pure work is `neuvolex_ingest::ingest`), publishing progress.
fn ingest_one(
    source: &Path,
    dest: &Path,
    name: &str,
    root: &Path,
    hub: &Hub,
) -> ApiResult<BrickStore> {
    if let Ok(s) = BrickStore::open(dest) {
        return Ok(s);
    }
    let mut src = neuvolex_bricks::open_volume(source, None)
        .map_err(|e| ApiError::BadRequest(format!("{name}: {e}")))?;
    // The voxels may come from another file (a detached NRRD header's data file): it must
    // lie in the data root too.
    let data = src
        .path()
        .canonicalize()
        .map_err(|e| ApiError::BadRequest(format!("{name}: {}: {e}", src.path().display())))?;
    let root_c = root
        .canonicalize()
        .map_err(|e| ApiError::Internal(format!("{}: {e}", root.display())))?;
    if !data.starts_with(&root_c) {
        return Err(ApiError::Forbidden(format!(
            "{name}: its data file {} lies outside the data root",
            src.path().display()
        )));
    }
    let (mut stage, mut total) = ("", 0u64);
    let mut last = std::time::Instant::now();
    neuvolex_ingest::ingest(
        src.as_mut(),
        dest,
        &neuvolex_ingest::IngestOptions {
            brick: 32,
            overwrite: true,
            ..Default::default()
        },
        &mut |p| match p {
            neuvolex_bricks::Progress::Stage { name: n, total: t } => {
                (stage, total) = (n, t);
                hub.publish(None, "ingest", serde_json::json!({"volume": name, "stage": n, "done": 0, "total": t}));
            }
            neuvolex_bricks::Progress::Advance { done } if last.elapsed().as_millis() > 250 => {
                last = std::time::Instant::now();
                hub.publish(None, "ingest", serde_json::json!({"volume": name, "stage": stage, "done": done, "total": total}));
            }
            _ => {}
        },
    )
    .map_err(|e| ApiError::BadRequest(format!("{name}: {e}")))?;
    hub.publish(
        None,
        "ingest",
        serde_json::json!({"volume": name, "stage": "done"}),
    );
    Ok(BrickStore::open(dest)?)
}

async fn classifier(
    rx: Inbox<ClassifyJob>,
    hub: Hub,
    cluster: Option<ClusterExecutor>,
    pool: Arc<rayon::ThreadPool>,
) {
    let mut rx = rx.lock().await;
    let mut pending: Vec<ClassifyJob> = Vec::new();
    loop {
        if pending.is_empty() {
            match rx.recv().await {
                Some(Mail::Work(j)) => pending.push(j),
                Some(Mail::Crash) => crash("classifier"),
                None => break,
            }
        }
        while let Ok(m) = rx.try_recv() {
            match m {
                Mail::Work(j) => pending.push(j),
                Mail::Crash => crash("classifier"),
            }
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
        if let Err(e) = spawn_classify(job, hub.clone(), cluster.clone(), pool.clone()).await {
            if e.is_panic() {
                // Fail this actor: the supervisor reports it and restarts it on the same mailbox.
                std::panic::resume_unwind(e.into_panic());
            }
        }
    }
}

fn spawn_classify(
    job: ClassifyJob,
    hub: Hub,
    cluster: Option<ClusterExecutor>,
    pool: Arc<rayon::ThreadPool>,
) -> tokio::task::JoinHandle<()> {
    tokio::task::spawn_blocking(move || pool.install(|| classify_job(job, &hub, cluster.as_ref())))
}

/// Classifies one job's session on the calling thread (inside the classifier's pool),
/// publishing each brick and the outcome.
fn classify_job(job: ClassifyJob, hub: &Hub, cluster: Option<&ClusterExecutor>) {
    let s = job.session.clone();
    let id = s.id.clone();
    let on_brick = |b: [usize; 3], done: usize, total: usize| {
        hub.publish(
                Some(&id),
                "classified",
                serde_json::json!({"brick": b, "done": done, "total": total, "generation": job.generation}),
            );
    };
    let t = std::time::Instant::now();
    let r = s.classify_with(job.generation, s.round_trees(), &on_brick, cluster);
    let status = s.status.read().unwrap_or_else(|p| p.into_inner()).clone();
    tracing::info!(
        session = %id,
        generation = job.generation,
        state = %status.state,
        bricks = status.done,
        seconds = t.elapsed().as_secs_f64(),
        "classification"
    );
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
}

/// Starts each training as its own task (the HTTP layer caps how many run at once), so the
/// mailbox is never held up by a running training.
async fn trainer(
    rx: Inbox<TrainCommand>,
    hub: Hub,
    classify: mpsc::Sender<Mail<ClassifyJob>>,
    compute: Arc<crate::compute::Compute>,
    pool: Arc<rayon::ThreadPool>,
) {
    let mut rx = rx.lock().await;
    while let Some(m) = rx.recv().await {
        let TrainCommand::Start {
            session,
            epochs,
            resume,
            cancel,
            slot,
            lock,
        } = match m {
            Mail::Work(c) => c,
            Mail::Crash => crash("trainer"),
        };
        let (h, c, e, p) = (hub.clone(), classify.clone(), compute.clone(), pool.clone());
        tokio::spawn(async move {
            let (s, flag, h2) = (session.clone(), cancel.clone(), h.clone());
            let r = tokio::task::spawn_blocking(move || {
                p.install(|| train(&s, epochs, resume, &flag, &h2, &c, &e))
            })
            .await;
            {
                // Only this training's flag: a newer one may have been installed since.
                let mut tc = session
                    .train_cancel
                    .lock()
                    .unwrap_or_else(|p| p.into_inner());
                if tc.as_ref().is_some_and(|t| Arc::ptr_eq(t, &cancel)) {
                    *tc = None;
                }
            }
            drop(slot);
            drop(lock);
            let err = match r {
                Ok(Ok(())) => return,
                Ok(Err(e)) => e.to_string(),
                Err(_) => "training panicked".to_string(),
            };
            h.publish(
                Some(&session.id),
                "training",
                serde_json::json!({"state": "failed", "error": err}),
            );
        });
    }
}

/// Re-classifies `s` with its newest model when its feature set reads the INR, it has
/// strokes and the classifier is not busy with it (a snapshot arriving mid-run waits for the
/// next one, so a run always ends). Returns the generation queued, if any.
fn reclassify(
    s: &Arc<Session>,
    classify: &mpsc::Sender<Mail<ClassifyJob>>,
    force: bool,
) -> Option<u64> {
    if !s.uses_model() {
        return None;
    }
    let has_strokes = !s
        .strokes
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .is_empty();
    let state = s
        .status
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .state
        .clone();
    if !has_strokes || (!force && (state == "training" || state == "classifying")) {
        return None;
    }
    let generation = s.bump_generation();
    classify
        .try_send(Mail::Work(ClassifyJob {
            session: s.clone(),
            generation,
        }))
        .ok()
        .map(|()| generation)
}

/// Steps between model snapshots while training in the service (each one refreshes the
/// recommended views' features, and the classification when its feature set reads the INR).
pub const SNAPSHOT_EVERY: u64 = 40;

fn train(
    s: &Arc<Session>,
    epochs: f64,
    resume: bool,
    cancel: &AtomicBool,
    hub: &Hub,
    classify: &mpsc::Sender<Mail<ClassifyJob>>,
    compute: &crate::compute::Compute,
) -> ApiResult<()> {
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
        checkpoint_every: SNAPSHOT_EVERY,
        preview_every: SNAPSHOT_EVERY / 2,
        ..TrainConfig::default()
    };
    let id = s.id.clone();
    let mut last = std::time::Instant::now();
    let mut on = |e: TrainEvent| match e {
        // Between steps, a render in flight goes first.
        TrainEvent::Step { .. } if s.memory.renders_in_flight() > 0 => s.memory.yield_to_renders(),
        TrainEvent::Step {
            epoch,
            psnr,
            loss,
            samples_per_sec,
            ..
        } if last.elapsed().as_millis() > 250 => {
            last = std::time::Instant::now();
            hub.publish(
                Some(&id),
                "training",
                serde_json::json!({"state": "running", "epoch": epoch, "psnr": psnr, "loss": loss, "samples_per_sec": samples_per_sec, "backend": compute.info.train}),
            );
        }
        TrainEvent::Preview {
            step,
            width,
            height,
            recon,
            truth,
            psnr,
            ..
        } => {
            if let Ok(png) = crate::imaging::preview_png(width, height, &recon, &truth) {
                *s.preview.write().unwrap_or_else(|p| p.into_inner()) = Some((png, psnr));
                hub.publish(
                    Some(&id),
                    "preview",
                    serde_json::json!({"step": step, "psnr": psnr}),
                );
            }
        }
        TrainEvent::Checkpoint { step, path } => match checkpoint::load(&path) {
            Ok(l) => {
                let version = s.set_model(l.model);
                let generation = reclassify(s, classify, false);
                hub.publish(
                    Some(&id),
                    "training",
                    serde_json::json!({"state": "snapshot", "step": step, "model_version": version, "generation": generation, "classifies": s.uses_model()}),
                );
            }
            Err(e) => tracing::warn!("snapshot {}: {e}", path.display()),
        },
        TrainEvent::Finished {
            psnr, stopped_by, ..
        } => hub.publish(
            Some(&id),
            "training",
            serde_json::json!({"state": "finished", "psnr": psnr, "stopped_by": stopped_by}),
        ),
        _ => {}
    };
    let inr = InrConfig::default();
    let r = match compute.gpu() {
        #[cfg(feature = "gpu")]
        Some(ctx) => neuvolex_features_gpu::train_gpu(
            ctx,
            &s.store,
            &inr,
            &cfg,
            loaded,
            Some(&ckpt),
            cancel,
            &mut on,
        )
        .map(|g| g.trained)
        .map_err(neuvolex_features::FeatureError::from),
        _ => train(&s.store, &inr, &cfg, loaded, Some(&ckpt), cancel, &mut on),
    };
    let t = match r {
        Ok(t) => t,
        // Stopped (by the user or a shutdown): its checkpoint is saved for `resume`.
        Err(neuvolex_features::FeatureError::Cancelled) => {
            hub.publish(
                Some(&id),
                "training",
                serde_json::json!({"state": "stopped", "checkpoint": ckpt.exists()}),
            );
            return Ok(());
        }
        Err(e) => return Err(ApiError::Internal(e.to_string())),
    };
    // The model file is what `neuvolex classify` and later sessions use; a stopped run keeps
    // its checkpoint for `resume`, and its last snapshot serves this session.
    if !cancel.load(Ordering::SeqCst) {
        checkpoint::save(
            neuvolex_features::train::model_path(&s.store),
            &t.model,
            None,
        )
        .map_err(|e| ApiError::Internal(e.to_string()))?;
        let version = s.set_model(t.model);
        let generation = reclassify(s, classify, true);
        hub.publish(
            Some(&id),
            "training",
            serde_json::json!({"state": "model_saved", "psnr": t.psnr, "model_version": version, "generation": generation, "classifies": s.uses_model()}),
        );
    }
    Ok(())
}

async fn renderer(
    rx: Inbox<RenderJob>,
    compute: Arc<crate::compute::Compute>,
    pool: Arc<rayon::ThreadPool>,
    stopping: Arc<AtomicBool>,
) {
    let mut rx = rx.lock().await;
    while let Some(m) = rx.recv().await {
        let job = match m {
            Mail::Work(j) => j,
            Mail::Crash => crash("renderer"),
        };
        let RenderJob {
            session,
            params,
            tf,
            labels,
            reply,
            cancel,
            ticket,
        } = job;
        let memory = session.memory.clone();
        // Nobody waits for it any more: skip it.
        if cancel.load(Ordering::SeqCst) || reply.is_closed() {
            memory.render_cancelled();
            continue;
        }
        let gpu = compute.render_gpu();
        let (p, stop) = (pool.clone(), stopping.clone());
        let poll: neuvolex_render::CancelPoll =
            Arc::new(move || cancel.load(Ordering::SeqCst) || stop.load(Ordering::SeqCst));
        let r = tokio::task::spawn_blocking(move || {
            p.install(|| render(&session, &params, &tf, labels, gpu, poll))
        })
        .await;
        drop(ticket);
        let r = match r {
            Ok(Err(ApiError::Busy(m))) => {
                memory.render_cancelled();
                Err(ApiError::Busy(if stopping.load(Ordering::SeqCst) {
                    "the server is shutting down: the render was cancelled".into()
                } else {
                    m
                }))
            }
            Ok(r) => r,
            Err(_) => Err(ApiError::Internal("render panicked".into())),
        };
        let _ = reply.send(r);
    }
}

/// Renders a session: on the GPU when the service has one (whole frames), else on the CPU,
/// incrementally (only the pixels the changed bricks affect) when the frame, transfer function
/// and classes are those of the last frame, from scratch otherwise. `labels` draws the current
/// labels ([`crate::session::SessionSource`]) in the probability-intensity mode with the
/// transfer function's label tables ([`neuvolex_render::TfFile::compile_labels`]).
fn render(
    s: &Arc<Session>,
    params: &neuvolex_render::RenderParams,
    tf: &neuvolex_render::TfFile,
    labels: bool,
    gpu: bool,
    cancel: neuvolex_render::CancelPoll,
) -> ApiResult<Vec<u8>> {
    use neuvolex_render::BrickSource;
    let mut params = *params;
    if labels {
        params.mode = neuvolex_render::Mode::ProbIntensity;
    }
    let params = &params;
    let mut guard = s.renderer.lock().unwrap_or_else(|p| p.into_inner());
    let st = guard.get_or_insert_with(|| crate::session::RenderState {
        // Its bricks in the server's one render cache, under one budget for all sessions.
        renderer: neuvolex_render::Renderer::with_cache(
            s.source(),
            s.memory.render.clone(),
            s.render_owner,
        ),
        key: String::new(),
        labels: String::new(),
        #[cfg(feature = "gpu")]
        gpu: None,
    });
    // What the drawn channels depend on beyond the dirty bricks: the flavour, and for labels
    // the prior's verdict (a new one, or the toggle, changes labels anywhere).
    let flavour = if labels {
        let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let prior = s.active_prior(&probs).map(|p| p.generation);
        format!("labels|{}|{prior:?}", probs.generation)
    } else {
        "probabilities".to_string()
    };
    let all = || -> Vec<[usize; 3]> { s.store.bricks().map(|b| b.index).collect() };
    let switched = st.labels != flavour;
    let luts_for = |src: &crate::session::SessionSource| {
        let (norm, classes) = (src.normaliser(), src.classes());
        if labels {
            tf.compile_labels(&norm, &classes, LABEL_OPACITY, LABEL_CONTEXT)
        } else {
            tf.compile(&norm, &classes)
        }
    };
    #[cfg(feature = "gpu")]
    if gpu {
        if st.gpu.is_none() {
            st.gpu = Some(
                neuvolex_render::gpu::GpuRenderer::new(s.source())
                    .map_err(|e| ApiError::Internal(e.to_string()))?,
            );
        }
        if let Some(g) = st.gpu.as_mut() {
            g.source_mut().labels = labels;
            let luts = luts_for(g.source());
            // Bricks stay resident on the GPU: the changed ones (and their neighbours) are
            // uploaded again; all of them when the drawn channels changed.
            let mut dirty: Vec<[usize; 3]> =
                std::mem::take(&mut *s.dirty.lock().unwrap_or_else(|p| p.into_inner()))
                    .into_iter()
                    .collect();
            if switched {
                dirty = all();
                st.labels = flavour;
            }
            if let Err(e) = g.invalidate(&dirty) {
                restore_dirty(s, dirty);
                st.labels.clear();
                return Err(e.into());
            }
            let img = g.render(params, &luts)?;
            return crate::imaging::png(img.width, img.height, 3, &img.to_rgb8());
        }
    }
    #[cfg(not(feature = "gpu"))]
    let _ = (gpu, &all);
    st.renderer.set_cancel(Some(cancel));
    if switched {
        st.renderer.source_mut().labels = labels;
        st.renderer.forget();
        st.key.clear();
        st.labels = flavour;
    }
    let classes = st.renderer.source().classes();
    let luts = luts_for(st.renderer.source());
    let dirty: Vec<[usize; 3]> =
        std::mem::take(&mut *s.dirty.lock().unwrap_or_else(|p| p.into_inner()))
            .into_iter()
            .collect();
    let key = format!("{params:?}|{tf:?}|{classes:?}");
    let frame = if key == st.key && params.mode.needs_probs() {
        st.renderer.update_bricks(&dirty).and_then(|img| match img {
            Some(img) => Ok(img),
            None => st.renderer.render(params, &luts),
        })
    } else {
        // The changed bricks' cached copies are stale for this frame too.
        st.renderer
            .invalidate(&dirty)
            .and_then(|()| st.renderer.render(params, &luts))
    };
    let img = match frame {
        Ok(img) => img,
        Err(e) => {
            // A cancelled or failed frame has not drawn the changed bricks: they stay dirty,
            // and the next frame starts from scratch, so no change is ever lost.
            restore_dirty(s, dirty);
            st.key.clear();
            return Err(e.into());
        }
    };
    st.key = key;
    crate::imaging::png(img.width, img.height, 3, &img.to_rgb8())
}

/// Puts bricks a render took from the session's dirty set back into it.
fn restore_dirty(s: &Session, dirty: Vec<[usize; 3]>) {
    s.dirty
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .extend(dirty);
}

/// Opacity of a labelled voxel in the 3-D label view.
pub const LABEL_OPACITY: f32 = 0.6;
/// The label view's intensity context: the intensity map's opacity times this.
pub const LABEL_CONTEXT: f32 = 0.12;

async fn recommender(rx: Inbox<ViewJob>, hub: Hub, cluster: Option<ClusterExecutor>) {
    let mut rx = rx.lock().await;
    while let Some(m) = rx.recv().await {
        let job = match m {
            Mail::Work(j) => j,
            Mail::Crash => crash("viewpoints"),
        };
        let ViewJob {
            session,
            k,
            views,
            pick,
            reply,
        } = job;
        let (h, c) = (hub.clone(), cluster.clone());
        let r = tokio::task::spawn_blocking(move || {
            recommend(&session, k, views, &pick, &h, c.as_ref())
        })
        .await;
        let _ = reply.send(r.unwrap_or_else(|_| {
            Err(ApiError::Internal(
                "viewpoint recommendation panicked".into(),
            ))
        }));
    }
}

/// The view-entropy aggregation over a session's feature bricks (the pure pipeline is
/// `neuvolex_viewpoints::recommend`): mini-batch k-means, then per-brick cluster partials
/// merged progressively, with a snapshot of the best view published as bricks arrive. With a
/// cluster, every per-brick step runs as tasks on its workers (Lloyd k-means, whose passes
/// distribute; mini-batch updates are sequential). The views returned are
/// `neuvolex_viewpoints::pick_distinct`'s: `pick.count` of them, `pick.min_angle` apart, each
/// with the reason it was picked.
fn recommend(
    s: &Arc<Session>,
    k: usize,
    views: usize,
    pick: &neuvolex_viewpoints::PickConfig,
    hub: &Hub,
    cluster: Option<&ClusterExecutor>,
) -> ApiResult<serde_json::Value> {
    use neuvolex_classify::features::{BrickFeatures, FeatureSet};
    use neuvolex_viewpoints::{
        direction_to_view, fibonacci_sphere, recommend, KMeansConfig, RecommendConfig,
        ViewpointError,
    };
    let model = s.current_model();
    let set: FeatureSet = if model.is_some() { "paper" } else { "local" }
        .parse()
        .map_err(ApiError::Internal)?;
    let version = model.as_ref().map_or(0, |m| m.0);
    let model_for_blob = model.clone();
    let fx = BrickFeatures::new(&s.store, set.clone(), model.map(|m| m.1), false)?;
    let name = set.to_string();
    let bricks = s.store.occupied_bricks(None);
    let err = |e: String| ViewpointError::Input(e);
    let cfg = RecommendConfig {
        kmeans: KMeansConfig {
            k,
            algorithm: neuvolex_viewpoints::kmeans::Algorithm::MiniBatch { epochs: 3 },
            ..Default::default()
        },
        views,
        ..Default::default()
    };
    let dirs = fibonacci_sphere(views);
    let step = (bricks.len() / 10).max(1);
    let id = s.id.clone();
    let mut on_progress = |done: usize, agg: &neuvolex_viewpoints::scores::Aggregator| {
        if !done.is_multiple_of(step) && done != bricks.len() {
            return;
        }
        if let Ok(sc) = agg.snapshot(&dirs) {
            if let Some((best, h)) = sc
                .entropy
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
            {
                let (az, el) = direction_to_view(dirs[best]);
                hub.publish(
                    Some(&id),
                    "viewpoints_progress",
                    serde_json::json!({"bricks": done, "total": bricks.len(),
                        "best": {"azimuth": az, "elevation": el, "entropy": h}}),
                );
            }
        }
    };
    let rec = if let Some(c) = cluster {
        let (model_id, model_bytes) = match &model_for_blob {
            Some((v, m)) => {
                let (id, b) = s.model_blob(*v, m)?;
                (Some(id), Some(b))
            }
            None => (None, None),
        };
        let spec = neuvolex_classify::pipeline::FeatureSpec {
            store: neuvolex_classify::pipeline::store_path_string(s.store.root()),
            features: name.clone(),
            stored_features: false,
            model_blob: model_id.as_ref().map(|id| format!("model-{id}")),
            model: model_id,
        };
        let src = neuvolex_classify::pipeline::OpenedFeatures {
            store: s.store.clone(),
            model: model_for_blob.as_ref().map(|m| m.1.clone()),
            set: set.clone(),
            spec,
            model_bytes,
        };
        let cfg = RecommendConfig {
            kmeans: KMeansConfig {
                algorithm: neuvolex_viewpoints::kmeans::Algorithm::Lloyd,
                ..cfg.kmeans
            },
            ..cfg
        };
        neuvolex_viewpoints::distributed::recommend_on(
            c,
            src,
            &cfg,
            4,
            &mut |_| {},
            &mut on_progress,
        )
        .map(|r| r.0)
    } else {
        recommend(
            bricks.len(),
            fx.channels(),
            |i| {
                s.features
                    .get(&name, version, &fx, &bricks[i])
                    .map_err(|e| err(e.to_string()))
            },
            |i| {
                Ok(s.store
                    .derived(&bricks[i])
                    .map_err(|e| err(e.to_string()))?
                    .gradient)
            },
            s.store.info().spacing,
            &cfg,
            &mut on_progress,
        )
    }
    .map_err(|e| ApiError::BadRequest(e.to_string()))?;
    let picks = neuvolex_viewpoints::pick_distinct(&rec.summary, &rec.scores, pick)
        .map_err(|e| ApiError::BadRequest(e.to_string()))?;
    let picked: Vec<serde_json::Value> = picks
        .picks
        .iter()
        .map(|p| {
            let (az, el) = direction_to_view(rec.scores.views[p.view]);
            serde_json::json!({"azimuth": az, "elevation": el, "entropy": p.entropy,
                "mass": p.mass, "gain": p.gain, "in_view": p.in_view, "new": p.new,
                "nearest": p.nearest, "why": p.why, "reason": p.reason})
        })
        .collect();
    let out = serde_json::json!({
        "features": name, "views": picked,
        "count": pick.count, "min_angle": pick.min_angle, "clusters": picks.clusters,
        "clusters_used": rec.kmeans.counts.iter().filter(|&&c| c > 0).count(),
        "uncovered": picks.uncovered.len(),
        "seconds": rec.kmeans_seconds + rec.scoring_seconds,
    });
    hub.publish(Some(&s.id), "viewpoints", out.clone());
    Ok(out)
}

#[cfg(test)]
mod tree_tests {
    use super::*;

    #[test]
    fn large_volumes_get_fewer_trees_never_below_the_floor() {
        assert_eq!(trees_for(1_380_000), TREES, "the abdomen CT");
        assert_eq!(trees_for(2_000_000), TREES);
        assert_eq!(trees_for(2_500_000), 40);
        assert_eq!(trees_for(5_900_000), MIN_TREES, "a 6 M-voxel MRI");
        assert_eq!(trees_for(118_000_000), MIN_TREES, "the phantom");
        assert_eq!(trees_for(0), TREES);
    }
}
