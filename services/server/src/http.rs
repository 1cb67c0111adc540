//! The HTTP API (actix-web) and the embedded browser UI.

use crate::actors::{Actors, Hub, TrainCommand, TrainingSlot};
use crate::cache::FeatureCache;
use crate::error::{ApiError, ApiResult};
use crate::imaging::{png, window, SliceAxes};
use crate::session::{Session, BACKGROUND};
use actix_web::{web, HttpResponse};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::BrickStore;
use neuvolex_classify::scribble::Stroke;
use serde::Deserialize;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
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
}

impl ServerConfig {
    /// A configuration with the default budgets for all sessions together (feature cache
    /// 512 MiB, render cache 512 MiB, probabilities 2 GiB), no token,
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
        }
    }
}

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
    opening: AtomicUsize,
    /// Set once shutdown began: new requests get 503 and event streams end.
    shutdown: tokio::sync::watch::Sender<bool>,
    started: Instant,
    next: AtomicU64,
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
        })
    }

    fn session(&self, id: &str) -> ApiResult<Arc<Session>> {
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
        let mut stop = state.shutdown.subscribe();
        loop {
            tokio::select! {
                _ = tokio::time::sleep(every) => {}
                _ = stop.changed() => return,
            }
            if state.shutting_down() {
                return;
            }
            let st = state.clone();
            let _ = web::block(move || st.close_idle()).await;
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
        let id = format!("s{n}");
        let s = Session::with_memory(
            id.clone(),
            rel.to_string(),
            Arc::new(store),
            &self.memory,
            n,
        );
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id, s.clone());
        Ok(s)
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
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&s.id);
        s.release_memory();
        Ok(())
    }

    /// Begins shutdown and returns once in-flight work has stopped, or after `grace`: new
    /// requests get 503 and event streams end; every training is stopped (it saves its
    /// checkpoint) and every classification made stale; each session's state is saved to
    /// `WORK/sessions/` (atomically). Returns the session files written.
    pub async fn shutdown(&self, grace: Duration) -> Vec<PathBuf> {
        let deadline = Instant::now() + grace;
        self.shutdown.send_replace(true);
        self.actors.stop();
        let sessions = self.all_sessions();
        for s in &sessions {
            stop_work(s);
        }
        let work = self.cfg.work_dir.clone();
        let saved = web::block(move || {
            sessions
                .iter()
                .filter_map(|s| {
                    save_state(&work, s)
                        .map_err(|e| tracing::error!("session {} not saved: {e}", s.id))
                        .ok()
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
fn stop_work(s: &Session) {
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

/// Where a volume's session is saved between runs: `WORK/sessions/NAME.json`.
pub fn state_path(work: &std::path::Path, volume: &str) -> PathBuf {
    let name: String = volume
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    work.join("sessions").join(format!("{name}.json"))
}

/// Writes a session's state atomically (temporary file, fsync, rename): a crash leaves the
/// previous file or the new one, never a part, and the temporaries a killed server left are
/// removed by the next save. Sessions without strokes are not saved.
fn save_state(work: &std::path::Path, s: &Session) -> std::io::Result<PathBuf> {
    let state = s.state();
    let p = state_path(work, &s.name);
    if state.strokes.is_empty() && state.tf.is_none() {
        return Ok(p);
    }
    neuvolex_bricks::atomic::replace_file(&p, state.to_json().as_bytes())
        .map_err(std::io::Error::other)?;
    Ok(p)
}

/// Runs blocking work (store reads, classification, encoding) off the async workers.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    web::block(f)
        .await
        .map_err(|e| ApiError::Internal(e.to_string()))?
}

fn info(s: &Session) -> serde_json::Value {
    let i = s.store.info();
    let model = s.current_model();
    serde_json::json!({
        "id": s.id, "volume": s.name, "dims": i.dims, "spacing": i.spacing,
        // The anatomical direction of each voxel axis, from the source's affine (the slice
        // views' orientation and edge letters).
        "directions": neuvolex_formats::geometry::axis_directions(&s.store.meta().affine)
            .map(String::from),
        "range": [i.stats.min, i.stats.max], "percentiles": [i.stats.p0_5, i.stats.p99_5],
        "histogram": i.stats.histogram,
        "classes": *s.classes.read().unwrap_or_else(|p| p.into_inner()),
        "background": BACKGROUND,
        "strokes": s.strokes.read().unwrap_or_else(|p| p.into_inner()).len(),
        "generation": s.generation.load(Ordering::SeqCst),
        "status": *s.status.read().unwrap_or_else(|p| p.into_inner()),
        "trained": model.is_some(),
        "model_version": model.map_or(0, |m| m.0),
        "tf": s.tf.read().unwrap_or_else(|p| p.into_inner()).as_ref().map(|t| t.0.clone()),
        "prior": crate::assist::prior_summary(s),
    })
}

async fn index() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("text/html; charset=utf-8")
        .body(include_str!("../static/index.html"))
}

async fn app_js() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("text/javascript; charset=utf-8")
        .body(include_str!("../static/app.js"))
}

async fn favicon() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("image/svg+xml")
        .insert_header(("Cache-Control", "max-age=86400"))
        .body(include_str!("../static/favicon.svg"))
}

async fn backend(st: web::Data<AppState>) -> HttpResponse {
    HttpResponse::Ok().json(st.actors.compute())
}

async fn volumes(st: web::Data<AppState>) -> HttpResponse {
    let mut v = crate::paths::list(&st.cfg.data_root, 3);
    if let Some(g) = &st.cfg.generated_root {
        v.extend(
            crate::paths::list(g, 1)
                .into_iter()
                .map(|n| format!("generated/{n}")),
        );
    }
    // The configured default first: the UI opens the first entry.
    if let Some(d) = &st.cfg.default_volume {
        v.retain(|x| x != d);
        v.insert(0, d.clone());
    }
    HttpResponse::Ok().json(v)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OpenReq {
    volume: String,
    /// Restore the state saved when this volume's last session closed or the server stopped.
    #[serde(default)]
    restore: bool,
}

async fn open(st: web::Data<AppState>, req: web::Json<OpenReq>) -> ApiResult<HttpResponse> {
    let req = req.into_inner();
    let s = st.open(&req.volume).await?;
    if req.restore {
        let p = state_path(&st.cfg.work_dir, &s.name);
        let s2 = s.clone();
        let restored = blocking(move || {
            let Ok(text) = std::fs::read_to_string(&p) else {
                return Ok(None);
            };
            let src = p.display().to_string();
            let f = neuvolex_session::SessionFile::parse(&text, &src)
                .map_err(|e| ApiError::BadRequest(e.to_string()))?;
            s2.apply_state(&f, &src).map(Some)
        })
        .await;
        match restored {
            Ok(Some(g)) => st.actors.classify(s.clone(), g)?,
            Ok(None) => {}
            // A damaged saved state does not keep the volume from opening.
            Err(e) => tracing::warn!("not restoring {}: {e}", s.name),
        }
    }
    Ok(HttpResponse::Created().json(info(&s)))
}

async fn get_session(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(info(&s)))
}

async fn close_session(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let st2 = st.clone();
    blocking(move || st2.close(&s)).await?;
    Ok(HttpResponse::NoContent().finish())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SliceQuery {
    window: Option<f64>,
    level: Option<f64>,
    kind: Option<String>,
    /// Overlays: the class whose probability or uncertainty to show (all classes if absent).
    class: Option<u32>,
    /// A client's cache-buster, ignored.
    #[serde(rename = "t")]
    _t: Option<String>,
}

fn slice_index(s: &Session, axis: &str, index: usize) -> ApiResult<(SliceAxes, [usize; 3])> {
    let a = SliceAxes::parse(axis)?;
    let d = s.store.info().dims;
    if index >= d[a.fixed] {
        return Err(ApiError::BadRequest(format!(
            "slice {index} outside 0..{} along {axis}",
            d[a.fixed]
        )));
    }
    Ok((a, d))
}

async fn slice(
    st: web::Data<AppState>,
    path: web::Path<(String, String, usize)>,
    q: web::Query<SliceQuery>,
) -> ApiResult<HttpResponse> {
    let (id, axis, index) = path.into_inner();
    let s = st.session(&id)?;
    let (a, d) = slice_index(&s, &axis, index)?;
    let q = q.into_inner();
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let mut origin = [0; 3];
        let mut size = d;
        origin[a.fixed] = index;
        size[a.fixed] = 1;
        let vals = s.store.read_box(0, origin, size)?;
        let (w, h) = (d[a.u], d[a.v]);
        let stats = &s.store.info().stats;
        let level = q.level.unwrap_or((stats.p0_5 + stats.p99_5) / 2.0);
        let width = q.window.unwrap_or((stats.p99_5 - stats.p0_5).max(1e-12));
        let mut img = vec![0f32; w * h];
        for j in 0..h {
            for i in 0..w {
                let p = a.voxel(d, index, i, j);
                let l = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
                img[j * w + i] = vals[(l[2] * size[1] + l[1]) * size[0] + l[0]];
            }
        }
        png(w, h, 1, &window(&img, level, width))
    })
    .await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

async fn overlay(
    st: web::Data<AppState>,
    path: web::Path<(String, String, usize)>,
    q: web::Query<SliceQuery>,
) -> ApiResult<HttpResponse> {
    let (id, axis, index) = path.into_inner();
    let s = st.session(&id)?;
    let (a, d) = slice_index(&s, &axis, index)?;
    let q = q.into_inner();
    let kind = q.kind.unwrap_or_else(|| "labels".into());
    if !["labels", "uncertainty", "probability"].contains(&kind.as_str()) {
        return Err(ApiError::BadRequest(format!(
            "overlay kind '{}' must be labels, uncertainty or probability",
            kind.escape_debug()
        )));
    }
    if kind == "probability" && q.class.is_none() {
        return Err(ApiError::BadRequest(
            "the probability overlay needs a class (?class=ID)".into(),
        ));
    }
    let want = q.class;
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let (w, h) = (d[a.u], d[a.v]);
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let prior = crate::assist::active_prior(&s, &probs);
        let ids = &probs.ids;
        let color = |id: u32| {
            classes
                .iter()
                .find(|c| c.id == id)
                .map_or_else(|| neuvolex_bricks::synth::palette(id), |c| c.color)
        };
        // The channel of the requested class (404 once classified without it).
        let channel = match want {
            Some(c) if !ids.is_empty() && kind != "labels" => {
                Some(ids.iter().position(|&i| i == c).ok_or_else(|| {
                    ApiError::NotFound(format!("class {c} is not classified (have {ids:?})"))
                })?)
            }
            _ => None,
        };
        let mut rgba = vec![0u8; w * h * 4];
        for j in 0..h {
            for i in 0..w {
                let vox = a.voxel(d, index, i, j);
                let Some(p) = probs.at(&s.store, vox) else {
                    continue;
                };
                let o = &mut rgba[(j * w + i) * 4..(j * w + i + 1) * 4];
                if let Some(k) = channel {
                    let c = color(ids[k]);
                    let v = p[k] as i32;
                    let alpha = if kind == "probability" {
                        v
                    } else {
                        // Per class: bright where its probability is near 0.5, its boundary.
                        255 - (2 * v - 255).abs()
                    };
                    o.copy_from_slice(&[c[0], c[1], c[2], (alpha * 200 / 255) as u8]);
                    continue;
                }
                let mut order: Vec<usize> = (0..p.len()).collect();
                order.sort_by(|&x, &y| p[y].cmp(&p[x]));
                if kind == "uncertainty" {
                    // 1 - (p1 - p2): bright where the two best classes are close.
                    let m = p[order[0]] as i32 - order.get(1).map_or(0, |&k| p[k] as i32);
                    let u = (255 - m).clamp(0, 255) as u8;
                    o.copy_from_slice(&[255, 200, 0, u]);
                } else {
                    let best = order[0];
                    let mut id = ids[best];
                    if id == BACKGROUND || p[best] < 128 {
                        id = 0;
                    }
                    if let Some(l) = prior.as_ref().and_then(|pr| pr.label(&s.store, vox)) {
                        id = l as u32;
                    }
                    if id == 0 {
                        continue;
                    }
                    let c = color(id);
                    o.copy_from_slice(&[c[0], c[1], c[2], 140]);
                }
            }
        }
        drop(probs);
        png(w, h, 4, &rgba)
    })
    .await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct StrokesQuery {
    /// `x,y,z`: the voxel whose three slices are on screen, classified first after the
    /// stroke's own slice.
    focus: Option<String>,
}

/// Keeps the focus a stroke request names (a bad one is a 400 naming it).
fn set_focus(s: &Session, q: &StrokesQuery) -> ApiResult<()> {
    let Some(f) = &q.focus else { return Ok(()) };
    let dims = s.store.info().dims;
    let bad = || {
        ApiError::BadRequest(format!(
            "focus '{}' must be x,y,z voxel indices inside {dims:?}",
            f.escape_debug()
        ))
    };
    let v: Vec<usize> = f
        .split(',')
        .map(|t| t.trim().parse::<usize>().map_err(|_| bad()))
        .collect::<ApiResult<_>>()?;
    if v.len() != 3 || (0..3).any(|k| v[k] >= dims[k]) {
        return Err(bad());
    }
    *s.focus.lock().unwrap_or_else(|p| p.into_inner()) = Some([v[0], v[1], v[2]]);
    Ok(())
}

async fn put_strokes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    q: web::Query<StrokesQuery>,
    strokes: web::Json<Vec<Stroke>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    set_focus(&s, &q)?;
    let strokes = strokes.into_inner();
    let permit = st.actors.reserve_classify()?;
    let s2 = s.clone();
    let generation = blocking(move || s2.set_strokes(strokes)).await?;
    permit.send(s.clone(), generation);
    Ok(HttpResponse::Accepted().json(serde_json::json!({"generation": generation})))
}

/// Appends strokes (several clients may draw on one session: none is lost); answers the new
/// generation and how many strokes the session holds.
async fn post_strokes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    q: web::Query<StrokesQuery>,
    strokes: web::Json<Vec<Stroke>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    set_focus(&s, &q)?;
    let strokes = strokes.into_inner();
    // Reserved first: a busy answer means the strokes were not added (a retry adds them once).
    let permit = st.actors.reserve_classify()?;
    let s2 = s.clone();
    let (generation, total) = blocking(move || s2.add_strokes(strokes)).await?;
    permit.send(s.clone(), generation);
    Ok(HttpResponse::Accepted()
        .json(serde_json::json!({"generation": generation, "strokes": total})))
}

async fn get_strokes(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let strokes = s.strokes.read().unwrap_or_else(|p| p.into_inner()).clone();
    Ok(HttpResponse::Ok().json(strokes))
}

/// The rasterised strokes as a label volume (0 unlabelled, class ids, 255 background).
async fn export_scribbles(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let scr = s.scribbles()?;
        let mut voxels = vec![0u8; s.store.info().dims.iter().product()];
        for &(i, c) in &scr.voxels {
            voxels[i as usize] = c.min(255) as u8;
        }
        let mut vol = u8_volume(&s, voxels, "scribbles");
        nifti_bytes(&work, &format!("{}-scribbles", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(bytes, "scribbles.nii.gz"))
}

/// The session file: volume, classes, strokes and transfer function.
async fn get_state(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(s.state()))
}

/// Loads a session file into the session: every part is validated (and the strokes checked
/// against the grid) before anything changes.
async fn put_state(
    st: web::Data<AppState>,
    id: web::Path<String>,
    mut payload: web::Payload,
) -> ApiResult<HttpResponse> {
    use futures_util::StreamExt;
    let s = st.session(&id)?;
    let mut body = web::BytesMut::new();
    while let Some(chunk) = payload.next().await {
        let chunk = chunk.map_err(|e| ApiError::BadRequest(format!("request body: {e}")))?;
        if body.len() + chunk.len() > MAX_BODY {
            return Err(ApiError::TooLarge(format!(
                "request body over the server's limit of {} MiB",
                MAX_BODY >> 20
            )));
        }
        body.extend_from_slice(&chunk);
    }
    let src = format!("session file for {}", s.id);
    let text = std::str::from_utf8(&body)
        .map_err(|_| ApiError::BadRequest(format!("{src}: not UTF-8 text")))?;
    let f = neuvolex_session::SessionFile::parse(text, &src)
        .map_err(|e| ApiError::BadRequest(e.to_string()))?;
    if f.volume != s.name {
        return Err(ApiError::Conflict(format!(
            "{src}: it is for volume '{}', this session shows '{}'; open that volume first",
            f.volume.escape_debug(),
            s.name
        )));
    }
    let permit = st.actors.reserve_classify()?;
    let s2 = s.clone();
    let generation = blocking(move || s2.apply_state(&f, &src)).await?;
    permit.send(s.clone(), generation);
    Ok(HttpResponse::Ok().json(info(&s)))
}

/// The server's limits and how much of them is in use.
async fn server_status(st: web::Data<AppState>) -> HttpResponse {
    HttpResponse::Ok().json(serde_json::json!({
        "sessions": st.sessions.read().unwrap_or_else(|p| p.into_inner()).len(),
        "max_sessions": st.cfg.max_sessions,
        "trainings": st.trainings.load(Ordering::SeqCst),
        "max_trainings": st.cfg.max_trainings,
        "feature_cache": {"used": st.features.used(), "budget": st.features.budget()},
        "memory": st.memory.report(),
        "renders_in_flight": st.memory.renders_in_flight(),
        "renders_cancelled": st.memory.renders_cancelled(),
        "request_timeout_s": st.cfg.request_timeout.as_secs_f64(),
        "access": if st.cfg.token.is_some() { "token" } else { "open" },
        "uptime_s": st.started.elapsed().as_secs_f64(),
    }))
}

async fn put_classes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    classes: web::Json<Vec<ClassInfo>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let c = classes.into_inner();
    neuvolex_session::validate_classes(&c).map_err(ApiError::BadRequest)?;
    *s.classes.write().unwrap_or_else(|p| p.into_inner()) = c;
    // Recolouring changes the render classes; the next render starts from scratch.
    Ok(HttpResponse::Ok().json(info(&s)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RenderQuery {
    az: Option<f32>,
    el: Option<f32>,
    size: Option<usize>,
    mode: Option<String>,
    tf: Option<String>,
    /// A client's cache-buster, ignored.
    #[serde(rename = "t")]
    _t: Option<String>,
}

async fn render(
    st: web::Data<AppState>,
    id: web::Path<String>,
    q: web::Query<RenderQuery>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let q = q.into_inner();
    let size = q.size.unwrap_or(256);
    if size == 0 || size > 2048 {
        return Err(ApiError::BadRequest(format!(
            "size {size} must be 1..=2048"
        )));
    }
    let has_probs = !s
        .probs
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .ids
        .is_empty();
    // Once classified, the default is the current labels over a faint intensity context.
    let (mode, labels) = match q.mode.as_deref() {
        None | Some("labels") if has_probs => (neuvolex_render::Mode::ProbIntensity, true),
        // Nothing classified yet: every mode draws the intensity.
        None | Some("labels" | "prob" | "prob-intensity") if !has_probs => {
            (neuvolex_render::Mode::Intensity, false)
        }
        None | Some("labels") | Some("intensity") => (neuvolex_render::Mode::Intensity, false),
        Some("prob") => (neuvolex_render::Mode::Probabilistic, false),
        Some("prob-intensity") => (neuvolex_render::Mode::ProbIntensity, false),
        Some(o) => {
            return Err(ApiError::BadRequest(format!(
                "mode '{}' must be labels, intensity, prob or prob-intensity",
                o.escape_debug()
            )))
        }
    };
    let tf = match q.tf.as_deref() {
        Some(t) => neuvolex_render::TfFile::preset(t)?,
        None => session_tf(&s)?,
    };
    let params = neuvolex_render::RenderParams {
        width: size,
        height: size,
        mode,
        camera: neuvolex_render::Camera {
            azimuth: q.az.unwrap_or(30.0),
            elevation: q.el.unwrap_or(20.0),
            ..Default::default()
        },
        ..Default::default()
    };
    params.validate()?;
    let bytes = st.actors.render(s, params, tf, labels).await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TrainReq {
    action: String,
    epochs: Option<f64>,
}

async fn train(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<TrainReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let req = req.into_inner();
    let epochs = req.epochs.unwrap_or(1.0);
    if !(epochs > 0.0 && epochs <= 1000.0) {
        return Err(ApiError::BadRequest(format!(
            "epochs {epochs} must be in (0, 1000]"
        )));
    }
    match req.action.as_str() {
        "start" | "resume" => {
            if s.train_cancel
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .is_some()
            {
                return Err(ApiError::Conflict(
                    "this session is already training; stop it first".into(),
                ));
            }
            let max = st.cfg.max_trainings;
            let slot = TrainingSlot::take(&st.trainings, max).ok_or_else(|| {
                ApiError::Busy(format!(
                    "{max} training(s) running (the server's limit); stop one or try later"
                ))
            })?;
            // The training writes the store's checkpoint and model: it holds the store's
            // writer lock meanwhile (shared within this server; another process writing the
            // store, `neuvolex train` say, gets 409 naming it).
            let s2 = s.clone();
            let lock = blocking(move || {
                s2.store
                    .writer_lock(&format!("neuvolex serve: training session {}", s2.id))
                    .map_err(|e| match ApiError::from(e) {
                        ApiError::Conflict(m) => ApiError::Conflict(format!(
                            "cannot train: {m}; the training writes the store's model"
                        )),
                        o => o,
                    })
            })
            .await?;
            let mut tc = s.train_cancel.lock().unwrap_or_else(|p| p.into_inner());
            if tc.is_some() {
                return Err(ApiError::Conflict(
                    "this session is already training; stop it first".into(),
                ));
            }
            let cancel = Arc::new(AtomicBool::new(false));
            st.actors.train(TrainCommand::Start {
                session: s.clone(),
                epochs,
                resume: req.action == "resume",
                cancel: cancel.clone(),
                slot,
                lock,
            })?;
            *tc = Some(cancel);
        }
        "stop" => match s
            .train_cancel
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
        {
            Some(c) => c.store(true, Ordering::SeqCst),
            None => return Err(ApiError::Conflict("no training is running".into())),
        },
        o => {
            return Err(ApiError::BadRequest(format!(
                "action '{}' must be start, stop or resume",
                o.escape_debug()
            )))
        }
    }
    Ok(HttpResponse::Accepted().json(serde_json::json!({"action": req.action})))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct EventsQuery {
    session: Option<String>,
}

async fn events(st: web::Data<AppState>, q: web::Query<EventsQuery>) -> HttpResponse {
    let rx = st.actors.hub.subscribe();
    let want = q.into_inner().session;
    let stop = st.shutdown.subscribe();
    let stream =
        futures_util::stream::unfold((rx, want, stop), |(mut rx, want, mut stop)| async move {
            loop {
                if *stop.borrow() {
                    return None;
                }
                let got = tokio::select! {
                    e = rx.recv() => e,
                    // The server is stopping: say so and end the stream.
                    _ = stop.changed() => {
                        let line = "event: shutdown\ndata: {}\n\n";
                        return Some((Ok(web::Bytes::from(line)), (rx, want, stop)));
                    }
                };
                match got {
                    Ok(e) => {
                        if want.is_some() && e.session.is_some() && e.session != want {
                            continue;
                        }
                        let line = format!(
                            "event: {}\ndata: {}\n\n",
                            e.kind,
                            serde_json::to_string(&e).unwrap_or_default()
                        );
                        return Some((
                            Ok::<_, actix_web::Error>(web::Bytes::from(line)),
                            (rx, want, stop),
                        ));
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                        let line = format!("event: lagged\ndata: {{\"missed\": {n}}}\n\n");
                        return Some((Ok(web::Bytes::from(line)), (rx, want, stop)));
                    }
                    Err(_) => return None,
                }
            }
        });
    HttpResponse::Ok()
        .content_type("text/event-stream")
        .insert_header(("Cache-Control", "no-cache"))
        .streaming(stream)
}

/// The share of each class among the voxels classified so far, counted on the labels the
/// overlays and the label export show: each voxel's label ([`crate::assist::label_of`]) with
/// the spatial prior's changes when it is on. Unlabelled voxels (the background, or no class
/// reaching 0.5) count as the background, or as id 0 ("unlabelled") when no background was
/// scribbled.
async fn fractions(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let body = blocking(move || {
        let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let prior = crate::assist::active_prior(&s, &p);
        let c = p.ids.len().max(1);
        let slot = |label: u32| {
            let id = if label == 0 {
                crate::session::BACKGROUND
            } else {
                label
            };
            p.ids.iter().position(|&i| i == id)
        };
        let mut counts = vec![0u64; p.ids.len()];
        let mut unlabelled = 0u64;
        let mut total = 0u64;
        let mut labels = Vec::new();
        for (idx, v) in &p.bricks {
            labels.clear();
            labels.extend(
                v.chunks_exact(c)
                    .map(|px| crate::assist::label_of(&p.ids, px)),
            );
            if let Some(changed) = prior.as_ref().and_then(|pr| pr.changed.get(idx)) {
                for &(i, l) in changed.iter() {
                    if let Some(x) = labels.get_mut(i as usize) {
                        *x = l as u32;
                    }
                }
            }
            for &l in &labels {
                match slot(l) {
                    Some(k) => counts[k] += 1,
                    None => unlabelled += 1,
                }
                total += 1;
            }
        }
        let share = |n: u64| n as f64 / total.max(1) as f64;
        let mut classes: Vec<serde_json::Value> = p
            .ids
            .iter()
            .zip(&counts)
            .map(|(id, n)| serde_json::json!({"id": id, "fraction": share(*n)}))
            .collect();
        if unlabelled > 0 {
            classes.push(serde_json::json!({"id": 0, "fraction": share(unlabelled)}));
        }
        Ok(serde_json::json!({
            "classified_voxels": total,
            "prior": prior.is_some(),
            "classes": classes,
        }))
    })
    .await?;
    Ok(HttpResponse::Ok().json(body))
}

/// Every brick's probabilities, or a conflict while classification has not reached them all.
fn complete_probs(s: &Session) -> ApiResult<std::sync::RwLockReadGuard<'_, crate::session::Probs>> {
    let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
    let total = s.store.bricks().count();
    if p.ids.is_empty() || p.bricks.len() < total {
        return Err(ApiError::Conflict(format!(
            "classification has reached {} of {total} bricks: scribble two classes and wait \
             for it to finish",
            p.bricks.len()
        )));
    }
    Ok(p)
}

/// One u8 per voxel of the volume (x fastest), computed by `f` from each voxel's class
/// probabilities once every brick is classified.
fn per_voxel(s: &Session, f: impl Fn(&crate::session::Probs, &[u8]) -> u8) -> ApiResult<Vec<u8>> {
    let d = s.store.info().dims;
    let p = complete_probs(s)?;
    let c = p.ids.len();
    let mut out = vec![0u8; d.iter().product()];
    for (idx, v) in &p.bricks {
        let b = s.store.brick(*idx)?;
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                let row = ((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0] + b.origin[0];
                for x in 0..b.size[0] {
                    let i = (z * b.size[1] + y) * b.size[0] + x;
                    out[row + x] = f(&p, &v[i * c..(i + 1) * c]);
                }
            }
        }
    }
    Ok(out)
}

/// The arg-max label of every voxel (0 where the background wins or no class reaches 0.5),
/// with the spatial prior's changes when it is on (dropped parts cleared, kept parts grown).
fn label_voxels(s: &Session) -> ApiResult<Vec<u8>> {
    let mut out = per_voxel(s, |p, px| crate::assist::label_of(&p.ids, px) as u8)?;
    let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
    if let Some(pr) = crate::assist::active_prior(s, &probs) {
        let d = s.store.info().dims;
        for (idx, changed) in pr.changed.iter() {
            let b = s.store.brick(*idx)?;
            for &(i, l) in changed.iter() {
                let i = i as usize;
                let (x, y, z) = (
                    i % b.size[0],
                    (i / b.size[0]) % b.size[1],
                    i / (b.size[0] * b.size[1]),
                );
                out[((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0] + b.origin[0] + x] =
                    l as u8;
            }
        }
    }
    Ok(out)
}

/// One class's probability (0..255 for 0..1) of every voxel.
fn class_voxels(s: &Session, class: u32) -> ApiResult<Vec<u8>> {
    let ids = complete_probs(s)?.ids.clone();
    let Some(k) = ids.iter().position(|&i| i == class) else {
        return Err(ApiError::NotFound(format!(
            "class {class} is not classified (have {ids:?})"
        )));
    };
    per_voxel(s, |_, px| px[k])
}

/// A u8 volume on the session's grid, in the source's world geometry (spacing, affine and,
/// for a NIfTI source, its sform and qform codes), so exports overlay the scan.
fn u8_volume(s: &Session, voxels: Vec<u8>, name: &str) -> neuvolex_formats::MemVolume {
    let mut meta = s.store.meta();
    meta.dtype = neuvolex_formats::DType::U8;
    meta.scaling = None;
    neuvolex_formats::MemVolume {
        meta,
        bytes: voxels,
        name: PathBuf::from(name),
    }
}

/// Writes `vol` as NIfTI into the work folder (under a unique name), returning its bytes.
fn nifti_bytes(
    work: &std::path::Path,
    tag: &str,
    vol: &mut neuvolex_formats::MemVolume,
) -> ApiResult<Vec<u8>> {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let tmp = work.join(format!(
        ".{tag}-{}-{}.nii.gz",
        std::process::id(),
        SEQ.fetch_add(1, Ordering::SeqCst)
    ));
    let r = neuvolex_formats::nifti::write_nifti(&tmp, vol, 16)
        .map_err(ApiError::from)
        .and_then(|()| {
            std::fs::read(&tmp).map_err(|e| ApiError::Internal(format!("{}: {e}", tmp.display())))
        });
    let _ = std::fs::remove_file(&tmp);
    r
}

fn gzip_attachment(bytes: Vec<u8>, name: &str) -> HttpResponse {
    HttpResponse::Ok()
        .content_type("application/gzip")
        .insert_header((
            "Content-Disposition",
            format!("attachment; filename=\"{name}\""),
        ))
        .body(bytes)
}

async fn export_labels(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let mut vol = u8_volume(&s, label_voxels(&s)?, "labels");
        nifti_bytes(&work, &format!("{}-labels", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(bytes, "labels.nii.gz"))
}

async fn export_probability(
    st: web::Data<AppState>,
    path: web::Path<(String, String)>,
) -> ApiResult<HttpResponse> {
    let (id, file) = path.into_inner();
    let s = st.session(&id)?;
    let class: u32 = file
        .strip_suffix(".nii.gz")
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| {
            ApiError::BadRequest(format!(
                "'{}' must be CLASS.nii.gz with an integer class id",
                file.escape_debug()
            ))
        })?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || {
        let mut vol = u8_volume(&s, class_voxels(&s, class)?, "probability");
        nifti_bytes(&work, &format!("{}-p{class}", s.id), &mut vol)
    })
    .await?;
    Ok(gzip_attachment(
        bytes,
        &format!("probability_{class}.nii.gz"),
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ZarrExportReq {
    name: Option<String>,
}

/// Writes the labels as an OME-Zarr labels group (`labels/NAME`, with the class table) and the
/// probabilities as the u8 vector array `NAME_proba` into the session's store, where napari,
/// `neuvolex render --labels NAME` and `--probs NAME_proba` read them.
async fn export_zarr(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<ZarrExportReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let name = req.into_inner().name.unwrap_or_else(|| "neuvolex".into());
    // Checked before any work, so a bad name writes nothing.
    neuvolex_bricks::store::check_name("export", &name)?;
    if name.len() > 64 {
        return Err(ApiError::BadRequest(format!(
            "export name '{name}' is longer than 64 characters"
        )));
    }
    let (name2, root) = (name.clone(), s.store.root().to_path_buf());
    let out = blocking(move || -> ApiResult<serde_json::Value> {
        let mut vol = u8_volume(&s, label_voxels(&s)?, "labels");
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        // The label image and the probabilities are published together (one commit): a
        // reader, or a kill, sees both from before the export or both from it.
        let mut commit = neuvolex_bricks::Commit::new();
        let mut w = BrickStore::open(s.store.location().clone())?;
        w.stage_labels(&mut commit, &name, &mut vol, &classes, &mut |_| {})?;
        drop(vol);
        let p = complete_probs(&s)?;
        let c = p.ids.len();
        let arr = format!("{name}_proba");
        let mut va = s.store.create_vectors(
            &arr,
            c,
            neuvolex_bricks::VectorEncoding::U8 {
                lo: vec![0.0; c],
                hi: vec![1.0; c],
            },
        )?;
        va.set_extra(serde_json::json!({
            "kind": "class_probabilities",
            "labels": p.ids,
            "background": BACKGROUND,
            "features": s.status.read().unwrap_or_else(|p| p.into_inner()).features,
        }));
        for b in s.store.bricks() {
            let v = p.bricks.get(&b.index).ok_or_else(|| {
                ApiError::Conflict(format!("brick {:?} is not classified", b.index))
            })?;
            let f: Vec<f32> = v.iter().map(|&u| u as f32 / 255.0).collect();
            va.write_brick(&b, &f)?;
        }
        va.finish_into(&mut commit)?;
        commit.publish(w.backend())?;
        Ok(serde_json::json!({
            "store": s.store.root(),
            "labels": format!("labels/{name}"),
            "probabilities": arr,
            "classes": p.ids,
        }))
    })
    .await
    .map_err(|e| match e {
        // Nothing was published: the store reads as before the export.
        ApiError::Storage(m) => ApiError::Storage(format!(
            "export '{name2}' into {}: {m}; the store is unchanged",
            root.display()
        )),
        o => o,
    })?;
    Ok(HttpResponse::Ok().json(out))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ViewReq {
    k: Option<usize>,
    views: Option<usize>,
}

async fn viewpoints(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<ViewReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let req = req.into_inner();
    let (k, views) = (req.k.unwrap_or(50), req.views.unwrap_or(1800));
    if !(1..=256).contains(&k) || !(1..=20_000).contains(&views) {
        return Err(ApiError::BadRequest(format!(
            "k {k} must be 1..=256 and views {views} 1..=20000"
        )));
    }
    let out = st.actors.viewpoints(s, k, views).await?;
    Ok(HttpResponse::Ok().json(out))
}

/// The session's transfer function, else a preset suited to the data (CT bone or grey).
fn session_tf(s: &Session) -> ApiResult<neuvolex_render::TfFile> {
    if let Some((_, t)) = s.tf.read().unwrap_or_else(|p| p.into_inner()).as_ref() {
        return Ok(t.clone());
    }
    Ok(neuvolex_render::TfFile::preset(default_preset(s))?)
}

fn default_preset(s: &Session) -> &'static str {
    if s.store.info().stats.min < -500.0 {
        "ct-bone"
    } else {
        "grey"
    }
}

async fn get_tf(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let tf = s.tf.read().unwrap_or_else(|p| p.into_inner()).clone();
    let json = match tf {
        Some((v, _)) => v,
        None => preset_json(default_preset(&s))?,
    };
    Ok(HttpResponse::Ok().json(json))
}

fn preset_json(name: &str) -> ApiResult<serde_json::Value> {
    let (_, text) = neuvolex_render::tf::PRESETS
        .iter()
        .find(|(n, _)| *n == name)
        .ok_or_else(|| ApiError::NotFound(format!("no preset '{}'", name.escape_debug())))?;
    serde_json::from_str(text).map_err(|e| ApiError::Internal(e.to_string()))
}

async fn get_preset(name: web::Path<String>) -> ApiResult<HttpResponse> {
    Ok(HttpResponse::Ok().json(preset_json(&name)?))
}

/// Sets the session's transfer function (the JSON format of `neuvolex render --tf`); `null`
/// returns to the default preset.
async fn put_tf(
    st: web::Data<AppState>,
    id: web::Path<String>,
    body: web::Json<serde_json::Value>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let v = body.into_inner();
    let parsed = if v.is_null() {
        None
    } else {
        let tf = neuvolex_render::TfFile::parse(
            &v.to_string(),
            std::path::Path::new(&format!("session {} transfer function", s.id)),
        )?;
        Some((v, tf))
    };
    *s.tf.write().unwrap_or_else(|p| p.into_inner()) = parsed;
    Ok(HttpResponse::Ok().json(info(&s)))
}

async fn suggest(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let v = blocking(move || crate::assist::suggest(&s)).await?;
    Ok(HttpResponse::Ok().json(v))
}

async fn get_prior(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(crate::assist::prior_summary(&s)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PriorReq {
    enabled: bool,
}

async fn put_prior(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<PriorReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    s.prior_on.store(req.enabled, Ordering::SeqCst);
    let sum = blocking(move || crate::assist::refresh_prior(&s)).await?;
    Ok(HttpResponse::Ok().json(sum))
}

async fn preview(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let p = s.preview.read().unwrap_or_else(|p| p.into_inner()).clone();
    match p {
        Some((png, psnr)) => Ok(HttpResponse::Ok()
            .content_type("image/png")
            .insert_header(("X-Psnr", format!("{psnr:.2}")))
            .body(png)),
        None => Err(ApiError::NotFound(
            "no training preview yet: start training first".into(),
        )),
    }
}

async fn crash(st: web::Data<AppState>, actor: web::Path<String>) -> ApiResult<HttpResponse> {
    if !st.cfg.fault_injection {
        return Err(ApiError::NotFound("no such route".into()));
    }
    st.actors.crash(&actor)?;
    Ok(HttpResponse::Accepted().json(serde_json::json!({"crashing": actor.into_inner()})))
}

fn json_error(err: impl std::fmt::Display) -> actix_web::Error {
    ApiError::BadRequest(format!("malformed request: {err}")).into()
}

fn body_error(e: actix_web::error::JsonPayloadError) -> actix_web::Error {
    use actix_web::error::{JsonPayloadError as J, PayloadError as P};
    match e {
        J::Overflow { .. } | J::OverflowKnownLength { .. } | J::Payload(P::Overflow) => {
            ApiError::TooLarge(format!(
                "request body over the server's limit of {} MiB",
                MAX_BODY >> 20
            ))
            .into()
        }
        other => json_error(other),
    }
}

/// Registers the routes, body limits and error handlers, behind the access, timeout and
/// shutdown guard ([`crate::access`]).
pub fn configure(cfg: &mut web::ServiceConfig) {
    cfg.app_data(
        web::JsonConfig::default()
            .limit(MAX_BODY)
            .error_handler(|e, _| body_error(e)),
    )
    .app_data(web::QueryConfig::default().error_handler(|e, _| json_error(e)))
    .app_data(web::PathConfig::default().error_handler(|e, _| json_error(e)))
    .service(
        web::scope("")
            .wrap(actix_web::middleware::from_fn(crate::access::guard))
            .route("/", web::get().to(index))
            .route("/app.js", web::get().to(app_js))
            .route("/favicon.svg", web::get().to(favicon))
            .route("/favicon.ico", web::get().to(favicon))
            .service(
                web::scope("/api")
                    .route("/server", web::get().to(server_status))
                    .route("/volumes", web::get().to(volumes))
                    .route("/backend", web::get().to(backend))
                    .route("/events", web::get().to(events))
                    .route("/sessions", web::post().to(open))
                    .route("/sessions/{id}", web::get().to(get_session))
                    .route("/sessions/{id}", web::delete().to(close_session))
                    .route("/sessions/{id}/slice/{axis}/{index}", web::get().to(slice))
                    .route(
                        "/sessions/{id}/overlay/{axis}/{index}",
                        web::get().to(overlay),
                    )
                    .route("/sessions/{id}/strokes", web::put().to(put_strokes))
                    .route("/sessions/{id}/strokes", web::post().to(post_strokes))
                    .route("/sessions/{id}/strokes", web::get().to(get_strokes))
                    .route("/sessions/{id}/state", web::get().to(get_state))
                    .route("/sessions/{id}/state", web::put().to(put_state))
                    .route("/sessions/{id}/classes", web::put().to(put_classes))
                    .route("/sessions/{id}/render", web::get().to(render))
                    .route("/sessions/{id}/train", web::post().to(train))
                    .route("/sessions/{id}/fractions", web::get().to(fractions))
                    .route("/sessions/{id}/viewpoints", web::post().to(viewpoints))
                    .route("/sessions/{id}/tf", web::get().to(get_tf))
                    .route("/sessions/{id}/tf", web::put().to(put_tf))
                    .route("/sessions/{id}/preview.png", web::get().to(preview))
                    .route("/sessions/{id}/suggest", web::get().to(suggest))
                    .route("/sessions/{id}/prior", web::get().to(get_prior))
                    .route("/sessions/{id}/prior", web::put().to(put_prior))
                    .route("/presets/{name}", web::get().to(get_preset))
                    .route("/debug/crash/{actor}", web::post().to(crash))
                    .route(
                        "/sessions/{id}/export/labels.nii.gz",
                        web::get().to(export_labels),
                    )
                    .route(
                        "/sessions/{id}/export/scribbles.nii.gz",
                        web::get().to(export_scribbles),
                    )
                    .route(
                        "/sessions/{id}/export/probability/{file}",
                        web::get().to(export_probability),
                    )
                    .route("/sessions/{id}/export/zarr", web::post().to(export_zarr)),
            )
            .default_service(web::to(|| async {
                ApiError::NotFound("no such route".into()).error_response_owned()
            })),
    );
}

trait OwnedResponse {
    fn error_response_owned(self) -> HttpResponse;
}

impl OwnedResponse for ApiError {
    fn error_response_owned(self) -> HttpResponse {
        actix_web::ResponseError::error_response(&self)
    }
}
