//! The `neuvolex classify` pipeline, on any executor: the forest is trained once on the
//! scribbles, then the prediction stage ([`PredictStage`]) runs over every brick, writing
//! per-class u8 probabilities and the label of every voxel into the store, each brick marked
//! done once written (a re-run with the same forest resumes). The label image and the
//! optional NIfTI are assembled from the stored label bricks, so in-process and cluster runs
//! give the same bytes.

use crate::components::{apply_in_memory, PriorConfig};
use crate::features::{BrickFeatures, FeatureSet};
use crate::forest::Forest;
use crate::scribble::{load_scribbles, Scribbles};
use crate::shard::{
    classify_brick, empty_brick, fit, output_labels, training_set, BrickResult, ClassTable,
    ClassifyConfig,
};
use crate::ClassifyError;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{Brick, BrickStore, VectorArray, VectorEncoding};
use neuvolex_features::InrModel;
use neuvolex_formats::meta::MemVolume;
use neuvolex_formats::{DType, VolumeMeta};
use neuvolex_tasks::{
    codec, execute_ordered, fingerprint, Blob, Blobs, DeadTask, DynStage, Executor, RunEvent,
    RunReport, Stage, Task, TaskCtx, TaskError,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// The stage's name (workers dispatch on it).
pub const STAGE: &str = "classify";
/// The probability array the pipeline writes.
pub const PROBA: &str = "classes_proba";
/// The per-brick label array the pipeline writes (assembled into `labels/classified`).
pub const LABELS: &str = "classes_labels";

/// Where a stage's per-voxel features come from: a store, a feature set, and the trained
/// model the learned parts need (checked by fingerprint on every worker).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSpec {
    /// The store (path or URL).
    pub store: String,
    /// Feature set.
    pub features: String,
    /// Read INR features from the store's feature arrays.
    pub stored_features: bool,
    /// Version of the store's trained model, when the features need it
    /// ([`neuvolex_features::stage::model_identity`]).
    pub model: Option<String>,
    /// Blob holding that model, when it is not the store's model file (a snapshot of a model
    /// still training in the service).
    #[serde(default)]
    pub model_blob: Option<String>,
}

/// A [`FeatureSpec`] opened: the store, the model and the parsed feature set.
pub struct OpenedFeatures {
    /// The store.
    pub store: Arc<BrickStore>,
    /// The model, when the set needs one.
    pub model: Option<Arc<InrModel>>,
    /// The feature set.
    pub set: FeatureSet,
    /// What was opened.
    pub spec: FeatureSpec,
    /// The bytes of the model file to publish as `spec.model_blob` (coordinator side).
    pub model_bytes: Option<Arc<Vec<u8>>>,
}

impl FeatureSpec {
    /// The spec of `set` over the store at `store`, computed with `model` (the store's trained
    /// model, when the set needs one).
    pub fn new(
        store: &Path,
        set: &FeatureSet,
        stored_features: bool,
        model: Option<&InrModel>,
    ) -> Self {
        FeatureSpec {
            store: store_path_string(store),
            features: set.to_string(),
            stored_features,
            model: if set.needs_model() {
                model.map(neuvolex_features::stage::model_identity)
            } else {
                None
            },
            model_blob: None,
        }
    }

    /// Opens the store and the model, from its blob when the spec names one.
    pub fn open_with(&self, blobs: &dyn Blobs) -> Result<OpenedFeatures, ClassifyError> {
        let (Some(key), Some(version)) = (&self.model_blob, &self.model) else {
            return self.open();
        };
        let bytes = blobs
            .get(key)
            .map_err(|e| ClassifyError::Input(format!("model blob {key}: {e}")))?;
        let model = Arc::new(neuvolex_features::stage::model_from_bytes(&bytes, version)?);
        Ok(OpenedFeatures {
            store: Arc::new(BrickStore::open(Path::new(&self.store))?),
            model: Some(model),
            set: self.features.parse().map_err(ClassifyError::Input)?,
            spec: self.clone(),
            model_bytes: None,
        })
    }

    /// Opens the store and loads the model (checking its fingerprint).
    pub fn open(&self) -> Result<OpenedFeatures, ClassifyError> {
        let set: FeatureSet = self.features.parse().map_err(ClassifyError::Input)?;
        let store = Arc::new(BrickStore::open(Path::new(&self.store))?);
        let model = match &self.model {
            Some(v) => Some(Arc::new(neuvolex_features::stage::load_model_checked(
                &store, v,
            )?)),
            None if set.needs_model() => {
                return Err(ClassifyError::Input(format!(
                    "features '{set}' need a trained INR: run `neuvolex train {}` first",
                    self.store
                )))
            }
            None => None,
        };
        Ok(OpenedFeatures {
            store,
            model,
            set,
            spec: self.clone(),
            model_bytes: None,
        })
    }
}

impl OpenedFeatures {
    /// Another handle on the same store, model and spec.
    pub fn share(&self) -> OpenedFeatures {
        OpenedFeatures {
            store: self.store.clone(),
            model: self.model.clone(),
            set: self.set.clone(),
            spec: self.spec.clone(),
            model_bytes: self.model_bytes.clone(),
        }
    }

    /// The model blob workers fetch, when the spec names one.
    pub fn blobs(&self) -> Vec<Blob> {
        match (&self.spec.model_blob, &self.model_bytes) {
            (Some(k), Some(b)) => vec![Blob {
                key: k.clone(),
                bytes: b.clone(),
            }],
            _ => Vec::new(),
        }
    }

    /// The per-brick feature computer.
    pub fn features(&self) -> Result<BrickFeatures<'_>, ClassifyError> {
        BrickFeatures::new(
            &self.store,
            self.set.clone(),
            self.model.clone(),
            self.spec.stored_features,
        )
    }
}

/// The parameters of the prediction stage: everything a worker needs besides the forest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PredictParams {
    /// Where the features come from.
    pub source: FeatureSpec,
    /// Blob key of the trained forest.
    pub forest: String,
    /// Scribble label of each class index.
    pub labels: Vec<u32>,
    /// Threshold, background label, empty-brick rule.
    pub tau: f32,
    /// The label meaning background.
    pub background: u32,
    /// Empty bricks are background without prediction.
    pub skip_empty: bool,
    /// Bricks holding an ROI scribble (never skipped).
    pub roi_bricks: Vec<[usize; 3]>,
    /// Identity of this run (done markers).
    pub identity: String,
}

/// What one prediction task did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PredictOutput {
    /// Bricks predicted.
    pub predicted: u32,
    /// Empty bricks taken as background.
    pub empty: u32,
    /// Voxels predicted.
    pub voxels: u64,
    /// Seconds computing features.
    pub feature_seconds: f64,
    /// Seconds in the forest.
    pub predict_seconds: f64,
}

/// The prediction stage: a task's bricks are classified and their probabilities and labels
/// written into the store.
pub struct PredictStage {
    params: PredictParams,
    src: OpenedFeatures,
    forest: Arc<Forest>,
    forest_bytes: Arc<Vec<u8>>,
    cfg: ClassifyConfig,
    out_labels: Vec<u16>,
    roi: BTreeSet<[usize; 3]>,
    /// The pending generations the pipeline started; a brick is done once both mark it.
    proba: VectorArray,
    labels: VectorArray,
    /// Where this process keeps feature bricks between runs (never sent to workers).
    memo: Option<crate::FeatureMemo>,
    /// Predicts the bricks instead of the CPU forest (the GPU; never sent to workers).
    accel: Option<Arc<dyn crate::accel::BrickPredictor>>,
}

impl PredictStage {
    /// Serves the features of the bricks this process predicts through `memo`.
    pub fn with_memo(mut self, memo: Option<crate::FeatureMemo>) -> Self {
        self.memo = memo;
        self
    }

    /// Predicts the bricks this process runs with `pred` (the GPU) instead of the CPU forest:
    /// the same outputs where `pred` gives the CPU's u8 probabilities and classes.
    pub fn with_predictor(mut self, pred: Option<Arc<dyn crate::accel::BrickPredictor>>) -> Self {
        self.accel = pred;
        self
    }

    /// The stage over opened features; the probability and label arrays and the done markers
    /// must exist (the pipeline creates them).
    pub fn new(
        params: PredictParams,
        src: OpenedFeatures,
        forest_bytes: Arc<Vec<u8>>,
    ) -> Result<Self, ClassifyError> {
        let forest: Forest = codec::decode(&forest_bytes)
            .map_err(|e| ClassifyError::Input(format!("forest blob {}: {e}", params.forest)))?;
        let store = src.store.clone();
        let cfg = ClassifyConfig {
            tau: params.tau,
            background: params.background,
            skip_empty: params.skip_empty,
            ..ClassifyConfig::default()
        };
        Ok(PredictStage {
            out_labels: output_labels(&params.labels, params.background),
            roi: params.roi_bricks.iter().copied().collect(),
            proba: store.open_pending_vectors(PROBA, &params.identity)?,
            labels: store.open_pending_vectors(LABELS, &params.identity)?,
            forest: Arc::new(forest),
            forest_bytes,
            cfg,
            src,
            params,
            memo: None,
            accel: None,
        })
    }

    /// Rebuilds the stage on a worker from its parameters (the forest from the blob store).
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let p: PredictParams = neuvolex_tasks::codec::params(v)?;
        let src = p.source.open_with(blobs).map_err(TaskError::failed)?;
        let forest = blobs.get(&p.forest)?;
        Ok(Arc::new(
            PredictStage::new(p, src, forest).map_err(TaskError::failed)?,
        ))
    }
}

impl Stage for PredictStage {
    type Output = PredictOutput;

    fn name(&self) -> &'static str {
        STAGE
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }

    fn blobs(&self) -> Vec<Blob> {
        vec![Blob {
            key: self.params.forest.clone(),
            bytes: self.forest_bytes.clone(),
        }]
    }

    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<PredictOutput> {
        let mut out = PredictOutput::default();
        let mut todo = Vec::with_capacity(task.bricks.len());
        for &bi in &task.bricks {
            ctx.check()?;
            let b = self.src.store.brick(bi)?;
            if self.proba.is_done(&b)? && self.labels.is_done(&b)? {
                ctx.skip(1);
                continue;
            }
            todo.push(b);
        }
        let failed = |b: &Brick, e: &dyn std::fmt::Display| {
            TaskError::Failed(format!("brick {:?}: {e}", b.index))
        };
        let Some(p) = &self.accel else {
            let mut fx = self.src.features().map_err(TaskError::failed)?;
            fx.set_memo(self.memo.clone());
            for b in &todo {
                ctx.check()?;
                let r = classify_brick(
                    &fx,
                    &self.forest,
                    &self.params.labels,
                    &self.out_labels,
                    &self.roi,
                    &self.cfg,
                    b,
                )
                .map_err(|e| failed(b, &e))?;
                self.put(b, &r, &mut out)?;
            }
            return Ok(out);
        };
        // On the accelerator: empty bricks at once, the rest streamed through it (the next
        // bricks read while the device works on these).
        let mut rest = Vec::with_capacity(todo.len());
        for b in todo {
            match empty_brick(
                &self.src.store,
                &self.params.labels,
                &self.roi,
                &self.cfg,
                &b,
            ) {
                Some(r) => self.put(&b, &r, &mut out)?,
                None => rest.push(b),
            }
        }
        let mut err = None;
        let mut t = Instant::now();
        p.predict_stream(&rest, &mut |b, a| {
            let r = ctx.check().and_then(|()| {
                let r = crate::accel::brick_result(
                    a,
                    &self.params.labels,
                    &self.out_labels,
                    b,
                    t.elapsed().as_secs_f64(),
                )
                .map_err(|e| failed(b, &e))?;
                self.put(b, &r, &mut out)
            });
            t = Instant::now();
            match r {
                Ok(()) => true,
                Err(e) => {
                    err = Some(e);
                    false
                }
            }
        })
        .map_err(|e| TaskError::Failed(e.to_string()))?;
        match err {
            Some(e) => Err(e),
            None => Ok(out),
        }
    }
}

impl PredictStage {
    /// Writes brick `b`'s probabilities and labels, marks it done and counts it in `out`.
    fn put(
        &self,
        b: &Brick,
        r: &BrickResult,
        out: &mut PredictOutput,
    ) -> neuvolex_tasks::Result<()> {
        self.proba.write_brick(b, &r.proba)?;
        let lab: Vec<f32> = r.labels.iter().map(|&l| l as f32).collect();
        self.labels.write_brick(b, &lab)?;
        self.proba.mark_done(b)?;
        self.labels.mark_done(b)?;
        if r.skipped {
            out.empty += 1;
        } else {
            out.predicted += 1;
            out.voxels += b.voxels() as u64;
            out.feature_seconds += r.feature_seconds;
            out.predict_seconds += r.predict_seconds;
        }
        Ok(())
    }
}

/// What `neuvolex classify` is asked to do.
#[derive(Debug, Clone)]
pub struct ClassifyRequest {
    /// The store.
    pub store: PathBuf,
    /// Scribbles (sparse label volume or JSON strokes).
    pub scribbles: PathBuf,
    /// Feature set.
    pub features: FeatureSet,
    /// Class table.
    pub classes: Option<PathBuf>,
    /// NIfTI label volume to write.
    pub out: Option<PathBuf>,
    /// Replace an existing `out`.
    pub force: bool,
    /// Read INR features from the store.
    pub stored_features: bool,
    /// Forest and labelling settings.
    pub config: ClassifyConfig,
    /// Bricks per task.
    pub bricks_per_task: usize,
    /// The spatial prior applied to the label image (`None`: the forest's labels as they
    /// are). The probabilities and the per-brick label vectors stay raw either way.
    pub prior: Option<PriorConfig>,
    /// An earlier result of the same settings to hold to ([`crate::stable`]): beyond the
    /// margin of the strokes added since, a voxel keeps the label it showed unless the new
    /// probabilities prefer the change by the rule's `delta`. Ignored unless these scribbles
    /// keep every earlier one ([`crate::stable::added`]).
    pub hold: Option<crate::stable::Hold>,
    /// Predict on the accelerator passed to [`classify_with`] (the GPU of `neuvolex classify
    /// --gpu`) in this process; an error without one. Default false: the CPU forest, the
    /// reference.
    pub gpu: bool,
}

/// What the spatial prior did to the label image.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PriorReport {
    /// Its settings.
    pub config: PriorConfig,
    /// Connected components of the raw labels.
    pub components: usize,
    /// Of which kept.
    pub kept: usize,
    /// Voxels it set to background.
    pub voxels_cleared: u64,
    /// Doubtful voxels the kept labels grew into.
    pub voxels_grown: u64,
    /// Seconds it took.
    pub seconds: f64,
}

/// What `classify` did (the JSON report).
#[derive(Debug, Clone, Serialize)]
pub struct ClassifyReport {
    /// Feature set.
    pub features: String,
    /// Channels per voxel.
    pub channels: usize,
    /// Class labels (scribble labels).
    pub labels: Vec<u32>,
    /// Scribbled voxels per label.
    pub scribbled: Vec<(u32, u64)>,
    /// Bricks read for training.
    pub training_bricks: usize,
    /// Trees.
    pub trees: usize,
    /// Nodes.
    pub nodes: usize,
    /// Seconds gathering training features.
    pub seconds_training_features: f64,
    /// Seconds fitting the forest.
    pub seconds_fit: f64,
    /// Bricks predicted in this run.
    pub bricks_predicted: usize,
    /// Empty bricks taken as background in this run.
    pub bricks_skipped: usize,
    /// Bricks already done by an earlier run (resumed).
    pub bricks_resumed: u64,
    /// Voxels predicted in this run.
    pub voxels_predicted: u64,
    /// Wall-clock seconds of prediction.
    pub seconds_classify: f64,
    /// Voxels per second of prediction.
    pub voxels_per_second: f64,
    /// Seconds after prediction assembling the label image (the prior and the stability rule
    /// included), on the coordinator alone.
    pub seconds_assemble: f64,
    /// Seconds after that publishing the probabilities, label vectors and OME label image
    /// (and writing `--out`), on the coordinator alone.
    pub seconds_publish: f64,
    /// Voxels per output label (after the prior).
    pub counts: Vec<(u16, u64)>,
    /// The spatial prior's effect (absent when it was off or the run did not finish).
    pub prior: Option<PriorReport>,
    /// Voxels that kept the label of the result held to ([`ClassifyRequest::hold`]; absent
    /// when there was none to hold to).
    pub voxels_held: Option<u64>,
    /// How the stage ran.
    pub run: RunReport,
    /// The accelerator that predicted ([`ClassifyRequest::gpu`]; absent on the CPU).
    pub gpu: Option<String>,
}

/// The result of the pipeline.
#[derive(Debug, Clone)]
pub struct ClassifyOutcome {
    /// The report.
    pub report: ClassifyReport,
    /// The classes of the label image.
    pub classes: Vec<ClassInfo>,
    /// Scribbled voxels.
    pub scribbled_voxels: usize,
    /// Tasks given up (their bricks have no output; the label image was not written).
    pub dead: Vec<DeadTask>,
    /// The label image as written (after the prior; x fastest), empty when tasks died or
    /// the run was cancelled.
    pub labels: Vec<u16>,
    /// The run's own decisions (the forest's labels, and the labels after the prior before
    /// the rule), for a later run to hold ([`crate::stable::Hold::verdicts`]); `None` when no
    /// labels were made.
    pub verdicts: Option<crate::stable::RoundVerdicts>,
}

/// Loads the store's trained model (`None` when untrained).
pub fn load_model(store: &BrickStore) -> Result<Option<Arc<InrModel>>, ClassifyError> {
    let mp = neuvolex_features::train::model_path(store);
    if !mp.exists() {
        return Ok(None);
    }
    Ok(Some(Arc::new(
        neuvolex_features::checkpoint::load(&mp)?.model,
    )))
}

/// The label volume as u8 (or u16) on the store's grid.
fn label_volume(store: &BrickStore, labels: &[u16]) -> MemVolume {
    let max = labels.par_iter().copied().max().unwrap_or(0);
    let dtype = if max <= 255 { DType::U8 } else { DType::U16 };
    let bytes: Vec<u8> = if max <= 255 {
        labels.par_iter().map(|&l| l as u8).collect()
    } else {
        labels
            .par_iter()
            .flat_map_iter(|l| l.to_ne_bytes())
            .collect()
    };
    MemVolume {
        // The store's whole geometry (spacing, affine, NIfTI frames), in the labels' type.
        meta: VolumeMeta {
            dtype,
            scaling: None,
            ..store.meta()
        },
        bytes,
        name: PathBuf::from("<classified>"),
    }
}

/// Runs `neuvolex classify` on `exec`: reads the scribbles from `req.scribbles`, then
/// [`classify_scribbles`].
pub fn classify<E: Executor + ?Sized>(
    req: &ClassifyRequest,
    exec: &E,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<ClassifyOutcome, ClassifyError> {
    classify_with(req, None, exec, progress)
}

/// [`classify`] predicting on `accel` when [`ClassifyRequest::gpu`] is set (it must then be
/// given, and `exec` must run in this process).
pub fn classify_with<E: Executor + ?Sized>(
    req: &ClassifyRequest,
    accel: Option<&dyn crate::accel::Accelerator>,
    exec: &E,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<ClassifyOutcome, ClassifyError> {
    check_out(req)?;
    let meta = BrickStore::open(&req.store)?.meta();
    let scr = load_scribbles(&req.scribbles, &meta).map_err(|e| ClassifyError::File {
        path: req.scribbles.clone(),
        detail: format!("cannot use these scribbles: {e}"),
    })?;
    classify_scribbles_on(req, scr, None, accel, exec, progress)
}

/// Refuses an existing `--out` unless `--force`.
fn check_out(req: &ClassifyRequest) -> Result<(), ClassifyError> {
    match &req.out {
        Some(o) if o.exists() && !req.force => Err(ClassifyError::File {
            path: o.clone(),
            detail: "exists (use --force to replace it)".into(),
        }),
        _ => Ok(()),
    }
}

/// Runs `neuvolex classify` on `exec` with scribbles already in memory (the Python API):
/// the same forest, stage, prior and outputs as [`classify`], which reads them from a file.
/// `req.scribbles` only names them in errors.
pub fn classify_scribbles<E: Executor + ?Sized>(
    req: &ClassifyRequest,
    scr: Scribbles,
    exec: &E,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<ClassifyOutcome, ClassifyError> {
    classify_scribbles_memo(req, scr, None, exec, progress)
}

/// [`classify_scribbles`] with the features of every brick served through `memo` (the Python
/// package's session keeps them between rounds): the same outputs, since a memo returns what
/// the computation gives.
pub fn classify_scribbles_memo<E: Executor + ?Sized>(
    req: &ClassifyRequest,
    scr: Scribbles,
    memo: Option<crate::FeatureMemo>,
    exec: &E,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<ClassifyOutcome, ClassifyError> {
    classify_scribbles_on(req, scr, memo, None, exec, progress)
}

/// [`classify_scribbles_memo`] predicting on `accel` when [`ClassifyRequest::gpu`] is set.
pub fn classify_scribbles_on<E: Executor + ?Sized>(
    req: &ClassifyRequest,
    scr: Scribbles,
    memo: Option<crate::FeatureMemo>,
    accel: Option<&dyn crate::accel::Accelerator>,
    exec: &E,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<ClassifyOutcome, ClassifyError> {
    let cfg = &req.config;
    check_out(req)?;
    let accel = match (req.gpu, accel) {
        (false, _) => None,
        (true, Some(a)) => Some(a),
        (true, None) => {
            return Err(ClassifyError::Input(
                "--gpu: this build has no GPU classification (build neuvolex with the `gpu` \
                 feature)"
                    .into(),
            ))
        }
    };
    let mut store = BrickStore::open(&req.store)?;
    if scr.dims != store.info().dims {
        return Err(ClassifyError::File {
            path: req.scribbles.clone(),
            detail: format!(
                "grid {:?} differs from the store's {:?} (x, y, z)",
                scr.dims,
                store.info().dims
            ),
        });
    }
    let table = match &req.classes {
        Some(p) => {
            let t = ClassTable::load(p)?;
            if t.background != cfg.background {
                return Err(ClassifyError::File {
                    path: p.clone(),
                    detail: format!(
                        "background {} differs from --background {}",
                        t.background, cfg.background
                    ),
                });
            }
            let labels: Vec<u32> = scr.counts().keys().copied().collect();
            t.check(&labels).map_err(|e| ClassifyError::File {
                path: req.scribbles.clone(),
                detail: e.to_string(),
            })?;
            Some(t)
        }
        None => None,
    };
    let set = req.features.clone();
    let model = if set.needs_model() {
        load_model(&store)?
    } else {
        None
    };
    let spec = FeatureSpec::new(&req.store, &set, req.stored_features, model.as_deref());
    let (ts, t_feat, forest, t_fit) = {
        let mut fx = BrickFeatures::new(&store, set.clone(), model.clone(), req.stored_features)?;
        fx.set_memo(memo.clone());
        let t = Instant::now();
        let ts = training_set(&fx, &scr, cfg.background).map_err(|e| ClassifyError::File {
            path: req.scribbles.clone(),
            detail: e.to_string(),
        })?;
        let t_feat = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let forest = fit(&ts, &cfg.forest)?;
        let t_fit = t.elapsed().as_secs_f64();
        tracing::info!(
            rows = ts.y.len(),
            d = ts.d,
            classes = ts.labels.len(),
            t_feat,
            t_fit,
            "forest trained"
        );
        // Where the probability array goes.
        (ts, t_feat, forest, t_fit)
    };
    let max_label = output_labels(&ts.labels, cfg.background)
        .into_iter()
        .max()
        .unwrap_or(0);
    if max_label > 2048 {
        return Err(ClassifyError::Input(format!(
            "class id {max_label}: ids above 2048 are not supported"
        )));
    }
    let forest_bytes =
        Arc::new(codec::encode(&forest).map_err(|e| ClassifyError::Input(e.to_string()))?);
    let forest_key = format!("forest-{:016x}", fingerprint(&forest_bytes));
    let identity = format!(
        "{:016x}",
        fingerprint(
            format!(
                "{forest_key}|{set}|{:?}|{}|{}|{}|{}",
                spec.model, cfg.tau, cfg.background, cfg.skip_empty, req.stored_features
            )
            .as_bytes()
        )
    );
    let store_arc = Arc::new(BrickStore::open(&req.store)?);
    // The pending generations of both arrays for this run: resumed when an interrupted run
    // with the same forest and settings left them, published together at the end.
    let c = ts.labels.len();
    let mut proba_w = store_arc.resume_vectors(
        PROBA,
        c,
        VectorEncoding::U8 {
            lo: vec![0.0; c],
            hi: vec![1.0; c],
        },
        &identity,
    )?;
    let enc = if max_label <= 255 {
        VectorEncoding::U8 {
            lo: vec![0.0],
            hi: vec![255.0],
        }
    } else {
        VectorEncoding::F16
    };
    let mut labels_w = store_arc.resume_vectors(LABELS, 1, enc, &identity)?;
    let every: Vec<Brick> = store_arc.bricks().collect();
    let undone_p: BTreeSet<[usize; 3]> = proba_w
        .pending(every.iter().cloned())?
        .iter()
        .map(|b| b.index)
        .collect();
    let undone_l: BTreeSet<[usize; 3]> = labels_w
        .pending(every.iter().cloned())?
        .iter()
        .map(|b| b.index)
        .collect();
    let all: Vec<[usize; 3]> = every.iter().map(|b| b.index).collect();
    let pending: Vec<[usize; 3]> = all
        .iter()
        .copied()
        .filter(|i| undone_p.contains(i) || undone_l.contains(i))
        .collect();
    let resumed = (all.len() - pending.len()) as u64;
    if resumed > 0 {
        progress(RunEvent::Message(format!(
            "resuming: {resumed} of {} bricks already classified by an earlier run",
            all.len()
        )));
    }
    let params = PredictParams {
        source: spec.clone(),
        forest: forest_key,
        labels: ts.labels.clone(),
        tau: cfg.tau,
        background: cfg.background,
        skip_empty: cfg.skip_empty,
        roi_bricks: ts.roi_bricks.iter().copied().collect(),
        identity,
    };
    let src = OpenedFeatures {
        store: store_arc.clone(),
        model: model.clone(),
        set: set.clone(),
        spec,
        model_bytes: None,
    };
    let pred = match accel {
        Some(a) => {
            let p = a.prepare(
                store_arc.clone(),
                &set,
                &forest,
                &crate::accel::AccelOptions::tau(cfg.tau),
            )?;
            tracing::info!(
                adapter = %a.describe(),
                features = %set,
                "classify: predicting on the GPU (the filter bank and the forest per brick)"
            );
            Some(Arc::<dyn crate::accel::BrickPredictor>::from(p))
        }
        None => None,
    };
    let gpu = accel.map(|a| a.describe());
    let stage = PredictStage::new(params, src, forest_bytes)?
        .with_memo(memo)
        .with_predictor(pred);
    // An accelerator gets bricks in runs long enough for its stream to overlap and group them.
    let per = match &gpu {
        Some(_) => req.bricks_per_task.max(crate::accel::STREAM_BRICKS),
        None => req.bricks_per_task,
    };
    let tasks = neuvolex_tasks::plan(&pending, per, 0);
    let t = Instant::now();
    let (outs, run) = execute_ordered(exec, &stage, &tasks, progress)
        .map_err(|e| ClassifyError::Input(e.to_string()))?;
    let seconds = t.elapsed().as_secs_f64();
    let mut sum = PredictOutput::default();
    for o in outs.iter().flatten() {
        sum.predicted += o.predicted;
        sum.empty += o.empty;
        sum.voxels += o.voxels;
    }
    let classes: Vec<ClassInfo> = match &table {
        Some(t) => t.classes.clone(),
        None => ts
            .labels
            .iter()
            .filter(|&&l| l != cfg.background)
            .map(|&l| ClassInfo {
                id: l,
                name: format!("class_{l}"),
                color: neuvolex_bricks::synth::palette(l),
            })
            .collect(),
    };
    let mut counts = BTreeMap::<u16, u64>::new();
    let dead = run.dead.clone();
    let mut prior_report = None;
    let mut voxels_held = None;
    let mut out_labels = Vec::new();
    let mut verdicts = None;
    let (mut seconds_assemble, mut seconds_publish) = (0.0, 0.0);
    if dead.is_empty() && !run.cancelled {
        let t_assemble = Instant::now();
        let mut labels = assemble_labels(&store_arc, &stage.labels)?;
        let forest_labels = labels.clone();
        if let Some(pc) = &req.prior {
            let t = Instant::now();
            let (conf, best) = assemble_confidence(&store_arc, &stage.proba, &stage.out_labels)?;
            let seeds: Vec<(u64, u16)> = scr
                .voxels
                .iter()
                .filter(|&&(_, l)| l != cfg.background)
                .map(|&(i, l)| (i, l.min(u16::MAX as u32) as u16))
                .collect();
            let info = store_arc.info();
            let v = apply_in_memory(
                &mut labels,
                info.dims,
                info.brick,
                Some(&conf),
                Some(&best),
                &seeds,
                pc,
            );
            prior_report = Some(PriorReport {
                config: *pc,
                components: v.components,
                kept: v.kept,
                voxels_cleared: v.cleared,
                voxels_grown: v.grown,
                seconds: t.elapsed().as_secs_f64(),
            });
        }
        // Forests in a row count against the held round when this one extends its strokes.
        let before = req
            .hold
            .as_ref()
            .and_then(|h| h.verdicts_before(&scr, cfg.background));
        let v = crate::stable::RoundVerdicts::after(forest_labels, labels.clone(), before);
        if let Some(h) = &req.hold {
            voxels_held = hold_to(&store_arc, &stage, &scr, h, &v, &mut labels)?;
            if let (Some(held), Some(pc)) = (voxels_held.as_mut(), &req.prior) {
                let dims = store_arc.info().dims;
                // Each voxel growth now gives its verdict was one the rule had held.
                *held -= h
                    .config
                    .follow(&mut labels, (&v.forest, &v.verdict), dims, pc.grow);
            }
        }
        verdicts = Some(v);
        counts = label_counts(&labels);
        seconds_assemble = t_assemble.elapsed().as_secs_f64();
        let t_publish = Instant::now();
        proba_w.set_extra(serde_json::json!({
            "kind": "class_probabilities",
            "labels": ts.labels,
            "background": cfg.background,
            "features": set.to_string(),
            "identity": stage.params.identity,
            // What the prior did, without its timing: the metadata of the same inputs stays
            // byte-identical across runs and executors.
            "prior": prior_report.as_ref().map(|p| serde_json::json!({
                "config": p.config,
                "components": p.components,
                "kept": p.kept,
                "voxels_cleared": p.voxels_cleared,
                "voxels_grown": p.voxels_grown,
            })),
        }));
        // The probabilities, the label vectors and the OME label image appear together: a
        // reader (or a kill) sees all three from before or all three from this run.
        let mut commit = neuvolex_bricks::Commit::new();
        proba_w.finish_into(&mut commit)?;
        labels_w.finish_into(&mut commit)?;
        let mut lv = label_volume(&store, &labels);
        store.stage_labels(&mut commit, "classified", &mut lv, &classes, &mut |_| {})?;
        commit.publish(store.backend())?;
        if let Some(o) = &req.out {
            neuvolex_formats::nifti::write_nifti(o, &mut lv, 64)?;
        }
        seconds_publish = t_publish.elapsed().as_secs_f64();
        out_labels = labels;
    }
    Ok(ClassifyOutcome {
        report: ClassifyReport {
            features: set.to_string(),
            channels: ts.d,
            labels: ts.labels.clone(),
            scribbled: scr.counts().into_iter().collect(),
            training_bricks: ts.bricks,
            trees: forest.trees(),
            nodes: forest.nodes(),
            seconds_training_features: t_feat,
            seconds_fit: t_fit,
            bricks_predicted: sum.predicted as usize,
            bricks_skipped: sum.empty as usize,
            bricks_resumed: resumed + run.bricks_skipped,
            voxels_predicted: sum.voxels,
            seconds_classify: seconds,
            voxels_per_second: sum.voxels as f64 / seconds.max(1e-9),
            seconds_assemble,
            seconds_publish,
            counts: counts.into_iter().collect(),
            prior: prior_report,
            voxels_held,
            run,
            gpu,
        },
        classes,
        scribbled_voxels: scr.voxels.len(),
        dead,
        labels: out_labels,
        verdicts,
    })
}

/// Applies the stability rule of `hold` to the run's label image `labels`, with the run's
/// probabilities rounded to u8 as the service holds them and the run's own decisions `now`
/// against the held result's; the voxels held, or `None` when the scribbles do not extend the
/// held result's (or its grid differs).
fn hold_to(
    store: &BrickStore,
    stage: &PredictStage,
    scr: &Scribbles,
    h: &crate::stable::Hold,
    now: &crate::stable::RoundVerdicts,
    labels: &mut [u16],
) -> Result<Option<u64>, ClassifyError> {
    use crate::stable::{added, to_u8, Evidence};
    let before = h.verdicts.as_ref().filter(|v| {
        v.forest.len() == labels.len()
            && v.verdict.len() == labels.len()
            && now.forest.len() == labels.len()
    });
    let Some(new) = added(&h.scribbles, scr).filter(|_| h.labels.len() == labels.len()) else {
        return Ok(None);
    };
    let dims = store.info().dims;
    let c = stage.out_labels.len().max(1);
    let level = h.config.levels(&new);
    let bg = stage.out_labels.iter().position(|&o| o == 0);
    // Brick by brick, a row at a time: a row of the brick is a span of the volume.
    let mut held = 0;
    for b in store.bricks() {
        let p: Vec<u8> = stage
            .proba
            .read_brick(&b)?
            .iter()
            .map(|&v| to_u8(v))
            .collect();
        let w = b.size[0];
        for (row, pr) in b.rows(dims).zip(p.chunks_exact(w * c)) {
            let r = row..row + w;
            let ev = Evidence {
                probs: pr,
                out_labels: &stage.out_labels,
                bg,
            };
            let v = before.map(|b| b.span(&now.forest[r.clone()], r.clone()));
            held += h.config.hold(
                &mut labels[r.clone()],
                &h.labels[r.clone()],
                &ev,
                &level[r],
                v.as_ref(),
            );
        }
    }
    Ok(Some(held))
}

/// The store as workers should open it (see [`neuvolex_bricks::location::shared_path_string`]).
pub use neuvolex_bricks::location::shared_path_string as store_path_string;

/// Reads every label brick into one volume (x fastest).
fn assemble_labels(store: &BrickStore, va: &VectorArray) -> Result<Vec<u16>, ClassifyError> {
    let dims = store.info().dims;
    let mut out = vec![0u16; dims.iter().product()];
    let bs = store.info().brick;
    let bricks: Vec<Brick> = store.bricks().collect();
    // One slab of the volume per layer of bricks (disjoint, so layers fill in parallel), and
    // within a layer the bricks are read and decoded in parallel before they are placed.
    out.par_chunks_mut(bs * dims[0] * dims[1])
        .enumerate()
        .try_for_each(|(layer, slab)| -> Result<(), ClassifyError> {
            let z0 = layer * bs;
            let decoded: Vec<(&Brick, Vec<f32>)> = bricks
                .par_iter()
                .filter(|b| b.origin[2] == z0)
                .map(|b| Ok((b, va.read_brick(b)?)))
                .collect::<Result<_, ClassifyError>>()?;
            for (b, lab) in decoded {
                for (row, l) in b.rows(dims).zip(lab.chunks_exact(b.size[0])) {
                    let row = row - z0 * dims[0] * dims[1];
                    for (o, &v) in slab[row..row + b.size[0]].iter_mut().zip(l) {
                        *o = v.round() as u16;
                    }
                }
            }
            Ok(())
        })?;
    Ok(out)
}

/// Voxels per label of a label image, counted in parallel.
pub(crate) fn label_counts(labels: &[u16]) -> BTreeMap<u16, u64> {
    let hist = labels
        .par_chunks(1 << 20)
        .map(|c| {
            let mut h = vec![0u64; 1 << 16];
            for &l in c {
                h[l as usize] += 1;
            }
            h
        })
        .reduce(
            || vec![0u64; 1 << 16],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            },
        );
    hist.into_iter()
        .enumerate()
        .filter(|&(_, n)| n > 0)
        .map(|(l, n)| (l as u16, n))
        .collect()
}

/// Reads every probability brick into each voxel's largest class probability and the output
/// label of that class (`out_labels` per class index, 0 = background), x fastest.
fn assemble_confidence(
    store: &BrickStore,
    va: &VectorArray,
    out_labels: &[u16],
) -> Result<(Vec<f32>, Vec<u16>), ClassifyError> {
    let dims = store.info().dims;
    let c = va.info().channels.max(1);
    let n = dims.iter().product();
    let (mut conf, mut best) = (vec![1.0f32; n], vec![0u16; n]);
    for b in store.bricks() {
        let p = va.read_brick(&b)?;
        let mut k = 0;
        for row in b.rows(dims) {
            for i in row..row + b.size[0] {
                let (j, m) = crate::shard::argmax(&p[k * c..(k + 1) * c]);
                conf[i] = m.max(0.0);
                best[i] = out_labels.get(j).copied().unwrap_or(0);
                k += 1;
            }
        }
    }
    Ok((conf, best))
}

/// The class probabilities the last run wrote ([`PROBA`]), class-major: channel `k` holds
/// every voxel (x fastest) at `k * voxels`. The channels are the run's scribble labels in
/// order.
pub fn assemble_probabilities(store: &BrickStore) -> Result<Vec<f32>, ClassifyError> {
    let va = store.open_vectors(PROBA)?;
    let c = va.info().channels;
    let dims = store.info().dims;
    let n: usize = dims.iter().product();
    let mut out = vec![0f32; n * c];
    for b in store.bricks() {
        let p = va.read_brick(&b)?;
        let mut k = 0;
        for row in b.rows(dims) {
            for i in row..row + b.size[0] {
                for (ch, v) in p[k * c..(k + 1) * c].iter().enumerate() {
                    out[ch * n + i] = *v;
                }
                k += 1;
            }
        }
    }
    Ok(out)
}

/// The name of the stage that returns probabilities instead of writing them (the service).
pub const PROBA_STAGE: &str = "classify-proba";

/// Parameters of [`ProbaStage`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProbaParams {
    /// Where the features come from.
    pub source: FeatureSpec,
    /// Blob key of the trained forest.
    pub forest: String,
    /// Scribble label of each class index.
    pub labels: Vec<u32>,
    /// The label meaning background.
    pub background: u32,
    /// Round features to half precision first (what the service's feature cache holds).
    pub f16_features: bool,
}

/// Features of a brick from somewhere else than the store (the service's feature cache), in
/// half precision: it must give what [`BrickFeatures`] gives, rounded to f16 (a stage with a
/// hook needs [`ProbaParams::f16_features`]).
pub type FeatureHook<'a> =
    Box<dyn Fn(&Brick) -> Result<Arc<Vec<half::f16>>, ClassifyError> + Send + Sync + 'a>;

/// The u8 probabilities of an empty brick of `voxels` voxels over `classes` classes: the
/// background class (index `bg`, when the classes include it) with certainty.
pub fn certain_background(voxels: usize, classes: usize, bg: Option<usize>) -> Vec<u8> {
    let mut v = vec![0u8; voxels * classes];
    if let Some(k) = bg {
        for px in v.chunks_exact_mut(classes) {
            px[k] = 255;
        }
    }
    v
}

/// Predicts a task's bricks and returns their u8 probabilities (occupied bricks through the
/// forest, empty ones background with certainty): the service's streaming classification.
pub struct ProbaStage<'a> {
    params: ProbaParams,
    src: OpenedFeatures,
    forest: Arc<Forest>,
    forest_bytes: Arc<Vec<u8>>,
    hook: Option<FeatureHook<'a>>,
}

impl<'a> ProbaStage<'a> {
    /// The stage; `hook` serves features in this process.
    pub fn new(
        params: ProbaParams,
        src: OpenedFeatures,
        forest: Arc<Forest>,
        hook: Option<FeatureHook<'a>>,
    ) -> Result<Self, ClassifyError> {
        if hook.is_some() && !params.f16_features {
            return Err(ClassifyError::Input(
                "a feature hook serves half-precision features; set f16_features".into(),
            ));
        }
        let forest_bytes =
            Arc::new(codec::encode(&*forest).map_err(|e| ClassifyError::Input(e.to_string()))?);
        Ok(ProbaStage {
            params,
            src,
            forest,
            forest_bytes,
            hook,
        })
    }

    /// The blob key under which `forest` is published.
    pub fn forest_key(forest: &Forest) -> Result<String, ClassifyError> {
        let b = codec::encode(forest).map_err(|e| ClassifyError::Input(e.to_string()))?;
        Ok(format!("forest-{:016x}", fingerprint(&b)))
    }

    /// Rebuilds the stage on a worker.
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let p: ProbaParams = neuvolex_tasks::codec::params(v)?;
        let src = p.source.open_with(blobs).map_err(TaskError::failed)?;
        let bytes = blobs.get(&p.forest)?;
        let forest: Forest = codec::decode(&bytes)?;
        Ok(Arc::new(
            ProbaStage::<'static>::new(p, src, Arc::new(forest), None)
                .map_err(TaskError::failed)?,
        ))
    }
}

impl Stage for ProbaStage<'_> {
    type Output = Vec<([usize; 3], Vec<u8>)>;

    fn name(&self) -> &'static str {
        PROBA_STAGE
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }

    fn blobs(&self) -> Vec<Blob> {
        let mut v = vec![Blob {
            key: self.params.forest.clone(),
            bytes: self.forest_bytes.clone(),
        }];
        v.extend(self.src.blobs());
        v
    }

    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<Self::Output> {
        let mut fx = self.src.features().map_err(TaskError::failed)?;
        if self.params.f16_features {
            fx.set_quantise(crate::features::Quantise::F16);
        }
        let c = self.params.labels.len();
        let bg = self
            .params
            .labels
            .iter()
            .position(|&l| l == self.params.background);
        task.bricks
            .iter()
            .map(|&bi| {
                ctx.check()?;
                let b = self.src.store.brick(bi)?;
                let u8s: Vec<u8> = if self.src.store.is_occupied(&b, None) {
                    let failed =
                        |e: &dyn std::fmt::Display| TaskError::Failed(format!("brick {bi:?}: {e}"));
                    // The cache's half-precision features go to the forest as they are; the
                    // store's are rounded through f16 by `fx` when the params say so.
                    let p = match &self.hook {
                        Some(h) => {
                            let f = h(&b).map_err(|e| failed(&e))?;
                            // A newer run may have begun while the features were computed.
                            ctx.check()?;
                            self.forest.predict_proba_f16(&f)
                        }
                        None => {
                            let f = fx.brick(&b).map_err(|e| failed(&e))?;
                            ctx.check()?;
                            self.forest.predict_proba(&f)
                        }
                    }
                    .map_err(|e| failed(&e))?;
                    p.iter().map(|&v| crate::stable::to_u8(v)).collect()
                } else {
                    certain_background(b.voxels(), c, bg)
                };
                Ok((bi, u8s))
            })
            .collect()
    }
}
