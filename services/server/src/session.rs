//! A session: one opened volume, its classes and strokes, and the class probabilities that
//! stream in brick by brick.

use crate::error::{ApiError, ApiResult};
use neuvolex_bricks::synth::{palette, ClassInfo};
use neuvolex_bricks::{BrickStore, Normaliser};
use neuvolex_classify::accel::{AccelOptions, Accelerator, BrickPredictor};
use neuvolex_classify::features::{BrickFeatures, FeatureSet};
use neuvolex_classify::persist::PersistedFeatures;
use neuvolex_classify::pipeline::{
    store_path_string, FeatureHook, FeatureSpec, OpenedFeatures, ProbaParams, ProbaStage,
};
use neuvolex_classify::scribble::{rasterise, Scribbles, Stroke};
use neuvolex_classify::shard::{fit, training_set_boxed};
use neuvolex_render::source::{assemble, ChannelClass, RenderBrick};
use neuvolex_render::{BrickSource, StoreSource, VolumeGeom};
use neuvolex_tasks::executor::CancelPoll;
use neuvolex_tasks::{Event, Executor, LocalExecutor};
use serde::Serialize;
use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use crate::cache::{FeatureCache, SessionFeatures};
use neuvolex_features::InrModel;
use neuvolex_session::SessionFile;

/// The feature set the service classifies with (`neuvolex classify --features` defaults to
/// the same).
pub const DEFAULT_FEATURES: &str = "filters+xyz";

/// Forest size of interactive classification on volumes up to [`ROUND_TREE_VOXELS`] / `TREES`
/// predicted voxels.
pub const TREES: usize = 50;

/// The fewest trees a round uses: on the abdomen CT, 32 trees score within 0.012 mean F1 of 50
/// at S1 and S2 (3 seeds), 16 lose up to 0.05 (BENCHMARKS.md, issue 31).
pub const MIN_TREES: usize = 32;

/// Tree-voxel visits one round's prediction makes at most before the forest shrinks: about
/// 1.5 s of the service's prediction on 2 cores (the `rounds` bench measured 60-70 M a second,
/// features read from the cache and converted included).
pub const ROUND_TREE_VOXELS: u64 = 100_000_000;

/// The forest size of a round that predicts `voxels` voxels: [`TREES`], fewer on large volumes
/// so a round stays interactive, never below [`MIN_TREES`].
pub fn trees_for(voxels: u64) -> usize {
    ((ROUND_TREE_VOXELS / voxels.max(1)) as usize).clamp(MIN_TREES, TREES)
}

/// A feature set the page offers, with the trade measured in BENCHMARKS.md (mean F1 over the
/// ROI classes of a one-shot classification, seeds 0-2, 100 trees, the spatial prior on).
#[derive(Debug, Clone, Serialize)]
pub struct FeatureChoice {
    /// The set, as `neuvolex classify --features` writes it.
    pub set: &'static str,
    /// A short name.
    pub label: &'static str,
    /// Whether it needs a trained INR (then every model snapshot re-classifies).
    pub uses_inr: bool,
    /// What it costs and gains.
    pub help: &'static str,
}

/// The feature sets the page offers: the default, the default with the INR's features, and
/// the paper's feature.
pub const FEATURE_CHOICES: [FeatureChoice; 3] = [
    FeatureChoice {
        set: DEFAULT_FEATURES,
        label: "filters + position (default)",
        uses_inr: false,
        help: "Intensity filter bank (50 channels) and position. No training needed. Abdomen CT \
               F1 0.33 with scribbles on 0.03 % of the voxels, 0.50 on 0.07 %; brain MRI 0.27 / \
               0.38 (BENCHMARKS.md, one-shot tables).",
    },
    FeatureChoice {
        set: "hidden+filters+xyz",
        label: "filters + position + INR",
        uses_inr: true,
        help: "The default plus the INR's last hidden layer (64 channels). Needs a trained INR \
               (3 epochs: about 20 s on the abdomen CT); every model snapshot re-classifies. \
               Abdomen CT F1 0.34 / 0.47-0.49: the same as the default within the seed spread, \
               at 2.2x the features per voxel.",
    },
    FeatureChoice {
        set: "paper",
        label: "INR hidden layer (paper)",
        uses_inr: true,
        help: "The INR's last hidden layer alone, as in the paper. Needs a trained INR. Abdomen \
               CT F1 0.21-0.25 / 0.23-0.29: well below the default (it keeps little besides \
               intensity); for comparison with the paper.",
    },
];

/// A model and its version in a session (bumped by every snapshot).
pub type VersionedModel = (u64, Arc<InrModel>);

/// [`DEFAULT_FEATURES`], parsed.
pub fn default_features() -> FeatureSet {
    DEFAULT_FEATURES
        .parse()
        .expect("the default feature set parses")
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The label strokes use for background/other.
pub const BACKGROUND: u32 = neuvolex_session::BACKGROUND;

pub use crate::labels::Probs;

/// Classification progress.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Status {
    /// Stroke generation being (or last) classified.
    pub generation: u64,
    /// idle, training, classifying, done, cancelled or failed.
    pub state: String,
    /// Bricks classified of `total`.
    pub done: usize,
    /// Bricks to classify.
    pub total: usize,
    /// Last message (e.g. why nothing was classified).
    pub message: String,
    /// Feature set used.
    pub features: String,
    /// Where the round's bricks were predicted: `cpu`, `gpu`, `cluster`, or `gpu+cpu` (the
    /// GPU failed during the round and the CPU finished it).
    pub engine: String,
}

/// One opened volume.
pub struct Session {
    /// Id.
    pub id: String,
    /// Path relative to the data root.
    pub name: String,
    /// The store.
    pub store: Arc<BrickStore>,
    /// Classes (ids 1..N; the background 255 is implicit).
    pub classes: RwLock<Vec<ClassInfo>>,
    /// The strokes, as last sent.
    pub strokes: RwLock<Vec<Stroke>>,
    /// Held by whoever changes the strokes, so appends and replacements take turns while
    /// readers are not held up by the validation.
    stroke_writer: Mutex<()>,
    /// Bumped by every stroke update; work for older generations is stale.
    pub generation: AtomicU64,
    /// Probabilities streamed in so far.
    pub probs: RwLock<Probs>,
    /// Classification progress.
    pub status: RwLock<Status>,
    /// Bricks whose probabilities changed since the last render.
    pub dirty: Mutex<BTreeSet<[usize; 3]>>,
    /// Stops the running training, if any.
    pub train_cancel: Mutex<Option<Arc<AtomicBool>>>,
    /// The voxel whose three slices the user has on screen (sent with the strokes): their
    /// bricks are classified right after those of the last stroke.
    pub focus: Mutex<Option<[usize; 3]>>,
    /// When a request last named this session (ms since the Unix epoch): idle sessions are
    /// saved and closed ([`crate::http::AppState::close_idle`]).
    pub last_used: AtomicU64,
    /// Render state (the renderer keeps the last frame for incremental updates).
    pub renderer: Mutex<Option<RenderState>>,
    /// The INR the features come from, with a version bumped by every snapshot the trainer
    /// publishes (`None` until one is trained).
    pub model: RwLock<Option<VersionedModel>>,
    /// The feature set the classification uses ([`DEFAULT_FEATURES`] until the user picks
    /// another, [`Self::set_feature_set`]).
    pub feature_set: RwLock<FeatureSet>,
    /// The feature bricks kept in the store for the set the session opened with (shared
    /// with the other sessions on this store), once [`Self::prepare_features`] opened them.
    stored: Mutex<Option<Arc<PersistedFeatures>>>,
    /// Set when the session closes or the server stops: background work ends.
    pub closing: AtomicBool,
    /// Feature bricks shared by every classification and recommendation of this session (in
    /// the server's one cache, under one budget for all sessions).
    pub features: SessionFeatures,
    /// The session's transfer function (JSON as sent, and parsed); `None` uses a preset.
    pub tf: RwLock<Option<(serde_json::Value, neuvolex_render::TfFile)>>,
    /// The newest training preview: reconstruction beside the input, as PNG, and its PSNR.
    pub preview: RwLock<Option<(Vec<u8>, f64)>>,
    /// Whether the spatial prior filters the labels shown and exported (on by default).
    pub prior_on: AtomicBool,
    /// The prior's verdict on the last complete classification (beside the raw
    /// probabilities, which it never changes).
    pub prior: RwLock<Option<crate::labels::PriorState>>,
    /// The labels every complete round showed, and the one shown now: the base of the
    /// stability rule ([`neuvolex_classify::stable`]) and what undo, redo and a restore show
    /// again ([`crate::labels`]).
    pub labels: Mutex<crate::labels::LabelHistory>,
    /// The undone strokes, the next to redo last (the page's redo stack, saved with the
    /// session).
    pub redo: RwLock<Vec<Stroke>>,
    /// The page's own settings (slice positions, zoom, window/level, ...), saved with the
    /// session as sent.
    pub ui: RwLock<Option<serde_json::Value>>,
    /// Bumped by every change the session file keeps ([`Self::touch`]); the autosave writes
    /// while it differs from what was saved last.
    pub edits: AtomicU64,
    /// The [`Self::edits`] value (and label history revision) the last save wrote.
    pub saved: Mutex<(u64, u64)>,
    /// The current model as a blob for cluster workers (version, identity, bytes).
    model_bytes: Mutex<Option<ModelBlob>>,
    /// The server's session memory: this session's render bricks and probabilities count
    /// against its budgets.
    pub memory: Arc<crate::memory::Memory>,
    /// This session's key in the shared render cache.
    pub render_owner: u64,
    /// Bytes of probabilities this session has reserved in [`Self::memory`].
    probs_reserved: Mutex<usize>,
    /// Where rounds predict when not on a cluster: the server's GPU ([`Self::set_accelerator`];
    /// `None`, the CPU forest).
    accel: RwLock<Option<Arc<dyn Accelerator>>>,
}

type ModelBlob = (u64, String, Arc<Vec<u8>>);

/// A session's renderer and what its last frame was.
pub struct RenderState {
    /// The renderer (keeps the last frame's accumulators).
    pub renderer: neuvolex_render::Renderer<SessionSource>,
    /// Parameters, transfer function and classes of the last frame.
    pub key: String,
    /// What the cached bricks' channels hold: probabilities, or labels of one classification
    /// and prior verdict.
    pub labels: String,
    /// The wgpu renderer, when the service renders on the GPU.
    #[cfg(feature = "gpu")]
    pub gpu: Option<neuvolex_render::gpu::GpuRenderer<SessionSource>>,
}

impl Session {
    /// A session over an opened store, with memory of its own: a feature cache and a render
    /// cache of `cache_bytes` each, and no limit on its probabilities (the server shares one
    /// [`crate::memory::Memory`]: [`Session::with_memory`]).
    pub fn new(
        id: String,
        name: String,
        store: Arc<BrickStore>,
        cache_bytes: usize,
    ) -> Arc<Session> {
        let memory = crate::memory::Memory::new(cache_bytes, cache_bytes, usize::MAX / 2);
        Self::with_memory(id, name, store, &memory, 0)
    }

    /// A session over an opened store, holding its features, render bricks and probabilities
    /// in the server's `memory` (its render bricks as `render_owner`, unique per session).
    pub fn with_memory(
        id: String,
        name: String,
        store: Arc<BrickStore>,
        memory: &Arc<crate::memory::Memory>,
        render_owner: u64,
    ) -> Arc<Session> {
        let cache: &Arc<FeatureCache> = &memory.features;
        // Classes from the store's first label image with a class table, else two defaults.
        let mut classes = Vec::new();
        for l in &store.info().labels {
            if let Ok(c) = store.label_classes(l) {
                if !c.is_empty() {
                    classes = c
                        .into_iter()
                        .filter(|c| c.id != 0 && c.id != BACKGROUND)
                        .collect();
                    break;
                }
            }
        }
        if classes.is_empty() {
            classes = (1..=2)
                .map(|id| ClassInfo {
                    id,
                    name: format!("class {id}"),
                    color: palette(id),
                })
                .collect();
        }
        // A model trained earlier (by `neuvolex train` or a previous session) on this grid,
        // shared with the other sessions on this store.
        let model = memory.store_model(&store).map(|m| (1, m));
        let features = cache.for_session(&id);
        Arc::new(Session {
            id,
            name,
            store,
            classes: RwLock::new(classes),
            strokes: RwLock::new(Vec::new()),
            stroke_writer: Mutex::new(()),
            generation: AtomicU64::new(0),
            probs: RwLock::new(Probs::default()),
            status: RwLock::new(Status {
                state: "idle".into(),
                ..Default::default()
            }),
            dirty: Mutex::new(BTreeSet::new()),
            train_cancel: Mutex::new(None),
            last_used: AtomicU64::new(now_ms()),
            focus: Mutex::new(None),
            renderer: Mutex::new(None),
            model: RwLock::new(model),
            feature_set: RwLock::new(default_features()),
            stored: Mutex::new(None),
            closing: AtomicBool::new(false),
            features,
            tf: RwLock::new(None),
            preview: RwLock::new(None),
            prior_on: AtomicBool::new(true),
            prior: RwLock::new(None),
            labels: Mutex::new(crate::labels::LabelHistory::default()),
            redo: RwLock::new(Vec::new()),
            ui: RwLock::new(None),
            edits: AtomicU64::new(0),
            saved: Mutex::new((0, 0)),
            model_bytes: Mutex::new(None),
            memory: memory.clone(),
            render_owner,
            probs_reserved: Mutex::new(0),
            accel: RwLock::new(None),
        })
    }

    /// Predicts this session's rounds on `accel` (the server's GPU: the filter bank and the
    /// forest per block of bricks, streamed), for the feature sets it computes; `None` (the
    /// default), or a set it does not compute, predicts on the CPU as before. A round the
    /// accelerator fails finishes on the CPU.
    pub fn set_accelerator(&self, accel: Option<Arc<dyn Accelerator>>) {
        *self.accel.write().unwrap_or_else(|p| p.into_inner()) = accel;
    }

    /// The accelerator rounds predict on, if any.
    pub fn accelerator(&self) -> Option<Arc<dyn Accelerator>> {
        self.accel.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Gives back what this session holds in the server's memory (it was closed): its
    /// probabilities and their reservation, its render bricks and renderer, its features.
    pub fn release_memory(&self) {
        {
            let mut p = self.probs.write().unwrap_or_else(|p| p.into_inner());
            *p = Probs::default();
            let mut held = self
                .probs_reserved
                .lock()
                .unwrap_or_else(|p| p.into_inner());
            self.memory.release_probs(&mut held);
        }
        *self.renderer.lock().unwrap_or_else(|p| p.into_inner()) = None;
        self.labels
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clear();
        // The stored features' writer (and the store's lock, while they are pending) goes
        // with the last session holding them.
        *self.stored.lock().unwrap_or_else(|p| p.into_inner()) = None;
        let owner = self.render_owner;
        self.memory.render.retain(|k| k.0 != owner);
        self.features.close();
    }

    /// The forest size of this session's rounds ([`trees_for`] the voxels of its
    /// occupied bricks, the ones a round predicts).
    pub fn round_trees(&self) -> usize {
        let voxels: u64 = self
            .store
            .occupied_bricks(None)
            .iter()
            .map(|b| b.voxels() as u64)
            .sum();
        trees_for(voxels)
    }

    /// Records a change the session file keeps (strokes, redo, classes, transfer function,
    /// features, prior, page settings): the autosave writes it within its period.
    pub fn touch(&self) {
        self.edits.fetch_add(1, Ordering::SeqCst);
    }

    /// Settles the labels of the current probabilities once they are complete: the prior's
    /// verdict, growth and the stability rule against the label history, or a recorded round
    /// shown again ([`crate::labels::settle_labels`]). Called when a classification finishes
    /// and when the prior is switched on.
    pub fn refresh_prior(&self) -> ApiResult<crate::labels::PriorSummary> {
        let probs = self.probs.read().unwrap_or_else(|p| p.into_inner());
        let total = self.store.bricks().count();
        if !self.prior_enabled() || probs.ids.is_empty() || probs.bricks.len() < total {
            return Ok(self.prior_summary());
        }
        let st = crate::labels::settle_labels(&self.store, &probs, &self.labels)?;
        drop(probs);
        let sum = st.summary;
        *self.prior.write().unwrap_or_else(|p| p.into_inner()) = Some(st);
        Ok(sum)
    }

    /// What the prior does now.
    pub fn prior_summary(&self) -> crate::labels::PriorSummary {
        let mut sum = self
            .prior
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|p| p.summary)
            .unwrap_or_default();
        sum.enabled = self.prior_enabled();
        sum
    }

    /// The verdict that applies to `probs` (this session's), when the prior is on.
    pub fn active_prior(&self, probs: &Probs) -> Option<crate::labels::PriorState> {
        if !self.prior_enabled() {
            return None;
        }
        self.prior
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .filter(|p| p.generation == probs.generation)
            .cloned()
    }

    /// Whether the spatial prior is on.
    pub fn prior_enabled(&self) -> bool {
        self.prior_on.load(Ordering::SeqCst)
    }

    /// Replaces the strokes (validated against the grid); returns the new generation.
    pub fn set_strokes(&self, strokes: Vec<Stroke>) -> ApiResult<u64> {
        let _writer = self.stroke_writer.lock().unwrap_or_else(|p| p.into_inner());
        self.check_strokes(&strokes)?;
        *self.strokes.write().unwrap_or_else(|p| p.into_inner()) = strokes;
        self.touch();
        Ok(self.generation.fetch_add(1, Ordering::SeqCst) + 1)
    }

    /// Replaces the strokes and the redo stack together (an undo or a redo of the page);
    /// returns the new generation.
    pub fn set_strokes_and_redo(&self, strokes: Vec<Stroke>, redo: Vec<Stroke>) -> ApiResult<u64> {
        let _writer = self.stroke_writer.lock().unwrap_or_else(|p| p.into_inner());
        self.check_strokes(&strokes)?;
        self.check_strokes(&redo)
            .map_err(|e| ApiError::BadRequest(format!("redo: {e}")))?;
        *self.strokes.write().unwrap_or_else(|p| p.into_inner()) = strokes;
        *self.redo.write().unwrap_or_else(|p| p.into_inner()) = redo;
        self.touch();
        Ok(self.generation.fetch_add(1, Ordering::SeqCst) + 1)
    }

    /// The session's line: its strokes, then the undone ones in the order a redo brings them
    /// back (the saved label rounds are made from prefixes of it).
    pub fn line(&self) -> Vec<Stroke> {
        let mut l = self
            .strokes
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        l.extend(
            self.redo
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .iter()
                .rev()
                .cloned(),
        );
        l
    }

    /// Appends strokes to the session's list, atomically with respect to other appends and
    /// replacements (so concurrent clients drawing on one session lose nothing); returns the
    /// new generation and the number of strokes now held.
    pub fn add_strokes(&self, strokes: Vec<Stroke>) -> ApiResult<(u64, usize)> {
        // Writers take turns; readers are only held while the new list is swapped in.
        let _writer = self.stroke_writer.lock().unwrap_or_else(|p| p.into_inner());
        let mut all = self
            .strokes
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        all.extend(strokes);
        self.check_strokes(&all)?;
        let n = all.len();
        *self.strokes.write().unwrap_or_else(|p| p.into_inner()) = all;
        self.touch();
        Ok((self.generation.fetch_add(1, Ordering::SeqCst) + 1, n))
    }

    /// Checks a whole stroke list: its size, its classes and its fit to the grid.
    fn check_strokes(&self, strokes: &[Stroke]) -> ApiResult<()> {
        let classes = self.classes.read().unwrap_or_else(|p| p.into_inner());
        neuvolex_session::validate_strokes(strokes, &classes).map_err(ApiError::BadRequest)?;
        drop(classes);
        rasterise(strokes, self.store.info().dims)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        Ok(())
    }

    /// The session as a session file (volume, classes, strokes, transfer function; the view is
    /// the client's).
    pub fn state(&self) -> SessionFile {
        SessionFile {
            format: neuvolex_session::FORMAT.into(),
            version: neuvolex_session::VERSION,
            volume: self.name.clone(),
            classes: self
                .classes
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
            strokes: self
                .strokes
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
            tf: self
                .tf
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .as_ref()
                .map(|t| t.0.clone()),
            view: None,
            features: Some(self.feature_set().to_string()),
            id: Some(self.id.clone()),
            redo: self.redo.read().unwrap_or_else(|p| p.into_inner()).clone(),
            ui: self.ui.read().unwrap_or_else(|p| p.into_inner()).clone(),
            prior: Some(self.prior_enabled()),
            rounds: Vec::new(),
            saved_ms: None,
        }
    }

    /// Applies a session file (already validated) to this session: everything is checked
    /// against the grid first, then classes, transfer function and strokes are replaced
    /// together. Returns the new stroke generation.
    pub fn apply_state(&self, f: &SessionFile, source: &str) -> ApiResult<u64> {
        f.validate(source)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        f.check_grid(self.store.info().dims, source)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        let tf = f
            .tf_file(source)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        let _writer = self.stroke_writer.lock().unwrap_or_else(|p| p.into_inner());
        *self.classes.write().unwrap_or_else(|p| p.into_inner()) = f.classes.clone();
        *self.tf.write().unwrap_or_else(|p| p.into_inner()) =
            tf.map(|t| (f.tf.clone().unwrap_or_default(), t));
        *self.strokes.write().unwrap_or_else(|p| p.into_inner()) = f.strokes.clone();
        *self.redo.write().unwrap_or_else(|p| p.into_inner()) = f.redo.clone();
        if let Some(ui) = &f.ui {
            *self.ui.write().unwrap_or_else(|p| p.into_inner()) = Some(ui.clone());
        }
        if let Some(on) = f.prior {
            self.prior_on.store(on, Ordering::SeqCst);
        }
        self.touch();
        if let Some(name) = &f.features {
            // A set that needs an INR this volume does not have yet keeps the current one:
            // the strokes still apply.
            if let Err(e) = self.check_feature_set(name) {
                tracing::warn!("{source}: features '{name}' not restored: {e}");
            } else if let Ok(set) = name.parse() {
                *self.feature_set.write().unwrap_or_else(|p| p.into_inner()) = set;
            }
        }
        Ok(self.generation.fetch_add(1, Ordering::SeqCst) + 1)
    }

    /// Starts a new generation without new strokes (e.g. a newer model): work for the current
    /// one becomes stale. Returns the new generation.
    pub fn bump_generation(&self) -> u64 {
        self.generation.fetch_add(1, Ordering::SeqCst) + 1
    }

    /// Installs a newer model snapshot; returns its version.
    pub fn set_model(&self, model: InrModel) -> u64 {
        let mut m = self.model.write().unwrap_or_else(|p| p.into_inner());
        let v = m.as_ref().map_or(0, |(v, _)| *v) + 1;
        *m = Some((v, Arc::new(model)));
        v
    }

    /// The current model and its version.
    pub fn current_model(&self) -> Option<VersionedModel> {
        self.model.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The feature set the classification uses.
    pub fn feature_set(&self) -> FeatureSet {
        self.feature_set
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Whether the classification reads the INR (then each model snapshot re-classifies).
    pub fn uses_model(&self) -> bool {
        self.feature_set().needs_model()
    }

    /// Parses `name` as a feature set this session can use now: one that needs the INR is a
    /// conflict until a model is trained on this volume.
    pub fn check_feature_set(&self, name: &str) -> ApiResult<FeatureSet> {
        let set: FeatureSet = name.parse().map_err(|e: String| {
            ApiError::BadRequest(format!("features '{}': {e}", name.escape_debug()))
        })?;
        self.model_for(&set)?;
        Ok(set)
    }

    /// The model `set` needs: none for sets without INR parts, the current one otherwise
    /// (a conflict while none is trained on this volume).
    fn model_for(&self, set: &FeatureSet) -> ApiResult<Option<VersionedModel>> {
        if !set.needs_model() {
            return Ok(None);
        }
        self.current_model().map(Some).ok_or_else(|| {
            ApiError::Conflict(format!(
                "features '{set}' need the INR, and none is trained on this volume yet: train \
                 it first (INR training, or `neuvolex train`)"
            ))
        })
    }

    /// Switches the classification to feature set `name` ([`Self::check_feature_set`]) and
    /// starts a new generation (the caller re-classifies). Returns it.
    pub fn set_feature_set(&self, name: &str) -> ApiResult<u64> {
        let set = self.check_feature_set(name)?;
        *self.feature_set.write().unwrap_or_else(|p| p.into_inner()) = set;
        self.touch();
        Ok(self.bump_generation())
    }

    /// The feature set the classification uses, with the model it needs (none for sets
    /// without INR parts).
    pub fn feature_source(&self) -> ApiResult<(FeatureSet, Option<VersionedModel>)> {
        let set = self.feature_set();
        let model = self.model_for(&set)?;
        Ok((set, model))
    }

    /// The feature bricks kept in the store for `set`, when the background pass opened them.
    pub fn stored_for(&self, set: &FeatureSet) -> Option<Arc<PersistedFeatures>> {
        let name = neuvolex_classify::persist::array_name(set)?;
        self.stored
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .filter(|p| p.name() == name)
    }

    /// True while the session's own work runs (forest training, classification, INR training)
    /// or a render is in flight: background work waits.
    fn busy(&self) -> bool {
        let working = matches!(
            self.status
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .state
                .as_str(),
            "training" | "classifying"
        );
        working
            || self.memory.renders_in_flight() > 0
            || self
                .train_cancel
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .is_some()
    }

    /// Opens the feature bricks kept in the store for the session's feature set (shared with
    /// the other sessions on this store), so classifications read them from now on: the
    /// published array, or the pending one with the bricks done so far. Sets with INR parts,
    /// and arrays over `limit` bytes, are not kept: `Ok(None)`.
    pub fn open_stored_features(&self, limit: u64) -> ApiResult<Option<Arc<PersistedFeatures>>> {
        let set = self.feature_set();
        if set.needs_model() {
            return Ok(None);
        }
        let fx = BrickFeatures::new(&self.store, set.clone(), None, false)?;
        let bytes = neuvolex_classify::persist::stored_bytes(&self.store, fx.channels());
        if bytes > limit {
            tracing::info!(
                "{}: features {set} not kept in the store ({} MiB, over the {} MiB limit)",
                self.name,
                bytes >> 20,
                limit >> 20
            );
            return Ok(None);
        }
        let p = self
            .memory
            .stored_features(&self.store, &set, fx.channels())?;
        *self.stored.lock().unwrap_or_else(|p| p.into_inner()) = p.clone();
        Ok(p)
    }

    /// The background feature pass over the array [`Self::open_stored_features`] opened:
    /// computes the features of every brick not stored yet (nearest the middle of the volume
    /// first) and keeps them, so the first stroke finds them ready and a reopened volume is
    /// warm. Waits whenever [`Self::busy`], ends when the session closes (or only the pass
    /// still holds it), and publishes the array once complete. `progress(done, total)` follows
    /// the bricks stored (`done == total` once published). Returns the bricks now stored, or
    /// `None` when nothing is kept.
    pub fn prepare_features(
        self: &Arc<Self>,
        progress: &dyn Fn(usize, usize),
    ) -> ApiResult<Option<usize>> {
        let set = self.feature_set();
        let Some(p) = self.stored_for(&set) else {
            return Ok(None);
        };
        let fx = BrickFeatures::new(&self.store, set.clone(), None, false)?;
        let all: Vec<neuvolex_bricks::Brick> = self.store.bricks().collect();
        let middle = self.store.info().dims.map(|d| d / 2);
        let order: Vec<neuvolex_bricks::Brick> = brick_order(&all, None, Some(middle))
            .into_iter()
            .filter_map(|i| self.store.brick(i).ok())
            .collect();
        let missing = p.missing(&order);
        let total = all.len();
        let mut done = total - missing.len();
        let name = set.to_string();
        for b in missing {
            loop {
                // Closed, or dropped by everyone else (a server gone without closing it).
                if self.closing.load(Ordering::SeqCst) || Arc::strong_count(self) == 1 {
                    return Ok(Some(done));
                }
                if !self.busy() {
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            // Through the session's cache: a brick a classification computed is not computed
            // again, and the first stroke finds the rest there while the cache has room.
            let v = self.features.get_with(&name, 0, &fx, &b, Some(&p))?;
            p.write(&b, &v)?;
            done += 1;
            if done < total {
                progress(done, total);
            }
        }
        // The last announcement follows the publication.
        p.finish_if_complete(&self.store)?;
        progress(done, total);
        Ok(Some(done))
    }

    /// The scribbled voxels of the current strokes (class 0 strokes erase).
    pub fn scribbles(&self) -> ApiResult<Scribbles> {
        let strokes = self
            .strokes
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        self.scribbles_of(&strokes)
    }

    /// The scribbled voxels of `strokes` on this session's grid (class 0 strokes erase).
    pub fn scribbles_of(&self, strokes: &[Stroke]) -> ApiResult<Scribbles> {
        let mut s = rasterise(strokes, self.store.info().dims)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        s.voxels.retain(|v| v.1 != 0);
        Ok(s)
    }

    fn set_status(&self, f: impl FnOnce(&mut Status)) {
        f(&mut self.status.write().unwrap_or_else(|p| p.into_inner()));
    }

    /// True while `generation` is the newest.
    pub fn current(&self, generation: u64) -> bool {
        self.generation.load(Ordering::SeqCst) == generation
    }

    /// Trains a forest on the current scribbles and classifies every brick in this process
    /// ([`Self::classify_with`] without a cluster).
    pub fn classify(
        self: &Arc<Self>,
        generation: u64,
        trees: usize,
        on_brick: &(dyn Fn([usize; 3], usize, usize) + Sync),
    ) -> ApiResult<usize> {
        self.classify_with(generation, trees, on_brick, None)
    }

    /// The current model as a blob for cluster workers: its identity and the model file's
    /// bytes, serialised once per snapshot version.
    pub fn model_blob(&self, version: u64, model: &InrModel) -> ApiResult<(String, Arc<Vec<u8>>)> {
        let mut c = self.model_bytes.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((v, id, b)) = &*c {
            if *v == version {
                return Ok((id.clone(), b.clone()));
            }
        }
        let id = neuvolex_features::stage::model_identity(model);
        let b = Arc::new(
            neuvolex_features::stage::model_to_bytes(model)
                .map_err(|e| ApiError::Internal(e.to_string()))?,
        );
        *c = Some((version, id.clone(), b.clone()));
        Ok((id, b))
    }

    /// Trains a forest on the current scribbles and classifies every brick as tasks of the
    /// prediction stage: in this process (one brick a task in [`brick_order`], features
    /// through the session's cache), or on `cluster`'s workers (the
    /// forest and the model snapshot published once as blobs). Probabilities are stored as
    /// bricks arrive and `on_brick` is called for each. Stops early, as `cancelled`, once a
    /// newer stroke generation exists. Returns the bricks classified.
    pub fn classify_with(
        self: &Arc<Self>,
        generation: u64,
        trees: usize,
        on_brick: &(dyn Fn([usize; 3], usize, usize) + Sync),
        cluster: Option<&neuvolex_cluster::ClusterExecutor>,
    ) -> ApiResult<usize> {
        let t0 = std::time::Instant::now();
        // The strokes this round is made from, read once: the probabilities and the labels
        // settled over them name these, whatever arrives meanwhile.
        let strokes = Arc::new(
            self.strokes
                .read()
                .unwrap_or_else(|p| p.into_inner())
                .clone(),
        );
        let scr = self.scribbles_of(&strokes)?;
        let counts = scr.counts();
        let rois = counts.keys().filter(|&&c| c != BACKGROUND).count();
        if counts.len() < 2 || rois == 0 {
            self.set_status(|s| {
                s.generation = generation;
                s.state = "idle".into();
                s.message = "scribble at least two classes (or one class and background)".into();
            });
            return Ok(0);
        }
        let (set, model) = self.feature_source()?;
        let version = model.as_ref().map_or(0, |m| m.0);
        // Training and prediction both read through the feature cache, which holds f16
        // (shown to cost no F1), so both see the same values; cluster workers round their
        // features to f16 the same way.
        let fx = BrickFeatures::new(
            &self.store,
            set.clone(),
            model.as_ref().map(|m| m.1.clone()),
            false,
        )?;
        self.set_status(|s| {
            s.generation = generation;
            s.state = "training".into();
            s.features = set.to_string();
            s.message.clear();
        });
        let name = set.to_string();
        let stored = self.stored_for(&set);
        // Newer strokes make this run stale: stop fetching features for it at once.
        // A brick not cached yet gives just the slices its strokes cross (the prediction
        // computes and caches the whole brick moments later).
        let ts = match training_set_boxed(&fx, &scr, BACKGROUND, &|whole, part| {
            if !self.current(generation) {
                return Err(neuvolex_classify::ClassifyError::Input(
                    "superseded by newer strokes".into(),
                ));
            }
            self.features
                .get_part(&name, version, &fx, whole, part, stored.as_deref())
        }) {
            Ok(ts) => ts,
            Err(_) if !self.current(generation) => {
                self.set_status(|s| s.state = "cancelled".into());
                return Ok(0);
            }
            Err(e) => return Err(e.into()),
        };
        if !self.current(generation) {
            self.set_status(|s| s.state = "cancelled".into());
            return Ok(0);
        }
        // The CLI's and the evaluation's forest (balanced classes), at the session's size.
        let forest = Arc::new(fit(
            &ts,
            &neuvolex_classify::ForestConfig {
                trees,
                ..neuvolex_classify::ClassifyConfig::default().forest
            },
        )?);
        let trained = t0.elapsed().as_secs_f64();
        let bricks = {
            let all: Vec<neuvolex_bricks::Brick> = self.store.bricks().collect();
            let focus = *self.focus.lock().unwrap_or_else(|p| p.into_inner());
            brick_order(&all, strokes.last(), focus)
        };
        let total = bricks.len();
        {
            let mut p = self.probs.write().unwrap_or_else(|p| p.into_inner());
            if !self.current(generation) || p.generation > generation {
                self.set_status(|s| s.state = "cancelled".into());
                return Ok(0);
            }
            if p.ids != ts.labels {
                // One byte per voxel and class, reserved in full before any brick arrives.
                let voxels: usize = self.store.info().dims.iter().product();
                let mut held = self
                    .probs_reserved
                    .lock()
                    .unwrap_or_else(|p| p.into_inner());
                if let Err(e) =
                    self.memory
                        .reserve_probs(&mut held, voxels * ts.labels.len(), &self.id)
                {
                    self.set_status(|s| {
                        s.state = "failed".into();
                        s.message = e.to_string();
                    });
                    return Err(e);
                }
                p.bricks.clear();
            }
            p.ids = ts.labels.clone();
            p.generation = generation;
            p.strokes = strokes.clone();
            p.features = crate::labels::features_key(&set, version);
        }
        self.set_status(|s| {
            s.state = "classifying".into();
            s.done = 0;
            s.total = total;
            s.engine = if cluster.is_some() { "cluster" } else { "cpu" }.into();
        });
        let (model_id, model_bytes) = match (&model, cluster) {
            (Some((v, m)), Some(_)) => {
                let (id, b) = self.model_blob(*v, m)?;
                (Some(id), Some(b))
            }
            (Some((_, m)), None) => (Some(neuvolex_features::stage::model_identity(m)), None),
            (None, _) => (None, None),
        };
        let spec = FeatureSpec {
            store: store_path_string(self.store.root()),
            features: name.clone(),
            stored_features: false,
            model_blob: model_bytes
                .as_ref()
                .and(model_id.as_ref())
                .map(|id| format!("model-{id}")),
            model: model_id,
        };
        let params = ProbaParams {
            source: spec.clone(),
            forest: ProbaStage::forest_key(&forest)?,
            labels: ts.labels.clone(),
            background: BACKGROUND,
            f16_features: true,
        };
        let src = OpenedFeatures {
            store: self.store.clone(),
            model: model.as_ref().map(|m| m.1.clone()),
            set: set.clone(),
            spec,
            model_bytes,
        };
        let mut done = 0usize;
        let mut cancelled = false;
        // Each brick's probabilities as they arrive: shown at once (false: a newer round began).
        let mut deliver = |bi: [usize; 3], u8s: Vec<u8>| -> bool {
            {
                let mut p = self.probs.write().unwrap_or_else(|p| p.into_inner());
                if p.generation != generation {
                    cancelled = true;
                    return false;
                }
                p.bricks.insert(bi, Arc::new(u8s));
            }
            self.dirty
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(bi);
            done += 1;
            let n = done;
            self.set_status(|s| s.done = n);
            on_brick(bi, n, total);
            true
        };
        // On the GPU where the server has one and it computes this feature set (not on a
        // cluster): the filter bank and the forest per block of bricks, streamed; the features
        // are rounded through f16 as the cache holds them, so the forest sees what it was
        // trained on. What it does not finish (a device error) goes to the CPU below.
        let (mut bricks, mut stopped) = (bricks, false);
        if let Some(a) = cluster.is_none().then(|| self.accelerator()).flatten() {
            let opts = AccelOptions {
                tau: 0.0,
                f16_features: true,
            };
            match a.prepare(self.store.clone(), &set, &forest, &opts) {
                Ok(p) => {
                    self.set_status(|s| s.engine = "gpu".into());
                    let t = std::time::Instant::now();
                    match self.predict_on(p.as_ref(), &bricks, &ts.labels, generation, &mut deliver)
                    {
                        Ok(left) => {
                            tracing::debug!(
                                session = %self.id,
                                adapter = %a.describe(),
                                seconds = t.elapsed().as_secs_f64(),
                                stopped = left.is_none(),
                                "predicted on the GPU"
                            );
                            stopped = left.is_none();
                            bricks = left.unwrap_or_default();
                        }
                        Err((left, e)) => {
                            tracing::warn!(
                                session = %self.id,
                                "GPU classification failed ({e}); the round finishes on the CPU"
                            );
                            self.set_status(|s| s.engine = "gpu+cpu".into());
                            bricks = left;
                        }
                    }
                }
                Err(e) => tracing::debug!(
                    session = %self.id,
                    features = %set,
                    "not on the GPU ({e}); the CPU forest predicts"
                ),
            }
        }
        let hook: Option<FeatureHook<'_>> = match cluster {
            Some(_) => None,
            None => Some(Box::new(|b: &neuvolex_bricks::Brick| {
                // A render in flight goes first (it runs on its own threads meanwhile).
                self.memory.yield_to_renders();
                self.features
                    .get_f16_with(&name, version, &fx, b, stored.as_deref())
            })),
        };
        let stage = ProbaStage::new(params, src, forest, hook)?;
        // One brick a task in process: each brick shows as soon as it is classified, in
        // `brick_order` (the executor starts tasks in order); batches of four on a cluster.
        let per = if cluster.is_some() { 4 } else { 1 };
        let tasks = neuvolex_tasks::plan(&bricks, per, 0);
        let me = self.clone();
        let poll: CancelPoll = Arc::new(move || !me.current(generation));
        let mut on = |e: Event<Vec<([usize; 3], Vec<u8>)>>| {
            let Event::Done(d) = e else { return };
            for (bi, u8s) in d.output {
                if !deliver(bi, u8s) {
                    return;
                }
            }
        };
        let run = match (cluster, bricks.is_empty()) {
            (_, true) => Ok(neuvolex_tasks::RunReport::default()),
            (Some(c), false) => c.with_cancel(poll).execute(&stage, &tasks, &mut on),
            (None, false) => LocalExecutor::new()
                .labelled("actors")
                .with_cancel(poll)
                .execute(&stage, &tasks, &mut on),
        }
        .map_err(|e| ApiError::Internal(e.to_string()))?;
        if let Some(d) = run.dead.first() {
            return Err(ApiError::Internal(format!(
                "classification failed on bricks {:?}: {}",
                d.bricks, d.error
            )));
        }
        let cancelled = cancelled || run.cancelled || stopped;
        let predicted = t0.elapsed().as_secs_f64();
        if !cancelled {
            self.refresh_prior()?;
            tracing::debug!(
                session = %self.id,
                generation,
                train_s = trained,
                predict_s = predicted - trained,
                prior_s = t0.elapsed().as_secs_f64() - predicted,
                "classified"
            );
        }
        self.set_status(|s| s.state = if cancelled { "cancelled" } else { "done" }.into());
        Ok(done)
    }

    /// Predicts the bricks `order` (indices, in the round's order) on `pred` and gives each
    /// brick's u8 probabilities to `deliver`: occupied bricks streamed through the accelerator
    /// (block by block, in the order of each block's first brick), empty bricks as certain
    /// background (as [`ProbaStage`] gives them) at their place in the order. `Ok(Some)` with
    /// the bricks left to predict elsewhere (none when all went well), `Ok(None)` when a newer
    /// round stopped it; `Err` with the bricks not given yet and the accelerator's error.
    #[allow(clippy::type_complexity)]
    fn predict_on(
        &self,
        pred: &dyn BrickPredictor,
        order: &[[usize; 3]],
        labels: &[u32],
        generation: u64,
        deliver: &mut dyn FnMut([usize; 3], Vec<u8>) -> bool,
    ) -> Result<Option<Vec<[usize; 3]>>, (Vec<[usize; 3]>, neuvolex_classify::ClassifyError)> {
        let bg = labels.iter().position(|&l| l == BACKGROUND);
        let background = |b: &neuvolex_bricks::Brick| {
            neuvolex_classify::pipeline::certain_background(b.voxels(), labels.len(), bg)
        };
        // Occupied bricks go to the accelerator; empty ones need no device and are given at
        // their place in the order, before the first predicted brick that comes after them.
        let (mut occupied, mut empties) = (Vec::with_capacity(order.len()), Vec::new());
        let mut rank = std::collections::HashMap::with_capacity(order.len());
        for (i, &bi) in order.iter().enumerate() {
            let b = self
                .store
                .brick(bi)
                .map_err(|e| (order[i..].to_vec(), e.into()))?;
            rank.insert(bi, i);
            if self.store.is_occupied(&b, None) {
                occupied.push(b);
            } else {
                empties.push((i, b));
            }
        }
        let mut next = 0usize;
        let mut given = BTreeSet::new();
        let mut stopped = false;
        let r = pred.predict_stream(&occupied, &mut |b, a| {
            // A render in flight goes first; a newer round stops this one.
            self.memory.yield_to_renders();
            if !self.current(generation) {
                stopped = true;
                return false;
            }
            let at = rank.get(&b.index).copied().unwrap_or(usize::MAX);
            while let Some((_, e)) = empties.get(next).filter(|(i, _)| *i < at) {
                if !deliver(e.index, background(e)) {
                    stopped = true;
                    return false;
                }
                next += 1;
            }
            if !deliver(b.index, a.probs) {
                stopped = true;
                return false;
            }
            given.insert(b.index);
            true
        });
        if stopped {
            return Ok(None);
        }
        for (_, e) in &empties[next..] {
            if !deliver(e.index, background(e)) {
                return Ok(None);
            }
        }
        let left: Vec<[usize; 3]> = occupied
            .iter()
            .map(|b| b.index)
            .filter(|i| !given.contains(i))
            .collect();
        match r {
            Ok(()) => Ok(Some(left)),
            Err(e) => Err((left, e)),
        }
    }

    /// The render source over this session's store and streamed probabilities.
    pub fn source(self: &Arc<Self>) -> SessionSource {
        SessionSource {
            inner: StoreSource::new(self.store.clone()),
            session: self.clone(),
            labels: false,
            one_hot: neuvolex_bricks::lru::Lru::new(ONE_HOT_CACHE_BYTES),
        }
    }
}

impl Drop for Session {
    /// A session dropped without [`Session::release_memory`] (a work item outliving its
    /// close) still gives its reservation back.
    fn drop(&mut self) {
        let held = self
            .probs_reserved
            .get_mut()
            .unwrap_or_else(|p| p.into_inner());
        self.memory.release_probs(held);
    }
}

/// The order bricks are classified in, so that what the user looks at arrives first: the
/// bricks the last stroke's slice crosses, nearest the stroke first; then those under the
/// slices on screen (the three planes through `focus`); then the rest, nearest the stroke (or
/// the focus) first.
pub fn brick_order(
    bricks: &[neuvolex_bricks::Brick],
    last: Option<&Stroke>,
    focus: Option<[usize; 3]>,
) -> Vec<[usize; 3]> {
    let crosses = |b: &neuvolex_bricks::Brick, axis: usize, at: usize| {
        b.origin[axis] <= at && at < b.origin[axis] + b.size[axis]
    };
    let stroke = last.map(|s| {
        let (ua, va, wa) = s.axis.grid_axes();
        let n = s.points.len().max(1) as f64;
        let mut c = [0f64; 3];
        c[ua] = s.points.iter().map(|p| p[0] as f64).sum::<f64>() / n;
        c[va] = s.points.iter().map(|p| p[1] as f64).sum::<f64>() / n;
        c[wa] = s.slice as f64;
        (wa, s.slice, c)
    });
    let centre = stroke
        .map(|s| s.2)
        .or(focus.map(|f| f.map(|v| v as f64)))
        .unwrap_or([0.0; 3]);
    let mut keyed: Vec<(u8, f64, [usize; 3])> = bricks
        .iter()
        .map(|b| {
            let tier = if stroke.is_some_and(|(wa, sl, _)| crosses(b, wa, sl)) {
                0
            } else if focus.is_some_and(|f| (0..3).any(|k| crosses(b, k, f[k]))) {
                1
            } else {
                2
            };
            let d: f64 = (0..3)
                .map(|k| (b.origin[k] as f64 + b.size[k] as f64 / 2.0 - centre[k]).powi(2))
                .sum();
            (tier, d, b.index)
        })
        .collect();
    keyed.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
    keyed.into_iter().map(|k| k.2).collect()
}

/// Intensity from the store, probabilities from the session's streamed bricks: the class
/// probabilities themselves, or (`labels`) the current labels as one-hot channels
/// ([`crate::labels::one_hot_labels`]: the 0.5 rule, the prior's changes when it is on), the
/// same labels the overlays, fractions and exports show.
pub struct SessionSource {
    inner: StoreSource,
    session: Arc<Session>,
    /// Draw the current labels instead of the probabilities. Switching it, or a new verdict of
    /// the prior, needs the renderer's cached bricks dropped.
    pub labels: bool,
    /// Recent one-hot bricks, each with the probabilities and prior changes it was made from
    /// (a brick is read again as the apron of each of its neighbours).
    one_hot: neuvolex_bricks::lru::Lru<[usize; 3], Arc<OneHot>>,
}

/// Bytes of one-hot bricks a session's label view keeps between neighbouring loads.
const ONE_HOT_CACHE_BYTES: usize = 32 << 20;

/// A brick's one-hot labels and what they were computed from.
struct OneHot {
    probs: Arc<Vec<u8>>,
    changes: Option<Arc<Vec<(u32, u16)>>>,
    channels: Vec<u32>,
    data: Arc<Vec<u8>>,
}

impl SessionSource {
    /// The channels drawn: the probabilities' classes, or the label channels.
    fn channel_ids(&self) -> Vec<u32> {
        let ids = self
            .session
            .probs
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .ids
            .clone();
        if self.labels && !ids.is_empty() {
            crate::labels::label_channels(&ids)
        } else {
            ids
        }
    }

    /// Brick `n`'s one-hot labels (None before it is classified), from the cache while its
    /// probabilities and prior changes are the ones it was made from.
    fn one_hot(
        &self,
        pr: &Probs,
        prior: Option<&crate::labels::PriorState>,
        channels: &[u32],
        n: [usize; 3],
    ) -> Option<Arc<Vec<u8>>> {
        let probs = pr.bricks.get(&n)?;
        let changes = prior.and_then(|p| p.changed.get(&n));
        if let Some(h) = self.one_hot.get(&n) {
            let same_changes = match (&h.changes, changes) {
                (None, None) => true,
                (Some(a), Some(b)) => Arc::ptr_eq(a, b),
                _ => false,
            };
            if Arc::ptr_eq(&h.probs, probs) && same_changes && h.channels == channels {
                return Some(h.data.clone());
            }
        }
        let data = Arc::new(crate::labels::one_hot_labels(
            &pr.ids,
            probs,
            changes.map(|c| c.as_slice()),
            channels,
        ));
        let cost = data.len();
        self.one_hot.insert(
            n,
            Arc::new(OneHot {
                probs: probs.clone(),
                changes: changes.cloned(),
                channels: channels.to_vec(),
                data: data.clone(),
            }),
            cost,
        );
        Some(data)
    }
}

impl BrickSource for SessionSource {
    fn geom(&self) -> VolumeGeom {
        self.inner.geom()
    }

    fn normaliser(&self) -> Normaliser {
        self.inner.normaliser()
    }

    fn classes(&self) -> Vec<ChannelClass> {
        let ids = self.channel_ids();
        let classes = self
            .session
            .classes
            .read()
            .unwrap_or_else(|p| p.into_inner());
        ids.iter()
            .map(|&id| {
                let c = classes
                    .iter()
                    .find(|c| c.id == id)
                    .map_or_else(|| palette(id), |c| c.color);
                (id, c.map(|v| v as f32 / 255.0), id == BACKGROUND)
            })
            .collect()
    }

    fn coarse_range(&self, index: [usize; 3]) -> Option<(f32, f32)> {
        self.inner.coarse_range(index)
    }

    fn load(&self, index: [usize; 3], probs: bool) -> neuvolex_render::Result<RenderBrick> {
        let b = self.inner.load(index, false)?;
        if !probs {
            return Ok(b);
        }
        let pr = self.session.probs.read().unwrap_or_else(|p| p.into_inner());
        let ch = pr.ids.len();
        if ch == 0 {
            return Ok(b);
        }
        let geom = self.geom();
        let (ch, p) = if self.labels {
            let channels = crate::labels::label_channels(&pr.ids);
            let prior = self.session.active_prior(&pr);
            let p = assemble(&geom, index, channels.len(), |n| {
                Ok(self.one_hot(&pr, prior.as_ref(), &channels, n))
            })?;
            (channels.len(), p)
        } else {
            (
                ch,
                assemble(&geom, index, ch, |n| Ok(pr.bricks.get(&n).cloned()))?,
            )
        };
        Ok(RenderBrick::new(
            b.index,
            b.origin,
            b.size,
            b.intensity,
            ch,
            p,
        ))
    }
}

#[cfg(test)]
mod order_tests {
    use super::*;
    use neuvolex_bricks::Brick;
    use neuvolex_classify::scribble::Axis;

    fn grid(n: usize, edge: usize) -> Vec<Brick> {
        let mut v = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    v.push(Brick {
                        index: [x, y, z],
                        origin: [x * edge, y * edge, z * edge],
                        size: [edge; 3],
                    });
                }
            }
        }
        v
    }

    #[test]
    fn the_stroked_slice_comes_first_then_the_slices_on_screen() {
        let b = grid(4, 16);
        // A stroke on axial slice 40 (brick row z = 2) near x = 5, y = 60.
        let s = Stroke {
            class: 1,
            axis: Axis::Z,
            slice: 40,
            points: vec![[4.0, 59.0], [6.0, 61.0]],
            radius: 2.0,
        };
        let o = brick_order(&b, Some(&s), Some([20, 20, 40]));
        assert_eq!(o.len(), 64);
        // First the 16 bricks of z row 2, the one under the stroke first.
        assert_eq!(o[0], [0, 3, 2]);
        assert!(o[..16].iter().all(|i| i[2] == 2), "{o:?}");
        // Then those under the coronal (y = 20) and sagittal (x = 20) slices on screen: 7 in
        // each of the other 3 brick rows; then the rest.
        let on_screen = |i: &[usize; 3]| i[0] == 1 || i[1] == 1;
        assert!(o[16..37].iter().all(on_screen), "{o:?}");
        assert!(!o[37..].iter().any(on_screen), "{o:?}");
        // Every brick once.
        let mut u = o.clone();
        u.sort();
        u.dedup();
        assert_eq!(u.len(), 64);
        // Nothing known: all bricks, nearest the origin first.
        let o = brick_order(&b, None, None);
        assert_eq!((o.len(), o[0]), (64, [0, 0, 0]));
    }
}
