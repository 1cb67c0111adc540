//! The one-shot protocol: scribbles simulated at fixed levels, one prediction each.

use crate::data::{train_inr, Dataset, DatasetSpec, TrainedInr};
use crate::predict::{predict, score, train, with_prior, Features};
use crate::{EvalConfig, EvalError, EvalEvent, Events, Method, Prior, Result};
use neuvolex_classify::cache::FeatureCache;
use neuvolex_classify::{
    rasterise, simulate, thicken, BrickFeatures, FeatureSet, Level, Quantise, Scribbles, SimConfig,
    F1,
};
use serde::{Deserialize, Serialize};

/// Settings of the one-shot protocol.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OneShotConfig {
    /// Scribble levels.
    pub levels: Vec<Level>,
    /// Forest sizes to score (sub-forests of one fit of the largest).
    pub tree_counts: Vec<usize>,
    /// Feature precision: f32 (recomputed), f16 (the cache, the default), u8.
    pub quantise: Vec<String>,
}

/// One scored run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Row {
    /// Dataset.
    pub dataset: String,
    /// Method (features and prior).
    pub method: String,
    /// Scribble level.
    pub level: String,
    /// Scribble seed.
    pub seed: u64,
    /// INR variant (`-` without one).
    pub inr: String,
    /// INR epochs (0 without one).
    pub epochs: f64,
    /// Trees.
    pub trees: usize,
    /// Feature precision.
    pub quantise: String,
    /// Fraction of the voxels scribbled.
    pub scribbled_fraction: f64,
    /// F1 per ROI class.
    pub f1: Vec<F1>,
    /// Mean F1 over the ROI classes.
    pub mean_f1: f64,
    /// Seconds gathering the training rows.
    pub seconds_features: f64,
    /// Seconds fitting (the share of this forest size).
    pub seconds_fit: f64,
    /// Seconds predicting the volume.
    pub seconds_classify: f64,
    /// Seconds of the prior.
    pub seconds_prior: f64,
    /// Voxels predicted.
    pub voxels_predicted: u64,
}

/// One INR trained for the evaluation.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelRow {
    /// Dataset.
    pub dataset: String,
    /// Variant.
    pub inr: String,
    /// Epochs.
    pub epochs: f64,
    /// Reconstruction PSNR.
    pub psnr: f64,
    /// Training seconds.
    pub seconds: f64,
    /// Dead hidden units.
    pub dead_units: usize,
}

/// The name of a level (`S1`..`S4`).
pub fn level_name(l: Level) -> String {
    format!("S{}", l as usize + 1)
}

/// Feature sets of the methods, each with the priors asked for it, in first-seen order.
pub fn feature_sets(methods: &[Method]) -> Vec<(String, Vec<Prior>)> {
    let mut out: Vec<(String, Vec<Prior>)> = Vec::new();
    for m in methods {
        match out.iter_mut().find(|(f, _)| *f == m.features) {
            Some((_, p)) => {
                if !p.contains(&m.prior) {
                    p.push(m.prior)
                }
            }
            None => out.push((m.features.clone(), vec![m.prior])),
        }
    }
    out
}

/// Trains the INR variants when a method needs one.
pub fn models_for(cfg: &EvalConfig, ds: &Dataset, events: Events) -> Result<Vec<TrainedInr>> {
    let needs = cfg.methods.iter().any(|m| {
        m.features
            .parse::<FeatureSet>()
            .is_ok_and(|s| s.needs_model())
    });
    if !needs {
        return Ok(Vec::new());
    }
    cfg.inr
        .iter()
        .map(|v| {
            let t = train_inr(ds, v, events)?;
            events(EvalEvent::Model(ModelRow {
                dataset: ds.spec.name.clone(),
                inr: v.name(),
                epochs: v.epochs,
                psnr: t.psnr,
                seconds: t.seconds,
                dead_units: t.dead_units,
            }));
            Ok(t)
        })
        .collect()
}

/// Checks settings shared by both protocols.
pub fn check(cfg: &EvalConfig) -> Result<()> {
    if cfg.seeds == 0 {
        return Err(EvalError::Config("--seeds 0: need at least one".into()));
    }
    if cfg.methods.is_empty() {
        return Err(EvalError::Config("no method".into()));
    }
    for v in &cfg.inr {
        if !(v.epochs > 0.0 && v.epochs.is_finite()) {
            return Err(EvalError::Config(format!(
                "--epochs {} must be positive",
                v.epochs
            )));
        }
    }
    Ok(())
}

/// Runs the one-shot protocol; rows are also sent as events.
pub fn run(cfg: &EvalConfig, os: &OneShotConfig, events: Events) -> Result<Vec<Row>> {
    check(cfg)?;
    let mut trees = os.tree_counts.clone();
    if trees.is_empty() {
        trees.push(cfg.classify.forest.trees);
    }
    trees.sort_unstable();
    trees.dedup();
    if trees[0] == 0 {
        return Err(EvalError::Config("--tree-counts: 0 trees".into()));
    }
    for q in &os.quantise {
        if !matches!(q.as_str(), "f32" | "f16" | "u8") {
            return Err(EvalError::Config(format!(
                "--quantise '{q}' must be f32, f16 or u8"
            )));
        }
    }
    let max_trees = *trees.last().unwrap_or(&1);
    let mut rows = Vec::new();
    for spec in &cfg.datasets {
        let ds = Dataset::prepare(DatasetSpec::parse(spec, &cfg.data)?, &cfg.work)?;
        events(ds.event());
        let models = models_for(cfg, &ds, events)?;
        let mut scribbles: Vec<(Level, u64, Scribbles)> = Vec::new();
        for &level in &os.levels {
            for seed in 0..cfg.seeds {
                let mut src = ds.truth_source()?;
                let (strokes, s) = simulate(
                    &mut *src,
                    &SimConfig {
                        level,
                        seed,
                        background: cfg.classify.background,
                        ..SimConfig::default()
                    },
                )?;
                let s = if cfg.thicken > 0 {
                    let dims = ds.store.info().dims;
                    rasterise(&thicken(&strokes, cfg.thicken, dims), dims)?
                } else {
                    s
                };
                scribbles.push((level, seed, s));
            }
        }
        let cache = std::sync::Arc::new(FeatureCache::new(cfg.cache_bytes)).for_session("eval");
        let dims = ds.store.info().dims;
        let brick = ds.store.info().brick;
        for (fname, priors) in feature_sets(&cfg.methods) {
            let set: FeatureSet = fname.parse().map_err(EvalError::Config)?;
            let variants: Vec<Option<&TrainedInr>> = if set.needs_model() {
                models.iter().map(Some).collect()
            } else {
                vec![None]
            };
            for model in variants {
                for q in &os.quantise {
                    let fx = BrickFeatures::new(
                        &ds.store,
                        set.clone(),
                        model.map(|m| m.model.clone()),
                        false,
                    )?;
                    let (inr, epochs) =
                        model.map_or(("-".into(), 0.0), |m| (m.variant.name(), m.variant.epochs));
                    let key = format!("{fname}/{inr}/{epochs}");
                    let mut f = Features::new(fx, (q != "f32").then_some(&cache), key);
                    for (level, seed, scr) in &scribbles {
                        let mut c = cfg.classify.clone();
                        c.forest.trees = max_trees;
                        if q == "u8" {
                            // Per-channel range of the training rows, as stored u8 features.
                            f.set_quantise(Quantise::F32);
                            let t = train(&f, scr, &c)?;
                            f.set_quantise(Quantise::u8_from_rows(&t.ts.x, t.ts.d));
                        }
                        let t = train(&f, scr, &c)?;
                        for &k in &trees {
                            let forest = t.forest.truncated(k);
                            let p = predict(&f, &forest, &t.ts, &c, events)?;
                            for &prior in &priors {
                                let (labels, sp) = match prior {
                                    Prior::None => (None, 0.0),
                                    Prior::Components => {
                                        let (l, s) = with_prior(
                                            &p,
                                            dims,
                                            brick,
                                            scr,
                                            c.background,
                                            &cfg.prior,
                                        );
                                        (Some(l), s)
                                    }
                                };
                                let (f1, mean_f1) = score(
                                    labels.as_deref().unwrap_or(&p.labels),
                                    &ds.truth,
                                    &ds.classes,
                                );
                                let row = Row {
                                    dataset: ds.spec.name.clone(),
                                    method: Method {
                                        features: fname.clone(),
                                        prior,
                                    }
                                    .to_string(),
                                    level: level_name(*level),
                                    seed: *seed,
                                    inr: inr.clone(),
                                    epochs,
                                    trees: k,
                                    quantise: q.clone(),
                                    scribbled_fraction: scr.fraction(),
                                    f1,
                                    mean_f1,
                                    seconds_features: t.seconds_features,
                                    seconds_fit: t.seconds_fit * k as f64 / max_trees as f64,
                                    seconds_classify: p.seconds,
                                    seconds_prior: sp,
                                    voxels_predicted: p.voxels_predicted,
                                };
                                events(EvalEvent::Row(row.clone()));
                                rows.push(row);
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(rows)
}
