//! Robot rounds in the service path (`cargo bench -p neuvolex-benches --bench rounds`).
//!
//! A session of `neuvolex serve` driven without HTTP, as the UI drives it: S1 strokes (seed 0)
//! from the ground truth, then the robot user of `neuvolex eval --interactive`
//! ([`neuvolex_eval::robot::next_strokes`], largest error region) adds one slice visit per
//! round on the labels the session shows (the 0.5 rule, the spatial prior and the stability
//! rule, as the overlays and exports show them). Each round is timed from the strokes'
//! arrival to the first classified brick under the stroked slice (the overlay the user looks
//! at) and to the whole round (training, every brick predicted, the prior and growth). The
//! feature cache is warm after round 0, as in a session.
//!
//! Volumes: the abdomen CT (1.4 M voxels), a 160x232x160 crop of the brain MRI (5.9 M voxels,
//! the size of the MRI), both from `../shared/data` (skipped where absent), and the
//! 512x512x452 CT-like phantom (118 M voxels; its features pass the cache, so each round
//! recomputes those it needs): three rounds of a class and a background stroke on a new axial
//! slice, timed to the first overlay and then cancelled (`NEUVOLEX_BENCH_NO_PHANTOM` skips it);
//! `NEUVOLEX_BENCH_PHANTOM_WHOLE=N` then runs N rounds more to their end (minutes each on 2
//! cores: the features of most bricks are recomputed), and with
//! `NEUVOLEX_BENCH_PHANTOM_STORED` set, first keeps every brick's features in the store, as
//! `neuvolex serve` does in the background when a volume opens, so the rounds read them (the
//! whole rounds then run twice: with nothing kept, then with the features kept).
//!
//! The GPU path (issue 49; `--features gpu`): `NEUVOLEX_BENCH_GPU=1` predicts the phantom's
//! rounds on a hardware GPU (the filter bank and the forest, streamed by block, as
//! `neuvolex serve --backend auto` does; `NEUVOLEX_BENCH_GPU=software` allows lavapipe for a dry
//! run, whose times are no evidence of speed), and reports the peak GPU buffer bytes of the
//! phantom's whole rounds; `NEUVOLEX_BENCH_PHANTOM_CPU=N` then runs N whole rounds more with the
//! CPU forest in the same run, for the ratio. `NEUVOLEX_BENCH_ONLY_PHANTOM` skips the real
//! volumes; `NEUVOLEX_BENCH_PHANTOM_DIMS=X,Y,Z` changes the phantom's grid (a dry run).
//! Rounds: `NEUVOLEX_BENCH_ROUNDS` (default 10).

use neuvolex_benches::{machine, shared, spread};
use neuvolex_bricks::rng::Rng;
use neuvolex_bricks::synth::PhantomParams;
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::accel::Accelerator;
use neuvolex_classify::scribble::{simulate, Level, SimConfig, Stroke};
use neuvolex_classify::SliceMass;
use neuvolex_eval::robot::{next_strokes, Placement};
use neuvolex_formats::MemVolume;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_server::session::{Session, BACKGROUND};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// A volume and its truth, `dims[0]` fastest.
struct Volume {
    name: String,
    dims: [usize; 3],
    values: Vec<f32>,
    truth: Vec<u32>,
}

fn read(img: &Path, lab: &Path) -> (Vec<f32>, Vec<u32>, [usize; 3]) {
    let mut v = open_volume(img, None).expect("image");
    let d = v.meta().dims;
    let values = MemVolume::read_all(v.as_mut()).expect("image").to_f32();
    let mut l = open_volume(lab, None).expect("labels");
    let truth = MemVolume::read_all(l.as_mut())
        .expect("labels")
        .to_f32()
        .iter()
        .map(|&x| x as u32)
        .collect();
    (values, truth, d)
}

/// The box `lo..lo+size` of a volume.
fn crop<T: Copy>(v: &[T], d: [usize; 3], lo: [usize; 3], size: [usize; 3]) -> Vec<T> {
    let mut out = Vec::with_capacity(size.iter().product());
    for z in lo[2]..lo[2] + size[2] {
        for y in lo[1]..lo[1] + size[1] {
            let row = (z * d[1] + y) * d[0];
            out.extend_from_slice(&v[row + lo[0]..row + lo[0] + size[0]]);
        }
    }
    out
}

/// Classifies the session's strokes (generation `g`): seconds to the first brick under axial
/// `slice` and to the end; `cancel_after_first` stops the run there (the phantom).
fn timed_round(s: &Arc<Session>, g: u64, slice: usize, cancel_after_first: bool) -> (f64, f64) {
    let brick = s.store.info().brick;
    let t = Instant::now();
    let first = Mutex::new(None::<f64>);
    let on = |b: [usize; 3], _: usize, _: usize| {
        let mut f = first.lock().unwrap();
        if f.is_none() && b[2] == slice / brick {
            *f = Some(t.elapsed().as_secs_f64());
            if cancel_after_first {
                s.bump_generation();
            }
        }
    };
    s.classify(g, s.round_trees(), &on).expect("classify");
    let all = t.elapsed().as_secs_f64();
    let first = first.lock().unwrap().unwrap_or(all);
    (first, all)
}

fn mean_f1(shown: &[u16], truth: &[u32], ids: &[u32]) -> f64 {
    let f1 = neuvolex_classify::shard::f1_scores(shown, truth, ids);
    f1.iter().map(|f| f.f1).sum::<f64>() / f1.len().max(1) as f64
}

fn robot(v: &Volume, rounds: usize) {
    let dir = tempfile::tempdir().expect("tmp");
    let sp = dir.path().join("s.zarr");
    let mut mem = MemVolume::from_f32(v.dims, &v.values);
    let opts = IngestOptions {
        brick: 32,
        ..Default::default()
    };
    ingest(&mut mem, &sp, &opts, &mut |_| {}).expect("ingest");
    let store = Arc::new(BrickStore::open(&sp).expect("store"));
    let (s, ids) = neuvolex_benches::session_with_classes("rounds", store.clone(), &v.truth);
    let tf: Vec<f32> = v.truth.iter().map(|&t| t as f32).collect();
    let mut src = MemVolume::from_f32(v.dims, &tf);
    let (strokes, _) = simulate(
        &mut src,
        &SimConfig {
            level: Level::S1,
            seed: 0,
            background: BACKGROUND,
            ..Default::default()
        },
    )
    .expect("scribbles");
    let slice = strokes.last().map_or(0, |s| s.slice);
    let g = s.set_strokes(strokes).expect("strokes");
    let (_, cold) = timed_round(&s, g, slice, false);
    let shown_of = |s: &Session| -> Vec<u16> {
        neuvolex_server::assist::label_voxels(s)
            .expect("labels")
            .into_iter()
            .map(u16::from)
            .collect()
    };
    let mut shown = shown_of(&s);
    let mut f1 = vec![mean_f1(&shown, &v.truth, &ids)];
    let (mut firsts, mut alls) = (Vec::new(), Vec::new());
    let mut rng = Rng::new(0);
    let radius = SimConfig::default().radius;
    for _ in 0..rounds {
        let added: Vec<Stroke> = next_strokes(
            &v.truth,
            &shown,
            v.dims,
            store.info().brick,
            Placement::Largest,
            &SliceMass::zeros(v.dims, 2),
            &[],
            &[],
            &mut rng,
            BACKGROUND,
            radius,
        );
        if added.is_empty() {
            break;
        }
        let slice = added[0].slice;
        let (g, _) = s.add_strokes(added).expect("strokes");
        let (first, all) = timed_round(&s, g, slice, false);
        firsts.push(first);
        alls.push(all);
        shown = shown_of(&s);
        f1.push(mean_f1(&shown, &v.truth, &ids));
    }
    let drops: Vec<f64> = f1.windows(2).map(|w| w[1] - w[0]).collect();
    let worse = drops.iter().filter(|&&d| d < 0.0).count();
    let worst = -drops.iter().copied().fold(0.0, f64::min);
    println!(
        "| {} | {} | {:.1} M | {} | {cold:.2} | {} | {} | {:.3} → {:.3} | {worse} of {} | {worst:.3} |",
        v.name,
        v.dims.map(|d| d.to_string()).join("x"),
        v.truth.len() as f64 / 1e6,
        s.round_trees(),
        spread(&firsts, 2),
        spread(&alls, 2),
        f1[0],
        f1[f1.len() - 1],
        drops.len(),
    );
}

/// The GPU rounds predict on (`NEUVOLEX_BENCH_GPU`), with a reader of its peak buffer bytes
/// (reset on each call).
type Gpu = (Arc<dyn Accelerator>, Box<dyn Fn() -> u64>);

fn gpu() -> Option<Gpu> {
    let want = std::env::var("NEUVOLEX_BENCH_GPU").ok()?;
    #[cfg(feature = "gpu")]
    {
        use neuvolex_classify_gpu::{AdapterKind, GpuAccelerator, GpuDevice};
        let kind = if want == "software" {
            AdapterKind::Any
        } else {
            AdapterKind::Hardware
        };
        match GpuDevice::new(kind) {
            Ok(d) => {
                println!("GPU: {} (streamed blocks, 2 GiB budget)", d.describe());
                let dev = d.clone();
                let peak = Box::new(move || {
                    let p = dev.peak_bytes();
                    dev.reset_peak();
                    p
                });
                Some((Arc::new(GpuAccelerator::new(d)), peak))
            }
            Err(e) => {
                println!("SKIP: the GPU path ({want}): {e}");
                None
            }
        }
    }
    #[cfg(not(feature = "gpu"))]
    {
        println!("SKIP: NEUVOLEX_BENCH_GPU={want} needs --features gpu");
        None
    }
}

/// The phantom's grid (`NEUVOLEX_BENCH_PHANTOM_DIMS`, default 512x512x452).
fn phantom_dims() -> [usize; 3] {
    let v: Vec<usize> = std::env::var("NEUVOLEX_BENCH_PHANTOM_DIMS")
        .ok()
        .map(|s| s.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .unwrap_or_default();
    match v[..] {
        [x, y, z] if x > 0 && y > 0 && z > 0 => [x, y, z],
        _ => [512, 512, 452],
    }
}

/// The phantom: a class and a background stroke on a new axial slice per round, timed to the
/// first overlay under it, then cancelled; then `whole` rounds more that run to their end
/// (features recomputed where the cache no longer holds them, the prior over 118 M voxels),
/// on the GPU where one is asked for (then `NEUVOLEX_BENCH_PHANTOM_CPU` rounds on the CPU),
/// and again with the features kept in the store where `NEUVOLEX_BENCH_PHANTOM_STORED` is set.
fn phantom(rounds: usize, whole: usize) {
    let dir = tempfile::tempdir().expect("tmp");
    let sp = dir.path().join("phantom.zarr");
    let opts = IngestOptions {
        brick: 32,
        ..Default::default()
    };
    let params = PhantomParams {
        dims: phantom_dims(),
        seed: 0,
        noise: 18.0,
    };
    let t = Instant::now();
    neuvolex_ingest::phantom_store(&sp, params, &opts, &mut |_| {}).expect("phantom");
    eprintln!("phantom written in {:.0} s", t.elapsed().as_secs_f64());
    let store = Arc::new(BrickStore::open(&sp).expect("store"));
    let d = store.info().dims;
    let size = format!("{}x{}x{}", d[0], d[1], d[2]);
    let mvox = format!("{:.1} M", d.iter().product::<usize>() as f64 / 1e6);
    let truth = store
        .read_labels_box("ground_truth", [0; 3], d)
        .expect("truth");
    let (s, _) = neuvolex_benches::session_with_classes("phantom", store.clone(), &truth);
    let gpu = gpu();
    s.set_accelerator(gpu.as_ref().map(|g| g.0.clone()));
    let engine = if gpu.is_some() { "GPU" } else { "CPU" };
    // Each round strokes a new axial slice.
    let mut k = 0usize;
    let mut next_slice = || {
        k += 1;
        (d[2] / 2 + k * 40) % d[2]
    };
    let mut firsts = Vec::new();
    for r in 0..=rounds {
        let z = next_slice();
        let class = neuvolex_benches::main_class(&truth, d, z);
        let strokes = neuvolex_benches::strokes_on(&truth, d, z, class, 0);
        let (g, _) = s.add_strokes(strokes).expect("strokes");
        let (first, _) = timed_round(&s, g, z, true);
        if r > 0 {
            firsts.push(first);
        }
    }
    println!(
        "| phantom, {engine} | {size} | {mvox} | {} | — | {} | — (cancelled after the first overlay) | — | — | — |",
        s.round_trees(),
        spread(&firsts, 2)
    );
    if whole == 0 {
        return;
    }
    let cpu_rounds: usize = std::env::var("NEUVOLEX_BENCH_PHANTOM_CPU")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let mut whole_rounds = |n: usize, engine: &str, kept: &str| {
        let (mut firsts, mut alls) = (Vec::new(), Vec::new());
        for r in 0..n {
            let z = next_slice();
            let class = neuvolex_benches::main_class(&truth, d, z);
            let strokes = neuvolex_benches::strokes_on(&truth, d, z, class, 0);
            let (g, _) = s.add_strokes(strokes).expect("strokes");
            let (first, all) = timed_round(&s, g, z, false);
            let st = s.status.read().unwrap().clone();
            assert_eq!(st.state, "done", "round {r}: {st:?}");
            eprintln!(
                "phantom whole round {r} ({engine}{kept}, predicted on {}): first overlay {first:.2} s, round {all:.1} s",
                st.engine
            );
            firsts.push(first);
            alls.push(all);
        }
        let peak = match (&gpu, engine) {
            (Some(g), "GPU") => format!(
                ", peak GPU buffers {:.0} MiB",
                g.1() as f64 / (1u64 << 20) as f64
            ),
            _ => String::new(),
        };
        println!(
            "| phantom, whole rounds, {engine}{kept}{peak} | {size} | {mvox} | {} | — | {} | {} | — | — | — |",
            s.round_trees(),
            spread(&firsts, 2),
            spread(&alls, 1)
        );
    };
    let both = |run: &mut dyn FnMut(usize, &str, &str), kept: &str| {
        if let Some(g) = &gpu {
            g.1();
        }
        run(whole, engine, kept);
        if gpu.is_some() && cpu_rounds > 0 {
            s.set_accelerator(None);
            run(cpu_rounds, "CPU", kept);
            s.set_accelerator(gpu.as_ref().map(|g| g.0.clone()));
        }
    };
    both(&mut whole_rounds, "");
    // The features kept in the store, as `neuvolex serve` computes them in the background
    // when a volume opens (its `--feature-store-gib` set high enough for the phantom).
    if std::env::var_os("NEUVOLEX_BENCH_PHANTOM_STORED").is_some() {
        let t = Instant::now();
        // The pass ends when only it holds the session (a server that dropped it): the
        // server's session table holds another, as this clone does.
        let _table = s.clone();
        let p = s.open_stored_features(u64::MAX).expect("stored features");
        assert!(p.is_some(), "the phantom's features are kept");
        let n = s
            .prepare_features(&|done, total| {
                if done % 500 == 0 || done == total {
                    eprintln!("features kept: {done} of {total} bricks");
                }
            })
            .expect("feature pass");
        eprintln!(
            "phantom features kept in the store ({n:?} bricks) in {:.0} s",
            t.elapsed().as_secs_f64()
        );
        both(&mut whole_rounds, ", features kept in the store");
    }
}

fn main() {
    // `RUST_LOG=neuvolex_server=debug` prints each round's training, prediction and prior times.
    if std::env::var_os("RUST_LOG").is_some() {
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
            .with_writer(std::io::stderr)
            .init();
    }
    let rounds: usize = std::env::var("NEUVOLEX_BENCH_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    println!(
        "machine: {}, {} threads",
        machine(),
        rayon::current_num_threads(),
    );
    println!("| volume | dims | voxels | trees | round 0 (cold features) s | first overlay s, median [range] | round s, median [range] | mean F1 r0 → last | worse rounds | worst drop |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let only_phantom = std::env::var_os("NEUVOLEX_BENCH_ONLY_PHANTOM").is_some();
    match (
        shared("abdomen_ct/ct.nii.gz").filter(|_| !only_phantom),
        shared("abdomen_ct/labels.nii.gz"),
    ) {
        (Some(img), Some(lab)) => {
            let (values, truth, dims) = read(&img, &lab);
            robot(
                &Volume {
                    name: "abdomen CT".into(),
                    dims,
                    values,
                    truth,
                },
                rounds,
            );
        }
        _ if only_phantom => println!("SKIP: abdomen_ct (NEUVOLEX_BENCH_ONLY_PHANTOM is set)"),
        _ => println!("SKIP: abdomen_ct is absent (../shared/data)"),
    }
    match (
        shared("brain_mri/t1_norm.nii.gz").filter(|_| !only_phantom),
        shared("brain_mri/labels.nii.gz"),
    ) {
        (Some(img), Some(lab)) => {
            let (values, truth, d) = read(&img, &lab);
            let (lo, size) = ([48, 12, 48], [160, 232, 160]);
            robot(
                &Volume {
                    name: "brain MRI crop".into(),
                    dims: size,
                    values: crop(&values, d, lo, size),
                    truth: crop(&truth, d, lo, size),
                },
                rounds,
            );
        }
        _ if only_phantom => println!("SKIP: brain_mri (NEUVOLEX_BENCH_ONLY_PHANTOM is set)"),
        _ => println!("SKIP: brain_mri is absent (../shared/data)"),
    }
    if std::env::var_os("NEUVOLEX_BENCH_NO_PHANTOM").is_some() {
        println!("SKIP: the phantom (NEUVOLEX_BENCH_NO_PHANTOM is set)");
    } else {
        let whole = std::env::var("NEUVOLEX_BENCH_PHANTOM_WHOLE")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0);
        phantom(3, whole);
    }
}
