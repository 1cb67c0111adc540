//! Helpers shared by the tests that drive `neuvolex serve` as a real process (`serve.rs`,
//! `e2e.rs`, `crash.rs`): a phantom data root, the server process, plain HTTP/1.1 requests and
//! event streams.
#![allow(dead_code)]

use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A data root with a small labelled phantom store.
pub fn data_root(d: &Path) -> PathBuf {
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

pub struct Server {
    pub child: Child,
    /// host:port to connect to.
    pub addr: String,
    /// The first URL printed.
    pub url: String,
    /// The server's log (its stderr), printed when the test panics.
    pub log: Option<std::path::PathBuf>,
}

impl Server {
    pub fn start(d: &Path, data: &Path, extra: &[&str], env: &[(&str, &str)]) -> Server {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_neuvolex"));
        // Its log (`D/server-N.log`, N counting the servers of one test) is shown on failure.
        let log = (0..)
            .map(|n| d.join(format!("server-{n}.log")))
            .find(|p| !p.exists());
        cmd.args(["serve", "--port", "0", "--data-root"])
            .arg(data)
            .arg("--work")
            .arg(d.join("work"))
            .args(extra)
            .env_remove("NEUVOLEX_TOKEN")
            .stdout(Stdio::piped())
            .stderr(
                log.as_ref()
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
            log,
        }
    }

    pub fn signal(&self, sig: &str) {
        let st = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(st.success());
    }

    /// Waits for the process to end; returns how long it took and whether it exited cleanly.
    pub fn wait_exit(&mut self, limit: Duration) -> (Duration, bool) {
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
        if std::thread::panicking() {
            if let Some(p) = &self.log {
                let text = std::fs::read_to_string(p).unwrap_or_default();
                eprintln!(
                    "--- {} ---\n{text}--- end of {} ---",
                    p.display(),
                    p.display()
                );
            }
        }
    }
}

/// One HTTP/1.1 request (`Connection: close`); returns the status and the body.
pub fn http(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&Value>,
) -> (u16, String) {
    try_http(addr, method, path, headers, body)
        .unwrap_or_else(|e| panic!("{method} {path} on {addr}: {e}"))
}

/// [`http`] without panicking: an error when the connection fails or no status comes back
/// (a server killed mid-request).
pub fn try_http(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&Value>,
) -> std::io::Result<(u16, String)> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
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
    s.write_all(req.as_bytes())?;
    let mut resp = Vec::new();
    let _ = s.read_to_end(&mut resp);
    let text = String::from_utf8_lossy(&resp).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| std::io::Error::other(format!("no status in {text:?}")))?;
    let body = text.split_once("\r\n\r\n").map_or("", |x| x.1).to_string();
    Ok((status, body))
}

/// An open event stream read on a thread: events arrive on the channel as `(kind, data)`;
/// `None` marks the end of the stream.
pub fn event_stream(addr: &str) -> mpsc::Receiver<Option<(String, String)>> {
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
pub fn wait_event(rx: &mpsc::Receiver<Option<(String, String)>>, kind: &str, needle: &str) {
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
pub fn wait_end(rx: &mpsc::Receiver<Option<(String, String)>>, limit: Duration) -> bool {
    let deadline = Instant::now() + limit;
    loop {
        match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(None) | Err(mpsc::RecvTimeoutError::Disconnected) => return true,
            Ok(Some(_)) => {}
            Err(mpsc::RecvTimeoutError::Timeout) => return false,
        }
    }
}

/// Sends `strokes` to session `id` and waits until their classification is done.
pub fn classify_strokes(addr: &str, id: &str, strokes: &Value) {
    let (st, body) = http(
        addr,
        "PUT",
        &format!("/api/sessions/{id}/strokes"),
        &[],
        Some(strokes),
    );
    assert_eq!(st, 202, "{body}");
    let t = Instant::now();
    loop {
        let (_, body) = http(addr, "GET", &format!("/api/sessions/{id}"), &[], None);
        let v: Value = serde_json::from_str(&body).unwrap();
        if v["status"]["state"] == "done" && v["status"]["generation"] == v["generation"] {
            return;
        }
        assert!(
            v["status"]["state"] != "failed" && t.elapsed() < Duration::from_secs(120),
            "classification did not finish: {v}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Opens the phantom as a session (resuming its newest saved session when `restore`); its id.
pub fn open_phantom(addr: &str, restore: bool) -> String {
    let (st, body) = http(
        addr,
        "POST",
        "/api/sessions",
        &[],
        Some(&json!({"volume": "phantom.zarr", "restore": restore})),
    );
    // 200: a saved session of the volume resumed; 201: a new one.
    assert!(st == 201 || (restore && st == 200), "{st}: {body}");
    serde_json::from_str::<Value>(&body).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string()
}

pub fn phantom_strokes() -> Value {
    json!([
        {"class": 1, "axis": "z", "slice": 21, "points": [[23, 30], [25, 31]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[2, 2], [12, 2], [12, 8]], "radius": 1.5},
        {"class": 255, "axis": "z", "slice": 21, "points": [[40, 44], [46, 44]], "radius": 1.5}
    ])
}

/// `v` with every number as a float (the server writes stroke points as floats).
pub fn numbers_as_f64(v: &Value) -> Value {
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
