//! Scaling of the distributed stages on NATS JetStream: ingest (slab tasks reading a shared
//! file), classification (prediction into the store), feature extraction, and Lloyd k-means
//! with view partials (both volumes), in one process and on
//! 1, 2 and 4 worker processes, on the abdomen CT and a 512x512x452 volume (the CT-like
//! phantom at CTA scale). Per stage and worker count: wall time, mean work per task, queue
//! overhead per task (the worker's fetch, decode, result publish and ack around the work), bytes
//! through the queue and written to the store.
//!
//! Bytes through the store are the store layer's counters (`neuvolex_bricks::store_io`), summed
//! over the tasks wherever they ran. The queue's own cost is measured first, with tasks that do
//! no work: publish, delivery, result and ack per task (`R_q`, tasks per second).
//!
//! `cargo bench -p neuvolex-benches --bench cluster` (needs nats-server, which
//! deploy/test.sh or deploy/cluster.sh install). `NEUVOLEX_BENCH_BIG=0` skips the large volume.
//! Workers are this binary re-executed with `--worker`, one process each. Results also go to
//! `benches/results/cluster.json`. `NEUVOLEX_BENCH_WORKERS=1,2` picks the worker counts
//! (default 1,2,4) and `NEUVOLEX_BENCH_WORKER_THREADS` each worker's threads (default: the two
//! cores shared); `NEUVOLEX_BENCH_OUT` moves the JSON report. `NEUVOLEX_BENCH_STAGES=classify`
//! (a comma list of `queue`, `ingest`, `classify`, `features`, `kmeans`; default all) runs only
//! the stages named. `NEUVOLEX_BENCH_S3=1` puts the stores on an S3 server (s3s-fs from
//! `deploy/s3.sh install`, on loopback) instead of the local file system.

use neuvolex_bricks::BrickStore;

use neuvolex_classify::pipeline::{classify, ClassifyRequest, FeatureSpec, OpenedFeatures};
use neuvolex_classify::{ClassifyConfig, FeatureSet};
use neuvolex_cluster::{ClusterExecutor, EngineConfig, WorkerOptions};
use neuvolex_ingest::IngestOptions;
use neuvolex_tasks::{plan, DynStage, Executor, LocalExecutor, RunReport, Stage, Task, TaskCtx};
use neuvolex_viewpoints::distributed::recommend_on;
use neuvolex_viewpoints::{KMeansConfig, RecommendConfig};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Workers(Vec<Child>);

impl Drop for Workers {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn start_workers(url: &str, n: usize) -> Workers {
    let exe = std::env::current_exe().expect("exe");
    // Each worker's rayon threads: `NEUVOLEX_BENCH_WORKER_THREADS`, else the 2 cores shared.
    let threads = std::env::var("NEUVOLEX_BENCH_WORKER_THREADS")
        .ok()
        .and_then(|t| t.parse().ok())
        .unwrap_or((2 / n).max(1));
    let ws = (0..n)
        .map(|i| {
            Command::new(&exe)
                .args(["--worker", url, &format!("w{i}"), &threads.to_string()])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("worker")
        })
        .collect();
    // Let them connect before timing.
    std::thread::sleep(Duration::from_millis(800));
    Workers(ws)
}

#[derive(serde::Serialize)]
struct Row {
    volume: String,
    stage: String,
    workers: usize,
    tasks: usize,
    wall_s: f64,
    work_ms_per_task: f64,
    queue_ms_per_task: f64,
    queue_share: f64,
    queue_bytes: u64,
    /// Bytes the stage's tasks read from the store.
    store_read: u64,
    /// Bytes the stage's tasks wrote to the store.
    store_written: u64,
    /// Seconds on the coordinator alone after the tasks (classification: assembling and
    /// publishing the label image; 0 where the stage does not report it).
    after_tasks_s: f64,
}

fn row(volume: &str, stage: &str, workers: usize, r: &RunReport, wall: f64) -> Row {
    let n = r.completed.max(1) as f64;
    let w = r.work_seconds / n;
    let q = r.queue_seconds / n;
    let row = Row {
        volume: volume.into(),
        stage: stage.into(),
        workers,
        tasks: r.completed,
        wall_s: wall,
        work_ms_per_task: w * 1e3,
        queue_ms_per_task: q * 1e3,
        queue_share: if w > 0.0 { q / w } else { 0.0 },
        queue_bytes: r.queue_bytes,
        store_read: r.store_read_bytes,
        store_written: r.store_written_bytes,
        after_tasks_s: 0.0,
    };
    println!(
        "| {} | {} | {} | {} | {:.2} | {:.1} | {:.2} ({:.1}%) | {:.2} | {:.1} | {:.1} |",
        row.volume,
        row.stage,
        if workers == 0 {
            "in process".to_string()
        } else {
            workers.to_string()
        },
        row.tasks,
        row.wall_s,
        row.work_ms_per_task,
        row.queue_ms_per_task,
        100.0 * row.queue_share,
        row.queue_bytes as f64 / 1e6,
        row.store_read as f64 / 1e6,
        row.store_written as f64 / 1e6,
    );
    row
}

/// Ingest of `source` into a fresh store beside `store` (slab tasks; default options).
fn ingest_stage<E: Executor>(
    exec: &E,
    workers: usize,
    volume: &str,
    source: &Path,
    store: &Path,
    rows: &mut Vec<Row>,
) {
    let out = PathBuf::from(format!("{}.ingest.zarr", store.display()));
    let t = Instant::now();
    let (_, r) = neuvolex_ingest::ingest_on(
        exec,
        source,
        None,
        None,
        &neuvolex_bricks::StoreLocation::from(&out),
        &IngestOptions {
            overwrite: true,
            ..IngestOptions::default()
        },
        1,
        &mut |_| {},
    )
    .expect("ingest");
    let wall = t.elapsed().as_secs_f64();
    rows.push(row(volume, "ingest", workers, &r, wall));
    let _ = std::fs::remove_dir_all(&out);
}

#[allow(clippy::too_many_arguments)]
fn stages<E: Executor>(
    exec: &E,
    workers: usize,
    volume: &str,
    store: &Path,
    scribbles: &Path,
    features: bool,
    big: bool,
    rows: &mut Vec<Row>,
) {
    if !wanted("classify") {
        return kmeans_and_features(exec, workers, volume, store, features, rows);
    }
    // Every run computes every brick: drop pending generations an interrupted run left.
    if let Ok(s) = BrickStore::open(store) {
        for name in ["classes_proba", "classes_labels", "inr_hidden"] {
            let _ = s.discard_pending_vectors(name);
        }
    }
    // Classification: the forest (50 trees) on local features (the large volume: 20 trees on
    // intensity, to bound the bench's time), prediction into the store.
    let req = ClassifyRequest {
        store: store.to_path_buf(),
        scribbles: scribbles.to_path_buf(),
        features: if big { "intensity" } else { "local" }.parse().unwrap(),
        classes: None,
        out: None,
        force: true,
        stored_features: false,
        config: ClassifyConfig {
            forest: neuvolex_classify::ForestConfig {
                trees: if big { 20 } else { 50 },
                class_weight: neuvolex_classify::ClassWeight::Balanced,
                ..Default::default()
            },
            ..ClassifyConfig::default()
        },
        bricks_per_task: 1,
        prior: None,
        hold: None,
        gpu: false,
    };
    let t = Instant::now();
    let o = classify(&req, exec, &mut |_| {}).expect("classify");
    let wall =
        t.elapsed().as_secs_f64() - o.report.seconds_training_features - o.report.seconds_fit;
    let mut r = row(volume, "classify", workers, &o.report.run, wall);
    r.after_tasks_s = o.report.seconds_assemble + o.report.seconds_publish;
    println!(
        "  classify after the tasks: labels assembled in {:.2} s, published in {:.2} s; prediction {:.2} s",
        o.report.seconds_assemble, o.report.seconds_publish, o.report.seconds_classify
    );
    rows.push(r);
    kmeans_and_features(exec, workers, volume, store, features, rows);
}

/// Whether stage `name` runs (`NEUVOLEX_BENCH_STAGES`, default every stage).
fn wanted(name: &str) -> bool {
    std::env::var("NEUVOLEX_BENCH_STAGES")
        .map(|v| v.split(',').any(|s| s.trim() == name))
        .unwrap_or(true)
}

/// The stages after classification: feature extraction (where `features`) and k-means with
/// view partials.
fn kmeans_and_features<E: Executor>(
    exec: &E,
    workers: usize,
    volume: &str,
    store: &Path,
    features: bool,
    rows: &mut Vec<Row>,
) {
    // Feature extraction (the INR's 64-D hidden layer).
    if features && wanted("features") {
        let s = BrickStore::open(store).expect("store");
        let model = neuvolex_classify::pipeline::load_model(&s)
            .expect("model")
            .expect("trained");
        let t = Instant::now();
        let (_, r) = neuvolex_features::stage::write_features_on(
            exec,
            &s,
            &store.display().to_string(),
            model,
            neuvolex_features::FeatureKind::Hidden,
            false,
            1,
            &mut |_| {},
        )
        .expect("features");
        let wall = t.elapsed().as_secs_f64();
        rows.push(row(volume, "features", workers, &r, wall));
    }
    if !wanted("kmeans") {
        return;
    }
    // Lloyd k-means (k = 16, 10 iterations) and the view partials, on local features (both
    // volumes: on the large one the adaptive batching is not capped by the brick count).
    let set: FeatureSet = "local".parse().unwrap();
    let src = OpenedFeatures {
        store: std::sync::Arc::new(BrickStore::open(store).expect("store")),
        model: None,
        spec: FeatureSpec::new(store, &set, false, None),
        set,
        model_bytes: None,
    };
    let cfg = RecommendConfig {
        kmeans: KMeansConfig {
            k: 16,
            max_iter: 10,
            ..Default::default()
        },
        views: 600,
        ..Default::default()
    };
    let t = Instant::now();
    let (_, r) = recommend_on(exec, src, &cfg, 1, &mut |_| {}, &mut |_, _| {}).expect("kmeans");
    rows.push(row(
        volume,
        "kmeans+views",
        workers,
        &r,
        t.elapsed().as_secs_f64(),
    ));
}

/// A stage that does nothing: its tasks measure the queue alone.
struct Noop;

const NOOP: &str = "bench-noop";

impl Stage for Noop {
    type Output = u32;
    fn name(&self) -> &'static str {
        NOOP
    }
    fn params(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    fn run(&self, task: &Task, _: &TaskCtx<'_>) -> neuvolex_tasks::Result<u32> {
        Ok(task.index)
    }
}

fn noop_build(
    _: &serde_json::Value,
    _: &dyn neuvolex_tasks::Blobs,
) -> neuvolex_tasks::Result<std::sync::Arc<dyn DynStage>> {
    Ok(std::sync::Arc::new(Noop))
}

/// The queue's cost per task: `n` tasks without work through the coordinator and the workers
/// (publish, pull, result stored, ack, coordinator decode), three times; prints R_q.
fn queue_rows<E: Executor>(exec: &E, workers: usize, n: usize, rows: &mut Vec<Row>) {
    let bricks: Vec<[usize; 3]> = (0..n).map(|i| [i, 0, 0]).collect();
    let tasks = plan(&bricks, 1, 0);
    for _ in 0..3 {
        let t = Instant::now();
        let r = exec.execute(&Noop, &tasks, &mut |_| {}).expect("noop run");
        let wall = t.elapsed().as_secs_f64();
        assert_eq!(r.completed, n);
        eprintln!(
            "queue: {n} empty tasks on {workers} workers in {wall:.2} s: R_q = {:.0} tasks/s",
            n as f64 / wall
        );
        rows.push(row("none", "queue (empty tasks)", workers, &r, wall));
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("--worker") {
        let threads: usize = args.get(4).and_then(|t| t.parse().ok()).unwrap_or(1);
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global();
        let _ = neuvolex_cluster::serve(
            EngineConfig::new(&args[2]),
            neuvolex_cluster::standard_registry().with(NOOP, noop_build),
            WorkerOptions {
                name: args.get(3).cloned(),
                ..Default::default()
            },
            &mut |_| {},
        );
        return;
    }
    if args.iter().any(|a| a == "--list" || a == "--test") {
        return;
    }
    let tmp = tempfile::tempdir().expect("tmp");
    let Some(nats) = neuvolex_tests::NatsServer::start(tmp.path(), "127.0.0.1", &[]) else {
        return;
    };
    let url = nats.url();
    println!("machine: {}", neuvolex_benches::machine());
    // Stores on an S3 server instead of the local file system: the workers inherit the AWS_*
    // environment set here.
    let s3 = if std::env::var("NEUVOLEX_BENCH_S3").is_ok_and(|v| v == "1") {
        let Some(s3) = neuvolex_tests::S3Server::start() else {
            eprintln!("SKIP: NEUVOLEX_BENCH_S3=1 needs s3s-fs (deploy/s3.sh install)");
            return;
        };
        for (k, v) in s3.env() {
            std::env::set_var(k, v);
        }
        println!("stores on s3s-fs at {} (bucket test)", s3.endpoint);
        Some(s3)
    } else {
        None
    };
    let root = |name: &str| -> PathBuf {
        match &s3 {
            Some(_) => PathBuf::from(format!("s3://test/{name}")),
            None => tmp.path().join(name),
        }
    };
    println!(
        "\n| volume | stage | workers | tasks | wall s | work ms/task | queue ms/task (share) | queue MB | store read MB | store written MB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    // (name, store, scribbles, features, big, source file for the ingest stage)
    type Vol = (String, PathBuf, PathBuf, bool, bool, PathBuf);
    let mut vols: Vec<Vol> = Vec::new();
    if let (Some(ct), Some(lab)) = (
        neuvolex_benches::shared("abdomen_ct/ct.nii.gz"),
        neuvolex_benches::shared("abdomen_ct/labels.nii.gz"),
    ) {
        let p = root("abdomen.zarr");
        let mut src = neuvolex_bricks::open_volume(&ct, None).expect("ct");
        neuvolex_ingest::ingest(src.as_mut(), &p, &IngestOptions::default(), &mut |_| {})
            .expect("ingest");
        let s = BrickStore::open(&p).expect("store");
        let model = neuvolex_benches::train_one_epoch(&s);
        neuvolex_features::checkpoint::save(neuvolex_features::train::model_path(&s), &model, None)
            .expect("model");
        vols.push((
            "abdomen CT 122x101x112".into(),
            p,
            scribbles(&lab, tmp.path(), "ct"),
            true,
            false,
            ct.clone(),
        ));
    }
    // The large volume stays on the local file system (S3 mode measures the abdomen).
    if s3.is_none()
        && std::env::var("NEUVOLEX_BENCH_BIG")
            .map(|v| v != "0")
            .unwrap_or(true)
    {
        let p = root("big.zarr");
        let params = neuvolex_bricks::synth::PhantomParams {
            dims: [512, 512, 452],
            ..neuvolex_bricks::synth::PhantomParams::with_size(512, 0)
        };
        neuvolex_ingest::phantom_store(&p, params, &IngestOptions::default(), &mut |_| {})
            .expect("phantom");
        let lab = p.join("labels/ground_truth");
        // The ingest stage reads the phantom as an uncompressed NIfTI (memory-mapped).
        let nii = tmp.path().join("big.nii");
        neuvolex_formats::nifti::write_nifti(
            &nii,
            &mut neuvolex_bricks::synth::Phantom::new(
                params,
                neuvolex_bricks::synth::PhantomChannel::Image,
            ),
            16,
        )
        .expect("phantom NIfTI");
        vols.push((
            "phantom 512x512x452".into(),
            p.clone(),
            scribbles(&lab, tmp.path(), "big"),
            false,
            true,
            nii,
        ));
    }
    let counts: Vec<usize> = std::env::var("NEUVOLEX_BENCH_WORKERS")
        .ok()
        .map(|v| v.split(',').filter_map(|w| w.trim().parse().ok()).collect())
        .filter(|v: &Vec<usize>| !v.is_empty())
        .unwrap_or_else(|| vec![1, 2, 4]);
    let mut rows = Vec::new();
    let queue_tasks: usize = std::env::var("NEUVOLEX_BENCH_QUEUE_TASKS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    for &w in &counts {
        let _ws = start_workers(&url, w);
        let ex = ClusterExecutor::connect(EngineConfig::new(&url)).expect("connect");
        if wanted("queue") {
            queue_rows(&ex, w, queue_tasks, &mut rows);
        }
    }
    for (name, store, scr, features, big, source) in &vols {
        let local = LocalExecutor::new();
        if wanted("ingest") {
            ingest_stage(&local, 0, name, source, store, &mut rows);
        }
        stages(&local, 0, name, store, scr, *features, *big, &mut rows);
        for &w in &counts {
            let _ws = start_workers(&url, w);
            let ex = ClusterExecutor::connect(EngineConfig::new(&url)).expect("connect");
            if wanted("ingest") {
                ingest_stage(&ex, w, name, source, store, &mut rows);
            }
            stages(&ex, w, name, store, scr, *features, *big, &mut rows);
        }
    }
    drop(nats);
    let out = std::env::var_os("NEUVOLEX_BENCH_OUT").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("results/cluster.json"),
        PathBuf::from,
    );
    let _ = std::fs::write(
        &out,
        serde_json::to_string_pretty(&serde_json::json!({
            "machine": neuvolex_benches::machine(),
            "store": if s3.is_some() { "s3s-fs on loopback" } else { "local file system" },
            "rows": rows,
        }))
        .unwrap_or_default(),
    );
    println!("\nresults: {}", out.display());
}

/// S2 scribbles simulated from ground truth, as NIfTI.
fn scribbles(labels: &Path, dir: &Path, name: &str) -> PathBuf {
    use neuvolex_classify::{simulate, Level, ScribbleSource, SimConfig};
    let mut src = neuvolex_bricks::open_volume(labels, None).expect("labels");
    let meta = src.meta().clone();
    let (_, s) = simulate(
        src.as_mut(),
        &SimConfig {
            level: Level::S2,
            ..SimConfig::default()
        },
    )
    .expect("scribbles");
    let out = dir.join(format!("{name}_scr.nii.gz"));
    neuvolex_formats::nifti::write_nifti(&out, &mut ScribbleSource::new(s, &meta), 16)
        .expect("nifti");
    out
}
