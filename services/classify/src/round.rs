//! One interactive round in memory (the Python package's `Session`): the forest trained on the
//! scribbles from features kept in half precision between rounds ([`KeptFeatures`], what the
//! service's feature cache holds), every occupied brick predicted in parallel into u8
//! probabilities (the service's [`crate::pipeline::ProbaStage`] path: empty bricks background
//! with certainty, the bricks of the newest strokes first), the label image assembled in memory,
//! the spatial prior ([`apply_in_memory`]) and the stability rule held to the previous round
//! ([`crate::stable`]), and nothing written into the store.
//!
//! It is the pipeline's round ([`crate::pipeline::classify_scribbles_memo`] with a
//! [`crate::pipeline::ClassifyRequest::hold`]) on features rounded to f16: the same forest, the
//! same labels (each voxel's most probable class where at least `tau`, from the f32
//! probabilities), the same u8 probabilities the pipeline stores, the same prior, rule and
//! growth (tested below against the pipeline itself).

use crate::cache::widen;
use crate::components::apply_in_memory;
use crate::features::{f16_saturating, BrickFeatures, FeatureMemo};
use crate::pipeline::{ClassifyReport, PriorReport};
use crate::scribble::Scribbles;
use crate::shard::{argmax, fit, output_labels, training_set_boxed, ClassifyConfig};
use crate::stable::{added, to_u8, Evidence, Hold, RoundVerdicts};
use crate::{ClassifyError, PriorConfig};
use half::f16;
use neuvolex_bricks::Brick;
use neuvolex_tasks::RunReport;
use rayon::prelude::*;
use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// A kept brick: the features' name (set and model), the brick's origin and size.
type KeptKey = (String, [usize; 3], [usize; 3]);

/// Feature bricks (`voxels x channels`, f16) kept between the rounds of one session, up to a
/// byte budget: once full it keeps no more (a brick not kept is computed again when needed).
pub struct KeptFeatures {
    map: Mutex<HashMap<KeptKey, Arc<Vec<f16>>>>,
    used: AtomicUsize,
    budget: usize,
}

impl KeptFeatures {
    /// Keeps at most `budget` bytes of features.
    pub fn new(budget: usize) -> Self {
        KeptFeatures {
            map: Mutex::default(),
            used: AtomicUsize::new(0),
            budget,
        }
    }

    /// Bytes of features kept.
    pub fn used(&self) -> usize {
        self.used.load(Ordering::SeqCst)
    }

    fn get(&self, k: &KeptKey) -> Option<Arc<Vec<f16>>> {
        self.map
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(k)
            .cloned()
    }

    fn keep(&self, k: KeptKey, v: &Arc<Vec<f16>>) {
        let cost = v.len() * 2;
        if self.used() + cost > self.budget {
            return;
        }
        let mut m = self.map.lock().unwrap_or_else(|p| p.into_inner());
        if m.insert(k, v.clone()).is_none() {
            self.used.fetch_add(cost, Ordering::SeqCst);
        }
    }

    /// The features of brick `b` named `key` (feature set and model identity), rounded to
    /// f16: kept ones as they are, others computed by `fx` (and kept while the budget allows).
    pub fn brick(
        &self,
        key: &str,
        fx: &BrickFeatures<'_>,
        b: &Brick,
    ) -> Result<Arc<Vec<f16>>, ClassifyError> {
        let k = (key.to_string(), b.origin, b.size);
        if let Some(v) = self.get(&k) {
            return Ok(v);
        }
        let v = Arc::new(fx.brick(b)?.into_iter().map(f16_saturating).collect());
        self.keep(k, &v);
        Ok(v)
    }

    /// The kept features named `key` as a [`FeatureMemo`] for [`BrickFeatures::set_memo`]
    /// (the slice preview): every brick rounded to f16, as a round reads it.
    pub fn memo(self: &Arc<Self>, key: String) -> FeatureMemo {
        let kept = self.clone();
        Arc::new(move |b, compute| {
            let k = (key.clone(), b.origin, b.size);
            let v = match kept.get(&k) {
                Some(v) => v,
                None => {
                    let v = Arc::new(compute()?.into_iter().map(f16_saturating).collect());
                    kept.keep(k, &v);
                    v
                }
            };
            Ok(widen(&v))
        })
    }
}

/// What a round is asked to do.
#[derive(Debug, Clone, Copy)]
pub struct RoundRequest<'a> {
    /// The scribbles (on the store's grid).
    pub scribbles: &'a Scribbles,
    /// Forest and labelling settings.
    pub config: &'a ClassifyConfig,
    /// The spatial prior (`None`: the forest's labels as they are).
    pub prior: Option<PriorConfig>,
    /// The previous round to hold to (made with the same settings and features: the caller
    /// checks); ignored unless these scribbles keep every one of its scribbles.
    pub hold: Option<&'a Hold>,
}

/// What a round gives.
#[derive(Debug, Clone)]
pub struct Round {
    /// The label image shown (after the prior and the rule), x fastest.
    pub labels: Vec<u16>,
    /// Class probabilities in u8 steps ([`to_u8`]), voxel-major (classes innermost), channel
    /// `k` the class `report.labels[k]`: the pipeline's stored probabilities are `p / 255`.
    pub proba: Vec<u8>,
    /// The round's own decisions, for the next round to hold.
    pub verdicts: RoundVerdicts,
    /// The pipeline's report of the round (nothing resumed or published).
    pub report: ClassifyReport,
}

fn cancelled_error() -> ClassifyError {
    ClassifyError::Input("cancelled".into())
}

/// Runs one round over `fx`'s store with features through `kept` (named `key`: the feature set
/// and model identity). `cancelled` is polled between bricks; `progress(done, total)` follows
/// the prediction brick by brick.
pub fn classify_round(
    fx: &BrickFeatures<'_>,
    kept: &KeptFeatures,
    key: &str,
    req: &RoundRequest<'_>,
    cancelled: &(dyn Fn() -> bool + Sync),
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Round, ClassifyError> {
    let store = fx.store();
    let info = store.info();
    let (dims, bs) = (info.dims, info.brick);
    let n: usize = dims.iter().product();
    let (cfg, scr) = (req.config, req.scribbles);
    let d = fx.channels();
    // Training rows: each scribbled brick's features kept whole (its prediction needs them),
    // only the box around its scribbles widened to f32.
    let t = Instant::now();
    let ts = training_set_boxed(fx, scr, cfg.background, &|whole, part| {
        if cancelled() {
            return Err(cancelled_error());
        }
        let f = kept.brick(key, fx, whole)?;
        Ok((part_of(&f, whole, part, d), *part))
    })
    .map_err(|e| match e {
        // Scribbles that cannot train a forest, named as the pipeline names them.
        ClassifyError::Input(m) if !cancelled() => ClassifyError::Input(format!("scribbles: {m}")),
        e => e,
    })?;
    let t_feat = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let forest = fit(&ts, &cfg.forest)?;
    let t_fit = t.elapsed().as_secs_f64();
    let out_labels = output_labels(&ts.labels, cfg.background);
    let max_label = out_labels.iter().copied().max().unwrap_or(0);
    if max_label > 2048 {
        return Err(ClassifyError::Input(format!(
            "class id {max_label}: ids above 2048 are not supported"
        )));
    }
    let c = ts.labels.len();
    let bg = ts.labels.iter().position(|&l| l == cfg.background);
    // The bricks of the strokes added since the previous round first (all strokes without one).
    let new = req.hold.and_then(|h| added(&h.scribbles, scr));
    let focus = new.as_ref().filter(|s| !s.voxels.is_empty()).unwrap_or(scr);
    let (w, h) = (dims[0] as u64, dims[1] as u64);
    let first: BTreeSet<[usize; 3]> = focus
        .voxels
        .iter()
        .map(|&(i, _)| {
            let p = [i % w, (i / w) % h, i / (w * h)];
            p.map(|v| v as usize / bs)
        })
        .collect();
    let mut bricks: Vec<Brick> = store.bricks().collect();
    bricks.sort_by_key(|b| !first.contains(&b.index));
    // Each worker takes the next brick in that order; a brick's rows go through the forest
    // in parallel blocks besides.
    let t = Instant::now();
    let labels = Mutex::new(vec![0u16; n]);
    let proba = Mutex::new(vec![0u8; n * c]);
    let (next, done) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let (skipped, voxels) = (AtomicUsize::new(0), AtomicU64::new(0));
    let stop = AtomicBool::new(false);
    let total = bricks.len();
    let one = |b: &Brick| -> Result<(), ClassifyError> {
        // The pipeline's empty brick ([`crate::shard::empty_brick`]): background with certainty.
        let empty = cfg.skip_empty
            && bg.is_some()
            && !store.is_occupied(b, None)
            && !ts.roi_bricks.contains(&b.index);
        let rw = b.size[0];
        if let (true, Some(k)) = (empty, bg) {
            skipped.fetch_add(1, Ordering::Relaxed);
            let mut p = proba.lock().unwrap_or_else(|p| p.into_inner());
            for row in b.rows(dims) {
                p[row * c..(row + rw) * c]
                    .chunks_exact_mut(c)
                    .for_each(|px| px[k] = 255);
            }
            return Ok(());
        }
        let f = kept.brick(key, fx, b)?;
        if cancelled() {
            return Err(cancelled_error());
        }
        let p = forest.predict_proba_f16(&f)?;
        let lab: Vec<u16> = p
            .chunks_exact(c)
            .map(|r| {
                let (k, v) = argmax(r);
                if v >= cfg.tau {
                    out_labels[k]
                } else {
                    0
                }
            })
            .collect();
        let p8: Vec<u8> = p.iter().map(|&v| to_u8(v)).collect();
        voxels.fetch_add(b.voxels() as u64, Ordering::Relaxed);
        {
            let mut g = labels.lock().unwrap_or_else(|p| p.into_inner());
            for (row, l) in b.rows(dims).zip(lab.chunks_exact(rw)) {
                g[row..row + rw].copy_from_slice(l);
            }
        }
        let mut g = proba.lock().unwrap_or_else(|p| p.into_inner());
        for (row, q) in b.rows(dims).zip(p8.chunks_exact(rw * c)) {
            g[row * c..(row + rw) * c].copy_from_slice(q);
        }
        Ok(())
    };
    (0..rayon::current_num_threads().max(1))
        .into_par_iter()
        .try_for_each(|_| -> Result<(), ClassifyError> {
            loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                if i >= total || stop.load(Ordering::SeqCst) {
                    return Ok(());
                }
                if cancelled() {
                    stop.store(true, Ordering::SeqCst);
                    return Err(cancelled_error());
                }
                if let Err(e) = one(&bricks[i]) {
                    stop.store(true, Ordering::SeqCst);
                    return Err(e);
                }
                progress(done.fetch_add(1, Ordering::SeqCst) + 1, total);
            }
        })?;
    let seconds = t.elapsed().as_secs_f64();
    let t_assemble = Instant::now();
    let mut labels = labels.into_inner().unwrap_or_else(|p| p.into_inner());
    let proba = proba.into_inner().unwrap_or_else(|p| p.into_inner());
    let forest_labels = labels.clone();
    let prior = req.prior.map(|pc| {
        let t = Instant::now();
        // Each voxel's largest probability (as the pipeline reads the stored u8 back) and
        // the output label of its class.
        let (conf, best): (Vec<f32>, Vec<u16>) = proba
            .par_chunks_exact(c)
            .map(|px| {
                let (j, m) = px
                    .iter()
                    .enumerate()
                    .fold((0, 0u8), |b, (k, &v)| if v > b.1 { (k, v) } else { b });
                (m as f32 / 255.0, out_labels.get(j).copied().unwrap_or(0))
            })
            .unzip();
        let seeds: Vec<(u64, u16)> = scr
            .voxels
            .iter()
            .filter(|&&(_, l)| l != cfg.background)
            .map(|&(i, l)| (i, l.min(u16::MAX as u32) as u16))
            .collect();
        let v = apply_in_memory(&mut labels, dims, bs, Some(&conf), Some(&best), &seeds, &pc);
        PriorReport {
            config: pc,
            components: v.components,
            kept: v.kept,
            voxels_cleared: v.cleared,
            voxels_grown: v.grown,
            seconds: t.elapsed().as_secs_f64(),
        }
    });
    // Forests in a row count against the held round when this one extends its strokes.
    let before = req
        .hold
        .and_then(|h| h.verdicts_before(scr, cfg.background));
    let verdicts = RoundVerdicts::after(forest_labels, labels.clone(), before);
    let mut voxels_held = None;
    if let Some(h) = req.hold {
        voxels_held = hold_in_memory(h, scr, &verdicts, &proba, &out_labels, &mut labels);
        if let (Some(held), Some(pc)) = (voxels_held.as_mut(), &req.prior) {
            // Each voxel growth now gives its verdict was one the rule had held.
            let grown = h.config.follow(
                &mut labels,
                (&verdicts.forest, &verdicts.verdict),
                dims,
                pc.grow,
            );
            *held = held.saturating_sub(grown);
        }
    }
    let counts: Vec<(u16, u64)> = crate::pipeline::label_counts(&labels).into_iter().collect();
    let seconds_assemble = t_assemble.elapsed().as_secs_f64();
    let voxels = voxels.into_inner();
    let report = ClassifyReport {
        features: fx.set().to_string(),
        channels: ts.d,
        labels: ts.labels.clone(),
        scribbled: scr.counts().into_iter().collect(),
        training_bricks: ts.bricks,
        trees: forest.trees(),
        nodes: forest.nodes(),
        seconds_training_features: t_feat,
        seconds_fit: t_fit,
        bricks_predicted: total - skipped.load(Ordering::Relaxed),
        bricks_skipped: skipped.into_inner(),
        bricks_resumed: 0,
        voxels_predicted: voxels,
        seconds_classify: seconds,
        voxels_per_second: voxels as f64 / seconds.max(1e-9),
        seconds_assemble,
        seconds_publish: 0.0,
        counts,
        prior,
        voxels_held,
        run: RunReport {
            stage: "round".into(),
            executor: "in-memory".into(),
            tasks: total,
            completed: total,
            seconds,
            ..RunReport::default()
        },
        gpu: None,
    };
    Ok(Round {
        labels,
        proba,
        verdicts,
        report,
    })
}

/// The features of `part` (a box inside brick `whole`) from the whole brick's f16 features
/// `f` (`d` per voxel), widened to f32, voxel-major.
fn part_of(f: &[f16], whole: &Brick, part: &Brick, d: usize) -> Vec<f32> {
    use half::slice::HalfFloatSliceExt;
    let len = part.size[0] * d;
    let mut out = vec![0f32; part.voxels() * d];
    let rows = out.chunks_exact_mut(len.max(1));
    let at = (0..part.size[2]).flat_map(|z| (0..part.size[1]).map(move |y| (y, z)));
    for (o, (y, z)) in rows.zip(at) {
        let (lx, ly, lz) = (
            part.origin[0] - whole.origin[0],
            part.origin[1] - whole.origin[1] + y,
            part.origin[2] - whole.origin[2] + z,
        );
        let s = ((lz * whole.size[1] + ly) * whole.size[0] + lx) * d;
        f[s..s + len].convert_to_f32_slice(o);
    }
    out
}

/// The stability rule of `h` over the whole label image in memory (the pipeline's per-brick
/// `hold_to` on the probabilities it stored): the voxels held, or `None` when the scribbles do
/// not extend the held round's (or its grid differs).
fn hold_in_memory(
    h: &Hold,
    scr: &Scribbles,
    now: &RoundVerdicts,
    proba: &[u8],
    out_labels: &[u16],
    labels: &mut [u16],
) -> Option<u64> {
    let n = labels.len();
    let before = h
        .verdicts
        .as_ref()
        .filter(|v| v.forest.len() == n && v.verdict.len() == n && now.forest.len() == n);
    let new = added(&h.scribbles, scr).filter(|_| h.labels.len() == n)?;
    let level = h.config.levels(&new);
    let bg = out_labels.iter().position(|&o| o == 0);
    let c = out_labels.len().max(1);
    const SPAN: usize = 1 << 16;
    Some(
        labels
            .par_chunks_mut(SPAN)
            .enumerate()
            .map(|(k, l)| {
                let r = k * SPAN..k * SPAN + l.len();
                let ev = Evidence {
                    probs: &proba[r.start * c..r.end * c],
                    out_labels,
                    bg,
                };
                let v = before.map(|b| b.span(&now.forest[r.clone()], r.clone()));
                h.config
                    .hold(l, &h.labels[r.clone()], &ev, &level[r], v.as_ref())
            })
            .sum(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::{FeatureSet, Quantise};
    use crate::pipeline::{self, ClassifyRequest};
    use crate::stable::StableConfig;
    use neuvolex_bricks::synth::PhantomParams;
    use neuvolex_bricks::BrickStore;
    use std::path::{Path, PathBuf};

    /// A 32x32x28 phantom in bricks of 8 (the corners empty), with its ground truth.
    fn phantom(dir: &Path) -> (PathBuf, BrickStore, Vec<u32>) {
        let path = dir.join("ph.zarr");
        let store = neuvolex_ingest::phantom_store(
            &path,
            PhantomParams::with_size(32, 3),
            &neuvolex_ingest::IngestOptions {
                brick: 8,
                ..Default::default()
            },
            &mut |_| {},
        )
        .unwrap();
        let truth = store
            .read_labels_box("ground_truth", [0, 0, 0], store.info().dims)
            .unwrap();
        (path, store, truth)
    }

    /// Scribbles of the truth: every `step`-th voxel of the z slices `zs` (background 255).
    fn strokes(dims: [usize; 3], truth: &[u32], zs: &[usize], step: usize) -> Scribbles {
        let plane = dims[0] * dims[1];
        let mut voxels: Vec<(u64, u32)> = zs
            .iter()
            .flat_map(|&z| (z * plane..(z + 1) * plane).step_by(step))
            .map(|i| (i as u64, if truth[i] == 0 { 255 } else { truth[i] }))
            .collect();
        voxels.sort_unstable();
        Scribbles { dims, voxels }
    }

    /// Asserts `a == b`, naming how many entries differ (not the arrays).
    fn same<T: PartialEq>(a: &[T], b: &[T], what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        let differ = a.iter().zip(b).filter(|(x, y)| x != y).count();
        assert_eq!(differ, 0, "{what}: {differ} of {} differ", a.len());
    }

    fn config() -> ClassifyConfig {
        let mut c = ClassifyConfig::default();
        c.forest.trees = 12;
        c
    }

    /// The pipeline's round on features rounded to f16 (through its feature memo), holding to
    /// `hold`: labels, the stored probabilities (u8 steps, voxel-major), verdicts, report.
    fn pipeline_round(
        path: &Path,
        scr: &Scribbles,
        set: &FeatureSet,
        hold: Option<Hold>,
    ) -> (Vec<u16>, Vec<u8>, RoundVerdicts, ClassifyReport) {
        let req = ClassifyRequest {
            store: path.to_path_buf(),
            scribbles: PathBuf::from("scribbles"),
            features: set.clone(),
            classes: None,
            out: None,
            force: false,
            stored_features: false,
            config: config(),
            bricks_per_task: 1,
            prior: Some(PriorConfig::default()),
            hold,
            gpu: false,
        };
        let f16: FeatureMemo = Arc::new(|_, compute| {
            let mut v = compute()?;
            Quantise::F16.apply(&mut v, 1);
            Ok(v)
        });
        let o = pipeline::classify_scribbles_memo(
            &req,
            scr.clone(),
            Some(f16),
            &neuvolex_tasks::LocalExecutor::new(),
            &mut |_| {},
        )
        .unwrap();
        let store = BrickStore::open(path).unwrap();
        let class_major = pipeline::assemble_probabilities(&store).unwrap();
        let n = o.labels.len();
        let c = class_major.len() / n;
        let proba = (0..n * c)
            .map(|i| to_u8(class_major[(i % c) * n + i / c]))
            .collect();
        (o.labels, proba, o.verdicts.unwrap(), o.report)
    }

    fn round(
        store: &BrickStore,
        set: &FeatureSet,
        kept: &KeptFeatures,
        scr: &Scribbles,
        hold: Option<&Hold>,
    ) -> Round {
        let fx = BrickFeatures::new(store, set.clone(), None, false).unwrap();
        let cfg = config();
        let req = RoundRequest {
            scribbles: scr,
            config: &cfg,
            prior: Some(PriorConfig::default()),
            hold,
        };
        classify_round(&fx, kept, &set.to_string(), &req, &|| false, &|_, _| {}).unwrap()
    }

    #[test]
    fn a_round_in_memory_is_the_pipelines_round_on_f16_features() {
        let dir = tempfile::tempdir().unwrap();
        let (path, store, truth) = phantom(dir.path());
        let dims = store.info().dims;
        let set: FeatureSet = crate::DEFAULT_FEATURES.parse().unwrap();
        let first = strokes(dims, &truth, &[6, 20], 5);
        let mut second = first.clone();
        second.voxels.extend(strokes(dims, &truth, &[13], 3).voxels);
        second.voxels.sort_unstable();
        let rule = StableConfig::default();
        let kept = KeptFeatures::new(1 << 30);
        // Round 1, nothing to hold to.
        let (p_labels, p_proba, p_verdicts, _) = pipeline_round(&path, &first, &set, None);
        let r1 = round(&store, &set, &kept, &first, None);
        assert!(kept.used() > 0);
        same(&r1.labels, &p_labels, "round 1 labels");
        same(&r1.proba, &p_proba, "round 1 probabilities");
        same(
            &r1.verdicts.forest,
            &p_verdicts.forest,
            "round 1 forest labels",
        );
        same(
            &r1.verdicts.verdict,
            &p_verdicts.verdict,
            "round 1 verdicts",
        );
        assert_eq!(r1.report.voxels_held, None);
        // Round 2 holds to round 1 through the rule, the prior's verdicts and growth.
        let hold = |labels: &[u16], verdicts: &RoundVerdicts| Hold {
            scribbles: first.clone(),
            labels: labels.to_vec(),
            config: rule,
            verdicts: Some(verdicts.clone()),
        };
        let (q_labels, q_proba, q_verdicts, q_report) =
            pipeline_round(&path, &second, &set, Some(hold(&p_labels, &p_verdicts)));
        let r2 = round(
            &store,
            &set,
            &kept,
            &second,
            Some(&hold(&r1.labels, &r1.verdicts)),
        );
        same(&r2.proba, &q_proba, "round 2 probabilities");
        same(
            &r2.verdicts.forest,
            &q_verdicts.forest,
            "round 2 forest labels",
        );
        same(
            &r2.verdicts.verdict,
            &q_verdicts.verdict,
            "round 2 verdicts",
        );
        same(&r2.labels, &q_labels, "round 2 labels");
        assert_eq!(r2.report.voxels_held, q_report.voxels_held);
        assert!(
            r2.report.voxels_held.is_some_and(|h| h > 0)
                && r2.report.bricks_skipped > 0
                && r2.report.bricks_predicted > 0,
            "held {:?}, {} bricks predicted, {} empty",
            r2.report.voxels_held,
            r2.report.bricks_predicted,
            r2.report.bricks_skipped
        );
        assert_eq!(r2.report.counts, q_report.counts);
        assert_eq!(r2.report.labels, q_report.labels);
        // The probabilities are the forest's on the f16 features, in u8 steps.
        let fx = BrickFeatures::new(&store, set.clone(), None, false).unwrap();
        let b = store.bricks().find(|b| store.is_occupied(b, None)).unwrap();
        let ts = crate::shard::training_set_boxed(&fx, &second, 255, &|whole, part| {
            Ok((
                part_of(
                    &kept.brick(&set.to_string(), &fx, whole)?,
                    whole,
                    part,
                    fx.channels(),
                ),
                *part,
            ))
        })
        .unwrap();
        let forest = fit(&ts, &config().forest).unwrap();
        let p = forest
            .predict_proba_f16(&kept.brick(&set.to_string(), &fx, &b).unwrap())
            .unwrap();
        let c = ts.labels.len();
        for (k, row) in b.rows(dims).enumerate() {
            let w = b.size[0];
            let want: Vec<u8> = p[k * w * c..(k + 1) * w * c]
                .iter()
                .map(|&v| to_u8(v))
                .collect();
            same(
                &r2.proba[row * c..(row + w) * c],
                &want,
                "a brick's probabilities",
            );
        }
    }

    /// Every file under `dir` with its bytes.
    fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
        let mut out = Vec::new();
        let mut todo = vec![dir.to_path_buf()];
        while let Some(d) = todo.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    todo.push(p);
                } else {
                    out.push((p.clone(), std::fs::read(&p).unwrap()));
                }
            }
        }
        out.sort();
        out
    }

    #[test]
    fn a_round_writes_nothing_into_the_store_and_a_budget_of_zero_changes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (path, store, truth) = phantom(dir.path());
        let dims = store.info().dims;
        let set: FeatureSet = "local+xyz".parse().unwrap();
        let first = strokes(dims, &truth, &[6, 20], 5);
        let mut second = first.clone();
        second.voxels.extend(strokes(dims, &truth, &[13], 3).voxels);
        second.voxels.sort_unstable();
        let before = files(&path);
        let kept = KeptFeatures::new(1 << 30);
        let r1 = round(&store, &set, &kept, &first, None);
        let hold = Hold {
            scribbles: first.clone(),
            labels: r1.labels.clone(),
            config: StableConfig::default(),
            verdicts: Some(r1.verdicts.clone()),
        };
        let r2 = round(&store, &set, &kept, &second, Some(&hold));
        assert!(r2.report.voxels_held.is_some());
        assert!(files(&path) == before, "a round changed the store's files");
        // Nothing kept: the same round from features computed again.
        let none = KeptFeatures::new(0);
        let again = round(&store, &set, &none, &second, Some(&hold));
        assert_eq!(none.used(), 0);
        same(&again.labels, &r2.labels, "labels");
        same(&again.proba, &r2.proba, "probabilities");
        // A cancelled round stops with an error.
        let fx = BrickFeatures::new(&store, set.clone(), None, false).unwrap();
        let cfg = config();
        let req = RoundRequest {
            scribbles: &second,
            config: &cfg,
            prior: None,
            hold: None,
        };
        assert!(classify_round(&fx, &kept, "k", &req, &|| true, &|_, _| {}).is_err());
    }
}
