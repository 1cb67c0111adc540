//! `neuvolex serve` as a real process: SIGTERM and Ctrl-C (SIGINT) stop it within 2 s with
//! event streams open and a training running; the training's checkpoint and the session's
//! state on disk are complete afterwards. On a non-loopback address a token is required: the
//! generated one printed in the URL, `--token`, or `NEUVOLEX_TOKEN`. With `--cluster` the
//! session's classification runs on `neuvolex worker` processes.

mod support;

use serde_json::{json, Value};
use std::process::Command;
use std::time::{Duration, Instant};
use support::{
    data_root, event_stream, http, numbers_as_f64, phantom_strokes, wait_end, wait_event, Server,
};

/// A session on the phantom with its strokes (which start a classification); its id.
fn session_with_strokes(a: &str) -> String {
    let (st, body) = http(
        a,
        "POST",
        "/api/sessions",
        &[],
        Some(&json!({"volume": "phantom.zarr"})),
    );
    assert_eq!(st, 201, "{body}");
    let id = serde_json::from_str::<Value>(&body).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (st, _) = http(
        a,
        "PUT",
        &format!("/api/sessions/{id}/strokes"),
        &[],
        Some(&phantom_strokes()),
    );
    assert_eq!(st, 202);
    id
}

#[test]
fn sigterm_stops_a_training_server_within_two_seconds_and_keeps_complete_state() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let mut srv = Server::start(d.path(), &data, &[], &[]);
    let a = &srv.addr.clone();
    let streams: Vec<_> = (0..3).map(|_| event_stream(a)).collect();
    let id = session_with_strokes(a);
    let (st, body) = http(
        a,
        "POST",
        &format!("/api/sessions/{id}/train"),
        &[],
        Some(&json!({"action": "start", "epochs": 1000})),
    );
    assert_eq!(st, 202, "{body}");
    // Mid-training: a snapshot (and so a checkpoint) has been written.
    wait_event(&streams[0], "training", "snapshot");
    let t0 = Instant::now();
    srv.signal("-TERM");
    let (took, clean) = srv.wait_exit(Duration::from_secs(30));
    eprintln!("SIGTERM with 3 event streams and a training: stopped in {took:?}");
    let log = || std::fs::read_to_string(d.path().join("server-0.log")).unwrap_or_default();
    assert!(clean, "exit status 0: {}", log());
    assert!(
        took < Duration::from_secs(2),
        "stopped in {took:?}: {}",
        log()
    );
    for s in &streams {
        assert!(wait_end(
            s,
            Duration::from_secs(2).saturating_sub(t0.elapsed()) + Duration::from_millis(100)
        ));
    }
    // The checkpoint is complete: it loads (CRC and sizes checked) and resumes.
    let ckpt = data.join("phantom.zarr/neuvolex/inr/checkpoint.nvx");
    let l = neuvolex_features::checkpoint::load(&ckpt).unwrap();
    assert_eq!(l.model.dims, [48, 48, 42]);
    assert!(l.header.state.unwrap().step > 0);
    // The session was saved, whole.
    let saved = d.path().join("work/sessions/phantom.zarr.json");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&saved).unwrap()).unwrap();
    assert_eq!(
        numbers_as_f64(&v["strokes"]),
        numbers_as_f64(&phantom_strokes())
    );
    assert_eq!(v["volume"], "phantom.zarr");
    let partial: Vec<_> = std::fs::read_dir(saved.parent().unwrap())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains("partial"))
        .collect();
    assert!(partial.is_empty(), "no half-written session file");
    // A new server restores it and resumes the training from the checkpoint.
    let srv2 = Server::start(d.path(), &data, &[], &[]);
    let a = &srv2.addr.clone();
    let (st, body) = http(
        a,
        "POST",
        "/api/sessions",
        &[],
        Some(&json!({"volume": "phantom.zarr", "restore": true})),
    );
    assert_eq!(st, 201, "{body}");
    let v: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["strokes"], 3, "{v}");
    let id = v["id"].as_str().unwrap();
    let ev = event_stream(a);
    let (st, _) = http(
        a,
        "POST",
        &format!("/api/sessions/{id}/train"),
        &[],
        Some(&json!({"action": "resume", "epochs": 1000})),
    );
    assert_eq!(st, 202);
    wait_event(&ev, "training", "running");
    srv2.signal("-INT");
}

#[test]
fn ctrl_c_stops_an_idle_server_with_open_streams() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let mut srv = Server::start(d.path(), &data, &[], &[]);
    let streams: Vec<_> = (0..4).map(|_| event_stream(&srv.addr)).collect();
    let (st, _) = http(&srv.addr, "GET", "/api/volumes", &[], None);
    assert_eq!(st, 200);
    std::thread::sleep(Duration::from_millis(200));
    srv.signal("-INT");
    let (took, clean) = srv.wait_exit(Duration::from_secs(30));
    eprintln!("SIGINT with 4 event streams: stopped in {took:?}");
    assert!(clean);
    assert!(took < Duration::from_secs(2), "stopped in {took:?}");
    for s in &streams {
        assert!(wait_end(s, Duration::from_secs(1)));
    }
}

#[test]
fn beyond_loopback_a_token_is_required() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    // Generated and printed in the URL.
    let srv = Server::start(d.path(), &data, &["--host", "0.0.0.0"], &[]);
    let token = srv
        .url
        .split_once("?token=")
        .unwrap_or_else(|| panic!("no token in {}", srv.url))
        .1
        .to_string();
    assert!(token.len() >= 32, "{token}");
    let (st, body) = http(&srv.addr, "GET", "/api/volumes", &[], None);
    assert_eq!(st, 401, "{body}");
    assert!(body.contains("token"), "{body}");
    let auth = format!("Bearer {token}");
    let (st, _) = http(
        &srv.addr,
        "GET",
        "/api/volumes",
        &[("Authorization", &auth)],
        None,
    );
    assert_eq!(st, 200);
    let (st, _) = http(
        &srv.addr,
        "GET",
        &format!("/api/volumes?token={token}"),
        &[],
        None,
    );
    assert_eq!(st, 200);
    drop(srv);
    // Given with --token, or in the environment.
    for (extra, env) in [
        (
            vec!["--host", "0.0.0.0", "--token", "given-token-42"],
            vec![],
        ),
        (
            vec!["--host", "0.0.0.0"],
            vec![("NEUVOLEX_TOKEN", "given-token-42")],
        ),
    ] {
        let srv = Server::start(d.path(), &data, &extra, &env);
        assert!(srv.url.ends_with("?token=given-token-42"), "{}", srv.url);
        let (st, _) = http(&srv.addr, "GET", "/api/server", &[], None);
        assert_eq!(st, 401);
        let (st, body) = http(
            &srv.addr,
            "GET",
            "/api/server",
            &[("Authorization", "Bearer given-token-42")],
            None,
        );
        assert_eq!(st, 200);
        assert!(body.contains("\"access\":\"token\""), "{body}");
    }
    // On loopback it stays open.
    let srv = Server::start(d.path(), &data, &[], &[]);
    assert!(!srv.url.contains("token"), "{}", srv.url);
    let (st, _) = http(&srv.addr, "GET", "/api/volumes", &[], None);
    assert_eq!(st, 200);
    // A weak token is refused at start.
    let out = Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .args(["serve", "--port", "0", "--token", "short", "--data-root"])
        .arg(&data)
        .arg("--work")
        .arg(d.path().join("work"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("at least 8"));
}

#[test]
fn serve_with_cluster_classifies_on_the_workers() {
    let d = tempfile::tempdir().unwrap();
    let Some(nats) = neuvolex_tests::NatsServer::start(d.path(), "127.0.0.1", &[]) else {
        return;
    };
    let url = nats.url();
    let logs: Vec<_> = (0..2)
        .map(|i| d.path().join(format!("worker-{i}.log")))
        .collect();
    let mut workers: Vec<_> = logs
        .iter()
        .enumerate()
        .map(|(i, log)| {
            Command::new(env!("CARGO_BIN_EXE_neuvolex"))
                .args(["worker", "--nats", &url, "--threads", "1", "--quiet"])
                .args(["--name", &format!("w{i}")])
                .env("RUST_LOG", "neuvolex=info,warn")
                .stderr(std::fs::File::create(log).unwrap())
                .spawn()
                .unwrap()
        })
        .collect();
    let data = data_root(d.path());
    let srv = Server::start(d.path(), &data, &["--cluster", &url], &[]);
    let a = &srv.addr.clone();
    let ev = event_stream(a);
    session_with_strokes(a);
    // The strokes start a classification; it finishes without error, on the workers.
    let t = Instant::now();
    let done = loop {
        match ev.recv_timeout(Duration::from_secs(120)) {
            Ok(Some((k, d))) if k == "classification" => break d,
            Ok(Some(_)) => {}
            other => panic!("no classification event: {other:?}"),
        }
        assert!(t.elapsed() < Duration::from_secs(120), "no classification");
    };
    assert!(!done.contains("\"error\""), "{done}");
    let started: usize = logs
        .iter()
        .map(|l| {
            std::fs::read_to_string(l)
                .unwrap_or_default()
                .matches("task started")
                .count()
        })
        .sum();
    assert!(started >= 1, "the workers ran the classification's tasks");
    srv.signal("-INT");
    for w in &mut workers {
        let _ = w.kill();
        let _ = w.wait();
    }
}
