//! Crash safety of the brick store (issue 16, "Stores, crash-safe"), on the real `neuvolex`
//! binary:
//!
//! - **SIGKILL**: each stage (ingest with labels over an existing store; train with periodic
//!   checkpoints; features; classify) runs once uninterrupted for its reference result and
//!   duration, then `NEUVOLEX_CRASH_KILLS` times (default 6; the recorded run uses 50) is killed
//!   with SIGKILL at a time drawn from a seeded RNG (`NEUVOLEX_CRASH_SEED`) over that duration
//!   (+10 %, so some kills land after the end). After each kill every node of the store (image,
//!   each label image, each vector array, the model) must read as its state before the
//!   interrupted step or after it, and the store as a whole as one of them (a step's
//!   outputs are one commit; `NEUVOLEX_CRASH_STRICT=0` only counts a mix); then `--resume`
//!   (training with a checkpoint) or a re-run must complete and give the reference result bit
//!   for bit, leaving no debris (temporary folders, unpublished generations).
//! - **SIGKILL in the server** (`neuvolex serve`): the OME-Zarr export (a label image and a
//!   probability array written into the store) and the session save (the session file
//!   written when a session closes) are killed the same way, at seeded offsets over the
//!   step's duration, on a fresh server brought to the step each time; then the store or
//!   the session file must read as before or after, and a re-run on a new server must give the
//!   uninterrupted result with no debris.
//! - **Disk full**: the same stages on a small tmpfs (mounted by the test, unmounted after)
//!   filled to a few KiB: a clear error naming a path on it, the previous store intact, and a
//!   re-run after space is freed completes; the server's OME-Zarr export and session save
//!   likewise (507 naming the path, the previous store or saved session intact, the request
//!   completing once space is freed). Skips visibly where mounting is not permitted (fails
//!   under `CI=true`).
//! - **Concurrent writers**: while one process writes a store, every other writer (ingest,
//!   train, features, classify) is refused with an error naming the store and the holder.

use std::collections::BTreeMap;
use std::hash::{Hash, Hasher};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use neuvolex_bricks::BrickStore;
use serde_json::{json, Value};
use support::{classify_strokes, http, open_phantom, try_http, Server};

mod support;

const BIN: &str = env!("CARGO_BIN_EXE_neuvolex");

/// splitmix64: the kill offsets.
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn env_num(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn command(dir: &Path, args: &[String]) -> Command {
    let mut c = Command::new(BIN);
    c.current_dir(dir)
        .args(args)
        .arg("--quiet")
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null());
    c
}

/// Runs to completion; panics with stderr on failure.
fn run_ok(dir: &Path, args: &[String]) -> Duration {
    let t = Instant::now();
    let o = command(dir, args).output().expect("run neuvolex");
    assert!(
        o.status.success(),
        "neuvolex {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    t.elapsed()
}

fn args(a: &[&str]) -> Vec<String> {
    a.iter().map(|s| s.to_string()).collect()
}

fn hash_bytes(parts: &[&[u8]]) -> String {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for p in parts {
        p.hash(&mut h);
    }
    format!("{:016x}", h.finish())
}

/// What a reader sees in the store, node by node: a content hash per node, "absent", or the
/// error a reader gets.
type State = BTreeMap<String, String>;

fn digest(store: &Path) -> State {
    let mut m = State::new();
    if !store.exists() {
        m.insert("store".into(), "absent".into());
        return m;
    }
    let s = match BrickStore::open(store) {
        Ok(s) => s,
        Err(e) => {
            m.insert("store".into(), format!("unreadable: {e}"));
            return m;
        }
    };
    let info = s.info().clone();
    let mut head = serde_json::to_value(&info).unwrap();
    head.as_object_mut().unwrap().remove("labels");
    let mut parts = vec![serde_json::to_vec(&head).unwrap()];
    for (k, d) in info.levels.iter().enumerate() {
        match s.read_box(k, [0; 3], *d) {
            Ok(v) => parts.push(bytemuck_f32(&v)),
            Err(e) => parts.push(format!("level {k}: {e}").into_bytes()),
        }
    }
    let refs: Vec<&[u8]> = parts.iter().map(|p| p.as_slice()).collect();
    m.insert("image".into(), hash_bytes(&refs));
    for l in &info.labels {
        let v = match (s.label_classes(l), s.read_labels_box(l, [0; 3], info.dims)) {
            (Ok(c), Ok(v)) => {
                let c = serde_json::to_vec(&c).unwrap();
                let v: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
                hash_bytes(&[&c, &v])
            }
            (c, v) => format!("error: {:?} {:?}", c.err(), v.err()),
        };
        m.insert(format!("labels/{l}"), v);
    }
    for name in ["inr_hidden", "classes_proba", "classes_labels", "nx_proba"] {
        match s.has_vectors(name) {
            Ok(true) => {}
            Ok(false) => {
                m.insert(format!("vectors/{name}"), "absent".into());
                continue;
            }
            Err(e) => {
                m.insert(format!("vectors/{name}"), format!("error: {e}"));
                continue;
            }
        }
        let v = match s.open_vectors(name) {
            Ok(va) => {
                let mut parts = vec![serde_json::to_vec(va.info()).unwrap()];
                for b in s.bricks() {
                    match va.read_brick(&b) {
                        Ok(v) => parts.push(bytemuck_f32(&v)),
                        Err(e) if e.to_string().contains("missing") => {
                            parts.push(b"unwritten".to_vec())
                        }
                        Err(e) => parts.push(format!("error: {e}").into_bytes()),
                    }
                }
                let refs: Vec<&[u8]> = parts.iter().map(|p| p.as_slice()).collect();
                hash_bytes(&refs)
            }
            Err(e) => format!("error: {e}"),
        };
        m.insert(format!("vectors/{name}"), v);
    }
    let model = store.join("neuvolex/inr/model.nvx");
    let v = match std::fs::read(&model) {
        Err(_) => "absent".into(),
        Ok(bytes) => match neuvolex_features::checkpoint::load(&model) {
            Ok(_) => hash_bytes(&[&bytes]),
            Err(e) => format!("error: {e}"),
        },
    };
    m.insert("model".into(), v);
    // The training checkpoint is resume data, not a result: it must load wherever it exists.
    let ck = store.join("neuvolex/inr/checkpoint.nvx");
    if ck.exists() {
        if let Err(e) = neuvolex_features::checkpoint::load(&ck) {
            m.insert("checkpoint".into(), format!("error: {e}"));
        }
    }
    m
}

fn bytemuck_f32(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_bits().to_le_bytes()).collect()
}

/// Every file under `dir` (relative), without the lock file, for the debris check.
fn files(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<String>) {
        let Ok(rd) = std::fs::read_dir(d) else {
            return;
        };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let r = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                if !r.ends_with("writer.lock") {
                    out.push(r);
                }
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// Generation folders (`vN`) renamed to `v*`, so two runs' file sets compare.
fn shape(files: &[String]) -> Vec<String> {
    let mut v: Vec<String> = files
        .iter()
        // Saved label bricks (named by content) are as many as rounds finished before the
        // step; their temporaries still count as debris.
        .filter(|f| !(f.starts_with("labels/") && f.ends_with(".zst") && !f.contains("/.")))
        .map(|f| {
            f.split('/')
                .map(|c| {
                    if c.len() > 1
                        && c.starts_with('v')
                        && c[1..].chars().all(|d| d.is_ascii_digit())
                    {
                        "v*".to_string()
                    } else {
                        c.to_string()
                    }
                })
                .collect::<Vec<_>>()
                .join("/")
        })
        .collect();
    v.sort();
    v
}

fn copy_dir(from: &Path, to: &Path) {
    if to.exists() {
        std::fs::remove_dir_all(to).unwrap();
    }
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        let t = to.join(e.file_name());
        if p.is_dir() {
            copy_dir(&p, &t);
        } else {
            std::fs::copy(&p, &t).unwrap();
        }
    }
}

/// The inputs every stage uses: a 40-voxel phantom (new) and another seed (the store the
/// ingest replaces), simulated scribbles.
struct Inputs {
    dir: tempfile::TempDir,
}

impl Inputs {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for (name, seed) in [("ph", "0"), ("old", "1")] {
            run_ok(
                d,
                &args(&[
                    "synth",
                    "phantom",
                    "--out",
                    &format!("{name}.nii.gz"),
                    "--size",
                    "40",
                    "--seed",
                    seed,
                ]),
            );
        }
        run_ok(
            d,
            &args(&[
                "scribble-sim",
                "ph_labels.nii.gz",
                "--level",
                "S2",
                "--out",
                "scr.nii.gz",
            ]),
        );
        Inputs { dir }
    }

    fn path(&self, name: &str) -> String {
        self.dir.path().join(name).to_string_lossy().into_owned()
    }
}

/// A stage: steps run one after the other on `st.zarr` in its work folder.
struct Stage {
    name: &'static str,
    steps: Vec<Vec<String>>,
}

impl Stage {
    /// The arguments to re-run `step` after an interruption: training resumes from its
    /// checkpoint when one was saved.
    fn rerun(&self, step: usize, work: &Path) -> Vec<String> {
        let mut a = self.steps[step].clone();
        if a[0] == "train" && work.join("st.zarr/neuvolex/inr/checkpoint.nvx").exists() {
            a.push("--resume".into());
        }
        a
    }
}

fn stages(inp: &Inputs) -> Vec<(Stage, Vec<Vec<String>>)> {
    let ingest = |src: &str, lab: &str| {
        args(&[
            "ingest",
            &inp.path(&format!("{src}.nii.gz")),
            "st.zarr",
            "--brick",
            "16",
            "--labels",
            &inp.path(&format!("{lab}_labels.nii.gz")),
            "--classes",
            &inp.path("ph_classes.json"),
            "--force",
        ])
    };
    let train = args(&[
        "train",
        "st.zarr",
        "--samples",
        "40000",
        "--batch",
        "1024",
        "--checkpoint-every",
        "6",
        "--log2-table",
        "14",
    ]);
    let features = args(&["features", "st.zarr", "--all-bricks"]);
    let classify = args(&[
        "classify",
        "st.zarr",
        "--scribbles",
        &inp.path("scr.nii.gz"),
        "--features",
        "paper",
        "--stored-features",
        "--trees",
        "12",
    ]);
    vec![
        (
            Stage {
                name: "ingest",
                steps: vec![ingest("ph", "ph")],
            },
            vec![ingest("old", "old")],
        ),
        (
            Stage {
                name: "train + checkpoint",
                steps: vec![train.clone()],
            },
            vec![ingest("ph", "ph")],
        ),
        // Features and classify are stages of their own, each with its own kills.
        (
            Stage {
                name: "features",
                steps: vec![features.clone()],
            },
            vec![ingest("ph", "ph"), train.clone()],
        ),
        (
            Stage {
                name: "classify",
                steps: vec![classify],
            },
            vec![ingest("ph", "ph"), train, features],
        ),
    ]
}

/// Outcome counts of one stage's kills.
#[derive(Default, Debug)]
struct Tally {
    kills: usize,
    killed_running: usize,
    saw_before: usize,
    saw_after: usize,
    mixed_nodes: usize,
    resumed: usize,
    failures: Vec<String>,
}

impl Tally {
    /// Prints the stage's line of the record (RELIABILITY.md): kills, how the store read after
    /// them, and how many re-runs gave the uninterrupted result.
    fn summarise(&self, stage: &str, total: f64) {
        eprintln!(
            "crash-safety {stage:<20} {} kills over {total:.3} s (seed {}): {} killed while the step ran, read as before {} / after {} / complete nodes from both {}, re-run equal to uninterrupted {}/{}, failures {}",
            self.kills,
            env_num("NEUVOLEX_CRASH_SEED", 16),
            self.killed_running,
            self.saw_before,
            self.saw_after,
            self.mixed_nodes,
            self.resumed,
            self.kills,
            self.failures.len()
        );
    }

    /// The last check of a kill whose re-run gave the uninterrupted result: the files left
    /// (`left`) must be the uninterrupted run's (`want`); counts it resumed, or records the
    /// debris.
    fn settle(&mut self, i: usize, at: f64, left: &[String], want: &[String]) {
        if left == want {
            self.resumed += 1;
            return;
        }
        let extra: Vec<&String> = left.iter().filter(|f| !want.contains(f)).collect();
        let missing: Vec<&String> = want.iter().filter(|f| !left.contains(f)).collect();
        self.failures.push(format!(
            "kill {i} at {at:.3} s: debris after the re-run: extra {extra:?}, missing {missing:?}"
        ));
    }
}

fn kill_stage(stage: &Stage, setup: &[Vec<String>], kills: usize, rng: &mut Rng) -> Tally {
    let root = tempfile::tempdir().unwrap();
    let base = root.path().join("base");
    let work = root.path().join("work");
    std::fs::create_dir_all(&base).unwrap();
    for s in setup {
        run_ok(&base, s);
    }
    // The reference: each step uninterrupted, the state after it, and its duration.
    copy_dir(&base, &work);
    let mut states = vec![digest(&work.join("st.zarr"))];
    let mut durations = Vec::new();
    for s in &stage.steps {
        durations.push(run_ok(&work, s).as_secs_f64());
        states.push(digest(&work.join("st.zarr")));
    }
    let final_files = shape(&files(&work));
    let total: f64 = durations.iter().sum();
    assert_ne!(
        states[0],
        states[stage.steps.len()],
        "{}: the stage must change the store",
        stage.name
    );
    let mut t = Tally::default();
    for i in 0..kills {
        copy_dir(&base, &work);
        let at = rng.unit() * total * 1.1;
        // The step the kill lands in; earlier steps complete.
        let (mut k, mut before) = (0, 0.0);
        while k + 1 < stage.steps.len() && at > before + durations[k] {
            before += durations[k];
            run_ok(&work, &stage.steps[k]);
            k += 1;
        }
        let mut child = command(&work, &stage.steps[k])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn neuvolex");
        std::thread::sleep(Duration::from_secs_f64((at - before).max(0.0)));
        let _ = child.kill(); // SIGKILL
        let status = child.wait().unwrap();
        t.kills += 1;
        {
            use std::os::unix::process::ExitStatusExt;
            if status.signal() == Some(9) {
                t.killed_running += 1;
            }
        }
        let seen = digest(&work.join("st.zarr"));
        if seen == states[k] {
            t.saw_before += 1;
        } else if seen == states[k + 1] {
            t.saw_after += 1;
        } else if std::env::var("NEUVOLEX_CRASH_STRICT").as_deref() == Ok("0")
            && seen
                .iter()
                .all(|(n, v)| states[k].get(n) == Some(v) || states[k + 1].get(n) == Some(v))
        {
            // Every node is complete (old or new), but not all from one state. Counted and
            // tolerated only with NEUVOLEX_CRASH_STRICT=0 (steps publish their outputs in one
            // commit, so by default this is a failure).
            t.mixed_nodes += 1;
        } else {
            let diff: Vec<String> = seen
                .iter()
                .filter(|(n, v)| states[k].get(*n) != Some(v) && states[k + 1].get(*n) != Some(v))
                .map(|(n, v)| format!("{n}={v}"))
                .collect();
            t.failures.push(format!(
                "kill {i} at {at:.3} s in step {k} ({:?}): a mixed or unreadable store: {diff:?} (nodes in neither state), whole {seen:?}",
                stage.steps[k][0]
            ));
            continue;
        }
        // Resume or re-run the interrupted step, then the rest.
        let mut ok = true;
        for s in k..stage.steps.len() {
            let a = stage.rerun(s, &work);
            let o = command(&work, &a).output().unwrap();
            if !o.status.success() {
                t.failures.push(format!(
                    "kill {i} at {at:.3} s: re-run {a:?} failed: {}",
                    String::from_utf8_lossy(&o.stderr)
                ));
                ok = false;
                break;
            }
        }
        if !ok {
            continue;
        }
        let end = digest(&work.join("st.zarr"));
        if end != states[stage.steps.len()] {
            t.failures.push(format!(
                "kill {i} at {at:.3} s: the re-run's result differs from the uninterrupted run: {end:?} vs {:?}",
                states[stage.steps.len()]
            ));
            continue;
        }
        t.settle(i, at, &shape(&files(&work)), &final_files);
    }
    t.summarise(stage.name, total);
    t
}

#[test]
fn sigkill_at_random_points_leaves_a_complete_store_and_resumes_to_the_same_result() {
    let kills = env_num("NEUVOLEX_CRASH_KILLS", 6) as usize;
    let only = std::env::var("NEUVOLEX_CRASH_STAGE").ok();
    let mut rng = Rng(env_num("NEUVOLEX_CRASH_SEED", 16));
    let inp = Inputs::new();
    let mut failures = Vec::new();
    for (stage, setup) in stages(&inp) {
        if only.as_deref().is_some_and(|o| !stage.name.starts_with(o)) {
            continue;
        }
        let t = kill_stage(&stage, &setup, kills, &mut rng);
        failures.extend(t.failures.iter().map(|f| format!("{}: {f}", stage.name)));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The strokes of the server stages' earlier state (the step sends [`support::phantom_strokes`]).
fn earlier_strokes() -> Value {
    json!([
        {"class": 1, "axis": "z", "slice": 20, "points": [[22, 29], [26, 31]], "radius": 2.0},
        {"class": 255, "axis": "z", "slice": 20, "points": [[3, 3], [12, 3]], "radius": 2.0}
    ])
}

/// A step run in `neuvolex serve`. Each run starts from a fresh copy of the stage's base
/// folder (`data/phantom.zarr` and the server's `work/`).
struct ServerStage {
    name: &'static str,
    /// Makes the stage's base folder: the state the step replaces.
    setup: fn(&Server),
    /// Brings a fresh server to the start of the step; the session id.
    prepare: fn(&Server) -> String,
    /// The step's requests; true when every one succeeded.
    step: fn(&str, &str) -> bool,
    /// What a reader sees in the run's folder.
    digest: fn(&Path) -> State,
    /// The folder (in the run's folder) checked for debris.
    files_under: &'static str,
}

fn export_prepare(srv: &Server) -> String {
    let id = open_phantom(&srv.addr, false);
    classify_strokes(&srv.addr, &id, &support::phantom_strokes());
    id
}

fn export_step(addr: &str, id: &str) -> bool {
    let r = try_http(
        addr,
        "POST",
        &format!("/api/sessions/{id}/export/zarr"),
        &[],
        Some(&json!({"name": "nx"})),
    );
    matches!(r, Ok((200, _)))
}

fn export_digest(run: &Path) -> State {
    digest(&run.join("data/phantom.zarr"))
}

fn save_prepare(srv: &Server) -> String {
    open_phantom(&srv.addr, true)
}

fn save_step(addr: &str, id: &str) -> bool {
    let put = try_http(
        addr,
        "PUT",
        &format!("/api/sessions/{id}/strokes"),
        &[],
        Some(&support::phantom_strokes()),
    );
    let del = try_http(addr, "DELETE", &format!("/api/sessions/{id}"), &[], None);
    matches!(put, Ok((202, _))) && matches!(del, Ok((204, _)))
}

/// The saved sessions as a reader sees them: each file (by name) whole, without the time it
/// was saved and its label rounds (which follow how far classification got before the step),
/// and whether every label brick the files list is there and reads.
fn save_digest(run: &Path) -> State {
    let dir = run.join("work/sessions");
    let mut st = State::new();
    let mut whole = true;
    for e in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.extension().is_none_or(|x| x != "json") {
            continue;
        }
        let v = match std::fs::read(&p) {
            Err(_) => "absent".to_string(),
            Ok(b) => match serde_json::from_slice::<Value>(&b) {
                Ok(mut v) => {
                    for r in v["rounds"].as_array().into_iter().flatten() {
                        for b in r["bricks"].as_array().into_iter().flatten() {
                            let name = b[1].as_str().unwrap_or("");
                            let f = dir.join("labels").join(format!("{name}.zst"));
                            whole &= std::fs::read(&f)
                                .ok()
                                .and_then(|z| zstd::decode_all(&z[..]).ok())
                                .is_some();
                        }
                    }
                    let o = v.as_object_mut().unwrap();
                    o.remove("saved_ms");
                    o.remove("rounds");
                    v.to_string()
                }
                Err(e) => format!("unreadable: {e}"),
            },
        };
        st.insert(format!("session {}", e.file_name().to_string_lossy()), v);
    }
    st.insert("label bricks listed are whole".into(), whole.to_string());
    st
}

/// The server stages and how their base folder is made: the export over an earlier export of
/// other strokes (`labels/nx`, `nx_proba`), the session save over a saved session of other
/// strokes.
fn server_stages() -> Vec<ServerStage> {
    fn earlier_export(srv: &Server) {
        let id = open_phantom(&srv.addr, false);
        classify_strokes(&srv.addr, &id, &earlier_strokes());
        assert!(export_step(&srv.addr, &id));
    }
    fn earlier_save(srv: &Server) {
        let id = open_phantom(&srv.addr, false);
        let (st, _) = http(
            &srv.addr,
            "PUT",
            &format!("/api/sessions/{id}/strokes"),
            &[],
            Some(&earlier_strokes()),
        );
        assert_eq!(st, 202);
        let (st, _) = http(
            &srv.addr,
            "DELETE",
            &format!("/api/sessions/{id}"),
            &[],
            None,
        );
        assert_eq!(st, 204);
    }
    vec![
        ServerStage {
            name: "OME-Zarr export",
            setup: earlier_export,
            prepare: export_prepare,
            step: export_step,
            digest: export_digest,
            files_under: "data/phantom.zarr",
        },
        ServerStage {
            name: "session save",
            setup: earlier_save,
            prepare: save_prepare,
            step: save_step,
            digest: save_digest,
            files_under: "work/sessions",
        },
    ]
}

fn kill_server_stage(stage: &ServerStage, kills: usize, rng: &mut Rng) -> Tally {
    let root = tempfile::tempdir().unwrap();
    let base = root.path().join("base");
    let run = root.path().join("run");
    std::fs::create_dir_all(&base).unwrap();
    let data = support::data_root(&base);
    // The background feature pass writes its own resumable array into the store as the
    // servers here start and stop, at times no two runs share; it is kept out so the files
    // compared are the step's alone (the resumable writer has its own kill test,
    // `sigkill_at_random_points_leaves_a_complete_store_and_resumes_to_the_same_result`).
    const STEP_ONLY: &[&str] = &["--feature-store-gib=0"];
    {
        let srv = Server::start(&base, &data, STEP_ONLY, &[]);
        (stage.setup)(&srv);
    }
    for e in std::fs::read_dir(&base).unwrap().flatten() {
        if e.file_name().to_string_lossy().ends_with(".log") {
            std::fs::remove_file(e.path()).unwrap();
        }
    }
    let start = |dir: &Path| Server::start(dir, &dir.join("data"), STEP_ONLY, &[]);
    // The reference: the step uninterrupted, its duration and the state before and after.
    copy_dir(&base, &run);
    let before = (stage.digest)(&run);
    let total = {
        let srv = start(&run);
        let id = (stage.prepare)(&srv);
        let t = Instant::now();
        assert!(
            (stage.step)(&srv.addr, &id),
            "{}: the step failed",
            stage.name
        );
        t.elapsed().as_secs_f64()
    };
    let after = (stage.digest)(&run);
    assert_ne!(
        before, after,
        "{}: the step must change the state",
        stage.name
    );
    let final_files = shape(&files(&run.join(stage.files_under)));
    let mut t = Tally::default();
    for i in 0..kills {
        copy_dir(&base, &run);
        let at = rng.unit() * total * 1.1;
        {
            let mut srv = start(&run);
            let id = (stage.prepare)(&srv);
            let (addr, step) = (srv.addr.clone(), stage.step);
            let h = std::thread::spawn(move || step(&addr, &id));
            std::thread::sleep(Duration::from_secs_f64(at));
            if !h.is_finished() {
                t.killed_running += 1;
            }
            let _ = srv.child.kill(); // SIGKILL
            let _ = srv.child.wait();
            let _ = h.join();
        }
        t.kills += 1;
        let seen = (stage.digest)(&run);
        if seen == before {
            t.saw_before += 1;
        } else if seen == after {
            t.saw_after += 1;
        } else {
            let diff: Vec<String> = seen
                .iter()
                .filter(|(n, v)| before.get(*n) != Some(v) && after.get(*n) != Some(v))
                .map(|(n, v)| format!("{n}={v}"))
                .collect();
            t.failures.push(format!(
                "kill {i} at {at:.3} s: neither the state before nor after: {diff:?} (nodes in neither), whole {seen:?}"
            ));
            continue;
        }
        // A re-run on a new server.
        {
            let srv = start(&run);
            let id = (stage.prepare)(&srv);
            if !(stage.step)(&srv.addr, &id) {
                t.failures
                    .push(format!("kill {i} at {at:.3} s: the re-run failed"));
                continue;
            }
        }
        let end = (stage.digest)(&run);
        if end != after {
            t.failures.push(format!(
                "kill {i} at {at:.3} s: the re-run's result differs from the uninterrupted run: {end:?} vs {after:?}"
            ));
            continue;
        }
        t.settle(
            i,
            at,
            &shape(&files(&run.join(stage.files_under))),
            &final_files,
        );
    }
    t.summarise(stage.name, total);
    t
}

#[test]
fn sigkill_in_the_server_keeps_exports_and_saved_sessions_whole() {
    let kills = env_num(
        "NEUVOLEX_CRASH_SERVER_KILLS",
        env_num("NEUVOLEX_CRASH_KILLS", 4),
    ) as usize;
    let only = std::env::var("NEUVOLEX_CRASH_STAGE").ok();
    let mut rng = Rng(env_num("NEUVOLEX_CRASH_SEED", 16));
    let mut failures = Vec::new();
    for stage in server_stages() {
        if only.as_deref().is_some_and(|o| !stage.name.starts_with(o)) {
            continue;
        }
        let t = kill_server_stage(&stage, kills, &mut rng);
        failures.extend(t.failures.iter().map(|f| format!("{}: {f}", stage.name)));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A tmpfs of `mb` MiB at a new folder, unmounted and removed on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(mb: u64) -> Option<Self> {
        let dir = tempfile::tempdir().unwrap();
        let o = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(dir.path())
            .output();
        match o {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            o => {
                let why = match o {
                    Ok(o) => String::from_utf8_lossy(&o.stderr).into_owned(),
                    Err(e) => e.to_string(),
                };
                assert!(
                    std::env::var("CI").as_deref() != Ok("true"),
                    "cannot mount a tmpfs for the disk-full test under CI: {why}"
                );
                eprintln!("SKIPPED disk-full test: cannot mount a tmpfs ({why})");
                None
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

/// Fills the file system of `dir` up to `leave` bytes with `dir/filler`.
fn fill(dir: &Path, leave: u64) -> PathBuf {
    let p = dir.join("filler");
    let mut f = std::fs::File::create(&p).unwrap();
    let mut n = 0u64;
    // Large blocks, then smaller ones down to single bytes: nothing is left over.
    for size in [1usize << 16, 4096, 1] {
        let block = vec![0x5au8; size];
        while let Ok(k @ 1..) = f.write(&block) {
            n += k as u64;
        }
    }
    let _ = f.flush();
    f.set_len(n.saturating_sub(leave)).unwrap();
    p
}

#[test]
fn a_full_disk_gives_a_clear_error_and_keeps_the_previous_store() {
    let Some(fs) = Tmpfs::mount(96) else {
        return;
    };
    let inp = Inputs::new();
    for (stage, setup) in stages(&inp) {
        let work = fs.dir.path().join("work");
        if work.exists() {
            std::fs::remove_dir_all(&work).unwrap();
        }
        std::fs::create_dir_all(&work).unwrap();
        for s in &setup {
            run_ok(&work, s);
        }
        for (k, step) in stage.steps.iter().enumerate() {
            let before = digest(&work.join("st.zarr"));
            let filler = fill(fs.dir.path(), 48 << 10);
            let o = command(&work, step).output().unwrap();
            let err = String::from_utf8_lossy(&o.stderr);
            assert!(
                !o.status.success(),
                "{}: {step:?} succeeded on a full disk",
                stage.name
            );
            assert!(!err.contains("panicked"), "{}: panic: {err}", stage.name);
            assert!(
                err.contains("No space left on device") || err.contains("no space"),
                "{}: {step:?} does not say the disk is full: {err}",
                stage.name
            );
            let fs_root = fs.dir.path().to_string_lossy();
            assert!(
                err.contains(fs_root.as_ref()) || err.contains("st.zarr"),
                "{}: {step:?}: the error names no path: {err}",
                stage.name
            );
            assert_eq!(
                digest(&work.join("st.zarr")),
                before,
                "{}: {step:?} on a full disk changed the store",
                stage.name
            );
            eprintln!(
                "disk full, {} step {k} ({}): {}",
                stage.name,
                step[0],
                err.lines().last().unwrap_or_default()
            );
            std::fs::remove_file(filler).unwrap();
            // With space again, the step completes.
            run_ok(&work, &stage.rerun(k, &work));
        }
    }
}

/// The server's OME-Zarr export and session save on a full disk (the data root and the work
/// folder on a tmpfs filled to the last byte): 507 with an error naming the path and the
/// cause, the previous store or saved session intact (the session stays open, so nothing is
/// lost), and the same request succeeds once there is space again.
#[test]
fn a_full_disk_in_the_server_gives_a_clear_error_and_keeps_the_previous_state() {
    let Some(fs) = Tmpfs::mount(96) else {
        return;
    };
    // The server's log stays off the full disk; its data and work folder are on it.
    let logs = tempfile::tempdir().unwrap();
    for stage in server_stages() {
        let base = fs.dir.path().join("base");
        if base.exists() {
            std::fs::remove_dir_all(&base).unwrap();
        }
        std::fs::create_dir_all(base.join("work")).unwrap();
        let d = logs.path().join(stage.name.replace(' ', "-"));
        std::fs::create_dir_all(&d).unwrap();
        std::os::unix::fs::symlink(base.join("work"), d.join("work")).unwrap();
        let data = support::data_root(&base);
        // No background feature pass (`--feature-store-gib 0`): it writes into the same store,
        // and a pass that failed on the full disk and removed its partial array freed room
        // for the request under test (seen once in a local CI run). Only the request writes.
        let quiet = ["--feature-store-gib", "0"];
        {
            let srv = Server::start(&d, &data, &quiet, &[]);
            (stage.setup)(&srv);
        }
        let srv = Server::start(&d, &data, &quiet, &[]);
        let id = (stage.prepare)(&srv);
        let before = (stage.digest)(&base);
        let filler = fill(fs.dir.path(), 0);
        let (path, method, uri, body) = if stage.name.contains("export") {
            (
                "phantom.zarr".to_string(),
                "POST",
                format!("/api/sessions/{id}/export/zarr"),
                Some(json!({"name": "nx"})),
            )
        } else {
            let (st, _) = http(
                &srv.addr,
                "PUT",
                &format!("/api/sessions/{id}/strokes"),
                &[],
                Some(&support::phantom_strokes()),
            );
            assert_eq!(st, 202);
            (
                format!("sessions/{id}.json"),
                "DELETE",
                format!("/api/sessions/{id}"),
                None,
            )
        };
        let (st, err) = http(&srv.addr, method, &uri, &[], body.as_ref());
        assert_eq!(
            st, 507,
            "{}: {method} {uri} on a full disk: {err}",
            stage.name
        );
        assert!(
            err.contains("No space left on device") && err.contains(path.as_str()),
            "{}: the error names neither the cause nor {path}: {err}",
            stage.name
        );
        assert_eq!(
            (stage.digest)(&base),
            before,
            "{}: a full disk changed the previous state",
            stage.name
        );
        eprintln!("disk full, server {}: {st} {err}", stage.name);
        // The NIfTI exports go through the work folder: refused the same way (filled again:
        // the refused export gave back what it had written).
        if stage.name.contains("export") {
            std::fs::remove_file(&filler).unwrap();
            fill(fs.dir.path(), 0);
            let (st, err) = http(
                &srv.addr,
                "GET",
                &format!("/api/sessions/{id}/export/labels.nii.gz"),
                &[],
                None,
            );
            assert_eq!(st, 507, "labels.nii.gz on a full disk: {err}");
            assert!(err.contains("No space left on device"), "{err}");
        }
        std::fs::remove_file(filler).unwrap();
        // With space again, the same request completes (the session was kept open).
        let (st2, body2) = http(&srv.addr, method, &uri, &[], body.as_ref());
        assert!(
            st2 == 200 || st2 == 204,
            "{}: after freeing space: {st2} {body2}",
            stage.name
        );
        assert_ne!((stage.digest)(&base), before, "{}", stage.name);
    }
}

#[test]
fn a_second_writer_is_refused_with_the_store_and_the_holder() {
    let inp = Inputs::new();
    let d = tempfile::tempdir().unwrap();
    let w = d.path();
    let all = stages(&inp);
    // A trained store: every writer has something to do.
    for s in &all[2].1 {
        run_ok(w, s);
    }
    let pristine = d.path().join("pristine");
    copy_dir(&w.join("st.zarr"), &pristine);
    run_ok(w, &args(&["features", "st.zarr"]));
    let reference = digest(&w.join("st.zarr"));
    let others = [
        all[0].0.steps[0].clone(),
        all[1].0.steps[0].clone(),
        args(&["features", "st.zarr"]),
        all[3].0.steps[0].clone(),
    ];
    let lock = w.join("st.zarr/neuvolex/writer.lock");
    for other in &others {
        let mut refused = false;
        for _attempt in 0..10 {
            copy_dir(&pristine, &w.join("st.zarr"));
            // The holder: feature extraction, a few seconds on this store.
            let mut holder = command(w, &args(&["features", "st.zarr"]))
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap();
            let pid = holder.id().to_string();
            let t = Instant::now();
            while !std::fs::read_to_string(&lock).is_ok_and(|s| s.contains(&pid))
                && t.elapsed() < Duration::from_secs(20)
            {
                std::thread::sleep(Duration::from_millis(5));
            }
            let o = command(w, other).output().unwrap();
            let still = holder.try_wait().unwrap().is_none();
            let h = holder.wait_with_output().unwrap();
            assert!(
                h.status.success(),
                "the holder failed: {}",
                String::from_utf8_lossy(&h.stderr)
            );
            let err = String::from_utf8_lossy(&o.stderr);
            if o.status.success() {
                assert!(!still, "{other:?} ran beside a writer");
                continue; // the holder had finished first: try again
            }
            assert!(
                err.contains("st.zarr") && err.contains(&format!("pid {pid}")),
                "{other:?} beside a writer: the error names neither the store nor the holder: {err}"
            );
            eprintln!("second writer {:?}: {}", other[0], err.trim());
            refused = true;
            break;
        }
        assert!(
            refused,
            "{other:?}: never ran while the holder held the lock"
        );
        // The holder's result is intact.
        assert_eq!(digest(&w.join("st.zarr")), reference, "after {other:?}");
    }
}
