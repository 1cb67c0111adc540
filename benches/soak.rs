//! The soak test: a real `neuvolex serve` process driven over HTTP on loopback by several
//! worker processes at once, for a fixed time:
//!
//! - `drawer` (two by default): append strokes to the shared session (each on its own slices),
//!   keeping every acknowledged one;
//! - `viewer`: slices, overlays, class fractions, session info;
//! - `renderer`: 3-D frames at random views and sizes, and transfer-function edits;
//! - `editor`: class edits (rename, recolour), session files, NIfTI and OME-Zarr exports;
//! - `trainer`: INR training started, left running a few seconds, stopped, resumed;
//! - `streamer`: Server-Sent Events streams opened, read and dropped.
//!
//! At the end it reports p50/p99 latency per route, the status counts, the server's peak RSS
//! (sampled every 100 ms, and `VmHWM`), and checks that not one stroke is lost: the server's
//! scribble volume (`export/scribbles.nii.gz`) equals the rasterisation of every acknowledged
//! stroke. It fails on any error other than the documented ones (503 busy or timed out, 409 for
//! an export before classification finished), a lost stroke, or RSS above `--max-rss-mib`.
//!
//! ```text
//! cargo build --release -p neuvolex -p neuvolex-benches --bin soak
//! target/release/soak --seconds 600 --out soak.json
//! ```
//!
//! Options: `--seconds N` (600), `--drawers N` (2), `--size N` (phantom edge, 64), `--data-root
//! DIR --volume REL` (a real volume instead of the phantom), `--neuvolex PATH` (default: beside
//! this binary), `--max-rss-mib N` (3072), `--out FILE` (JSON report).

use anyhow::{bail, Context, Result};
use neuvolex_bricks::rng::Rng;
use neuvolex_classify::scribble::{rasterise, Stroke};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

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

// ---------------------------------------------------------------- worker side

/// Latencies (ms) and status counts per route.
#[derive(Default)]
struct Record {
    ms: BTreeMap<String, Vec<f64>>,
    status: BTreeMap<String, BTreeMap<u16, u64>>,
    /// Bodies of unexpected answers (at most a few per route), for the report.
    samples: BTreeMap<String, Vec<String>>,
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
        if !expected(route, status) {
            let v = self.samples.entry(route.into()).or_default();
            if v.len() < 3 {
                v.push(format!(
                    "{status}: {}",
                    body.chars().take(300).collect::<String>()
                ));
            }
        }
    }
}

/// The answers the API documents for load: success, 503 (a full mailbox, a limit, the request
/// timeout), 409 for exports asked before classification reached every brick and for training
/// commands that race with a stop, and 404 for the training preview before a training has drawn
/// its first one ("no training preview yet").
fn expected(route: &str, status: u16) -> bool {
    (200..300).contains(&status)
        || status == 503
        || (status == 409 && (route.contains("export") || route.contains("train")))
        || (status == 404 && route == "GET /preview.png")
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
}

fn worker(o: &Opts) -> Result<()> {
    let addr = o.get("addr").context("--addr")?;
    let session = o.get("session").context("--session")?.to_string();
    let role = o.get("role").context("--role")?;
    let seconds: f64 = o.num("seconds", 60.0)?;
    let seed: u64 = o.num("seed", 1)?;
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
    let mut acked: Vec<Stroke> = Vec::new();
    let pause = |rng: &mut Rng, lo: u64, hi: u64| {
        std::thread::sleep(Duration::from_millis(
            lo + rng.below((hi - lo) as usize) as u64,
        ))
    };
    let s = &session;
    match role {
        "drawer" => {
            let k: usize = o.num("index", 0)?;
            let n: usize = o.num("drawers", 1)?;
            let slices: Vec<usize> = (0..dims[2]).filter(|z| z % n == k).collect();
            while Instant::now() < deadline {
                let class = [1, 2, 3, 255][rng.below(4)];
                let pts = 2 + rng.below(3);
                let stroke = Stroke {
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
                };
                let body = serde_json::to_value([&stroke])?;
                let (st, _) = c.call(
                    "POST /strokes",
                    "POST",
                    &format!("/api/sessions/{s}/strokes"),
                    Some(&body),
                );
                if st == 202 {
                    acked.push(stroke);
                }
                pause(&mut rng, 20, 120);
            }
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
                pause(&mut rng, 10, 60);
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
                pause(&mut rng, 20, 100);
            }
        }
        "editor" => {
            let mut n = 0u32;
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
                match rng.below(5) {
                    0 => {
                        c.call(
                            "GET /export/labels.nii.gz",
                            "GET",
                            &format!("/api/sessions/{s}/export/labels.nii.gz"),
                            None,
                        );
                    }
                    1 => {
                        c.call(
                            "GET /export/probability",
                            "GET",
                            &format!("/api/sessions/{s}/export/probability/1.nii.gz"),
                            None,
                        );
                    }
                    2 => {
                        c.call(
                            "POST /export/zarr",
                            "POST",
                            &format!("/api/sessions/{s}/export/zarr"),
                            Some(&json!({"name": "soak"})),
                        );
                    }
                    3 => {
                        c.call(
                            "GET /export/scribbles.nii.gz",
                            "GET",
                            &format!("/api/sessions/{s}/export/scribbles.nii.gz"),
                            None,
                        );
                    }
                    _ => {
                        c.call(
                            "GET /strokes",
                            "GET",
                            &format!("/api/sessions/{s}/strokes"),
                            None,
                        );
                    }
                }
                pause(&mut rng, 200, 800);
            }
        }
        "trainer" => {
            let mut resume = false;
            while Instant::now() < deadline {
                let action = if resume { "resume" } else { "start" };
                c.call(
                    "POST /train start",
                    "POST",
                    &format!("/api/sessions/{s}/train"),
                    Some(&json!({"action": action, "epochs": 1000})),
                );
                resume = !resume;
                pause(&mut rng, 3000, 8000);
                c.call(
                    "POST /train stop",
                    "POST",
                    &format!("/api/sessions/{s}/train"),
                    Some(&json!({"action": "stop"})),
                );
                // Until the server reports it stopped.
                let t = Instant::now();
                while t.elapsed() < Duration::from_secs(60) {
                    let (_, v) = c.json("GET /server", "GET", "/api/server", None);
                    if v["trainings"] == 0 {
                        break;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
                c.call(
                    "GET /preview.png",
                    "GET",
                    &format!("/api/sessions/{s}/preview.png"),
                    None,
                );
            }
        }
        "streamer" => {
            while Instant::now() < deadline {
                let t = Instant::now();
                let r = c
                    .agent
                    .get(&format!("{}/api/events?session={s}", c.base))
                    .timeout(Duration::from_secs(30))
                    .call();
                match r {
                    Ok(resp) => {
                        c.rec.add(
                            "GET /events (headers)",
                            t.elapsed().as_secs_f64() * 1e3,
                            resp.status(),
                            "",
                        );
                        let mut lines = BufReader::new(resp.into_reader());
                        let until =
                            Instant::now() + Duration::from_millis(2000 + rng.below(6000) as u64);
                        let mut l = String::new();
                        let mut events = 0u64;
                        while Instant::now() < until.min(deadline) {
                            l.clear();
                            match lines.read_line(&mut l) {
                                Ok(0) | Err(_) => break,
                                Ok(_) if l.starts_with("event:") => events += 1,
                                Ok(_) => {}
                            }
                        }
                        *c.rec
                            .status
                            .entry("events received".into())
                            .or_default()
                            .entry(200)
                            .or_insert(0) += events;
                    }
                    Err(ureq::Error::Status(st, _)) => {
                        c.rec.add("GET /events (headers)", 0.0, st, "")
                    }
                    Err(e) => c.rec.add("GET /events (headers)", 0.0, 0, &e.to_string()),
                }
            }
        }
        other => bail!("unknown role '{other}'"),
    }
    let report = json!({
        "role": role,
        "ms": c.rec.ms,
        "status": c.rec.status.iter().map(|(k, v)| (k.clone(), v.iter().map(|(s, n)| (s.to_string(), *n)).collect::<BTreeMap<_, _>>())).collect::<BTreeMap<_, _>>(),
        "samples": c.rec.samples,
        "acked": acked,
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

fn start_server(bin: &Path, data: &Path, work: &Path) -> Result<Server> {
    let mut child = Command::new(bin)
        .args([
            "serve",
            "--port",
            "0",
            "--max-sessions",
            "8",
            "--cache-mib",
            "256",
            "--request-timeout",
            "30",
            "--data-root",
        ])
        .arg(data)
        .arg("--work")
        .arg(work)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
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

fn coordinator(o: &Opts) -> Result<()> {
    let seconds: f64 = o.num("seconds", 600.0)?;
    let drawers: usize = o.num("drawers", 2)?;
    let size: usize = o.num("size", 64)?;
    let max_rss: f64 = o.num("max-rss-mib", 3072.0)?;
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
    let srv = start_server(&bin, &data, &work)?;
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
    eprintln!(
        "soak: {} for {seconds} s on {volume} {:?} at {} (pid {pid}), {drawers} drawers + viewer, renderer, editor, trainer, streamer",
        bin.display(),
        info["dims"],
        srv.addr
    );
    let mut roles: Vec<(String, usize)> = (0..drawers).map(|k| ("drawer".to_string(), k)).collect();
    for r in ["viewer", "renderer", "editor", "trainer", "streamer"] {
        roles.push((r.to_string(), 0));
    }
    let started = Instant::now();
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
            ])
            .args([
                "--seconds",
                &seconds.to_string(),
                "--seed",
                &(i as u64 + 1).to_string(),
            ])
            .args(["--index", &k.to_string(), "--drawers", &drawers.to_string()])
            .arg("--out")
            .arg(&out)
            .spawn()?;
        kids.push((role.clone(), *k, child, out));
    }
    // Sample the server's memory while the workers run.
    let mut peak_rss: f64 = 0.0;
    let mut samples = 0u64;
    loop {
        let done = kids
            .iter_mut()
            .all(|k| matches!(k.2.try_wait(), Ok(Some(_))));
        let (rss, _) = rss_mib(pid);
        peak_rss = peak_rss.max(rss);
        samples += 1;
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
    let mut unexpected_samples = Vec::new();
    let mut acked: Vec<Stroke> = Vec::new();
    for (role, k, mut child, out) in kids {
        let st = child.wait()?;
        anyhow::ensure!(st.success(), "worker {role} {k} failed: {st}");
        let v: Value = serde_json::from_slice(&std::fs::read(&out)?)?;
        for (route, xs) in v["ms"].as_object().into_iter().flatten() {
            ms.entry(route.clone()).or_default().extend(
                xs.as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(Value::as_f64),
            );
        }
        for (route, codes) in v["status"].as_object().into_iter().flatten() {
            for (code, n) in codes.as_object().into_iter().flatten() {
                *status
                    .entry(route.clone())
                    .or_default()
                    .entry(code.parse().unwrap_or(0))
                    .or_insert(0) += n.as_u64().unwrap_or(0);
            }
        }
        for (route, xs) in v["samples"].as_object().into_iter().flatten() {
            for x in xs.as_array().into_iter().flatten() {
                unexpected_samples.push(format!("{route}: {}", x.as_str().unwrap_or("")));
            }
        }
        if role == "drawer" {
            let a: Vec<Stroke> = serde_json::from_value(v["acked"].clone())?;
            acked.extend(a);
        }
    }
    // Every acknowledged stroke is held, and the scribble volume is exactly their union.
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
    let p = tmp.path().join("scribbles.nii.gz");
    std::fs::write(&p, &nii)?;
    let mut src = neuvolex_bricks::open_volume(&p, None)?;
    let vol = neuvolex_bricks::MemVolume::read_all(src.as_mut())?;
    let painted: Vec<(u64, u32)> = vol
        .bytes
        .iter()
        .enumerate()
        .filter(|(_, &v)| v != 0)
        .map(|(i, &v)| (i as u64, v as u32))
        .collect();
    let want = rasterise(&acked, vol.meta.dims)?.voxels;
    let strokes_ok = held == acked.len() && painted == want;
    // The last classification converges.
    let t = Instant::now();
    let mut converged = None;
    while t.elapsed() < Duration::from_secs(300) {
        let (_, v) = c.json(
            "GET /sessions/{id}",
            "GET",
            &format!("/api/sessions/{sid}"),
            None,
        );
        let g = &v["generation"];
        if v["status"]["generation"] == *g && v["status"]["state"] == "done" {
            converged = Some(t.elapsed().as_secs_f64());
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
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
    // The report.
    let mut rows = Vec::new();
    let mut unexpected = 0u64;
    let mut busy = 0u64;
    let mut conflicts = 0u64;
    let mut requests = 0u64;
    println!("| route | requests | p50 ms | p99 ms | max ms | statuses |");
    println!("|---|---|---|---|---|---|");
    let routes: std::collections::BTreeSet<&String> = ms.keys().chain(status.keys()).collect();
    for route in routes {
        let mut xs = ms.get(route).cloned().unwrap_or_default();
        xs.sort_by(f64::total_cmp);
        let codes = status.get(route).cloned().unwrap_or_default();
        let counted = route != "events received";
        for (&code, &n) in &codes {
            if !counted {
                continue;
            }
            requests += n;
            if code == 503 {
                busy += n;
            } else if code == 409 && expected(route, code) {
                conflicts += n;
            } else if !expected(route, code) {
                unexpected += n;
            }
        }
        let codes_s: Vec<String> = codes.iter().map(|(c, n)| format!("{c}: {n}")).collect();
        println!(
            "| {route} | {} | {:.1} | {:.1} | {:.1} | {} |",
            xs.len(),
            percentile(&xs, 0.5),
            percentile(&xs, 0.99),
            xs.last().copied().unwrap_or(f64::NAN),
            codes_s.join(", ")
        );
        rows.push(
            json!({"route": route, "requests": xs.len(), "p50_ms": percentile(&xs, 0.5),
            "p99_ms": percentile(&xs, 0.99), "max_ms": xs.last(), "statuses": codes}),
        );
    }
    println!();
    println!(
        "soak: {ran:.0} s, {requests} requests, {unexpected} unexpected errors, {busy} documented 503s, \
         {conflicts} documented 409s; server peak RSS {peak_rss:.0} MiB sampled ({samples} samples), \
         VmHWM {hwm:.0} MiB; strokes acknowledged {}, held {held}, scribble voxels {} (expected {}): {}; \
         last classification converged {}; SIGTERM stop {stop_s:.2} s",
        acked.len(),
        painted.len(),
        want.len(),
        if strokes_ok { "none lost" } else { "MISMATCH" },
        converged.map_or("never".into(), |s| format!("{s:.1} s after the load"))
    );
    for s in unexpected_samples.iter().take(20) {
        println!("unexpected: {s}");
    }
    let report = json!({
        "seconds": ran, "volume": volume, "dims": info["dims"], "drawers": drawers,
        "requests": requests, "unexpected_errors": unexpected, "documented_503": busy,
        "documented_409": conflicts, "peak_rss_mib_sampled": peak_rss, "vmhwm_mib": hwm,
        "strokes_acknowledged": acked.len(), "strokes_held": held,
        "scribble_voxels": painted.len(), "expected_voxels": want.len(), "strokes_ok": strokes_ok,
        "converged_s": converged, "sigterm_stop_s": stop_s, "routes": rows,
        "unexpected_samples": unexpected_samples,
    });
    if let Some(out) = o.get("out") {
        std::fs::write(out, serde_json::to_vec_pretty(&report)?)?;
    }
    anyhow::ensure!(unexpected == 0, "{unexpected} unexpected error(s)");
    anyhow::ensure!(strokes_ok, "strokes lost or the scribble volume differs");
    anyhow::ensure!(!acked.is_empty(), "no stroke was acknowledged");
    anyhow::ensure!(
        converged.is_some(),
        "the last classification never finished"
    );
    anyhow::ensure!(
        hwm.max(peak_rss) <= max_rss,
        "server peak RSS {:.0} MiB above --max-rss-mib {max_rss}",
        hwm.max(peak_rss)
    );
    anyhow::ensure!(stop_s < 2.0, "SIGTERM took {stop_s:.2} s");
    Ok(())
}
