//! Scribbles: replace, append, list, with the focus the page has on screen.

use super::{blocking, AppState};
use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use actix_web::{web, HttpResponse};
use neuvolex_classify::scribble::Stroke;
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct StrokesQuery {
    /// `x,y,z`: the voxel whose three slices are on screen, classified first after the
    /// stroke's own slice.
    focus: Option<String>,
}

/// Keeps the focus a stroke request names (a bad one is a 400 naming it).
pub(super) fn set_focus(s: &Session, q: &StrokesQuery) -> ApiResult<()> {
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

/// The body of `PUT .../strokes`: the whole stroke list, or the list with the page's redo
/// stack (undo and redo send both, so a reload keeps redo).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WithRedo {
    strokes: Vec<Stroke>,
    redo: Vec<Stroke>,
}

pub(super) async fn put_strokes(
    st: web::Data<AppState>,
    id: web::Path<String>,
    q: web::Query<StrokesQuery>,
    body: web::Json<serde_json::Value>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    set_focus(&s, &q)?;
    let body = body.into_inner();
    let bad = |e: serde_json::Error| {
        ApiError::BadRequest(format!(
            "malformed request: strokes: {e} (send a list of strokes, or \
             {{\"strokes\": [...], \"redo\": [...]}})"
        ))
    };
    let (strokes, redo) = if body.is_array() {
        (
            serde_json::from_value::<Vec<Stroke>>(body).map_err(bad)?,
            None,
        )
    } else {
        let w = serde_json::from_value::<WithRedo>(body).map_err(bad)?;
        (w.strokes, Some(w.redo))
    };
    let permit = st.actors.reserve_classify()?;
    let s2 = s.clone();
    let generation = blocking(move || match redo {
        Some(r) => s2.set_strokes_and_redo(strokes, r),
        None => s2.set_strokes(strokes),
    })
    .await?;
    permit.send(s.clone(), generation);
    Ok(HttpResponse::Accepted().json(serde_json::json!({"generation": generation})))
}

/// Appends strokes (several clients may draw on one session: none is lost); answers the new
/// generation and how many strokes the session holds.
pub(super) async fn post_strokes(
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

pub(super) async fn get_strokes(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let strokes = s.strokes.read().unwrap_or_else(|p| p.into_inner()).clone();
    Ok(HttpResponse::Ok().json(strokes))
}
