//! The INR on the GPU (`cargo bench -p neuvolex-benches --bench inr_gpu [--features gpu]`):
//! 1. per volume (CT-Tooth, the abdomen CT, a 512x512x452 CT-like phantom), the paper's model
//!    trained by the GPU engine: steady samples/s, PSNR against time, peak GPU memory, and
//!    feature extraction voxels/s (compute only, and into the store as f16); the CPU engine on
//!    the same volume in the same run for the ratio;
//! 2. the same model in PyTorch on the same device (`benches/inr_torch.py --device cuda`,
//!    dense Adam, sparse Adam and torch.compile; the fastest is the reference);
//! 3. per-kernel times of one step on both launch paths (each dispatch waited for: where the
//!    time goes, not speed), and a sweep of launch path x batch size on CT-Tooth (samples/s
//!    and PSNR after the same seconds of training);
//! 4. with `--features gpu`, the wgpu renderer against the CPU renderer (bonsai, abdomen;
//!    512^2 and 1024^2).
//!
//! The phantom runs last (its extraction into the store is the longest part), so a run cut
//! short by the device's time limit still reports the rest.
//!
//! Options: `--quick` (1 epoch on the large volume, short PyTorch runs), `--large-epochs N`
//! (default 100, the paper's), `--cap-s S` (wall-clock cap of the large run, default 480; the
//! 100-epoch time is then extrapolated and marked so), `--sweep-s S` and `--sweep-batches
//! B,B,..` (the launch-path x batch sweep), `--torch-s S` (each PyTorch variant), `--cpu-s S`
//! (the CPU engine per volume), `--only agree` (only the fused-against-layered check), `--out
//! FILE` (JSON of everything).
//! `NEUVOLEX_DATA` names the data folder (default ../shared/data), `NEUVOLEX_TORCH_PYTHON` the
//! Python with torch. On a software adapter (lavapipe) every figure is correctness evidence,
//! not speed, and the bench says so.

use neuvolex_benches::{machine, shared};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_features::tile::Tile;
use neuvolex_features::train::training_bricks;
use neuvolex_features::{train, Budget, FeatureKind, InrConfig, TrainConfig, TrainEvent};
use neuvolex_features_gpu::{
    train_gpu, train_gpu_tuned, write_features_gpu, AdapterKind, EngineOptions, GpuContext, GpuInr,
    GpuTune, MlpPath,
};
use neuvolex_ingest::{ingest, IngestOptions};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

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
) -> Value {
    let voxels: u64 = training_bricks(store, false)
        .iter()
        .map(|b| b.voxels() as u64)
        .sum();
    let mut ev = Vec::new();
    let t = Instant::now();
    let g = train_gpu(
        ctx,
        store,
        &InrConfig::default(),
        &cfg(epochs, cap_s),
        None,
        None,
        &AtomicBool::new(false),
        &mut |e| ev.push(e),
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
        EngineOptions::inference(store.info().brick),
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
        "volume": name, "dims": store.info().dims, "voxels_per_epoch": voxels,
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

/// The same model in PyTorch on `device` (each variant; the fastest is the reference).
fn torch(device: &str, finest: usize, seconds: f64) -> Vec<Value> {
    let py = std::env::var("NEUVOLEX_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = std::env::var_os("NEUVOLEX_TORCH_SCRIPT")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("inr_torch.py"));
    let mut out = Vec::new();
    // On CUDA the strongest settings: fused Adam and CUDA graphs (`reduce-overhead`) beside the
    // default compile; on the CPU the plain, sparse and compiled variants.
    let variants: Vec<&[&str]> = if device == "cuda" {
        vec![
            &["--compile"],
            &["--compile", "--fused-adam"],
            &[
                "--compile",
                "--fused-adam",
                "--compile-mode",
                "reduce-overhead",
            ],
        ]
    } else {
        vec![&[], &["--sparse"], &["--compile"]]
    };
    for extra in variants {
        let o = std::process::Command::new(&py)
            .arg(&script)
            .args([
                "--device",
                device,
                "--finest",
                &finest.to_string(),
                "--seconds",
                &seconds.to_string(),
            ])
            .args(extra)
            .output();
        match o {
            Ok(o) if o.status.success() => {
                if let Some(v) = String::from_utf8_lossy(&o.stdout)
                    .lines()
                    .last()
                    .and_then(|l| serde_json::from_str::<Value>(l).ok())
                {
                    out.push(v);
                }
            }
            Ok(o) => eprintln!(
                "torch {extra:?}: {}",
                String::from_utf8_lossy(&o.stderr)
                    .lines()
                    .last()
                    .unwrap_or("failed")
            ),
            Err(e) => eprintln!("SKIP torch: {e}"),
        }
    }
    out
}

/// Launch path x batch size on `store`: each trains the paper's model for `seconds` from the
/// same seed; samples/s (steady) and the PSNR reached, so speed and quality are read together.
fn sweep(ctx: &Arc<GpuContext>, store: &BrickStore, seconds: f64, batches: &[usize]) -> Value {
    println!("\nlaunch path x batch ({seconds} s of training each, same seed):");
    println!("| path | batch | micro-batch | samples/s | steps | PSNR dB | peak GPU memory |");
    println!("|---|---|---|---|---|---|---|");
    let mut out = Vec::new();
    for &batch in batches {
        for mlp in [MlpPath::Layered, MlpPath::Fused] {
            let mut ev = Vec::new();
            let c = TrainConfig {
                batch,
                ..cfg(1000.0, Some(seconds))
            };
            let r = train_gpu_tuned(
                ctx,
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
    let grads = |mlp| {
        let mut e = GpuInr::new(
            ctx,
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
        .expect("engine");
        e.gradients(&xs, &ps, &ts).expect("gradients")
    };
    let (a, b) = (grads(MlpPath::Layered), grads(MlpPath::Fused));
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
    let (dl, dd, dt) = (
        (a.loss - b.loss).abs() / a.loss.abs().max(1e-30),
        rel(&b.dense, &a.dense),
        rel(&b.table, &a.table),
    );
    let ok = dl < 1e-6 && dd < 1e-5 && dt < 1e-5 && a.touched == b.touched;
    println!(
        "\nfused against layered on this adapter (paper model, {n} samples, micro-batches of 8192): loss {dl:.1e} relative, dense gradients {dd:.1e}, table gradients {dt:.1e} of the largest; touched entries {}: {}",
        if a.touched == b.touched { "equal" } else { "DIFFER" },
        if ok { "PASS (tolerances 1e-6, 1e-5, 1e-5)" } else { "FAIL" }
    );
    json!({"loss_rel": dl, "dense_rel": dd, "table_rel": dt, "touched_equal": a.touched == b.touched, "pass": ok})
}

/// Seconds per kernel of one step of the paper's model on `store`'s first tiles, per path.
fn profile(ctx: &Arc<GpuContext>, store: &BrickStore) -> Value {
    json!([MlpPath::Layered, MlpPath::Fused]
        .into_iter()
        .map(|p| json!({"path": p.name(), "kernels": profile_path(ctx, store, p)}))
        .collect::<Vec<_>>())
}

fn profile_path(ctx: &Arc<GpuContext>, store: &BrickStore, mlp: MlpPath) -> Value {
    let m = neuvolex_features::InrModel::new(&InrConfig::default(), store.info().dims, 0);
    let brick = store.info().brick;
    let mut e = GpuInr::new(
        ctx,
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
    )
    .expect("engine");
    let b = training_bricks(store, false)[0];
    let tile = Tile::load(store, &b, 5).expect("tile");
    e.upload_tile(0, &tile).expect("tile");
    let n = tile.voxels();
    let pairs: Vec<u32> = (0..16384u32).flat_map(|i| [0, i % n as u32]).collect();
    e.upload_order(0, &pairs).expect("order");
    let rates = neuvolex_features_gpu::StepRates {
        lr: 1e-3,
        lr_table: 1e-2,
        mode: neuvolex_features::TableAdam::Lazy,
    };
    e.step(0, 16384, rates, 0).expect("warm-up");
    ctx.wait().expect("wait");
    e.set_profile(true);
    e.step(0, 16384, rates, 1).expect("step");
    let p = e.profile();
    let total: f64 = p.iter().map(|x| x.2).sum();
    println!(
        "\nper-kernel time of one 16384-sample step, {} path (each dispatch waited for; total {:.2} ms):",
        mlp.name(),
        total * 1e3
    );
    println!("| kernel | dispatches | ms | share |\n|---|---|---|---|");
    for (k, n, s) in &p {
        println!(
            "| {k:?} | {n} | {:.3} | {:.0}% |",
            s * 1e3,
            100.0 * s / total
        );
    }
    json!(p
        .iter()
        .map(|(k, n, s)| json!({"kernel": format!("{k:?}"), "dispatches": n, "seconds": s}))
        .collect::<Vec<_>>())
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
    let torch_s: f64 = arg(&args, "--torch-s", if quick { 8.0 } else { 20.0 });
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
    // `--only agree`: just the fused-against-layered check (a quick smoke test of a build).
    if arg(&args, "--only", String::new()) == "agree" {
        report["paths_agree"] = paths_agree(&ctx, [103, 94, 161]);
        if let Some(o) = out {
            std::fs::write(&o, serde_json::to_vec_pretty(&report).expect("json"))
                .expect("write report");
        }
        return;
    }
    volume_table_header();
    let mut vols = Vec::new();
    let mut tooth_sps = f64::NAN;
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
        let v = gpu_volume(&ctx, name, &store, *epochs, *cap, cpu_s);
        if name == "CT-Tooth" {
            tooth_sps = v["train_samples_per_s"].as_f64().unwrap_or(f64::NAN);
            report["paths_agree"] = paths_agree(&ctx, store.info().dims);
            report["profile"] = profile(&ctx, &store);
            report["sweep"] = sweep(&ctx, &store, sweep_s, &sweep_batches);
            volume_table_header();
        }
        vols.push(v);
    }
    let device = if ctx.info().vendor == 0x10de {
        "cuda"
    } else {
        "cpu"
    };
    let t = torch(device, 161, torch_s);
    if let Some(best) = t.iter().max_by(|a, b| {
        a["train_samples_per_s"]
            .as_f64()
            .partial_cmp(&b["train_samples_per_s"].as_f64())
            .unwrap_or(std::cmp::Ordering::Equal)
    }) {
        let ts = best["train_samples_per_s"].as_f64().unwrap_or(f64::NAN);
        println!(
            "\nPyTorch on {device} (CT-Tooth model sizes): {}",
            t.iter()
                .map(|v| format!(
                    "{}{}{}{}: {:.2} M samples/s",
                    if v["sparse"] == true {
                        "sparse"
                    } else {
                        "dense"
                    },
                    if v["fused_adam"] == true {
                        " fused Adam"
                    } else {
                        ""
                    },
                    if v["compile"] == true { "+compile" } else { "" },
                    match v["compile_mode"].as_str() {
                        Some(m) if m != "default" => format!(" ({m})"),
                        _ => String::new(),
                    },
                    v["train_samples_per_s"].as_f64().unwrap_or(0.0) / 1e6
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
        println!(
            "neuvolex GPU / best PyTorch: {:.2}x (training)",
            tooth_sps / ts
        );
        report["torch"] = json!({"device": device, "runs": t, "ratio": tooth_sps / ts});
    }
    report["renderer"] = json!(renderer());
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
    ));
    report["volumes"] = json!(vols);
    if let Some(o) = out {
        std::fs::write(&o, serde_json::to_vec_pretty(&report).expect("json"))
            .expect("write report");
        println!("\nreport: {}", o.display());
    }
}
