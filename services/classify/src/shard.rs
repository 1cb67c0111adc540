//! Sharded classification: the training set gathered brick by brick from scribbles, prediction
//! brick by brick (empty bricks skipped), per-class u8 probabilities written into the store, and
//! the argmax label volume thresholded at `tau`.
//!
//! [`training_set`] and [`predict_brick`] are pure per-brick computations; [`classify_volume`]
//! only schedules them (here with rayon; the actor runtime schedules the same functions).

use crate::features::BrickFeatures;
use crate::forest::{ClassWeight, Dataset, Forest, ForestConfig};
use crate::scribble::Scribbles;
use crate::ClassifyError;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{Brick, BrickStore, VectorArray};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// A class table: ROI classes with names and colours, and the label meaning background.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassTable {
    /// ROI classes.
    pub classes: Vec<ClassInfo>,
    /// The scribble label that means background/other.
    #[serde(default = "default_background")]
    pub background: u32,
}

fn default_background() -> u32 {
    255
}

#[derive(Deserialize)]
#[serde(untagged)]
enum TableFile {
    Full(ClassTable),
    List(Vec<ClassInfo>),
}

impl ClassTable {
    /// Reads `{"classes": [{"id", "name", "color"}...], "background": 255}` or a bare class list.
    pub fn load(path: &Path) -> Result<Self, ClassifyError> {
        let text = std::fs::read_to_string(path).map_err(|e| ClassifyError::File {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })?;
        Self::parse(&text, path)
    }

    /// Parses a class table from JSON text; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self, ClassifyError> {
        let bad = |d: String| ClassifyError::File {
            path: path.to_path_buf(),
            detail: d,
        };
        let t = match serde_json::from_str::<TableFile>(text) {
            Ok(TableFile::Full(t)) => t,
            Ok(TableFile::List(classes)) => ClassTable {
                classes,
                background: default_background(),
            },
            Err(e) => {
                return Err(bad(format!(
                    "not a class table ({e}); expected {{\"classes\": [{{\"id\", \"name\", \
                     \"color\"}}, ...], \"background\": 255}}"
                )))
            }
        };
        if t.background == 0 {
            return Err(bad(
                "background 0 is the unlabelled value; use another label (255 by default)".into(),
            ));
        }
        let mut ids: Vec<u32> = t.classes.iter().map(|c| c.id).collect();
        ids.sort_unstable();
        if ids.windows(2).any(|w| w[0] == w[1]) {
            return Err(bad("duplicate class ids".into()));
        }
        if ids.contains(&0) || ids.contains(&t.background) {
            return Err(bad(format!(
                "class id 0 (unlabelled) and the background label {} cannot be ROI classes",
                t.background
            )));
        }
        Ok(t)
    }

    /// Checks that every scribbled label is in the table.
    pub fn check(&self, labels: &[u32]) -> Result<(), ClassifyError> {
        let missing: Vec<u32> = labels
            .iter()
            .copied()
            .filter(|&l| l != self.background && !self.classes.iter().any(|c| c.id == l))
            .collect();
        if missing.is_empty() {
            Ok(())
        } else {
            Err(ClassifyError::Input(format!(
                "scribbled labels {missing:?} are not in the class table (ids {:?}, background {})",
                self.classes.iter().map(|c| c.id).collect::<Vec<_>>(),
                self.background
            )))
        }
    }
}

/// Classification settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassifyConfig {
    /// The forest.
    pub forest: ForestConfig,
    /// A voxel takes its most probable class when that probability is at least `tau`;
    /// otherwise it is background.
    pub tau: f32,
    /// The scribble label meaning background/other.
    pub background: u32,
    /// Bricks below the store's background threshold are background without prediction
    /// (only when background is scribbled and no ROI scribble lies in them).
    pub skip_empty: bool,
}

impl Default for ClassifyConfig {
    fn default() -> Self {
        ClassifyConfig {
            forest: ForestConfig {
                class_weight: ClassWeight::Balanced,
                ..ForestConfig::default()
            },
            tau: 0.5,
            background: 255,
            skip_empty: true,
        }
    }
}

/// Labelled rows gathered from scribbles.
#[derive(Debug, Clone)]
pub struct TrainingSet {
    /// `rows x d` features.
    pub x: Vec<f32>,
    /// Class index per row.
    pub y: Vec<u16>,
    /// Features per row.
    pub d: usize,
    /// Scribble label of each class index (ascending; the background label included).
    pub labels: Vec<u32>,
    /// Bricks holding an ROI (non-background) scribble.
    pub roi_bricks: BTreeSet<[usize; 3]>,
    /// Bricks read.
    pub bricks: usize,
}

/// Gathers the features of every scribbled voxel, brick by brick.
pub fn training_set(
    fx: &BrickFeatures<'_>,
    s: &Scribbles,
    background: u32,
) -> Result<TrainingSet, ClassifyError> {
    training_set_with(fx, s, background, &|b| fx.brick(b))
}

/// [`training_set`] with the features of a brick from `fetch` (e.g. a cache in front of `fx`).
pub fn training_set_with(
    fx: &BrickFeatures<'_>,
    s: &Scribbles,
    background: u32,
    fetch: &(dyn Fn(&Brick) -> Result<Vec<f32>, ClassifyError> + Sync),
) -> Result<TrainingSet, ClassifyError> {
    training_set_boxed(fx, s, background, &|b, _| Ok((fetch(b)?, *b)))
}

/// A fetch of the features a brick's scribbles need: given the brick and the box around its
/// scribbled voxels, the features of a box holding that one (voxel-major) and the box.
pub type PartFetch<'a> =
    dyn Fn(&Brick, &Brick) -> Result<(Vec<f32>, Brick), ClassifyError> + Sync + 'a;

/// [`training_set`] with features from `fetch`, which may compute just the box around each
/// brick's scribbled voxels (a stroke's slice of a brick) instead of the whole brick.
pub fn training_set_boxed(
    fx: &BrickFeatures<'_>,
    s: &Scribbles,
    background: u32,
    fetch: &PartFetch<'_>,
) -> Result<TrainingSet, ClassifyError> {
    let store = fx.store();
    let dims = store.info().dims;
    if s.dims != dims {
        return Err(ClassifyError::Input(format!(
            "scribbles are on a {:?} grid, the store {} is {:?}",
            s.dims,
            store.root().display(),
            dims
        )));
    }
    if s.voxels.is_empty() {
        return Err(ClassifyError::Input(
            "the scribbles label no voxel: paint at least two classes".into(),
        ));
    }
    let labels: Vec<u32> = s.counts().keys().copied().collect();
    if labels.len() < 2 {
        return Err(ClassifyError::Input(format!(
            "the scribbles hold one class only (label {}): paint at least two, e.g. an ROI and \
             background ({background})",
            labels[0]
        )));
    }
    if labels.len() > u16::MAX as usize {
        return Err(ClassifyError::Input(format!("{} classes", labels.len())));
    }
    let bs = store.info().brick;
    let mut per_brick: BTreeMap<[usize; 3], Vec<(u64, u32)>> = BTreeMap::new();
    let (w, h) = (dims[0] as u64, dims[1] as u64);
    for &(i, c) in &s.voxels {
        let (x, y, z) = (
            (i % w) as usize,
            ((i / w) % h) as usize,
            (i / (w * h)) as usize,
        );
        per_brick
            .entry([x / bs, y / bs, z / bs])
            .or_default()
            .push((i, c));
    }
    let roi_bricks = per_brick
        .iter()
        .filter(|(_, v)| v.iter().any(|&(_, c)| c != background))
        .map(|(k, _)| *k)
        .collect();
    let d = fx.channels();
    let parts: Vec<(Vec<f32>, Vec<u16>)> = per_brick
        .par_iter()
        .map(|(bi, vox)| {
            let whole = store.brick(*bi)?;
            // The box around this brick's scribbled voxels.
            let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
            for &(i, _) in vox {
                let p = [
                    (i % w) as usize,
                    ((i / w) % h) as usize,
                    (i / (w * h)) as usize,
                ];
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
            let part = Brick {
                index: whole.index,
                origin: lo,
                size: [0, 1, 2].map(|a| hi[a] + 1 - lo[a]),
            };
            let (f, b) = fetch(&whole, &part)?;
            let mut x = Vec::with_capacity(vox.len() * d);
            let mut y = Vec::with_capacity(vox.len());
            for &(i, c) in vox {
                let (vx, vy, vz) = (
                    (i % w) as usize,
                    ((i / w) % h) as usize,
                    (i / (w * h)) as usize,
                );
                let li = ((vz - b.origin[2]) * b.size[1] + vy - b.origin[1]) * b.size[0] + vx
                    - b.origin[0];
                x.extend_from_slice(&f[li * d..(li + 1) * d]);
                y.push(labels.binary_search(&c).unwrap_or(0) as u16);
            }
            Ok((x, y))
        })
        .collect::<Result<_, ClassifyError>>()?;
    let mut x = Vec::with_capacity(s.voxels.len() * d);
    let mut y = Vec::with_capacity(s.voxels.len());
    for (px, py) in parts {
        x.extend(px);
        y.extend(py);
    }
    Ok(TrainingSet {
        x,
        y,
        d,
        labels,
        roi_bricks,
        bricks: per_brick.len(),
    })
}

/// Trains the forest on a training set.
pub fn fit(ts: &TrainingSet, cfg: &ForestConfig) -> Result<Forest, ClassifyError> {
    Ok(Forest::fit(
        Dataset {
            x: &ts.x,
            y: &ts.y,
            d: ts.d,
            classes: ts.labels.len(),
        },
        cfg,
    )?)
}

/// Output label of each class index: its scribble label, or 0 for background.
pub fn output_labels(labels: &[u32], background: u32) -> Vec<u16> {
    labels
        .iter()
        .map(|&l| {
            if l == background {
                0
            } else {
                l.min(u16::MAX as u32) as u16
            }
        })
        .collect()
}

/// Classifies the rows of one brick's features: probabilities (`voxels x classes`) and the
/// output label per voxel (argmax where its probability is at least `tau`, else 0).
pub fn predict_brick(
    forest: &Forest,
    features: &[f32],
    out_labels: &[u16],
    tau: f32,
) -> Result<(Vec<f32>, Vec<u16>), ClassifyError> {
    let p = forest.predict_proba(features)?;
    let c = forest.classes();
    let lab = p
        .chunks(c)
        .map(|r| {
            let (k, v) = argmax(r);
            if v >= tau {
                out_labels[k]
            } else {
                0
            }
        })
        .collect();
    Ok((p, lab))
}

/// The index and value of the largest probability of one voxel (the first on ties; `(0,
/// f32::MIN)` for an empty row).
pub fn argmax(row: &[f32]) -> (usize, f32) {
    row.iter()
        .enumerate()
        .fold((0, f32::MIN), |b, (k, &v)| if v > b.1 { (k, v) } else { b })
}

/// The result of classifying a volume.
#[derive(Debug, Clone)]
pub struct Classified {
    /// Output label per voxel (x fastest): the ROI label, 0 for background or uncertain.
    pub labels: Vec<u16>,
    /// Grid.
    pub dims: [usize; 3],
    /// Bricks predicted.
    pub bricks_predicted: usize,
    /// Bricks skipped as empty.
    pub bricks_skipped: usize,
    /// Voxels predicted.
    pub voxels_predicted: u64,
    /// Seconds spent computing features (summed over threads).
    pub feature_seconds: f64,
    /// Seconds spent in the forest (summed over threads).
    pub predict_seconds: f64,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// What classifying one brick gives.
#[derive(Debug, Clone, PartialEq)]
pub struct BrickResult {
    /// Probabilities, `voxels x classes`.
    pub proba: Vec<f32>,
    /// Output label per voxel (all 0 for a skipped brick).
    pub labels: Vec<u16>,
    /// True when the brick was empty and taken as background without prediction.
    pub skipped: bool,
    /// Seconds computing features.
    pub feature_seconds: f64,
    /// Seconds in the forest.
    pub predict_seconds: f64,
}

/// The result of an empty brick taken as background with certainty, without prediction:
/// when `cfg.skip_empty`, background is scribbled, the brick is below the store's background
/// threshold and no ROI scribble lies in it; `None` when the brick must be predicted.
pub fn empty_brick(
    store: &BrickStore,
    labels: &[u32],
    roi_bricks: &BTreeSet<[usize; 3]>,
    cfg: &ClassifyConfig,
    b: &Brick,
) -> Option<BrickResult> {
    let k = labels.iter().position(|&l| l == cfg.background)?;
    if !cfg.skip_empty || store.is_occupied(b, None) || roi_bricks.contains(&b.index) {
        return None;
    }
    let mut p = vec![0.0f32; b.voxels() * labels.len()];
    p.iter_mut()
        .skip(k)
        .step_by(labels.len())
        .for_each(|v| *v = 1.0);
    Some(BrickResult {
        proba: p,
        labels: vec![0; b.voxels()],
        skipped: true,
        feature_seconds: 0.0,
        predict_seconds: 0.0,
    })
}

/// Classifies one brick: the pure per-brick step that every executor schedules. A brick below
/// the store's background threshold is background with certainty, without prediction, when
/// `cfg.skip_empty`, background is scribbled and no ROI scribble lies in it.
pub fn classify_brick(
    fx: &BrickFeatures<'_>,
    forest: &Forest,
    labels: &[u32],
    out_labels: &[u16],
    roi_bricks: &BTreeSet<[usize; 3]>,
    cfg: &ClassifyConfig,
    b: &Brick,
) -> Result<BrickResult, ClassifyError> {
    if let Some(r) = empty_brick(fx.store(), labels, roi_bricks, cfg, b) {
        return Ok(r);
    }
    let t = Instant::now();
    let f = fx.brick(b)?;
    let t1 = Instant::now();
    let (proba, lab) = predict_brick(forest, &f, out_labels, cfg.tau)?;
    Ok(BrickResult {
        proba,
        labels: lab,
        skipped: false,
        feature_seconds: t1.duration_since(t).as_secs_f64(),
        predict_seconds: t1.elapsed().as_secs_f64(),
    })
}

/// Classifies every brick (empty ones skipped per `cfg`), optionally writing probabilities.
/// `progress` is called with the number of bricks done.
pub fn classify_volume(
    fx: &BrickFeatures<'_>,
    forest: &Forest,
    ts: &TrainingSet,
    cfg: &ClassifyConfig,
    proba: Option<&mut VectorArray>,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Classified, ClassifyError> {
    let t0 = Instant::now();
    let store = fx.store();
    let dims = store.info().dims;
    if forest.features() != fx.channels() || forest.classes() != ts.labels.len() {
        return Err(ClassifyError::Input(format!(
            "the forest takes {} features and {} classes, the feature set gives {} and the \
             scribbles {}",
            forest.features(),
            forest.classes(),
            fx.channels(),
            ts.labels.len()
        )));
    }
    let out_labels = output_labels(&ts.labels, cfg.background);
    let bricks: Vec<Brick> = store.bricks().collect();
    let labels = Mutex::new(vec![0u16; dims.iter().product()]);
    let done = AtomicU64::new(0);
    let ns = [AtomicU64::new(0), AtomicU64::new(0)];
    let skipped = AtomicU64::new(0);
    let voxels = AtomicU64::new(0);
    let proba_ref = proba.as_deref();
    bricks
        .par_iter()
        .try_for_each(|b| -> Result<(), ClassifyError> {
            let r = classify_brick(fx, forest, &ts.labels, &out_labels, &ts.roi_bricks, cfg, b)?;
            if r.skipped {
                skipped.fetch_add(1, Ordering::Relaxed);
            } else {
                voxels.fetch_add(b.voxels() as u64, Ordering::Relaxed);
                ns[0].fetch_add((r.feature_seconds * 1e9) as u64, Ordering::Relaxed);
                ns[1].fetch_add((r.predict_seconds * 1e9) as u64, Ordering::Relaxed);
            }
            if let Some(va) = proba_ref {
                va.write_brick(b, &r.proba)?;
            }
            if !r.skipped {
                let mut g = labels.lock().unwrap_or_else(|p| p.into_inner());
                let mut k = 0;
                for z in 0..b.size[2] {
                    for y in 0..b.size[1] {
                        let row =
                            ((b.origin[2] + z) * dims[1] + b.origin[1] + y) * dims[0] + b.origin[0];
                        g[row..row + b.size[0]].copy_from_slice(&r.labels[k..k + b.size[0]]);
                        k += b.size[0];
                    }
                }
            }
            progress(done.fetch_add(1, Ordering::Relaxed) + 1);
            Ok(())
        })?;
    if let Some(va) = proba {
        va.finish()?;
    }
    let skipped = skipped.into_inner() as usize;
    let voxels_predicted = voxels.into_inner();
    Ok(Classified {
        labels: labels.into_inner().unwrap_or_else(|p| p.into_inner()),
        dims,
        bricks_predicted: bricks.len() - skipped,
        bricks_skipped: skipped,
        voxels_predicted,
        feature_seconds: ns[0].load(Ordering::Relaxed) as f64 * 1e-9,
        predict_seconds: ns[1].load(Ordering::Relaxed) as f64 * 1e-9,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Precision, recall and F1 of one class.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct F1 {
    /// Class label.
    pub label: u32,
    /// Precision.
    pub precision: f64,
    /// Recall.
    pub recall: f64,
    /// F1 (0 when the class is neither predicted nor present).
    pub f1: f64,
    /// Ground-truth voxels.
    pub support: u64,
}

/// F1 of each of `classes` for a predicted label volume against the ground truth.
pub fn f1_scores(pred: &[u16], truth: &[u32], classes: &[u32]) -> Vec<F1> {
    classes
        .iter()
        .map(|&c| {
            let (mut tp, mut fp, mut fnn) = (0u64, 0u64, 0u64);
            for (&p, &t) in pred.iter().zip(truth) {
                let (p, t) = (p as u32 == c, t == c);
                tp += (p && t) as u64;
                fp += (p && !t) as u64;
                fnn += (!p && t) as u64;
            }
            let precision = if tp + fp > 0 {
                tp as f64 / (tp + fp) as f64
            } else {
                0.0
            };
            let recall = if tp + fnn > 0 {
                tp as f64 / (tp + fnn) as f64
            } else {
                0.0
            };
            let f1 = if tp > 0 {
                2.0 * tp as f64 / (2 * tp + fp + fnn) as f64
            } else {
                0.0
            };
            F1 {
                label: c,
                precision,
                recall,
                f1,
                support: tp + fnn,
            }
        })
        .collect()
}
