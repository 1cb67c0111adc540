//! The spatial prior and the next-slice suggestion.

use super::{blocking, AppState};
use crate::error::ApiResult;
use actix_web::{web, HttpResponse};
use serde::Deserialize;
use std::sync::atomic::Ordering;

pub(super) async fn suggest(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    let v = blocking(move || crate::assist::suggest(&s)).await?;
    Ok(HttpResponse::Ok().json(v))
}

pub(super) async fn get_prior(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    Ok(HttpResponse::Ok().json(s.prior_summary()))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PriorReq {
    enabled: bool,
}

pub(super) async fn put_prior(
    st: web::Data<AppState>,
    id: web::Path<String>,
    req: web::Json<PriorReq>,
) -> ApiResult<HttpResponse> {
    let s = st.session(&id)?;
    s.prior_on.store(req.enabled, Ordering::SeqCst);
    s.touch();
    let sum = blocking(move || s.refresh_prior()).await?;
    Ok(HttpResponse::Ok().json(sum))
}
