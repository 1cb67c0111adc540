//! INR feature benchmarks (`cargo bench -p neuvolex-benches --bench inr`):
//! 1. neuvolex against the same model in PyTorch on the CPU, like for like (below; run when a
//!    Python with torch is found: `NEUVOLEX_TORCH_PYTHON`, else `python3`), then neuvolex's
//!    end-to-end `train()` on CT-Tooth and burn's forward+backward for reference;
//! 2. lazy against dense Adam for the hash table;
//! 3. the speed/accuracy trade: PSNR against training budget;
//! 4. time and peak RSS to features (train 1 epoch + extract) for CT-Tooth, the abdomen CT,
//!    bonsai and a 512x512x452 volume, each in a child process.
//!
//! Options: `--quick` skips the 512x512x452 run; `--only torch` runs section 1's comparison
//! alone; `--threads N` (default: all cores) threads on both sides; `--rounds R` (default 3);
//! `--torch-steps S` (default 20) optimiser steps per round and side; `--torch-variants a,b,..`
//! (default eager,fused,sparse,compile+fused,compile+cstep,sparse+compile, see
//! benches/inr_torch.py); `--screen 0` runs every variant in every round instead of screening;
//! `--nv-modes lazy,dense` neuvolex's table Adam modes (default lazy, neuvolex's default);
//! `--torch-data DIR` writes (and keeps) the export for PyTorch in DIR; `--out FILE` writes
//! section 1's JSON (every round and screening figure of every side and variant).
//!
//! The comparison with PyTorch (`neuvolex_benches::vs_torch`, shared with `inr_gpu.rs`):
//! - Inputs: the real volume, CT-Tooth. Every brick is loaded as a neuvolex tile (normalised
//!   intensities with halo, and the targets neuvolex trains on: intensity, gradient, local mean,
//!   local std); the volume (padded by the patch radius) and the targets are written to files
//!   that `inr_torch.py` loads onto its device. The training samples are `steps x batch`
//!   voxels of the training (occupied) bricks in one seeded random order (every voxel once per
//!   epoch): both sides train on exactly these samples in this order, batch 16384, with
//!   neuvolex's default learning rates (1e-3 MLPs, 1e-2 table) and Adam (0.9, 0.999, 1e-8).
//!   (`train()` samples the same voxels brick group by brick group; here the whole volume is
//!   resident, so the order is one permutation.)
//! - Timed, training: the `steps` optimiser steps on the pre-loaded volume, each step gathering
//!   its samples' positions, 5^3 patches and targets (neuvolex: `train::step` over the resident
//!   tiles; PyTorch: index arithmetic and gathers on the resident volume), forward, loss,
//!   backward, Adam. Not timed: loading and exporting the volume, the model's initialisation.
//! - Timed, extraction: the 64-D hidden feature of every voxel of the volume, from the resident
//!   tiles/volume into memory (neuvolex: `extract::extract_tile` per tile, which allocates its
//!   output; PyTorch: no_grad forward in chunks of 16384 voxels (65536 on CUDA) into one
//!   pre-allocated output).
//! - Accuracy at an equal sample budget: the loss and the PSNR of the intensity head over every
//!   voxel of the volume (PSNR = `train::psnr` of the mean squared error on the normalised
//!   range), computed outside the timed regions; and the loss of the last training batch.
//! - Warm-up: PyTorch compiles and runs every variant (3 training steps and 2 no_grad
//!   extraction chunks, in the mode it is timed in) before the first round and then resets
//!   parameters and optimiser state; neuvolex runs one untimed 2-step round first. Every round
//!   starts from the same initial parameters on both sides: neuvolex's seed-0 init, which
//!   `vs_torch::Bank::export` writes to init.f32 and inr_torch.py loads into every variant
//!   (its "ready" line says so, with its heads' difference from neuvolex's on the first
//!   samples; before issue 46 PyTorch started from its own `torch.manual_seed(0)` init).
//! - Threads: `--threads` on both sides (a rayon pool; `torch.set_num_threads` and
//!   `set_num_interop_threads`); the two never run at once.
//! - Interleaved: a screening round runs every PyTorch variant once (all in the JSON and the
//!   table); then `--rounds` rounds each run neuvolex and then the fastest PyTorch variant in
//!   training and the fastest in extraction (by the screening round), in one persistent PyTorch
//!   process driven by JSON lines on stdin, so compilation happens once. Printed: every round,
//!   then median [min-max] per side and of the per-round ratio against the fastest PyTorch
//!   variant (by median), for training and, separately, extraction, both ways, and the PSNRs
//!   side by side.
//! - PyTorch variants (inr_torch.py): eager (default Adam), fused (Adam(fused=True)), sparse
//!   (SparseAdam on the table: touched rows only, as neuvolex's lazy Adam), compile+fused
//!   (torch.compile of gather+forward+loss and its backward, fused Adam), compile+cstep (the
//!   same and opt.step compiled, the "compiling the optimizer" recipe), sparse+compile
//!   (compiled gather, indexing, MLPs and loss around an eager sparse table lookup). A variant
//!   this torch cannot build is printed as failed with the reason, not replaced.

use neuvolex_benches::{arg, machine, peak_rss_mib, shared, vs_torch};
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

/// The PyTorch variants timed by default on the CPU (see inr_torch.py).
const CPU_VARIANTS: &str = "eager,fused,sparse,compile+fused,compile+cstep,sparse+compile";

/// Section 1: neuvolex's CPU engine against PyTorch on the CPU, like for like (see the file's
/// documentation for every condition).
fn torch_section(store: &BrickStore, args: &[String]) -> serde_json::Value {
    use vs_torch::{compare, cpu_round, Bank, Side, Torch};
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    let threads: usize = arg(args, "--threads", cores);
    let rounds: usize = arg(args, "--rounds", 3);
    let steps: usize = arg(args, "--torch-steps", 20);
    let variants: String = arg(args, "--torch-variants", CPU_VARIANTS.to_string());
    let modes: String = arg(args, "--nv-modes", "lazy".to_string());
    let screen = arg(args, "--screen", 1u32) != 0;
    let inr = InrConfig::default();
    let tc = TrainConfig::default();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let bank = pool.install(|| Bank::load(store, &inr));
    let order = bank.order(steps, tc.batch, tc.seed);
    let init = neuvolex_features::InrModel::new(&inr, bank.dims, tc.seed);
    let tmp = tempfile::tempdir().expect("tmp");
    // `--torch-data DIR` keeps the export (to run inr_torch.py by hand).
    let data: std::path::PathBuf = arg(args, "--torch-data", tmp.path().to_path_buf());
    std::fs::create_dir_all(&data).expect("data dir");
    bank.export(
        &data,
        &order,
        steps,
        &tc,
        &init,
        vs_torch::EXTRACT_BATCH_CPU,
    )
    .expect("export for PyTorch");
    let samples = steps * tc.batch;
    println!(
        "\nINR against PyTorch on the CPU, like for like: CT-Tooth {:?} ({} voxels, {} in training bricks); per round and side {steps} steps x {} = {samples} samples ({:.2} epochs), the same samples in the same order; {threads} threads each; {rounds} rounds alternating.",
        bank.dims,
        bank.voxels(),
        bank.train_voxels(),
        tc.batch,
        samples as f64 / bank.train_voxels().max(1) as f64
    );
    println!("timed: training = the {steps} steps on the resident volume (sample gather, forward, loss, backward, Adam); extraction = the 64-D hidden feature of all {} voxels from the resident volume. Not timed: loading and export, PyTorch's compilation and warm-up (3 steps + 2 no_grad extraction chunks per variant, then reset), neuvolex's warm-up round, the loss/PSNR evaluation over every voxel.", bank.voxels());
    let mut torch = match Torch::start(&data, "cpu", threads, &variants) {
        Ok(t) => {
            println!("{}", t.describe("the CPU"));
            Some(t)
        }
        Err(e) => {
            println!("PyTorch unavailable ({e}): neuvolex alone");
            None
        }
    };
    pool.install(|| cpu_round(&bank, &init, &order, 2, &tc, TableAdam::Lazy));
    let mut sides: Vec<Side<'_>> = Vec::new();
    for m in modes.split(',') {
        let mode = match m.trim() {
            "lazy" => TableAdam::Lazy,
            "dense" => TableAdam::Dense,
            _ => continue,
        };
        let (bank, init, order, tc, pool) = (&bank, &init, &order, &tc, &pool);
        sides.push((
            format!("neuvolex CPU ({m} table Adam)"),
            Box::new(move || pool.install(|| cpu_round(bank, init, order, steps, tc, mode))),
        ));
    }
    let t = Instant::now();
    let context = format!(
        "CPU, CT-Tooth, {steps} x {} samples, {threads} threads each",
        tc.batch
    );
    let v = compare(rounds, &mut sides, torch.as_mut(), screen, &context);
    println!("(rounds took {:.0} s)", t.elapsed().as_secs_f64());
    v
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
    // 1. Against PyTorch, like for like; then neuvolex's end-to-end train() and burn.
    let v = torch_section(&store, &args);
    let out: String = arg(&args, "--out", String::new());
    if !out.is_empty() {
        let report = serde_json::json!({"machine": machine(), "torch": v});
        std::fs::write(&out, serde_json::to_vec_pretty(&report).expect("json"))
            .expect("write report");
        println!("report: {out}");
    }
    if arg(&args, "--only", String::new()) == "torch" {
        return;
    }
    let (ours, psnr, secs) = run(&store, &cfg(2.0, TableAdam::Lazy));
    println!("\n| neuvolex train() end to end (tile loading and grouping included), CT-Tooth 2 epochs, all cores | {:.0} k samples/s | {secs:.1} s | last-batch PSNR {psnr:.2} dB |", ours / 1e3);
    // burn (flex backend, autodiff): forward + backward of the same model on random inputs, no
    // optimiser step (a reference for the Rust ML stack, not like for like).
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
        println!("| burn 0.22 flex + autodiff (reference, random inputs), forward+backward only | train {:.0} k samples/s |", (reps * n) as f64 / t.elapsed().as_secs_f64() / 1e3);
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
