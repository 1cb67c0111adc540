//! Training on the GPU by tile, with the CPU trainer's schedule: the same epochs, tile
//! groups, sample order, budgets, checkpoints and events (`neuvolex_features::train`).
//!
//! Three things run at once: a loader thread reads the next tile group from the store and
//! computes its targets and sample order (bricks in parallel); the host records and submits
//! steps without waiting for the GPU; and the GPU trains. The next group is written into the
//! other half of a two-group tile ring as soon as it is ready, so tile preparation overlaps
//! training, and GPU memory is the model plus the ring. Losses are read back a few steps
//! late (every `report_every` steps, at most 64 apart), which is when events are emitted and a
//! non-finite loss stops training.

use crate::context::{GpuContext, MemoryReport, Tracked};
use crate::engine::{EngineOptions, GpuInr, MlpPath, StepRates};
use crate::error::{GpuError, Result};
use crate::plan::STATS_RING;
use neuvolex_bricks::{Brick, BrickStore, StoreLocation};
use neuvolex_features::checkpoint::{save, Loaded};
use neuvolex_features::tile::Tile;
use neuvolex_features::train::{
    epoch_groups, group_order, preview_inputs, psnr, start, PreviewInputs, PreviewSlice, Start,
    Trained,
};
use neuvolex_features::{FeatureError, InrConfig, InrModel, TrainConfig, TrainEvent};
use rayon::prelude::*;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

/// Most steps between loss readbacks.
const READBACK_EVERY: u64 = 64;
/// Readbacks in flight before the host waits for the oldest.
const READBACKS_AHEAD: usize = 2;

/// What a GPU run measured besides the model.
#[derive(Debug, Clone, PartialEq)]
pub struct GpuReport {
    /// The adapter.
    pub adapter: String,
    /// GPU memory: the engine's buffers and, where reported, the allocator's peak.
    pub memory: MemoryReport,
    /// Samples per micro-batch.
    pub micro_batch: usize,
    /// Tile groups resident at once (2: the next group uploads while the current trains).
    pub ring_groups: usize,
    /// Bytes of tiles and sample orders written to the GPU.
    pub upload_bytes: u64,
    /// Seconds the host waited for the loader (tile preparation slower than training).
    pub loader_wait_s: f64,
    /// Seconds the host waited for the GPU at loss readbacks.
    pub readback_wait_s: f64,
}

/// The result of [`train_gpu`].
pub struct GpuTrained {
    /// The model, position and last PSNR, as the CPU trainer returns them.
    pub trained: Trained,
    /// GPU figures of the run.
    pub report: GpuReport,
}

/// A tile group ready for the GPU.
struct Prepared {
    epoch: u64,
    group: usize,
    tiles: Vec<Tile>,
    /// (slot, voxel) pairs in training order.
    pairs: Vec<u32>,
}

/// A submitted step whose loss is not read yet.
struct Pending {
    step: u64,
    samples: u64,
    len: usize,
    seconds: f64,
}

struct Readback {
    upto: u64,
    buf: Tracked,
    rx: mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

/// The host side of the loss readbacks.
struct Stats {
    pending: VecDeque<Pending>,
    readbacks: VecDeque<Readback>,
    scheduled: u64,
    voxels: u64,
    last_psnr: f64,
    win: (u64, Instant),
    wait_s: f64,
}

impl Stats {
    fn schedule(&mut self, engine: &GpuInr, step: u64) -> Result<()> {
        if step <= self.scheduled {
            return Ok(());
        }
        let buf = engine.stats_readback()?;
        let (tx, rx) = mpsc::channel();
        buf.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.readbacks.push_back(Readback {
            upto: step,
            buf,
            rx,
        });
        self.scheduled = step;
        Ok(())
    }

    /// Handles finished readbacks (all of them when `wait`), emitting step events.
    fn drain(
        &mut self,
        ctx: &GpuContext,
        wait: bool,
        report_every: u64,
        final_step: Option<u64>,
        events: &mut dyn FnMut(TrainEvent),
    ) -> Result<()> {
        let _ = ctx.gpu.device.poll(wgpu::PollType::Poll);
        while let Some(rb) = self.readbacks.front() {
            let ready = match rb.rx.try_recv() {
                Ok(r) => Some(r),
                Err(mpsc::TryRecvError::Empty) if wait => {
                    let t = Instant::now();
                    ctx.wait()?;
                    self.wait_s += t.elapsed().as_secs_f64();
                    Some(
                        rb.rx
                            .recv()
                            .map_err(|e| neuvolex_gpu::GpuError::Device(e.to_string()))?,
                    )
                }
                Err(mpsc::TryRecvError::Empty) => None,
                Err(e) => return Err(neuvolex_gpu::GpuError::Device(e.to_string()).into()),
            };
            let Some(r) = ready else { break };
            r.map_err(|e| neuvolex_gpu::GpuError::Device(e.to_string()))?;
            ctx.check()?;
            let Some(rb) = self.readbacks.pop_front() else {
                break;
            };
            let stats: Vec<f32> = {
                let view = rb
                    .buf
                    .slice(..)
                    .get_mapped_range()
                    .map_err(|e| neuvolex_gpu::GpuError::Device(e.to_string()))?;
                bytemuck::pod_collect_to_vec(&view)
            };
            rb.buf.unmap();
            while self.pending.front().is_some_and(|p| p.step <= rb.upto) {
                let Some(p) = self.pending.pop_front() else {
                    break;
                };
                let slot = (p.step as usize) % STATS_RING;
                let (loss, sse) = (stats[2 * slot] as f64, stats[2 * slot + 1] as f64);
                if !loss.is_finite() {
                    return Err(FeatureError::Config(format!(
                        "loss became {loss} at step {}; lower the learning rate",
                        p.step - 1
                    ))
                    .into());
                }
                self.last_psnr = psnr(sse / p.len as f64);
                let due = report_every > 0 && p.step % report_every == 0;
                if due || final_step == Some(p.step) {
                    let el = self.win.1.elapsed().as_secs_f64();
                    events(TrainEvent::Step {
                        step: p.step,
                        epoch: p.samples as f64 / self.voxels.max(1) as f64,
                        samples: p.samples,
                        loss,
                        psnr: self.last_psnr,
                        samples_per_sec: (p.samples - self.win.0) as f64 / el.max(1e-9),
                        seconds: p.seconds,
                    });
                    self.win = (p.samples, Instant::now());
                }
            }
        }
        Ok(())
    }
}

/// The loader: tile groups of every epoch from `(epoch, group)` on, in the CPU trainer's
/// order, bricks loaded in parallel; group `k` goes to ring half `k % halves`.
#[allow(clippy::too_many_arguments)]
fn load_groups(
    store: &BrickStore,
    bricks: &[Brick],
    tc: &TrainConfig,
    patch: usize,
    halves: usize,
    (mut epoch, mut group): (u64, usize),
    tx: mpsc::SyncSender<Result<Prepared>>,
) {
    let tb = tc.tile_bricks;
    let mut k = 0usize;
    loop {
        let groups = epoch_groups(bricks, tc.seed, epoch, tb);
        while group < groups.len() {
            let tiles: Result<Vec<Tile>> = groups[group]
                .par_iter()
                .map(|b| Tile::load(store, b, patch).map_err(GpuError::from))
                .collect();
            let prepared = tiles.map(|tiles| {
                let base = ((k % halves) * tb) as u32;
                let pairs = group_order(&tiles, tc.seed, epoch, group)
                    .into_iter()
                    .flat_map(|(t, v)| [base + t, v])
                    .collect();
                Prepared {
                    epoch,
                    group,
                    tiles,
                    pairs,
                }
            });
            let failed = prepared.is_err();
            if tx.send(prepared).is_err() || failed {
                return;
            }
            k += 1;
            group += 1;
        }
        group = 0;
        epoch += 1;
    }
}

/// A checkpoint being written on another thread.
type Saving = std::thread::JoinHandle<(u64, StoreLocation, neuvolex_features::Result<()>)>;

fn finish_save(h: Saving, events: &mut dyn FnMut(TrainEvent)) -> Result<()> {
    let (step, path, r) = h
        .join()
        .map_err(|_| GpuError::Config("the checkpoint writer panicked".into()))?;
    r?;
    events(TrainEvent::Checkpoint { step, path });
    Ok(())
}

/// How a GPU run launches its work (the model and its training are the same either way).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct GpuTune {
    /// Layered or fused dense layers.
    pub mlp: MlpPath,
    /// Samples per micro-batch; `None`: 16384, halved until the activations fit the binding
    /// limit.
    pub micro_batch: Option<usize>,
    /// The loss-scale exponent; `None`: the path's own ([`GpuInr::loss_scale_exp`]).
    pub loss_scale_exp: Option<u32>,
}

/// Trains the INR on `store` on the GPU of `ctx`: [`neuvolex_features::train`]'s contract
/// (configuration, resume, checkpoints, events, cancellation) with the GPU engine.
#[allow(clippy::too_many_arguments)]
pub fn train_gpu(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    inr: &InrConfig,
    cfg: &TrainConfig,
    resume: Option<Loaded>,
    checkpoint: Option<&StoreLocation>,
    cancel: &AtomicBool,
    events: &mut dyn FnMut(TrainEvent),
) -> Result<GpuTrained> {
    train_gpu_tuned(
        ctx,
        store,
        inr,
        cfg,
        resume,
        checkpoint,
        cancel,
        events,
        GpuTune::default(),
    )
}

/// [`train_gpu`] with the launch chosen by `tune` (for benchmarks and equivalence tests).
#[allow(clippy::too_many_arguments)]
pub fn train_gpu_tuned(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    inr: &InrConfig,
    cfg: &TrainConfig,
    resume: Option<Loaded>,
    checkpoint: Option<&StoreLocation>,
    cancel: &AtomicBool,
    events: &mut dyn FnMut(TrainEvent),
    tune: GpuTune,
) -> Result<GpuTrained> {
    if resume.is_none() {
        // Refuse a model the device cannot hold before building it on the host.
        neuvolex_features::train::check_configs(inr, cfg)?;
        if !inr.context_sigmas.is_empty() {
            return Err(GpuError::Config(
                "the GPU engine has the paper's six heads only, not context heads: use --backend cpu".into(),
            ));
        }
        let grid = neuvolex_features::hashgrid::HashGrid::new(
            inr,
            *store.info().dims.iter().max().unwrap_or(&1),
        );
        let bytes = grid.table_len() as u64 * 4;
        if bytes > ctx.max_binding() {
            return Err(GpuError::Config(format!(
                "the hash table ({} MiB: {} levels of 2^{} entries) exceeds the adapter's storage binding limit of {} MiB; lower levels or log2_table",
                bytes >> 20,
                inr.levels,
                inr.log2_table,
                ctx.max_binding() >> 20
            )));
        }
    }
    let run = start(store, inr, cfg, resume)?;
    events(run.started(store));
    let Start {
        model,
        adam,
        mut state,
        tc,
        bricks,
        voxels,
        budget_samples,
    } = run;
    ctx.reset_peak();
    let brick = store.info().brick;
    let tb = tc.tile_bricks;
    let group_voxels = tb * brick.pow(3);
    // Two ring halves where they fit the binding limit, else one (uploads then wait for the
    // group boundary).
    let halo = neuvolex_bricks::derived::DERIVED_HALO.max(model.cfg.patch / 2);
    let slot_bytes =
        4 * ((brick + 2 * halo).pow(3) + brick.pow(3) * neuvolex_features::model::TARGETS) as u64;
    let halves = if 2 * tb as u64 * slot_bytes + 4096 <= ctx.max_binding() {
        2
    } else {
        1
    };
    let mut engine = GpuInr::new(
        ctx,
        &model,
        Some(&adam),
        EngineOptions {
            batch: tc.batch,
            micro_batch: tune.micro_batch,
            train: true,
            slots: halves * tb,
            brick,
            order_pairs: halves * group_voxels,
            mlp: tune.mlp,
        },
    )?;
    engine.set_loss_scale_exp(tune.loss_scale_exp)?;
    drop(adam);
    let patch = model.cfg.patch;
    drop(model);
    let rates = StepRates {
        lr: tc.lr,
        lr_table: tc.lr_table,
        mode: tc.table_adam,
    };
    let start_t = Instant::now();
    let seconds0 = state.seconds;
    let mut stats = Stats {
        pending: VecDeque::new(),
        readbacks: VecDeque::new(),
        scheduled: state.step,
        voxels,
        last_psnr: 0.0,
        win: (state.samples, Instant::now()),
        wait_s: 0.0,
    };
    let mut upload_bytes = 0u64;
    let mut loader_wait = 0.0f64;
    let mut preview_in: Option<PreviewInputs> = None;
    let mut saving: Option<Saving> = None;
    let mut last_ckpt = Instant::now();
    let report_every = tc.report_every;
    let (tx, rx) = mpsc::sync_channel::<Result<Prepared>>(1);
    let from = (state.epoch, state.group);
    let upload = |engine: &GpuInr, p: &Prepared, k: usize, bytes: &mut u64| -> Result<()> {
        let half = k % halves;
        for (t, tile) in p.tiles.iter().enumerate() {
            engine.upload_tile(half * tb + t, tile)?;
            *bytes += 4 * (tile.norm.len() + tile.targets.len() * 6) as u64;
        }
        engine.upload_order(half * group_voxels, &p.pairs)?;
        *bytes += 4 * p.pairs.len() as u64;
        Ok(())
    };
    let stopped_by: Result<String> = std::thread::scope(|scope| {
        // Owned by this closure, so it closes when training stops and the loader ends.
        let rx = rx;
        let tcl = tc.clone();
        let bricks_l = bricks.clone();
        scope.spawn(move || load_groups(store, &bricks_l, &tcl, patch, halves, from, tx));
        let recv = |wait: &mut f64| -> Result<Prepared> {
            let t = Instant::now();
            let p = rx
                .recv()
                .map_err(|_| GpuError::Config("the tile loader stopped".into()))?;
            *wait += t.elapsed().as_secs_f64();
            p
        };
        let mut k = 0usize;
        let mut cur = recv(&mut loader_wait)?;
        upload(&engine, &cur, k, &mut upload_bytes)?;
        let mut next: Option<Prepared> = None;
        loop {
            state.epoch = cur.epoch;
            state.group = cur.group;
            let len = cur.pairs.len() / 2;
            let batches = len.div_ceil(tc.batch);
            let half = k % halves;
            while state.batch < batches {
                if cancel.load(Ordering::Relaxed) {
                    return Ok("cancelled".to_string());
                }
                if halves == 2 && next.is_none() {
                    if let Ok(p) = rx.try_recv() {
                        let p = p?;
                        upload(&engine, &p, k + 1, &mut upload_bytes)?;
                        next = Some(p);
                    }
                }
                let b0 = state.batch * tc.batch;
                let n = tc.batch.min(len - b0);
                engine.step(half * group_voxels + b0, n, rates, state.step as usize + 1)?;
                state.step += 1;
                state.batch += 1;
                state.samples += n as u64;
                state.seconds = seconds0 + start_t.elapsed().as_secs_f64();
                stats.pending.push_back(Pending {
                    step: state.step,
                    samples: state.samples,
                    len: n,
                    seconds: state.seconds,
                });
                let done_samples = budget_samples.is_some_and(|b| state.samples >= b);
                let done_time = tc.budget.seconds.is_some_and(|s| state.seconds >= s);
                let done = done_samples || done_time;
                let preview_due = tc.preview_every > 0 && state.step % tc.preview_every == 0;
                let ckpt_due = tc.checkpoint_every > 0 && state.step % tc.checkpoint_every == 0
                    || last_ckpt.elapsed().as_secs_f64() > 120.0;
                let sync = done || preview_due || (checkpoint.is_some() && ckpt_due);
                if sync
                    || (report_every > 0 && state.step % report_every == 0)
                    || state.step >= stats.scheduled + READBACK_EVERY
                {
                    stats.schedule(&engine, state.step)?;
                }
                let wait = sync || stats.readbacks.len() > READBACKS_AHEAD;
                let fin = done.then_some(state.step);
                stats.drain(ctx, wait, report_every, fin, events)?;
                if preview_due {
                    if preview_in.is_none() {
                        preview_in = Some(preview_inputs(store, patch, 128)?);
                    }
                    if let Some(pi) = &preview_in {
                        let outs = engine.layout.head.out;
                        let y = engine.outputs(&pi.coords, &pi.patches)?;
                        let slice = PreviewSlice {
                            z: pi.z,
                            width: pi.width,
                            height: pi.height,
                            recon: y.chunks(outs).map(|o| o[0]).collect(),
                            truth: pi.truth.clone(),
                        };
                        events(slice.event(state.step));
                    }
                }
                if let Some(h) = saving.take_if(|h| h.is_finished()) {
                    finish_save(h, events)?;
                }
                if let (Some(p), true) = (checkpoint, ckpt_due) {
                    let m = engine.download_model()?;
                    let a = engine.download_adam()?;
                    if let Some(h) = saving.take() {
                        finish_save(h, events)?;
                    }
                    let (p, tcc, st) = (p.clone(), tc.clone(), state);
                    saving = Some(std::thread::spawn(move || {
                        let r = save(p.clone(), &m, Some((&tcc, &st, &a)));
                        (st.step, p, r)
                    }));
                    last_ckpt = Instant::now();
                }
                if let Some(why) =
                    neuvolex_features::train::stop_reason(&tc, &state, done_samples, done_time)
                {
                    return Ok(why);
                }
            }
            state.batch = 0;
            k += 1;
            cur = match next.take() {
                Some(p) => p,
                None => {
                    let p = recv(&mut loader_wait)?;
                    upload(&engine, &p, k, &mut upload_bytes)?;
                    p
                }
            };
        }
    });
    let stopped_by = stopped_by?;
    stats.schedule(&engine, state.step)?;
    stats.drain(ctx, true, report_every, Some(state.step), events)?;
    if let Some(h) = saving.take() {
        finish_save(h, events)?;
    }
    let model: InrModel = engine.download_model()?;
    if let Some(p) = checkpoint {
        let a = engine.download_adam()?;
        save(p.clone(), &model, Some((&tc, &state, &a)))?;
        events(TrainEvent::Checkpoint {
            step: state.step,
            path: p.clone(),
        });
    }
    let seconds = seconds0 + start_t.elapsed().as_secs_f64();
    state.seconds = seconds;
    events(TrainEvent::Finished {
        steps: state.step,
        samples: state.samples,
        seconds,
        psnr: stats.last_psnr,
        stopped_by: stopped_by.clone(),
    });
    let report = GpuReport {
        adapter: ctx.describe(),
        memory: ctx.memory(),
        micro_batch: engine.micro_batch(),
        ring_groups: halves,
        upload_bytes,
        loader_wait_s: loader_wait,
        readback_wait_s: stats.wait_s,
    };
    if stopped_by == "cancelled" {
        return Err(FeatureError::Cancelled.into());
    }
    Ok(GpuTrained {
        trained: Trained {
            model,
            state,
            psnr: stats.last_psnr,
        },
        report,
    })
}
