//! INR training (start, stop, resume) and its preview.

use super::{blocking, AppState};
use crate::actors::{TrainCommand, TrainingSlot};
use crate::error::{ApiError, ApiResult};
use actix_web::{web, HttpResponse};
use serde::Deserialize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct TrainReq {
    action: String,
    epochs: Option<f64>,
}

pub(super) async fn train(
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

pub(super) async fn preview(
    st: web::Data<AppState>,
    id: web::Path<String>,
) -> ApiResult<HttpResponse> {
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
