//! Sessions: open (restoring the saved state), describe, close; the session file; classes.

use super::{blocking, info, state_path, AppState, MAX_BODY};
use crate::error::{ApiError, ApiResult};
use actix_web::{web, HttpResponse};
use neuvolex_bricks::synth::ClassInfo;
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct OpenReq {
    volume: String,
    /// Restore the state saved when this volume's last session closed or the server stopped.
    #[serde(default)]
    restore: bool,
}

pub(super) async fn open(
    st: web::Data<AppState>,
    req: web::Json<OpenReq>,
) -> ApiResult<HttpResponse> {
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

/// The session file: volume, classes, strokes and transfer function.
pub(super) async fn get_state(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(s.state()))
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
    let s2 = s.clone();
    let generation = blocking(move || s2.apply_state(&f, &src)).await?;
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
    // Recolouring changes the render classes; the next render starts from scratch.
    Ok(HttpResponse::Ok().json(info(&s)))
}
