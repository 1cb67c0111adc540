//! Training by tile: batches are drawn brick by brick from the store, with only the current
//! group of tiles (and the next, prefetched) in memory.
//!
//! Each epoch visits the training bricks in a seeded random order, in groups of
//! `tile_bricks`; within a group every voxel is used once, in a seeded random order. A batch is
//! split into a fixed number of lanes whose gradients are summed in lane order, so results are
//! identical for any number of threads, and a checkpoint's (epoch, group, batch) position lets
//! `--resume` continue exactly where training stopped.

use crate::adam::{Adam, TableGrad};
use crate::checkpoint::{save, Loaded, TrainState};
use crate::config::{InrConfig, TrainConfig};
use crate::error::{FeatureError, Result};
use crate::model::{InrModel, Work, CHUNK};
use crate::rng::Rng;
use crate::tile::Tile;
use neuvolex_bricks::{Brick, BrickStore, StoreLocation};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Independent gradient lanes per batch (fixed, for determinism across thread counts).
pub const LANES: usize = 16;

/// A progress event of training. The CLI prints them; the service forwards them to browsers.
#[derive(Debug, Clone, PartialEq)]
pub enum TrainEvent {
    /// Training begins (or resumes).
    Started {
        /// Bricks trained on.
        bricks: usize,
        /// Bricks in the store.
        total_bricks: usize,
        /// Voxels per epoch.
        voxels: u64,
        /// Trainable parameters.
        params: usize,
        /// Sample budget, if bounded by samples or epochs.
        budget_samples: Option<u64>,
        /// Step training resumes from (0 for a fresh start).
        from_step: u64,
    },
    /// A step finished (every `report_every` steps).
    Step {
        /// Optimiser steps so far.
        step: u64,
        /// Epochs so far (fractional).
        epoch: f64,
        /// Samples so far.
        samples: u64,
        /// Batch loss.
        loss: f64,
        /// PSNR of the intensity head on the batch, dB (normalised range 1).
        psnr: f64,
        /// Recent throughput.
        samples_per_sec: f64,
        /// Training seconds so far.
        seconds: f64,
    },
    /// A reconstructed slice (intensity head) beside the truth, both normalised.
    Preview {
        /// Step.
        step: u64,
        /// Slice index (z).
        z: usize,
        /// Preview width.
        width: usize,
        /// Preview height.
        height: usize,
        /// Reconstruction, row-major.
        recon: Vec<f32>,
        /// Normalised input, row-major.
        truth: Vec<f32>,
        /// PSNR of the preview, dB.
        psnr: f64,
    },
    /// A checkpoint was written.
    Checkpoint {
        /// Step.
        step: u64,
        /// Where the checkpoint was written.
        path: StoreLocation,
    },
    /// Training ended.
    Finished {
        /// Steps.
        steps: u64,
        /// Samples.
        samples: u64,
        /// Seconds (all sessions).
        seconds: f64,
        /// PSNR of the last reported batch.
        psnr: f64,
        /// What stopped it: "epochs", "samples", "seconds" or "cancelled".
        stopped_by: String,
    },
}

/// Where the model of a store lives (inside the store, local or on S3).
pub fn model_path(store: &BrickStore) -> StoreLocation {
    store.location().join("neuvolex/inr/model.nvx")
}

/// The resumable checkpoint of a store.
pub fn checkpoint_path(store: &BrickStore) -> StoreLocation {
    store.location().join("neuvolex/inr/checkpoint.nvx")
}

/// The bricks training uses: the occupied ones (all if none is occupied or `include_empty`).
pub fn training_bricks(store: &BrickStore, include_empty: bool) -> Vec<Brick> {
    let occ = if include_empty {
        store.bricks().collect()
    } else {
        store.occupied_bricks(None)
    };
    if occ.is_empty() {
        store.bricks().collect()
    } else {
        occ
    }
}

fn mix(a: u64, b: u64, c: u64) -> u64 {
    let mut r =
        Rng::new(a ^ b.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ c.wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    r.next_u64()
}

/// Checks a model and training configuration before anything is allocated.
pub fn check_configs(inr: &InrConfig, cfg: &TrainConfig) -> Result<()> {
    if cfg.batch == 0 || cfg.tile_bricks == 0 {
        return Err(FeatureError::Config(
            "batch and tile_bricks must be positive".into(),
        ));
    }
    if !(cfg.lr > 0.0 && cfg.lr.is_finite() && cfg.lr_table > 0.0 && cfg.lr_table.is_finite()) {
        return Err(FeatureError::Config(format!(
            "learning rates {} / {} must be positive and finite",
            cfg.lr, cfg.lr_table
        )));
    }
    if inr.patch.is_multiple_of(2) || inr.patch > 9 {
        return Err(FeatureError::Config(format!(
            "patch {} must be odd and at most 9",
            inr.patch
        )));
    }
    if inr.features_per_level != 2 {
        return Err(FeatureError::Config(
            "the CPU engine supports 2 features per level".into(),
        ));
    }
    if inr.log2_table > 24 || inr.levels == 0 || inr.levels > 32 {
        return Err(FeatureError::Config(
            "levels must be 1..=32 and log2_table at most 24".into(),
        ));
    }
    Ok(())
}

/// Where a training run starts: the model and optimiser (fresh or from a checkpoint), the
/// position, the effective settings, and the bricks and sample budget of an epoch.
pub struct Start {
    /// The model to train.
    pub model: InrModel,
    /// Its optimiser state.
    pub adam: Adam,
    /// The position training starts from.
    pub state: TrainState,
    /// Effective settings (a checkpoint's, with the caller's budget).
    pub tc: TrainConfig,
    /// The bricks an epoch visits.
    pub bricks: Vec<Brick>,
    /// Voxels per epoch.
    pub voxels: u64,
    /// Sample budget, if bounded by samples or epochs.
    pub budget_samples: Option<u64>,
}

/// Why a run stops after this step, if it does: "samples" or "epochs" when the sample budget is
/// spent (`done_samples`), "seconds" when the time budget is (`done_time`).
pub fn stop_reason(
    tc: &TrainConfig,
    state: &TrainState,
    done_samples: bool,
    done_time: bool,
) -> Option<String> {
    if done_samples {
        let by = if tc.budget.samples.is_some_and(|s| state.samples >= s) {
            "samples"
        } else {
            "epochs"
        };
        return Some(by.into());
    }
    done_time.then(|| "seconds".into())
}

impl Start {
    /// The [`TrainEvent::Started`] event of this run on `store`.
    pub fn started(&self, store: &BrickStore) -> TrainEvent {
        TrainEvent::Started {
            bricks: self.bricks.len(),
            total_bricks: store.bricks().count(),
            voxels: self.voxels,
            params: self.model.table.len() + self.model.dense.len(),
            budget_samples: self.budget_samples,
            from_step: self.state.step,
        }
    }
}

/// Validates the configuration and sets up a run: fresh, or continuing `resume` (whose
/// configuration wins over `inr`/`cfg`, except for the budget).
pub fn start(
    store: &BrickStore,
    inr: &InrConfig,
    cfg: &TrainConfig,
    resume: Option<Loaded>,
) -> Result<Start> {
    check_configs(inr, cfg)?;
    let dims = store.info().dims;
    let (model, adam, state, mut tc) = match resume {
        Some(l) => {
            if l.model.dims != dims {
                return Err(FeatureError::Config(format!(
                    "checkpoint was trained on a {:?} grid, the store is {dims:?}",
                    l.model.dims
                )));
            }
            let mut tc = l.header.train.clone().unwrap_or_else(|| cfg.clone());
            tc.budget = cfg.budget;
            let state = l.header.state.unwrap_or_default();
            let adam = l
                .adam
                .unwrap_or_else(|| Adam::new(l.model.dense.len(), l.model.table.len()));
            (l.model, adam, state, tc)
        }
        None => {
            let m = InrModel::new(inr, dims, cfg.seed);
            let a = Adam::new(m.dense.len(), m.table.len());
            (m, a, TrainState::default(), cfg.clone())
        }
    };
    // A resumed checkpoint brings its own settings: they are checked too.
    check_configs(&model.cfg, &tc)?;
    tc.batch = tc.batch.max(1);
    model.cfg.check().map_err(FeatureError::Config)?;
    let bricks = training_bricks(store, tc.include_empty);
    let voxels: u64 = bricks.iter().map(|b| b.voxels() as u64).sum();
    let budget_samples = match (tc.budget.epochs, tc.budget.samples) {
        (Some(e), Some(s)) => Some(((e * voxels as f64) as u64).min(s)),
        (Some(e), None) => Some((e * voxels as f64).ceil() as u64),
        (None, s) => s,
    };
    if budget_samples.is_none() && tc.budget.seconds.is_none() {
        return Err(FeatureError::Config(
            "no budget: give epochs, samples or seconds".into(),
        ));
    }
    Ok(Start {
        model,
        adam,
        state,
        tc,
        bricks,
        voxels,
        budget_samples,
    })
}

/// The tile groups of an epoch: the bricks in the epoch's seeded order, `tile_bricks` at a time.
pub fn epoch_groups(
    bricks: &[Brick],
    seed: u64,
    epoch: u64,
    tile_bricks: usize,
) -> Vec<Vec<Brick>> {
    let mut order = bricks.to_vec();
    Rng::new(mix(seed, epoch, 0)).shuffle(&mut order);
    order.chunks(tile_bricks).map(|c| c.to_vec()).collect()
}

/// The samples of a tile group in their seeded order: (tile, voxel) pairs, every voxel once.
/// Batches are consecutive runs of `batch` of them.
pub fn group_order(tiles: &[Tile], seed: u64, epoch: u64, group: usize) -> Vec<(u32, u32)> {
    let mut order: Vec<(u32, u32)> = tiles
        .iter()
        .enumerate()
        .flat_map(|(t, tile)| (0..tile.voxels() as u32).map(move |v| (t as u32, v)))
        .collect();
    Rng::new(mix(seed, epoch, group as u64 + 1)).shuffle(&mut order);
    order
}

/// A reconstructed slice beside its input.
#[derive(Debug, Clone, PartialEq)]
pub struct PreviewSlice {
    /// Slice index (z).
    pub z: usize,
    /// Width in preview pixels.
    pub width: usize,
    /// Height in preview pixels.
    pub height: usize,
    /// Intensity-head reconstruction, row-major, normalised.
    pub recon: Vec<f32>,
    /// Normalised input at the same pixels.
    pub truth: Vec<f32>,
}

/// The inputs of a preview: the middle z-slice, at most `max_px` wide, as model samples.
#[derive(Debug, Clone, PartialEq)]
pub struct PreviewInputs {
    /// Slice index (z).
    pub z: usize,
    /// Width in preview pixels.
    pub width: usize,
    /// Height in preview pixels.
    pub height: usize,
    /// Normalised position of every pixel, row-major.
    pub coords: Vec<[f32; 3]>,
    /// The normalised `patch^3` neighbourhood of every pixel (edge-clamped), x fastest.
    pub patches: Vec<f32>,
    /// Normalised input at the same pixels.
    pub truth: Vec<f32>,
}

/// Samples the middle z-slice of `store` (at most `max_px` wide) for a model whose patch edge
/// is `patch`.
pub fn preview_inputs(store: &BrickStore, patch: usize, max_px: usize) -> Result<PreviewInputs> {
    let d = store.info().dims;
    let z = d[2] / 2;
    let r = patch / 2;
    let z0 = z.saturating_sub(r);
    let z1 = (z + r + 1).min(d[2]);
    let raw = store.read_box(0, [0, 0, z0], [d[0], d[1], z1 - z0])?;
    let norm = store.normaliser();
    let vals: Vec<f32> = raw.iter().map(|&v| norm.apply(v)).collect();
    let stride = d[0].max(d[1]).div_ceil(max_px.max(1)).max(1);
    let (w, h) = (d[0].div_ceil(stride), d[1].div_ceil(stride));
    let at = |x: isize, y: isize, zz: isize| {
        let cx = x.clamp(0, d[0] as isize - 1) as usize;
        let cy = y.clamp(0, d[1] as isize - 1) as usize;
        let cz = zz.clamp(z0 as isize, z1 as isize - 1) as usize - z0;
        vals[(cz * d[1] + cy) * d[0] + cx]
    };
    let pix: Vec<(usize, usize)> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i * stride, j * stride)))
        .collect();
    let mut patches = Vec::with_capacity(pix.len() * patch.pow(3));
    for &(px, py) in &pix {
        for dz in 0..patch as isize {
            for dy in 0..patch as isize {
                for dx in 0..patch as isize {
                    patches.push(at(
                        px as isize + dx - r as isize,
                        py as isize + dy - r as isize,
                        z as isize + dz - r as isize,
                    ));
                }
            }
        }
    }
    let coords = pix
        .iter()
        .map(|&(px, py)| {
            [
                (px as f32 + 0.5) / d[0] as f32,
                (py as f32 + 0.5) / d[1] as f32,
                (z as f32 + 0.5) / d[2] as f32,
            ]
        })
        .collect();
    let truth: Vec<f32> = pix
        .iter()
        .map(|&(x, y)| at(x as isize, y as isize, z as isize))
        .collect();
    Ok(PreviewInputs {
        z,
        width: w,
        height: h,
        coords,
        patches,
        truth,
    })
}

/// Reconstructs the middle z-slice (at most `max_px` wide) with the intensity head.
pub fn preview(store: &BrickStore, model: &InrModel, max_px: usize) -> Result<PreviewSlice> {
    let inp = preview_inputs(store, model.cfg.patch, max_px)?;
    let p3 = model.cfg.patch.pow(3);
    let n = inp.coords.len();
    let recon: Vec<f32> = (0..n)
        .collect::<Vec<_>>()
        .par_chunks(CHUNK)
        .flat_map_iter(|chunk| {
            let mut wk = model.work();
            model.load_with(&mut wk, chunk.len(), |i, x, p, t| {
                let k = chunk[i];
                *x = inp.coords[k];
                p.copy_from_slice(&inp.patches[k * p3..(k + 1) * p3]);
                t.iter_mut().for_each(|v| *v = 0.0);
            });
            model.forward(&mut wk);
            let outs = model.layout.head.out;
            model
                .outputs(&wk)
                .chunks(outs)
                .map(|o| o[0])
                .collect::<Vec<_>>()
        })
        .collect();
    Ok(PreviewSlice {
        z: inp.z,
        width: inp.width,
        height: inp.height,
        recon,
        truth: inp.truth,
    })
}

impl PreviewSlice {
    /// The training event of this preview at `step` (with the PSNR of the slice).
    pub fn event(self, step: u64) -> TrainEvent {
        let mse = self
            .recon
            .iter()
            .zip(&self.truth)
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum::<f64>()
            / self.recon.len().max(1) as f64;
        TrainEvent::Preview {
            step,
            z: self.z,
            width: self.width,
            height: self.height,
            recon: self.recon,
            truth: self.truth,
            psnr: psnr(mse),
        }
    }
}

/// PSNR in dB of a mean squared error on the normalised range (peak 1).
pub fn psnr(mse: f64) -> f64 {
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

/// The reusable buffers of [`step`]: one gradient lane per [`LANES`], the table gradient and
/// the dense gradient.
pub struct StepBuffers {
    works: Vec<Work>,
    tg: TableGrad,
    g_dense: Vec<f32>,
}

impl StepBuffers {
    /// Buffers for `model`.
    pub fn new(model: &InrModel) -> Self {
        StepBuffers {
            works: (0..LANES).map(|_| model.work()).collect(),
            tg: TableGrad::new(model.grid.levels.len(), model.grid.t, model.grid.f),
            g_dense: vec![0.0f32; model.dense.len()],
        }
    }
}

/// What one optimiser step saw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepStats {
    /// Batch loss.
    pub loss: f64,
    /// Sum of squared errors of the intensity head over the batch.
    pub sse: f64,
}

/// One optimiser step on `batch` ((tile, voxel) pairs of `tiles`): gradients in [`LANES`]
/// fixed lanes summed in lane order (the same for any thread count), then Adam. This is the
/// step of the single-node trainer ([`train`]) and of every replica of distributed training
/// ([`crate::distributed`]). `touched`, when given, gets the hash-table entries this step's
/// gradient touched OR-ed in (one bitset per level). `step_no` names the step in errors.
#[allow(clippy::too_many_arguments)]
pub fn step(
    model: &mut InrModel,
    adam: &mut Adam,
    buf: &mut StepBuffers,
    tiles: &[Tile],
    batch: &[(u32, u32)],
    rates: crate::adam::Rates,
    step_no: u64,
    touched: Option<&mut [Vec<u64>]>,
) -> Result<StepStats> {
    let patch = model.cfg.patch;
    let len = batch.len();
    let per = len.div_ceil(LANES);
    let m = &*model;
    buf.works.par_iter_mut().enumerate().for_each(|(li, w)| {
        m.reset(w);
        let lane = &batch[(li * per).min(len)..((li + 1) * per).min(len)];
        for chunk in lane.chunks(CHUNK) {
            m.load_with(w, chunk.len(), |i, x, p, t| {
                let (ti, v) = chunk[i];
                tiles[ti as usize].sample(v as usize, patch, x, p, t);
            });
            m.forward_backward(w, len);
        }
    });
    buf.g_dense.iter_mut().for_each(|g| *g = 0.0);
    let (mut loss, mut sse) = (0.0f64, 0.0f64);
    for w in &buf.works {
        buf.g_dense
            .iter_mut()
            .zip(&w.grad)
            .for_each(|(a, b)| *a += b);
        loss += w.loss;
        sse += w.sse_int;
    }
    let lanes: Vec<&Work> = buf.works.iter().collect();
    buf.tg.scatter(&lanes);
    if !loss.is_finite() {
        return Err(FeatureError::Config(format!(
            "loss became {loss} at step {step_no}; lower the learning rate"
        )));
    }
    if let Some(t) = touched {
        buf.tg.mark_into(t);
    }
    adam.step(
        &mut model.dense,
        &buf.g_dense,
        &mut model.table,
        &mut buf.tg,
        rates,
    );
    Ok(StepStats { loss, sse })
}

/// The result of [`train`].
pub struct Trained {
    /// The trained model.
    pub model: InrModel,
    /// Final position.
    pub state: TrainState,
    /// PSNR of the last batch.
    pub psnr: f64,
}

/// Trains the INR on `store`. With `resume`, continues from a checkpoint (its configuration
/// wins over `inr`/`cfg`, except for the budget). Checkpoints go to `checkpoint` when given.
pub fn train(
    store: &BrickStore,
    inr: &InrConfig,
    cfg: &TrainConfig,
    resume: Option<Loaded>,
    checkpoint: Option<&StoreLocation>,
    cancel: &AtomicBool,
    events: &mut dyn FnMut(TrainEvent),
) -> Result<Trained> {
    let run = start(store, inr, cfg, resume)?;
    events(run.started(store));
    let Start {
        mut model,
        mut adam,
        mut state,
        tc,
        bricks,
        voxels,
        budget_samples,
    } = run;
    let mut buf = StepBuffers::new(&model);
    let start = Instant::now();
    let seconds0 = state.seconds;
    let mut last_ckpt = Instant::now();
    let (mut last_psnr, mut win_samples, mut win_start) = (0.0f64, 0u64, Instant::now());
    let tile_bricks = tc.tile_bricks;
    let seed = tc.seed;
    let groups_of = |epoch: u64| epoch_groups(&bricks, seed, epoch, tile_bricks);
    let inr_cfg = model.cfg.clone();
    let load_group = |g: &[Brick]| -> Result<Vec<Tile>> {
        g.iter()
            .map(|b| Tile::load_for(store, b, &inr_cfg).map_err(FeatureError::from))
            .collect()
    };
    let stopped_by: String = std::thread::scope(|scope| -> Result<String> {
        // Resuming a training that had already met its budget (e.g. killed after its last
        // checkpoint) trains no further step, so the model equals an uninterrupted run's.
        if budget_samples.is_some_and(|b| state.samples >= b) {
            return Ok(if tc.budget.samples.is_some_and(|s| state.samples >= s) {
                "samples"
            } else {
                "epochs"
            }
            .into());
        }
        if tc.budget.seconds.is_some_and(|s| state.seconds >= s) {
            return Ok("seconds".into());
        }
        loop {
            let groups = groups_of(state.epoch);
            let mut next: Option<std::thread::ScopedJoinHandle<'_, Result<Vec<Tile>>>> = None;
            while state.group < groups.len() {
                let tiles = match next.take() {
                    Some(h) => h
                        .join()
                        .map_err(|_| FeatureError::Config("tile loader panicked".into()))??,
                    None => load_group(&groups[state.group])?,
                };
                if state.group + 1 < groups.len() {
                    let g = groups[state.group + 1].clone();
                    next = Some(scope.spawn(move || load_group(&g)));
                }
                let order = group_order(&tiles, seed, state.epoch, state.group);
                let batches: Vec<&[(u32, u32)]> = order.chunks(tc.batch).collect();
                while state.batch < batches.len() {
                    if cancel.load(Ordering::Relaxed) {
                        return Ok("cancelled".into());
                    }
                    let batch = batches[state.batch];
                    let len = batch.len();
                    let rates = crate::adam::Rates {
                        lr: tc.lr,
                        lr_table: tc.lr_table,
                        mode: tc.table_adam,
                    };
                    let st = step(
                        &mut model, &mut adam, &mut buf, &tiles, batch, rates, state.step, None,
                    )?;
                    let (loss, sse) = (st.loss, st.sse);
                    state.step += 1;
                    state.batch += 1;
                    state.samples += len as u64;
                    state.seconds = seconds0 + start.elapsed().as_secs_f64();
                    win_samples += len as u64;
                    last_psnr = psnr(sse / len as f64);
                    let done_samples = budget_samples.is_some_and(|b| state.samples >= b);
                    let done_time = tc.budget.seconds.is_some_and(|s| state.seconds >= s);
                    if tc.report_every > 0
                        && (state.step % tc.report_every == 0 || done_samples || done_time)
                    {
                        let el = win_start.elapsed().as_secs_f64();
                        events(TrainEvent::Step {
                            step: state.step,
                            epoch: state.samples as f64 / voxels.max(1) as f64,
                            samples: state.samples,
                            loss,
                            psnr: last_psnr,
                            samples_per_sec: win_samples as f64 / el.max(1e-9),
                            seconds: state.seconds,
                        });
                        win_samples = 0;
                        win_start = Instant::now();
                    }
                    if tc.preview_every > 0 && state.step % tc.preview_every == 0 {
                        events(preview(store, &model, 128)?.event(state.step));
                    }
                    let ckpt_due = tc.checkpoint_every > 0 && state.step % tc.checkpoint_every == 0
                        || last_ckpt.elapsed().as_secs_f64() > 120.0;
                    if let (Some(p), true) = (checkpoint, ckpt_due) {
                        save(p, &model, Some((&tc, &state, &adam)))?;
                        last_ckpt = Instant::now();
                        events(TrainEvent::Checkpoint {
                            step: state.step,
                            path: p.clone(),
                        });
                    }
                    if let Some(why) = stop_reason(&tc, &state, done_samples, done_time) {
                        return Ok(why);
                    }
                }
                state.batch = 0;
                state.group += 1;
            }
            if let Some(h) = next.take() {
                let _ = h.join();
            }
            state.group = 0;
            state.epoch += 1;
        }
    })?;
    if let Some(p) = checkpoint {
        save(p, &model, Some((&tc, &state, &adam)))?;
        events(TrainEvent::Checkpoint {
            step: state.step,
            path: p.clone(),
        });
    }
    events(TrainEvent::Finished {
        steps: state.step,
        samples: state.samples,
        seconds: state.seconds,
        psnr: last_psnr,
        stopped_by: stopped_by.clone(),
    });
    if stopped_by == "cancelled" {
        return Err(FeatureError::Cancelled);
    }
    Ok(Trained {
        model,
        state,
        psnr: last_psnr,
    })
}
