//! Who may use the server, and how long a request may take: the one middleware in front of
//! every route.
//!
//! - **Token.** With [`ServerConfig::token`](crate::ServerConfig::token) set (as `neuvolex
//!   serve` does whenever it listens beyond loopback), a request must carry the token: as
//!   `Authorization: Bearer TOKEN`, as an `X-Neuvolex-Token` header, as the cookie the first
//!   visit of the printed URL sets (`?token=TOKEN`, as Jupyter does; the page is then reloaded
//!   without it), or as `?token=`. Others get 401 with a JSON error.
//! - **Host.** With [`ServerConfig::local_only`](crate::ServerConfig::local_only) (loopback
//!   without a token), a `Host` that is not a loopback name is refused (403): a web page cannot
//!   reach the server by rebinding its own domain name to 127.0.0.1.
//! - **Origin.** A state-changing request (anything but GET, HEAD and OPTIONS) from a browser
//!   page of another origin is refused (403), whatever the address: another site cannot draw,
//!   train or export on your behalf.
//! - **Timeout.** A request that takes longer than
//!   [`ServerConfig::request_timeout`](crate::ServerConfig::request_timeout) is answered with
//!   503; a render is cancelled with it, other work already under way finishes in the
//!   background; event streams are exempt.
//! - **Shutdown.** Once shutdown began, new requests get 503.

use crate::error::ApiError;
use crate::http::AppState;
use actix_web::body::{BoxBody, MessageBody};
use actix_web::dev::{ServiceRequest, ServiceResponse};
use actix_web::http::{header, Method, StatusCode};
use actix_web::middleware::Next;
use actix_web::{web, HttpResponse, ResponseError};

/// The cookie that carries the token; the port is part of the name because browsers share
/// cookies between ports of one host.
pub fn cookie_name(port: u16) -> String {
    format!("neuvolex_token_{port}")
}

/// Compares in time independent of where the strings differ.
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// The `token` query parameter, if any.
fn query_token(req: &ServiceRequest) -> Option<&str> {
    req.query_string()
        .split('&')
        .find_map(|kv| kv.strip_prefix("token="))
}

/// The token a request carries, wherever it is.
fn presented(req: &ServiceRequest) -> Vec<String> {
    let mut out = Vec::new();
    let h = req.headers();
    if let Some(v) = h.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()) {
        if let Some(t) = v
            .strip_prefix("Bearer ")
            .or_else(|| v.strip_prefix("token "))
        {
            out.push(t.trim().to_string());
        }
    }
    if let Some(v) = h.get("x-neuvolex-token").and_then(|v| v.to_str().ok()) {
        out.push(v.trim().to_string());
    }
    for v in h.get_all(header::COOKIE).filter_map(|v| v.to_str().ok()) {
        for kv in v.split(';') {
            if let Some((k, val)) = kv.trim().split_once('=') {
                if k.starts_with("neuvolex_token_") {
                    out.push(val.to_string());
                }
            }
        }
    }
    if let Some(t) = query_token(req) {
        out.push(t.to_string());
    }
    out
}

/// The host name of a `Host` header, without the port.
fn host_name(host: &str) -> &str {
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split(']').next().unwrap_or("");
    }
    host.rsplit_once(':').map_or(host, |(h, _)| h)
}

/// True for names that can only mean this machine.
pub fn is_loopback_name(host: &str) -> bool {
    let h = host_name(host).to_ascii_lowercase();
    h == "localhost"
        || h.ends_with(".localhost")
        || h == "::1"
        || h.parse::<std::net::Ipv4Addr>()
            .is_ok_and(|a| a.is_loopback())
}

fn refuse(req: ServiceRequest, e: ApiError) -> ServiceResponse<BoxBody> {
    req.into_response(e.error_response())
}

fn unauthorized(req: ServiceRequest) -> ServiceResponse<BoxBody> {
    let path = req.path().to_string();
    let body = serde_json::json!({
        "error": format!(
            "{path}: this server needs its token: open the URL `neuvolex serve` printed \
             (http://HOST:PORT/?token=...), or send `Authorization: Bearer TOKEN`"
        )
    });
    let resp = HttpResponse::build(StatusCode::UNAUTHORIZED)
        .insert_header((header::WWW_AUTHENTICATE, "Bearer realm=\"neuvolex\""))
        .json(body);
    req.into_response(resp)
}

/// The middleware: shutdown, host, token, origin, then the request under its timeout.
pub async fn guard(
    req: ServiceRequest,
    next: Next<impl MessageBody + 'static>,
) -> Result<ServiceResponse<BoxBody>, actix_web::Error> {
    let Some(st) = req.app_data::<web::Data<AppState>>().cloned() else {
        return next.call(req).await.map(|r| r.map_into_boxed_body());
    };
    if st.shutting_down() {
        return Ok(refuse(
            req,
            ApiError::Busy("the server is shutting down".into()),
        ));
    }
    let host = req
        .headers()
        .get(header::HOST)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    if st.cfg.local_only {
        if let Some(h) = &host {
            if !is_loopback_name(h) {
                return Ok(refuse(
                    req,
                    ApiError::Forbidden(format!(
                        "host '{}' is not this machine: the server only answers on loopback \
                         (start it with --host and a token to serve other machines)",
                        h.escape_debug()
                    )),
                ));
            }
        }
    }
    let mut set_cookie = None;
    if let Some(token) = &st.cfg.token {
        if !presented(&req).iter().any(|t| same(t, token)) {
            return Ok(unauthorized(req));
        }
        if let Some(t) = query_token(&req) {
            let port = req.app_config().local_addr().port();
            let cookie = format!(
                "{}={t}; Path=/; HttpOnly; SameSite=Strict",
                cookie_name(port)
            );
            // The first visit of the printed URL: keep the token in a cookie and show the
            // page without it in the address bar.
            if req.method() == Method::GET && !req.path().starts_with("/api/") {
                let rest: Vec<&str> = req
                    .query_string()
                    .split('&')
                    .filter(|kv| !kv.is_empty() && !kv.starts_with("token="))
                    .collect();
                let to = if rest.is_empty() {
                    req.path().to_string()
                } else {
                    format!("{}?{}", req.path(), rest.join("&"))
                };
                let resp = HttpResponse::Found()
                    .insert_header((header::LOCATION, to))
                    .insert_header((header::SET_COOKIE, cookie))
                    .finish();
                return Ok(req.into_response(resp));
            }
            set_cookie = Some(cookie);
        }
    }
    if !matches!(*req.method(), Method::GET | Method::HEAD | Method::OPTIONS) {
        let h = req.headers();
        let origin = h.get(header::ORIGIN).and_then(|v| v.to_str().ok());
        let site = h.get("sec-fetch-site").and_then(|v| v.to_str().ok());
        let cross = match (origin, &host) {
            (Some(o), Some(hst)) => {
                let o = o.to_ascii_lowercase();
                let hst = hst.to_ascii_lowercase();
                o != format!("http://{hst}") && o != format!("https://{hst}")
            }
            (Some(_), None) => true,
            (None, _) => site.is_some_and(|s| s != "same-origin" && s != "none"),
        };
        if cross {
            let msg = format!(
                "{} {}: refused a state-changing request from another origin ({})",
                req.method(),
                req.path(),
                origin.or(site).unwrap_or("?").escape_debug()
            );
            return Ok(refuse(req, ApiError::Forbidden(msg)));
        }
    }
    let streaming = req.path() == "/api/events";
    let what = format!("{} {}", req.method(), req.path());
    let mut resp = if streaming {
        next.call(req).await?.map_into_boxed_body()
    } else {
        match tokio::time::timeout(st.cfg.request_timeout, next.call(req)).await {
            Ok(r) => r?.map_into_boxed_body(),
            Err(_) => {
                // The request went with the dropped handler: the error becomes the answer. A
                // render is cancelled with it (the renderer polls its requester); other work
                // already handed to a worker thread (an export, a viewpoint search) cannot be
                // interrupted safely and finishes in the background.
                let fate = if what.ends_with("/render") {
                    "the render was cancelled"
                } else {
                    "work already under way finishes in the background"
                };
                let e = ApiError::Busy(format!(
                    "{what} took longer than the server's request timeout of {:?}; {fate}",
                    st.cfg.request_timeout
                ));
                return Err(e.into());
            }
        }
    };
    if let Some(c) = set_cookie {
        if let Ok(v) = header::HeaderValue::from_str(&c) {
            resp.headers_mut().append(header::SET_COOKIE, v);
        }
    }
    Ok(resp)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_names() {
        for h in [
            "localhost:8080",
            "127.0.0.1:1",
            "127.3.4.5",
            "[::1]:8080",
            "LOCALHOST",
            "a.localhost",
        ] {
            assert!(is_loopback_name(h), "{h}");
        }
        for h in [
            "evil.example:8080",
            "10.0.0.1:8080",
            "[::2]:80",
            "localhost.evil.com",
            "",
        ] {
            assert!(!is_loopback_name(h), "{h}");
        }
    }

    #[test]
    fn comparison() {
        assert!(same("abc", "abc"));
        assert!(!same("abc", "abd"));
        assert!(!same("abc", "abcd"));
    }
}
