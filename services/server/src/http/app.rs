//! The server's configuration and shared state: sessions opened, closed when idle, saved at
//! shutdown.

use super::blocking;
use crate::actors::{Actors, Hub};
use crate::cache::FeatureCache;
use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use actix_web::web;
use neuvolex_bricks::BrickStore;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

/// Default for [`ServerConfig::max_sessions`]: most sessions open at once (each holds its
/// strokes, probabilities and render state; memory stays bounded).
pub const MAX_SESSIONS: usize = 32;

/// Largest JSON body accepted.
pub const MAX_BODY: usize = 4 << 20;

/// Where volumes come from and where derived stores go, who may connect, and the limits.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Only volumes under this folder can be opened.
    pub data_root: PathBuf,
    /// Stores ingested from plain files are kept here.
    pub work_dir: PathBuf,
    /// The volume the UI opens first (relative to the data root).
    pub default_volume: Option<String>,
    /// A second folder of volumes the server made (the generated phantom), addressed as
    /// `generated/NAME`.
    pub generated_root: Option<PathBuf>,
    /// Feature-cache budget, bytes, across all sessions together.
    pub feature_cache_bytes: usize,
    /// Render-cache budget, bytes, for every session's renderer together.
    pub render_cache_bytes: usize,
    /// Class-probability budget, bytes, for all sessions together (one byte per voxel and
    /// class of each classified session).
    pub probs_bytes: usize,
    /// Exposes `POST /api/debug/crash/{actor}` (supervisor tests only).
    pub fault_injection: bool,
    /// Engines of the trainer and renderer: cpu, gpu (any adapter) or auto (a hardware GPU).
    pub backend: neuvolex_features::Backend,
    /// Runs classification and viewpoints on this cluster's workers (`serve --cluster`).
    pub cluster: Option<neuvolex_cluster::ClusterExecutor>,
    /// When set, every request must carry this token (`Authorization: Bearer`, the
    /// `X-Neuvolex-Token` header, the cookie set by the first visit, or `?token=`); others get
    /// 401. `neuvolex serve` sets one whenever it listens beyond loopback.
    pub token: Option<String>,
    /// Refuse requests whose `Host` is not a loopback name (a server on loopback without a
    /// token; guards against DNS rebinding).
    pub local_only: bool,
    /// Most sessions open at once; one more gets 503.
    pub max_sessions: usize,
    /// Most trainings running at once; one more gets 503.
    pub max_trainings: usize,
    /// Longest a request may take before it is answered with 503 (event streams excepted).
    pub request_timeout: Duration,
    /// A session no request has named for this long, and not training, is saved and closed,
    /// giving its share of the caches back (`None`: never).
    pub idle_close: Option<Duration>,
    /// Largest feature array (bytes, f16 before compression) a session computes in the
    /// background when its volume opens and keeps in the store, so the first stroke and
    /// every later open find the features ready; 0 turns the background pass off.
    pub feature_store_bytes: u64,
}

impl ServerConfig {
    /// A configuration with the default budgets for all sessions together (feature cache
    /// 512 MiB, render cache 512 MiB, probabilities 2 GiB), features kept in stores up to
    /// [`DEFAULT_FEATURE_STORE_BYTES`], no token,
    /// [`MAX_SESSIONS`] sessions, one training at a time, a 60 s request timeout and no fault
    /// injection.
    pub fn new(data_root: PathBuf, work_dir: PathBuf) -> Self {
        ServerConfig {
            data_root,
            work_dir,
            default_volume: None,
            generated_root: None,
            feature_cache_bytes: 512 << 20,
            render_cache_bytes: 512 << 20,
            probs_bytes: 2 << 30,
            fault_injection: false,
            backend: neuvolex_features::Backend::Cpu,
            cluster: None,
            token: None,
            local_only: false,
            max_sessions: MAX_SESSIONS,
            max_trainings: 1,
            request_timeout: Duration::from_secs(60),
            idle_close: Some(DEFAULT_IDLE_CLOSE),
            feature_store_bytes: DEFAULT_FEATURE_STORE_BYTES,
        }
    }
}

/// Default for [`ServerConfig::feature_store_bytes`]: 4 GiB (the filter bank and position
/// take 106 bytes a voxel, so volumes up to about 40 M voxels, a 512 x 512 x 150 CT).
pub const DEFAULT_FEATURE_STORE_BYTES: u64 = 4 << 30;

/// How long a session may sit unused before it is saved and closed.
pub const DEFAULT_IDLE_CLOSE: Duration = Duration::from_secs(30 * 60);

/// Shared state of the server.
pub struct AppState {
    /// Configuration.
    pub cfg: ServerConfig,
    /// Open sessions by id.
    pub sessions: RwLock<HashMap<String, Arc<Session>>>,
    /// The actors.
    pub actors: Actors,
    /// Feature bricks of every session, under one budget (the same as `memory.features`).
    pub features: Arc<FeatureCache>,
    /// What sessions hold in memory, under the server's budgets.
    pub memory: Arc<crate::memory::Memory>,
    /// Trainings running now.
    pub trainings: Arc<AtomicUsize>,
    /// Sessions being opened (counted against the session limit while they ingest).
    pub(crate) opening: AtomicUsize,
    /// Set once shutdown began: new requests get 503 and event streams end.
    pub(crate) shutdown: tokio::sync::watch::Sender<bool>,
    pub(crate) started: Instant,
    pub(crate) next: AtomicU64,
    /// Held while a saved session is reopened, so two tabs resuming it at once open it once.
    resuming: tokio::sync::Mutex<()>,
}

impl AppState {
    /// State with the actors started (call inside a tokio runtime).
    pub fn new(cfg: ServerConfig) -> web::Data<AppState> {
        let compute = crate::compute::Compute::resolve(cfg.backend);
        let actors = Actors::start_with(Hub::default(), compute, cfg.cluster.clone());
        let memory = crate::memory::Memory::new(
            cfg.feature_cache_bytes,
            cfg.render_cache_bytes,
            cfg.probs_bytes,
        );
        // Label bricks no saved session lists any more (rounds forgotten, sessions deleted).
        let removed = crate::labels::collect_garbage(&cfg.work_dir);
        if removed > 0 {
            tracing::info!("removed {removed} label bricks no saved session lists");
        }
        web::Data::new(AppState {
            features: memory.features.clone(),
            memory,
            cfg,
            sessions: RwLock::new(HashMap::new()),
            actors,
            trainings: Arc::new(AtomicUsize::new(0)),
            opening: AtomicUsize::new(0),
            shutdown: tokio::sync::watch::channel(false).0,
            started: Instant::now(),
            next: AtomicU64::new(1),
            resuming: tokio::sync::Mutex::new(()),
        })
    }

    pub(crate) fn session(&self, id: &str) -> ApiResult<Arc<Session>> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(id)
            .cloned()
            .inspect(|s| {
                s.last_used
                    .store(crate::session::now_ms(), Ordering::Relaxed)
            })
            .ok_or_else(|| ApiError::NotFound(format!("no session '{}'", id.escape_debug())))
    }

    /// Saves and closes every session unused for `cfg.idle_close` that is not training, and
    /// returns their ids (a session whose state cannot be saved stays open and is logged).
    pub fn close_idle(&self) -> Vec<String> {
        let Some(idle) = self.cfg.idle_close else {
            return Vec::new();
        };
        let now = crate::session::now_ms();
        let mut closed = Vec::new();
        for s in self.all_sessions() {
            let unused = now.saturating_sub(s.last_used.load(Ordering::Relaxed));
            let training = s
                .train_cancel
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .is_some();
            if unused < idle.as_millis() as u64 || training {
                continue;
            }
            match self.close(&s) {
                Ok(()) => {
                    tracing::info!(
                        "closed session {} ({}): idle for {} s",
                        s.id,
                        s.name,
                        unused / 1000
                    );
                    closed.push(s.id.clone());
                }
                Err(e) => tracing::warn!("idle session {} stays open: {e}", s.id),
            }
        }
        closed
    }

    /// Runs [`Self::close_idle`] every so often (a quarter of `cfg.idle_close`, at most a
    /// minute) until shutdown; spawn it on the server's runtime.
    pub async fn reap_idle(state: web::Data<AppState>) {
        let Some(idle) = state.cfg.idle_close else {
            return;
        };
        let every = (idle / 4).clamp(Duration::from_millis(100), Duration::from_secs(60));
        Self::every(state, every, |st| {
            st.close_idle();
        })
        .await
    }

    /// Runs `f` on the blocking pool every `period` until shutdown.
    async fn every(
        state: web::Data<AppState>,
        period: Duration,
        f: impl Fn(&AppState) + Send + Sync + Copy + 'static,
    ) {
        let mut stop = state.shutdown.subscribe();
        loop {
            tokio::select! {
                _ = tokio::time::sleep(period) => {}
                _ = stop.changed() => return,
            }
            if state.shutting_down() {
                return;
            }
            let st = state.clone();
            let _ = web::block(move || f(&st)).await;
        }
    }

    /// Every open session.
    pub fn all_sessions(&self) -> Vec<Arc<Session>> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .values()
            .cloned()
            .collect()
    }

    /// True once shutdown began.
    pub fn shutting_down(&self) -> bool {
        *self.shutdown.borrow()
    }

    /// Opens `rel` (a store, or a file the ingest actor turns into a store in the work
    /// folder) as a new session.
    pub async fn open(&self, rel: &str) -> ApiResult<Arc<Session>> {
        self.open_as(rel, new_id()).await
    }

    /// Re-attaches to session `id`: the open one, or the one saved under that id
    /// ([`session_path`]), reopened with its strokes, redo stack, classes, transfer function,
    /// features, prior, page settings and label history, so it shows the labels it showed
    /// when it was saved. Returns the session and whether it was reopened from its file.
    pub async fn resume(&self, id: &str) -> ApiResult<(Arc<Session>, bool)> {
        neuvolex_session::validate_id(id).map_err(ApiError::BadRequest)?;
        let _one = self.resuming.lock().await;
        if let Ok(s) = self.session(id) {
            return Ok((s, false));
        }
        let p = session_path(&self.cfg.work_dir, id);
        let src = p.display().to_string();
        let p2 = p.clone();
        let text = blocking(move || match std::fs::read_to_string(&p2) {
            Ok(t) => Ok(t),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(ApiError::NotFound(format!(
                "no session '{id}' is open or saved",
                id = p2.file_stem().unwrap_or_default().to_string_lossy()
            ))),
            Err(e) => Err(ApiError::Internal(format!("{}: {e}", p2.display()))),
        })
        .await?;
        let f = neuvolex_session::SessionFile::parse(&text, &src)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        let s = self.open_as(&f.volume, id.to_string()).await?;
        let (s2, work) = (s.clone(), self.cfg.work_dir.clone());
        let restored = blocking(move || restore(&work, &s2, &f, &src)).await;
        match restored {
            Ok(g) => {
                if !s
                    .strokes
                    .read()
                    .unwrap_or_else(|p| p.into_inner())
                    .is_empty()
                {
                    self.actors.classify(s.clone(), g)?;
                }
                Ok((s, true))
            }
            Err(e) => {
                // A file that does not fit the volume leaves nothing half-open.
                stop_work(&s);
                self.forget(&s);
                Err(e)
            }
        }
    }

    /// The saved and the open sessions, newest first: id, volume, whether open, strokes, and
    /// when last changed or saved (ms since the Unix epoch).
    pub fn list(&self) -> Vec<serde_json::Value> {
        let open = self.all_sessions();
        let mut out: Vec<(u64, serde_json::Value)> = open
            .iter()
            .map(|s| {
                let t = s.last_used.load(Ordering::Relaxed);
                (
                    t,
                    serde_json::json!({
                        "id": s.id, "volume": s.name, "open": true,
                        "strokes": s.strokes.read().unwrap_or_else(|p| p.into_inner()).len(),
                        "updated_ms": t,
                    }),
                )
            })
            .collect();
        for (id, f) in saved_sessions(&self.cfg.work_dir) {
            if open.iter().any(|s| s.id == id) {
                continue;
            }
            let t = f.saved_ms.unwrap_or(0);
            out.push((
                t,
                serde_json::json!({
                    "id": id, "volume": f.volume, "open": false,
                    "strokes": f.strokes.len(), "updated_ms": t,
                }),
            ));
        }
        out.sort_by_key(|x| std::cmp::Reverse(x.0));
        out.into_iter().map(|x| x.1).collect()
    }

    /// The newest saved session of volume `rel` that is not open, if any.
    pub fn newest_saved(&self, rel: &str) -> Option<String> {
        let open = self.all_sessions();
        saved_sessions(&self.cfg.work_dir)
            .into_iter()
            .filter(|(id, f)| f.volume == rel && !open.iter().any(|s| &s.id == id))
            .max_by_key(|(_, f)| f.saved_ms.unwrap_or(0))
            .map(|(id, _)| id)
    }

    /// Writes every open session whose state changed since it was last saved (the autosave,
    /// [`Self::autosave`]); returns the files written. A failed write is logged and retried at
    /// the next pass.
    pub fn save_changed(&self) -> Vec<PathBuf> {
        let mut out = Vec::new();
        for s in self.all_sessions() {
            if s.closing.load(Ordering::SeqCst) || !unsaved(&s) {
                continue;
            }
            let t = std::time::Instant::now();
            let r = save_state(&self.cfg.work_dir, &s);
            let took = t.elapsed();
            if took > AUTOSAVE {
                tracing::warn!(
                    "session {} took {} ms to save (the autosave runs every {} ms)",
                    s.id,
                    took.as_millis(),
                    AUTOSAVE.as_millis()
                );
            }
            match r {
                Ok(Some(p)) => out.push(p),
                Ok(None) => {}
                Err(e) => tracing::warn!("session {} not saved: {e}", s.id),
            }
        }
        out
    }

    /// Saves changed sessions every [`AUTOSAVE`] until shutdown (spawn it on the server's
    /// runtime): a crash or `kill -9` loses at most that much of the work, plus the write.
    pub async fn autosave(state: web::Data<AppState>) {
        Self::every(state, AUTOSAVE, |st| {
            st.save_changed();
        })
        .await
    }

    /// Takes a session out of the server (its work already stopped) and gives back what it
    /// held in memory: after its save ([`Self::close`]), or unsaved when it failed to reopen.
    fn forget(&self, s: &Session) {
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&s.id);
        s.closing.store(true, Ordering::SeqCst);
        s.release_memory();
    }

    /// Opens `rel` as a session named `id`.
    async fn open_as(&self, rel: &str, id: String) -> ApiResult<Arc<Session>> {
        // Reserve a place first, so concurrent opens (each ingesting for a while) cannot
        // exceed the limit together.
        {
            let sessions = self.sessions.read().unwrap_or_else(|p| p.into_inner());
            let max = self.cfg.max_sessions;
            let took = self
                .opening
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                    (sessions.len() + n < max).then_some(n + 1)
                })
                .is_ok();
            if !took {
                return Err(ApiError::Busy(format!(
                    "{max} sessions are open (the server's limit); close one first"
                )));
            }
        }
        struct Release<'a>(&'a AtomicUsize);
        impl Drop for Release<'_> {
            fn drop(&mut self) {
                self.0.fetch_sub(1, Ordering::SeqCst);
            }
        }
        let _release = Release(&self.opening);
        let path = match (rel.strip_prefix("generated/"), &self.cfg.generated_root) {
            (Some(r), Some(g)) => crate::paths::resolve(g, r)?,
            _ => crate::paths::resolve(&self.cfg.data_root, rel)?,
        };
        let p2 = path.clone();
        let opened = blocking(move || Ok(BrickStore::open(&p2).ok())).await?;
        let store = match opened {
            Some(s) => s,
            None if path.is_dir() => {
                return Err(ApiError::BadRequest(format!(
                    "'{rel}' is a folder, not a volume or brick store"
                )))
            }
            None => {
                let name: String = rel
                    .chars()
                    .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
                    .collect();
                let dest = self.cfg.work_dir.join(format!("{name}.zarr"));
                let root = match (rel.strip_prefix("generated/"), &self.cfg.generated_root) {
                    (Some(_), Some(g)) => g.clone(),
                    _ => self.cfg.data_root.clone(),
                };
                self.actors
                    .ingest(path, dest, rel.to_string(), root)
                    .await?
            }
        };
        let n = self.next.fetch_add(1, Ordering::SeqCst);
        let s = Session::with_memory(
            id.clone(),
            rel.to_string(),
            Arc::new(store),
            &self.memory,
            n,
        );
        s.set_accelerator(self.actors.accelerator());
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id, s.clone());
        self.prepare_features(&s).await;
        Ok(s)
    }

    /// Opens the features kept in the session's store (before the first stroke can arrive, so
    /// it reads them), then starts the background feature pass
    /// ([`Session::prepare_features`]) on a thread of its own (not the runtime's blocking pool,
    /// whose shutdown would wait for it), announcing progress as `features` events.
    async fn prepare_features(&self, s: &Arc<Session>) {
        let limit = self.cfg.feature_store_bytes;
        if limit == 0 {
            return;
        }
        let s2 = s.clone();
        match blocking(move || s2.open_stored_features(limit)).await {
            Ok(Some(_)) => {}
            Ok(None) => return,
            Err(e) => {
                tracing::warn!("{}: features not kept in the store: {e}", s.name);
                return;
            }
        }
        let (s, hub) = (s.clone(), self.actors.hub.clone());
        let name = format!("features-{}", s.id);
        let started = std::thread::Builder::new().name(name).spawn(move || {
            let last = std::sync::Mutex::new(Instant::now());
            let progress = |done: usize, total: usize| {
                let mut l = last.lock().unwrap_or_else(|p| p.into_inner());
                if done == total || l.elapsed() > Duration::from_millis(500) {
                    *l = Instant::now();
                    hub.publish(
                        Some(&s.id),
                        "features",
                        serde_json::json!({"done": done, "total": total}),
                    );
                }
            };
            match s.prepare_features(&progress) {
                Ok(Some(n)) => tracing::info!("{}: {n} feature bricks kept in the store", s.name),
                Ok(None) => {}
                Err(e) => tracing::warn!("{}: features not kept in the store: {e}", s.name),
            }
        });
        if let Err(e) = started {
            tracing::warn!("no background feature pass: {e}");
        }
    }

    /// Closes a session: its work is cancelled (training stopped, classification made
    /// stale), its state saved for the next open, and what it held in memory given back. When
    /// the state cannot be saved (a full disk), the session stays open and the error names the
    /// file: nothing is lost, and closing again once there is space saves it.
    pub fn close(&self, s: &Session) -> ApiResult<()> {
        stop_work(s);
        save_state(&self.cfg.work_dir, s).map_err(|e| {
            ApiError::write_failed(format!(
                "session {} was not closed: saving its state failed: {e}",
                s.id
            ))
        })?;
        self.forget(s);
        Ok(())
    }

    /// Begins shutdown and returns once in-flight work has stopped, or after `grace`: new
    /// requests get 503 and event streams end; every training is stopped (it saves its
    /// checkpoint) and every classification made stale; each session's state is saved to
    /// `WORK/sessions/` (atomically). Returns the session files written (sessions with
    /// nothing to keep write none).
    pub async fn shutdown(&self, grace: Duration) -> Vec<PathBuf> {
        let deadline = Instant::now() + grace;
        self.shutdown.send_replace(true);
        self.actors.stop();
        let sessions = self.all_sessions();
        for s in &sessions {
            stop_work(s);
            s.closing.store(true, Ordering::SeqCst);
        }
        let work = self.cfg.work_dir.clone();
        let saved = web::block(move || {
            sessions
                .iter()
                .filter_map(|s| {
                    save_state(&work, s)
                        .map_err(|e| tracing::error!("session {} not saved: {e}", s.id))
                        .ok()
                        .flatten()
                })
                .collect::<Vec<_>>()
        })
        .await
        .unwrap_or_default();
        while self.trainings.load(Ordering::SeqCst) > 0 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        saved
    }
}

/// Stops a session's training and makes its classification stale.
pub(crate) fn stop_work(s: &Session) {
    if let Some(c) = s
        .train_cancel
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .as_ref()
    {
        c.store(true, Ordering::SeqCst);
    }
    s.bump_generation();
}

/// How often the autosave looks for changed sessions ([`AppState::autosave`]).
pub const AUTOSAVE: Duration = Duration::from_millis(250);

/// Most rounds of its label history a session file keeps (the newest of its line).
pub const SAVED_ROUNDS: usize = 64;

/// A new session id: `s-` and 12 random hex digits. It names the session's file and stays the
/// same across reloads and restarts (the page keeps it in its URL).
pub fn new_id() -> String {
    let mut b = [0u8; 6];
    if getrandom::fill(&mut b).is_err() {
        // No entropy source: the clock and a counter still give ids unique on this server.
        static N: AtomicU64 = AtomicU64::new(0);
        let t = crate::session::now_ms() ^ (N.fetch_add(1, Ordering::SeqCst) << 40);
        b.copy_from_slice(&t.to_le_bytes()[..6]);
    }
    format!(
        "s-{}",
        b.iter().map(|v| format!("{v:02x}")).collect::<String>()
    )
}

/// Where session `id` is saved: `WORK/sessions/ID.json` (its label bricks beside, in
/// [`crate::labels::bricks_dir`]).
pub fn session_path(work: &std::path::Path, id: &str) -> PathBuf {
    work.join("sessions").join(format!("{id}.json"))
}

/// Every readable saved session under `WORK/sessions/`, with its id (the file's name: files of
/// earlier versions, saved per volume, keep theirs). Unreadable files are logged and skipped.
pub fn saved_sessions(work: &std::path::Path) -> Vec<(String, neuvolex_session::SessionFile)> {
    let Ok(dir) = std::fs::read_dir(work.join("sessions")) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for e in dir.flatten() {
        let p = e.path();
        let Some(id) = p
            .file_stem()
            .and_then(|s| s.to_str())
            .filter(|_| p.extension().is_some_and(|x| x == "json"))
        else {
            continue;
        };
        if neuvolex_session::validate_id(id).is_err() {
            continue;
        }
        let src = p.display().to_string();
        match std::fs::read_to_string(&p)
            .map_err(|e| e.to_string())
            .and_then(|t| neuvolex_session::SessionFile::parse(&t, &src).map_err(|e| e.to_string()))
        {
            Ok(f) => out.push((id.to_string(), f)),
            Err(e) => tracing::warn!("saved session skipped: {src}: {e}"),
        }
    }
    out
}

/// Whether the session changed since its last save.
fn unsaved(s: &Session) -> bool {
    let rev = s
        .labels
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .revision();
    let saved = *s.saved.lock().unwrap_or_else(|p| p.into_inner());
    saved != (s.edits.load(Ordering::SeqCst), rev)
}

/// Applies a saved session to a freshly opened one: its state, then its label history (a
/// damaged or missing label file is logged and the labels are classified afresh). Returns the
/// stroke generation to classify.
pub(crate) fn restore(
    work: &std::path::Path,
    s: &Session,
    f: &neuvolex_session::SessionFile,
    src: &str,
) -> ApiResult<u64> {
    let g = s.apply_state(f, src)?;
    restore_rounds(work, s, f, src);
    let rev = s
        .labels
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .revision();
    *s.saved.lock().unwrap_or_else(|p| p.into_inner()) = (s.edits.load(Ordering::SeqCst), rev);
    Ok(g)
}

/// Reads a session file's label history into the session (see [`restore`]).
pub(crate) fn restore_rounds(
    work: &std::path::Path,
    s: &Session,
    f: &neuvolex_session::SessionFile,
    src: &str,
) {
    if f.rounds.is_empty() {
        return;
    }
    let key = match s.feature_source() {
        Ok((set, model)) => crate::labels::features_key(&set, model.map_or(0, |m| m.0)),
        Err(_) => return,
    };
    match crate::labels::load_rounds(work, &s.store, &f.rounds, &f.line()) {
        Ok(rounds) => s
            .labels
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .restore(rounds, &f.strokes, &key),
        Err(e) => tracing::warn!(
            "{src}: label history not restored ({e}); the labels are classified afresh"
        ),
    }
}

/// Writes a session's state atomically (temporary file, fsync, rename): first the label
/// bricks of its history not saved yet (the newest [`SAVED_ROUNDS`] rounds of its line), then
/// the file that lists them, so a crash leaves the previous file or the new one, each whole
/// with its bricks. Serialised per session. A session with nothing to keep (never changed,
/// no strokes) writes nothing: `None`.
pub(crate) fn save_state(work: &std::path::Path, s: &Session) -> ApiResult<Option<PathBuf>> {
    let mut saved = s.saved.lock().unwrap_or_else(|p| p.into_inner());
    let edits = s.edits.load(Ordering::SeqCst);
    let rev = s
        .labels
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .revision();
    let p = session_path(work, &s.id);
    if edits == 0 && rev == 0 && !p.exists() {
        return Ok(None);
    }
    let mut state = file_with_rounds(work, s)?;
    state.saved_ms = Some(crate::session::now_ms());
    neuvolex_bricks::atomic::replace_file(&p, state.to_json().as_bytes())
        .map_err(|e| ApiError::write_failed(format!("{}: {e}", p.display())))?;
    *saved = (edits, rev);
    Ok(Some(p))
}

/// The session as a session file with its label history: the newest [`SAVED_ROUNDS`] rounds
/// of its line, their bricks written to [`crate::labels::bricks_dir`] first where missing.
pub(crate) fn file_with_rounds(
    work: &std::path::Path,
    s: &Session,
) -> ApiResult<neuvolex_session::SessionFile> {
    let mut state = s.state();
    let line = state.line();
    let rounds = s
        .labels
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .on_line(&line);
    let keep = rounds.len().saturating_sub(SAVED_ROUNDS);
    state.rounds = crate::labels::save_bricks(work, &rounds[keep..], &line)?;
    Ok(state)
}
