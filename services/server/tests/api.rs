//! The HTTP API end to end (in process): sessions, slices, strokes, streaming classification,
//! rendering, export, hostile and malformed requests, and 20 concurrent clients.

use actix_web::{test, App};
use neuvolex_bricks::synth::{phantom_classes, Phantom, PhantomChannel, PhantomParams};
use neuvolex_bricks::{ingest, BrickStore, IngestOptions};
use neuvolex_server::{configure, AppState, ServerConfig};
use serde_json::{json, Value};
use std::time::{Duration, Instant};

/// A data root holding a small labelled phantom store, and a work folder.
fn data() -> (tempfile::TempDir, ServerConfig) {
    let d = tempfile::tempdir().unwrap();
    let root = d.path().join("data");
    let work = d.path().join("work");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::create_dir_all(&work).unwrap();
    let params = PhantomParams::with_size(48, 0);
    let p = root.join("ph.zarr");
    ingest(
        &mut Phantom::new(params, PhantomChannel::Image),
        &p,
        &IngestOptions {
            brick: 16,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    let mut s = BrickStore::open(&p).unwrap();
    s.add_labels(
        "ground_truth",
        &mut Phantom::new(params, PhantomChannel::Labels),
        &phantom_classes(),
        &mut |_| {},
    )
    .unwrap();
    let cfg = ServerConfig {
        data_root: root.canonicalize().unwrap(),
        work_dir: work.canonicalize().unwrap(),
    };
    (d, cfg)
}

macro_rules! app {
    ($cfg:expr) => {
        test::init_service(
            App::new()
                .app_data(AppState::new($cfg.clone()))
                .configure(configure),
        )
        .await
    };
}

/// Strokes on the phantom's middle axial slice: spine (class 1) and air around it (background).
fn strokes(n: usize) -> Value {
    json!([
        {"class": 1, "axis": "z", "slice": 21, "points": [[23, 30 + n % 3], [25, 31]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[2, 2], [12, 2], [12, 8]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[40, 44], [46, 44]], "radius": 1.5}
    ])
}

async fn wait_done<S>(app: &S, id: &str, generation: u64) -> Value
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let t = Instant::now();
    loop {
        let req = test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}"))
            .to_request();
        let v: Value = test::call_and_read_body_json(app, req).await;
        let st = &v["status"];
        if st["generation"] == json!(generation) && (st["state"] == "done" || st["state"] == "idle")
        {
            return v;
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "classification never finished: {v}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[actix_web::test]
async fn scribble_classify_render_export() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let req = test::TestRequest::get().uri("/api/volumes").to_request();
    let v: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(v, json!(["ph.zarr"]));
    let req = test::TestRequest::post()
        .uri("/api/sessions")
        .set_json(json!({"volume": "ph.zarr"}))
        .to_request();
    let s: Value = test::call_and_read_body_json(&app, req).await;
    let id = s["id"].as_str().unwrap().to_string();
    assert_eq!(s["dims"], json!([48, 48, 42]));
    assert!(
        s["classes"].as_array().unwrap().len() >= 4,
        "the store's class table: {s}"
    );
    // A slice with window/level.
    let req = test::TestRequest::get()
        .uri(&format!(
            "/api/sessions/{id}/slice/z/21?window=400&level=40"
        ))
        .to_request();
    let r = test::call_service(&app, req).await;
    assert_eq!(r.status(), 200);
    assert_eq!(&test::read_body(r).await[1..4], b"PNG");
    // Strokes start classification; it streams brick by brick and finishes.
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .set_json(strokes(0))
        .to_request();
    let r: Value = test::call_and_read_body_json(&app, req).await;
    assert_eq!(r["generation"], 1);
    let v = wait_done(&app, &id, 1).await;
    assert_eq!(v["status"]["state"], "done", "{v}");
    assert_eq!(v["status"]["done"], v["status"]["total"]);
    // The spine is found: the class-1 overlay covers the scribbled pixel's neighbourhood.
    let req = test::TestRequest::get()
        .uri(&format!("/api/sessions/{id}/fractions"))
        .to_request();
    let f: Value = test::call_and_read_body_json(&app, req).await;
    let sum: f64 = f["classes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["fraction"].as_f64().unwrap())
        .sum();
    assert!((sum - 1.0).abs() < 1e-9, "{f}");
    let spine = f["classes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["id"] == 1)
        .unwrap()["fraction"]
        .as_f64()
        .unwrap();
    assert!(spine > 0.001 && spine < 0.5, "{f}");
    for uri in [
        format!("/api/sessions/{id}/overlay/z/21?kind=labels"),
        format!("/api/sessions/{id}/overlay/y/20?kind=uncertainty"),
        format!("/api/sessions/{id}/render?size=64&az=10&el=5&t=123"),
        format!("/api/sessions/{id}/render?size=64&mode=prob-intensity&tf=grey"),
        format!("/api/sessions/{id}/overlay/x/20?kind=labels&t=99"),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status(), 200, "{uri}");
        assert_eq!(&test::read_body(r).await[1..4], b"PNG", "{uri}");
    }
    // A second render of the same frame after new strokes updates incrementally and still works.
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .set_json(strokes(1))
        .to_request();
    let _: Value = test::call_and_read_body_json(&app, req).await;
    wait_done(&app, &id, 2).await;
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/render?size=64&az=10&el=5"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    // Viewpoints of the session's volume.
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/viewpoints"))
        .set_json(json!({"k": 12, "views": 300}))
        .to_request();
    let v: Value = test::call_and_read_body_json(&app, req).await;
    assert!(!v["views"].as_array().unwrap().is_empty(), "{v}");
    let req = test::TestRequest::post()
        .uri(&format!("/api/sessions/{id}/viewpoints"))
        .set_json(json!({"k": 0}))
        .to_request();
    assert_eq!(test::call_service(&app, req).await.status(), 400);
    // Export as NIfTI.
    let r = test::call_service(
        &app,
        test::TestRequest::get()
            .uri(&format!("/api/sessions/{id}/export/labels.nii.gz"))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 200);
    let body = test::read_body(r).await;
    assert_eq!(&body[..2], &[0x1f, 0x8b], "gzip");
}

#[actix_web::test]
async fn hostile_and_malformed_requests_get_clear_4xx() {
    let (d, cfg) = data();
    std::fs::write(d.path().join("secret.nii"), b"not yours").unwrap();
    let app = app!(cfg);
    let open = |v: Value| {
        test::TestRequest::post()
            .uri("/api/sessions")
            .set_json(v)
            .to_request()
    };
    for (body, code, needle) in [
        (json!({"volume": "../secret.nii"}), 403, "without '..'"),
        (json!({"volume": "/etc/passwd"}), 403, "relative"),
        (json!({"volume": "nope.nii"}), 404, "no volume"),
        (json!({"volume": ""}), 400, "empty"),
        (json!({"path": "ph.zarr"}), 400, "malformed"),
        (json!({"volume": "."}), 400, "folder"),
    ] {
        let r = test::call_service(&app, open(body.clone())).await;
        assert_eq!(r.status().as_u16(), code, "{body}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{body}: {v}");
    }
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(d.path().join("secret.nii"), cfg.data_root.join("link.nii"))
            .unwrap();
        let r = test::call_service(&app, open(json!({"volume": "link.nii"}))).await;
        assert_eq!(r.status(), 403, "a link out of the data root");
    }
    // Bad JSON, a huge body, unknown ids and routes.
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .insert_header(("content-type", "application/json"))
            .set_payload("{not json")
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 400);
    let huge = format!("{{\"volume\": \"{}\"}}", "a".repeat(5 << 20));
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri("/api/sessions")
            .insert_header(("content-type", "application/json"))
            .set_payload(huge)
            .to_request(),
    )
    .await;
    assert!(r.status().is_client_error(), "huge body: {}", r.status());
    for uri in [
        "/api/sessions/s999",
        "/api/sessions/s999/render",
        "/api/nothing",
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(uri).to_request()).await;
        assert_eq!(r.status(), 404, "{uri}");
    }
    // Bad values on a real session.
    let r = test::call_service(&app, open(json!({"volume": "ph.zarr"}))).await;
    let s: Value = test::read_body_json(r).await;
    let id = s["id"].as_str().unwrap();
    for (uri, needle) in [
        (format!("/api/sessions/{id}/slice/w/1"), "axis"),
        (format!("/api/sessions/{id}/slice/z/999"), "outside"),
        (format!("/api/sessions/{id}/slice/z/-1"), "malformed"),
        (
            format!("/api/sessions/{id}/overlay/z/1?kind=rainbow"),
            "kind",
        ),
        (format!("/api/sessions/{id}/render?size=0"), "size"),
        (format!("/api/sessions/{id}/render?size=100000"), "size"),
        (format!("/api/sessions/{id}/render?el=200"), "elevation"),
        (format!("/api/sessions/{id}/render?mode=x"), "mode"),
        (format!("/api/sessions/{id}/render?tf=nope"), "preset"),
        (format!("/api/sessions/{id}/render?bogus=1"), "malformed"),
    ] {
        let r = test::call_service(&app, test::TestRequest::get().uri(&uri).to_request()).await;
        assert_eq!(r.status(), 400, "{uri}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{uri}: {v}");
    }
    for (body, needle) in [
        (
            json!([{"class": 1, "axis": "z", "slice": 99, "points": [[1, 1]], "radius": 1}]),
            "slice",
        ),
        (
            json!([{"class": 77, "axis": "z", "slice": 1, "points": [[1, 1]], "radius": 1}]),
            "class 77",
        ),
        (
            json!([{"class": 1, "axis": "q", "slice": 1, "points": [[1, 1]], "radius": 1}]),
            "malformed",
        ),
        (json!({"strokes": []}), "malformed"),
    ] {
        let r = test::call_service(
            &app,
            test::TestRequest::put()
                .uri(&format!("/api/sessions/{id}/strokes"))
                .set_json(&body)
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 400, "{body}");
        let v: Value = test::read_body_json(r).await;
        assert!(v["error"].as_str().unwrap().contains(needle), "{body}: {v}");
    }
    let r = test::call_service(
        &app,
        test::TestRequest::post()
            .uri(&format!("/api/sessions/{id}/train"))
            .set_json(json!({"action": "stop"}))
            .to_request(),
    )
    .await;
    assert_eq!(r.status(), 409, "nothing to stop");
    let r = test::call_service(
        &app,
        test::TestRequest::put().uri(&format!("/api/sessions/{id}/classes")).set_json(json!([{"id": 1, "name": "a", "color": [1, 2, 3]}, {"id": 1, "name": "b", "color": [1, 2, 3]}])).to_request(),
    )
    .await;
    assert_eq!(r.status(), 400, "duplicate class ids");
}

fn rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .map(|l| l.to_string())
        })
        .and_then(|l| {
            l.split_whitespace()
                .nth(1)
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

#[actix_web::test]
async fn twenty_concurrent_clients_lose_no_scribbles() {
    let (_d, cfg) = data();
    let app = app!(cfg);
    let before = rss_mib();
    let mut ids = Vec::new();
    for _ in 0..20 {
        let r = test::call_service(
            &app,
            test::TestRequest::post()
                .uri("/api/sessions")
                .set_json(json!({"volume": "ph.zarr"}))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 201);
        let v: Value = test::read_body_json(r).await;
        ids.push(v["id"].as_str().unwrap().to_string());
    }
    // Every client sends its strokes three times (each send cancels the stale classification)
    // and reads slices, all at once.
    let work = ids.iter().enumerate().map(|(n, id)| {
        let app = &app;
        async move {
            for k in 0..3 {
                let req = test::TestRequest::put()
                    .uri(&format!("/api/sessions/{id}/strokes"))
                    .set_json(strokes(n + k))
                    .to_request();
                let r = test::call_service(app, req).await;
                assert!(r.status() == 202 || r.status() == 503, "{}", r.status());
                if r.status() == 503 {
                    // Backpressure: the mailbox was full; the client retries.
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    let req = test::TestRequest::put()
                        .uri(&format!("/api/sessions/{id}/strokes"))
                        .set_json(strokes(n + k))
                        .to_request();
                    assert_eq!(test::call_service(app, req).await.status(), 202);
                }
                let req = test::TestRequest::get()
                    .uri(&format!("/api/sessions/{id}/slice/x/{}", 10 + k))
                    .to_request();
                assert_eq!(test::call_service(app, req).await.status(), 200);
            }
        }
    });
    futures_util::future::join_all(work).await;
    for id in &ids {
        let v = wait_done(&app, id, 3).await;
        assert_eq!(v["strokes"], 3, "no scribble lost: {v}");
        assert_eq!(v["generation"], 3);
    }
    let grown = rss_mib() - before;
    eprintln!("RSS grew {grown:.0} MiB for 20 sessions");
    assert!(grown < 1500.0, "memory stays bounded: +{grown} MiB");
}
