//! `neuvolex serve` as a real process: SIGTERM and Ctrl-C (SIGINT) stop it within 2 s with
//! event streams open and a training running, or a render and an export in flight; the
//! training's checkpoint, the store and the session's state on disk are complete afterwards.
//! On a non-loopback address a token is required: the generated one printed in the URL,
//! `--token`, or `NEUVOLEX_TOKEN`. The server and a CLI writer (`neuvolex train`) take turns
//! on one store through its writer lock, each refused with the other named. With `--cluster`
//! the session's classification runs on `neuvolex worker` processes.

mod support;

use serde_json::{json, Value};
use std::process::Command;
use std::time::{Duration, Instant};
use support::{
    classify_strokes, data_root, event_stream, http, numbers_as_f64, open_phantom, phantom_strokes,
    try_http, wait_end, wait_event, Server,
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
    // The session was saved, whole, to a file of its own.
    let saved = d.path().join(format!("work/sessions/{id}.json"));
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&saved).unwrap()).unwrap();
    assert_eq!(
        numbers_as_f64(&v["strokes"]),
        numbers_as_f64(&phantom_strokes())
    );
    assert_eq!(v["volume"], "phantom.zarr");
    assert_eq!(v["id"], json!(id));
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
    assert_eq!(st, 200, "the saved session is resumed: {body}");
    let v: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["strokes"], 3, "{v}");
    assert_eq!(v["id"], json!(id), "under its own id");
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
fn bad_serve_limits_are_refused_naming_the_flag() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    for (flag, value) in [
        ("--feature-store-gib", "-1"),
        ("--feature-store-gib", "NaN"),
        ("--idle-minutes", "-5"),
        ("--request-timeout", "0"),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_neuvolex"))
            .args([
                "serve",
                "--port",
                "0",
                &format!("{flag}={value}"),
                "--data-root",
            ])
            .arg(&data)
            .arg("--work")
            .arg(d.path().join("work"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{flag} {value} was accepted");
        assert!(err.contains(flag), "{flag} {value}: {err}");
    }
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

/// The server's status (`GET /api/server`).
fn server_status(addr: &str) -> Value {
    serde_json::from_str(&http(addr, "GET", "/api/server", &[], None).1).unwrap()
}

#[test]
fn sigterm_with_a_render_and_an_export_in_flight_stops_within_two_seconds() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let mut srv = Server::start(d.path(), &data, &[], &[]);
    let a = srv.addr.clone();
    let id = open_phantom(&a, false);
    classify_strokes(&a, &id, &phantom_strokes());
    // A full-size frame (seconds of work here) and an OME-Zarr export, both in flight.
    let (a1, i1) = (a.clone(), id.clone());
    let render = std::thread::spawn(move || {
        try_http(
            &a1,
            "GET",
            &format!("/api/sessions/{i1}/render?size=2048"),
            &[],
            None,
        )
    });
    let (a2, i2) = (a.clone(), id.clone());
    let export = std::thread::spawn(move || {
        try_http(
            &a2,
            "POST",
            &format!("/api/sessions/{i2}/export/zarr"),
            &[],
            Some(&json!({"name": "sx"})),
        )
    });
    let t = Instant::now();
    while server_status(&a)["renders_in_flight"] == 0 {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "the render never started"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    srv.signal("-TERM");
    let (took, clean) = srv.wait_exit(Duration::from_secs(30));
    eprintln!("SIGTERM with a render and an export in flight: stopped in {took:?}");
    let log = std::fs::read_to_string(d.path().join("server-0.log")).unwrap_or_default();
    assert!(clean, "exit status 0: {log}");
    assert!(took < Duration::from_secs(2), "stopped in {took:?}: {log}");
    // The render was cancelled (503) or its connection closed; never a frame after the stop.
    match render.join().unwrap() {
        Ok((st, body)) => assert_eq!(st, 503, "{body}"),
        Err(e) => eprintln!("render: connection closed ({e})"),
    }
    let exported = matches!(export.join().unwrap(), Ok((200, _)));
    // The store reads whole: the export is there complete, or not at all.
    let store = neuvolex_bricks::BrickStore::open(data.join("phantom.zarr")).unwrap();
    let has_labels = store.info().labels.iter().any(|l| l == "sx");
    let has_probs = store.has_vectors("sx_proba").unwrap();
    assert_eq!(
        has_labels, has_probs,
        "labels {has_labels}, probabilities {has_probs}"
    );
    assert!(
        !exported || has_labels,
        "an acknowledged export must be in the store"
    );
    if has_labels {
        let dims = store.info().dims;
        store.read_labels_box("sx", [0; 3], dims).unwrap();
        let va = store.open_vectors("sx_proba").unwrap();
        for b in store.bricks() {
            va.read_brick(&b).unwrap();
        }
    }
    // The session was saved, whole.
    let saved = d.path().join(format!("work/sessions/{id}.json"));
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&saved).unwrap()).unwrap();
    assert_eq!(
        numbers_as_f64(&v["strokes"]),
        numbers_as_f64(&phantom_strokes())
    );
}

#[test]
fn a_cli_writer_and_the_server_take_turns_on_the_store() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let store = data.join("phantom.zarr");
    let lock = store.join("neuvolex/writer.lock");
    let srv = Server::start(d.path(), &data, &[], &[]);
    let a = srv.addr.clone();
    let id = open_phantom(&a, false);
    classify_strokes(&a, &id, &phantom_strokes());
    // A CLI training holds the store's writer lock.
    let mut cli = Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .arg("train")
        .arg(&store)
        .args(["--seconds", "120"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let pid = cli.id().to_string();
    let t = Instant::now();
    while !std::fs::read_to_string(&lock).is_ok_and(|s| s.contains(&pid)) {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "the CLI never took the lock"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    // The server's writes are refused with 409 naming the holder.
    let train = |action: &str| {
        http(
            &a,
            "POST",
            &format!("/api/sessions/{id}/train"),
            &[],
            Some(&json!({"action": action, "epochs": 1000})),
        )
    };
    let export = || {
        http(
            &a,
            "POST",
            &format!("/api/sessions/{id}/export/zarr"),
            &[],
            Some(&json!({"name": "nx"})),
        )
    };
    for (what, (st, body)) in [("train", train("start")), ("export", export())] {
        assert_eq!(st, 409, "{what} beside a CLI writer: {body}");
        assert!(
            body.contains("locked by another writer")
                && body.contains(&format!("pid {pid}"))
                && body.contains("train"),
            "{what}: the holder is not named: {body}"
        );
        eprintln!("server {what} beside `neuvolex train`: {st} {body}");
    }
    assert_eq!(
        server_status(&a)["trainings"],
        0,
        "a refused training holds no slot"
    );
    // Once the CLI writer is gone, the server writes.
    cli.kill().unwrap();
    cli.wait().unwrap();
    let (st, body) = export();
    assert_eq!(st, 200, "{body}");
    let (st, body) = train("start");
    assert_eq!(st, 202, "{body}");
    // Now the server holds the lock: its own export still works, a CLI writer is refused.
    let (st, body) = export();
    assert_eq!(st, 200, "{body}");
    let o = Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .arg("train")
        .arg(&store)
        .args(["--seconds", "1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success(),
        "a CLI training ran beside the server's"
    );
    assert!(
        err.contains("locked by another writer")
            && err.contains(&format!("pid {}", srv.child.id()))
            && err.contains("neuvolex serve: training session"),
        "{err}"
    );
    eprintln!(
        "`neuvolex train` beside the server's training: {}",
        err.trim()
    );
    let (st, _) = train("stop");
    assert_eq!(st, 202);
}

/// Issue 45: the autosave keeps strokes as they come, so `kill -9` of the server loses at most
/// the last second of them. Strokes are sent one at a time, 100 ms apart, for 3 s; the server
/// is killed with SIGKILL at once after the last; a new server resumes the session by its id
/// and holds every stroke sent up to a second before the kill, in order, with the redo stack
/// and the page's settings.
#[test]
fn kill_9_loses_at_most_the_last_second_of_strokes() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let mut srv = Server::start(d.path(), &data, &["--feature-store-gib=0"], &[]);
    let a = &srv.addr.clone();
    let id = open_phantom(a, false);
    let (st, _) = http(
        a,
        "PUT",
        &format!("/api/sessions/{id}/ui"),
        &[],
        Some(&json!({"idx": {"x": 1, "y": 2, "z": 3}})),
    );
    assert_eq!(st, 204);
    let stroke = |i: usize| {
        json!({"class": if i.is_multiple_of(2) { 1 } else { 255 }, "axis": "z", "slice": 5 + i % 30,
               "points": [[2 + i % 40, 3], [4 + i % 40, 6]], "radius": 1.0})
    };
    let mut sent: Vec<(Instant, usize)> = Vec::new();
    let t0 = Instant::now();
    let mut i = 0;
    while t0.elapsed() < Duration::from_secs(3) {
        let (st, body) = http(
            a,
            "POST",
            &format!("/api/sessions/{id}/strokes"),
            &[],
            Some(&json!([stroke(i)])),
        );
        assert_eq!(st, 202, "{body}");
        sent.push((Instant::now(), i + 1));
        i += 1;
        std::thread::sleep(Duration::from_millis(100));
    }
    // The undo stack of the page: the last stroke undone, kept for redo.
    let strokes: Vec<Value> = (0..i - 1).map(stroke).collect();
    let (st, _) = http(
        a,
        "PUT",
        &format!("/api/sessions/{id}/strokes"),
        &[],
        Some(&json!({"strokes": strokes, "redo": [stroke(i - 1)]})),
    );
    assert_eq!(st, 202);
    std::thread::sleep(Duration::from_millis(1000));
    srv.signal("-KILL");
    let killed = Instant::now();
    srv.wait_exit(Duration::from_secs(10));
    // Everything sent a second before the kill is there.
    let must = sent
        .iter()
        .filter(|(t, _)| killed.duration_since(*t) >= Duration::from_secs(1))
        .map(|&(_, n)| n)
        .max()
        .unwrap_or(0);
    assert!(must >= 20, "the test sent too little: {must}");
    let srv2 = Server::start(d.path(), &data, &["--feature-store-gib=0"], &[]);
    let a = &srv2.addr.clone();
    let (st, body) = http(a, "GET", "/api/sessions", &[], None);
    assert_eq!(st, 200);
    assert!(body.contains(&id), "the saved session is listed: {body}");
    let (st, body) = http(
        a,
        "POST",
        "/api/sessions",
        &[],
        Some(&json!({"resume": id})),
    );
    assert_eq!(st, 200, "{body}");
    let (_, body) = http(a, "GET", &format!("/api/sessions/{id}/state"), &[], None);
    let v: Value = serde_json::from_str(&body).unwrap();
    let got = v["strokes"].as_array().unwrap().len() + v["redo"].as_array().map_or(0, Vec::len);
    eprintln!("kill -9: {got} of {i} strokes kept ({must} sent a second or more before the kill)");
    assert!(
        got >= must,
        "lost strokes: {got} kept, {must} sent a second before the kill"
    );
    let want: Vec<Value> = (0..got).map(|k| numbers_as_f64(&stroke(k))).collect();
    let mut have: Vec<Value> = v["strokes"]
        .as_array()
        .unwrap()
        .iter()
        .map(numbers_as_f64)
        .collect();
    have.extend(
        v["redo"]
            .as_array()
            .into_iter()
            .flatten()
            .rev()
            .map(numbers_as_f64),
    );
    assert_eq!(have, want, "the strokes kept, in order");
    assert_eq!(v["redo"].as_array().map(Vec::len), Some(1), "{v}");
    assert_eq!(v["ui"]["idx"]["z"], 3, "{v}");
}
