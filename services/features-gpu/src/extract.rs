//! Feature extraction on the GPU into the store: tiles are read on host threads, each brick's
//! features are computed, converted to f16 on the GPU (the store's encoding: half the bytes to
//! copy back and map) and copied back while the next brick uploads, and writer threads (one
//! per core, up to [`MAX_WRITERS`]) compress them into bricks in parallel (the same arrays and
//! metadata as the CPU's `write_features`, values within f16 rounding of its: each brick is its
//! own chunk, so the order they finish in does not matter).

use crate::context::GpuContext;
use crate::engine::{EngineOptions, FeatureFormat, GpuInr};
use crate::error::{GpuError, Result};
use neuvolex_bricks::{Brick, BrickStore, Progress};
use neuvolex_features::extract::{feature_output, ExtractReport};
use neuvolex_features::tile::Tile;
use neuvolex_features::{FeatureKind, InrModel};
use rayon::prelude::*;
use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

/// Bricks the loader reads at once (in parallel).
const LOAD_AHEAD: usize = 8;
/// Most writer threads: compressing f16 features on the CPU, not the GPU, bounds extraction
/// into the store, so it runs on every core up to this many.
pub const MAX_WRITERS: usize = 16;

/// Extracts `kind` features of the training bricks (or all bricks) into the store as f16 on
/// the GPU of `ctx`; the result equals the CPU's within rounding (`tests/features_gpu.rs`).
pub fn write_features_gpu(
    ctx: &Arc<GpuContext>,
    store: &BrickStore,
    model: &InrModel,
    kind: FeatureKind,
    all_bricks: bool,
    progress: &mut dyn FnMut(Progress),
) -> Result<ExtractReport> {
    let t = Instant::now();
    if model.dims != store.info().dims {
        return Err(GpuError::Config(format!(
            "the model was trained on a {:?} grid, the store is {:?}",
            model.dims,
            store.info().dims
        )));
    }
    let (mut va, bricks) = feature_output(store, model, kind, all_bricks)?;
    let c = kind.channels(model);
    let mut engine = GpuInr::new(
        ctx,
        model,
        None,
        EngineOptions::inference(store.info().brick),
    )?;
    let most = bricks.iter().map(|b| b.voxels()).max().unwrap_or(1);
    let fmt = FeatureFormat::F16;
    let staging = [
        engine.staging_in(most, kind, fmt)?,
        engine.staging_in(most, kind, fmt)?,
    ];
    progress(Progress::Stage {
        name: "features",
        total: bricks.len() as u64,
    });
    let patch = model.cfg.patch;
    let voxels: u64 = bricks.iter().map(|b| b.voxels() as u64).sum();
    let va_ref = &va;
    std::thread::scope(|scope| -> Result<()> {
        let (tile_tx, tile_rx) = mpsc::sync_channel::<Result<(Brick, Tile)>>(LOAD_AHEAD);
        let writers = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .clamp(1, MAX_WRITERS);
        let (out_tx, out_rx) = mpsc::sync_channel::<(Brick, Vec<half::f16>)>(2 * writers);
        let out_rx = Arc::new(Mutex::new(out_rx));
        let list = &bricks;
        scope.spawn(move || {
            for chunk in list.chunks(LOAD_AHEAD) {
                let tiles: Vec<Result<(Brick, Tile)>> = chunk
                    .par_iter()
                    .map(|b| Ok((*b, Tile::load(store, b, patch)?)))
                    .collect();
                for t in tiles {
                    if tile_tx.send(t).is_err() {
                        return;
                    }
                }
            }
        });
        let pool: Vec<_> = (0..writers)
            .map(|_| {
                let out_rx = out_rx.clone();
                scope.spawn(move || -> Result<()> {
                    loop {
                        // The lock is held only to take the next brick.
                        let next = out_rx.lock().unwrap_or_else(|p| p.into_inner()).recv();
                        let Ok((b, f)) = next else {
                            return Ok(());
                        };
                        va_ref.write_brick_f16(&b, &f)?;
                    }
                })
            })
            .collect();
        let mut prev: Option<(usize, Brick, wgpu::SubmissionIndex)> = None;
        let mut done = 0u64;
        let mut flush = |prev: Option<(usize, Brick, wgpu::SubmissionIndex)>| -> Result<()> {
            if let Some((i, b, sub)) = prev {
                let f = ctx.map_read_f16(&staging[i % 2], b.voxels() * c, Some(sub))?;
                out_tx
                    .send((b, f))
                    .map_err(|_| GpuError::Config("the feature writer stopped".into()))?;
                done += 1;
                progress(Progress::Advance { done });
            }
            Ok(())
        };
        for (i, item) in tile_rx.iter().enumerate() {
            let (b, tile) = item?;
            engine.upload_tile(i % 2, &tile)?;
            let sub = engine.record_tile_in(i % 2, tile.voxels(), kind, fmt, &staging[i % 2])?;
            flush(prev.take())?;
            prev = Some((i, b, sub));
        }
        flush(prev)?;
        drop(out_tx);
        for w in pool {
            w.join()
                .map_err(|_| GpuError::Config("a feature writer panicked".into()))??;
        }
        Ok(())
    })?;
    va.finish()?;
    Ok(ExtractReport {
        name: neuvolex_features::extract::vectors_name(kind),
        channels: c,
        bricks: bricks.len(),
        voxels,
        seconds: t.elapsed().as_secs_f64(),
    })
}
