//! Feature extraction into the store, and the feature cache.
//!
//! Features are computed tile by tile (pure: a brick's halo in, its feature brick out) and
//! written as f16 vectors with the store's brick grid. At 512x512x452 the 64-D feature takes
//! 15 GB at f16, so [`FeatureCache`] can also recompute a brick's features on demand from the
//! model instead of reading them; both modes share one LRU of recently used feature bricks.

use crate::error::{FeatureError, Result};
use crate::model::{FeatureKind, InrModel, CHUNK};
use crate::tile::Tile;
use crate::train::training_bricks;
use neuvolex_bricks::lru::Lru;
use neuvolex_bricks::{Brick, BrickStore, Progress, VectorArray, VectorEncoding};
use rayon::prelude::*;
use std::sync::Arc;

/// Name of the store's vector array for a feature kind.
pub fn vectors_name(kind: FeatureKind) -> String {
    match kind {
        FeatureKind::Hidden => "inr_hidden",
        FeatureKind::Pos => "inr_pos",
        FeatureKind::Mod => "inr_mod",
        FeatureKind::Concat => "inr_concat",
        FeatureKind::Region => "inr_region",
    }
    .to_string()
}

/// Features of every core voxel of a tile (`voxels x channels`, voxel-major, x fastest).
pub fn extract_tile(model: &InrModel, tile: &Tile, kind: FeatureKind) -> Vec<f32> {
    let c = kind.channels(model);
    let n = tile.voxels();
    let patch = model.cfg.patch;
    let mut out = vec![0.0f32; n * c];
    out.par_chunks_mut(CHUNK * c).enumerate().for_each_init(
        || model.work(),
        |w, (ci, o)| {
            let v0 = ci * CHUNK;
            let len = o.len() / c;
            model.load_with(w, len, |i, x, p, t| tile.sample(v0 + i, patch, x, p, t));
            model.forward(w);
            model.features(w, kind, o);
        },
    );
    out
}

/// Features of one brick of the store.
pub fn extract_brick(
    model: &InrModel,
    store: &BrickStore,
    b: &Brick,
    kind: FeatureKind,
) -> Result<Vec<f32>> {
    if model.dims != store.info().dims {
        return Err(FeatureError::Config(format!(
            "the model was trained on a {:?} grid, the store is {:?}",
            model.dims,
            store.info().dims
        )));
    }
    let tile = Tile::load(store, b, model.cfg.patch)?;
    Ok(extract_tile(model, &tile, kind))
}

/// What [`write_features`] did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExtractReport {
    /// Vector array written.
    pub name: String,
    /// Channels per voxel.
    pub channels: usize,
    /// Bricks written.
    pub bricks: usize,
    /// Voxels written.
    pub voxels: u64,
    /// Seconds.
    pub seconds: f64,
}

/// The vector array `kind` features of `model` are written to, and the bricks written: the
/// training bricks, or all with `all_bricks`.
pub fn feature_output(
    store: &BrickStore,
    model: &InrModel,
    kind: FeatureKind,
    all_bricks: bool,
) -> Result<(VectorArray, Vec<Brick>)> {
    let bricks = training_bricks(store, all_bricks);
    let mut va = store.create_vectors(
        &vectors_name(kind),
        kind.channels(model),
        VectorEncoding::F16,
    )?;
    va.set_extra(serde_json::json!({"kind": kind, "bricks": if all_bricks { "all" } else { "occupied" }, "background": store.info().background, "inr": model.cfg}));
    Ok((va, bricks))
}

/// Extracts `kind` features of the training bricks (or all bricks) into the store as f16, in
/// this process (the extraction stage on the in-process executor). Bricks left out are empty
/// (below the store's background threshold).
pub fn write_features(
    store: &BrickStore,
    model: &InrModel,
    kind: FeatureKind,
    all_bricks: bool,
    progress: &mut dyn FnMut(Progress),
) -> Result<ExtractReport> {
    let (r, _) = crate::stage::write_features_on(
        &neuvolex_tasks::LocalExecutor::new(),
        store,
        &store.root().display().to_string(),
        Arc::new(model.clone()),
        kind,
        all_bricks,
        1,
        &mut |e| match e {
            neuvolex_tasks::RunEvent::Stage { total, .. } => progress(Progress::Stage {
                name: "features",
                total,
            }),
            neuvolex_tasks::RunEvent::Task { done, .. } => progress(Progress::Advance { done }),
            neuvolex_tasks::RunEvent::Message(m) => tracing::info!("{m}"),
        },
    )?;
    Ok(r)
}

/// Where feature bricks come from.
pub enum FeatureSource {
    /// Read from a vector array in the store.
    Stored(Box<VectorArray>),
    /// Recomputed from the model for each brick.
    OnDemand {
        /// The trained model.
        model: Arc<InrModel>,
        /// Which feature.
        kind: FeatureKind,
    },
}

/// An LRU of recently used feature bricks over either source.
pub struct FeatureCache<'s> {
    store: &'s BrickStore,
    source: FeatureSource,
    cache: Lru<[usize; 3], Arc<Vec<f32>>>,
}

impl<'s> FeatureCache<'s> {
    /// A cache holding at most `cap_bricks` feature bricks.
    pub fn new(store: &'s BrickStore, source: FeatureSource, cap_bricks: usize) -> Self {
        FeatureCache {
            store,
            source,
            cache: Lru::new(cap_bricks),
        }
    }

    /// Channels per voxel.
    pub fn channels(&self) -> usize {
        match &self.source {
            FeatureSource::Stored(v) => v.info().channels,
            FeatureSource::OnDemand { model, kind } => kind.channels(model),
        }
    }

    /// The features of brick `b` (`voxels x channels`).
    pub fn get(&self, b: &Brick) -> Result<Arc<Vec<f32>>> {
        self.cache.get_or_try_insert(&b.index, || {
            let v = match &self.source {
                FeatureSource::Stored(va) => va.read_brick(b)?,
                FeatureSource::OnDemand { model, kind } => {
                    extract_brick(model, self.store, b, *kind)?
                }
            };
            Ok((Arc::new(v), 1))
        })
    }

    /// (hits, misses) so far.
    pub fn stats(&self) -> (u64, u64) {
        self.cache.hit_stats()
    }
}
