//! The HTTP API (actix-web) and the embedded browser UI, one module per resource.

mod app;
mod assist;
mod features;
mod results;
mod server;
mod sessions;
mod slices;
mod strokes;
mod training;
mod views;

pub use app::{
    new_id, saved_sessions, session_path, AppState, ServerConfig, AUTOSAVE, DEFAULT_IDLE_CLOSE,
    MAX_BODY, MAX_SESSIONS, SAVED_ROUNDS,
};

use crate::error::{ApiError, ApiResult};
use crate::session::{Session, BACKGROUND};
use actix_web::{web, HttpResponse};
use std::sync::atomic::Ordering;

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
        // The voxel -> world (mm) affine, row-major 4x4, for the slice positions and readout.
        "affine": i.affine,
        "range": [i.stats.min, i.stats.max], "percentiles": [i.stats.p0_5, i.stats.p99_5],
        // The intensities' unit ("HU" for CT, decided from the data), for the window/level
        // presets and the readout.
        "unit": crate::imaging::intensity_unit(i.stats.min),
        "histogram": i.stats.histogram,
        "classes": *s.classes.read().unwrap_or_else(|p| p.into_inner()),
        "background": BACKGROUND,
        "strokes": s.strokes.read().unwrap_or_else(|p| p.into_inner()).len(),
        "generation": s.generation.load(Ordering::SeqCst),
        "status": *s.status.read().unwrap_or_else(|p| p.into_inner()),
        "trained": model.is_some(),
        "features": s.feature_set().to_string(),
        "model_version": model.map_or(0, |m| m.0),
        "tf": s.tf.read().unwrap_or_else(|p| p.into_inner()).as_ref().map(|t| t.0.clone()),
        "prior": s.prior_summary(),
    })
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
            .route("/", web::get().to(server::index))
            .route("/app.js", web::get().to(server::app_js))
            .route("/favicon.svg", web::get().to(server::favicon))
            .route("/favicon.ico", web::get().to(server::favicon))
            .service(
                web::scope("/api")
                    .route("/server", web::get().to(server::server_status))
                    .route("/volumes", web::get().to(server::volumes))
                    .route("/backend", web::get().to(server::backend))
                    .route("/events", web::get().to(server::events))
                    .route("/sessions", web::post().to(sessions::open))
                    .route("/sessions", web::get().to(sessions::list))
                    .route("/sessions/{id}/ui", web::put().to(sessions::put_ui))
                    .route("/sessions/{id}", web::get().to(sessions::get_session))
                    .route("/sessions/{id}", web::delete().to(sessions::close_session))
                    .route(
                        "/sessions/{id}/slice/{axis}/{index}",
                        web::get().to(slices::slice),
                    )
                    .route(
                        "/sessions/{id}/overlay/{axis}/{index}",
                        web::get().to(slices::overlay),
                    )
                    .route(
                        "/sessions/{id}/voxel/{x}/{y}/{z}",
                        web::get().to(slices::voxel),
                    )
                    .route(
                        "/sessions/{id}/strokes",
                        web::put().to(strokes::put_strokes),
                    )
                    .route(
                        "/sessions/{id}/strokes",
                        web::post().to(strokes::post_strokes),
                    )
                    .route(
                        "/sessions/{id}/strokes",
                        web::get().to(strokes::get_strokes),
                    )
                    .route("/sessions/{id}/state", web::get().to(sessions::get_state))
                    .route("/sessions/{id}/state", web::put().to(sessions::put_state))
                    .route(
                        "/sessions/{id}/classes",
                        web::put().to(sessions::put_classes),
                    )
                    .route("/sessions/{id}/render", web::get().to(views::render))
                    .route("/sessions/{id}/train", web::post().to(training::train))
                    .route(
                        "/sessions/{id}/features",
                        web::get().to(features::get_features),
                    )
                    .route(
                        "/sessions/{id}/features",
                        web::put().to(features::put_features),
                    )
                    .route(
                        "/sessions/{id}/fractions",
                        web::get().to(results::fractions),
                    )
                    .route(
                        "/sessions/{id}/viewpoints",
                        web::post().to(views::viewpoints),
                    )
                    .route("/sessions/{id}/tf", web::get().to(views::get_tf))
                    .route("/sessions/{id}/tf", web::put().to(views::put_tf))
                    .route(
                        "/sessions/{id}/preview.png",
                        web::get().to(training::preview),
                    )
                    .route("/sessions/{id}/suggest", web::get().to(assist::suggest))
                    .route("/sessions/{id}/prior", web::get().to(assist::get_prior))
                    .route("/sessions/{id}/prior", web::put().to(assist::put_prior))
                    .route("/presets/{name}", web::get().to(views::get_preset))
                    .route("/debug/crash/{actor}", web::post().to(server::crash))
                    .route(
                        "/sessions/{id}/export/labels.nii.gz",
                        web::get().to(results::export_labels),
                    )
                    .route(
                        "/sessions/{id}/export/scribbles.nii.gz",
                        web::get().to(results::export_scribbles),
                    )
                    .route(
                        "/sessions/{id}/export/probability/{file}",
                        web::get().to(results::export_probability),
                    )
                    .route(
                        "/sessions/{id}/export/zarr",
                        web::post().to(results::export_zarr),
                    ),
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
