//! `neuvolex._native`: the native half of the `neuvolex` Python package. It wraps the library
//! crates (not the CLI): ingest from a file or a numpy array, INR training, per-brick
//! features, scribble classification with the spatial prior (the `neuvolex classify`
//! pipeline itself), slice suggestion, viewpoints, rendering and NIfTI export. Arrays cross
//! in the store's order, x fastest: a C-ordered numpy array indexed `[z, y, x]`.
//!
//! Long calls run on a worker thread without the GIL ([`run::detached`]); Ctrl-C cancels them
//! at the next brick. The pure-Python layer (`python/neuvolex/__init__.py`) gives the public
//! API its numpy conventions.

mod arrays;
mod run;

use arrays::{ScribbleArray, VolumeArray};
use neuvolex_bricks::{BrickStore, Progress};
use neuvolex_classify::features::{BrickFeatures, FeatureSet};
use neuvolex_classify::pipeline::{self, ClassifyRequest, FeatureSpec, OpenedFeatures};
use neuvolex_classify::round::{self, KeptFeatures, RoundRequest};
use neuvolex_classify::{ClassWeight, ClassifyConfig, PriorConfig, SliceMass};
use neuvolex_formats::VolumeMeta;
use neuvolex_render::{BrickSource, Camera, Mode, RenderParams, Renderer, StoreSource, TfFile};
use neuvolex_tasks::{LocalExecutor, RunEvent};
use numpy::IntoPyArray;
use pyo3::prelude::*;
use pyo3::types::PyAny;
use run::{bad_argument, detached, Ctl, WorkError};
use std::path::PathBuf;
use std::sync::Arc;

/// A progress sink for the library's brick progress, relayed to the caller.
fn brick_progress<'a>(ctl: &'a Ctl, what: &'a str) -> impl FnMut(Progress) + 'a {
    let mut total = 0;
    move |p| match p {
        Progress::Stage { total: t, .. } => {
            total = t;
            ctl.progress(0, t, what);
        }
        Progress::Advance { done } => ctl.progress(done, total, what),
    }
}

/// A task executor in this process that stops when the caller cancels.
fn executor(ctl: &Ctl) -> LocalExecutor {
    let c = ctl.cancel.clone();
    LocalExecutor::new().with_cancel(Arc::new(move || {
        c.load(std::sync::atomic::Ordering::SeqCst)
    }))
}

/// Relays a stage's task events as progress.
fn task_progress<'a>(ctl: &'a Ctl) -> impl FnMut(RunEvent) + 'a {
    let mut stage = String::new();
    move |e| match e {
        RunEvent::Stage { name, total } => {
            ctl.progress(0, total, name.clone());
            stage = name;
        }
        RunEvent::Task { done, total, .. } => ctl.progress(done, total, stage.clone()),
        _ => {}
    }
}

/// The forest and labelling settings of `classify`, checked.
fn classify_config(
    trees: usize,
    min_split: usize,
    seed: u64,
    class_weight: &str,
    tau: f32,
    background: u32,
) -> PyResult<ClassifyConfig> {
    let bad = |m: String| Err(bad_argument(m));
    if trees == 0 || trees > 100_000 {
        return bad(format!("trees {trees}: must be 1..=100000"));
    }
    if min_split < 2 {
        return bad(format!("min_split {min_split}: must be at least 2"));
    }
    if !(0.0..=1.0).contains(&tau) {
        return bad(format!("tau {tau}: must be in [0, 1]"));
    }
    if background == 0 {
        return bad("background 0: label 0 means unlabelled".into());
    }
    let mut config = ClassifyConfig::default();
    config.forest.trees = trees;
    config.forest.min_samples_split = min_split;
    config.forest.seed = seed;
    config.forest.class_weight = match class_weight {
        "balanced" => ClassWeight::Balanced,
        "none" => ClassWeight::None,
        o => return bad(format!("class_weight '{o}': must be 'balanced' or 'none'")),
    };
    config.tau = tau;
    config.background = background;
    Ok(config)
}

/// A store of bricks: opened once, shared by every call.
#[pyclass(module = "neuvolex._native")]
struct Store {
    location: PathBuf,
    store: Arc<BrickStore>,
    /// The trained INR, read once from the store (and replaced by `train`).
    model: std::sync::Mutex<Option<Arc<neuvolex_features::InrModel>>>,
}

/// What a session's round showed and what made it: the next round with the same `key`
/// (settings, features and model) and more scribbles holds to it
/// ([`neuvolex_classify::stable`]).
struct Shown {
    key: String,
    scribbles: neuvolex_classify::Scribbles,
    labels: Vec<u16>,
    /// The round's own decisions (the forest's labels, and the labels after the prior), for
    /// the rule to hold them ([`neuvolex_classify::stable::Hold::verdicts`]).
    verdicts: Option<neuvolex_classify::stable::RoundVerdicts>,
}

/// The axis index of `x`, `y` or `z`.
fn axis_index(axis: &str) -> PyResult<usize> {
    match axis {
        "x" => Ok(0),
        "y" => Ok(1),
        "z" => Ok(2),
        o => Err(bad_argument(format!(
            "axis '{o}': expected 'x', 'y' or 'z'"
        ))),
    }
}

fn feature_set(features: &str) -> PyResult<FeatureSet> {
    features
        .parse()
        .map_err(|e: String| bad_argument(format!("features '{features}': {e}")))
}

impl Store {
    fn opened(location: PathBuf) -> Result<Store, WorkError> {
        let store = BrickStore::open(&location).map_err(|e| WorkError::bricks(&e))?;
        Ok(Store {
            location,
            store: Arc::new(store),
            model: Default::default(),
        })
    }

    /// The feature source of `set`: the store's model when the set needs one.
    fn features_of(&self, set: &FeatureSet) -> Result<OpenedFeatures, WorkError> {
        let model = if set.needs_model() {
            let mut held = self
                .model
                .lock()
                .map_err(|_| WorkError::other("model lock"))?;
            if held.is_none() {
                *held = pipeline::load_model(&self.store).map_err(WorkError::other)?;
            }
            held.clone()
        } else {
            None
        };
        let spec = FeatureSpec::new(&self.location, set, false, model.as_deref());
        Ok(OpenedFeatures {
            store: self.store.clone(),
            model,
            set: set.clone(),
            spec,
            model_bytes: None,
        })
    }

    /// The store reopened (after a step that published new labels).
    fn refresh(&mut self) -> PyResult<()> {
        let store = BrickStore::open(&self.location).map_err(|e| bad_argument(e.to_string()))?;
        self.store = Arc::new(store);
        Ok(())
    }
}

#[pymethods]
impl Store {
    /// Opens an existing brick store (a folder, `.zarr`, or `s3://bucket/prefix.zarr`).
    #[staticmethod]
    fn open(py: Python<'_>, path: PathBuf) -> PyResult<Store> {
        detached(py, None, move |_| Store::opened(path))
    }

    /// Ingests a volume file (NIfTI, NRRD, OME-Zarr) into a new store at `store` and opens it.
    #[staticmethod]
    #[pyo3(signature = (source, store, brick=64, force=false, progress=None))]
    fn ingest(
        py: Python<'_>,
        source: PathBuf,
        store: PathBuf,
        brick: usize,
        force: bool,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Store> {
        detached(py, progress, move |ctl| {
            let mut src =
                neuvolex_bricks::open_volume(&source, None).map_err(|e| WorkError::bricks(&e))?;
            let opts = neuvolex_ingest::IngestOptions {
                brick,
                overwrite: force,
                ..Default::default()
            };
            neuvolex_ingest::ingest(
                src.as_mut(),
                &store,
                &opts,
                &mut brick_progress(ctl, "ingest"),
            )
            .map_err(|e| WorkError::ingest(&e))?;
            Store::opened(store)
        })
    }

    /// Ingests a C-ordered 3-D numpy array (`[z, y, x]`, read in place) with the given
    /// spacing and voxel-to-world affine (both in x, y, z order) into a new store.
    #[staticmethod]
    #[pyo3(signature = (array, spacing, affine, store, brick=64, force=false, progress=None))]
    #[allow(clippy::too_many_arguments)]
    fn from_array(
        py: Python<'_>,
        array: &Bound<'_, PyAny>,
        spacing: [f64; 3],
        affine: [[f64; 4]; 4],
        store: PathBuf,
        brick: usize,
        force: bool,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Store> {
        let vol = VolumeArray::extract(array, "array")?;
        let mut meta = VolumeMeta::new(vol.dims, vol.dtype);
        meta.spacing = spacing;
        meta.affine = affine;
        meta.validate(std::path::Path::new("array"))
            .map_err(|e| bad_argument(e.to_string()))?;
        let bytes = vol.bytes();
        detached(py, progress, move |ctl| {
            let mut src = arrays::BorrowedVolume::new(meta, bytes);
            let opts = neuvolex_ingest::IngestOptions {
                brick,
                overwrite: force,
                ..Default::default()
            };
            neuvolex_ingest::ingest(&mut src, &store, &opts, &mut brick_progress(ctl, "ingest"))
                .map_err(|e| WorkError::ingest(&e))?;
            Store::opened(store)
        })
    }

    /// Ingests a volume that `reader(z0, depth)` hands over slab by slab (a C-ordered numpy
    /// array `[depth, y, x]` of `dtype` each call), never whole: dask, zarr or memory-mapped
    /// arrays larger than memory. `shape` is `[z, y, x]`; spacing and affine as `from_array`.
    #[staticmethod]
    #[pyo3(signature = (reader, shape, dtype, spacing, affine, store, brick=64, force=false,
        progress=None))]
    #[allow(clippy::too_many_arguments)]
    fn from_slabs(
        py: Python<'_>,
        reader: Py<PyAny>,
        shape: [usize; 3],
        dtype: &str,
        spacing: [f64; 3],
        affine: [[f64; 4]; 4],
        store: PathBuf,
        brick: usize,
        force: bool,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Store> {
        use neuvolex_formats::DType as D;
        let dt = match dtype {
            "uint8" => D::U8,
            "int8" => D::I8,
            "uint16" => D::U16,
            "int16" => D::I16,
            "uint32" => D::U32,
            "int32" => D::I32,
            "float32" => D::F32,
            "float64" => D::F64,
            o => {
                return Err(bad_argument(format!(
                    "array: dtype {o} is not supported (uint8, int8, uint16, int16, uint32, \
                     int32, float32, float64)"
                )))
            }
        };
        if shape.contains(&0) {
            return Err(bad_argument(format!(
                "array: shape {shape:?} has an empty axis"
            )));
        }
        let mut meta = VolumeMeta::new([shape[2], shape[1], shape[0]], dt);
        meta.spacing = spacing;
        meta.affine = affine;
        meta.validate(std::path::Path::new("array"))
            .map_err(|e| bad_argument(e.to_string()))?;
        detached(py, progress, move |ctl| {
            let mut src = arrays::PySlabs::new(meta, reader);
            let opts = neuvolex_ingest::IngestOptions {
                brick,
                overwrite: force,
                ..Default::default()
            };
            neuvolex_ingest::ingest(&mut src, &store, &opts, &mut brick_progress(ctl, "ingest"))
                .map_err(|e| WorkError::ingest(&e))?;
            Store::opened(store)
        })
    }

    /// Writes the generated phantom (an abdomen-like CT, `size` voxels wide) with its ground
    /// truth as label image `ground_truth` into a new store at `store` and opens it.
    #[staticmethod]
    #[pyo3(signature = (store, size=96, seed=0, brick=32, force=false))]
    fn phantom(
        py: Python<'_>,
        store: PathBuf,
        size: usize,
        seed: u64,
        brick: usize,
        force: bool,
    ) -> PyResult<Store> {
        if !(8..=2048).contains(&size) {
            return Err(bad_argument(format!("size {size}: must be 8..=2048")));
        }
        detached(py, None, move |ctl| {
            let opts = neuvolex_ingest::IngestOptions {
                brick,
                overwrite: force,
                ..Default::default()
            };
            neuvolex_ingest::phantom_store(
                &store,
                neuvolex_bricks::synth::PhantomParams::with_size(size, seed),
                &opts,
                &mut brick_progress(ctl, "phantom"),
            )
            .map_err(|e| WorkError::bricks(&e))?;
            Store::opened(store)
        })
    }

    /// The names of the store's label images.
    #[getter]
    fn label_names(&self) -> Vec<String> {
        self.store.info().labels.clone()
    }

    /// Label image `name` of the store, flat (x fastest).
    fn read_labels<'py>(
        &self,
        py: Python<'py>,
        name: &str,
    ) -> PyResult<Bound<'py, numpy::PyArray1<u32>>> {
        if !self.store.info().labels.iter().any(|l| l == name) {
            return Err(bad_argument(format!(
                "labels '{name}': the store has {:?}",
                self.store.info().labels
            )));
        }
        let store = self.store.clone();
        let name = name.to_string();
        let v = detached(py, None, move |_| {
            let dims = store.info().dims;
            store
                .read_labels_box(&name, [0, 0, 0], dims)
                .map_err(|e| WorkError::bricks(&e))
        })?;
        Ok(v.into_pyarray(py))
    }

    /// Where the store is.
    #[getter]
    fn path(&self) -> String {
        self.location.display().to_string()
    }

    /// Voxels along x, y, z.
    #[getter]
    fn dims(&self) -> [usize; 3] {
        self.store.info().dims
    }

    /// Voxel size along x, y, z.
    #[getter]
    fn spacing(&self) -> [f64; 3] {
        self.store.meta().spacing
    }

    /// The voxel (x, y, z) to world affine, row-major 4x4.
    #[getter]
    fn affine(&self) -> [[f64; 4]; 4] {
        self.store.meta().affine
    }

    /// The source's voxel type as numpy names it (`uint8`, `int16`, `float32`, ...).
    #[getter]
    fn dtype(&self) -> &'static str {
        use neuvolex_formats::DType as D;
        match self.store.info().source_dtype {
            D::U8 => "uint8",
            D::I8 => "int8",
            D::U16 => "uint16",
            D::I16 => "int16",
            D::U32 => "uint32",
            D::I32 => "int32",
            D::F32 => "float32",
            D::F64 => "float64",
        }
    }

    /// The brick edge in voxels.
    #[getter]
    fn brick(&self) -> usize {
        self.store.info().brick
    }

    /// Bricks along x, y, z.
    #[getter]
    fn grid(&self) -> [usize; 3] {
        self.store.info().grid()
    }

    /// The value range `(min, max)` of the volume.
    #[getter]
    fn range(&self) -> (f64, f64) {
        let s = &self.store.info().stats;
        (s.min, s.max)
    }

    /// Whether the store has a trained INR.
    #[getter]
    fn trained(&self) -> bool {
        neuvolex_features::train::model_path(&self.store).exists()
    }

    /// The volume's values (scaled), flat, x fastest.
    #[pyo3(signature = (progress=None))]
    fn read<'py>(
        &self,
        py: Python<'py>,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, numpy::PyArray1<f32>>> {
        let loc = self.location.clone();
        let v = detached(py, progress, move |ctl| {
            let mut src =
                neuvolex_bricks::open_volume(&loc, None).map_err(|e| WorkError::bricks(&e))?;
            let meta = src.meta().clone();
            let slice = meta.slice_len();
            let mut out = vec![0f32; meta.voxels() as usize];
            let depth = ((8 << 20) / slice.max(1)).max(1);
            let mut z = 0;
            while z < meta.dims[2] {
                if ctl.cancelled() {
                    return Err(WorkError::Other("cancelled".into()));
                }
                let d = depth.min(meta.dims[2] - z);
                let slab = src.read_slab(z, d).map_err(WorkError::other)?;
                out[z * slice..(z + d) * slice].copy_from_slice(&slab.to_f32_scaled(&meta));
                src.release(z, d);
                z += d;
                ctl.progress(z as u64, meta.dims[2] as u64, "read");
            }
            Ok(out)
        })?;
        Ok(v.into_pyarray(py))
    }

    /// Trains the INR (CPU engine): a preset (`fast`, `balanced`, `paper`), optionally a
    /// budget in epochs or seconds. Returns a JSON report.
    #[pyo3(signature = (preset="fast", epochs=None, seconds=None, seed=0, progress=None))]
    fn train(
        &self,
        py: Python<'_>,
        preset: &str,
        epochs: Option<f64>,
        seconds: Option<f64>,
        seed: u64,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<String> {
        use neuvolex_features::{Budget, InrConfig, Preset, TrainConfig, TrainEvent};
        let p: Preset = preset
            .parse()
            .map_err(|e: String| bad_argument(format!("preset '{preset}': {e}")))?;
        for (name, v) in [("epochs", epochs), ("seconds", seconds)] {
            if let Some(v) = v {
                if !(v > 0.0 && v.is_finite()) {
                    return Err(bad_argument(format!(
                        "{name} {v}: must be a positive number"
                    )));
                }
            }
        }
        let mut cfg = TrainConfig::preset(p);
        if epochs.is_some() || seconds.is_some() {
            cfg.budget = Budget {
                epochs,
                samples: None,
                seconds,
            };
        }
        cfg.seed = seed;
        let ms_budget = seconds.map_or(0, |s| (s * 1e3) as u64);
        let store = self.store.clone();
        detached(py, progress, move |ctl| {
            let _lock = store
                .writer_lock("train")
                .map_err(|e| WorkError::bricks(&e))?;
            let ckpt = neuvolex_features::train::checkpoint_path(&store);
            // Progress in samples against the budget; a budget in seconds only counts
            // milliseconds instead.
            let mut budget = 0;
            let mut events = |e: TrainEvent| match e {
                TrainEvent::Started { budget_samples, .. } => {
                    budget = budget_samples.unwrap_or(0);
                    let of = if budget > 0 { budget } else { ms_budget };
                    ctl.progress(0, of, "train");
                }
                TrainEvent::Step {
                    samples,
                    psnr,
                    seconds,
                    ..
                } => {
                    let msg = format!("train: PSNR {psnr:.2} dB, {samples} samples");
                    if budget == 0 && ms_budget > 0 {
                        ctl.progress(((seconds * 1e3) as u64).min(ms_budget), ms_budget, msg)
                    } else {
                        ctl.progress(samples, budget, msg)
                    }
                }
                _ => {}
            };
            let t = neuvolex_features::train(
                &store,
                &InrConfig::default(),
                &cfg,
                None,
                Some(&ckpt),
                &ctl.cancel,
                &mut events,
            )
            .map_err(WorkError::other)?;
            if ctl.cancelled() {
                return Err(WorkError::Other("training cancelled".into()));
            }
            let path = neuvolex_features::train::model_path(&store);
            neuvolex_features::checkpoint::save(&path, &t.model, None).map_err(WorkError::other)?;
            if let Ok(mut held) = self.model.lock() {
                *held = Some(Arc::new(t.model));
            }
            Ok(serde_json::json!({
                "model": path.to_string(),
                "psnr": t.psnr,
                "samples": t.state.samples,
                "steps": t.state.step,
                "seconds": t.state.seconds,
            })
            .to_string())
        })
    }

    /// Channels per voxel of a feature set.
    fn feature_channels(&self, py: Python<'_>, features: &str) -> PyResult<usize> {
        let set = feature_set(features)?;
        let src = detached(py, None, |_| self.features_of(&set))?;
        let fx = src.features().map_err(|e| bad_argument(e.to_string()))?;
        Ok(fx.channels())
    }

    /// The features of brick `(bx, by, bz)`: flat, voxel-major (x fastest), channels
    /// innermost; and the brick's size (x, y, z).
    fn feature_brick<'py>(
        &self,
        py: Python<'py>,
        features: &str,
        index: [usize; 3],
    ) -> PyResult<(Bound<'py, numpy::PyArray1<f32>>, [usize; 3])> {
        let set = feature_set(features)?;
        let b = self
            .store
            .brick(index)
            .map_err(|e| bad_argument(format!("brick {index:?}: {e}")))?;
        let size = b.size;
        let v = detached(py, None, |_| {
            let src = self.features_of(&set)?;
            let fx = BrickFeatures::new(&src.store, set.clone(), src.model.clone(), false)
                .map_err(WorkError::value)?;
            fx.brick(&b).map_err(WorkError::other)
        })?;
        Ok((v.into_pyarray(py), size))
    }

    /// Classifies every voxel from scribbles (the `neuvolex classify` pipeline), a function of
    /// its arguments only: returns the label image (flat, x fastest, after the prior), the
    /// class probabilities (flat, voxel-major: channels innermost), the label of each
    /// probability channel and the JSON report. The settings are checked as the CLI checks
    /// them; the Python layer passes [`defaults`] where the caller gives none.
    #[pyo3(signature = (scribbles, features, prior, trees, seed, tau, min_split, class_weight,
        background, prior_mass, prior_grow, probabilities, progress=None))]
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn classify<'py>(
        &mut self,
        py: Python<'py>,
        scribbles: &Bound<'py, PyAny>,
        features: &str,
        prior: bool,
        trees: usize,
        seed: u64,
        tau: f32,
        min_split: usize,
        class_weight: &str,
        background: u32,
        prior_mass: Option<f64>,
        prior_grow: Option<u32>,
        probabilities: bool,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Classified<'py>> {
        let s = Settings::new(
            features,
            prior,
            trees,
            seed,
            tau,
            min_split,
            class_weight,
            background,
            prior_mass,
            prior_grow,
        )?;
        let scr = ScribbleArray::extract(scribbles, "scribbles", self.store.info().dims)?;
        let o = self.run_classify(py, scr, &s, probabilities, progress)?;
        Ok(o.into_py(py))
    }

    /// The forest's labels on one slice before the rest of the volume (and before the
    /// spatial prior): the same forest as `classify` with these settings, only the bricks
    /// crossing the slice read. Returns the plane (flat, the lower remaining axis fastest)
    /// and its size.
    #[pyo3(signature = (scribbles, axis, index, features, trees, seed, tau, min_split,
        class_weight, background))]
    #[allow(clippy::too_many_arguments)]
    fn preview_slice<'py>(
        &self,
        py: Python<'py>,
        scribbles: &Bound<'py, PyAny>,
        axis: &str,
        index: usize,
        features: &str,
        trees: usize,
        seed: u64,
        tau: f32,
        min_split: usize,
        class_weight: &str,
        background: u32,
    ) -> PyResult<(Bound<'py, numpy::PyArray1<u16>>, [usize; 2])> {
        let config = classify_config(trees, min_split, seed, class_weight, tau, background)?;
        self.run_preview(py, scribbles, axis, index, features, config, None)
    }

    /// The most doubtful slice along `axis` (`x`, `y` or `z`) under the last classification's
    /// probabilities, skipping near `visited`: `(index, score)`, or `None` before any.
    #[pyo3(signature = (axis="z", visited=Vec::new()))]
    fn suggest_slice(
        &self,
        py: Python<'_>,
        axis: &str,
        visited: Vec<usize>,
    ) -> PyResult<Option<(usize, f64)>> {
        let a = axis_index(axis)?;
        let store = self.store.clone();
        detached(py, None, move |_| {
            let Ok(va) = store.open_vectors(pipeline::PROBA) else {
                return Ok(None);
            };
            let dims = store.info().dims;
            let c = va.info().channels;
            let mut mass = SliceMass::zeros(dims, c);
            for b in store.bricks() {
                let p = va.read_brick(&b).map_err(WorkError::other)?;
                mass.merge(&SliceMass::of_brick(dims, b.origin, b.size, &p, c));
            }
            Ok(mass.suggest(a, &visited).map(|s| (s.slice, s.share)))
        })
    }

    /// Recommended viewpoints: k-means on the features, view entropy over `views` directions,
    /// greedy complementary selection. Returns the JSON list of selected views.
    #[pyo3(signature = (k=8, features="filters+xyz", views=1800, max_views=6, seed=0, progress=None))]
    #[allow(clippy::too_many_arguments)]
    fn viewpoints(
        &self,
        py: Python<'_>,
        k: usize,
        features: &str,
        views: usize,
        max_views: usize,
        seed: u64,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<String> {
        use neuvolex_viewpoints::scores::SelectConfig;
        use neuvolex_viewpoints::{direction_to_view, KMeansConfig, RecommendConfig};
        if k == 0 || k > u16::MAX as usize {
            return Err(bad_argument(format!("k {k}: must be 1..=65535")));
        }
        if views == 0 || views > 1_000_000 {
            return Err(bad_argument(format!("views {views}: must be 1..=1000000")));
        }
        if max_views == 0 {
            return Err(bad_argument("max_views 0: must be at least 1"));
        }
        let set = feature_set(features)?;
        let cfg = RecommendConfig {
            kmeans: KMeansConfig {
                k,
                seed,
                ..Default::default()
            },
            views,
            select: SelectConfig {
                max_views,
                ..Default::default()
            },
        };
        detached(py, progress, |ctl| {
            let src = self.features_of(&set)?;
            let (rec, _) = neuvolex_viewpoints::distributed::recommend_on(
                &executor(ctl),
                src,
                &cfg,
                1,
                &mut task_progress(ctl),
                &mut |_, _| {},
            )
            .map_err(WorkError::value)?;
            if ctl.cancelled() {
                return Err(WorkError::Other("viewpoints cancelled".into()));
            }
            let (scores, sel) = (&rec.scores, &rec.selection);
            let out: Vec<serde_json::Value> = sel
                .views
                .iter()
                .zip(&sel.gains)
                .map(|(&i, &g)| {
                    let (az, el) = direction_to_view(scores.views[i]);
                    serde_json::json!({"azimuth": az, "elevation": el,
                        "direction": scores.views[i], "entropy": scores.entropy[i], "gain": g})
                })
                .collect();
            Ok(serde_json::Value::from(out).to_string())
        })
    }

    /// Writes `labels` (flat, x fastest; default: the last classification) as a NIfTI label
    /// volume with the store's geometry (affine, spacing, NIfTI frames).
    #[pyo3(signature = (path, labels=None, force=false))]
    fn export(
        &self,
        py: Python<'_>,
        path: PathBuf,
        labels: Option<&Bound<'_, PyAny>>,
        force: bool,
    ) -> PyResult<()> {
        if path.exists() && !force {
            return Err(bad_argument(format!(
                "{}: exists (pass force=True to replace it)",
                path.display()
            )));
        }
        let lab = labels
            .map(|l| ScribbleArray::extract(l, "labels", self.store.info().dims))
            .transpose()?;
        let store = self.store.clone();
        detached(py, None, move |_| {
            let meta = store.meta();
            match lab {
                Some(l) => {
                    let mut v = l.label_volume(&meta);
                    neuvolex_formats::nifti::write_nifti(&path, &mut v, 64)
                        .map_err(WorkError::other)
                }
                None => {
                    let img = store.root().join("labels").join("classified");
                    let mut src = neuvolex_bricks::open_volume(&img, None).map_err(|_| {
                        WorkError::Value(format!(
                            "{}: no classification to export yet (classify first, or pass labels)",
                            store.root().display()
                        ))
                    })?;
                    neuvolex_formats::nifti::write_nifti(&path, src.as_mut(), 64)
                        .map_err(WorkError::other)
                }
            }
        })
    }

    /// Writes a label array (flat, x fastest) into the store as label image `name`.
    fn write_labels(
        &mut self,
        py: Python<'_>,
        name: &str,
        labels: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let lab = ScribbleArray::extract(labels, "labels", self.store.info().dims)?;
        let loc = self.location.clone();
        let name = name.to_string();
        detached(py, None, move |_| {
            let mut store = BrickStore::open(&loc).map_err(|e| WorkError::bricks(&e))?;
            let mut v = lab.label_volume(&store.meta());
            let classes: Vec<neuvolex_bricks::synth::ClassInfo> = lab
                .classes()
                .into_iter()
                .map(|id| neuvolex_bricks::synth::ClassInfo {
                    id,
                    name: format!("class_{id}"),
                    color: neuvolex_bricks::synth::palette(id),
                })
                .collect();
            store
                .add_labels(&name, &mut v, &classes, &mut |_| {})
                .map_err(|e| WorkError::bricks(&e))
        })?;
        self.refresh()
    }

    /// Renders the volume: intensity with a transfer function, or as colours a label image
    /// of the store (`labels`), labels in memory (`label_array`, an integer array `[z, y, x]`,
    /// not saved anywhere) or the last classification's probabilities (`probabilities`).
    /// Returns RGBA bytes (rows top first).
    #[pyo3(signature = (labels=None, probabilities=false, azimuth=30.0, elevation=20.0,
        width=512, height=512, tf=None, mode=None, label_array=None))]
    #[allow(clippy::too_many_arguments)]
    fn render<'py>(
        &self,
        py: Python<'py>,
        labels: Option<&str>,
        probabilities: bool,
        azimuth: f32,
        elevation: f32,
        width: usize,
        height: usize,
        tf: Option<&str>,
        mode: Option<&str>,
        label_array: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, numpy::PyArray1<u8>>> {
        let memory = label_array
            .map(|a| ScribbleArray::extract(a, "labels", self.store.info().dims))
            .transpose()?
            .map(|a| Arc::new(a.dense()));
        let coloured = probabilities || labels.is_some() || memory.is_some();
        let mode =
            Mode::from_name(mode, coloured).map_err(|e| bad_argument(format!("mode {e}")))?;
        if mode.needs_probs() && !coloured {
            return Err(bad_argument(format!(
                "mode {mode:?} needs labels or probabilities"
            )));
        }
        let p = RenderParams {
            width,
            height,
            camera: Camera {
                azimuth,
                elevation,
                ..Camera::default()
            },
            mode,
            ..RenderParams::default()
        };
        p.validate()
            .map_err(|e| bad_argument(format!("render: {e}")))?;
        let tf = match tf {
            Some(t) => TfFile::from_arg(t).map_err(|e| bad_argument(format!("tf: {e}")))?,
            None => TfFile::preset(TfFile::default_preset(self.store.info().stats.min))
                .map_err(|e| bad_argument(e.to_string()))?,
        };
        let store = self.store.clone();
        let labels = labels.map(str::to_string);
        let rgba = detached(py, None, move |_| {
            let mut src = StoreSource::new(store);
            if probabilities {
                src = src.with_vectors(pipeline::PROBA).map_err(|_| {
                    WorkError::Value("probabilities: no classification yet (classify first)".into())
                })?;
            }
            if let Some(l) = &labels {
                src = src
                    .with_labels(l)
                    .map_err(|e| WorkError::Value(format!("labels '{l}': {e}")))?;
            }
            if let Some(l) = memory {
                src = src.with_label_array(l).map_err(WorkError::value)?;
            }
            let luts = tf.compile(&src.normaliser(), &src.classes());
            let img = Renderer::new(src, 1 << 30)
                .render(&p, &luts)
                .map_err(WorkError::other)?;
            let rgb = img.to_rgb8();
            let mut out = Vec::with_capacity(img.width * img.height * 4);
            for (px, a) in rgb.chunks(3).zip(&img.alpha) {
                out.extend_from_slice(px);
                out.push((a.clamp(0.0, 1.0) * 255.0).round() as u8);
            }
            Ok(out)
        })?;
        Ok(rgba.into_pyarray(py))
    }

    fn __repr__(&self) -> String {
        let i = self.store.info();
        format!(
            "Store('{}', dims (x, y, z) {:?}, {:?}, brick {})",
            self.location.display(),
            i.dims,
            i.source_dtype,
            i.brick
        )
    }
}

/// What `classify` returns to Python: the labels, the probabilities (or `None`), the label
/// of each probability channel, and the JSON report.
type Classified<'py> = (
    Bound<'py, PyAny>,
    Option<Bound<'py, numpy::PyArray1<f32>>>,
    Vec<u32>,
    String,
);

/// The settings of one classification, checked.
struct Settings {
    set: FeatureSet,
    config: ClassifyConfig,
    prior: Option<PriorConfig>,
    /// What a held result must share (the model's identity is added once known).
    key: String,
}

impl Settings {
    #[allow(clippy::too_many_arguments)]
    fn new(
        features: &str,
        prior: bool,
        trees: usize,
        seed: u64,
        tau: f32,
        min_split: usize,
        class_weight: &str,
        background: u32,
        prior_mass: Option<f64>,
        prior_grow: Option<u32>,
    ) -> PyResult<Settings> {
        let set = feature_set(features)?;
        let config = classify_config(trees, min_split, seed, class_weight, tau, background)?;
        let defaults = PriorConfig::default();
        let prior = if prior {
            let mass = prior_mass.unwrap_or(defaults.relative_mass);
            let grow = prior_grow.unwrap_or(defaults.grow);
            Some(
                PriorConfig::new(mass)
                    .map_err(|e| bad_argument(format!("prior_mass {mass}: {e}")))?
                    .with_grow(grow)
                    .map_err(|e| bad_argument(format!("prior_grow {grow}: {e}")))?,
            )
        } else {
            None
        };
        let key = format!(
            "{set}|{config:?}|{prior:?}",
            config = (trees, min_split, seed, class_weight, tau, background)
        );
        Ok(Settings {
            set,
            config,
            prior,
            key,
        })
    }
}

/// A classification's results, before they become numpy arrays.
struct Outcome {
    labels: Vec<u16>,
    proba: Option<Vec<f32>>,
    classes: Vec<u32>,
    report: String,
}

impl Outcome {
    /// As Python values: labels in the smallest unsigned type that holds them.
    fn into_py(self, py: Python<'_>) -> Classified<'_> {
        Outcome::py_values(py, self.labels, self.proba, self.classes, self.report)
    }

    /// [`Outcome::into_py`] of the parts.
    fn py_values(
        py: Python<'_>,
        labels: Vec<u16>,
        proba: Option<Vec<f32>>,
        classes: Vec<u32>,
        report: String,
    ) -> Classified<'_> {
        let max = labels.iter().copied().max().unwrap_or(0);
        let labels: Bound<'_, PyAny> = if max <= 255 {
            let v: Vec<u8> = labels.iter().map(|&l| l as u8).collect();
            v.into_pyarray(py).into_any()
        } else {
            labels.into_pyarray(py).into_any()
        };
        (labels, proba.map(|p| p.into_pyarray(py)), classes, report)
    }
}

/// The class probabilities the last run wrote, voxel-major (x fastest, channels innermost):
/// the package's one channel convention, `[z, y, x, channel]`.
fn probabilities_last(store: &BrickStore) -> Result<Vec<f32>, WorkError> {
    let va = store
        .open_vectors(pipeline::PROBA)
        .map_err(|e| WorkError::bricks(&e))?;
    let c = va.info().channels;
    let dims = store.info().dims;
    let n: usize = dims.iter().product();
    let mut out = vec![0f32; n * c];
    for b in store.bricks() {
        let p = va.read_brick(&b).map_err(|e| WorkError::bricks(&e))?;
        let w = b.size[0];
        for (k, row) in b.rows(dims).enumerate() {
            out[row * c..(row + w) * c].copy_from_slice(&p[k * w * c..(k + 1) * w * c]);
        }
    }
    Ok(out)
}

impl Store {
    /// The identity of the model `set` reads ('' when it needs none).
    fn model_key(&self, set: &FeatureSet) -> Result<String, WorkError> {
        Ok(self.features_of(set)?.model.map_or_else(String::new, |m| {
            neuvolex_features::stage::model_identity(&m)
        }))
    }

    /// Runs the `neuvolex classify` pipeline on `scr` with settings `s` (its outputs written
    /// into the store as its last classification).
    fn run_classify(
        &mut self,
        py: Python<'_>,
        scr: ScribbleArray,
        s: &Settings,
        probabilities: bool,
        progress: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Outcome> {
        let req = ClassifyRequest {
            store: self.location.clone(),
            scribbles: PathBuf::from("scribbles"),
            features: s.set.clone(),
            classes: None,
            out: None,
            force: false,
            stored_features: false,
            config: s.config.clone(),
            bricks_per_task: 1,
            prior: s.prior,
            hold: None,
            gpu: false,
        };
        let (o, proba, store) = detached(py, progress, |ctl| {
            let scr = scr.scribbles();
            // An earlier call stopped half way (Ctrl-C) left pending outputs of its own
            // scribbles: a new call starts over instead of being refused.
            for name in [pipeline::PROBA, pipeline::LABELS] {
                self.store
                    .discard_pending_vectors(name)
                    .map_err(|e| WorkError::bricks(&e))?;
            }
            let o =
                pipeline::classify_scribbles(&req, scr, &executor(ctl), &mut task_progress(ctl))
                    .map_err(|e| match e {
                        // The "file" of in-memory scribbles is the caller's argument.
                        neuvolex_classify::ClassifyError::File { ref path, .. }
                            if *path == req.scribbles =>
                        {
                            WorkError::value(e)
                        }
                        e => WorkError::classify(&e),
                    })?;
            if !o.dead.is_empty() || o.labels.is_empty() {
                return Err(WorkError::Other(if ctl.cancelled() {
                    "classification cancelled".into()
                } else {
                    format!("classification failed: {:?}", o.dead)
                }));
            }
            // The store as the run left it: this handle serves the next calls.
            let store = BrickStore::open(&req.store).map_err(|e| WorkError::bricks(&e))?;
            let proba = if probabilities {
                Some(probabilities_last(&store)?)
            } else {
                None
            };
            Ok((o, proba, store))
        })?;
        self.store = Arc::new(store);
        let report = serde_json::to_string(&o.report)
            .map_err(|e| run::raise(py, "NeuvolexRuntimeError", e.to_string()))?;
        Ok(Outcome {
            classes: o.report.labels.clone(),
            labels: o.labels,
            proba,
            report,
        })
    }

    /// The forest's labels on one slice (see [`Store::preview_slice`]), its features through
    /// `memo` when given.
    #[allow(clippy::too_many_arguments)]
    fn run_preview<'py>(
        &self,
        py: Python<'py>,
        scribbles: &Bound<'py, PyAny>,
        axis: &str,
        index: usize,
        features: &str,
        config: ClassifyConfig,
        memo: Option<&Arc<KeptFeatures>>,
    ) -> PyResult<(Bound<'py, numpy::PyArray1<u16>>, [usize; 2])> {
        let a = axis_index(axis)?;
        let dims = self.store.info().dims;
        if index >= dims[a] {
            return Err(bad_argument(format!(
                "index {index}: the volume has {} slices along {axis}",
                dims[a]
            )));
        }
        let set = feature_set(features)?;
        let scr = ScribbleArray::extract(scribbles, "scribbles", dims)?;
        let plane = detached(py, None, |ctl| {
            let src = self.features_of(&set)?;
            let mut fx = src.features().map_err(|e| WorkError::classify(&e))?;
            if let Some(m) = memo {
                fx.set_memo(Some(m.memo(format!("{set}|{}", self.model_key(&set)?))));
            }
            let scr = scr.scribbles();
            let cancel = ctl.cancel.clone();
            neuvolex_classify::preview::preview_plane(&fx, &scr, &config, a, index, &move || {
                cancel.load(std::sync::atomic::Ordering::SeqCst)
            })
            .map_err(|e| match e {
                neuvolex_classify::ClassifyError::Volume(e) => WorkError::bricks(&e),
                e => WorkError::value(format!("scribbles: {e}")),
            })
        })?;
        Ok((plane.labels.into_pyarray(py), plane.size))
    }
}

/// A series of interactive rounds on one store, run in memory ([`neuvolex_classify::round`]):
/// each `classify` holds to the labels the session showed last with the stability rule of
/// [`neuvolex_classify::stable`], the feature bricks it computed are kept (f16) for the next
/// rounds, and nothing is written into the store.
#[pyclass(module = "neuvolex._native")]
struct Session {
    store: Py<Store>,
    kept: Arc<KeptFeatures>,
    shown: Option<Shown>,
    /// The last round's u8 probabilities (voxel-major) and their channels.
    proba: Option<(Vec<u8>, usize)>,
    rule: neuvolex_classify::StableConfig,
}

#[pymethods]
impl Session {
    /// A session on `store`: the rule's `delta` (`None`: the rule's default), and at most
    /// `cache_bytes` of features kept.
    #[new]
    #[pyo3(signature = (store, delta=None, cache_bytes=1 << 30))]
    fn new(store: Py<Store>, delta: Option<f32>, cache_bytes: usize) -> PyResult<Session> {
        let mut rule = neuvolex_classify::StableConfig::default();
        if let Some(d) = delta {
            if !(0.0..=1.0).contains(&d) {
                return Err(bad_argument(format!("delta {d}: must be between 0 and 1")));
            }
            rule.delta = d;
        }
        Ok(Session {
            store,
            kept: Arc::new(KeptFeatures::new(cache_bytes)),
            shown: None,
            proba: None,
            rule,
        })
    }

    /// The store.
    #[getter]
    fn store(&self, py: Python<'_>) -> Py<Store> {
        self.store.clone_ref(py)
    }

    /// The stability rule's `delta`.
    #[getter]
    fn delta(&self) -> f32 {
        self.rule.delta
    }

    /// Bytes of feature bricks kept.
    #[getter]
    fn cached_bytes(&self) -> usize {
        self.kept.used()
    }

    /// One round, in memory ([`neuvolex_classify::round`]): [`Store::classify`]'s forest,
    /// labels, prior and report on the kept features rounded to f16, the probabilities in u8
    /// steps, holding to the labels of the session's last round when the scribbles extend its
    /// scribbles and the settings and model are the same; nothing is written into the store.
    #[pyo3(signature = (scribbles, features, prior, trees, seed, tau, min_split, class_weight,
        background, prior_mass, prior_grow, probabilities, progress=None))]
    #[allow(clippy::too_many_arguments)]
    fn classify<'py>(
        &mut self,
        py: Python<'py>,
        scribbles: &Bound<'py, PyAny>,
        features: &str,
        prior: bool,
        trees: usize,
        seed: u64,
        tau: f32,
        min_split: usize,
        class_weight: &str,
        background: u32,
        prior_mass: Option<f64>,
        prior_grow: Option<u32>,
        probabilities: bool,
        progress: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Classified<'py>> {
        let s = Settings::new(
            features,
            prior,
            trees,
            seed,
            tau,
            min_split,
            class_weight,
            background,
            prior_mass,
            prior_grow,
        )?;
        let store = self.store.bind(py).try_borrow()?;
        let scr = ScribbleArray::extract(scribbles, "scribbles", store.store.info().dims)?;
        let st: &Store = &store;
        let (shown, rule, kept) = (self.shown.as_ref(), self.rule, &self.kept);
        let (r, key, scr) = detached(py, progress, |ctl| {
            let src = st.features_of(&s.set)?;
            let model = src
                .model
                .as_deref()
                .map_or_else(String::new, neuvolex_features::stage::model_identity);
            let key = format!("{}|{model}", s.key);
            // The last round, when made with these settings and model (the rule checks that
            // the scribbles extend its scribbles).
            let hold = shown
                .filter(|sh| sh.key == key)
                .map(|sh| neuvolex_classify::stable::Hold {
                    scribbles: sh.scribbles.clone(),
                    labels: sh.labels.clone(),
                    config: rule,
                    verdicts: sh.verdicts.clone(),
                });
            let fx = src.features().map_err(|e| WorkError::classify(&e))?;
            let scr = scr.scribbles();
            let req = RoundRequest {
                scribbles: &scr,
                config: &s.config,
                prior: s.prior,
                hold: hold.as_ref(),
            };
            let cancel = ctl.cancel.clone();
            let r = round::classify_round(
                &fx,
                kept,
                &format!("{}|{model}", s.set),
                &req,
                &move || cancel.load(std::sync::atomic::Ordering::SeqCst),
                &|done, total| ctl.progress(done as u64, total as u64, "classify"),
            )
            .map_err(|e| WorkError::classify(&e))?;
            Ok((r, key, scr))
        })?;
        drop(store);
        let report = serde_json::to_string(&r.report)
            .map_err(|e| run::raise(py, "NeuvolexRuntimeError", e.to_string()))?;
        let classes = r.report.labels.clone();
        // The probabilities as the pipeline stores and `Store.classify` returns them.
        let proba = probabilities.then(|| r.proba.iter().map(|&q| q as f32 / 255.0).collect());
        self.shown = Some(Shown {
            key,
            scribbles: scr,
            labels: r.labels.clone(),
            verdicts: Some(r.verdicts),
        });
        self.proba = Some((r.proba, classes.len()));
        Ok(Outcome::py_values(py, r.labels, proba, classes, report))
    }

    /// The most doubtful slice along `axis` (`x`, `y` or `z`) under the probabilities of the
    /// session's last round, skipping near `visited`: `(index, score)`, or `None` before any.
    #[pyo3(signature = (axis="z", visited=Vec::new()))]
    fn suggest_slice(
        &self,
        py: Python<'_>,
        axis: &str,
        visited: Vec<usize>,
    ) -> PyResult<Option<(usize, f64)>> {
        let a = axis_index(axis)?;
        let dims = self.store.bind(py).try_borrow()?.store.info().dims;
        let Some((p, c)) = &self.proba else {
            return Ok(None);
        };
        let c = *c;
        detached(py, None, move |_| {
            let mass = SliceMass::of_brick(dims, [0, 0, 0], dims, p, c);
            Ok(mass.suggest(a, &visited).map(|s| (s.slice, s.share)))
        })
    }

    /// [`Store::preview_slice`] through the session's kept features.
    #[pyo3(signature = (scribbles, axis, index, features, trees, seed, tau, min_split,
        class_weight, background))]
    #[allow(clippy::too_many_arguments)]
    fn preview_slice<'py>(
        &self,
        py: Python<'py>,
        scribbles: &Bound<'py, PyAny>,
        axis: &str,
        index: usize,
        features: &str,
        trees: usize,
        seed: u64,
        tau: f32,
        min_split: usize,
        class_weight: &str,
        background: u32,
    ) -> PyResult<(Bound<'py, numpy::PyArray1<u16>>, [usize; 2])> {
        let config = classify_config(trees, min_split, seed, class_weight, tau, background)?;
        let store = self.store.bind(py).try_borrow()?;
        store.run_preview(
            py,
            scribbles,
            axis,
            index,
            features,
            config,
            Some(&self.kept),
        )
    }

    /// The last round (what the next one holds to): its settings key, its scribbles as
    /// voxel indices (x fastest) and labels, its label image, and its own decisions (the
    /// forest's labels, the labels after the prior and the forests in a row behind each forest
    /// label, empty where not counted; or `None`), all flat, x fastest; `None` before any round.
    #[allow(clippy::type_complexity)]
    fn history<'py>(
        &self,
        py: Python<'py>,
    ) -> Option<(
        String,
        Bound<'py, numpy::PyArray1<u64>>,
        Bound<'py, numpy::PyArray1<u32>>,
        Bound<'py, numpy::PyArray1<u16>>,
        Option<(
            Bound<'py, numpy::PyArray1<u16>>,
            Bound<'py, numpy::PyArray1<u16>>,
            Bound<'py, numpy::PyArray1<u16>>,
        )>,
    )> {
        self.shown.as_ref().map(|s| {
            let (i, l): (Vec<u64>, Vec<u32>) = s.scribbles.voxels.iter().copied().unzip();
            (
                s.key.clone(),
                i.into_pyarray(py),
                l.into_pyarray(py),
                s.labels.clone().into_pyarray(py),
                s.verdicts.as_ref().map(|v| {
                    (
                        v.forest.clone().into_pyarray(py),
                        v.verdict.clone().into_pyarray(py),
                        v.agree.clone().into_pyarray(py),
                    )
                }),
            )
        })
    }

    /// Restores a round [`Session::history`] gave (a saved session), checked against the
    /// store's grid.
    #[pyo3(signature = (key, index, scribbles, labels, verdicts=None, agree=None))]
    #[allow(clippy::too_many_arguments)]
    fn restore(
        &mut self,
        py: Python<'_>,
        key: String,
        index: Vec<u64>,
        scribbles: Vec<u32>,
        labels: Vec<u16>,
        verdicts: Option<(Vec<u16>, Vec<u16>)>,
        agree: Option<Vec<u16>>,
    ) -> PyResult<()> {
        let dims = self.store.bind(py).try_borrow()?.store.info().dims;
        let n: usize = dims.iter().product();
        if labels.len() != n {
            return Err(run::raise(
                py,
                "FileError",
                format!("labels: {} voxels, the store has {n}", labels.len()),
            ));
        }
        if index.len() != scribbles.len() || index.iter().any(|&i| i as usize >= n) {
            return Err(run::raise(
                py,
                "FileError",
                "scribbles: indices and labels differ in length or lie outside the volume".into(),
            ));
        }
        if verdicts
            .as_ref()
            .is_some_and(|(f, v)| f.len() != n || v.len() != n)
        {
            return Err(run::raise(
                py,
                "FileError",
                format!("verdicts: not {n} voxels each"),
            ));
        }
        let agree = agree.unwrap_or_default();
        if !agree.is_empty() && agree.len() != n {
            return Err(run::raise(
                py,
                "FileError",
                format!("agree: {} voxels, the store has {n}", agree.len()),
            ));
        }
        let voxels: Vec<(u64, u32)> = index.into_iter().zip(scribbles).collect();
        self.shown = Some(Shown {
            key,
            scribbles: ScribbleArray::from_parts(dims, voxels).scribbles(),
            labels,
            verdicts: verdicts.map(
                |(forest, verdict)| neuvolex_classify::stable::RoundVerdicts {
                    forest,
                    verdict,
                    agree,
                },
            ),
        });
        Ok(())
    }

    /// Forgets the last round: the next holds to nothing.
    fn reset(&mut self) {
        self.shown = None;
    }
}

/// The classification defaults of the CLI, the service and the package, from the library's
/// own `Default`s: `features`, `trees`, `min_split`, `seed`, `class_weight`, `tau`,
/// `background`, `prior_mass`, `prior_grow`, and the stability rule's `delta` and `margin`.
#[pyfunction]
fn defaults(py: Python<'_>) -> PyResult<Bound<'_, pyo3::types::PyDict>> {
    let c = ClassifyConfig::default();
    let p = PriorConfig::default();
    let r = neuvolex_classify::StableConfig::default();
    let d = pyo3::types::PyDict::new(py);
    d.set_item("features", neuvolex_classify::DEFAULT_FEATURES)?;
    d.set_item("prior", true)?;
    d.set_item("trees", c.forest.trees)?;
    d.set_item("min_split", c.forest.min_samples_split)?;
    d.set_item("seed", c.forest.seed)?;
    d.set_item(
        "class_weight",
        match c.forest.class_weight {
            ClassWeight::Balanced => "balanced",
            ClassWeight::None => "none",
        },
    )?;
    d.set_item("tau", c.tau)?;
    d.set_item("background", c.background)?;
    d.set_item("prior_mass", p.relative_mass)?;
    d.set_item("prior_grow", p.grow)?;
    d.set_item("delta", r.delta)?;
    d.set_item("margin", r.margin)?;
    Ok(d)
}

/// The native module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Store>()?;
    m.add_class::<Session>()?;
    m.add_function(wrap_pyfunction!(defaults, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
