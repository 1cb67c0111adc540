//! INR feature benchmarks (`cargo bench -p neuvolex-benches --bench inr`):
//! 1. training and extraction throughput on CT-Tooth against the same model in PyTorch (run in
//!    the same bench when a Python with torch is found: `NEUVOLEX_TORCH_PYTHON` or `python3`);
//! 2. lazy against dense Adam for the hash table;
//! 3. the speed/accuracy trade: PSNR against training budget;
//! 4. time and peak RSS to features (train 1 epoch + extract) for CT-Tooth, the abdomen CT,
//!    bonsai and a 512x512x452 volume, each in a child process.
//!
//! `--quick` skips the 512x512x452 run.

use neuvolex_benches::{machine, peak_rss_mib, shared};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_features::extract::write_features;
use neuvolex_features::{
    train, Budget, FeatureKind, InrConfig, TableAdam, TrainConfig, TrainEvent,
};
use neuvolex_ingest::{ingest, IngestOptions};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

fn store_for(src: &Path, dir: &Path, name: &str) -> BrickStore {
    let out = dir.join(format!("{name}.zarr"));
    if !out.exists() {
        let mut s = open_volume(src, None).expect("open");
        ingest(s.as_mut(), &out, &IngestOptions::default(), &mut |_| {}).expect("ingest");
    }
    BrickStore::open(&out).expect("store")
}

fn cfg(epochs: f64, adam: TableAdam) -> TrainConfig {
    TrainConfig {
        budget: Budget {
            epochs: Some(epochs),
            ..Default::default()
        },
        table_adam: adam,
        preview_every: 0,
        checkpoint_every: 0,
        report_every: 1,
        ..TrainConfig::default()
    }
}

/// Trains; returns (steady samples/s excluding the first step, final PSNR, seconds).
fn run(store: &BrickStore, c: &TrainConfig) -> (f64, f64, f64) {
    let mut steps = Vec::new();
    let t = Instant::now();
    let r = train(
        store,
        &InrConfig::default(),
        c,
        None,
        None,
        &AtomicBool::new(false),
        &mut |e| {
            if let TrainEvent::Step {
                samples, seconds, ..
            } = e
            {
                steps.push((samples, seconds));
            }
        },
    )
    .expect("train");
    let secs = t.elapsed().as_secs_f64();
    let sps = if steps.len() > 2 {
        (steps[steps.len() - 1].0 - steps[0].0) as f64 / (steps[steps.len() - 1].1 - steps[0].1)
    } else {
        r.state.samples as f64 / secs
    };
    (sps, r.psnr, secs)
}

fn torch_reference(finest: usize) -> Option<serde_json::Value> {
    let py = std::env::var("NEUVOLEX_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("inr_torch.py");
    let mut best: Option<serde_json::Value> = None;
    for extra in [&[][..], &["--sparse"][..], &["--compile"][..]] {
        let o = std::process::Command::new(&py)
            .arg(&script)
            .args([
                "--threads",
                &std::thread::available_parallelism()
                    .map(|n| n.get())
                    .unwrap_or(2)
                    .to_string(),
                "--finest",
                &finest.to_string(),
                "--seconds",
                "15",
            ])
            .args(extra)
            .output()
            .ok()?;
        if !o.status.success() {
            eprintln!(
                "torch reference {extra:?} unavailable: {}",
                String::from_utf8_lossy(&o.stderr)
                    .lines()
                    .last()
                    .unwrap_or("")
            );
            continue;
        }
        let v: serde_json::Value =
            serde_json::from_slice(o.stdout.split(|&b| b == b'\n').rfind(|l| !l.is_empty())?)
                .ok()?;
        println!(
            "| PyTorch {} ({extra:?}) | train {:.0} k samples/s | extract {:.0} k voxels/s |",
            v["torch"],
            v["train_samples_per_s"].as_f64()? / 1e3,
            v["extract_voxels_per_s"].as_f64()? / 1e3
        );
        let better = best
            .as_ref()
            .is_none_or(|b| v["train_samples_per_s"].as_f64() > b["train_samples_per_s"].as_f64());
        if better {
            best = Some(v);
        }
    }
    best
}

fn child(src: &str, out_dir: &str, epochs: f64) {
    let dir = Path::new(out_dir);
    let t = Instant::now();
    let store = store_for(Path::new(src), dir, "v");
    let t_ingest = t.elapsed().as_secs_f64();
    let r = train(
        &store,
        &InrConfig::default(),
        &cfg(epochs, TableAdam::Lazy),
        None,
        None,
        &AtomicBool::new(false),
        &mut |_| {},
    )
    .expect("train");
    let t_train = t.elapsed().as_secs_f64() - t_ingest;
    let rep = write_features(&store, &r.model, FeatureKind::Hidden, false, &mut |_| {})
        .expect("features");
    let total = t.elapsed().as_secs_f64();
    println!(
        "{}",
        serde_json::json!({"dims": store.info().dims, "ingest_s": t_ingest, "train_s": t_train, "extract_s": rep.seconds, "total_s": total, "psnr": r.psnr, "samples": r.state.samples, "bricks": rep.bricks, "voxels": rep.voxels, "peak_rss_mib": peak_rss_mib()})
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child") {
        child(
            &args[i + 1],
            &args[i + 2],
            args[i + 3].parse().unwrap_or(1.0),
        );
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    println!("machine: {}", machine());
    let dir = tempfile::tempdir().expect("tmp");
    let Some(tooth) = shared("tooth/tooth.nhdr") else {
        return;
    };
    let store = store_for(&tooth, dir.path(), "tooth");
    // 1. Throughput against PyTorch, in one run.
    let (ours, psnr, secs) = run(&store, &cfg(2.0, TableAdam::Lazy));
    let model = train(
        &store,
        &InrConfig::default(),
        &cfg(0.05, TableAdam::Lazy),
        None,
        None,
        &AtomicBool::new(false),
        &mut |_| {},
    )
    .expect("train")
    .model;
    let rep =
        write_features(&store, &model, FeatureKind::Hidden, false, &mut |_| {}).expect("extract");
    let t = Instant::now();
    let bricks: Vec<_> = store.bricks().collect();
    let mut vox = 0usize;
    for b in &bricks {
        vox += neuvolex_features::extract::extract_brick(&model, &store, b, FeatureKind::Hidden)
            .expect("x")
            .len()
            / 64;
    }
    let compute_only = vox as f64 / t.elapsed().as_secs_f64();
    println!("| neuvolex fused CPU, CT-Tooth 2 epochs | train {:.0} k samples/s ({secs:.1} s, PSNR {psnr:.2} dB) | extract+write {:.0} k voxels/s, extract only {:.0} k voxels/s |", ours / 1e3, rep.voxels as f64 / rep.seconds / 1e3, compute_only / 1e3);
    // burn (flex backend, autodiff): forward + backward of the same model, no optimiser step.
    {
        let m = neuvolex_features::InrModel::new(&InrConfig::default(), [103, 94, 161], 0);
        let b = neuvolex_features_burn::BurnInr::new(&m, burn_tensor::Device::flex().autodiff());
        let mut r = neuvolex_features::rng::Rng::new(1);
        let n = 16384;
        let coords: Vec<[f32; 3]> = (0..n).map(|_| [r.f32(), r.f32(), r.f32()]).collect();
        let patches: Vec<f32> = (0..n * 125).map(|_| r.f32()).collect();
        let targets: Vec<f32> = (0..n * 6).map(|_| r.f32()).collect();
        let _ = b.gradients(&coords, &patches, &targets);
        let t = Instant::now();
        let reps = 3;
        for _ in 0..reps {
            std::hint::black_box(b.gradients(&coords, &patches, &targets));
        }
        println!("| burn 0.22 flex + autodiff (reference), forward+backward only | train {:.0} k samples/s |", (reps * n) as f64 / t.elapsed().as_secs_f64() / 1e3);
    }
    if let Some(v) = torch_reference(161) {
        let tt = v["train_samples_per_s"].as_f64().unwrap_or(f64::NAN);
        let te = v["extract_voxels_per_s"].as_f64().unwrap_or(f64::NAN);
        println!(
            "| ratio neuvolex / best PyTorch | train {:.2}x | extract {:.2}x |",
            ours / tt,
            compute_only / te
        );
    }
    // 2. Lazy against dense table Adam.
    for mode in [TableAdam::Lazy, TableAdam::Dense] {
        let (sps, p, s) = run(&store, &cfg(1.0, mode));
        println!(
            "| table Adam {mode:?}, 1 epoch | {:.0} k samples/s | PSNR {p:.2} dB | {s:.1} s |",
            sps / 1e3
        );
    }
    // 3. PSNR against budget.
    for e in [0.25, 1.0, 3.0, 10.0] {
        let (sps, p, s) = run(&store, &cfg(e, TableAdam::Lazy));
        println!(
            "| CT-Tooth budget {e} epochs | PSNR {p:.2} dB | {s:.1} s | {:.0} k samples/s |",
            sps / 1e3
        );
    }
    // 4. Time and peak RSS to features, each volume in its own process.
    let exe = std::env::current_exe().expect("exe");
    let mut vols: Vec<(String, std::path::PathBuf)> = vec![("CT-Tooth".into(), tooth.clone())];
    if let Some(p) = shared("abdomen_ct/ct.nii.gz") {
        vols.push(("CT abdomen".into(), p));
    }
    if let Some(p) = shared("scivis/bonsai.nii.gz") {
        vols.push(("bonsai".into(), p));
    }
    if !quick {
        let raw = dir.path().join("cta_512x512x452_int16.raw");
        neuvolex_benches::write_cta(&raw);
        vols.push(("phantom 512x512x452 i16".into(), raw));
    }
    for (name, p) in vols {
        let sub = dir.path().join(name.replace(' ', "_"));
        std::fs::create_dir_all(&sub).expect("dir");
        let o = std::process::Command::new(&exe)
            .args(["--child", &p.to_string_lossy(), &sub.to_string_lossy(), "1"])
            .output()
            .expect("child");
        let text = String::from_utf8_lossy(&o.stdout);
        match text.lines().rfind(|l| l.starts_with('{')).and_then(|l| serde_json::from_str::<serde_json::Value>(l).ok()) {
            Some(v) => println!(
                "| {name} {:?} | ingest {:.1} s | train 1 epoch {:.1} s (PSNR {:.2} dB) | extract {:.1} s ({} bricks) | total {:.1} s | peak RSS {:.0} MiB |",
                v["dims"], v["ingest_s"].as_f64().unwrap_or(0.0), v["train_s"].as_f64().unwrap_or(0.0), v["psnr"].as_f64().unwrap_or(0.0), v["extract_s"].as_f64().unwrap_or(0.0), v["bricks"], v["total_s"].as_f64().unwrap_or(0.0), v["peak_rss_mib"].as_f64().unwrap_or(0.0)
            ),
            None => eprintln!("{name}: child failed: {}", String::from_utf8_lossy(&o.stderr)),
        }
    }
}
