//! The INR on the GPU (`cargo bench -p neuvolex-benches --bench inr_gpu [--features gpu]`):
//! 1. per volume (CT-Tooth, the abdomen CT, a 512x512x452 CT-like phantom), the paper's model
//!    trained by the GPU engine: steady samples/s, PSNR against time, peak GPU memory, and
//!    feature extraction voxels/s (compute only, and into the store as f16); the CPU engine on
//!    the same volume in the same run for the ratio;
//! 2. on CT-Tooth, neuvolex's GPU engine against the same model in PyTorch on the same device
//!    (`benches/inr_torch.py --device cuda`), like for like (below);
//! 3. per-kernel times of one step on every launch path (layered; fused with blocks of 64, 32
//!    and 16 samples per workgroup; fused-f16, its GEMM tiles on the tensor cores where the
//!    device has cooperative matrices): GPU timestamps per dispatch in one submission where the
//!    adapter has timestamp queries, else each dispatch waited for; and a sweep of launch path
//!    x batch size on CT-Tooth (samples/s and PSNR after the same seconds of training);
//! 4. with `--features gpu`, the wgpu renderer against the CPU renderer (bonsai, abdomen;
//!    512^2 and 1024^2).
//!
//! The phantom runs last (its extraction into the store is the longest part), so a run cut
//! short by the device's time limit still reports the rest.
//!
//! Options: `--quick` (1 epoch on the large volume, 100-step PyTorch rounds), `--large-epochs
//! N` (default 100, the paper's), `--cap-s S` (wall-clock cap of the large run, default 480; the
//! 100-epoch time is then extrapolated and marked so), `--sweep-s S` and `--sweep-batches
//! B,B,..` (the launch-path x batch sweep), `--torch-steps S` (default 400: steps per round and
//! side of the comparison with PyTorch), `--rounds R` (default 3), `--torch-variants a,b,..`
//! (default on CUDA fused,sparse,compile+fused,ro+fused,ro+cstep; ma+cstep (max-autotune) and
//! eager exist too), `--screen 0` (every variant in every round), `--cpu-s S` (the CPU engine
//! per volume), `--only agree` (only the check of the fused paths, f32 and f16, against the layered one), `--only torch` (only the
//! comparison with PyTorch), `--only stages` (only the path checks, profile, sweep and
//! extraction sweep), `--volume FILE` (with `--only torch` or `--only stages`: that volume
//! instead of CT-Tooth, e.g. a small one for a smoke test on lavapipe), `--sweep-paths P,P,..` (default layered,fused,fused32,fused16; any `MlpPath` name, the f16
//! ones `fused-f16`, `fused32-f16`, `fused16-f16` too),
//! `--paths P,P,..` (neuvolex's sides in the comparison with PyTorch, default
//! fused,fused32,fused16; the ratios are of the first), `--mlp P` (the per-volume runs'
//! path, default fused), `--extract-batches B,B,..` (inference micro-batches of the
//! extraction sweep on the `--paths` paths, default 32768,65536,262144; 32768 is the engine's
//! default), `--out FILE` (JSON of everything; written after each stage).
//! `NEUVOLEX_TORCH_DATA` keeps PyTorch's inputs (meta.json, volume, targets, order, init.f32)
//! in that folder.
//! `NEUVOLEX_DATA` names the data folder (default ../shared/data), `NEUVOLEX_TORCH_PYTHON` the
//! Python with torch, `NEUVOLEX_TORCH_SCRIPT` the script. On a software adapter (lavapipe)
//! every figure is correctness evidence, not speed, and the bench says so; there PyTorch runs
//! on the CPU (a dry run of the code path).
//!
//! The comparison with PyTorch (inr.rs's module `vs_torch`, included here; the CPU bench's
//! documentation lists every condition) on the GPU:
//! - Inputs: CT-Tooth's tiles (every brick), the same initial parameters (neuvolex's, written to
//!   init.f32 and loaded by inr_torch.py) and the same `steps x 16384` samples in the same
//!   order on both sides; neuvolex holds every tile in its engine's ring and the whole sample
//!   order on the device, PyTorch the padded volume, the targets and the order on the device.
//! - Timed training, between device synchronisations: neuvolex `GpuInr::step` x steps from the
//!   uploaded initial model and a zero Adam state (lazy table Adam, neuvolex's default);
//!   PyTorch's steps (gather, forward, loss, backward, Adam).
//! - Timed extraction: the 64-D hidden feature of every voxel: neuvolex `record_tile` per
//!   resident tile, which also copies the features into a host-mappable buffer; PyTorch
//!   no_grad forward in chunks of 65536 into a device tensor.
//! - Not timed: uploads, the engines' creation, PyTorch's compilation, autotuning and CUDA-graph
//!   capture (3 steps, 5 with CUDA graphs, and 2/3 extraction chunks per variant, then reset),
//!   a 2-step warm-up round of neuvolex, and the loss/PSNR over every voxel (neuvolex's on the
//!   CPU from the downloaded model, PyTorch's from its extraction pass).
//! - PyTorch variants: fused (eager, Adam(fused=True)), sparse (SparseAdam on the table),
//!   compile+fused (torch.compile default mode), ro+fused (mode="reduce-overhead": CUDA graphs,
//!   fused Adam), ro+cstep (reduce-overhead and opt.step compiled with reduce-overhead); TF32
//!   off, f32 on both sides. A screening round runs every variant once; the 3 rounds then
//!   alternate neuvolex with the fastest in training and the fastest in extraction. Printed:
//!   each round, median [min-max] per side, the per-round ratios both ways (training and
//!   extraction, saying plainly which side is slower) and the PSNRs side by side.

use neuvolex_benches::{arg, machine, shared, vs_torch};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_features::tile::Tile;
use neuvolex_features::train::training_bricks;
use neuvolex_features::{train, Budget, FeatureKind, InrConfig, InrModel, TrainConfig, TrainEvent};
use neuvolex_features_gpu::{
    train_gpu_tuned, write_features_gpu, AdapterKind, EngineOptions, FeatureFormat, GpuContext,
    GpuInr, GpuTune, MlpPath,
};
use neuvolex_ingest::{ingest, IngestOptions};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

fn store_for(src: &Path, dir: &Path) -> BrickStore {
    let out = dir.join("s.zarr");
    let mut s = open_volume(src, None).expect("open");
    ingest(s.as_mut(), &out, &IngestOptions::default(), &mut |_| {}).expect("ingest");
    BrickStore::open(&out).expect("store")
}

/// The fast preset's learning rates over `epochs` (capped at `cap_s` seconds), reporting every
/// 10 steps; no previews or checkpoints.
fn cfg(epochs: f64, cap_s: Option<f64>) -> TrainConfig {
    TrainConfig {
        budget: Budget {
            epochs: Some(epochs),
            seconds: cap_s,
            ..Default::default()
        },
        preview_every: 0,
        checkpoint_every: 0,
        report_every: 10,
        ..TrainConfig::default()
    }
}

/// (seconds, samples, psnr) of every step event.
type Curve = Vec<(f64, u64, f64)>;

fn curve_of(ev: &[TrainEvent]) -> Curve {
    ev.iter()
        .filter_map(|e| match e {
            TrainEvent::Step {
                seconds,
                samples,
                psnr,
                ..
            } => Some((*seconds, *samples, *psnr)),
            _ => None,
        })
        .collect()
}

/// Samples/s between the first and last step event (start-up and first tile load excluded).
fn steady(c: &Curve) -> f64 {
    match (c.first(), c.last()) {
        (Some(a), Some(b)) if b.0 > a.0 => (b.1 - a.1) as f64 / (b.0 - a.0),
        _ => f64::NAN,
    }
}

/// PSNR reached by each time mark (the last event at or before it).
fn psnr_at(c: &Curve, marks: &[f64]) -> Vec<Value> {
    marks
        .iter()
        .filter_map(|&t| {
            c.iter()
                .rev()
                .find(|e| e.0 <= t)
                .map(|e| json!({"seconds": t, "psnr": e.2, "samples": e.1}))
        })
        .collect()
}

fn gpu_volume(
    ctx: &Arc<GpuContext>,
    name: &str,
    store: &BrickStore,
    epochs: f64,
    cap_s: Option<f64>,
    cpu_s: f64,
    mlp: MlpPath,
) -> Value {
    let voxels: u64 = training_bricks(store, false)
        .iter()
        .map(|b| b.voxels() as u64)
        .sum();
    let mut ev = Vec::new();
    let t = Instant::now();
    let ctx = ctx_for(ctx, mlp);
    let g = train_gpu_tuned(
        ctx,
        store,
        &InrConfig::default(),
        &cfg(epochs, cap_s),
        None,
        None,
        &AtomicBool::new(false),
        &mut |e| ev.push(e),
        GpuTune {
            mlp,
            micro_batch: None,
            loss_scale_exp: None,
        },
    )
    .expect("GPU training");
    let train_s = t.elapsed().as_secs_f64();
    let c = curve_of(&ev);
    let sps = steady(&c);
    let epochs_done = g.trained.state.samples as f64 / voxels.max(1) as f64;
    // The CPU engine on the same volume, same settings, for a short budget.
    let mut cev = Vec::new();
    train(
        store,
        &InrConfig::default(),
        &cfg(100.0, Some(cpu_s)),
        None,
        None,
        &AtomicBool::new(false),
        &mut |e| cev.push(e),
    )
    .expect("CPU training");
    let cpu_sps = steady(&curve_of(&cev));
    // Extraction: compute only over the training tiles (tiles loaded first), then into the store.
    let model = &g.trained.model;
    let bricks = training_bricks(store, false);
    let tiles: Vec<Tile> = bricks
        .iter()
        .take(64)
        .map(|b| Tile::load(store, b, model.cfg.patch).expect("tile"))
        .collect();
    let mut eng = GpuInr::new(
        ctx,
        model,
        None,
        EngineOptions {
            mlp,
            ..EngineOptions::inference(store.info().brick)
        },
    )
    .expect("engine");
    let staging = eng
        .staging_for(
            tiles.iter().map(|t| t.voxels()).max().unwrap_or(1),
            FeatureKind::Hidden,
        )
        .expect("staging");
    let n: u64 = tiles.iter().map(|t| t.voxels() as u64).sum();
    let t = Instant::now();
    for (i, tile) in tiles.iter().enumerate() {
        eng.upload_tile(i % 2, tile).expect("upload");
        eng.record_tile(i % 2, tile.voxels(), FeatureKind::Hidden, &staging)
            .expect("extract");
    }
    ctx.wait().expect("wait");
    let compute_vps = n as f64 / t.elapsed().as_secs_f64();
    drop(eng);
    let rep = write_features_gpu(ctx, store, model, FeatureKind::Hidden, false, &mut |_| {})
        .expect("features");
    let mem = g.report.memory;
    let marks = [1.0, 2.0, 5.0, 10.0, 20.0, 60.0, 120.0, 300.0, 600.0];
    let per100 = if epochs_done > 0.0 {
        train_s * 100.0 / epochs_done
    } else {
        f64::NAN
    };
    println!(
        "| {name} | {:?} | {:.2} M | {:.2} M | {:.1}x | {:.1} | {epochs_done:.2} in {train_s:.1} s{} | {:.2} M / {:.2} M | {:.0} MiB ({} MiB allocator) |",
        store.info().dims,
        sps / 1e6,
        cpu_sps / 1e6,
        sps / cpu_sps,
        g.trained.psnr,
        if epochs_done + 1e-9 < epochs { format!(" (100 epochs: {per100:.0} s extrapolated)") } else { String::new() },
        compute_vps / 1e6,
        rep.voxels as f64 / rep.seconds / 1e6,
        mem.peak_bytes as f64 / 1048576.0,
        mem.reserved_peak_bytes.map_or("-".into(), |b| format!("{:.0}", b as f64 / 1048576.0)),
    );
    json!({
        "volume": name, "dims": store.info().dims, "voxels_per_epoch": voxels, "path": mlp.name(),
        "train_samples_per_s": sps, "cpu_train_samples_per_s": cpu_sps, "ratio_cpu": sps / cpu_sps,
        "epochs": epochs_done, "train_s": train_s, "psnr": g.trained.psnr,
        "seconds_per_100_epochs": per100, "psnr_at": psnr_at(&c, &marks),
        "extract_compute_voxels_per_s": compute_vps, "extract_store_voxels_per_s": rep.voxels as f64 / rep.seconds,
        "peak_gpu_bytes": mem.peak_bytes, "allocator_peak_bytes": mem.reserved_peak_bytes,
        "micro_batch": g.report.micro_batch, "ring_groups": g.report.ring_groups,
        "loader_wait_s": g.report.loader_wait_s, "readback_wait_s": g.report.readback_wait_s,
        "upload_bytes": g.report.upload_bytes,
    })
}

/// The PyTorch variants timed by default on CUDA (see inr_torch.py), and on the CPU when the
/// adapter is no NVIDIA GPU (a dry run of the code path, not a speed comparison).
const CUDA_VARIANTS: &str = "fused,sparse,compile+fused,ro+fused,ro+cstep";
const CPU_VARIANTS: &str = "fused,compile+fused";

/// neuvolex's GPU engine against PyTorch on `device`, like for like on CT-Tooth (the module
/// `vs_torch` of inr.rs: the same resident volume, samples, order, budget, timed regions and
/// rounds as the CPU comparison; see this file's documentation).
#[allow(clippy::too_many_arguments)]
fn vs_torch_gpu(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    device: &str,
    steps: usize,
    rounds: usize,
    variants: &str,
    screen: bool,
    paths: &[MlpPath],
) -> Value {
    use vs_torch::{compare, Bank, Round, Side, Torch};
    let inr = InrConfig::default();
    let tc = TrainConfig::default();
    let b = tc.batch;
    let bank = Bank::load(store, &inr);
    let order = bank.order(steps, b, tc.seed);
    let init = InrModel::new(&inr, bank.dims, tc.seed);
    // `NEUVOLEX_TORCH_DATA` keeps the export in that folder (to inspect or rerun PyTorch alone).
    let tmp = tempfile::tempdir().expect("tmp");
    let data_dir = match std::env::var_os("NEUVOLEX_TORCH_DATA") {
        Some(d) => {
            let d = PathBuf::from(d);
            std::fs::create_dir_all(&d).expect("NEUVOLEX_TORCH_DATA");
            d
        }
        None => tmp.path().to_path_buf(),
    };
    let eb = if device == "cuda" {
        vs_torch::EXTRACT_BATCH_CUDA
    } else {
        vs_torch::EXTRACT_BATCH_CPU
    };
    bank.export(&data_dir, &order, steps, &tc, &init, eb)
        .expect("export for PyTorch");
    let init_note = match vs_torch::torch_init(&init) {
        Ok(t) => format!(
            "both sides start from neuvolex's initial parameters (seed {}; {} tensors exported to init.f32, loaded by inr_torch.py)",
            tc.seed,
            t.len()
        ),
        Err(e) => format!("initial parameters NOT shared ({e}): PyTorch starts from its own seed"),
    };
    println!("{init_note}");
    println!(
        "\nINR on the GPU against PyTorch on {device}, like for like: CT-Tooth {:?} ({} voxels, {} in training bricks); per round and side {steps} steps x {b} = {} samples ({:.2} epochs), the same samples in the same order; {rounds} rounds alternating after a screening round of every PyTorch variant.",
        bank.dims,
        bank.voxels(),
        bank.train_voxels(),
        steps * b,
        (steps * b) as f64 / bank.train_voxels().max(1) as f64
    );
    println!("timed, between device synchronisations: training = the {steps} steps on the resident volume (neuvolex: GpuInr::step over every brick's tile resident in the ring and the whole sample order uploaded; PyTorch: gathers on the resident volume; both forward, loss, backward, Adam); extraction = the 64-D hidden feature of all {} voxels (neuvolex: record_tile per resident tile, which copies the features into a host-mappable buffer; PyTorch: no_grad forward in chunks of {eb} into a device tensor). Not timed: uploads, PyTorch's compilation, CUDA-graph capture and warm-up, a 2-step warm-up round of neuvolex, the loss/PSNR evaluation (neuvolex's on the CPU from the downloaded model).", bank.voxels());
    let rates = neuvolex_features_gpu::StepRates {
        lr: tc.lr,
        lr_table: tc.lr_table,
        mode: tc.table_adam,
    };
    let mut runs = Vec::new();
    let mut skipped = Vec::new();
    for &mlp in paths {
        let warm = gpu_side(ctx, store.info().brick, &bank, &init, &order, b, rates, mlp)
            .and_then(|mut r| r(2).map(|_| r).map_err(|e| e.to_string()));
        match warm {
            Ok(r) => runs.push((mlp, r)),
            Err(e) => {
                println!("neuvolex path {} left out of the comparison: its engines could not be set up or warmed up ({e})", mlp.name());
                skipped.push(json!({"path": mlp.name(), "error": e}));
            }
        }
    }
    if runs.is_empty() {
        println!("SKIP the comparison with PyTorch: no GPU engine could be set up");
        return json!({"error": "no GPU engine could be set up", "skipped_paths": skipped});
    }
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    let mut torch = match Torch::start(&data_dir, device, threads, variants) {
        Ok(t) => {
            println!("{}", t.describe(device));
            Some(t)
        }
        Err(e) => {
            println!("PyTorch unavailable ({e}): neuvolex alone");
            None
        }
    };
    let mut sides: Vec<Side<'_>> = runs
        .into_iter()
        .map(|(mlp, mut run)| -> Side<'_> {
            (
                format!(
                    "neuvolex GPU {} [{}] ({})",
                    mlp.name(),
                    ctx_for(ctx, mlp).tile_arith_for(mlp.half()).name(),
                    ctx.info().name
                ),
                Box::new(move || {
                    run(steps).unwrap_or_else(|e| {
                        eprintln!("neuvolex GPU round ({}) failed: {e}", mlp.name());
                        Round {
                            train_s: f64::NAN,
                            extract_s: f64::NAN,
                            volume_loss: f64::NAN,
                            psnr: f64::NAN,
                            ..Round::default()
                        }
                    })
                }),
            )
        })
        .collect();
    let context = format!("GPU ({device}), CT-Tooth, {steps} x {b} samples");
    let mut out = compare(rounds, &mut sides, torch.as_mut(), screen, &context);
    out["init"] = json!(init_note);
    out["skipped_paths"] = json!(skipped);
    out
}

/// One round of a neuvolex side of the comparison: `n` steps, then extraction and evaluation.
type GpuRun<'a> = Box<dyn FnMut(usize) -> neuvolex_features_gpu::Result<vs_torch::Round> + 'a>;

/// A neuvolex side of the comparison on MLP path `mlp`: a training engine and an inference
/// engine with every tile of `bank` resident and the whole sample order uploaded; each round
/// starts from `init` and a zero Adam state, trains `n` steps of `b` samples (timed), copies
/// the model into the inference engine and extracts the hidden features of every voxel
/// (timed), then evaluates loss and PSNR on the CPU (untimed).
#[allow(clippy::too_many_arguments)]
fn gpu_side<'a>(
    ctx: &'a Arc<GpuContext>,
    brick: usize,
    bank: &'a vs_torch::Bank,
    init: &'a InrModel,
    order: &[(u32, u32)],
    b: usize,
    rates: neuvolex_features_gpu::StepRates,
    mlp: MlpPath,
) -> Result<GpuRun<'a>, String> {
    use vs_torch::{evaluate, Round};
    let ctx = ctx_for(ctx, mlp);
    let slots = bank.tiles.len();
    let setup = || -> neuvolex_features_gpu::Result<_> {
        let eng = GpuInr::new(
            ctx,
            init,
            None,
            EngineOptions {
                batch: b,
                micro_batch: None,
                train: true,
                slots,
                brick,
                order_pairs: order.len().div_ceil(2),
                mlp,
            },
        )?;
        let inf = GpuInr::new(
            ctx,
            init,
            None,
            EngineOptions {
                slots,
                mlp,
                ..EngineOptions::inference(brick)
            },
        )?;
        for (i, t) in bank.tiles.iter().enumerate() {
            eng.upload_tile(i, t)?;
            inf.upload_tile(i, t)?;
        }
        let pairs: Vec<u32> = order.iter().flat_map(|&(t, v)| [t, v]).collect();
        eng.upload_order(0, &pairs)?;
        let most = bank.tiles.iter().map(|t| t.voxels()).max().unwrap_or(1);
        let staging = inf.staging_for(most, FeatureKind::Hidden)?;
        ctx.wait()?;
        Ok((eng, inf, staging))
    };
    let (mut eng, mut inf, staging) = setup().map_err(|e| e.to_string())?;
    let steps_max = order.len() / b.max(1);
    Ok(Box::new(
        move |n: usize| -> neuvolex_features_gpu::Result<Round> {
            if n > steps_max {
                return Err(neuvolex_features_gpu::GpuError::Config(format!(
                    "{n} steps need more than the {steps_max} steps of samples uploaded"
                )));
            }
            eng.upload_model(init);
            eng.upload_adam(&neuvolex_features::adam::Adam::new(
                init.dense.len(),
                init.table.len(),
            ))?;
            ctx.wait()?;
            let t = Instant::now();
            for s in 0..n {
                eng.step(s * b, b, rates, s + 1)?;
            }
            ctx.wait()?;
            let train_s = t.elapsed().as_secs_f64();
            let model = eng.download_model()?;
            inf.upload_model(&model);
            ctx.wait()?;
            let t = Instant::now();
            for (i, tile) in bank.tiles.iter().enumerate() {
                inf.record_tile(i, tile.voxels(), FeatureKind::Hidden, &staging)?;
            }
            ctx.wait()?;
            let extract_s = t.elapsed().as_secs_f64();
            let (volume_loss, psnr) = evaluate(&model, bank);
            Ok(Round {
                train_s,
                samples: n * b,
                last_loss: None,
                extract_s,
                extract_voxels: bank.voxels(),
                volume_loss,
                psnr,
            })
        },
    ))
}

/// Launch path x batch size on `store`: each trains the paper's model for `seconds` from the
/// same seed; samples/s (steady) and the PSNR reached, so speed and quality are read together.
fn sweep(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    seconds: f64,
    batches: &[usize],
    paths: &[MlpPath],
) -> Value {
    println!("\nlaunch path x batch ({seconds} s of training each, same seed):");
    println!("| path | batch | micro-batch | samples/s | steps | PSNR dB | peak GPU memory |");
    println!("|---|---|---|---|---|---|---|");
    let mut out = Vec::new();
    for &batch in batches {
        for &mlp in paths {
            let mut ev = Vec::new();
            let c = TrainConfig {
                batch,
                ..cfg(1000.0, Some(seconds))
            };
            let r = train_gpu_tuned(
                ctx_for(ctx, mlp),
                store,
                &InrConfig::default(),
                &c,
                None,
                None,
                &AtomicBool::new(false),
                &mut |e| ev.push(e),
                GpuTune {
                    mlp,
                    micro_batch: Some(batch.min(65536)),
                    loss_scale_exp: None,
                },
            );
            let g = match r {
                Ok(g) => g,
                Err(e) => {
                    println!("| {} | {batch} | - | failed: {e} | | | |", mlp.name());
                    continue;
                }
            };
            let curve = curve_of(&ev);
            let sps = steady(&curve);
            let steps = g.trained.state.samples / batch as u64;
            println!(
                "| {} | {batch} | {} | {:.2} M | {steps} | {:.2} | {:.0} MiB |",
                mlp.name(),
                g.report.micro_batch,
                sps / 1e6,
                g.trained.psnr,
                g.report.memory.peak_bytes as f64 / 1048576.0
            );
            out.push(json!({"path": mlp.name(), "batch": batch, "micro_batch": g.report.micro_batch,
                "samples_per_s": sps, "steps": steps, "psnr": g.trained.psnr, "seconds": seconds,
                "peak_gpu_bytes": g.report.memory.peak_bytes,
                "readback_wait_s": g.report.readback_wait_s, "loader_wait_s": g.report.loader_wait_s}));
        }
    }
    json!(out)
}

/// Extraction alone on `store` (every tile resident): the 64-D hidden feature of every voxel
/// of the paper's model (initial weights: the time does not depend on them) per MLP path and
/// inference micro-batch, as f32 and as f16 (converted on the GPU, as the store keeps them),
/// each into host-mappable memory (what the comparison with PyTorch times) and into a device
/// buffer (no transfer); median of 5 passes after a warm-up pass.
fn extract_sweep(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    paths: &[MlpPath],
    batches: &[usize],
) -> Value {
    let inr = InrConfig::default();
    let bank = vs_torch::Bank::load(store, &inr);
    let model = InrModel::new(&inr, bank.dims, 0);
    let brick = store.info().brick;
    let voxels = bank.voxels();
    println!(
        "\nfeature extraction alone ({voxels} voxels, every tile resident, the 64-D hidden feature; median of 5 passes):"
    );
    println!(
        "| path | micro-batch | f32 into mapped memory, M voxels/s | f32 into device memory | f16 into mapped memory | f16 into device memory |"
    );
    println!("|---|---|---|---|---|---|");
    let mut out = Vec::new();
    for &mlp in paths {
        for &mb in batches {
            let run = || -> neuvolex_features_gpu::Result<(usize, [f64; 4], [usize; 3])> {
                let mut inf = GpuInr::new(
                    ctx_for(ctx, mlp),
                    &model,
                    None,
                    EngineOptions {
                        batch: mb,
                        micro_batch: Some(mb),
                        slots: bank.tiles.len(),
                        mlp,
                        ..EngineOptions::inference(brick)
                    },
                )?;
                for (i, t) in bank.tiles.iter().enumerate() {
                    inf.upload_tile(i, t)?;
                }
                let most = bank.tiles.iter().map(|t| t.voxels()).max().unwrap_or(1);
                let mut rates = [0.0; 4];
                for (j, fmt) in [FeatureFormat::F32, FeatureFormat::F16]
                    .into_iter()
                    .enumerate()
                {
                    let mapped = inf.staging_in(most, FeatureKind::Hidden, fmt)?;
                    let device = inf.device_buffer_in(most, FeatureKind::Hidden, fmt)?;
                    ctx.wait()?;
                    let mut rate = |dst: &neuvolex_features_gpu::context::Tracked| -> neuvolex_features_gpu::Result<f64> {
                        let mut secs = Vec::new();
                        for _ in 0..6 {
                            let t = Instant::now();
                            for (i, tile) in bank.tiles.iter().enumerate() {
                                inf.record_tile_in(i, tile.voxels(), FeatureKind::Hidden, fmt, dst)?;
                            }
                            ctx.wait()?;
                            secs.push(t.elapsed().as_secs_f64());
                        }
                        Ok(voxels as f64 / vs_torch::spread(&secs[1..]).0)
                    };
                    rates[2 * j] = rate(&mapped)?;
                    rates[2 * j + 1] = rate(&device)?;
                }
                // The device's f16 conversion against the host's (round to nearest even) on
                // the first tile: values equal, one f16 step apart, further apart.
                let tile = &bank.tiles[0];
                let f = inf.extract_tile(tile, FeatureKind::Hidden)?;
                let h = inf.extract_tile_f16(tile, FeatureKind::Hidden)?;
                let mut agree = [0usize; 3];
                for (x, y) in f.iter().zip(&h) {
                    let d = (half::f16::from_f32(*x).to_bits() as i32 - y.to_bits() as i32).abs();
                    agree[d.min(2) as usize] += 1;
                }
                Ok((inf.micro_batch(), rates, agree))
            };
            match run() {
                Ok((got, r, agree)) => {
                    println!(
                        "| {} | {got} | {:.1} | {:.1} | {:.1} | {:.1} |",
                        mlp.name(),
                        r[0] / 1e6,
                        r[1] / 1e6,
                        r[2] / 1e6,
                        r[3] / 1e6
                    );
                    println!(
                        "f16 check ({}, first tile): {} values equal the host's conversion of the f32 features, {} one f16 step apart, {} further",
                        mlp.name(),
                        agree[0],
                        agree[1],
                        agree[2]
                    );
                    out.push(json!({"path": mlp.name(), "micro_batch": got,
                        "mapped_voxels_per_s": r[0], "device_voxels_per_s": r[1],
                        "f16_mapped_voxels_per_s": r[2], "f16_device_voxels_per_s": r[3],
                        "f16_equal": agree[0], "f16_one_step": agree[1], "f16_further": agree[2],
                        "voxels": voxels}));
                }
                Err(e) => {
                    println!("| {} | {mb} | failed: {e} | | | |", mlp.name());
                    out.push(
                        json!({"path": mlp.name(), "micro_batch": mb, "error": e.to_string()}),
                    );
                }
            }
        }
    }
    json!(out)
}

/// The fused path against the layered one on this adapter: one step's loss and gradients of
/// the paper's model on the same random samples (on lavapipe both are checked against the CPU
/// engine by `tests/features_gpu.rs`; here the check is that the device runs the fused program
/// as lavapipe does). Differences relative to the largest gradient of each kind.
fn paths_agree(ctx: &Arc<GpuContext>, dims: [usize; 3]) -> Value {
    use neuvolex_features::rng::Rng;
    let m = neuvolex_features::InrModel::new(&InrConfig::default(), dims, 3);
    let n = 20000;
    let mut r = Rng::new(11);
    let xs: Vec<[f32; 3]> = (0..n).map(|_| [r.f32(), r.f32(), r.f32()]).collect();
    let ps: Vec<f32> = (0..n * 125).map(|_| r.uniform(-1.0, 1.0)).collect();
    let ts: Vec<[f32; 6]> = (0..n)
        .map(|_| {
            std::array::from_fn(|k| {
                if k == 0 {
                    r.f32()
                } else {
                    r.uniform(-0.2, 0.2)
                }
            })
        })
        .collect();
    let engine = |mlp| {
        GpuInr::new(
            ctx_for(ctx, mlp),
            &m,
            None,
            EngineOptions {
                batch: n,
                micro_batch: Some(8192),
                train: true,
                slots: 1,
                brick: 8,
                order_pairs: 0,
                mlp,
            },
        )
    };
    let grads = |mlp| engine(mlp)?.gradients(&xs, &ps, &ts);
    let a = match grads(MlpPath::Layered) {
        Ok(a) => a,
        Err(e) => {
            println!("\nfused against layered: the layered path failed ({e})");
            return json!({"error": e.to_string(), "pass": false});
        }
    };
    let rel = |x: &[f32], y: &[f32]| {
        let scale = y
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs() as f64))
            .max(1e-30);
        x.iter()
            .zip(y)
            .map(|(p, q)| (*p as f64 - *q as f64).abs())
            .fold(0.0, f64::max)
            / scale
    };
    let mut out = Vec::new();
    for mlp in MlpPath::ALL.into_iter().filter(|p| p.block().is_some()) {
        let b = match grads(mlp) {
            Ok(b) => b,
            Err(e) => {
                println!("\n{} against layered: failed ({e})", mlp.name());
                out.push(json!({"path": mlp.name(), "error": e.to_string(), "pass": false}));
                continue;
            }
        };
        let (dl, dd, dt) = (
            (a.loss - b.loss).abs() / a.loss.abs().max(1e-30),
            rel(&b.dense, &a.dense),
            rel(&b.table, &a.table),
        );
        let ok = dl < 1e-6 && dd < 1e-5 && dt < 1e-5 && a.touched == b.touched;
        println!(
            "\n{} against layered on this adapter (paper model, {n} samples, micro-batches of 8192): loss {dl:.1e} relative, dense gradients {dd:.1e}, table gradients {dt:.1e} of the largest; touched entries {}: {}",
            mlp.name(),
            if a.touched == b.touched { "equal" } else { "DIFFER" },
            if ok { "PASS (tolerances 1e-6, 1e-5, 1e-5)" } else { "FAIL" }
        );
        out.push(
            json!({"path": mlp.name(), "loss_rel": dl, "dense_rel": dd, "table_rel": dt,
            "touched_equal": a.touched == b.touched, "pass": ok}),
        );
    }
    // The f16 paths: against the layered f32 path (f16's rounding, stated tolerances: loss
    // 1e-3 relative, dense 1e-2, table 5e-2 of the largest gradient), and, where the device
    // has tensor cores, against their own arithmetic on the f32 units (inputs rounded to f16,
    // products exact, only the f32 sums' order differs: 1e-5, 1e-4, 1e-3).
    for mlp in MlpPath::HALF {
        let mut e = match engine(mlp) {
            Ok(e) => e,
            Err(err) => {
                println!(
                    "
{} against layered: failed ({err})",
                    mlp.name()
                );
                out.push(json!({"path": mlp.name(), "error": err.to_string(), "pass": false}));
                continue;
            }
        };
        let arith = e.tile_arith();
        let run = |e: &mut GpuInr| e.gradients(&xs, &ps, &ts);
        let b = match run(&mut e) {
            Ok(b) => b,
            Err(err) => {
                println!(
                    "
{} ({}) against layered: failed ({err})",
                    mlp.name(),
                    arith.name()
                );
                out.push(json!({"path": mlp.name(), "arith": arith.name(), "error": err.to_string(), "pass": false}));
                continue;
            }
        };
        let d = |x: &neuvolex_features_gpu::engine::Gradients,
                 y: &neuvolex_features_gpu::engine::Gradients| {
            (
                (x.loss - y.loss).abs() / y.loss.abs().max(1e-30),
                rel(&x.dense, &y.dense),
                rel(&x.table, &y.table),
            )
        };
        let (dl, dd, dt) = d(&b, &a);
        let ok = dl < 1e-3 && dd < 1e-2 && dt < 5e-2;
        println!(
            "
{} [{}] against the layered f32 path (paper model, {n} samples, loss scale 2^{}): loss {dl:.1e} relative, dense gradients {dd:.1e}, table gradients {dt:.1e} of the largest: {}",
            mlp.name(),
            arith.name(),
            e.loss_scale_exp(n),
            if ok { "PASS (tolerances 1e-3, 1e-2, 5e-2)" } else { "FAIL" }
        );
        let mut row = json!({"path": mlp.name(), "arith": arith.name(), "loss_rel": dl,
            "dense_rel": dd, "table_rel": dt, "pass": ok});
        if arith == neuvolex_features_gpu::TileArith::TensorCores {
            let emu = e
                .set_tile_arith(neuvolex_features_gpu::TileArith::HalfRounded)
                .and_then(|_| run(&mut e));
            match emu {
                Ok(c) => {
                    let (el, ed, et) = d(&b, &c);
                    let ok2 = el < 1e-5 && ed < 1e-4 && et < 1e-3;
                    println!(
                        "{} tensor cores against the same f16 inputs on the f32 units: loss {el:.1e}, dense {ed:.1e}, table {et:.1e}: {}",
                        mlp.name(),
                        if ok2 { "PASS (tolerances 1e-5, 1e-4, 1e-3)" } else { "FAIL" }
                    );
                    row["vs_rounded"] =
                        json!({"loss_rel": el, "dense_rel": ed, "table_rel": et, "pass": ok2});
                    row["pass"] = json!(ok && ok2);
                }
                Err(err) => {
                    println!("{}: the f32-unit reference failed ({err})", mlp.name());
                    row["vs_rounded"] = json!({"error": err.to_string(), "pass": false});
                    row["pass"] = json!(false);
                }
            }
        }
        out.push(row);
    }
    // The first entry's fields at the top level, as before (the default fused path).
    let mut v = out.first().cloned().unwrap_or(json!({}));
    v["pass"] = json!(out.iter().all(|o| o["pass"] == true));
    v["paths"] = json!(out);
    v
}

/// The context a launch path's engines run on: the f32 paths on `ctx`; the f16 paths on a
/// second device on the same adapter opened for the tensor cores where it has them
/// (`GpuContext::for_tensor_cores`: with the cooperative-matrix extension on, wgpu compiles every
/// shader of the device under the Vulkan memory model, so the f32 paths stay on a device
/// opened as before), else on `ctx` with the same arithmetic on the f32 units.
fn ctx_for(ctx: &Arc<GpuContext>, mlp: MlpPath) -> &Arc<GpuContext> {
    static TENSOR: std::sync::OnceLock<Arc<GpuContext>> = std::sync::OnceLock::new();
    if !mlp.half() {
        return ctx;
    }
    TENSOR.get_or_init(|| match ctx.for_tensor_cores() {
        Ok(c) => {
            if c.has_tensor_cores() {
                println!(
                    "f16 paths: on a second device of {} opened for the tensor cores",
                    c.describe()
                );
            } else {
                println!(
                    "f16 paths: {} has no cooperative matrices of 16 x 16 f16 with f32 sums; the f16 arithmetic runs on the f32 units",
                    ctx.describe()
                );
            }
            c
        }
        Err(e) => {
            println!("f16 paths: the tensor-core device could not be opened ({e}); the f16 arithmetic runs on the f32 units");
            ctx.clone()
        }
    })
}

/// The paths whose kernels are profiled: every f32 path and the f16 path with blocks of 64.
const PROFILED: [MlpPath; 5] = [
    MlpPath::Layered,
    MlpPath::Fused,
    MlpPath::Fused32,
    MlpPath::Fused16,
    MlpPath::FusedF16,
];

/// Seconds per kernel of one step of the paper's model on `store`'s first tiles, per path.
fn profile(ctx: &Arc<GpuContext>, store: &BrickStore, paths: &[MlpPath]) -> Value {
    json!(paths
        .iter()
        .map(|&p| {
            let (timer, kernels) = match profile_path(ctx, store, p) {
                Ok(x) => x,
                Err(e) => {
                    println!("\nper-kernel time, {} path: failed ({e})", p.name());
                    return json!({"path": p.name(), "error": e.to_string()});
                }
            };
            let total: f64 = kernels
                .as_array()
                .map_or(0.0, |k| k.iter().filter_map(|x| x["seconds"].as_f64()).sum());
            json!({"path": p.name(), "timer": timer, "step_kernel_seconds": total, "kernels": kernels})
        })
        .collect::<Vec<_>>())
}

/// (timer, per-kernel JSON) of one profiled step; the timer is `gpu timestamps` where the
/// adapter has them (each dispatch's own GPU time, one submission), else `host` (each
/// dispatch submitted alone and waited for).
fn profile_path(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    mlp: MlpPath,
) -> neuvolex_features_gpu::Result<(String, Value)> {
    let m = neuvolex_features::InrModel::new(&InrConfig::default(), store.info().dims, 0);
    let brick = store.info().brick;
    let mut e = GpuInr::new(
        ctx_for(ctx, mlp),
        &m,
        None,
        EngineOptions {
            batch: 16384,
            micro_batch: None,
            train: true,
            slots: 1,
            brick,
            order_pairs: brick.pow(3),
            mlp,
        },
    )?;
    let b = training_bricks(store, false)[0];
    let tile = Tile::load(store, &b, 5).expect("tile");
    e.upload_tile(0, &tile)?;
    let n = tile.voxels();
    let pairs: Vec<u32> = (0..16384u32).flat_map(|i| [0, i % n as u32]).collect();
    e.upload_order(0, &pairs)?;
    let rates = neuvolex_features_gpu::StepRates {
        lr: 1e-3,
        lr_table: 1e-2,
        mode: neuvolex_features::TableAdam::Lazy,
    };
    e.step(0, 16384, rates, 0)?;
    ctx.wait()?;
    e.set_profile(true);
    e.step(0, 16384, rates, 1)?;
    // A second profiled step: the first on a path may include the driver's first-use costs.
    e.set_profile(true);
    e.step(0, 16384, rates, 2)?;
    let p = e.profile();
    let timer = e.profile_timer();
    let total: f64 = p.iter().map(|x| x.2).sum();
    println!(
        "\nper-kernel time of one 16384-sample step, {} path ({}; total {:.3} ms = {:.2} M samples/s if nothing else ran):",
        mlp.name(),
        if timer == "host" { "each dispatch submitted alone and waited for" } else { "GPU timestamps per dispatch, one submission" },
        total * 1e3,
        16384.0 / total / 1e6
    );
    println!("| kernel | dispatches | ms | share |\n|---|---|---|---|");
    for (k, n, s) in &p {
        println!(
            "| {k:?} | {n} | {:.3} | {:.0}% |",
            s * 1e3,
            100.0 * s / total
        );
    }
    Ok((
        timer.to_string(),
        json!(p
            .iter()
            .map(|(k, n, s)| json!({"kernel": format!("{k:?}"), "dispatches": n, "seconds": s}))
            .collect::<Vec<_>>()),
    ))
}

#[cfg(feature = "gpu")]
fn renderer() -> Vec<Value> {
    use neuvolex_render::{BrickSource, RenderParams, Renderer, StoreSource, TfFile};
    let mut out = Vec::new();
    println!("\n| volume | size | CPU ms/frame | wgpu ms/frame, still camera | CPU / wgpu | wgpu ms/frame, orbiting (new view each frame) | wgpu fps orbiting |\n|---|---|---|---|---|---|---|");
    for (name, rel, preset) in [
        ("bonsai", "scivis/bonsai.nii.gz", "grey"),
        ("abdomen_ct", "abdomen_ct/ct.nii.gz", "ct-bone"),
    ] {
        let Some(src) = shared(rel) else { continue };
        let dir = tempfile::tempdir().expect("tmp");
        let st = Arc::new(store_for(&src, dir.path()));
        let tf = TfFile::preset(preset).expect("preset");
        for size in [512usize, 1024, 2048] {
            let p = RenderParams::bench_view(size);
            let source = StoreSource::new(st.clone());
            let luts = tf.compile(&source.normaliser(), &source.classes());
            let mut c = Renderer::new(source, 2 << 30);
            c.render(&p, &luts).expect("render");
            let cpu = neuvolex_benches::median(3, || {
                c.render(&p, &luts).expect("render");
            })
            .as_secs_f64()
                * 1e3;
            let Ok(mut g) = neuvolex_render::gpu::GpuRenderer::new(StoreSource::new(st.clone()))
            else {
                continue;
            };
            g.render(&p, &luts).expect("gpu render");
            let gpu = neuvolex_benches::median(5, || {
                g.render(&p, &luts).expect("gpu render");
            })
            .as_secs_f64()
                * 1e3;
            // A camera that moves every frame (2 degrees of azimuth), as a user orbits.
            let mut az = p.camera.azimuth;
            let orbit = neuvolex_benches::median(9, || {
                az += 2.0;
                let mut q = p;
                q.camera.azimuth = az;
                g.render(&q, &luts).expect("gpu render");
            })
            .as_secs_f64()
                * 1e3;
            println!(
                "| {name} | {size}^2 | {cpu:.1} | {gpu:.1} (on {}) | {:.1}x | {orbit:.1} | {:.0} |",
                g.adapter(),
                cpu / gpu,
                1e3 / orbit
            );
            out.push(
                json!({"volume": name, "size": size, "cpu_ms": cpu, "gpu_ms": gpu,
                "gpu_orbit_ms": orbit, "adapter": g.adapter()}),
            );
        }
    }
    out
}

#[cfg(not(feature = "gpu"))]
fn renderer() -> Vec<Value> {
    eprintln!("SKIP renderer: build with --features gpu to time the wgpu renderer");
    Vec::new()
}

/// The header of the per-volume table [`gpu_volume`] prints rows of.
fn volume_table_header() {
    println!("\n| volume | dims | GPU samples/s | CPU samples/s (same run) | GPU/CPU | PSNR dB | epochs | extract voxels/s (compute / to store) | peak GPU memory |");
    println!("|---|---|---|---|---|---|---|---|---|");
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let large_epochs: f64 = arg(&args, "--large-epochs", if quick { 1.0 } else { 100.0 });
    let cap_s: f64 = arg(&args, "--cap-s", 480.0);
    // The launch-path x batch sweep: seconds per run and the batches (comma-separated).
    let sweep_s: f64 = arg(&args, "--sweep-s", if quick { 2.0 } else { 8.0 });
    let sweep_batches: Vec<usize> = arg(&args, "--sweep-batches", "16384,65536,262144".to_string())
        .split(',')
        .filter_map(|v| v.trim().parse().ok())
        .collect();
    // MLP launch paths (names of `MlpPath::name`): of the sweep, of the neuvolex sides of the
    // comparison with PyTorch (the first is the one the ratios are of), and of the per-volume
    // runs.
    let paths_of = |flag: &str, default: &str| -> Vec<MlpPath> {
        arg(&args, flag, default.to_string())
            .split(',')
            .filter(|v| !v.trim().is_empty())
            .filter_map(|v| match MlpPath::from_name(v.trim()) {
                Ok(p) => Some(p),
                Err(e) => {
                    eprintln!("{flag}: {e}; left out");
                    None
                }
            })
            .collect()
    };
    let sweep_paths = paths_of("--sweep-paths", "layered,fused,fused32,fused16");
    // Inference micro-batches of the extraction sweep (on the paths of `--paths`).
    let extract_batches: Vec<usize> =
        arg(&args, "--extract-batches", "32768,65536,262144".to_string())
            .split(',')
            .filter_map(|v| v.trim().parse().ok())
            .collect();
    let torch_paths = paths_of("--paths", "fused,fused32,fused16");
    let mlp = paths_of("--mlp", "fused")
        .first()
        .copied()
        .unwrap_or_default();
    // The comparison with PyTorch: steps per round and side, rounds, variants, screening.
    let torch_steps: usize = arg(&args, "--torch-steps", if quick { 100 } else { 400 });
    let rounds: usize = arg(&args, "--rounds", 3);
    let screen = arg(&args, "--screen", 1u32) != 0;
    let cpu_s: f64 = arg(&args, "--cpu-s", if quick { 5.0 } else { 15.0 });
    let out: Option<PathBuf> = arg(&args, "--out", String::new())
        .parse()
        .ok()
        .filter(|p: &PathBuf| !p.as_os_str().is_empty());
    let ctx = GpuContext::new(AdapterKind::Any).expect("a wgpu adapter");
    println!(
        "machine: {}; GPU: {}; date: run {}",
        machine(),
        ctx.describe(),
        std::env::var("BENCH_DATE").unwrap_or_default()
    );
    if ctx.is_software() {
        println!("NOTE: {} is a software adapter: these figures are correctness evidence, not GPU speed.", ctx.info().name);
    }
    let mut report =
        json!({"machine": machine(), "adapter": ctx.describe(), "software": ctx.is_software()});
    // PyTorch on CUDA beside an NVIDIA adapter, else on the CPU (a dry run of the code path).
    let device = if ctx.info().vendor == 0x10de {
        "cuda"
    } else {
        "cpu"
    };
    let variants: String = arg(
        &args,
        "--torch-variants",
        if device == "cuda" {
            CUDA_VARIANTS
        } else {
            CPU_VARIANTS
        }
        .to_string(),
    );
    let vs = |store: &BrickStore| {
        vs_torch_gpu(
            &ctx,
            store,
            device,
            torch_steps,
            rounds,
            &variants,
            screen,
            &torch_paths,
        )
    };
    let write = |report: &Value| {
        if let Some(o) = &out {
            std::fs::write(o, serde_json::to_vec_pretty(report).expect("json"))
                .expect("write report");
            println!("\nreport: {}", o.display());
        }
    };
    // `--only torch`: just the comparison with PyTorch on CT-Tooth.
    if arg(&args, "--only", String::new()) == "torch" {
        let vol = match arg(&args, "--volume", String::new()) {
            v if v.is_empty() => shared("tooth/tooth.nhdr"),
            v => Some(PathBuf::from(v)),
        };
        if let Some(p) = vol {
            let dir = tempfile::tempdir().expect("tmp");
            report["torch"] = vs(&store_for(&p, dir.path()));
        }
        write(&report);
        return;
    }
    // `--only stages`: the path checks, per-kernel profile, sweep and extraction sweep alone,
    // on `--volume FILE` (any readable volume; a small one makes a smoke test on lavapipe)
    // or CT-Tooth.
    if arg(&args, "--only", String::new()) == "stages" {
        let vol = match arg(&args, "--volume", String::new()) {
            v if v.is_empty() => shared("tooth/tooth.nhdr"),
            v => Some(PathBuf::from(v)),
        };
        if let Some(p) = vol {
            let dir = tempfile::tempdir().expect("tmp");
            let store = store_for(&p, dir.path());
            report["paths_agree"] = paths_agree(&ctx, store.info().dims);
            write(&report);
            report["profile"] = profile(&ctx, &store, &PROFILED);
            write(&report);
            report["sweep"] = sweep(&ctx, &store, sweep_s, &sweep_batches, &sweep_paths);
            write(&report);
            report["extract_sweep"] = extract_sweep(&ctx, &store, &torch_paths, &extract_batches);
        }
        write(&report);
        return;
    }
    // `--only agree`: just the fused-against-layered check (a quick smoke test of a build).
    if arg(&args, "--only", String::new()) == "agree" {
        report["paths_agree"] = paths_agree(&ctx, [103, 94, 161]);
        write(&report);
        return;
    }
    volume_table_header();
    let mut vols = Vec::new();
    let work = tempfile::tempdir().expect("tmp");
    let mut cases: Vec<(String, PathBuf, f64, Option<f64>)> = Vec::new();
    if let Some(p) = shared("tooth/tooth.nhdr") {
        cases.push((
            "CT-Tooth".into(),
            p,
            if quick { 3.0 } else { 10.0 },
            Some(cap_s),
        ));
    }
    if let Some(p) = shared("abdomen_ct/ct.nii.gz") {
        cases.push((
            "abdomen CT".into(),
            p,
            if quick { 3.0 } else { 10.0 },
            Some(cap_s),
        ));
    }
    for (name, src, epochs, cap) in &cases {
        let dir = tempfile::tempdir_in(work.path()).expect("tmp");
        let store = store_for(src, dir.path());
        let v = gpu_volume(&ctx, name, &store, *epochs, *cap, cpu_s, mlp);
        if name == "CT-Tooth" {
            report["paths_agree"] = paths_agree(&ctx, store.info().dims);
            report["profile"] = profile(&ctx, &store, &PROFILED);
            write(&report);
            report["sweep"] = sweep(&ctx, &store, sweep_s, &sweep_batches, &sweep_paths);
            write(&report);
            report["extract_sweep"] = extract_sweep(&ctx, &store, &torch_paths, &extract_batches);
            write(&report);
            report["torch"] = vs(&store);
            // A partial report now, in case the device's time limit cuts the run short.
            write(&report);
            volume_table_header();
        }
        vols.push(v);
        report["volumes"] = json!(vols);
        write(&report);
    }
    report["renderer"] = json!(renderer());
    write(&report);
    // The large phantom last: its extraction into the store is the longest part of the run,
    // so a run cut short still reports the rest.
    let raw = work.path().join("cta_512x512x452_int16.raw");
    neuvolex_benches::write_cta(&raw);
    volume_table_header();
    let dir = tempfile::tempdir_in(work.path()).expect("tmp");
    let store = store_for(&raw, dir.path());
    vols.push(gpu_volume(
        &ctx,
        "phantom 512x512x452",
        &store,
        large_epochs,
        Some(cap_s),
        cpu_s,
        mlp,
    ));
    report["volumes"] = json!(vols);
    write(&report);
}
