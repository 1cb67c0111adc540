//! Server-wide routes: the page and its assets, the volumes on offer, the backend, the
//! server's limits, the event stream and fault injection.

use super::AppState;
use crate::error::{ApiError, ApiResult};
use actix_web::{web, HttpResponse};
use serde::Deserialize;
use std::sync::atomic::Ordering;

/// A page asset: the copy embedded at build time, or, where `NEUVOLEX_STATIC_DIR` names a
/// folder (UI development), the file of that name read from it at each request.
fn asset(name: &str, embedded: &'static str) -> String {
    match std::env::var_os("NEUVOLEX_STATIC_DIR") {
        Some(dir) => std::fs::read_to_string(std::path::Path::new(&dir).join(name))
            .unwrap_or_else(|e| format!("/* {name}: {e} */")),
        None => embedded.to_string(),
    }
}

pub(super) async fn index() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("text/html; charset=utf-8")
        .insert_header(("Cache-Control", "no-cache"))
        .body(asset("index.html", include_str!("../../static/index.html")))
}

pub(super) async fn app_js() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("text/javascript; charset=utf-8")
        .insert_header(("Cache-Control", "no-cache"))
        .body(asset("app.js", include_str!("../../static/app.js")))
}

pub(super) async fn favicon() -> HttpResponse {
    HttpResponse::Ok()
        .content_type("image/svg+xml")
        .insert_header(("Cache-Control", "max-age=86400"))
        .body(include_str!("../../static/favicon.svg"))
}

pub(super) async fn backend(st: web::Data<AppState>) -> HttpResponse {
    HttpResponse::Ok().json(st.actors.compute())
}

pub(super) async fn volumes(st: web::Data<AppState>) -> HttpResponse {
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

/// The server's limits and how much of them is in use.
pub(super) async fn server_status(st: web::Data<AppState>) -> HttpResponse {
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

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct EventsQuery {
    session: Option<String>,
}

pub(super) async fn events(st: web::Data<AppState>, q: web::Query<EventsQuery>) -> HttpResponse {
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

pub(super) async fn crash(
    st: web::Data<AppState>,
    actor: web::Path<String>,
) -> ApiResult<HttpResponse> {
    if !st.cfg.fault_injection {
        return Err(ApiError::NotFound("no such route".into()));
    }
    st.actors.crash(&actor)?;
    Ok(HttpResponse::Accepted().json(serde_json::json!({"crashing": actor.into_inner()})))
}
