//! `neuvolex serve` as a real process: SIGTERM and Ctrl-C (SIGINT) stop it within 2 s with
//! event streams open and a training running; the training's checkpoint and the session's
//! state on disk are complete afterwards. On a non-loopback address a token is required: the
//! generated one printed in the URL, `--token`, or `NEUVOLEX_TOKEN`.

use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A data root with a small labelled phantom store.
fn data_root(d: &Path) -> PathBuf {
    let data = d.join("data");
    std::fs::create_dir_all(&data).unwrap();
    let st = Command::new(env!("CARGO_BIN_EXE_neuvolex"))
        .args([
            "synth", "phantom", "--size", "48", "--brick", "16", "--quiet", "--out",
        ])
        .arg(data.join("phantom.zarr"))
        .status()
        .unwrap();
    assert!(st.success());
    data
}

struct Server {
    child: Child,
    /// host:port to connect to.
    addr: String,
    /// The first URL printed.
    url: String,
}

impl Server {
    fn start(d: &Path, data: &Path, extra: &[&str], env: &[(&str, &str)]) -> Server {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_neuvolex"));
        // Its log (`D/server-N.log`, N counting the servers of one test) is shown on failure.
        cmd.args(["serve", "--port", "0", "--data-root"])
            .arg(data)
            .arg("--work")
            .arg(d.join("work"))
            .args(extra)
            .env_remove("NEUVOLEX_TOKEN")
            .stdout(Stdio::piped())
            .stderr(
                (0..)
                    .map(|n| d.join(format!("server-{n}.log")))
                    .find(|p| !p.exists())
                    .and_then(|p| std::fs::File::create(p).ok())
                    .map_or_else(Stdio::null, Stdio::from),
            );
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().unwrap();
        let mut out = BufReader::new(child.stdout.take().unwrap());
        let mut lines = Vec::new();
        let mut line = String::new();
        while out.read_line(&mut line).unwrap() > 0 {
            lines.push(line.trim().to_string());
            line.clear();
            if lines.last().unwrap().contains("127.0.0.1") {
                break;
            }
        }
        let url = lines
            .iter()
            .find_map(|l| l.split_whitespace().find(|w| w.starts_with("http://")))
            .unwrap_or_else(|| panic!("no URL printed: {lines:?}"))
            .to_string();
        let port = lines
            .iter()
            .find_map(|l| {
                let w = l.split_whitespace().find(|w| w.starts_with("http://"))?;
                let hp = w.trim_start_matches("http://").split('/').next()?;
                hp.rsplit_once(':').map(|(_, p)| p.to_string())
            })
            .unwrap();
        // Keep draining stdout so the server never blocks on it.
        std::thread::spawn(move || {
            let mut sink = Vec::new();
            let _ = out.read_to_end(&mut sink);
        });
        Server {
            child,
            addr: format!("127.0.0.1:{port}"),
            url,
        }
    }

    fn signal(&self, sig: &str) {
        let st = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(st.success());
    }

    /// Waits for the process to end; returns how long it took and whether it exited cleanly.
    fn wait_exit(&mut self, limit: Duration) -> (Duration, bool) {
        let t = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                return (t.elapsed(), st.success());
            }
            if t.elapsed() > limit {
                let _ = self.child.kill();
                panic!("the server did not stop within {limit:?}");
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request (`Connection: close`); returns the status and the body.
fn http(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&Value>,
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut req = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    if !body.is_empty() {
        req.push_str("Content-Type: application/json\r\n");
    }
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    req.push_str(&body);
    s.write_all(req.as_bytes()).unwrap();
    let mut resp = Vec::new();
    let _ = s.read_to_end(&mut resp);
    let text = String::from_utf8_lossy(&resp).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status in {text:?}"));
    let body = text.split_once("\r\n\r\n").map_or("", |x| x.1).to_string();
    (status, body)
}

/// An open event stream read on a thread: events arrive on the channel as `(kind, data)`;
/// `None` marks the end of the stream.
fn event_stream(addr: &str) -> mpsc::Receiver<Option<(String, String)>> {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(s, "GET /api/events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut r = BufReader::new(s);
        let mut kind = String::new();
        let mut line = String::new();
        loop {
            line.clear();
            match r.read_line(&mut line) {
                Ok(0) | Err(_) => {
                    let _ = tx.send(None);
                    return;
                }
                Ok(_) => {}
            }
            let l = line.trim_end();
            if let Some(k) = l.strip_prefix("event: ") {
                kind = k.to_string();
            } else if let Some(d) = l.strip_prefix("data: ") {
                let _ = tx.send(Some((kind.clone(), d.to_string())));
            }
        }
    });
    rx
}

/// Waits for an event of `kind` whose data contains `needle`.
fn wait_event(rx: &mpsc::Receiver<Option<(String, String)>>, kind: &str, needle: &str) {
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(Some((k, d))) if k == kind && d.contains(needle) => return,
            Ok(Some(_)) => {}
            Ok(None) => panic!("the event stream ended while waiting for {kind} {needle}"),
            Err(_) => panic!("no {kind} event with {needle} within 240 s"),
        }
    }
}

/// Waits for the end of an event stream (events before it are skipped).
fn wait_end(rx: &mpsc::Receiver<Option<(String, String)>>, limit: Duration) -> bool {
    let deadline = Instant::now() + limit;
    loop {
        match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(None) | Err(mpsc::RecvTimeoutError::Disconnected) => return true,
            Ok(Some(_)) => {}
            Err(mpsc::RecvTimeoutError::Timeout) => return false,
        }
    }
}

fn phantom_strokes() -> Value {
    json!([
        {"class": 1, "axis": "z", "slice": 21, "points": [[23, 30], [25, 31]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[2, 2], [12, 2], [12, 8]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[40, 44], [46, 44]], "radius": 1.5}
    ])
}

/// `v` with every number as a float (the server writes stroke points as floats).
fn numbers_as_f64(v: &Value) -> Value {
    match v {
        Value::Number(n) => json!(n.as_f64()),
        Value::Array(a) => Value::Array(a.iter().map(numbers_as_f64).collect()),
        Value::Object(o) => Value::Object(
            o.iter()
                .map(|(k, x)| (k.clone(), numbers_as_f64(x)))
                .collect(),
        ),
        x => x.clone(),
    }
}

#[test]
fn sigterm_stops_a_training_server_within_two_seconds_and_keeps_complete_state() {
    let d = tempfile::tempdir().unwrap();
    let data = data_root(d.path());
    let mut srv = Server::start(d.path(), &data, &[], &[]);
    let a = &srv.addr.clone();
    let streams: Vec<_> = (0..3).map(|_| event_stream(a)).collect();
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
