//! Sessions: open (restoring the saved state), describe, close; the session file; classes.

use super::{blocking, info, AppState, MAX_BODY};
use crate::error::{ApiError, ApiResult};
use actix_web::{web, HttpResponse};
use neuvolex_bricks::synth::ClassInfo;
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct OpenReq {
    /// Open a new session on this volume.
    #[serde(default)]
    volume: Option<String>,
    /// With `volume`: resume the newest saved session of that volume instead, if there is one.
    #[serde(default)]
    restore: bool,
    /// Re-attach to this session: the open one, or reopen the one saved under this id.
    #[serde(default)]
    resume: Option<String>,
}

/// `POST /sessions`: `{volume}` opens a new session; `{resume: ID}` re-attaches to session ID
/// (open, or reopened from its file: 200) and `{volume, restore: true}` to the newest saved
/// session of that volume (a new one where none is saved).
pub(super) async fn open(
    st: web::Data<AppState>,
    req: web::Json<OpenReq>,
) -> ApiResult<HttpResponse> {
    let req = req.into_inner();
    let resume = match (&req.volume, req.resume) {
        (Some(_), Some(_)) => {
            return Err(ApiError::BadRequest(
                "give either volume (a new session) or resume (an existing one), not both".into(),
            ))
        }
        (None, None) => {
            return Err(ApiError::BadRequest(
                "give volume (a new session) or resume (a session id)".into(),
            ))
        }
        (Some(v), None) if req.restore => st.newest_saved(v),
        (_, r) => r,
    };
    if let Some(id) = resume {
        let (s, _) = st.resume(&id).await?;
        return Ok(HttpResponse::Ok().json(info(&s)));
    }
    let s = st.open(req.volume.as_deref().unwrap_or_default()).await?;
    Ok(HttpResponse::Created().json(info(&s)))
}

/// `GET /sessions`: the open and the saved sessions, newest first.
pub(super) async fn list(st: web::Data<AppState>) -> ApiResult<HttpResponse> {
    let st2 = st.clone();
    let v = blocking(move || Ok(st2.list())).await?;
    Ok(HttpResponse::Ok().json(serde_json::json!({ "sessions": v })))
}

/// `PUT /sessions/{id}/ui`: the page's own settings (a JSON object of at most
/// `neuvolex_session::MAX_UI` bytes), saved with the session.
pub(super) async fn put_ui(
    st: web::Data<AppState>,
    id: web::Path<String>,
    ui: web::Json<serde_json::Value>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let ui = ui.into_inner();
    neuvolex_session::validate_ui(&ui).map_err(ApiError::BadRequest)?;
    *s.ui.write().unwrap_or_else(|p| p.into_inner()) = Some(ui);
    s.touch();
    Ok(HttpResponse::NoContent().finish())
}

pub(super) async fn get_session(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(info(&s)))
}

pub(super) async fn close_session(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let st2 = st.clone();
    blocking(move || st2.close(&s)).await?;
    Ok(HttpResponse::NoContent().finish())
}

/// The session file: volume, classes, strokes, redo stack, transfer function, features,
/// prior, page settings, and the label rounds of its last save.
pub(super) async fn get_state(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let (s2, work) = (s.clone(), st.cfg.work_dir.clone());
    // The label bricks its rounds name are written first, so loading the file on this server
    // brings the labels back.
    let state = blocking(move || super::app::file_with_rounds(&work, &s2)).await?;
    Ok(HttpResponse::Ok().json(state))
}

/// Loads a session file into the session: every part is validated (and the strokes checked
/// against the grid) before anything changes.
pub(super) async fn put_state(
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
    let (s2, work) = (s.clone(), st.cfg.work_dir.clone());
    let generation = blocking(move || {
        let g = s2.apply_state(&f, &src)?;
        // A file saved by this server brings its label history, so the labels it showed come
        // back voxel for voxel (without it, they are classified afresh).
        super::app::restore_rounds(&work, &s2, &f, &src);
        Ok(g)
    })
    .await?;
    permit.send(s.clone(), generation);
    Ok(HttpResponse::Ok().json(info(&s)))
}

pub(super) async fn put_classes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    classes: web::Json<Vec<ClassInfo>>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let c = classes.into_inner();
    neuvolex_session::validate_classes(&c).map_err(ApiError::BadRequest)?;
    *s.classes.write().unwrap_or_else(|p| p.into_inner()) = c;
    s.touch();
    // Recolouring changes the render classes; the next render starts from scratch.
    Ok(HttpResponse::Ok().json(info(&s)))
}
