//! The HTTP API (actix-web) and the embedded browser UI.

use crate::actors::{Actors, Hub, TrainCommand};
use crate::error::{ApiError, ApiResult};
use crate::imaging::{png, window, SliceAxes};
use crate::session::{Session, BACKGROUND};
use actix_web::{web, HttpResponse};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{ingest, open_volume, BrickStore, IngestOptions};
use neuvolex_classify::scribble::Stroke;
use serde::Deserialize;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

/// Most sessions open at once (each holds caches; memory stays bounded).
pub const MAX_SESSIONS: usize = 32;
/// Largest JSON body accepted.
pub const MAX_BODY: usize = 4 << 20;

/// Where volumes come from and where derived stores go.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Only volumes under this folder can be opened.
    pub data_root: PathBuf,
    /// Stores ingested from plain files are kept here.
    pub work_dir: PathBuf,
}

/// Shared state of the server.
pub struct AppState {
    /// Configuration.
    pub cfg: ServerConfig,
    /// Open sessions by id.
    pub sessions: RwLock<HashMap<String, Arc<Session>>>,
    /// The actors.
    pub actors: Actors,
    next: AtomicU64,
}

impl AppState {
    /// State with the actors started (call inside a tokio runtime).
    pub fn new(cfg: ServerConfig) -> web::Data<AppState> {
        web::Data::new(AppState {
            cfg,
            sessions: RwLock::new(HashMap::new()),
            actors: Actors::start(Hub::default()),
            next: AtomicU64::new(1),
        })
    }

    fn session(&self, id: &str) -> ApiResult<Arc<Session>> {
        self.sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(id)
            .cloned()
            .ok_or_else(|| ApiError::NotFound(format!("no session '{}'", id.escape_debug())))
    }

    /// Opens `rel` (a store, or a file ingested into the work folder) as a new session.
    pub fn open(&self, rel: &str) -> ApiResult<Arc<Session>> {
        if self
            .sessions
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .len()
            >= MAX_SESSIONS
        {
            return Err(ApiError::Busy(format!(
                "{MAX_SESSIONS} sessions are open; close one first"
            )));
        }
        let path = crate::paths::resolve(&self.cfg.data_root, rel)?;
        let store = match BrickStore::open(&path) {
            Ok(s) => s,
            Err(_) if path.is_dir() => {
                return Err(ApiError::BadRequest(format!(
                    "'{rel}' is a folder, not a volume or brick store"
                )))
            }
            Err(_) => {
                let name: String = rel
                    .chars()
                    .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
                    .collect();
                let dest = self.cfg.work_dir.join(format!("{name}.zarr"));
                match BrickStore::open(&dest) {
                    Ok(s) => s,
                    Err(_) => {
                        let mut src = open_volume(&path, None)
                            .map_err(|e| ApiError::BadRequest(format!("{rel}: {e}")))?;
                        ingest(
                            src.as_mut(),
                            &dest,
                            &IngestOptions {
                                brick: 32,
                                overwrite: true,
                                ..Default::default()
                            },
                            &mut |_| {},
                        )
                        .map_err(|e| ApiError::BadRequest(format!("{rel}: {e}")))?;
                        BrickStore::open(&dest)?
                    }
                }
            }
        };
        let id = format!("s{}", self.next.fetch_add(1, Ordering::SeqCst));
        let s = Session::new(id.clone(), rel.to_string(), Arc::new(store));
        self.sessions
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id, s.clone());
        Ok(s)
    }
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
    serde_json::json!({
        "id": s.id, "volume": s.name, "dims": i.dims, "spacing": i.spacing,
        "range": [i.stats.min, i.stats.max], "percentiles": [i.stats.p0_5, i.stats.p99_5],
        "histogram": i.stats.histogram,
        "classes": *s.classes.read().unwrap_or_else(|p| p.into_inner()),
        "background": BACKGROUND,
        "strokes": s.strokes.read().unwrap_or_else(|p| p.into_inner()).len(),
        "generation": s.generation.load(Ordering::SeqCst),
        "status": *s.status.read().unwrap_or_else(|p| p.into_inner()),
        "trained": neuvolex_features::train::model_path(&s.store).exists(),
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

async fn volumes(st: web::Data<AppState>) -> HttpResponse {
    HttpResponse::Ok().json(crate::paths::list(&st.cfg.data_root, 3))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OpenReq {
    volume: String,
}

async fn open(st: web::Data<AppState>, req: web::Json<OpenReq>) -> ApiResult<HttpResponse> {
    let st2 = st.clone();
    let rel = req.into_inner().volume;
    let s = blocking(move || st2.open(&rel)).await?;
    Ok(HttpResponse::Created().json(info(&s)))
}

async fn get_session(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(info(&s)))
}

async fn close_session(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    s.generation.fetch_add(1, Ordering::SeqCst); // cancels its work
    st.sessions
        .write()
        .unwrap_or_else(|p| p.into_inner())
        .remove(&s.id);
    Ok(HttpResponse::NoContent().finish())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SliceQuery {
    window: Option<f64>,
    level: Option<f64>,
    kind: Option<String>,
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
    let kind = q.into_inner().kind.unwrap_or_else(|| "labels".into());
    if !["labels", "uncertainty"].contains(&kind.as_str()) {
        return Err(ApiError::BadRequest(format!(
            "overlay kind '{}' must be labels or uncertainty",
            kind.escape_debug()
        )));
    }
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let (w, h) = (d[a.u], d[a.v]);
        let classes = s.classes.read().unwrap_or_else(|p| p.into_inner()).clone();
        let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let ids = &probs.ids;
        let mut rgba = vec![0u8; w * h * 4];
        for j in 0..h {
            for i in 0..w {
                let Some(p) = probs.at(&s.store, a.voxel(d, index, i, j)) else {
                    continue;
                };
                let mut order: Vec<usize> = (0..p.len()).collect();
                order.sort_by(|&x, &y| p[y].cmp(&p[x]));
                let o = &mut rgba[(j * w + i) * 4..(j * w + i + 1) * 4];
                if kind == "uncertainty" {
                    // 1 - (p1 - p2): bright where the two best classes are close.
                    let m = p[order[0]] as i32 - order.get(1).map_or(0, |&k| p[k] as i32);
                    let u = (255 - m).clamp(0, 255) as u8;
                    o.copy_from_slice(&[255, 200, 0, u]);
                } else {
                    let best = order[0];
                    let id = ids[best];
                    if id == BACKGROUND || p[best] < 128 {
                        continue;
                    }
                    let c = classes
                        .iter()
                        .find(|c| c.id == id)
                        .map_or_else(|| neuvolex_bricks::synth::palette(id), |c| c.color);
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

async fn put_strokes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    strokes: web::Json<Vec<Stroke>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let strokes = strokes.into_inner();
    if strokes.len() > 100_000 {
        return Err(ApiError::BadRequest(format!(
            "{} strokes: at most 100000",
            strokes.len()
        )));
    }
    let generation = s.set_strokes(strokes)?;
    st.actors.classify(s.clone(), generation)?;
    Ok(HttpResponse::Accepted().json(serde_json::json!({"generation": generation})))
}

async fn put_classes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    classes: web::Json<Vec<ClassInfo>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let c = classes.into_inner();
    let mut ids: Vec<u32> = c.iter().map(|c| c.id).collect();
    ids.sort_unstable();
    ids.dedup();
    if ids.len() != c.len() || c.iter().any(|c| c.id == 0 || c.id >= BACKGROUND) || c.len() > 64 {
        return Err(ApiError::BadRequest(
            "classes need distinct ids in 1..254, at most 64".into(),
        ));
    }
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
    let mode = match q.mode.as_deref() {
        None if has_probs => neuvolex_render::Mode::Probabilistic,
        None | Some("intensity") => neuvolex_render::Mode::Intensity,
        Some("prob") => neuvolex_render::Mode::Probabilistic,
        Some("prob-intensity") => neuvolex_render::Mode::ProbIntensity,
        Some(o) => {
            return Err(ApiError::BadRequest(format!(
                "mode '{}' must be intensity, prob or prob-intensity",
                o.escape_debug()
            )))
        }
    };
    let tf = match q.tf.as_deref() {
        Some(t) => neuvolex_render::TfFile::preset(t)?,
        None => neuvolex_render::TfFile::preset(if s.store.info().stats.min < -500.0 {
            "ct-bone"
        } else {
            "grey"
        })?,
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
    let bytes = st.actors.render(s, params, tf).await?;
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
        "start" | "resume" => st.actors.train(TrainCommand::Start {
            session: s,
            epochs,
            resume: req.action == "resume",
        })?,
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
    let stream = futures_util::stream::unfold((rx, want), |(mut rx, want)| async move {
        loop {
            match rx.recv().await {
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
                        (rx, want),
                    ));
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => {
                    let line = format!("event: lagged\ndata: {{\"missed\": {n}}}\n\n");
                    return Some((Ok(web::Bytes::from(line)), (rx, want)));
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

async fn fractions(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
    let c = p.ids.len();
    let mut counts = vec![0u64; c];
    let mut total = 0u64;
    for v in p.bricks.values() {
        for px in v.chunks_exact(c.max(1)) {
            if let Some((k, _)) = px.iter().enumerate().max_by_key(|(_, &v)| v) {
                counts[k] += 1;
            }
            total += 1;
        }
    }
    let out: Vec<serde_json::Value> = p
        .ids
        .iter()
        .zip(&counts)
        .map(|(id, n)| serde_json::json!({"id": id, "fraction": *n as f64 / total.max(1) as f64}))
        .collect();
    Ok(HttpResponse::Ok().json(serde_json::json!({"classified_voxels": total, "classes": out})))
}

async fn export_labels(st: web::Data<AppState>, id: web::Path<String>) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let work = st.cfg.work_dir.clone();
    let bytes = blocking(move || -> ApiResult<Vec<u8>> {
        let d = s.store.info().dims;
        let mut lab = vec![0f64; d.iter().product()];
        let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
        let c = p.ids.len();
        for (idx, v) in &p.bricks {
            let b = s.store.brick(*idx)?;
            for z in 0..b.size[2] {
                for y in 0..b.size[1] {
                    for x in 0..b.size[0] {
                        let i = (z * b.size[1] + y) * b.size[0] + x;
                        let px = &v[i * c..(i + 1) * c];
                        let (k, &m) = px
                            .iter()
                            .enumerate()
                            .max_by_key(|(_, &v)| v)
                            .unwrap_or((0, &0));
                        let id = p.ids.get(k).copied().unwrap_or(0);
                        if m >= 128 && id != BACKGROUND {
                            let g = ((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0]
                                + b.origin[0]
                                + x;
                            lab[g] = id as f64;
                        }
                    }
                }
            }
        }
        drop(p);
        let mut vol = neuvolex_bricks::MemVolume::from_f64(d, neuvolex_bricks::DType::U8, &lab);
        vol.meta.spacing = s.store.info().spacing;
        let tmp = work.join(format!("{}-labels-{}.nii.gz", s.id, std::process::id()));
        neuvolex_bricks::nifti::write_nifti(&tmp, &mut vol, 6)?;
        let bytes = std::fs::read(&tmp).map_err(|e| ApiError::Internal(e.to_string()))?;
        let _ = std::fs::remove_file(&tmp);
        Ok(bytes)
    })
    .await?;
    Ok(HttpResponse::Ok()
        .content_type("application/gzip")
        .insert_header((
            "Content-Disposition",
            "attachment; filename=\"labels.nii.gz\"",
        ))
        .body(bytes))
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
    let hub = st.actors.hub.clone();
    let out = blocking(move || -> ApiResult<serde_json::Value> {
        use neuvolex_classify::features::{BrickFeatures, FeatureSet};
        use neuvolex_viewpoints::{direction_to_view, recommend, KMeansConfig, RecommendConfig};
        let model = neuvolex_features::checkpoint::load(&neuvolex_features::train::model_path(&s.store))
            .ok()
            .map(|l| Arc::new(l.model));
        let set: FeatureSet = if model.is_some() { "paper" } else { "local" }
            .parse()
            .map_err(ApiError::Internal)?;
        let fx = BrickFeatures::new(&s.store, set.clone(), model, false)?;
        let bricks = s.store.occupied_bricks(None);
        let rows: Vec<Vec<f32>> = bricks.iter().map(|b| fx.brick(b)).collect::<Result<_, _>>()?;
        let err = |e: String| neuvolex_viewpoints::ViewpointError::Input(e);
        let cfg = RecommendConfig {
            kmeans: KMeansConfig {
                k,
                algorithm: neuvolex_viewpoints::kmeans::Algorithm::MiniBatch { epochs: 3 },
                ..Default::default()
            },
            views,
            ..Default::default()
        };
        let rec = recommend(
            bricks.len(),
            fx.channels(),
            |i| Ok(&rows[i][..]),
            |i| Ok(s.store.derived(&bricks[i]).map_err(|e| err(e.to_string()))?.gradient),
            s.store.info().spacing,
            &cfg,
            &mut |_, _| {},
        )
        .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        let picked: Vec<serde_json::Value> = rec
            .selection
            .views
            .iter()
            .map(|&i| {
                let (az, el) = direction_to_view(rec.scores.views[i]);
                serde_json::json!({"azimuth": az, "elevation": el, "entropy": rec.scores.entropy[i]})
            })
            .collect();
        let out = serde_json::json!({
            "features": set.to_string(), "views": picked,
            "clusters_used": rec.kmeans.counts.iter().filter(|&&c| c > 0).count(),
            "uncovered": rec.selection.uncovered.len(),
            "seconds": rec.kmeans_seconds + rec.scoring_seconds,
        });
        hub.publish(Some(&s.id), "viewpoints", out.clone());
        Ok(out)
    })
    .await?;
    Ok(HttpResponse::Ok().json(out))
}

fn json_error(err: impl std::fmt::Display) -> actix_web::Error {
    ApiError::BadRequest(format!("malformed request: {err}")).into()
}

/// Registers the routes, body limits and error handlers.
pub fn configure(cfg: &mut web::ServiceConfig) {
    cfg.app_data(
        web::JsonConfig::default()
            .limit(MAX_BODY)
            .error_handler(|e, _| json_error(e)),
    )
    .app_data(web::QueryConfig::default().error_handler(|e, _| json_error(e)))
    .app_data(web::PathConfig::default().error_handler(|e, _| json_error(e)))
    .route("/", web::get().to(index))
    .route("/app.js", web::get().to(app_js))
    .service(
        web::scope("/api")
            .route("/volumes", web::get().to(volumes))
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
            .route("/sessions/{id}/classes", web::put().to(put_classes))
            .route("/sessions/{id}/render", web::get().to(render))
            .route("/sessions/{id}/train", web::post().to(train))
            .route("/sessions/{id}/fractions", web::get().to(fractions))
            .route("/sessions/{id}/viewpoints", web::post().to(viewpoints))
            .route(
                "/sessions/{id}/export/labels.nii.gz",
                web::get().to(export_labels),
            ),
    )
    .default_service(web::to(|| async {
        ApiError::NotFound("no such route".into()).error_response_owned()
    }));
}

trait OwnedResponse {
    fn error_response_owned(self) -> HttpResponse;
}

impl OwnedResponse for ApiError {
    fn error_response_owned(self) -> HttpResponse {
        actix_web::ResponseError::error_response(&self)
    }
}
