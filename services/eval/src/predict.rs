//! One scored prediction: the forest trained on the scribbled voxels' features, every brick
//! predicted (empty ones skipped), the labels, each voxel's confidence and the per-slice
//! uncertainty gathered brick by brick, then optionally the component prior.
//!
//! Features come through the half-precision [`neuvolex_classify::cache::FeatureCache`] keyed by (method, model), so
//! seeds, levels and robot rounds on one volume compute them once.

use crate::{EvalEvent, Events, Result};
use neuvolex_bricks::Brick;
use neuvolex_classify::cache::SessionFeatures;
use neuvolex_classify::components::{apply_in_memory, PriorConfig};
use neuvolex_classify::shard::{
    argmax, fit, output_labels, predict_brick, training_set_with, TrainingSet,
};
use neuvolex_classify::suggest::SliceMass;
use neuvolex_classify::{BrickFeatures, ClassifyConfig, Forest, Quantise, Scribbles, F1};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// The features of one method on one store, through the cache.
pub struct Features<'s> {
    /// The feature set over the store.
    pub fx: BrickFeatures<'s>,
    cache: Option<&'s SessionFeatures>,
    key: String,
    quantise: Quantise,
}

impl<'s> Features<'s> {
    /// Features of `fx` cached in `cache` under `key` (the method and model); `None` recomputes
    /// every brick in full precision.
    pub fn new(fx: BrickFeatures<'s>, cache: Option<&'s SessionFeatures>, key: String) -> Self {
        Features {
            fx,
            cache,
            key,
            quantise: Quantise::F32,
        }
    }

    /// Rounds the features further (u8 precision experiments).
    pub fn set_quantise(&mut self, q: Quantise) {
        self.quantise = q;
    }

    /// The features of brick `b` (`voxels x channels`).
    pub fn brick(
        &self,
        b: &Brick,
    ) -> std::result::Result<Vec<f32>, neuvolex_classify::ClassifyError> {
        let mut f = match self.cache {
            Some(c) => c.get(&self.key, 0, &self.fx, b)?,
            None => self.fx.brick(b)?,
        };
        self.quantise.apply(&mut f, self.fx.channels());
        Ok(f)
    }
}

/// A forest trained on scribbles.
pub struct Trained {
    /// The training set (labels, rows, bricks holding ROI scribbles).
    pub ts: TrainingSet,
    /// The forest.
    pub forest: Forest,
    /// Seconds gathering the training rows.
    pub seconds_features: f64,
    /// Seconds fitting.
    pub seconds_fit: f64,
}

/// Gathers the scribbled voxels' features and fits a forest of `cfg.forest.trees` trees.
pub fn train(f: &Features, scr: &Scribbles, cfg: &ClassifyConfig) -> Result<Trained> {
    let t = Instant::now();
    let ts = training_set_with(&f.fx, scr, cfg.background, &|b| f.brick(b))?;
    let seconds_features = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let forest = fit(&ts, &cfg.forest)?;
    Ok(Trained {
        ts,
        forest,
        seconds_features,
        seconds_fit: t.elapsed().as_secs_f64(),
    })
}

/// A classified volume in memory.
#[derive(Debug, Clone)]
pub struct Prediction {
    /// Output label per voxel (0 = background or below tau).
    pub labels: Vec<u16>,
    /// Probability of each voxel's label (of background for label 0).
    pub confidence: Vec<f32>,
    /// Uncertainty (`1 - max p`) summed per slice.
    pub slices: SliceMass,
    /// Most probable output label per voxel, whatever its probability (0 = background).
    pub best: Vec<u16>,
    /// Class probabilities as the service keeps them (u8, `classes` per voxel in the
    /// training set's class order; skipped bricks certain background).
    pub probs: Vec<u8>,
    /// Output label of each class index (0 for the background).
    pub out_labels: Vec<u16>,
    /// Voxels the forest predicted (the rest lay in skipped empty bricks).
    pub voxels_predicted: u64,
    /// Wall-clock seconds of the prediction.
    pub seconds: f64,
}

/// Predicts every brick of the store with `forest` (trained on `ts`).
pub fn predict(
    f: &Features,
    forest: &Forest,
    ts: &TrainingSet,
    cfg: &ClassifyConfig,
    events: Events,
) -> Result<Prediction> {
    let t0 = Instant::now();
    let store = f.fx.store();
    let dims = store.info().dims;
    let out_labels = output_labels(&ts.labels, cfg.background);
    let bg = ts.labels.iter().position(|&l| l == cfg.background);
    let nc = ts.labels.len();
    let bricks: Vec<Brick> = store.bricks().collect();
    events(EvalEvent::Predicting {
        what: f.fx.set().to_string(),
        total: bricks.len() as u64,
    });
    let done = AtomicU64::new(0);
    type BrickOut = (
        Brick,
        Option<(Vec<u16>, Vec<f32>, Vec<u16>, Vec<u8>)>,
        SliceMass,
    );
    let parts: Vec<BrickOut> = bricks
        .par_iter()
        .map(|b| -> Result<BrickOut> {
            let skip = cfg.skip_empty
                && bg.is_some()
                && !store.is_occupied(b, None)
                && !ts.roi_bricks.contains(&b.index);
            let r = if skip {
                (*b, None, SliceMass::zeros(dims, nc))
            } else {
                let x = f.brick(b)?;
                let (p, lab) = predict_brick(forest, &x, &out_labels, cfg.tau)?;
                let conf: Vec<f32> = p
                    .chunks(nc)
                    .zip(&lab)
                    .map(|(r, &l)| {
                        let k = if l == 0 {
                            bg
                        } else {
                            out_labels.iter().position(|&o| o == l)
                        };
                        k.map_or(0.0, |k| r[k])
                    })
                    .collect();
                let best: Vec<u16> = p.chunks(nc).map(|r| out_labels[argmax(r).0]).collect();
                let m = SliceMass::of_brick(dims, b.origin, b.size, &p, nc);
                let u8s = p
                    .iter()
                    .map(|&v| neuvolex_classify::stable::to_u8(v))
                    .collect();
                (*b, Some((lab, conf, best, u8s)), m)
            };
            events(EvalEvent::Bricks {
                done: done.fetch_add(1, Ordering::Relaxed) + 1,
            });
            Ok(r)
        })
        .collect::<Result<_>>()?;
    let n: usize = dims.iter().product();
    let mut labels = vec![0u16; n];
    let mut confidence = vec![1.0f32; n];
    let mut best = vec![0u16; n];
    let mut slices = SliceMass::zeros(dims, nc);
    let mut probs = vec![0u8; n * nc];
    if let Some(k) = bg {
        probs.chunks_exact_mut(nc).for_each(|px| px[k] = 255);
    }
    let mut voxels_predicted = 0;
    for (b, r, m) in parts {
        slices.merge(&m);
        let Some((lab, conf, bst, u8s)) = r else {
            continue;
        };
        voxels_predicted += b.voxels() as u64;
        let mut k = 0;
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                let row = ((b.origin[2] + z) * dims[1] + b.origin[1] + y) * dims[0] + b.origin[0];
                labels[row..row + b.size[0]].copy_from_slice(&lab[k..k + b.size[0]]);
                confidence[row..row + b.size[0]].copy_from_slice(&conf[k..k + b.size[0]]);
                best[row..row + b.size[0]].copy_from_slice(&bst[k..k + b.size[0]]);
                probs[row * nc..(row + b.size[0]) * nc]
                    .copy_from_slice(&u8s[k * nc..(k + b.size[0]) * nc]);
                k += b.size[0];
            }
        }
    }
    Ok(Prediction {
        labels,
        confidence,
        slices,
        best,
        probs,
        out_labels: out_labels.clone(),
        voxels_predicted,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// The scribbles of ROI classes as prior seeds (voxel, output label).
pub fn seeds(scr: &Scribbles, background: u32) -> Vec<(u64, u16)> {
    scr.voxels
        .iter()
        .filter(|&&(_, l)| l != background)
        .map(|&(i, l)| (i, l.min(u16::MAX as u32) as u16))
        .collect()
}

/// The labels after the component prior, and the seconds it took.
pub fn with_prior(
    p: &Prediction,
    dims: [usize; 3],
    brick: usize,
    scr: &Scribbles,
    background: u32,
    cfg: &PriorConfig,
) -> (Vec<u16>, f64) {
    let t = Instant::now();
    let mut l = p.labels.clone();
    apply_in_memory(
        &mut l,
        dims,
        brick,
        Some(&p.confidence),
        Some(&p.best),
        &seeds(scr, background),
        cfg,
    );
    (l, t.elapsed().as_secs_f64())
}

/// F1 per class and its mean over the classes.
pub fn score(labels: &[u16], truth: &[u32], classes: &[u32]) -> (Vec<F1>, f64) {
    let f1 = neuvolex_classify::f1_scores(labels, truth, classes);
    let mean = f1.iter().map(|f| f.f1).sum::<f64>() / f1.len().max(1) as f64;
    (f1, mean)
}
