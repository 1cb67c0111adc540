//! The cluster: `neuvolex classify --cluster` on real NATS JetStream (Debian's nats-server)
//! with several `neuvolex worker` processes, against `neuvolex classify` in one process, and
//! the faults a cluster meets: a worker killed mid-task, a worker's link cut for longer than
//! AckWait (network namespaces), the NATS server restarted, the coordinator killed and re-run,
//! a poisoned brick, and unreachable or unauthorised servers. After every fault the result is
//! compared with the single-process result bit for bit.
//!
//! Without nats-server (or, for the link test, root and `ip netns`) the tests print SKIP; under
//! `CI=true` that is a failure.

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_neuvolex");

fn ci() -> bool {
    std::env::var("CI").map(|v| v == "true").unwrap_or(false)
}

fn skip(why: &str) -> bool {
    if ci() {
        panic!("required under CI=true: {why}");
    }
    eprintln!("SKIP: {why}");
    true
}

fn nats_server() -> Option<PathBuf> {
    for p in [
        "/usr/sbin/nats-server",
        "/usr/bin/nats-server",
        "/usr/local/bin/nats-server",
    ] {
        if Path::new(p).exists() {
            return Some(p.into());
        }
    }
    None
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .arg("--quiet")
        .env("RUST_LOG", "warn")
        .output()
        .expect("run neuvolex")
}

fn ok(args: &[&str]) -> String {
    let o = run(args);
    assert!(
        o.status.success(),
        "neuvolex {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A nats-server with JetStream on a store directory.
struct Nats {
    child: Option<Child>,
    bin: PathBuf,
    dir: PathBuf,
    host: String,
    port: u16,
    extra: Vec<String>,
}

impl Nats {
    fn start(dir: &Path, host: &str, extra: &[&str]) -> Option<Nats> {
        let Some(bin) = nats_server() else {
            skip("nats-server is not installed (deploy/test.sh installs it)");
            return None;
        };
        let mut n = Nats {
            child: None,
            bin,
            dir: dir.join("nats"),
            host: host.into(),
            port: free_port(),
            extra: extra.iter().map(|s| s.to_string()).collect(),
        };
        n.spawn();
        Some(n)
    }

    fn spawn(&mut self) {
        let child = Command::new(&self.bin)
            .args(["-js", "-sd"])
            .arg(&self.dir)
            .args(["-a", &self.host, "-p", &self.port.to_string()])
            .args(&self.extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start nats-server");
        self.child = Some(child);
        let t = Instant::now();
        while std::net::TcpStream::connect((self.host.as_str(), self.port)).is_err() {
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "nats-server did not start"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn url(&self) -> String {
        format!("nats://{}:{}", self.host, self.port)
    }

    fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A worker process; counts the tasks it started (from its log).
struct Worker {
    child: Child,
    started: Arc<AtomicUsize>,
}

impl Worker {
    fn spawn(prefix: &[&str], url: &str, name: &str, extra: &[&str]) -> Worker {
        let (cmd, pre) = match prefix.split_first() {
            Some((c, rest)) => (c.to_string(), rest.to_vec()),
            None => (BIN.to_string(), vec![]),
        };
        let mut c = Command::new(cmd);
        c.args(pre);
        if !prefix.is_empty() {
            c.arg(BIN);
        }
        let mut child = c
            .args([
                "worker",
                "--nats",
                url,
                "--name",
                name,
                "--threads",
                "1",
                "--quiet",
            ])
            .args(extra)
            .env("RUST_LOG", "neuvolex=info,warn")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start worker");
        let started = Arc::new(AtomicUsize::new(0));
        let s = started.clone();
        let err = child.stderr.take().expect("stderr");
        std::thread::spawn(move || {
            for l in BufReader::new(err).lines().map_while(Result::ok) {
                if l.contains("task started") {
                    s.fetch_add(1, Ordering::SeqCst);
                }
            }
        });
        Worker { child, started }
    }

    fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    fn wait_started(&self, n: usize, limit: Duration) {
        let t = Instant::now();
        while self.started.load(Ordering::SeqCst) < n {
            assert!(t.elapsed() < limit, "worker started no task in {limit:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// A phantom store with its scribbles, ready to classify; `copies` identical stores.
struct Scene {
    dir: tempfile::TempDir,
}

impl Scene {
    fn new() -> Scene {
        let dir = tempfile::tempdir().expect("tmp");
        let s = Scene { dir };
        ok(&[
            "synth",
            "phantom",
            "--out",
            &s.p("base.zarr"),
            "--size",
            "64",
            "--brick",
            "16",
        ]);
        ok(&[
            "scribble-sim",
            &format!("{}/labels/ground_truth", s.p("base.zarr")),
            "--level",
            "S2",
            "--out",
            &s.p("scr.nii.gz"),
        ]);
        s
    }

    fn p(&self, n: &str) -> String {
        self.dir.path().join(n).to_string_lossy().into_owned()
    }

    /// A fresh copy of the base store named `name`.
    fn copy(&self, name: &str) -> String {
        let st = Command::new("cp")
            .args(["-r", &self.p("base.zarr"), &self.p(name)])
            .status()
            .expect("cp");
        assert!(st.success());
        self.p(name)
    }

    fn classify_args(&self, store: &str, out: &str, extra: &[&str]) -> Vec<String> {
        self.classify_with("local", store, out, extra)
    }

    fn classify_with(&self, features: &str, store: &str, out: &str, extra: &[&str]) -> Vec<String> {
        let mut v: Vec<String> = [
            "classify",
            store,
            "--scribbles",
            &self.p("scr.nii.gz"),
            "--features",
            features,
            "--trees",
            "20",
            "--out",
            out,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    }

    /// Classifies a copy in this process: the reference.
    fn reference(&self) -> String {
        let s = self.copy("local.zarr");
        let out = self.p("local.nii.gz");
        let a = self.classify_args(&s, &out, &[]);
        ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
        s
    }
}

/// A cluster run's store, NIfTI and report, and the coordinator's arguments.
struct Run {
    store: String,
    out: String,
    rep: String,
    args: Vec<String>,
}

impl Scene {
    /// A fresh store copy to classify on the cluster at `url` with AckWait `ack` seconds.
    fn cluster_run(&self, url: &str, ack: &str) -> Run {
        let store = self.copy("cluster.zarr");
        let out = self.p("cluster.nii.gz");
        let rep = self.p("cluster.json");
        let mut args = self.classify_args(&store, &out, &["--report", &rep, "--cluster", url]);
        args.extend(engine_args(ack).iter().map(|s| s.to_string()));
        Run {
            store,
            out,
            rep,
            args,
        }
    }
}

/// The coordinator as a child process.
fn coordinator(args: &[String]) -> Child {
    Command::new(BIN)
        .args(args)
        .arg("--quiet")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("coordinator")
}

/// `n` workers named w0.. with `extra` arguments.
fn workers(url: &str, n: usize, extra: &[&str]) -> Vec<Worker> {
    (0..n)
        .map(|i| Worker::spawn(&[], url, &format!("w{i}"), extra))
        .collect()
}

/// Every file under `rel` of two stores, byte for byte (zarr.json of the probability array
/// carries the same provenance in both).
fn same_tree(a: &str, b: &str, rel: &str) {
    let (ra, rb) = (Path::new(a).join(rel), Path::new(b).join(rel));
    let mut fa = files(&ra);
    let mut fb = files(&rb);
    fa.sort();
    fb.sort();
    assert!(!fa.is_empty(), "{} is empty", ra.display());
    assert_eq!(fa, fb, "{rel}: different files");
    for f in fa {
        let (x, y) = (
            std::fs::read(ra.join(&f)).unwrap(),
            std::fs::read(rb.join(&f)).unwrap(),
        );
        // The label image's metadata names the temporary folder it was written in (with the
        // writer's pid); everything else must match byte for byte.
        assert!(scrub(&x) == scrub(&y), "{rel}/{} differs", f.display());
    }
}

/// `partial-<digits>` replaced by `partial-N`.
fn scrub(b: &[u8]) -> Vec<u8> {
    let s = String::from_utf8_lossy(b);
    if !s.contains("partial-") {
        return b.to_vec();
    }
    let mut out = String::new();
    let mut rest: &str = &s;
    while let Some(i) = rest.find("partial-") {
        out.push_str(&rest[..i + 8]);
        rest = rest[i + 8..].trim_start_matches(|c: char| c.is_ascii_digit());
        out.push('N');
    }
    out.push_str(rest);
    out.into_bytes()
}

fn files(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if !e.file_name().to_string_lossy().starts_with('.') {
                out.push(p.strip_prefix(root).unwrap().to_path_buf());
            }
        }
    }
    out
}

/// The result of a cluster run equals the reference: probabilities, labels, NIfTI.
fn same_result(scene: &Scene, reference: &str, store: &str, out: &str) {
    same_tree(reference, store, "neuvolex/vectors/classes_proba");
    same_tree(reference, store, "labels/classified");
    assert_eq!(
        std::fs::read(scene.p("local.nii.gz")).unwrap(),
        std::fs::read(out).unwrap(),
        "NIfTI label volumes differ"
    );
}

fn report(path: &str) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("report")).expect("report JSON")
}

fn engine_args(ack_wait: &str) -> Vec<&str> {
    vec![
        "--ack-wait",
        ack_wait,
        "--max-deliver",
        "3",
        "--no-worker-timeout",
        "60",
    ]
}

#[test]
fn cluster_classify_on_three_workers_equals_one_process() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let reference = scene.reference();
    let _w: Vec<Worker> = (0..3)
        .map(|i| Worker::spawn(&[], &nats.url(), &format!("w{i}"), &[]))
        .collect();
    let store = scene.copy("cluster.zarr");
    let out = scene.p("cluster.nii.gz");
    let rep = scene.p("cluster.json");
    let mut a = scene.classify_args(&store, &out, &["--report", &rep, "--cluster", &nats.url()]);
    a.extend(["--bricks-per-task", "2"].map(String::from));
    let stdout = ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(stdout.contains("tasks per worker"), "{stdout}");
    same_result(&scene, &reference, &store, &out);
    let r = report(&rep);
    assert_eq!(r["run"]["completed"], 32, "{r}");
    assert!(r["run"]["dead"].as_array().unwrap().is_empty());
    assert!(
        r["run"]["per_worker"].as_object().unwrap().len() >= 2,
        "work spread over workers: {r}"
    );
}

#[test]
fn fault_worker_killed_mid_task_is_redelivered() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let reference = scene.reference();
    let slow = ["--task-delay-ms", "400"];
    let mut victim = Worker::spawn(
        &[],
        &nats.url(),
        "victim",
        &[&slow[..], &engine_args("2")].concat(),
    );
    let _others = workers(&nats.url(), 2, &[&slow[..], &engine_args("2")].concat());
    let Run {
        store,
        out,
        rep,
        args: a,
    } = scene.cluster_run(&nats.url(), "2");
    let coord = coordinator(&a);
    victim.wait_started(2, Duration::from_secs(60));
    victim.kill9();
    let o = coord.wait_with_output().expect("coordinator");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&rep);
    assert!(
        r["run"]["redeliveries"].as_u64().unwrap() >= 1,
        "the killed task was redelivered: {r}"
    );
    same_result(&scene, &reference, &store, &out);
}

/// Bricks marked done in the pending generation of the probability array (the store's done
/// markers, `classes_proba/GEN.done/X.Y.Z`).
fn markers_done(store: &str) -> usize {
    let node = Path::new(store).join("neuvolex/vectors/classes_proba");
    let Ok(gens) = std::fs::read_dir(&node) else {
        return 0;
    };
    gens.flatten()
        .filter(|g| g.file_name().to_string_lossy().ends_with(".done"))
        .filter_map(|g| std::fs::read_dir(g.path()).ok())
        .flat_map(|d| d.flatten())
        .filter(|e| e.file_name().to_string_lossy().split('.').count() == 3)
        .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
        .count()
}

#[test]
fn fault_nats_server_restarted_during_a_run() {
    let scene = Scene::new();
    let Some(mut nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let reference = scene.reference();
    let slow = ["--task-delay-ms", "300"];
    let w = workers(&nats.url(), 2, &[&slow[..], &engine_args("3")].concat());
    let Run {
        store,
        out,
        rep: _,
        args: a,
    } = scene.cluster_run(&nats.url(), "3");
    let coord = coordinator(&a);
    w[0].wait_started(3, Duration::from_secs(60));
    nats.stop();
    std::thread::sleep(Duration::from_millis(1500));
    nats.spawn();
    let o = coord.wait_with_output().expect("coordinator");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    same_result(&scene, &reference, &store, &out);
}

#[test]
fn fault_coordinator_killed_then_rerun_resumes_from_done_markers() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let reference = scene.reference();
    let slow = ["--task-delay-ms", "150"];
    let _w = workers(&nats.url(), 2, &[&slow[..], &engine_args("3")].concat());
    let Run {
        store,
        out,
        rep,
        args: a,
    } = scene.cluster_run(&nats.url(), "3");
    let mut coord = coordinator(&a);
    let t = Instant::now();
    while markers_done(&store) < 8 {
        assert!(t.elapsed() < Duration::from_secs(60), "no progress");
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = coord.kill();
    let _ = coord.wait();
    assert!(
        !Path::new(&out).exists(),
        "the killed run wrote no label volume"
    );
    ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let r = report(&rep);
    let resumed = r["bricks_resumed"].as_u64().unwrap();
    let computed = r["bricks_predicted"].as_u64().unwrap() + r["bricks_skipped"].as_u64().unwrap();
    assert!(resumed >= 8, "{r}");
    assert_eq!(
        resumed + computed,
        64,
        "every brick computed exactly once across both runs: {r}"
    );
    same_result(&scene, &reference, &store, &out);
}

#[test]
fn fault_poisoned_brick_is_dead_lettered_and_the_rest_completes() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    // The scribbles' slice; the poisoned brick lies elsewhere (training never reads it).
    let strokes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.p("scr.strokes.json")).unwrap()).unwrap();
    let zs: Vec<u64> = strokes
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["slice"].as_u64().unwrap() / 16)
        .collect();
    let bz = (0..4u64)
        .rev()
        .find(|z| !zs.contains(z))
        .expect("an unscribbled brick row");
    let _w: Vec<Worker> = (0..2)
        .map(|i| Worker::spawn(&[], &nats.url(), &format!("w{i}"), &engine_args("3")))
        .collect();
    let store = scene.copy("cluster.zarr");
    let chunk = Path::new(&store).join(format!("0/c.{bz}.1.1"));
    assert!(chunk.exists(), "{}", chunk.display());
    std::fs::write(&chunk, b"this is not a zstd chunk").unwrap();
    let out = scene.p("cluster.nii.gz");
    let rep = scene.p("cluster.json");
    let mut a = scene.classify_with(
        "intensity",
        &store,
        &out,
        &["--report", &rep, "--cluster", &nats.url()],
    );
    a.extend(engine_args("3").iter().map(|s| s.to_string()));
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "a dead task fails the run");
    assert!(
        err.contains(&format!("[1, 1, {bz}]")),
        "names the brick: {err}"
    );
    assert!(err.contains("after 3 deliveries"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let r = report(&rep);
    assert_eq!(r["run"]["dead"].as_array().unwrap().len(), 1, "{r}");
    assert_eq!(r["run"]["completed"], 63, "the other bricks completed: {r}");
    assert_eq!(markers_done(&store), 63);
    // The completed bricks equal a clean single-process run's.
    let clean = scene.copy("clean.zarr");
    let b = scene.classify_with("intensity", &clean, &scene.p("clean.nii.gz"), &[]);
    ok(&b.iter().map(String::as_str).collect::<Vec<_>>());
    let rel = "neuvolex/vectors/classes_proba";
    let poisoned = PathBuf::from(format!("c/{bz}/1/1/0"));
    for f in files(&Path::new(&clean).join(rel)) {
        if f.ends_with(&poisoned) || f.file_name().is_some_and(|n| n == "zarr.json") {
            continue;
        }
        assert_eq!(
            std::fs::read(Path::new(&clean).join(rel).join(&f)).unwrap(),
            std::fs::read(Path::new(&store).join(rel).join(&f)).unwrap(),
            "{}",
            f.display()
        );
    }
}

#[test]
fn unreachable_or_unauthorised_nats_fails_clearly_in_bounded_time() {
    let scene = Scene::new();
    let store = scene.copy("cluster.zarr");
    let out = scene.p("x.nii.gz");
    let timed = |url: &str, needle: &str| {
        let t = Instant::now();
        let mut a = scene.classify_args(&store, &out, &["--cluster", url]);
        a.extend(engine_args("3").iter().map(|s| s.to_string()));
        let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{url} should fail");
        assert!(err.contains(needle), "{url}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{url}: {:?}",
            t.elapsed()
        );
        let o = run(&["worker", "--nats", url]);
        assert!(!o.status.success());
        assert!(String::from_utf8_lossy(&o.stderr).contains(needle));
    };
    // Nothing listens.
    let closed = free_port();
    timed(
        &format!("nats://127.0.0.1:{closed}"),
        &format!("NATS at nats://127.0.0.1:{closed}"),
    );
    // Something listens but never speaks NATS.
    let silent = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = silent.local_addr().unwrap().port();
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for s in silent.incoming().flatten() {
            held.push(s);
        }
    });
    timed(&format!("nats://127.0.0.1:{port}"), "NATS at");
    timed("http://127.0.0.1:4222", "not a NATS URL");
    // Wrong credentials.
    let Some(nats) = Nats::start(
        scene.dir.path(),
        "127.0.0.1",
        &["--user", "nvx", "--pass", "right"],
    ) else {
        return;
    };
    timed(
        &format!("nats://nvx:wrong@127.0.0.1:{}", nats.port),
        "uthoriz",
    );
    // No worker: the coordinator gives up in bounded time.
    let Some(open) = Nats::start(&scene.dir.path().join("n2"), "127.0.0.1", &[]) else {
        return;
    };
    let t = Instant::now();
    let mut a = scene.classify_args(&store, &out, &["--cluster", &open.url()]);
    a.extend(["--no-worker-timeout", "3"].map(String::from));
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no worker answered"));
    assert!(t.elapsed() < Duration::from_secs(30));
}

/// A network namespace joined to the host by a veth pair, removed on drop.
struct Netns {
    name: String,
    host_if: String,
    host_ip: String,
}

impl Netns {
    fn create() -> Option<Netns> {
        let root = Command::new("id")
            .arg("-u")
            .output()
            .map(|o| o.stdout == b"0\n")
            .unwrap_or(false);
        if !root {
            skip("the link test needs root for network namespaces");
            return None;
        }
        let id = std::process::id() % 100_000;
        let k = (id % 250) as u8 + 1;
        let n = Netns {
            name: format!("nvxt{id}"),
            host_if: format!("nvxh{id}"),
            host_ip: format!("10.251.{k}.1"),
        };
        let peer = format!("nvxn{id}");
        let ns_ip = format!("10.251.{k}.2");
        let steps: Vec<Vec<String>> = vec![
            vec!["netns", "add", &n.name],
            vec![
                "link", "add", &n.host_if, "type", "veth", "peer", "name", &peer,
            ],
            vec!["link", "set", &peer, "netns", &n.name],
            vec![
                "addr",
                "add",
                &format!("{}/30", n.host_ip),
                "dev",
                &n.host_if,
            ],
            vec!["link", "set", &n.host_if, "up"],
            vec![
                "netns",
                "exec",
                &n.name,
                "ip",
                "addr",
                "add",
                &format!("{ns_ip}/30"),
                "dev",
                &peer,
            ],
            vec!["netns", "exec", &n.name, "ip", "link", "set", &peer, "up"],
            vec!["netns", "exec", &n.name, "ip", "link", "set", "lo", "up"],
        ]
        .into_iter()
        .map(|v| v.into_iter().map(String::from).collect())
        .collect();
        for s in steps {
            let st = Command::new("ip").args(&s).status();
            if !st.map(|s| s.success()).unwrap_or(false) {
                drop(n);
                skip(&format!(
                    "cannot set up a network namespace (ip {})",
                    s.join(" ")
                ));
                return None;
            }
        }
        Some(n)
    }

    fn link(&self, up: bool) {
        let st = Command::new("ip")
            .args(["link", "set", &self.host_if, if up { "up" } else { "down" }])
            .status()
            .expect("ip link");
        assert!(st.success());
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        let _ = Command::new("ip")
            .args(["link", "del", &self.host_if])
            .status();
        let _ = Command::new("ip")
            .args(["netns", "del", &self.name])
            .status();
    }
}

#[test]
fn fault_worker_link_cut_longer_than_ack_wait() {
    let scene = Scene::new();
    if nats_server().is_none() {
        skip("nats-server is not installed (deploy/test.sh installs it)");
        return;
    }
    let Some(ns) = Netns::create() else { return };
    let Some(nats) = Nats::start(scene.dir.path(), &ns.host_ip, &[]) else {
        return;
    };
    let reference = scene.reference();
    let slow = ["--task-delay-ms", "500"];
    let cut = Worker::spawn(
        &["ip", "netns", "exec", &ns.name],
        &nats.url(),
        "cut",
        &[&slow[..], &engine_args("2")].concat(),
    );
    let _w = workers(&nats.url(), 2, &[&slow[..], &engine_args("2")].concat());
    let Run {
        store,
        out,
        rep,
        args: a,
    } = scene.cluster_run(&nats.url(), "2");
    let coord = coordinator(&a);
    cut.wait_started(2, Duration::from_secs(60));
    ns.link(false);
    std::thread::sleep(Duration::from_secs(5));
    ns.link(true);
    let o = coord.wait_with_output().expect("coordinator");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&rep);
    assert_eq!(r["run"]["completed"], 64, "each task counted once: {r}");
    assert!(
        r["run"]["redeliveries"].as_u64().unwrap() >= 1,
        "the cut worker's task went elsewhere: {r}"
    );
    same_result(&scene, &reference, &store, &out);
}

/// `views.json` without its timings.
fn views_without_times(dir: &str) -> serde_json::Value {
    let mut v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(Path::new(dir).join("views.json")).unwrap()).unwrap();
    v["kmeans"]["seconds"] = serde_json::Value::Null;
    v["scoring_seconds"] = serde_json::Value::Null;
    v["store"] = serde_json::Value::Null;
    v
}

#[test]
fn features_and_viewpoints_on_the_cluster_equal_one_process() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    ok(&["train", &scene.p("base.zarr"), "--epochs", "0.05"]);
    let _w: Vec<Worker> = (0..2)
        .map(|i| Worker::spawn(&[], &nats.url(), &format!("w{i}"), &[]))
        .collect();
    let (a, b) = (scene.copy("local.zarr"), scene.copy("cluster.zarr"));
    ok(&["features", &a]);
    ok(&[
        "features",
        &b,
        "--cluster",
        &nats.url(),
        "--bricks-per-task",
        "3",
    ]);
    same_tree(&a, &b, "neuvolex/vectors/inr_hidden");
    for (store, out, cl) in [
        (&a, scene.p("va"), None),
        (&b, scene.p("vb"), Some(nats.url())),
    ] {
        let mut args = vec![
            "viewpoints",
            store,
            "--features",
            "paper",
            "--stored-features",
            "--k",
            "8",
            "--views",
            "300",
            "--size",
            "0",
            "--out",
            &out,
        ];
        if let Some(u) = &cl {
            args.extend(["--cluster", u.as_str()]);
        }
        ok(&args);
    }
    assert_eq!(
        views_without_times(&scene.p("va")),
        views_without_times(&scene.p("vb"))
    );
}

/// The middle-slice PSNR `neuvolex train` prints.
fn slice_psnr(stdout: &str) -> f64 {
    let i = stdout.find(" dB middle slice").expect("PSNR in the output");
    let head = &stdout[..i];
    let j = head.rfind(", ").expect("PSNR in the output") + 2;
    head[j..].parse().expect("PSNR")
}

fn model_bytes(store: &str) -> Vec<u8> {
    std::fs::read(Path::new(store).join("neuvolex/inr/model.nvx")).expect("model")
}

#[test]
fn distributed_training_is_deterministic_and_close_to_single_node() {
    let scene = Scene::new();
    let Some(nats) = Nats::start(scene.dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let train = |store: &str, samples: &str, batch: &str, extra: &[&str]| {
        let mut a = vec![
            "train",
            store,
            "--samples",
            samples,
            "--batch",
            batch,
            "--log2-table",
            "14",
            "--seed",
            "7",
            "--backend",
            "cpu",
        ];
        a.extend_from_slice(extra);
        ok(&a)
    };
    let _w = workers(&nats.url(), 2, &[]);
    let url = nats.url();
    let cl = ["--cluster", url.as_str(), "--no-worker-timeout", "60"];
    // One replica on the cluster is the single-node trainer, bit for bit (13 steps).
    let (single, one) = (scene.copy("single.zarr"), scene.copy("one.zarr"));
    train(&single, "98304", "8192", &[]);
    train(
        &one,
        "98304",
        "8192",
        &[&cl[..], &["--replicas", "1", "--sync-steps", "5"]].concat(),
    );
    assert!(
        model_bytes(&one) == model_bytes(&single),
        "1 replica != train"
    );
    // Two replicas (48 steps of 8192 samples, synchronised every 4): the same model from a
    // re-run and from the in-process executor, whichever worker took which replica.
    let two = ["--replicas", "2", "--sync-steps", "4"];
    let (a, b, c) = (
        scene.copy("a.zarr"),
        scene.copy("b.zarr"),
        scene.copy("c.zarr"),
    );
    let out_a = train(&a, "393216", "8192", &[&cl[..], &two[..]].concat());
    assert!(out_a.contains("per worker"), "{out_a}");
    train(&b, "393216", "8192", &[&cl[..], &two[..]].concat());
    train(&c, "393216", "8192", &two);
    assert!(model_bytes(&a) == model_bytes(&b), "re-run differs");
    assert!(model_bytes(&a) == model_bytes(&c), "cluster != in process");
    // At an equal sample budget two replicas of batch B take the optimiser steps of one
    // trainer at batch 2B: their PSNR is within 1 dB of it (measured: 20.70 vs 20.33 dB).
    let big = scene.copy("big.zarr");
    let psnr_big = slice_psnr(&train(&big, "393216", "16384", &[]));
    let psnr_two = slice_psnr(&out_a);
    eprintln!("middle-slice PSNR: 2 replicas {psnr_two:.2} dB, 1 at batch 2B {psnr_big:.2} dB");
    assert!(
        (psnr_two - psnr_big).abs() < 1.0 && psnr_two > 18.0,
        "2 replicas {psnr_two:.2} dB vs single node at batch 2B {psnr_big:.2} dB"
    );
}

/// A float raw volume (`name_WxHxD_f32.raw`) of smooth values with fine detail, and a NaN at
/// `nan` (x fastest) if given.
fn float_raw(dir: &Path, name: &str, dims: [usize; 3], nan: Option<usize>) -> String {
    let n = dims.iter().product::<usize>();
    let mut bytes = Vec::with_capacity(n * 4);
    for i in 0..n {
        let (x, y, z) = (
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        );
        let v = if Some(i) == nan {
            f32::NAN
        } else {
            1000.0 * ((x as f32 * 0.21).sin() + (y as f32 * 0.13).cos()) + z as f32 * 3.7
                - 0.001 * (i % 97) as f32
        };
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    let p = dir.join(format!(
        "{name}_{}x{}x{}_f32.raw",
        dims[0], dims[1], dims[2]
    ));
    std::fs::write(&p, bytes).expect("write raw");
    p.to_string_lossy().into_owned()
}

#[test]
fn cluster_ingest_on_two_workers_equals_one_process() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = |n: &str| dir.path().join(n).to_string_lossy().into_owned();
    let Some(nats) = Nats::start(dir.path(), "127.0.0.1", &[]) else {
        return;
    };
    let _w = workers(&nats.url(), 2, &[]);
    // A 16-bit gzipped NIfTI with its labels (exact count statistics), and a float raw file
    // (shifted sums per slice and the second, percentile round).
    ok(&["synth", "phantom", "--out", &p("ph.nii.gz"), "--size", "48"]);
    let float = float_raw(dir.path(), "f", [40, 36, 50], None);
    let cases: Vec<(String, Vec<String>)> = vec![
        (
            p("ph.nii.gz"),
            [
                "--labels",
                &p("ph_labels.nii.gz"),
                "--classes",
                &p("ph_classes.json"),
            ]
            .map(String::from)
            .to_vec(),
        ),
        (float.clone(), vec![]),
        (float.clone(), ["--shard", "2"].map(String::from).to_vec()),
    ];
    for (i, (src, extra)) in cases.iter().enumerate() {
        let (local, cluster) = (p(&format!("local{i}.zarr")), p(&format!("cluster{i}.zarr")));
        let mut a: Vec<String> = ["ingest", src, &local, "--brick", "16"]
            .map(String::from)
            .to_vec();
        a.extend(extra.iter().cloned());
        ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
        a[2] = cluster.clone();
        a.extend(["--cluster", &nats.url(), "--bricks-per-task", "1"].map(String::from));
        ok(&a.iter().map(String::as_str).collect::<Vec<_>>());
        // Arrays, statistics, per-brick ranges, labels: every file byte for byte (but the
        // writer lock, which names its process).
        same_store(&local, &cluster);
    }
    // A NaN in the middle, rejected on a worker: a clear error naming the file and the voxel,
    // and the store already at the output stays as it was.
    let bad = float_raw(dir.path(), "bad", [40, 36, 50], Some(40 * 36 * 37 + 5));
    let keep = p("cluster1.zarr");
    let before = std::fs::read(Path::new(&keep).join("zarr.json")).unwrap();
    let o = run(&[
        "ingest",
        &bad,
        &keep,
        "--brick",
        "16",
        "--force",
        "--cluster",
        &nats.url(),
        "--max-deliver",
        "1",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "a NaN must be refused");
    assert!(err.contains(&bad) && err.contains("z=37"), "{err}");
    assert_eq!(
        std::fs::read(Path::new(&keep).join("zarr.json")).unwrap(),
        before,
        "the previous store must stay intact"
    );
    same_store(&p("local1.zarr"), &keep);
}

/// Two stores byte for byte, without their writer-lock files (they name their process).
fn same_store(a: &str, b: &str) {
    for s in [a, b] {
        let _ = std::fs::remove_file(Path::new(s).join("neuvolex/writer.lock"));
    }
    same_tree(a, b, "");
}
