//! The soak test: a real `neuvolex serve` process driven over HTTP on loopback by several
//! worker processes at once, for a fixed time, each acting as a person would:
//!
//! - `drawer` (two by default): strokes on the shared session in bursts of 5 s (a stroke every
//!   0.25-0.6 s each) with 20 s of quiet between them, on one schedule shared by all drawers;
//!   every acknowledged stroke is kept with the generation the server answered;
//! - `viewer`: slices, overlays, class fractions, session info;
//! - `renderer`: 3-D frames at random views and sizes, and transfer-function edits;
//! - `editor`: class edits and session files; in the quiet periods it waits for the
//!   classification to converge (polling the session) and exports, in turn, the NIfTI labels,
//!   a class probability, the OME-Zarr labels and probabilities, and the scribbles: each kind
//!   must succeed at least once;
//! - `trainer`: INR training started (or resumed), run until a preview and a snapshot arrive
//!   on its event stream, the preview fetched (200), then stopped, waiting for `stopped`, and
//!   10-20 s of looking at the result before the next round;
//! - `streamer`: event streams opened, read until a deadline and dropped, events counted;
//! - `sessions`: every 15-25 s, further sessions on the volume opened until the session limit
//!   answers 503, the first given strokes and classified, each rendered, all closed (the limit,
//!   the cross-session caches and budgets, and the state saved at close).
//!
//! The coordinator also keeps one event stream open for the whole run and samples the
//! server's RSS and memory report every 100 ms. At the end it reports p50/p99 per route, the
//! statuses, the 503s by reason, the events by kind, and the RSS curve (start, min, max, end,
//! and whether it plateaus), and checks:
//!
//! - no answer outside the documented ones: 2xx, and 503 for a full mailbox, the session limit
//!   or the training limit (a request timeout is not excused: `--max-timeouts`, default 0);
//! - not one stroke lost: the server's scribble volume equals the rasterisation of every
//!   acknowledged stroke, and for every acknowledged stroke a `classification` event reported a
//!   finished classification of its generation or a later one;
//! - each export kind succeeded during the load, and the final exports agree with the final
//!   state (NIfTI labels equal the OME-Zarr label image; each class's NIfTI probability equals
//!   its channel of the exported probability array; the session did not change meanwhile);
//! - the trainer got a preview (200) and a snapshot; the sessions role opened and closed
//!   sessions and met the limit;
//! - RSS stays under `--max-rss-mib`; SIGTERM stops the server within 2 s, ending the event
//!   stream with a `shutdown` event.
//!
//! ```text
//! cargo build --release -p neuvolex -p neuvolex-benches --bin soak
//! target/release/soak --seconds 600 --out soak.json
//! ```
//!
//! Options: `--seconds N` (600), `--drawers N` (2), `--size N` (phantom edge, 64), `--data-root
//! DIR --volume REL` (a real volume instead of the phantom), `--neuvolex PATH` (default: beside
//! this binary), `--max-rss-mib N` (3072), `--max-timeouts N` (0), `--max-sessions N` (4),
//! `--server-log FILE` (the server's log), `--out FILE` (JSON report).

use anyhow::{bail, Context, Result};
use neuvolex_bricks::rng::Rng;
use neuvolex_classify::scribble::{rasterise, Stroke};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("worker") {
        return worker(&Opts::parse(&args[2..])?);
    }
    coordinator(&Opts::parse(&args[1..])?)
}

/// `--key value` options.
struct Opts(BTreeMap<String, String>);

impl Opts {
    fn parse(args: &[String]) -> Result<Opts> {
        let mut m = BTreeMap::new();
        let mut it = args.iter();
        while let Some(k) = it.next() {
            let Some(k) = k.strip_prefix("--") else {
                bail!("unexpected argument '{k}'");
            };
            let v = it.next().with_context(|| format!("--{k} needs a value"))?;
            m.insert(k.to_string(), v.clone());
        }
        Ok(Opts(m))
    }
    fn get(&self, k: &str) -> Option<&str> {
        self.0.get(k).map(String::as_str)
    }
    fn num<T: std::str::FromStr>(&self, k: &str, default: T) -> Result<T> {
        match self.get(k) {
            None => Ok(default),
            Some(v) => v
                .parse()
                .map_err(|_| anyhow::anyhow!("--{k} {v} is not a number")),
        }
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

// ---------------------------------------------------------------- the drawers' schedule

/// Seconds of drawing, then of quiet (looking at the result, exporting), in each period; all
/// drawers share the phase.
const BURST_S: f64 = 5.0;
const QUIET_S: f64 = 20.0;

/// Where in the schedule started at `t0_ms` (Unix ms) the time `now_ms` falls: `(drawing,
/// seconds left in this phase)`.
fn phase(t0_ms: u64, now_ms: u64) -> (bool, f64) {
    let t = now_ms.saturating_sub(t0_ms) as f64 / 1e3;
    let p = t % (BURST_S + QUIET_S);
    if p < BURST_S {
        (true, BURST_S - p)
    } else {
        (false, BURST_S + QUIET_S - p)
    }
}

// ---------------------------------------------------------------- answers

/// Why a 503 was given, from its error message; `None` for a reason the API does not document.
fn busy_reason(body: &str) -> Option<&'static str> {
    if body.contains("request timeout") {
        Some("request timeout")
    } else if body.contains("is busy; try again") {
        Some("mailbox full")
    } else if body.contains("sessions are open (the server's limit)") {
        Some("session limit")
    } else if body.contains("training(s) running (the server's limit)") {
        Some("training limit")
    } else {
        None
    }
}

/// Whether an answer is one the API documents for load: success, or a 503 for a full mailbox,
/// the session limit or the training limit. (A request timeout is counted apart.)
fn expected(status: u16, body: &str) -> bool {
    (200..300).contains(&status)
        || (status == 503 && busy_reason(body).is_some_and(|r| r != "request timeout"))
}

/// Latencies (ms), statuses and 503 reasons per route, and samples of unexpected answers.
#[derive(Default)]
struct Record {
    ms: BTreeMap<String, Vec<f64>>,
    status: BTreeMap<String, BTreeMap<u16, u64>>,
    busy: BTreeMap<String, u64>,
    timeouts: u64,
    unexpected: u64,
    samples: Vec<String>,
}

impl Record {
    fn add(&mut self, route: &str, ms: f64, status: u16, body: &str) {
        self.ms.entry(route.into()).or_default().push(ms);
        *self
            .status
            .entry(route.into())
            .or_default()
            .entry(status)
            .or_insert(0) += 1;
        if status == 503 {
            let r = busy_reason(body).unwrap_or("undocumented");
            *self.busy.entry(format!("{route}: {r}")).or_insert(0) += 1;
            if r == "request timeout" {
                self.timeouts += 1;
            }
        }
        if !expected(status, body) {
            self.unexpected += 1;
            if self.samples.len() < 10 {
                self.samples.push(format!(
                    "{route} {status}: {}",
                    body.chars().take(300).collect::<String>()
                ));
            }
        }
    }

    fn to_json(&self) -> Value {
        json!({
            "ms": self.ms,
            "status": self.status.iter().map(|(k, v)| (k.clone(), v.iter().map(|(s, n)| (s.to_string(), *n)).collect::<BTreeMap<_, _>>())).collect::<BTreeMap<_, _>>(),
            "busy": self.busy,
            "timeouts": self.timeouts,
            "unexpected": self.unexpected,
            "samples": self.samples,
        })
    }
}

struct Client {
    agent: ureq::Agent,
    base: String,
    rec: Record,
}

impl Client {
    fn new(addr: &str) -> Client {
        Client {
            agent: ureq::AgentBuilder::new()
                .timeout(Duration::from_secs(120))
                .build(),
            base: format!("http://{addr}"),
            rec: Record::default(),
        }
    }

    /// One request; records its latency and status under `route`; returns status and body.
    fn call(
        &mut self,
        route: &str,
        method: &str,
        path: &str,
        body: Option<&Value>,
    ) -> (u16, Vec<u8>) {
        let t = Instant::now();
        let req = self.agent.request(method, &format!("{}{path}", self.base));
        let r = match body {
            Some(b) => req
                .set("Content-Type", "application/json")
                .send_string(&b.to_string()),
            None => req.call(),
        };
        let (status, bytes) = match r {
            Ok(resp) => {
                let st = resp.status();
                let mut b = Vec::new();
                let _ = resp.into_reader().take(256 << 20).read_to_end(&mut b);
                (st, b)
            }
            Err(ureq::Error::Status(st, resp)) => {
                let mut b = Vec::new();
                let _ = resp.into_reader().take(1 << 20).read_to_end(&mut b);
                (st, b)
            }
            Err(e) => (0, e.to_string().into_bytes()),
        };
        let ms = t.elapsed().as_secs_f64() * 1e3;
        self.rec
            .add(route, ms, status, &String::from_utf8_lossy(&bytes));
        (status, bytes)
    }

    fn json(
        &mut self,
        route: &str,
        method: &str,
        path: &str,
        body: Option<&Value>,
    ) -> (u16, Value) {
        let (st, b) = self.call(route, method, path, body);
        (st, serde_json::from_slice(&b).unwrap_or(Value::Null))
    }

    /// Polls the session until its classification has finished its newest generation, at most
    /// `limit`; returns the session info then, or `None`.
    fn converged(&mut self, session: &str, limit: Duration) -> Option<Value> {
        let t = Instant::now();
        while t.elapsed() < limit {
            let (st, v) = self.json(
                "GET /sessions/{id}",
                "GET",
                &format!("/api/sessions/{session}"),
                None,
            );
            if st == 200
                && v["status"]["generation"] == v["generation"]
                && v["status"]["state"] == "done"
            {
                return Some(v);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        None
    }
}

/// An event stream read with deadlines: a plain HTTP/1.1 connection whose socket reads time
/// out, so no read ever waits past the caller's deadline.
struct EventStream {
    sock: TcpStream,
    buf: Vec<u8>,
    kind: String,
    ended: bool,
}

impl EventStream {
    /// Opens `/api/events` (for `session` when given); returns the stream and the status.
    fn open(addr: &str, session: Option<&str>) -> Result<(EventStream, u16)> {
        let mut sock = TcpStream::connect(addr)?;
        sock.set_read_timeout(Some(Duration::from_millis(200)))?;
        let q = session.map(|s| format!("?session={s}")).unwrap_or_default();
        write!(
            sock,
            "GET /api/events{q} HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
        )?;
        let mut es = EventStream {
            sock,
            buf: Vec::new(),
            kind: String::new(),
            ended: false,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        let status_line = loop {
            if let Some(l) = es.line(deadline)? {
                break l;
            }
            if es.ended || Instant::now() >= deadline {
                bail!("no answer to GET /api/events within 30 s");
            }
        };
        let status = status_line
            .split_whitespace()
            .nth(1)
            .and_then(|c| c.parse().ok())
            .unwrap_or(0);
        // The headers, up to the blank line.
        loop {
            match es.line(deadline)? {
                Some(l) if l.is_empty() => break,
                Some(_) => {}
                None if es.ended || Instant::now() >= deadline => {
                    bail!("GET /api/events: headers incomplete")
                }
                None => {}
            }
        }
        Ok((es, status))
    }

    /// The next line (without its end), `None` at the deadline or the end of the stream.
    fn line(&mut self, deadline: Instant) -> Result<Option<String>> {
        loop {
            if let Some(i) = self.buf.iter().position(|&b| b == b'\n') {
                let l: Vec<u8> = self.buf.drain(..=i).collect();
                return Ok(Some(String::from_utf8_lossy(&l).trim_end().to_string()));
            }
            if self.ended || Instant::now() >= deadline {
                return Ok(None);
            }
            let mut chunk = [0u8; 8192];
            match self.sock.read(&mut chunk) {
                Ok(0) => self.ended = true,
                Ok(n) => self.buf.extend_from_slice(&chunk[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(_) => self.ended = true,
            }
        }
    }

    /// The next event `(kind, data)`, `None` at the deadline or the end of the stream.
    fn next(&mut self, deadline: Instant) -> Result<Option<(String, Value)>> {
        while let Some(l) = self.line(deadline)? {
            if let Some(k) = l.strip_prefix("event: ") {
                self.kind = k.to_string();
            } else if let Some(d) = l.strip_prefix("data: ") {
                let v = serde_json::from_str(d).unwrap_or(Value::Null);
                return Ok(Some((self.kind.clone(), v)));
            }
        }
        Ok(None)
    }

    /// Waits for an event of `kind` whose JSON satisfies `want`, until `deadline`; counts
    /// every event read in `seen`.
    fn wait_for(
        &mut self,
        kind: &str,
        want: impl Fn(&Value) -> bool,
        deadline: Instant,
        seen: &mut BTreeMap<String, u64>,
    ) -> Result<Option<Value>> {
        while let Some((k, v)) = self.next(deadline)? {
            *seen.entry(k.clone()).or_insert(0) += 1;
            if k == kind && want(&v) {
                return Ok(Some(v));
            }
        }
        Ok(None)
    }
}

fn random_stroke(rng: &mut Rng, dims: &[usize], slices: &[usize]) -> Stroke {
    let class = [1, 2, 3, 255][rng.below(4)];
    let pts = 2 + rng.below(3);
    Stroke {
        class,
        axis: neuvolex_classify::scribble::Axis::Z,
        slice: slices[rng.below(slices.len())],
        points: (0..pts)
            .map(|_| {
                [
                    rng.below(dims[0]) as f32 * 0.999,
                    rng.below(dims[1]) as f32 * 0.999,
                ]
            })
            .collect(),
        radius: [0.5f32, 1.0, 2.0, 3.5][rng.below(4)],
    }
}

/// Sleeps a random `lo..hi` ms, but not past `deadline`.
fn pause(rng: &mut Rng, lo: u64, hi: u64, deadline: Instant) {
    let d = Duration::from_millis(lo + rng.below((hi - lo) as usize) as u64);
    std::thread::sleep(d.min(deadline.saturating_duration_since(Instant::now())));
}

/// The export kinds the editor must each get through at least once.
const EXPORTS: [&str; 4] = [
    "GET /export/labels.nii.gz",
    "GET /export/probability",
    "POST /export/zarr",
    "GET /export/scribbles.nii.gz",
];

fn worker(o: &Opts) -> Result<()> {
    let addr = o.get("addr").context("--addr")?;
    let session = o.get("session").context("--session")?.to_string();
    let role = o.get("role").context("--role")?;
    let seconds: f64 = o.num("seconds", 60.0)?;
    let seed: u64 = o.num("seed", 1)?;
    let t0: u64 = o.num("t0", unix_ms())?;
    let volume = o.get("volume").unwrap_or("phantom.zarr").to_string();
    let out = PathBuf::from(o.get("out").context("--out")?);
    let mut c = Client::new(addr);
    let mut rng = Rng::new(seed);
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let (_, info) = c.json(
        "GET /sessions/{id}",
        "GET",
        &format!("/api/sessions/{session}"),
        None,
    );
    let dims: Vec<usize> = info["dims"]
        .as_array()
        .context("session info has no dims")?
        .iter()
        .filter_map(Value::as_u64)
        .map(|v| v as usize)
        .collect();
    let mut extra = serde_json::Map::new();
    let mut acked: Vec<(Stroke, u64)> = Vec::new();
    let s = &session;
    match role {
        "drawer" => {
            let k: usize = o.num("index", 0)?;
            let n: usize = o.num("drawers", 1)?;
            let slices: Vec<usize> = (0..dims[2]).filter(|z| z % n == k).collect();
            let mut refused = 0u64;
            while Instant::now() < deadline {
                let (drawing, left) = phase(t0, unix_ms());
                if !drawing {
                    std::thread::sleep(Duration::from_secs_f64(left.min(1.0)));
                    continue;
                }
                let stroke = random_stroke(&mut rng, &dims, &slices);
                let body = serde_json::to_value([&stroke])?;
                let (st, v) = c.json(
                    "POST /strokes",
                    "POST",
                    &format!("/api/sessions/{s}/strokes"),
                    Some(&body),
                );
                if st == 202 {
                    let g = v["generation"].as_u64().context("no generation")?;
                    acked.push((stroke, g));
                } else {
                    // A refused stroke was not added: a person draws it again later.
                    refused += 1;
                }
                pause(&mut rng, 250, 600, deadline);
            }
            extra.insert("refused".into(), json!(refused));
        }
        "viewer" => {
            while Instant::now() < deadline {
                let a = rng.below(3);
                let axis = ["x", "y", "z"][a];
                let i = rng.below(dims[a]);
                c.call(
                    "GET /slice",
                    "GET",
                    &format!("/api/sessions/{s}/slice/{axis}/{i}"),
                    None,
                );
                let kind = ["labels", "uncertainty"][rng.below(2)];
                c.call(
                    "GET /overlay",
                    "GET",
                    &format!("/api/sessions/{s}/overlay/{axis}/{i}?kind={kind}"),
                    None,
                );
                if rng.below(4) == 0 {
                    c.call(
                        "GET /fractions",
                        "GET",
                        &format!("/api/sessions/{s}/fractions"),
                        None,
                    );
                    c.call(
                        "GET /sessions/{id}",
                        "GET",
                        &format!("/api/sessions/{s}"),
                        None,
                    );
                }
                pause(&mut rng, 50, 250, deadline);
            }
        }
        "renderer" => {
            let presets = ["grey", "ct-bone", "ct-soft-tissue"];
            while Instant::now() < deadline {
                let size = [96, 128, 192, 256][rng.below(4)];
                let az = rng.below(360);
                let el = rng.below(120) as i64 - 60;
                let mode =
                    ["", "&mode=intensity", "&mode=prob", "&mode=prob-intensity"][rng.below(4)];
                c.call(
                    "GET /render",
                    "GET",
                    &format!("/api/sessions/{s}/render?size={size}&az={az}&el={el}{mode}"),
                    None,
                );
                if rng.below(6) == 0 {
                    let p = presets[rng.below(presets.len())];
                    let (st, tf) = c.json(
                        "GET /presets/{name}",
                        "GET",
                        &format!("/api/presets/{p}"),
                        None,
                    );
                    if st == 200 {
                        c.call(
                            "PUT /tf",
                            "PUT",
                            &format!("/api/sessions/{s}/tf"),
                            Some(&tf),
                        );
                    }
                }
                pause(&mut rng, 200, 1000, deadline);
            }
        }
        "editor" => {
            let mut n = 0u32;
            let mut ok: BTreeMap<&str, u64> = EXPORTS.iter().map(|e| (*e, 0)).collect();
            let (mut not_converged, mut waits, mut exports) = (0u64, Vec::new(), 0usize);
            while Instant::now() < deadline {
                n += 1;
                let classes: Vec<Value> = (1..=3)
                    .map(|id| {
                        json!({"id": id, "name": format!("class {id} edit {n}"),
                               "color": [rng.below(256), rng.below(256), rng.below(256)]})
                    })
                    .collect();
                c.call(
                    "PUT /classes",
                    "PUT",
                    &format!("/api/sessions/{s}/classes"),
                    Some(&Value::Array(classes)),
                );
                c.call(
                    "GET /state",
                    "GET",
                    &format!("/api/sessions/{s}/state"),
                    None,
                );
                c.call(
                    "GET /strokes",
                    "GET",
                    &format!("/api/sessions/{s}/strokes"),
                    None,
                );
                // Exports in the quiet periods, once the classification converged.
                let (drawing, left) = phase(t0, unix_ms());
                if drawing {
                    std::thread::sleep(Duration::from_secs_f64(left.min(2.0)));
                    continue;
                }
                let t = Instant::now();
                let Some(_) = c.converged(s, Duration::from_secs_f64(left.max(0.5))) else {
                    not_converged += 1;
                    continue;
                };
                waits.push(t.elapsed().as_secs_f64());
                // A kind not yet through first, else in turn.
                exports += 1;
                let kind = EXPORTS
                    .iter()
                    .find(|e| ok[**e] == 0)
                    .copied()
                    .unwrap_or(EXPORTS[exports % EXPORTS.len()]);
                let (st, _) = match kind {
                    "GET /export/labels.nii.gz" => c.call(
                        kind,
                        "GET",
                        &format!("/api/sessions/{s}/export/labels.nii.gz"),
                        None,
                    ),
                    "GET /export/probability" => c.call(
                        kind,
                        "GET",
                        &format!("/api/sessions/{s}/export/probability/1.nii.gz"),
                        None,
                    ),
                    "POST /export/zarr" => c.call(
                        kind,
                        "POST",
                        &format!("/api/sessions/{s}/export/zarr"),
                        Some(&json!({"name": "soak"})),
                    ),
                    _ => c.call(
                        kind,
                        "GET",
                        &format!("/api/sessions/{s}/export/scribbles.nii.gz"),
                        None,
                    ),
                };
                if st == 200 {
                    *ok.entry(kind).or_insert(0) += 1;
                }
                pause(&mut rng, 200, 800, deadline);
            }
            extra.insert("exports_ok".into(), json!(ok));
            extra.insert("not_converged".into(), json!(not_converged));
            extra.insert("converge_waits_s".into(), json!(waits));
        }
        "trainer" => {
            let mut resume = false;
            let (mut previews, mut snapshots, mut stops, mut rounds) = (0u64, 0u64, 0u64, 0u64);
            let mut seen = BTreeMap::new();
            while Instant::now() + Duration::from_secs(5) < deadline {
                let t = Instant::now();
                let (mut ev, st) = EventStream::open(addr, Some(s))?;
                c.rec.add(
                    "GET /events (headers)",
                    t.elapsed().as_secs_f64() * 1e3,
                    st,
                    "",
                );
                let action = if resume { "resume" } else { "start" };
                let (st, _) = c.call(
                    "POST /train start",
                    "POST",
                    &format!("/api/sessions/{s}/train"),
                    Some(&json!({"action": action, "epochs": 1000})),
                );
                if st != 202 {
                    pause(&mut rng, 1000, 2000, deadline);
                    continue;
                }
                rounds += 1;
                resume = !resume;
                // Until a preview and a snapshot arrived (or the run ends).
                let until = deadline;
                if ev
                    .wait_for("preview", |_| true, until, &mut seen)?
                    .is_some()
                {
                    let (st, _) = c.call(
                        "GET /preview.png",
                        "GET",
                        &format!("/api/sessions/{s}/preview.png"),
                        None,
                    );
                    if st == 200 {
                        previews += 1;
                    }
                    if ev
                        .wait_for(
                            "training",
                            |v| v["data"]["state"] == "snapshot",
                            until,
                            &mut seen,
                        )?
                        .is_some()
                    {
                        snapshots += 1;
                    }
                }
                c.call(
                    "POST /train stop",
                    "POST",
                    &format!("/api/sessions/{s}/train"),
                    Some(&json!({"action": "stop"})),
                );
                // Until the server reports it stopped (the checkpoint is saved then).
                let stop_by = Instant::now() + Duration::from_secs(60);
                if ev
                    .wait_for(
                        "training",
                        |v| {
                            ["stopped", "finished", "failed", "model_saved"]
                                .iter()
                                .any(|x| v["data"]["state"] == *x)
                        },
                        stop_by,
                        &mut seen,
                    )?
                    .is_some()
                {
                    stops += 1;
                }
                let t = Instant::now();
                while t.elapsed() < Duration::from_secs(30) {
                    let (_, v) = c.json("GET /server", "GET", "/api/server", None);
                    if v["trainings"] == 0 {
                        break;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
                // Looking at the result before training again.
                pause(&mut rng, 10000, 20000, deadline);
            }
            extra.insert("rounds".into(), json!(rounds));
            extra.insert("previews_ok".into(), json!(previews));
            extra.insert("snapshots".into(), json!(snapshots));
            extra.insert("stops_confirmed".into(), json!(stops));
            extra.insert("events".into(), json!(seen));
        }
        "streamer" => {
            let mut seen = BTreeMap::new();
            let mut streams = 0u64;
            while Instant::now() < deadline {
                let t = Instant::now();
                match EventStream::open(addr, Some(s)) {
                    Ok((mut ev, st)) => {
                        c.rec.add(
                            "GET /events (headers)",
                            t.elapsed().as_secs_f64() * 1e3,
                            st,
                            "",
                        );
                        streams += 1;
                        let until = (Instant::now()
                            + Duration::from_millis(2000 + rng.below(6000) as u64))
                        .min(deadline);
                        while let Some((k, _)) = ev.next(until)? {
                            *seen.entry(k).or_insert(0u64) += 1;
                        }
                    }
                    Err(e) => c.rec.add(
                        "GET /events (headers)",
                        t.elapsed().as_secs_f64() * 1e3,
                        0,
                        &e.to_string(),
                    ),
                }
            }
            extra.insert("streams".into(), json!(streams));
            extra.insert("events".into(), json!(seen));
        }
        "sessions" => {
            let (mut opened, mut closed, mut at_limit, mut classified) = (0u64, 0u64, 0u64, 0u64);
            let slices: Vec<usize> = (0..dims[2]).collect();
            while Instant::now() + Duration::from_secs(10) < deadline {
                // Open until the limit answers.
                let mut mine = Vec::new();
                for _ in 0..8 {
                    let (st, v) = c.json(
                        "POST /sessions",
                        "POST",
                        "/api/sessions",
                        Some(&json!({"volume": volume})),
                    );
                    match (st, v["id"].as_str()) {
                        (201, Some(id)) => {
                            opened += 1;
                            mine.push(id.to_string());
                        }
                        (503, _) => {
                            at_limit += 1;
                            break;
                        }
                        _ => break,
                    }
                }
                // The first is drawn on and classified (sessions share the classifier, so
                // one per cycle); every one renders.
                for (i, id) in mine.iter().enumerate() {
                    if Instant::now() >= deadline {
                        break;
                    }
                    if i > 0 {
                        c.call(
                            "GET /render",
                            "GET",
                            &format!("/api/sessions/{id}/render?size=96"),
                            None,
                        );
                        continue;
                    }
                    let strokes: Vec<Stroke> = (0..4)
                        .map(|i| {
                            let mut st = random_stroke(&mut rng, &dims, &slices);
                            st.class = [1, 255, 2, 3][i];
                            st
                        })
                        .collect();
                    let (st, _) = c.call(
                        "PUT /strokes",
                        "PUT",
                        &format!("/api/sessions/{id}/strokes"),
                        Some(&serde_json::to_value(&strokes)?),
                    );
                    let left = deadline.saturating_duration_since(Instant::now());
                    if st == 202 && c.converged(id, left.min(Duration::from_secs(30))).is_some() {
                        classified += 1;
                    }
                    c.call(
                        "GET /render",
                        "GET",
                        &format!("/api/sessions/{id}/render?size=96"),
                        None,
                    );
                }
                for id in &mine {
                    let (st, _) = c.call(
                        "DELETE /sessions/{id}",
                        "DELETE",
                        &format!("/api/sessions/{id}"),
                        None,
                    );
                    if st == 204 {
                        closed += 1;
                    }
                }
                pause(&mut rng, 15000, 25000, deadline);
            }
            extra.insert("opened".into(), json!(opened));
            extra.insert("closed".into(), json!(closed));
            extra.insert("limit_answers".into(), json!(at_limit));
            extra.insert("classified".into(), json!(classified));
        }
        other => bail!("unknown role '{other}'"),
    }
    let report = json!({
        "role": role,
        "rec": c.rec.to_json(),
        "acked": acked,
        "extra": extra,
    });
    std::fs::write(&out, serde_json::to_vec(&report)?)
        .with_context(|| format!("{}", out.display()))?;
    Ok(())
}

// ---------------------------------------------------------------- coordinator side

struct Server {
    child: Child,
    addr: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server(
    bin: &Path,
    data: &Path,
    work: &Path,
    max_sessions: usize,
    log: Option<&Path>,
) -> Result<Server> {
    let stderr = match log {
        Some(p) => Stdio::from(
            std::fs::File::create(p).with_context(|| format!("--server-log {}", p.display()))?,
        ),
        None => Stdio::null(),
    };
    let mut child = Command::new(bin)
        .args(["serve", "--port", "0", "--max-sessions"])
        .arg(max_sessions.to_string())
        .args([
            "--cache-mib",
            "256",
            "--render-cache-mib",
            "256",
            "--probs-mib",
            "512",
            "--request-timeout",
            "30",
            "--backend",
            "cpu",
            "--data-root",
        ])
        .arg(data)
        .arg("--work")
        .arg(work)
        .stdout(Stdio::piped())
        .stderr(stderr)
        .spawn()
        .with_context(|| format!("starting {}", bin.display()))?;
    let mut out = BufReader::new(child.stdout.take().context("server stdout")?);
    let mut line = String::new();
    out.read_line(&mut line)?;
    let addr = line
        .split_whitespace()
        .find_map(|w| w.strip_prefix("http://"))
        .and_then(|w| w.split('/').next())
        .with_context(|| format!("no URL in '{line}'"))?
        .to_string();
    std::thread::spawn(move || {
        let mut sink = Vec::new();
        let _ = out.read_to_end(&mut sink);
    });
    Ok(Server { child, addr })
}

/// Resident and peak resident memory of a process, MiB (`VmRSS`, `VmHWM`).
fn rss_mib(pid: u32) -> (f64, f64) {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let get = |k: &str| {
        s.lines()
            .find(|l| l.starts_with(k))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    };
    (get("VmRSS:"), get("VmHWM:"))
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// The RSS curve summarised: start (median of the first 5 % of samples), min, max, end
/// (median of the last 5 %), the 90th percentile of each third, and whether it plateaus (the
/// last third's 90th percentile within 10 % of the middle third's).
fn rss_summary(curve: &[(f64, f64)]) -> Value {
    if curve.len() < 3 {
        return Value::Null;
    }
    let pct = |xs: &[(f64, f64)], p: f64| {
        let mut v: Vec<f64> = xs.iter().map(|x| x.1).collect();
        v.sort_by(f64::total_cmp);
        percentile(&v, p)
    };
    let n = curve.len();
    let k = (n / 20).max(1);
    let third = n / 3;
    let thirds = [
        pct(&curve[..third], 0.9),
        pct(&curve[third..2 * third], 0.9),
        pct(&curve[2 * third..], 0.9),
    ];
    // Eleven points of the curve, for the report.
    let points: Vec<Value> = (0..=10)
        .map(|i| {
            let (t, r) = curve[(i * (n - 1)) / 10];
            json!([(t * 10.0).round() / 10.0, r.round()])
        })
        .collect();
    json!({
        "start": pct(&curve[..k], 0.5),
        "min": curve.iter().map(|x| x.1).fold(f64::INFINITY, f64::min),
        "max": curve.iter().map(|x| x.1).fold(0.0, f64::max),
        "end": pct(&curve[n - k..], 0.5),
        "p90_thirds": thirds,
        "plateaus": thirds[2] <= thirds[1] * 1.10,
        "samples": n,
        "curve_s_mib": points,
    })
}

/// The coordinator's own event stream, open for the whole run: every event with the time it
/// arrived, read on a thread until the stream ends or `stop` is set.
fn watch(addr: &str, session: &str, stop: Arc<AtomicBool>) -> Result<WatchHandle> {
    let (mut ev, st) = EventStream::open(addr, Some(session))?;
    anyhow::ensure!(st == 200, "GET /api/events: {st}");
    let events = Arc::new(Mutex::new(Vec::<(f64, String, Value)>::new()));
    let (ev2, t0) = (events.clone(), Instant::now());
    let ended = Arc::new(Mutex::new(None::<f64>));
    let ended2 = ended.clone();
    let thread = std::thread::spawn(move || {
        while !stop.load(Ordering::SeqCst) {
            let until = Instant::now() + Duration::from_millis(500);
            match ev.next(until) {
                Ok(Some((k, v))) => ev2.lock().unwrap_or_else(|p| p.into_inner()).push((
                    t0.elapsed().as_secs_f64(),
                    k,
                    v,
                )),
                Ok(None) if ev.ended => {
                    *ended2.lock().unwrap_or_else(|p| p.into_inner()) =
                        Some(t0.elapsed().as_secs_f64());
                    return;
                }
                Ok(None) => {}
                Err(_) => return,
            }
        }
    });
    Ok(WatchHandle {
        events,
        ended,
        thread,
        t0,
    })
}

struct WatchHandle {
    events: Arc<Mutex<Vec<(f64, String, Value)>>>,
    ended: Arc<Mutex<Option<f64>>>,
    thread: std::thread::JoinHandle<()>,
    t0: Instant,
}

/// Reads a NIfTI answer's voxels.
fn nifti_voxels(bytes: &[u8], dir: &Path, name: &str) -> Result<Vec<u8>> {
    let p = dir.join(name);
    std::fs::write(&p, bytes)?;
    let mut src = neuvolex_bricks::open_volume(&p, None)?;
    Ok(neuvolex_formats::MemVolume::read_all(src.as_mut())?.bytes)
}

/// The final exports, checked against the final state and each other.
fn final_exports(c: &mut Client, sid: &str, store: &Path, dir: &Path) -> Result<Value> {
    let before = c
        .converged(sid, Duration::from_secs(120))
        .context("the last classification never finished")?;
    let (st, labels) = c.call(
        "GET /export/labels.nii.gz",
        "GET",
        &format!("/api/sessions/{sid}/export/labels.nii.gz"),
        None,
    );
    anyhow::ensure!(st == 200, "final labels export: {st}");
    let labels = nifti_voxels(&labels, dir, "labels.nii.gz")?;
    let (st, z) = c.json(
        "POST /export/zarr",
        "POST",
        &format!("/api/sessions/{sid}/export/zarr"),
        Some(&json!({"name": "final"})),
    );
    anyhow::ensure!(st == 200, "final OME-Zarr export: {st} {z}");
    let ids: Vec<u32> = z["classes"]
        .as_array()
        .context("export lists no classes")?
        .iter()
        .filter_map(|v| v.as_u64().map(|v| v as u32))
        .collect();
    let store = neuvolex_bricks::BrickStore::open(store)?;
    let dims = store.info().dims;
    // NIfTI labels = the OME-Zarr label image.
    let zl = store.read_labels_box("final", [0, 0, 0], dims)?;
    anyhow::ensure!(zl.len() == labels.len(), "label volumes differ in size");
    let label_diff = zl
        .iter()
        .zip(&labels)
        .filter(|(a, b)| **a != **b as u32)
        .count();
    let allowed: Vec<u32> = ids.iter().copied().chain([0]).collect();
    let foreign = labels
        .iter()
        .filter(|&&l| !allowed.contains(&(l as u32)) && l != 255)
        .count();
    // Each class's NIfTI probability = its channel of the exported probability array.
    let va = store.open_vectors("final_proba")?;
    let ch = va.info().channels;
    let mut probs = vec![0u8; labels.len() * ch];
    for b in store.bricks() {
        let v = va.read_brick(&b)?;
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                for x in 0..b.size[0] {
                    let i = (z * b.size[1] + y) * b.size[0] + x;
                    let g =
                        ((b.origin[2] + z) * dims[1] + b.origin[1] + y) * dims[0] + b.origin[0] + x;
                    for k in 0..ch {
                        probs[g * ch + k] = (v[i * ch + k] * 255.0).round() as u8;
                    }
                }
            }
        }
    }
    let mut prob_diff = BTreeMap::new();
    for (k, id) in ids.iter().enumerate() {
        let (st, p) = c.call(
            "GET /export/probability",
            "GET",
            &format!("/api/sessions/{sid}/export/probability/{id}.nii.gz"),
            None,
        );
        anyhow::ensure!(st == 200, "final probability export of class {id}: {st}");
        let p = nifti_voxels(&p, dir, &format!("p{id}.nii.gz"))?;
        let d = p
            .iter()
            .enumerate()
            .filter(|(g, v)| **v != probs[g * ch + k])
            .count();
        prob_diff.insert(id.to_string(), d);
    }
    let after = c
        .converged(sid, Duration::from_secs(10))
        .context("the session changed during the final exports")?;
    let unchanged = before["generation"] == after["generation"];
    let ok = label_diff == 0 && foreign == 0 && unchanged && prob_diff.values().all(|&d| d == 0);
    Ok(json!({
        "ok": ok, "generation": after["generation"], "classes": ids,
        "label_voxels_differing": label_diff, "foreign_labels": foreign,
        "probability_voxels_differing": prob_diff, "unchanged_during_exports": unchanged,
        "labelled_voxels": labels.iter().filter(|&&l| l != 0).count(),
    }))
}

fn coordinator(o: &Opts) -> Result<()> {
    let seconds: f64 = o.num("seconds", 600.0)?;
    let drawers: usize = o.num("drawers", 2)?;
    let size: usize = o.num("size", 64)?;
    let max_rss: f64 = o.num("max-rss-mib", 3072.0)?;
    let max_timeouts: u64 = o.num("max-timeouts", 0)?;
    let max_sessions: usize = o.num("max-sessions", 4)?;
    anyhow::ensure!(max_sessions >= 2, "--max-sessions must be at least 2");
    let me = std::env::current_exe()?;
    let bin = match o.get("neuvolex") {
        Some(p) => PathBuf::from(p),
        None => me.with_file_name("neuvolex"),
    };
    anyhow::ensure!(
        bin.exists(),
        "{}: no neuvolex binary (build it: cargo build --release -p neuvolex)",
        bin.display()
    );
    let tmp = tempfile::tempdir()?;
    let (data, volume) = match (o.get("data-root"), o.get("volume")) {
        (Some(d), Some(v)) => (PathBuf::from(d), v.to_string()),
        _ => {
            let d = tmp.path().join("data");
            std::fs::create_dir_all(&d)?;
            let st = Command::new(&bin)
                .args([
                    "synth",
                    "phantom",
                    "--size",
                    &size.to_string(),
                    "--brick",
                    "16",
                    "--quiet",
                    "--out",
                ])
                .arg(d.join("phantom.zarr"))
                .status()?;
            anyhow::ensure!(st.success(), "generating the phantom failed");
            (d, "phantom.zarr".to_string())
        }
    };
    let work = tmp.path().join("work");
    std::fs::create_dir_all(&work)?;
    let srv = start_server(
        &bin,
        &data,
        &work,
        max_sessions,
        o.get("server-log").map(Path::new),
    )?;
    let pid = srv.child.id();
    let mut c = Client::new(&srv.addr);
    let (st, info) = c.json(
        "POST /sessions",
        "POST",
        "/api/sessions",
        Some(&json!({"volume": volume})),
    );
    anyhow::ensure!(st == 201, "opening {volume}: {st} {info}");
    let sid = info["id"].as_str().context("session id")?.to_string();
    let classes: Vec<Value> = (1..=3)
        .map(|id| json!({"id": id, "name": format!("class {id}"), "color": [60 * id, 200, 255 - 60 * id]}))
        .collect();
    let (st, _) = c.call(
        "PUT /classes",
        "PUT",
        &format!("/api/sessions/{sid}/classes"),
        Some(&Value::Array(classes)),
    );
    anyhow::ensure!(st == 200, "setting classes: {st}");
    let stop_watch = Arc::new(AtomicBool::new(false));
    let watcher = watch(&srv.addr, &sid, stop_watch.clone())?;
    eprintln!(
        "soak: {} for {seconds} s on {volume} {:?} at {} (pid {pid}), {drawers} drawers + viewer, renderer, editor, trainer, streamer, sessions (limit {max_sessions})",
        bin.display(),
        info["dims"],
        srv.addr
    );
    let mut roles: Vec<(String, usize)> = (0..drawers).map(|k| ("drawer".to_string(), k)).collect();
    for r in [
        "viewer", "renderer", "editor", "trainer", "streamer", "sessions",
    ] {
        roles.push((r.to_string(), 0));
    }
    let started = Instant::now();
    let t0 = unix_ms();
    let mut kids = Vec::new();
    for (i, (role, k)) in roles.iter().enumerate() {
        let out = tmp.path().join(format!("{role}-{k}.json"));
        let child = Command::new(&me)
            .args([
                "worker",
                "--role",
                role,
                "--addr",
                &srv.addr,
                "--session",
                &sid,
                "--volume",
                &volume,
            ])
            .args([
                "--seconds",
                &seconds.to_string(),
                "--seed",
                &(i as u64 + 1).to_string(),
                "--t0",
                &t0.to_string(),
            ])
            .args(["--index", &k.to_string(), "--drawers", &drawers.to_string()])
            .arg("--out")
            .arg(&out)
            .spawn()?;
        kids.push((role.clone(), *k, child, out));
    }
    // Sample the server's memory while the workers run.
    let mut curve: Vec<(f64, f64)> = Vec::new();
    let mut budget_curve: Vec<(f64, f64)> = Vec::new();
    let mut memory_report = Value::Null;
    let mut over_budget = 0u64;
    let mut last_status = Instant::now() - Duration::from_secs(10);
    let mut probe = Client::new(&srv.addr);
    loop {
        let done = kids
            .iter_mut()
            .all(|k| matches!(k.2.try_wait(), Ok(Some(_))));
        let (rss, _) = rss_mib(pid);
        let t = started.elapsed().as_secs_f64();
        curve.push((t, rss));
        if last_status.elapsed() >= Duration::from_secs(1) {
            last_status = Instant::now();
            let (_, v) = probe.json("GET /server", "GET", "/api/server", None);
            let m = &v["memory"];
            if let (Some(u), Some(b)) = (m["used"].as_f64(), m["budget"].as_f64()) {
                budget_curve.push((t, u / f64::from(1 << 20)));
                if u > b {
                    over_budget += 1;
                }
                memory_report = m.clone();
            }
        }
        if done {
            break;
        }
        if started.elapsed().as_secs_f64() > seconds + 600.0 {
            bail!("workers still running 600 s after the end");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let ran = started.elapsed().as_secs_f64();
    // Merge the workers' records.
    let mut ms: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut status: BTreeMap<String, BTreeMap<u16, u64>> = BTreeMap::new();
    let mut busy: BTreeMap<String, u64> = BTreeMap::new();
    let (mut unexpected, mut timeouts) = (0u64, 0u64);
    let mut unexpected_samples = Vec::new();
    let mut acked: Vec<(Stroke, u64)> = Vec::new();
    let mut roles_extra = serde_json::Map::new();
    for (role, k, mut child, out) in kids {
        let st = child.wait()?;
        anyhow::ensure!(st.success(), "worker {role} {k} failed: {st}");
        let v: Value = serde_json::from_slice(&std::fs::read(&out)?)?;
        let rec = &v["rec"];
        for (route, xs) in rec["ms"].as_object().into_iter().flatten() {
            ms.entry(route.clone()).or_default().extend(
                xs.as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(Value::as_f64),
            );
        }
        for (route, codes) in rec["status"].as_object().into_iter().flatten() {
            for (code, n) in codes.as_object().into_iter().flatten() {
                *status
                    .entry(route.clone())
                    .or_default()
                    .entry(code.parse().unwrap_or(0))
                    .or_insert(0) += n.as_u64().unwrap_or(0);
            }
        }
        for (r, n) in rec["busy"].as_object().into_iter().flatten() {
            *busy.entry(r.clone()).or_insert(0) += n.as_u64().unwrap_or(0);
        }
        unexpected += rec["unexpected"].as_u64().unwrap_or(0);
        timeouts += rec["timeouts"].as_u64().unwrap_or(0);
        for x in rec["samples"].as_array().into_iter().flatten() {
            unexpected_samples.push(format!("{role} {k}: {}", x.as_str().unwrap_or("")));
        }
        if role == "drawer" {
            let a: Vec<(Stroke, u64)> = serde_json::from_value(v["acked"].clone())?;
            acked.extend(a);
        }
        roles_extra.insert(format!("{role}-{k}"), v["extra"].clone());
    }
    // Every acknowledged stroke is held, and the scribble volume is exactly their union.
    let strokes_only: Vec<Stroke> = acked.iter().map(|a| a.0.clone()).collect();
    let (_, held) = c.json(
        "GET /strokes",
        "GET",
        &format!("/api/sessions/{sid}/strokes"),
        None,
    );
    let held = held.as_array().map_or(0, Vec::len);
    let (st, nii) = c.call(
        "GET /export/scribbles.nii.gz",
        "GET",
        &format!("/api/sessions/{sid}/export/scribbles.nii.gz"),
        None,
    );
    anyhow::ensure!(st == 200, "scribble export: {st}");
    let scribbles = nifti_voxels(&nii, tmp.path(), "scribbles.nii.gz")?;
    let painted: Vec<(u64, u32)> = scribbles
        .iter()
        .enumerate()
        .filter(|(_, &v)| v != 0)
        .map(|(i, &v)| (i as u64, v as u32))
        .collect();
    let dims3: [usize; 3] = info["dims"]
        .as_array()
        .and_then(|a| {
            let v: Vec<usize> = a
                .iter()
                .filter_map(|x| x.as_u64().map(|x| x as usize))
                .collect();
            v.try_into().ok()
        })
        .context("dims")?;
    let want = rasterise(&strokes_only, dims3)?.voxels;
    let strokes_ok = held == acked.len() && painted == want;
    // The final state converges, and the final exports agree with it.
    let t = Instant::now();
    let finals = final_exports(&mut c, &sid, &data.join(&volume), tmp.path())?;
    let converged_s = t.elapsed().as_secs_f64();
    let (_, hwm) = rss_mib(pid);
    // A clean stop.
    let t = Instant::now();
    let _ = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status();
    let mut srv = srv;
    let mut stop_s = f64::NAN;
    while t.elapsed() < Duration::from_secs(30) {
        if let Ok(Some(_)) = srv.child.try_wait() {
            stop_s = t.elapsed().as_secs_f64();
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let term_at = watcher.t0.elapsed().as_secs_f64() - t.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_millis(300));
    stop_watch.store(true, Ordering::SeqCst);
    let _ = watcher.thread.join();
    let events = std::mem::take(&mut *watcher.events.lock().unwrap_or_else(|p| p.into_inner()));
    let stream_ended = *watcher.ended.lock().unwrap_or_else(|p| p.into_inner());
    // Events: counted by kind, and checked against the acknowledged strokes.
    let mut by_kind: BTreeMap<String, u64> = BTreeMap::new();
    let mut done_gens: Vec<u64> = Vec::new();
    for (_, k, v) in &events {
        *by_kind.entry(k.clone()).or_insert(0) += 1;
        if k == "classification" && v["data"]["status"]["state"] == "done" {
            if let Some(g) = v["data"]["status"]["generation"].as_u64() {
                done_gens.push(g);
            }
        }
    }
    let newest_done = done_gens.iter().copied().max().unwrap_or(0);
    let unclassified = acked.iter().filter(|(_, g)| *g > newest_done).count();
    let shutdown_event = events
        .iter()
        .any(|(t, k, _)| k == "shutdown" && *t >= term_at - 0.5);
    let events_ok = unclassified == 0
        && shutdown_event
        && stream_ended.is_some()
        && by_kind.get("lagged").copied().unwrap_or(0) == 0;
    // The report.
    let mut rows = Vec::new();
    let mut requests = 0u64;
    println!("| route | requests | p50 ms | p99 ms | max ms | statuses |");
    println!("|---|---|---|---|---|---|");
    // The coordinator's own requests count too.
    for (route, xs) in &c.rec.ms {
        ms.entry(route.clone()).or_default().extend(xs);
    }
    let mut all_status = status.clone();
    for (route, codes) in &c.rec.status {
        for (code, n) in codes {
            *all_status
                .entry(route.clone())
                .or_default()
                .entry(*code)
                .or_insert(0) += n;
        }
    }
    let routes: std::collections::BTreeSet<&String> = ms.keys().chain(all_status.keys()).collect();
    for route in routes {
        let mut xs = ms.get(route).cloned().unwrap_or_default();
        xs.sort_by(f64::total_cmp);
        let codes = all_status.get(route).cloned().unwrap_or_default();
        requests += codes.values().sum::<u64>();
        let codes_s: Vec<String> = codes.iter().map(|(c, n)| format!("{c}: {n}")).collect();
        println!(
            "| {route} | {} | {:.1} | {:.1} | {:.1} | {} |",
            codes.values().sum::<u64>(),
            percentile(&xs, 0.5),
            percentile(&xs, 0.99),
            xs.last().copied().unwrap_or(f64::NAN),
            codes_s.join(", ")
        );
        rows.push(
            json!({"route": route, "requests": codes.values().sum::<u64>(), "p50_ms": percentile(&xs, 0.5),
            "p99_ms": percentile(&xs, 0.99), "max_ms": xs.last(), "statuses": codes}),
        );
    }
    unexpected += c.rec.unexpected;
    unexpected_samples.extend(c.rec.samples.iter().cloned());
    let rss = rss_summary(&curve);
    let editor = &roles_extra["editor-0"];
    let exports_ok: BTreeMap<String, u64> = EXPORTS
        .iter()
        .map(|e| {
            (
                e.to_string(),
                editor["exports_ok"][*e].as_u64().unwrap_or(0),
            )
        })
        .collect();
    let every_export = exports_ok.values().all(|&n| n > 0);
    let trainer = &roles_extra["trainer-0"];
    let previews = trainer["previews_ok"].as_u64().unwrap_or(0);
    let snapshots = trainer["snapshots"].as_u64().unwrap_or(0);
    let sess = &roles_extra["sessions-0"];
    let sessions_ok = sess["opened"].as_u64().unwrap_or(0) > 0
        && sess["closed"] == sess["opened"]
        && sess["limit_answers"].as_u64().unwrap_or(0) > 0;
    println!();
    println!("503s by reason: {busy:?}");
    println!("events (coordinator's stream): {by_kind:?}");
    println!(
        "roles: {}",
        serde_json::to_string(&roles_extra).unwrap_or_default()
    );
    println!(
        "RSS MiB: start {:.0}, min {:.0}, max {:.0}, end {:.0}; 90th percentile of each third {}: {}; curve (s, MiB) {}",
        rss["start"].as_f64().unwrap_or(0.0),
        rss["min"].as_f64().unwrap_or(0.0),
        rss["max"].as_f64().unwrap_or(0.0),
        rss["end"].as_f64().unwrap_or(0.0),
        rss["p90_thirds"],
        if rss["plateaus"] == true { "plateaus" } else { "still growing" },
        rss["curve_s_mib"]
    );
    println!("session memory (last /api/server report): {memory_report}");
    println!("final exports: {finals}");
    println!(
        "soak: {ran:.0} s, {requests} requests, {unexpected} unexpected answers, {timeouts} request timeouts, \
         {} documented 503s; server RSS max {:.0} MiB, VmHWM {hwm:.0} MiB; strokes acknowledged {}, held {held}, \
         scribble voxels {} (expected {}): {}; {} acknowledged stroke(s) without a finished classification event; \
         exports ok {exports_ok:?}; trainer: {previews} preview(s) 200, {snapshots} snapshot(s); \
         final state converged {converged_s:.1} s after the load; SIGTERM stop {stop_s:.2} s, shutdown event {}",
        busy.values().sum::<u64>() - timeouts,
        rss["max"].as_f64().unwrap_or(0.0),
        acked.len(),
        painted.len(),
        want.len(),
        if strokes_ok { "none lost" } else { "MISMATCH" },
        unclassified,
        if shutdown_event { "received" } else { "MISSING" },
    );
    for s in unexpected_samples.iter().take(20) {
        println!("unexpected: {s}");
    }
    let peak = rss["max"].as_f64().unwrap_or(0.0).max(hwm);
    let report = json!({
        "seconds": ran, "volume": volume, "dims": info["dims"], "drawers": drawers,
        "requests": requests, "unexpected_errors": unexpected, "request_timeouts": timeouts,
        "busy_503": busy, "rss_mib": rss, "vmhwm_mib": hwm,
        "memory_report": memory_report, "memory_over_budget_samples": over_budget,
        "memory_used_curve_mib": budget_curve.iter().step_by((budget_curve.len() / 10).max(1)).map(|(t, u)| json!([t.round(), u.round()])).collect::<Vec<_>>(),
        "strokes_acknowledged": acked.len(), "strokes_held": held,
        "scribble_voxels": painted.len(), "expected_voxels": want.len(), "strokes_ok": strokes_ok,
        "events": by_kind, "unclassified_strokes": unclassified, "shutdown_event": shutdown_event,
        "events_ok": events_ok, "exports_ok": exports_ok, "every_export_ok": every_export,
        "previews_ok": previews, "snapshots": snapshots, "sessions_ok": sessions_ok,
        "final_exports": finals, "converged_s": converged_s, "sigterm_stop_s": stop_s,
        "routes": rows, "roles": roles_extra, "unexpected_samples": unexpected_samples,
    });
    if let Some(out) = o.get("out") {
        std::fs::write(out, serde_json::to_vec_pretty(&report)?)?;
    }
    anyhow::ensure!(unexpected == 0, "{unexpected} unexpected answer(s)");
    anyhow::ensure!(
        timeouts <= max_timeouts,
        "{timeouts} request(s) timed out (at most {max_timeouts} allowed)"
    );
    anyhow::ensure!(strokes_ok, "strokes lost or the scribble volume differs");
    anyhow::ensure!(!acked.is_empty(), "no stroke was acknowledged");
    anyhow::ensure!(
        events_ok,
        "events: {unclassified} stroke(s) without a finished classification, shutdown event {shutdown_event}, stream ended {stream_ended:?}, lagged {:?}",
        by_kind.get("lagged")
    );
    anyhow::ensure!(
        every_export,
        "not every export kind succeeded: {exports_ok:?}"
    );
    anyhow::ensure!(
        finals["ok"] == true,
        "the final exports disagree with the final state: {finals}"
    );
    anyhow::ensure!(
        previews > 0 && snapshots > 0,
        "the trainer got {previews} preview(s) and {snapshots} snapshot(s)"
    );
    anyhow::ensure!(sessions_ok, "the sessions role: {sess}");
    anyhow::ensure!(
        over_budget == 0,
        "the server's session memory passed its budget in {over_budget} report(s)"
    );
    anyhow::ensure!(
        peak <= max_rss,
        "server peak RSS {peak:.0} MiB above --max-rss-mib {max_rss}"
    );
    anyhow::ensure!(stop_s < 2.0, "SIGTERM took {stop_s:.2} s");
    Ok(())
}
