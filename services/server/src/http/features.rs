//! The feature set the classification uses: the choices with their measured trade, and the
//! switch (which re-classifies).

use super::{blocking, AppState};
use crate::error::{ApiError, ApiResult};
use crate::session::{Session, FEATURE_CHOICES};
use actix_web::{web, HttpResponse};
use serde::Deserialize;

/// The current set, whether it reads the INR, whether one is trained, whether its features
/// are kept in the store, and the choices.
fn features_json(s: &Session) -> serde_json::Value {
    let set = s.feature_set();
    let trained = s.current_model().is_some();
    // The background pass's array for this set: every brick in, some, or none kept.
    let stored = match s.stored_for(&set) {
        Some(p) if p.complete() => "complete",
        Some(_) => "pending",
        None => "none",
    };
    serde_json::json!({
        "set": set.to_string(),
        "stored": stored,
        "uses_inr": set.needs_model(),
        "inr_trained": trained,
        "choices": FEATURE_CHOICES
            .iter()
            .map(|c| {
                let mut v = serde_json::to_value(c).unwrap_or_default();
                v["available"] = (!c.uses_inr || trained).into();
                v
            })
            .collect::<Vec<_>>(),
    })
}

pub(super) async fn get_features(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(features_json(&s)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct FeaturesReq {
    set: String,
}

/// Switches the feature set (400 for an unknown set, 409 for one that needs an INR not
/// trained yet) and re-classifies the strokes with it.
pub(super) async fn put_features(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<FeaturesReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let name = req.into_inner().set;
    if name.len() > 200 {
        return Err(ApiError::BadRequest(
            "features: a set name is at most 200 characters".into(),
        ));
    }
    let permit = st.actors.reserve_classify()?;
    let s2 = s.clone();
    let generation = blocking(move || s2.set_feature_set(&name)).await?;
    let has_strokes = !s
        .strokes
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .is_empty();
    if has_strokes {
        permit.send(s.clone(), generation);
    }
    let mut out = features_json(&s);
    out["generation"] = generation.into();
    Ok(HttpResponse::Ok().json(out))
}
