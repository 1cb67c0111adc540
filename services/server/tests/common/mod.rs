//! Helpers shared by the server's API tests: a data root with a phantom store, the in-process
//! app, strokes on the phantom, and a Server-Sent Events reader.
#![allow(dead_code, unused_macros)]

use actix_web::test;
use neuvolex_bricks::synth::{ClassInfo, PhantomParams};
use neuvolex_classify::scribble::Stroke;
use neuvolex_ingest::IngestOptions;
use neuvolex_server::ServerConfig;
use serde_json::{json, Value};
use std::time::{Duration, Instant};

/// A data root holding a small labelled phantom store, and a work folder.
pub fn data() -> (tempfile::TempDir, ServerConfig) {
    let d = tempfile::tempdir().unwrap();
    let root = d.path().join("data");
    let work = d.path().join("work");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::create_dir_all(&work).unwrap();
    neuvolex_ingest::phantom_store(
        &root.join("ph.zarr"),
        PhantomParams::with_size(48, 0),
        &IngestOptions {
            brick: 16,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    let mut cfg = ServerConfig::new(root.canonicalize().unwrap(), work.canonicalize().unwrap());
    cfg.fault_injection = true;
    (d, cfg)
}

macro_rules! app {
    ($cfg:expr) => {
        test::init_service(
            actix_web::App::new()
                .app_data(neuvolex_server::AppState::new($cfg.clone()))
                .configure(neuvolex_server::configure),
        )
        .await
    };
}

/// Strokes on the phantom's middle axial slice: spine (class 1) and air around it (background).
pub fn strokes(n: usize) -> Value {
    json!([
        {"class": 1, "axis": "z", "slice": 21, "points": [[23, 30 + n % 3], [25, 31]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[2, 2], [12, 2], [12, 8]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[40, 44], [46, 44]], "radius": 1.5}
    ])
}

pub async fn wait_done<S>(app: &S, id: &str, generation: u64) -> Value
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    wait_state(app, id, generation, &["done", "idle"]).await
}

/// Waits until session `id`'s classification of `generation` is in one of `states`.
pub async fn wait_state<S>(app: &S, id: &str, generation: u64, states: &[&str]) -> Value
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
        if st["generation"] == json!(generation) && states.iter().any(|s| st["state"] == *s) {
            return v;
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "classification never reached {states:?}: {v}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A Server-Sent Events client over the in-process service.
pub struct Sse {
    body: actix_web::body::BoxBody,
    buf: String,
}

impl Sse {
    pub async fn open<S>(app: &S, query: &str) -> Sse
    where
        S: actix_web::dev::Service<
            actix_http::Request,
            Response = actix_web::dev::ServiceResponse,
            Error = actix_web::Error,
        >,
    {
        let r = test::call_service(
            app,
            test::TestRequest::get()
                .uri(&format!("/api/events{query}"))
                .to_request(),
        )
        .await;
        assert_eq!(r.status(), 200);
        Sse {
            body: r.into_body(),
            buf: String::new(),
        }
    }

    /// The next event of `kind` whose JSON satisfies `want`.
    pub async fn next(&mut self, kind: &str, want: impl Fn(&Value) -> bool) -> Value {
        use actix_web::body::MessageBody;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(180);
        loop {
            while let Some(i) = self.buf.find("\n\n") {
                let ev: String = self.buf.drain(..i + 2).collect();
                let Some(rest) = ev.strip_prefix(&format!("event: {kind}\ndata: ")) else {
                    continue;
                };
                let v: Value = serde_json::from_str(rest.trim()).unwrap();
                if want(&v) {
                    return v;
                }
            }
            let chunk = tokio::time::timeout_at(
                deadline,
                futures_util::future::poll_fn(|cx| {
                    std::pin::Pin::new(&mut self.body).poll_next(cx)
                }),
            )
            .await
            .unwrap_or_else(|_| panic!("no '{kind}' event within 180 s"));
            match chunk {
                Some(Ok(b)) => self.buf.push_str(std::str::from_utf8(&b).unwrap()),
                _ => panic!("the event stream ended"),
            }
        }
    }
}

/// Opens a session on the phantom store `ph.zarr`; its id.
pub async fn open_session<S>(app: &S) -> String
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let s = open_session_on(app, "ph.zarr").await;
    s["id"].as_str().unwrap().to_string()
}

/// Opens a session on `volume` (relative to the data root); the whole reply, which must carry
/// an id (the panic shows the reply otherwise).
pub async fn open_session_on<S>(app: &S, volume: &str) -> Value
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let req = test::TestRequest::post()
        .uri("/api/sessions")
        .set_json(json!({ "volume": volume }))
        .to_request();
    let s: Value = test::call_and_read_body_json(app, req).await;
    assert!(s["id"].is_string(), "opening {volume}: {s}");
    s
}

pub async fn put_strokes<S>(app: &S, id: &str, n: usize) -> u64
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let req = test::TestRequest::put()
        .uri(&format!("/api/sessions/{id}/strokes"))
        .set_json(strokes(n))
        .to_request();
    let r: Value = test::call_and_read_body_json(app, req).await;
    r["generation"].as_u64().unwrap()
}

/// A case where the stability rule acts: a 64^3 phantom store (16^3 bricks) at `path`, S1
/// scribbles from its truth (seed 0), the S2 strokes (seed 7) of one slice far from them, one
/// more S2 stroke on another far slice, and the phantom's classes.
pub struct RuleCase {
    pub store: neuvolex_bricks::BrickStore,
    pub first: Vec<Stroke>,
    pub more: Vec<Stroke>,
    pub extra: Stroke,
    pub classes: Vec<ClassInfo>,
}

pub fn rule_case(path: &std::path::Path) -> RuleCase {
    use neuvolex_classify::scribble::{simulate, Level, SimConfig};
    let store = neuvolex_ingest::phantom_store(
        path,
        PhantomParams::with_size(64, 0),
        &IngestOptions {
            brick: 16,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    let dims = store.info().dims;
    let truth = store.read_labels_box("ground_truth", [0; 3], dims).unwrap();
    let tf: Vec<f32> = truth.iter().map(|&t| t as f32).collect();
    let sim = |level, seed| {
        let mut src = neuvolex_formats::MemVolume::from_f32(dims, &tf);
        simulate(
            &mut src,
            &SimConfig {
                level,
                seed,
                background: 255,
                ..Default::default()
            },
        )
        .unwrap()
        .0
    };
    let first = sim(Level::S1, 0);
    // Strokes of another simulation on slices far from the first's.
    let far: Vec<Stroke> = sim(Level::S2, 7)
        .into_iter()
        .filter(|s| {
            first
                .iter()
                .all(|f| f.axis != s.axis || f.slice.abs_diff(s.slice) > 4)
        })
        .collect();
    let slice = (far[0].axis, far[0].slice);
    let more: Vec<Stroke> = far
        .iter()
        .filter(|s| (s.axis, s.slice) == slice)
        .cloned()
        .collect();
    assert!(!more.is_empty());
    let extra = far
        .iter()
        .find(|s| (s.axis, s.slice) != slice)
        .unwrap_or(&first[0])
        .clone();
    let mut ids: Vec<u32> = truth.iter().copied().filter(|&t| t > 0).collect();
    ids.sort_unstable();
    ids.dedup();
    let classes = ids
        .iter()
        .map(|&id| ClassInfo {
            id,
            name: format!("c{id}"),
            color: neuvolex_bricks::synth::palette(id),
        })
        .collect();
    RuleCase {
        store,
        first,
        more,
        extra,
        classes,
    }
}

/// One request; its status and its JSON body (`null` when the body is not JSON).
pub async fn call<S>(app: &S, req: actix_http::Request) -> (u16, Value)
where
    S: actix_web::dev::Service<
        actix_http::Request,
        Response = actix_web::dev::ServiceResponse,
        Error = actix_web::Error,
    >,
{
    let r = test::call_service(app, req).await;
    let code = r.status().as_u16();
    let body = test::read_body(r).await;
    (code, serde_json::from_slice(&body).unwrap_or(Value::Null))
}
