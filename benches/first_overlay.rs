//! Time to the first overlay, as a user of `neuvolex serve` meets it
//! (`cargo bench -p neuvolex-benches --bench first_overlay`).
//!
//! The service in process (its actors, feature cache and event hub, no HTTP): a fresh server
//! (new work folder, nothing cached) opens the volume, a user draws a class stroke and a
//! background stroke on the middle axial slice (placed on the ground truth), and the bench
//! times, from the strokes' arrival:
//! - the first classified brick under the stroked slice (the overlay on the slice the user is
//!   looking at can be drawn);
//! - the whole volume.
//!
//! Then a second stroke on the same slice (features warm) the same way. Then the bench waits
//! for the session's background feature pass to have kept every brick's features in the store
//! (timed from the open), closes the session, starts a new server on the same work folder
//! ("reopened": nothing in memory, the features in the store) and times the first strokes
//! again. Volumes whose features pass `--feature-store-gib` (4 GiB) are not kept: `—`.
//!
//! Volumes: the abdomen CT (`../shared/data`, skipped where absent) and the 512x512x452
//! CT-like phantom (generated; whole-volume times only with `--full`, it takes minutes).
//! Repeats: `NEUVOLEX_BENCH_REPEATS` (default 3) fresh servers per volume.

use neuvolex_benches::{machine, shared};
use neuvolex_bricks::synth::PhantomParams;
use neuvolex_bricks::BrickStore;
use neuvolex_classify::scribble::Stroke;
use neuvolex_ingest::IngestOptions;
use neuvolex_server::{AppState, ServerConfig};
use std::path::Path;
use std::time::{Duration, Instant};

/// Seconds to the first brick under `slice` and to the whole volume (`None`: not waited for).
async fn classify_times(
    st: &AppState,
    s: &std::sync::Arc<neuvolex_server::session::Session>,
    strokes: Vec<Stroke>,
    slice: usize,
    full: bool,
) -> (f64, Option<f64>) {
    let mut rx = st.actors.hub.subscribe();
    let brick = s.store.info().brick;
    let t0 = Instant::now();
    let generation = s.set_strokes(strokes).expect("strokes");
    st.actors.classify(s.clone(), generation).expect("classify");
    let mut first = None;
    let deadline = Instant::now() + Duration::from_secs(1800);
    while Instant::now() < deadline {
        let Ok(Ok(e)) = tokio::time::timeout(Duration::from_secs(60), rx.recv()).await else {
            continue;
        };
        if e.session.as_deref() != Some(s.id.as_str()) {
            continue;
        }
        match e.kind.as_str() {
            "classified" if e.data["generation"] == generation => {
                let z = e.data["brick"][2].as_u64().unwrap_or(u64::MAX) as usize;
                if first.is_none() && z == slice / brick {
                    first = Some(t0.elapsed().as_secs_f64());
                    if !full {
                        // Stop the rest (make this run stale), and wait for it to end.
                        s.bump_generation();
                    }
                }
            }
            "classification" => {
                let st = &e.data["status"];
                if st["generation"] == generation && !full {
                    return (first.unwrap_or(f64::NAN), None);
                }
                if st["generation"] == generation && st["state"] != "training" {
                    assert_eq!(st["state"], "done", "{e:?}");
                    return (first.unwrap_or(f64::NAN), Some(t0.elapsed().as_secs_f64()));
                }
            }
            _ => {}
        }
    }
    panic!("classification did not finish in 30 minutes");
}

/// Waits for the background feature pass of `s` to announce every brick stored; seconds
/// since `t0`, or `None` when nothing is kept (over the limit) within `patience`.
async fn features_kept(
    rx: &mut tokio::sync::broadcast::Receiver<neuvolex_server::actors::Event>,
    s: &neuvolex_server::session::Session,
    t0: Instant,
    patience: Duration,
) -> Option<f64> {
    let deadline = Instant::now() + patience;
    while Instant::now() < deadline {
        let left = deadline.saturating_duration_since(Instant::now());
        let Ok(Ok(e)) = tokio::time::timeout(left, rx.recv()).await else {
            continue;
        };
        if e.kind == "features"
            && e.session.as_deref() == Some(s.id.as_str())
            && e.data["done"] == e.data["total"]
        {
            return Some(t0.elapsed().as_secs_f64());
        }
    }
    None
}

fn run_volume(name: &str, data: &Path, rel: &str, labels: &[u32], full: bool, repeats: usize) {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    for rep in 0..repeats {
        let work = tempfile::tempdir().expect("tmp");
        let cfg = ServerConfig::new(data.to_path_buf(), work.path().to_path_buf());
        rt.block_on(async {
            let st = AppState::new(cfg.clone());
            let mut events = st.actors.hub.subscribe();
            let t = Instant::now();
            let s = st.open(rel).await.expect("open");
            let open_s = t.elapsed().as_secs_f64();
            let dims = s.store.info().dims;
            let z = dims[2] / 2;
            let class = neuvolex_benches::main_class(labels, dims, z);
            let fresh = neuvolex_benches::strokes_on(labels, dims, z, class, 0);
            let (f1, a1) = classify_times(&st, &s, fresh.clone(), z, full).await;
            // Warm: one more stroke on the same slice.
            let mut more = fresh.clone();
            more.extend(neuvolex_benches::strokes_on(labels, dims, z, class, 2).into_iter().take(1));
            let (f2, a2) = classify_times(&st, &s, more, z, full).await;
            let fmt = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.2}"));
            // Opened on open when the volume's features fit the limit.
            let stored = s
                .stored_for(&neuvolex_server::session::default_features())
                .is_some();
            let kept = if stored {
                features_kept(&mut events, &s, t, Duration::from_secs(1800)).await
            } else {
                None
            };
            st.close(&s).expect("close");
            drop(st);
            // A new server on the same work folder: the features come from the store.
            let (f3, a3) = if kept.is_some() {
                let st = AppState::new(cfg.clone());
                let s = st.open(rel).await.expect("reopen");
                let (f, a) = classify_times(&st, &s, fresh.clone(), z, full).await;
                (format!("{f:.2}"), fmt(a))
            } else {
                ("—".into(), "—".into())
            };
            println!(
                "| {name} {dims:?} | {} | {open_s:.2} | {f1:.2} | {} | {f2:.2} | {} | {} | {f3} | {a3} |",
                rep + 1,
                fmt(a1),
                fmt(a2),
                fmt(kept),
            );
        });
    }
}

fn main() {
    let full_phantom = std::env::args().any(|a| a == "--full");
    let repeats: usize = std::env::var("NEUVOLEX_BENCH_REPEATS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    println!(
        "machine: {}, {} threads",
        machine(),
        rayon::current_num_threads()
    );
    println!("| volume | run | open s | fresh: first overlay s | fresh: whole volume s | warm: first overlay s | warm: whole volume s | features kept s after open | reopened: first overlay s | reopened: whole volume s |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    if let (Some(ct), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) {
        let mut l = neuvolex_bricks::open_volume(&lab, None).expect("labels");
        let d = l.meta().dims;
        let labels: Vec<u32> = l
            .read_slab(0, d[2])
            .expect("read labels")
            .to_f64()
            .iter()
            .map(|&v| v as u32)
            .collect();
        let data = ct.parent().expect("folder").to_path_buf();
        run_volume("abdomen_ct", &data, "ct.nii.gz", &labels, true, repeats);
    } else {
        println!("SKIP: abdomen_ct is absent (../shared/data)");
    }
    let dir = tempfile::tempdir().expect("tmp");
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).expect("data");
    let store = data.join("phantom.zarr");
    let params = PhantomParams {
        dims: [512, 512, 452],
        seed: 0,
        noise: 18.0,
    };
    let t = Instant::now();
    // As `neuvolex serve` writes its phantom: 32^3 bricks.
    let opts = IngestOptions {
        brick: 32,
        ..Default::default()
    };
    neuvolex_ingest::phantom_store(&store, params, &opts, &mut |_| {}).expect("phantom");
    eprintln!("phantom written in {:.0} s", t.elapsed().as_secs_f64());
    let st = BrickStore::open(&store).expect("store");
    let labels = st
        .read_labels_box("ground_truth", [0; 3], st.info().dims)
        .expect("truth");
    run_volume(
        "phantom",
        &data,
        "phantom.zarr",
        &labels,
        full_phantom,
        repeats,
    );
}
