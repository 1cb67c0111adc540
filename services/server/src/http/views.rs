//! The 3-D view: renders, transfer functions and presets, recommended viewpoints.

use super::{info, AppState};
use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use actix_web::{web, HttpResponse};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RenderQuery {
    az: Option<f32>,
    el: Option<f32>,
    size: Option<usize>,
    mode: Option<String>,
    tf: Option<String>,
    /// Magnification over the default framing (the volume's bounding sphere fills the
    /// frame), in [0.25, 8].
    zoom: Option<f32>,
    /// A client's cache-buster, ignored.
    #[serde(rename = "t")]
    _t: Option<String>,
}

pub(super) async fn render(
    st: web::Data<AppState>,
    id: web::Path<String>,
    q: web::Query<RenderQuery>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let q = q.into_inner();
    let size = q.size.unwrap_or(256);
    let zoom = q.zoom.unwrap_or(1.0);
    if !(0.25..=8.0).contains(&zoom) {
        return Err(ApiError::BadRequest(format!(
            "zoom {zoom} must be in [0.25, 8]"
        )));
    }
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
            fov: neuvolex_render::Camera::default().fov / zoom,
            ..Default::default()
        },
        ..Default::default()
    };
    params.validate()?;
    let bytes = st.actors.render(s, params, tf, labels).await?;
    Ok(HttpResponse::Ok().content_type("image/png").body(bytes))
}

/// `POST /sessions/{id}/viewpoints`: all fields optional.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ViewReq {
    /// Feature clusters (50).
    k: Option<usize>,
    /// Candidate views on the sphere (1800).
    views: Option<usize>,
    /// Views to recommend (4).
    count: Option<usize>,
    /// Least angle between two recommended views, degrees (30).
    min_angle: Option<f32>,
}

/// Most views one recommendation returns.
const MAX_COUNT: usize = 12;
/// Largest `min_angle`, degrees: past it even a few views rarely fit on the sphere.
const MAX_MIN_ANGLE: f32 = 90.0;

pub(super) async fn viewpoints(
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
    let pick = neuvolex_viewpoints::PickConfig {
        count: req.count.unwrap_or(4),
        min_angle: req.min_angle.unwrap_or(30.0),
        ..Default::default()
    };
    if !(1..=MAX_COUNT).contains(&pick.count) {
        return Err(ApiError::BadRequest(format!(
            "count {} must be 1..={MAX_COUNT}",
            pick.count
        )));
    }
    if !(0.0..=MAX_MIN_ANGLE).contains(&pick.min_angle) {
        return Err(ApiError::BadRequest(format!(
            "min_angle {} must be 0..={MAX_MIN_ANGLE} degrees",
            pick.min_angle
        )));
    }
    let out = st.actors.viewpoints(s, k, views, pick).await?;
    Ok(HttpResponse::Ok().json(out))
}

/// The session's transfer function, else a preset suited to the data (CT bone or grey).
pub(super) fn session_tf(s: &Session) -> ApiResult<neuvolex_render::TfFile> {
    if let Some((_, t)) = s.tf.read().unwrap_or_else(|p| p.into_inner()).as_ref() {
        return Ok(t.clone());
    }
    Ok(neuvolex_render::TfFile::preset(default_preset(s))?)
}

pub(super) fn default_preset(s: &Session) -> &'static str {
    neuvolex_render::TfFile::default_preset(s.store.info().stats.min)
}

pub(super) async fn get_tf(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let tf = s.tf.read().unwrap_or_else(|p| p.into_inner()).clone();
    let json = match tf {
        Some((v, _)) => v,
        None => preset_json(default_preset(&s))?,
    };
    Ok(HttpResponse::Ok().json(json))
}

pub(super) fn preset_json(name: &str) -> ApiResult<serde_json::Value> {
    let (_, text) = neuvolex_render::tf::PRESETS
        .iter()
        .find(|(n, _)| *n == name)
        .ok_or_else(|| ApiError::NotFound(format!("no preset '{}'", name.escape_debug())))?;
    serde_json::from_str(text).map_err(|e| ApiError::Internal(e.to_string()))
}

pub(super) async fn get_preset(name: web::Path<String>) -> ApiResult<HttpResponse> {
    Ok(HttpResponse::Ok().json(preset_json(&name)?))
}

/// Sets the session's transfer function (the JSON format of `neuvolex render --tf`); `null`
/// returns to the default preset.
pub(super) async fn put_tf(
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
    s.touch();
    Ok(HttpResponse::Ok().json(info(&s)))
}
