//! Who may use the server and how much of it: the token, the loopback host check, refusal of
//! cross-origin writes, the data root as the only readable place (a detached NRRD header naming
//! a file outside it included), and each limit (sessions, the feature cache across sessions,
//! the render cache and probabilities across sessions, the request timeout, concurrent
//! trainings, the body size) answering with a clear 4xx/503 and a JSON error. Also the session
//! file (save, load, restore) and concurrent appends.

#[macro_use]
mod common;

use actix_web::http::StatusCode;
use actix_web::test;
use common::*;
use serde_json::{json, Value};
use std::time::{Duration, Instant};

async fn error_of(r: actix_web::dev::ServiceResponse) -> String {
    let v: Value = test::read_body_json(r).await;
    v["error"]
        .as_str()
        .unwrap_or_else(|| panic!("no JSON error: {v}"))
        .to_string()
}

#[actix_web::test]
async fn a_token_is_required_when_set() {
    let (_d, mut cfg) = data();
    cfg.token = Some("s3cret-token-0123".into());
    let app = app!(cfg);
    // Nothing without it: the page, the API, the event stream.
    for uri in [
        "/",
        "/app.js",
        "/api/volumes",
        "/api/events",
        "/api/nothing",
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(uri).to_request()).await;
        assert_eq!(r.status(), StatusCode::UNAUTHORIZED, "{uri}");
        assert!(r.headers().contains_key("www-authenticate"));
        assert!(error_of(r).await.contains("token"), "{uri}");
    }
    for bad in ["Bearer wrong-token-0123", "Bearer ", "Basic czNjcmV0"] {
        let r = test::call_service(
            &app,
            test::TestRequest::get()
                .uri("/api/volumes")
                .insert_header(("authorization", bad))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 401, "{bad}");
    }
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(json!({"volume": "ph.zarr"}))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 401, "no session opens without the token");
    // The header, the X-Neuvolex-Token header, the cookie.
    for (k, v) in [
        ("authorization", "Bearer s3cret-token-0123".to_string()),
        ("x-neuvolex-token", "s3cret-token-0123".to_string()),
        (
            "cookie",
            "a=b; neuvolex_token_8080=s3cret-token-0123".to_string(),
        ),
    ] {
        let r = test::call_service(
            &app,
            test::TestRequest::get()
                .uri("/api/volumes")
                .insert_header((k, v.clone()))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 200, "{k}: {v}");
    }
    // The printed URL: the first visit sets the cookie and drops the token from the address.
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/?token=s3cret-token-0123&x=1")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), StatusCode::FOUND);
    assert_eq!(r.headers().get("location").unwrap(), "/?x=1");
    let cookie = r.headers().get("set-cookie").unwrap().to_str().unwrap();
    assert!(cookie.starts_with("neuvolex_token_"), "{cookie}");
    assert!(
        cookie.contains("HttpOnly") && cookie.contains("SameSite=Strict"),
        "{cookie}"
    );
    let cookie = cookie.split(';').next().unwrap().to_string();
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/")
            .insert_header(("cookie", cookie.clone()))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200, "the page loads with the cookie");
    // An API call with ?token= works too, and sets the cookie.
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/api/server?token=s3cret-token-0123")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    assert!(r.headers().contains_key("set-cookie"));
    let v: Value = test::read_body_json(r).await;
    assert_eq!(v["access"], "token");
}

#[actix_web::test]
async fn on_loopback_only_loopback_names_are_answered() {
    let (_d, mut cfg) = data();
    cfg.local_only = true;
    let app = app!(cfg);
    for (host, code) in [
        ("127.0.0.1:8080", 200),
        ("localhost:8080", 200),
        ("[::1]:8080", 200),
        ("evil.example:8080", 403),
        ("192.168.1.20:8080", 403),
    ] {
        let r = test::call_service(
            &app,
            test::TestRequest::get()
                .uri("/api/volumes")
                .insert_header(("host", host))
                .to_request(),
        )
        .await;
        assert_eq!(r.status().as_u16(), code, "{host}");
        if code == 403 {
            assert!(error_of(r).await.contains("loopback"), "{host}");
        }
    }
}

#[actix_web::test]
async fn writes_from_another_origin_are_refused() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let open = |headers: &[(&str, &str)]| {
        let mut r = test::TestRequest::post()
            .uri("/api/sessions")
            .insert_header(("host", "127.0.0.1:8080"))
            .set_json(json!({"volume": "ph.zarr"}));
        for h in headers {
            r = r.insert_header(*h);
        }
        r.to_request()
    };
    for h in [
        vec![("origin", "http://evil.example")],
        vec![("origin", "http://127.0.0.1:9999")],
        vec![("origin", "null")],
        vec![("sec-fetch-site", "cross-site")],
    ] {
        let r = test::call_service(&app, open(&h)).await;
        assert_eq!(r.status(), 403, "{h:?}");
        assert!(error_of(r).await.contains("another origin"), "{h:?}");
    }
    // The page itself, and clients that are not browsers, may write.
    for h in [
        vec![("origin", "http://127.0.0.1:8080")],
        vec![("sec-fetch-site", "same-origin")],
        vec![],
    ] {
        let r = test::call_service(&app, open(&h)).await;
        assert_eq!(r.status(), 201, "{h:?}");
    }
    // Reads from another origin are answered (a browser does not let that page read them).
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri("/api/volumes")
            .insert_header(("origin", "http://evil.example"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
}

#[actix_web::test]
async fn a_detached_header_cannot_read_outside_the_data_root() {
    let (d, cfg) = data();
    // A secret beside the data root, and a header in the data root naming it.
    std::fs::write(d.path().join("secret.raw"), vec![7u8; 64]).unwrap();
    let hdr = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: ../secret.raw\n";
    std::fs::write(cfg.data_root.join("evil.nhdr"), hdr).unwrap();
    let inside =
        "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: ok.raw\n";
    std::fs::write(cfg.data_root.join("ok.nhdr"), inside).unwrap();
    std::fs::write(cfg.data_root.join("ok.raw"), vec![7u8; 64]).unwrap();
    let app = app!(cfg);
    let open = |v: &str| {
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(json!({"volume": v}))
            .to_request()
    };
    let r = test::call_service(&app, open("evil.nhdr")).await;
    assert_eq!(r.status(), 403);
    assert!(error_of(r).await.contains("outside the data root"));
    let r = test::call_service(&app, open("ok.nhdr")).await;
    assert_eq!(r.status(), 201, "a data file beside its header is fine");
}

#[actix_web::test]
async fn the_session_limit_answers_503() {
    let (_d, mut cfg) = data();
    cfg.max_sessions = 2;
    let app = app!(cfg);
    let a = open_session(&app).await;
    let _b = open_session(&app).await;
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(json!({"volume": "ph.zarr"}))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
    assert!(error_of(r).await.contains("2 sessions are open"));
    let r = test::call_service(
        &app,
        test::TestRequest::delete()
            .uri(&format!("/api/sessions/{a}"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 204);
    open_session(&app).await;
}

async fn server_status<S>(app: &S) -> Value
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    test::call_and_read_body_json(
        app,
        test::TestRequest::get().uri("/api/server").to_request(),
    )
    .await
}

#[actix_web::test]
async fn the_feature_cache_is_bounded_across_sessions() {
    let (_d, mut cfg) = data();
    // About 4 feature bricks of the default set (16^3 voxels x 53 `filters+xyz` channels x 2
    // bytes = 424 KiB each); every session's features are many times that.
    let budget = 4 * 16 * 16 * 16 * 53 * 2 + (16 << 10);
    cfg.feature_cache_bytes = budget;
    let app = app!(cfg);
    let mut ids = Vec::new();
    for _ in 0..4 {
        let id = open_session(&app).await;
        let g = put_strokes(&app, &id, 0).await;
        let v = wait_done(&app, &id, g).await;
        assert_eq!(v["status"]["state"], "done", "{v}");
        let s = server_status(&app).await;
        let used = s["feature_cache"]["used"].as_u64().unwrap();
        assert!(used > 0, "{s}");
        assert!(used <= budget as u64, "one budget for all sessions: {s}");
        ids.push(id);
    }
    // Closing sessions drops their features.
    for id in &ids {
        let r = test::call_service(
            &app,
            test::TestRequest::delete()
                .uri(&format!("/api/sessions/{id}"))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 204);
    }
    let s = server_status(&app).await;
    assert_eq!(s["feature_cache"]["used"], 0, "{s}");
    assert_eq!(s["sessions"], 0, "{s}");
}

#[actix_web::test]
async fn what_sessions_hold_stays_within_the_servers_budgets() {
    let (_d, mut cfg) = data();
    // Render bricks: 2 MiB for every session's 3-D view together (each session's frames
    // read far more). Probabilities: room for two sessions' (48 x 48 x 42 voxels, 2 classes).
    let one = 48 * 48 * 42 * 2;
    cfg.render_cache_bytes = 2 << 20;
    cfg.probs_bytes = 2 * one + 1000;
    let app = app!(cfg);
    let check = |s: &Value| {
        let m = &s["memory"];
        for part in ["feature_cache", "render_cache", "probabilities"] {
            assert!(
                m[part]["used"].as_u64().unwrap() <= m[part]["budget"].as_u64().unwrap(),
                "{part}: {m}"
            );
        }
        assert!(
            m["used"].as_u64().unwrap() <= m["budget"].as_u64().unwrap(),
            "{m}"
        );
    };
    let mut ids = Vec::new();
    for k in 0..3 {
        let id = open_session(&app).await;
        let g = put_strokes(&app, &id, k).await;
        let v = wait_state(&app, &id, g, &["done", "failed"]).await;
        if k < 2 {
            assert_eq!(v["status"]["state"], "done", "{v}");
        } else {
            // The third would pass the probability budget: refused, naming it.
            assert_eq!(v["status"]["state"], "failed", "{v}");
            let m = v["status"]["message"].as_str().unwrap();
            assert!(
                m.contains("--probs-mib") && m.contains("close a session"),
                "{m}"
            );
        }
        ids.push(id);
    }
    let s = server_status(&app).await;
    assert_eq!(s["memory"]["probabilities"]["used"], 2 * one, "{s}");
    check(&s);
    // Every session renders, sharing the one render budget.
    for (k, id) in ids.iter().enumerate() {
        for az in [0, 90] {
            let r = test::call_service(
                &app,
                test::TestRequest::get()
                    .uri(&format!("/api/sessions/{id}/render?size=96&az={az}"))
                    .to_request(),
            )
            .await;
            assert_eq!(r.status(), 200, "session {k}");
        }
        let s = server_status(&app).await;
        assert!(
            s["memory"]["render_cache"]["used"].as_u64().unwrap() > 0,
            "{s}"
        );
        check(&s);
    }
    // Closing the first gives its share back: the third classifies now.
    let close = |id: &str| {
        test::TestRequest::delete()
            .uri(&format!("/api/sessions/{id}"))
            .to_request()
    };
    assert_eq!(test::call_service(&app, close(&ids[0])).await.status(), 204);
    let g = put_strokes(&app, &ids[2], 1).await;
    let v = wait_state(&app, &ids[2], g, &["done", "failed"]).await;
    assert_eq!(v["status"]["state"], "done", "{v}");
    check(&server_status(&app).await);
    for id in &ids[1..] {
        assert_eq!(test::call_service(&app, close(id)).await.status(), 204);
    }
    let s = server_status(&app).await;
    assert_eq!(s["memory"]["used"], 0, "everything given back: {s}");
}

#[actix_web::test]
async fn a_store_model_is_loaded_once_for_all_its_sessions() {
    use neuvolex_features::InrModel;
    use std::sync::Arc;
    let (_d, cfg) = data();
    let store = neuvolex_bricks::BrickStore::open(cfg.data_root.join("ph.zarr")).unwrap();
    let m = neuvolex_server::memory::Memory::new(1 << 20, 1 << 20, 1 << 20);
    assert!(m.store_model(&store).is_none(), "no model file yet");
    let inr = neuvolex_features::InrConfig {
        log2_table: 10,
        ..Default::default()
    };
    let save = |seed| {
        let model = InrModel::new(&inr, store.info().dims, seed);
        let path = neuvolex_features::train::model_path(&store);
        neuvolex_features::checkpoint::save(path, &model, None).unwrap();
    };
    save(1);
    let (a, b) = (
        m.store_model(&store).unwrap(),
        m.store_model(&store).unwrap(),
    );
    assert!(Arc::ptr_eq(&a, &b), "two sessions share one model");
    assert_eq!(m.store_models().0, 1);
    // A rewritten file (another modification time) is loaded again.
    std::thread::sleep(Duration::from_millis(20));
    save(2);
    let c = m.store_model(&store).unwrap();
    assert!(!Arc::ptr_eq(&a, &c));
    drop((a, b, c));
    assert_eq!(
        m.store_models(),
        (0, 0),
        "nothing held once the sessions are gone"
    );
}

#[actix_web::test]
async fn slow_requests_time_out_with_503() {
    let (_d, mut cfg) = data();
    cfg.request_timeout = Duration::from_millis(5);
    let st = neuvolex_server::AppState::new(cfg);
    let app = test::init_service(
        actix_web::App::new()
            .app_data(st.clone())
            .configure(neuvolex_server::configure),
    )
    .await;
    let id = st.open("ph.zarr").await.unwrap().id.clone();
    // A 2048x2048 frame takes far longer than 5 ms. The answer is the middleware's error,
    // which the server turns into the response (the test harness hands it over as is).
    let e = test::try_call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/render?size=2048"))
            .to_request(),
    )
    .await
    .expect_err("timed out");
    let r = e.error_response();
    assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
    let body = actix_web::body::to_bytes(r.into_body()).await.unwrap();
    let v: Value = serde_json::from_slice(&body).unwrap();
    let e = v["error"].as_str().unwrap().to_string();
    assert!(e.contains("request timeout"), "{e}");
    assert!(
        e.contains("/render") && e.contains("the render was cancelled"),
        "{e}"
    );
    // And it was: the renderer stops the frame at its next batch of bricks instead of
    // finishing it for nobody.
    let t = Instant::now();
    loop {
        let s = server_status(&app).await;
        if s["renders_in_flight"] == 0 {
            assert_eq!(s["renders_cancelled"], 1, "{s}");
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "{s}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Event streams are not cut by the timeout.
    let mut sse = Sse::open(&app, "").await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    st.actors.hub.publish(None, "ping", json!({"n": 1}));
    sse.next("ping", |v| v["data"]["n"] == 1).await;
}

#[actix_web::test]
async fn concurrent_trainings_are_capped() {
    let (_d, mut cfg) = data();
    cfg.max_trainings = 1;
    let app = app!(cfg);
    let a = open_session(&app).await;
    let b = open_session(&app).await;
    let train = |id: &str, action: &str| {
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/train"))
            .set_json(json!({"action": action, "epochs": 1000}))
            .to_request()
    };
    assert_eq!(
        test::call_service(&app, train(&a, "start")).await.status(),
        202
    );
    let r = test::call_service(&app, train(&b, "start")).await;
    assert_eq!(r.status(), StatusCode::SERVICE_UNAVAILABLE);
    assert!(error_of(r).await.contains("1 training(s) running"));
    let r = test::call_service(&app, train(&a, "start")).await;
    assert_eq!(r.status(), StatusCode::CONFLICT, "already training");
    assert_eq!(server_status(&app).await["trainings"], 1);
    assert_eq!(
        test::call_service(&app, train(&a, "stop")).await.status(),
        202
    );
    let t = Instant::now();
    while server_status(&app).await["trainings"] != 0 {
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "the training never stopped"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        test::call_service(&app, train(&b, "start")).await.status(),
        202
    );
    assert_eq!(
        test::call_service(&app, train(&b, "stop")).await.status(),
        202
    );
}

#[actix_web::test]
async fn oversized_bodies_get_413() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let big = format!("[{}]", vec!["{\"class\":1}"; 500_000].join(","));
    for (m, uri) in [("PUT", "strokes"), ("POST", "strokes"), ("PUT", "state")] {
        let req = if m == "PUT" {
            test::TestRequest::put()
        } else {
            test::TestRequest::post()
        };
        let r = test::call_service(
            &app,
            req.uri(&format!("/api/sessions/{id}/{uri}"))
                .insert_header(("content-type", "application/json"))
                .set_payload(big.clone())
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), StatusCode::PAYLOAD_TOO_LARGE, "{m} {uri}");
        assert!(error_of(r).await.contains("limit"), "{m} {uri}");
    }
}

#[actix_web::test]
async fn session_files_save_load_and_restore() {
    let (_d, cfg) = data();
    let work = cfg.work_dir.clone();
    let app = app!(cfg);
    let id = open_session(&app).await;
    put_strokes(&app, &id, 1).await;
    let tf = json!({"intensity": {"opacity": [[0, 0], [1000, 0.5]]}});
    let r = test::call_service(
        &app,
        test::TestRequest::put()
            .uri(&format!("/api/sessions/{id}/tf"))
            .set_json(&tf)
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let saved: Value = test::call_and_read_body_json(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/state"))
            .to_request(),
    )
    .await;
    assert_eq!(saved["format"], "neuvolex-session");
    assert_eq!(saved["volume"], "ph.zarr");
    assert_eq!(saved["strokes"].as_array().unwrap().len(), 3);
    assert_eq!(saved["tf"], tf);
    // Loading it into a fresh session brings everything back.
    let id2 = open_session(&app).await;
    let put = |id: &str, body: String| {
        test::TestRequest::put()
            .uri(&format!("/api/sessions/{id}/state"))
            .insert_header(("content-type", "application/json"))
            .set_payload(body)
            .to_request()
    };
    let r = test::call_service(&app, put(&id2, saved.to_string())).await;
    assert_eq!(r.status(), 200);
    let v: Value = test::read_body_json(r).await;
    assert_eq!(v["strokes"], 3);
    assert_eq!(v["tf"], tf);
    // A bad file changes nothing and names the part.
    for (ptr, val, code, needle) in [
        ("/strokes/0/slice", json!(999), 400, "strokes"),
        ("/classes/0/id", json!(0), 400, "classes[0]"),
        ("/tf/intensity/opacity/0/1", json!(7), 400, "tf:"),
        (
            "/volume",
            json!("other.nii.gz"),
            409,
            "open that volume first",
        ),
    ] {
        let mut bad = saved.clone();
        *bad.pointer_mut(ptr).unwrap() = val;
        let r = test::call_service(&app, put(&id2, bad.to_string())).await;
        assert_eq!(r.status().as_u16(), code, "{ptr}");
        let e = error_of(r).await;
        assert!(e.contains(needle), "{ptr}: {e}");
    }
    let r = test::call_service(&app, put(&id2, "{not json".into())).await;
    assert_eq!(r.status(), 400);
    let again: Value = test::call_and_read_body_json(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id2}/state"))
            .to_request(),
    )
    .await;
    // The same but for the session's own id and its label rounds (which follow its own
    // classification).
    let strip = |v: &Value| {
        let mut v = v.clone();
        for k in ["id", "rounds"] {
            v.as_object_mut().unwrap().remove(k);
        }
        v
    };
    assert_eq!(strip(&again), strip(&saved), "nothing changed");
    // Closing saves the state; the next open with restore brings it back.
    let r = test::call_service(
        &app,
        test::TestRequest::delete()
            .uri(&format!("/api/sessions/{id}"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 204);
    assert!(neuvolex_server::http::session_path(&work, &id).exists());
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(json!({"volume": "ph.zarr", "restore": true}))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200, "the saved session is resumed");
    let v: Value = test::read_body_json(r).await;
    assert_eq!(v["id"], json!(id));
    assert_eq!(v["strokes"], 3, "{v}");
    assert_eq!(v["tf"], tf);
}

#[actix_web::test]
async fn concurrent_appends_lose_no_stroke() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let id = open_session(&app).await;
    let one = |k: usize| {
        json!([{"class": if k.is_multiple_of(2) { 1 } else { 255 }, "axis": "z", "slice": k % 40,
                "points": [[2 + k % 40, 3], [2 + k % 40, 20]], "radius": 0.5}])
    };
    let work = (0..40).map(|k| {
        let app = &app;
        let id = id.clone();
        async move {
            loop {
                let r = test::call_service(
                    app,
                    test::TestRequest::post()
                        .uri(&format!("/api/sessions/{id}/strokes"))
                        .set_json(one(k))
                        .to_request(),
                )
                .await;
                match r.status().as_u16() {
                    202 => return,
                    503 => tokio::time::sleep(Duration::from_millis(20)).await,
                    s => panic!("append {k}: {s}"),
                }
            }
        }
    });
    futures_util::future::join_all(work).await;
    let held: Vec<Value> = test::call_and_read_body_json(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/strokes"))
            .to_request(),
    )
    .await;
    assert_eq!(held.len(), 40);
    // The exported scribble volume is exactly the union of the strokes.
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/export/scribbles.nii.gz"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let bytes = test::read_body(r).await;
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("s.nii.gz");
    std::fs::write(&p, &bytes).unwrap();
    let mut src = neuvolex_bricks::open_volume(&p, None).unwrap();
    let got = neuvolex_formats::MemVolume::read_all(src.as_mut()).unwrap();
    let strokes: Vec<neuvolex_classify::scribble::Stroke> =
        serde_json::from_value(Value::Array(held)).unwrap();
    let want = neuvolex_classify::scribble::rasterise(&strokes, got.meta.dims).unwrap();
    let painted: Vec<(u64, u32)> = got
        .bytes
        .iter()
        .enumerate()
        .filter(|(_, &v)| v != 0)
        .map(|(i, &v)| (i as u64, v as u32))
        .collect();
    assert_eq!(painted, want.voxels);
    assert_eq!(painted.len(), 40 * 18, "every stroke painted its 18 voxels");
}
