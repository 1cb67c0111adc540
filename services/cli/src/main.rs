//! `neuvolex`: the command line of the neuvolex volume-exploration system.
//!
//! The binary only parses arguments, draws progress and prints; the work is in the library crates.

mod backend;
mod classify;
mod cluster;
mod eval;
mod render;
mod serve;
mod viewpoints;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_bricks::synth::{phantom_classes, ClassInfo, Phantom, PhantomChannel, PhantomParams};
use neuvolex_bricks::{open_volume, BrickStore, Progress, VolumeStats};
use neuvolex_formats::{DType, Endian, RawSpec};
use neuvolex_ingest::{ingest, IngestOptions, NonFinitePolicy};
use neuvolex_ingest::{scan_volume, ScanReport};
use std::path::{Path, PathBuf};

#[derive(Parser)]
#[command(
    name = "neuvolex",
    version,
    about = "Explore large 3-D volumes with learned features"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
    /// Hide progress bars.
    #[arg(long, global = true)]
    quiet: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum Scene {
    /// A labelled CT-like abdomen phantom (the embedded default).
    Phantom,
    /// Crawfis' analytic tornado, velocity magnitude (the paper's Tornado scene).
    Tornado,
    /// A solid cube with "NVX" engraved on its -y face, labelled (the paper's Cube scene).
    Cube,
}

#[derive(clap::Args, Clone, Default)]
struct RawArgs {
    /// Raw files: grid as X,Y,Z.
    #[arg(long)]
    dims: Option<String>,
    /// Raw files: voxel type (u8, i8, u16, i16, u32, i32, f32, f64).
    #[arg(long)]
    dtype: Option<String>,
    /// Raw files: byte order (little or big).
    #[arg(long, default_value = "little")]
    endian: String,
    /// Raw files: voxel spacing as X,Y,Z.
    #[arg(long)]
    spacing: Option<String>,
    /// Raw files: bytes to skip before the data.
    #[arg(long, default_value_t = 0)]
    offset: u64,
}

impl RawArgs {
    fn spec(&self) -> Result<Option<RawSpec>> {
        let (Some(d), Some(t)) = (&self.dims, &self.dtype) else {
            if self.dims.is_some() || self.dtype.is_some() {
                bail!("raw input needs both --dims and --dtype");
            }
            return Ok(None);
        };
        let dtype = DType::parse(t).with_context(|| {
            format!("unknown --dtype '{t}' (use u8, i8, u16, i16, u32, i32, f32 or f64)")
        })?;
        let endian = Endian::parse(&self.endian)
            .with_context(|| format!("--endian '{}' must be little or big", self.endian))?;
        let spacing = match &self.spacing {
            Some(s) => triple(s, "--spacing")?,
            None => [1.0; 3],
        };
        Ok(Some(RawSpec {
            dims: triple(d, "--dims")?,
            dtype,
            endian,
            spacing,
            offset: self.offset,
        }))
    }
}

/// Reads a JSON class table: `[{"id": 1, "name": "bone", "color": [r, g, b]}, ...]`.
fn read_classes(p: &Path) -> Result<Vec<ClassInfo>> {
    let text = std::fs::read_to_string(p)
        .with_context(|| format!("{}: cannot read class table", p.display()))?;
    let c: Vec<ClassInfo> = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not a class table (expected [{{\"id\", \"name\", \"color\"}}, ...])",
            p.display()
        )
    })?;
    let mut ids: Vec<u32> = c.iter().map(|c| c.id).collect();
    ids.sort_unstable();
    ids.dedup();
    if ids.len() != c.len() {
        bail!("{}: duplicate class ids", p.display());
    }
    Ok(c)
}

/// Parses `A,B,C`.
fn triple<T: std::str::FromStr + Copy>(s: &str, flag: &str) -> Result<[T; 3]> {
    let v: Vec<T> = s
        .split(',')
        .map(|p| p.trim().parse::<T>().ok())
        .collect::<Option<_>>()
        .with_context(|| format!("{flag} '{s}': expected three comma-separated numbers"))?;
    match v.as_slice() {
        [a, b, c] => Ok([*a, *b, *c]),
        _ => bail!(
            "{flag} '{s}': expected three comma-separated numbers, got {}",
            v.len()
        ),
    }
}

#[derive(Subcommand)]
enum Cmd {
    /// Generate a synthetic labelled scene (.zarr store, or .nii/.nii.gz plus a _labels file).
    Synth {
        /// Which scene.
        scene: Scene,
        /// Output path.
        #[arg(long)]
        out: PathBuf,
        /// Width in voxels (x = y = size, z = 7/8 size).
        #[arg(long, default_value_t = 128)]
        size: usize,
        /// Noise seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Brick edge for .zarr output.
        #[arg(long, default_value_t = 64)]
        brick: usize,
        /// Replace an existing output.
        #[arg(long)]
        force: bool,
    },
    /// Ingest a volume (NIfTI, NRRD, raw, OME-Zarr) into an OME-Zarr brick store.
    Ingest {
        /// Input volume.
        input: PathBuf,
        /// Output store (.zarr).
        output: PathBuf,
        /// Brick edge in voxels (power of two, 8..512).
        #[arg(long, default_value_t = 64)]
        brick: usize,
        /// Bricks per shard edge (enables Zarr sharding).
        #[arg(long)]
        shard: Option<usize>,
        /// zstd compression level.
        #[arg(long, default_value_t = 3)]
        zstd_level: i32,
        /// What to do with NaN/Inf values.
        #[arg(long, value_enum, default_value = "reject")]
        non_finite: NonFinite,
        /// Ground-truth or scribble label volume on the same grid.
        #[arg(long)]
        labels: Option<PathBuf>,
        /// Name of the label image in the store.
        #[arg(long, default_value = "ground_truth")]
        labels_name: String,
        /// JSON class table for the labels: [{"id": 1, "name": "bone", "color": [r, g, b]}, ...].
        #[arg(long)]
        classes: Option<PathBuf>,
        /// Replace an existing store.
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        raw: RawArgs,
        /// With --cluster, slab tasks (one brick of z-slices each, `--bricks-per-task` slabs a
        /// task) run on the workers, which must read INPUT at the same absolute path.
        #[command(flatten)]
        cluster: cluster::ClusterArgs,
    },
    /// Describe a volume file or store: grid, type, spacing, value range, histogram, bricks.
    Info {
        /// Input volume or store.
        input: PathBuf,
        /// Brick edge for occupancy of plain files.
        #[arg(long, default_value_t = 64)]
        brick: usize,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        raw: RawArgs,
    },
    /// Break the writer lock of a store on S3 whose holder is gone (file-system locks end
    /// with their process); prints the holder it had.
    Unlock {
        /// Brick store (path or s3://bucket/prefix.zarr).
        store: PathBuf,
    },
    /// Train the INR on a brick store (by tile, checkpointed, resumable).
    Train {
        /// Brick store (.zarr) from `neuvolex ingest`.
        store: PathBuf,
        #[command(flatten)]
        args: TrainArgs,
        /// Data-parallel replicas: each round, every replica trains `--sync-steps` batches of
        /// the sample stream from the shared model, then the replicas are averaged (hash-table
        /// entries over the replicas that touched them). The model depends on the seed and
        /// this count, not on how many workers run the replicas. 1 without --cluster is the
        /// single-node trainer.
        #[arg(long, default_value_t = 1)]
        replicas: u32,
        /// Optimiser steps each replica takes between synchronisations.
        #[arg(long, default_value_t = 16)]
        sync_steps: u64,
        #[command(flatten)]
        cluster: cluster::ClusterArgs,
    },
    /// Extract per-voxel INR features of a trained store into it (f16, one chunk per brick).
    Features {
        /// Brick store with a trained model (`neuvolex train`).
        store: PathBuf,
        /// Feature: hidden (the paper's 64-D last hidden layer), pos, mod, or concat.
        #[arg(long, default_value = "hidden")]
        kind: String,
        /// Also extract empty bricks.
        #[arg(long)]
        all_bricks: bool,
        /// Engine: cpu, gpu or auto (a hardware GPU where one exists).
        #[arg(long, default_value = "auto")]
        backend: String,
        #[command(flatten)]
        cluster: cluster::ClusterArgs,
    },
    /// Classify every voxel from scribbles: random forest on a feature set, per-class u8
    /// probabilities and a label image in the store, optionally a NIfTI label volume.
    Classify(classify::ClassifyArgs),
    /// Score feature sets against ground truth: simulated scribbles, F1 per class and level.
    Eval(eval::EvalArgs),
    /// Simulate scribbles (S1–S4) from a ground-truth label volume, deterministically.
    ScribbleSim {
        /// Ground-truth labels (0 = background), any readable format or store/labels/NAME.
        labels: PathBuf,
        /// Density: S1 (1 slice), S2 (~3), S3 (~9), S4 (~27).
        #[arg(long, default_value = "S1")]
        level: String,
        /// Seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Label painted on background.
        #[arg(long, default_value_t = 255)]
        background: u32,
        /// Output sparse label volume (.nii or .nii.gz); the strokes go beside it as JSON.
        #[arg(long)]
        out: PathBuf,
        /// Replace existing outputs.
        #[arg(long)]
        force: bool,
    },
    /// Render a store to PNG: intensity, class probabilities, or labels as probabilities.
    Render(render::RenderArgs),
    /// Serve the browser UI and HTTP API (prints the URL).
    Serve(serve::ServeArgs),
    /// Recommend viewpoints: k-means on features, view entropy, greedy complementary views.
    Viewpoints(viewpoints::ViewpointArgs),
    /// Serve brick tasks of a cluster (NATS JetStream) until told to stop.
    Worker(cluster::WorkerArgs),
    /// Convert any readable volume (including a store or store/labels/NAME) to NIfTI.
    Convert {
        /// Input volume.
        input: PathBuf,
        /// Output .nii or .nii.gz.
        output: PathBuf,
        /// Replace an existing output.
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        raw: RawArgs,
    },
}

/// Training options shared by `train`.
#[derive(clap::Args, Clone)]
struct TrainArgs {
    /// Speed/accuracy preset (fast: 1 epoch; balanced: 5; paper: 100 at lr 1e-4).
    #[arg(long, default_value = "fast")]
    preset: String,
    /// Budget in epochs (overrides the preset).
    #[arg(long)]
    epochs: Option<f64>,
    /// Budget in samples.
    #[arg(long)]
    samples: Option<u64>,
    /// Budget in wall-clock seconds.
    #[arg(long)]
    seconds: Option<f64>,
    /// Samples per step.
    #[arg(long)]
    batch: Option<usize>,
    /// MLP learning rate.
    #[arg(long)]
    lr: Option<f32>,
    /// Hash-table learning rate.
    #[arg(long)]
    lr_table: Option<f32>,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Ablation: base, structural, film, full.
    #[arg(long, default_value = "full")]
    ablation: String,
    /// Hash-table Adam: lazy (touched rows) or dense.
    #[arg(long, default_value = "lazy")]
    table_adam: String,
    /// Bricks resident at once.
    #[arg(long)]
    tile_bricks: Option<usize>,
    /// Train on empty bricks too.
    #[arg(long)]
    include_empty: bool,
    /// Continue from the store's checkpoint.
    #[arg(long)]
    resume: bool,
    /// Save a resumable checkpoint every N optimiser steps (0: only at the end and every 2 min).
    #[arg(long)]
    checkpoint_every: Option<u64>,
    /// log2 of the hash-table size per level (the paper's 19; smaller is a smaller model).
    #[arg(long)]
    log2_table: Option<u32>,
    /// Engine: cpu (the fused CPU engine), gpu (the GPU engine on any adapter, software ones
    /// included), auto (a hardware GPU where one exists, else cpu). GPU needs `--features gpu`.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// The GPU engine's MLP launch path: fused (the default, f32), fused32, fused16, layered,
    /// or fused-f16, fused32-f16, fused16-f16 (f16 GEMM inputs with f32 sums and loss scaling,
    /// on the tensor cores where the card has cooperative matrices, else on the f32 units; not
    /// yet measured on a GPU, BENCHMARKS.md). Only with the GPU engine.
    #[arg(long)]
    gpu_mlp: Option<String>,
}

impl TrainArgs {
    fn configs(&self) -> Result<(neuvolex_features::InrConfig, neuvolex_features::TrainConfig)> {
        use neuvolex_features::{InrConfig, Preset, TableAdam, TrainConfig};
        let preset: Preset = self.preset.parse().map_err(anyhow::Error::msg)?;
        let mut t = TrainConfig::preset(preset);
        if self.epochs.is_some() || self.samples.is_some() || self.seconds.is_some() {
            t.budget = neuvolex_features::Budget {
                epochs: self.epochs,
                samples: self.samples,
                seconds: self.seconds,
            };
        }
        for (name, v) in [("--epochs", self.epochs), ("--seconds", self.seconds)] {
            if let Some(v) = v {
                if !(v > 0.0 && v.is_finite()) {
                    bail!("{name} {v} must be positive");
                }
            }
        }
        if let Some(b) = self.batch {
            if b == 0 || b > 1 << 22 {
                bail!("--batch {b} must be 1..=4194304");
            }
            t.batch = b;
        }
        if let Some(v) = self.lr {
            t.lr = v;
        }
        if let Some(v) = self.lr_table {
            t.lr_table = v;
        }
        if let Some(v) = self.tile_bricks {
            t.tile_bricks = v;
        }
        if let Some(v) = self.checkpoint_every {
            t.checkpoint_every = v;
        }
        t.seed = self.seed;
        t.include_empty = self.include_empty;
        t.table_adam = match self.table_adam.as_str() {
            "lazy" => TableAdam::Lazy,
            "dense" => TableAdam::Dense,
            o => bail!("--table-adam '{o}' must be lazy or dense"),
        };
        let mut inr = InrConfig {
            ablation: self.ablation.parse().map_err(anyhow::Error::msg)?,
            ..InrConfig::default()
        };
        if let Some(v) = self.log2_table {
            if !(8..=24).contains(&v) {
                bail!("--log2-table {v} must be 8..=24");
            }
            inr.log2_table = v;
        }
        let _: neuvolex_features::Backend = self.backend.parse().map_err(anyhow::Error::msg)?;
        if let Some(m) = &self.gpu_mlp {
            backend::check_gpu_mlp(m)?;
            if self.backend == "cpu" {
                bail!("--gpu-mlp {m}: the GPU engine's option, and --backend is cpu");
            }
        }
        Ok((inr, t))
    }
}

/// The training progress bar (samples against the budget), hidden when `quiet`.
fn train_bar(quiet: bool) -> ProgressBar {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(0)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "train [{bar:40}] {pos}/{len} samples {msg} {elapsed} eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar
}

/// Saves a trained model into its store and returns its path with the PSNR of the middle slice
/// reconstructed by the CPU evaluator: one measure for every engine and executor.
fn save_model(
    store: &BrickStore,
    model: &neuvolex_features::InrModel,
) -> Result<(neuvolex_bricks::StoreLocation, f64)> {
    use neuvolex_features::{checkpoint, TrainEvent};
    let path = neuvolex_features::train::model_path(store);
    checkpoint::save(&path, model, None)?;
    let psnr = match neuvolex_features::train::preview(store, model, 512)?.event(0) {
        TrainEvent::Preview { psnr, .. } => psnr,
        _ => f64::NAN,
    };
    Ok((path, psnr))
}

fn run_train(store_path: &Path, args: &TrainArgs, quiet: bool) -> Result<()> {
    use neuvolex_features::{checkpoint, TrainEvent};
    let store = BrickStore::open(store_path)?;
    let (inr, cfg) = args.configs()?;
    // Checkpoints and the model are written into the store: one writer at a time.
    let _lock = store.writer_lock("train")?;
    let ckpt = neuvolex_features::train::checkpoint_path(&store);
    let resume = if args.resume {
        if !ckpt.exists() {
            bail!(
                "{}: no checkpoint to resume from (train without --resume first)",
                ckpt.display()
            );
        }
        Some(checkpoint::load(&ckpt)?)
    } else {
        None
    };
    let engine = backend::Engine::pick(&args.backend)?;
    let cancel = std::sync::atomic::AtomicBool::new(false);
    let bar = train_bar(quiet);
    let mut on_event = |e: TrainEvent| match &e {
        TrainEvent::Started {
            bricks,
            total_bricks,
            voxels,
            params,
            budget_samples,
            from_step,
        } => {
            bar.set_length(budget_samples.unwrap_or(0));
            tracing::info!(bricks, total_bricks, voxels, params, from_step, "training");
        }
        TrainEvent::Step {
            samples,
            loss,
            psnr,
            samples_per_sec,
            epoch,
            ..
        } => {
            bar.set_position(*samples);
            bar.set_message(format!(
                "epoch {epoch:.2} loss {loss:.3e} PSNR {psnr:.2} dB {:.0} k samples/s",
                samples_per_sec / 1e3
            ));
        }
        TrainEvent::Preview { step, psnr, .. } => tracing::debug!(step, psnr, "preview"),
        TrainEvent::Checkpoint { step, path } => {
            tracing::debug!(step, path = %path.display(), "checkpoint")
        }
        TrainEvent::Finished {
            steps,
            samples,
            seconds,
            psnr,
            stopped_by,
        } => {
            bar.finish_and_clear();
            tracing::info!(
                steps,
                samples,
                seconds,
                psnr,
                stopped_by,
                samples_per_sec = *samples as f64 / seconds.max(1e-9),
                "training finished"
            );
        }
    };
    let t = engine.train(
        &store,
        &inr,
        &cfg,
        resume,
        Some(&ckpt),
        &cancel,
        &mut on_event,
        args.gpu_mlp.as_deref(),
    )?;
    let (path, slice_psnr) = save_model(&store, &t.model)?;
    println!(
        "model: {} (PSNR {:.2} dB last batch, {:.2} dB middle slice, after {} samples in {:.1} s, {})",
        path.display(),
        t.psnr,
        slice_psnr,
        t.state.samples,
        t.state.seconds,
        match &args.gpu_mlp {
            Some(m) => format!("{}, MLP {m}", engine.describe()),
            None => engine.describe(),
        }
    );
    Ok(())
}

/// `neuvolex train --replicas N` / `--cluster URL`: data-parallel training on an executor.
fn run_train_distributed(
    store_path: &Path,
    args: &TrainArgs,
    replicas: u32,
    sync_steps: u64,
    cl: &cluster::ClusterArgs,
    quiet: bool,
) -> Result<()> {
    use neuvolex_features::{distributed, TrainEvent};
    let (inr, cfg) = args.configs()?;
    if args.resume {
        bail!("--resume continues a single-node checkpoint: drop --replicas/--cluster");
    }
    if args.backend == "gpu" || args.gpu_mlp.is_some() {
        bail!("distributed training runs the CPU engine on every worker: use --backend cpu without --gpu-mlp");
    }
    let store = BrickStore::open(store_path)?;
    let exec = cl.executor()?;
    let _lock = store.writer_lock("train")?;
    let bar = train_bar(quiet);
    let per_worker = std::cell::RefCell::new(std::collections::BTreeMap::<String, u64>::new());
    let mut progress = |e: neuvolex_tasks::RunEvent| match e {
        neuvolex_tasks::RunEvent::Task { worker, .. } => {
            *per_worker.borrow_mut().entry(worker).or_default() += 1
        }
        neuvolex_tasks::RunEvent::Message(m) => bar.suspend(|| eprintln!("{m}")),
        _ => {}
    };
    let mut on_event = |e: TrainEvent| match e {
        TrainEvent::Started { budget_samples, .. } => bar.set_length(budget_samples.unwrap_or(0)),
        TrainEvent::Step {
            samples,
            loss,
            psnr,
            epoch,
            ..
        } => {
            bar.set_position(samples);
            let w: Vec<String> = per_worker
                .borrow()
                .iter()
                .map(|(w, n)| format!("{w}:{n}"))
                .collect();
            bar.set_message(format!(
                "epoch {epoch:.2} loss {loss:.3e} PSNR {psnr:.2} dB [{}]",
                w.join(" ")
            ));
        }
        TrainEvent::Finished { .. } => bar.finish_and_clear(),
        _ => {}
    };
    let (t, report) = distributed::train_on(
        &exec,
        &store,
        &neuvolex_classify::pipeline::store_path_string(store_path),
        &inr,
        &cfg,
        distributed::Replication {
            replicas,
            sync_steps,
        },
        &mut progress,
        &mut on_event,
    )?;
    let (path, slice_psnr) = save_model(&store, &t.model)?;
    println!(
        "model: {} (PSNR {:.2} dB last round, {:.2} dB middle slice, after {} samples in {:.1} s, \
         {replicas} replicas x {sync_steps} steps per round on {}: {} tasks, {} redelivered, per worker {:?})",
        path.display(),
        t.psnr,
        slice_psnr,
        t.state.samples,
        t.state.seconds,
        report.executor,
        report.completed,
        report.redeliveries,
        report.per_worker
    );
    Ok(())
}

#[derive(Clone, Copy, ValueEnum)]
enum NonFinite {
    /// Fail, naming the first NaN/Inf voxel.
    Reject,
    /// Replace NaN/Inf by 0 and count them.
    Zero,
}

fn progress_sink(quiet: bool) -> impl FnMut(Progress) {
    let mut bar: Option<ProgressBar> = None;
    move |p| {
        if quiet {
            return;
        }
        match p {
            Progress::Stage { name, total } => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
                let b = ProgressBar::new(total);
                b.set_style(
                    ProgressStyle::with_template(
                        "{prefix:>10} [{bar:40}] {pos}/{len} slices {elapsed} eta {eta}",
                    )
                    .unwrap_or_else(|_| ProgressStyle::default_bar())
                    .progress_chars("=> "),
                );
                b.set_prefix(name);
                bar = Some(b);
            }
            Progress::Advance { done } => {
                if let Some(b) = &bar {
                    b.set_position(done);
                    if b.length() == Some(done) {
                        b.finish_and_clear();
                    }
                }
            }
        }
    }
}

fn sparkline(hist: &[u64], width: usize) -> String {
    let ticks = [' ', '▁', '▂', '▃', '▄', '▅', '▆', '▇', '█'];
    let per = hist.len().div_ceil(width);
    let sums: Vec<u64> = hist.chunks(per).map(|c| c.iter().sum()).collect();
    // Log scale: CT histograms are dominated by air.
    let max = sums
        .iter()
        .map(|&v| ((v + 1) as f64).ln())
        .fold(0.0, f64::max);
    sums.iter()
        .map(|&v| {
            if v == 0 {
                ' '
            } else {
                ticks[(1.0 + ((v + 1) as f64).ln() / max.max(1e-9) * 7.0).round() as usize]
            }
        })
        .collect()
}

fn print_stats(s: &VolumeStats) {
    println!("value range : {} .. {}", s.min, s.max);
    println!("mean ± std  : {:.4} ± {:.4}", s.mean, s.std);
    println!("p0.5 / p99.5: {:.4} / {:.4}", s.p0_5, s.p99_5);
    println!(
        "histogram   : |{}| (256 bins, log counts)",
        sparkline(&s.histogram, 64)
    );
    if s.non_finite_replaced > 0 {
        println!(
            "non-finite  : {} NaN/Inf values (treated as 0)",
            s.non_finite_replaced
        );
    }
}

fn is_store(p: &Path) -> bool {
    neuvolex_bricks::store::is_brick_store(p)
}

fn info(input: &Path, brick: usize, json: bool, raw: &RawArgs, quiet: bool) -> Result<()> {
    if is_store(input) {
        let store = BrickStore::open(input)?;
        let i = store.info();
        let occupied = store.occupied_bricks(None).len();
        let total = store.bricks().count();
        if json {
            let mut v = serde_json::to_value(i)?;
            v["bricks_total"] = total.into();
            v["bricks_occupied"] = occupied.into();
            println!("{}", serde_json::to_string_pretty(&v)?);
            return Ok(());
        }
        println!(
            "store       : {} (OME-Zarr 0.5, neuvolex v{})",
            input.display(),
            i.version
        );
        println!("source      : {} ({})", i.source, i.source_dtype);
        println!(
            "dims (xyz)  : {} x {} x {} = {} voxels",
            i.dims[0], i.dims[1], i.dims[2], i.stats.voxels
        );
        println!("dtype       : {}", i.dtype);
        println!("spacing     : {:?}", i.spacing);
        print_stats(&i.stats);
        let g = i.grid();
        println!("bricks      : {}^3, grid {} x {} x {} = {total}, occupied {occupied} ({:.1}%) above {:.4}", i.brick, g[0], g[1], g[2], 100.0 * occupied as f64 / total as f64, i.background);
        println!(
            "pyramid     : {}",
            i.levels
                .iter()
                .map(|d| format!("{}x{}x{}", d[0], d[1], d[2]))
                .collect::<Vec<_>>()
                .join(", ")
        );
        if let Some(s) = i.shard {
            println!("sharding    : {s}^3 bricks per shard");
        }
        for l in &i.labels {
            let classes = store.label_classes(l)?;
            let names: Vec<String> = classes
                .iter()
                .map(|c| format!("{}={}", c.id, c.name))
                .collect();
            let names = if names.is_empty() {
                "no class table".to_string()
            } else {
                names.join(", ")
            };
            println!("labels      : {l} ({names})");
        }
        return Ok(());
    }
    let mut src = open_volume(input, raw.spec()?.as_ref())?;
    let meta = src.meta().clone();
    let rep: ScanReport = scan_volume(src.as_mut(), brick, &mut progress_sink(quiet || json))?;
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({"path": input, "meta": meta, "scan": rep})
            )?
        );
        return Ok(());
    }
    let total: usize = rep.grid.iter().product();
    println!(
        "file        : {} ({:?})",
        input.display(),
        neuvolex_formats::detect_format(input).ok()
    );
    println!(
        "dims (xyz)  : {} x {} x {} = {} voxels",
        meta.dims[0],
        meta.dims[1],
        meta.dims[2],
        meta.voxels()
    );
    println!(
        "dtype       : {}{}",
        meta.dtype,
        meta.scaling
            .map(|(s, i)| format!(" (scaled: x{s} + {i})"))
            .unwrap_or_default()
    );
    println!("spacing     : {:?}", meta.spacing);
    println!("origin      : {:?}", meta.origin());
    print_stats(&rep.stats);
    println!(
        "bricks      : {}^3, grid {} x {} x {} = {total}, occupied {} ({:.1}%) above {:.4}",
        rep.brick,
        rep.grid[0],
        rep.grid[1],
        rep.grid[2],
        rep.occupied,
        100.0 * rep.occupied as f64 / total as f64,
        rep.background
    );
    Ok(())
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,async_nats=warn".into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    let quiet = cli.quiet;
    match cli.cmd {
        Cmd::Synth {
            scene: scene @ (Scene::Tornado | Scene::Cube),
            out,
            size,
            brick,
            force,
            ..
        } => synth_scene(scene, &out, size, brick, force, quiet)?,
        Cmd::Synth {
            scene: Scene::Phantom,
            out,
            size,
            seed,
            brick,
            force,
        } => {
            if !(1..=4096).contains(&size) {
                bail!("--size {size} must be 1..=4096");
            }
            let params = PhantomParams::with_size(size, seed);
            let name = out.to_string_lossy().to_ascii_lowercase();
            if name.ends_with(".nii") || name.ends_with(".nii.gz") {
                let orig = out.to_string_lossy();
                let suffix = if name.ends_with(".gz") {
                    ".nii.gz".len()
                } else {
                    ".nii".len()
                };
                let stem = orig[..orig.len() - suffix].to_string();
                let lab = PathBuf::from(format!("{stem}_labels.nii.gz"));
                let classes = PathBuf::from(format!("{stem}_classes.json"));
                for p in [&out, &lab] {
                    if p.exists() && !force {
                        bail!(
                            "{}: already exists (pass --force to replace it)",
                            p.display()
                        );
                    }
                }
                neuvolex_formats::nifti::write_nifti(
                    &out,
                    &mut Phantom::new(params, PhantomChannel::Image),
                    16,
                )?;
                neuvolex_formats::nifti::write_nifti(
                    &lab,
                    &mut Phantom::new(params, PhantomChannel::Labels),
                    16,
                )?;
                std::fs::write(&classes, serde_json::to_string_pretty(&phantom_classes())?)
                    .with_context(|| format!("{}: cannot write class table", classes.display()))?;
                tracing::info!(image = %out.display(), labels = %lab.display(), classes = %classes.display(), "phantom written");
            } else {
                let opts = IngestOptions {
                    brick,
                    overwrite: force,
                    ..IngestOptions::default()
                };
                let mut sink = progress_sink(quiet);
                neuvolex_ingest::phantom_store(&out, params, &opts, &mut sink)?;
                tracing::info!(store = %out.display(), dims = ?params.dims, "phantom store written with labels/ground_truth");
            }
        }
        Cmd::Ingest {
            input,
            output,
            brick,
            shard,
            zstd_level,
            non_finite,
            labels,
            labels_name,
            classes,
            force,
            raw,
            cluster,
        } => {
            let classes: Vec<ClassInfo> = match &classes {
                Some(p) => read_classes(p)?,
                None => Vec::new(),
            };
            let mut src = open_volume(&input, raw.spec()?.as_ref())?;
            // Open the labels first so a bad label file fails before any work is done.
            let mut lab = match &labels {
                Some(l) => {
                    let s = open_volume(l, None)?;
                    src.meta().check_same_grid(s.meta(), l)?;
                    Some(s)
                }
                None => None,
            };
            let opts = IngestOptions {
                brick,
                shard,
                zstd_level,
                non_finite: match non_finite {
                    NonFinite::Reject => NonFinitePolicy::Reject,
                    NonFinite::Zero => NonFinitePolicy::Zero,
                },
                overwrite: force,
                levels: None,
            };
            let t = std::time::Instant::now();
            let mut sink = progress_sink(quiet);
            let labels = lab.as_mut().map(|l| neuvolex_ingest::IngestLabels {
                name: &labels_name,
                source: l.as_mut(),
                classes: &classes,
            });
            let info = if cluster.cluster.is_some() {
                let exec = cluster.executor()?;
                let mut bar = cluster::StageBar::new(quiet);
                let (info, _) = neuvolex_ingest::ingest_on(
                    &exec,
                    &input,
                    raw.spec()?.as_ref(),
                    labels,
                    &neuvolex_bricks::StoreLocation::from(&output),
                    &opts,
                    cluster.bricks_per_task,
                    &mut |e| bar.on(e),
                )?;
                bar.finish();
                info
            } else {
                neuvolex_ingest::ingest_with_labels(
                    src.as_mut(),
                    labels,
                    &output,
                    &opts,
                    &mut sink,
                )?
            };
            let mb = info.stats.voxels as f64 * info.source_dtype.size() as f64 / 1e6;
            tracing::info!(store = %output.display(), dims = ?info.dims, bricks = info.grid().iter().product::<usize>(), seconds = t.elapsed().as_secs_f64(), mb_per_s = mb / t.elapsed().as_secs_f64(), "ingest complete");
        }
        Cmd::Train {
            store,
            args,
            replicas,
            sync_steps,
            cluster,
        } => {
            if replicas == 1 && cluster.cluster.is_none() {
                run_train(&store, &args, quiet)?
            } else {
                run_train_distributed(&store, &args, replicas, sync_steps, &cluster, quiet)?
            }
        }
        Cmd::Classify(a) => classify::run_classify(&a, quiet)?,
        Cmd::Eval(a) => eval::run_eval(&a, quiet)?,
        Cmd::Render(a) => render::run_render(&a, quiet)?,
        Cmd::Viewpoints(a) => viewpoints::run_viewpoints(&a, quiet)?,
        Cmd::Serve(a) => serve::run_serve(&a)?,
        Cmd::Worker(a) => cluster::run_worker(&a, quiet)?,
        Cmd::ScribbleSim {
            labels,
            level,
            seed,
            background,
            out,
            force,
        } => {
            use neuvolex_classify::{simulate, ScribbleSource, SimConfig};
            let level = level.parse().map_err(anyhow::Error::msg)?;
            if background == 0 {
                bail!("--background 0 would mean unlabelled; use 1..=65535");
            }
            let json = out.with_extension("").with_extension("strokes.json");
            for p in [&out, &json] {
                if p.exists() && !force {
                    bail!(
                        "{}: already exists (pass --force to replace it)",
                        p.display()
                    );
                }
            }
            let mut src = open_volume(&labels, None)?;
            let meta = src.meta().clone();
            let cfg = SimConfig {
                level,
                seed,
                background,
                ..SimConfig::default()
            };
            let (strokes, s) = simulate(src.as_mut(), &cfg)
                .with_context(|| format!("{}: cannot simulate scribbles", labels.display()))?;
            neuvolex_formats::nifti::write_nifti(
                &out,
                &mut ScribbleSource::new(s.clone(), &meta),
                16,
            )?;
            std::fs::write(&json, serde_json::to_string_pretty(&strokes)?)
                .with_context(|| format!("{}: cannot write strokes", json.display()))?;
            let counts: Vec<String> = s
                .counts()
                .iter()
                .map(|(c, n)| format!("{c}: {n}"))
                .collect();
            println!(
                "scribbles: {} ({} strokes in {}): {} voxels = {:.4}% of the volume [{}]",
                out.display(),
                strokes.len(),
                json.display(),
                s.voxels.len(),
                100.0 * s.fraction(),
                counts.join(", ")
            );
        }
        Cmd::Features {
            store,
            kind,
            all_bricks,
            backend,
            cluster,
        } => {
            let kind: neuvolex_features::FeatureKind = kind.parse().map_err(anyhow::Error::msg)?;
            // The engine first: a bad --backend is named before anything is read.
            let engine = backend::Engine::pick(&backend)?;
            let s = BrickStore::open(&store)?;
            let mp = neuvolex_features::train::model_path(&s);
            if !mp.exists() {
                bail!(
                    "{}: no trained model; run `neuvolex train {}` first",
                    mp.display(),
                    store.display()
                );
            }
            let model = std::sync::Arc::new(neuvolex_features::checkpoint::load(&mp)?.model);
            let r = if !engine.is_cpu() {
                if cluster.cluster.is_some() {
                    bail!("--backend gpu extracts in this process: drop --cluster, or use --backend cpu");
                }
                engine.features(&s, &model, kind, all_bricks, &mut progress_sink(quiet))?
            } else {
                let exec = cluster.executor()?;
                let mut bar = cluster::StageBar::new(quiet);
                let (r, _) = neuvolex_features::stage::write_features_on(
                    &exec,
                    &s,
                    &neuvolex_classify::pipeline::store_path_string(&store),
                    model,
                    kind,
                    all_bricks,
                    cluster.bricks_per_task,
                    &mut |e| bar.on(e),
                )?;
                bar.finish();
                r
            };
            println!(
                "features: {}/neuvolex/vectors/{} ({} channels, f16): {} bricks, {} voxels in {:.2} s ({:.0} k voxels/s, {})",
                store.display(), r.name, r.channels, r.bricks, r.voxels, r.seconds, r.voxels as f64 / r.seconds.max(1e-9) / 1e3, engine.describe()
            );
        }
        Cmd::Unlock { store } => {
            let backend =
                neuvolex_bricks::Backend::open(&neuvolex_bricks::StoreLocation::from(&store))?;
            match neuvolex_bricks::lock::break_lock(&backend)? {
                Some(h) => println!("{}: broke the writer lock held by {h}", store.display()),
                None => println!("{}: not locked", store.display()),
            }
        }
        Cmd::Info {
            input,
            brick,
            json,
            raw,
        } => info(&input, brick, json, &raw, quiet)?,
        Cmd::Convert {
            input,
            output,
            force,
            raw,
        } => {
            if output.exists() && !force {
                bail!(
                    "{}: already exists (pass --force to replace it)",
                    output.display()
                );
            }
            let mut src = open_volume(&input, raw.spec()?.as_ref())?;
            neuvolex_formats::nifti::write_nifti(&output, src.as_mut(), 16)?;
            tracing::info!(output = %output.display(), "written");
        }
    }
    Ok(())
}

/// Renders on the GPU (this build has no `gpu` feature).
#[cfg(not(feature = "gpu"))]
fn gpu_render(
    _src: neuvolex_render::StoreSource,
    _p: &neuvolex_render::RenderParams,
    _luts: &neuvolex_render::Luts,
    _out: &Path,
    _bar: &ProgressBar,
) -> Result<()> {
    bail!("--gpu needs a build with the gpu feature (cargo build --release --features gpu)")
}

/// Renders on the GPU and writes the PNG.
#[cfg(feature = "gpu")]
fn gpu_render(
    src: neuvolex_render::StoreSource,
    p: &neuvolex_render::RenderParams,
    luts: &neuvolex_render::Luts,
    out: &Path,
    bar: &ProgressBar,
) -> Result<()> {
    let mut r = neuvolex_render::gpu::GpuRenderer::new(src)?;
    let img = r.render(p, luts)?;
    img.save_png(out)?;
    bar.finish_and_clear();
    let (load, gpu, all) = r.last_seconds;
    println!(
        "{}: {}x{} on {} in {all:.3} s (bricks {load:.3} s, GPU {gpu:.3} s)",
        out.display(),
        p.width,
        p.height,
        r.adapter()
    );
    Ok(())
}

/// Writes the Tornado or Cube scene as a store (with the cube's labels) or NIfTI.
fn synth_scene(
    scene: Scene,
    out: &Path,
    size: usize,
    brick: usize,
    force: bool,
    quiet: bool,
) -> Result<()> {
    if !(8..=1024).contains(&size) {
        bail!("--size {size} must be 8..=1024");
    }
    let dims = [size; 3];
    let (values, labels) = match scene {
        Scene::Tornado => (neuvolex_bricks::synth::tornado(size, 0.0), None),
        Scene::Cube => {
            let (v, l) = neuvolex_bricks::synth::cube(size);
            (v, Some(l))
        }
        Scene::Phantom => unreachable!("the phantom has its own writer"),
    };
    let mut vol = neuvolex_formats::MemVolume::from_f32(dims, &values);
    let name = out.to_string_lossy().to_ascii_lowercase();
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        if out.exists() && !force {
            bail!(
                "{}: already exists (pass --force to replace it)",
                out.display()
            );
        }
        neuvolex_formats::nifti::write_nifti(out, &mut vol, 16)?;
        return Ok(());
    }
    let opts = IngestOptions {
        brick,
        overwrite: force,
        ..IngestOptions::default()
    };
    let mut sink = progress_sink(quiet);
    ingest(&mut vol, out, &opts, &mut sink)?;
    if let Some(l) = labels {
        let mut store = BrickStore::open(out)?;
        let lv: Vec<f64> = l.iter().map(|&v| v as f64).collect();
        let mut lab = neuvolex_formats::MemVolume::from_f64(dims, DType::U8, &lv);
        let classes = vec![
            ClassInfo {
                id: 1,
                name: "cube".into(),
                color: [200, 200, 200],
            },
            ClassInfo {
                id: 2,
                name: "engraving".into(),
                color: [230, 60, 40],
            },
        ];
        store.add_labels("ground_truth", &mut lab, &classes, &mut sink)?;
    }
    tracing::info!(store = %out.display(), ?dims, "scene written");
    Ok(())
}
