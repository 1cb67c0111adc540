//! A session: one opened volume, its classes and strokes, and the class probabilities that
//! stream in brick by brick.

use crate::error::{ApiError, ApiResult};
use neuvolex_bricks::synth::{palette, ClassInfo};
use neuvolex_bricks::{BrickStore, Normaliser};
use neuvolex_classify::features::{BrickFeatures, FeatureSet};
use neuvolex_classify::scribble::{rasterise, Scribbles, Stroke};
use neuvolex_classify::shard::{fit, predict_brick, training_set_with};
use neuvolex_render::source::{assemble, ChannelClass, RenderBrick};
use neuvolex_render::{BrickSource, StoreSource, VolumeGeom};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use crate::cache::{FeatureCache, SessionFeatures};
use neuvolex_features::InrModel;
use neuvolex_session::SessionFile;

/// A model and its version in a session (bumped by every snapshot).
pub type VersionedModel = (u64, Arc<InrModel>);

/// The label strokes use for background/other.
pub const BACKGROUND: u32 = neuvolex_session::BACKGROUND;

/// Class probabilities received so far, per brick (u8, voxel-major).
#[derive(Default)]
pub struct Probs {
    /// Class id of each channel (ascending; the background label included).
    pub ids: Vec<u32>,
    /// Stroke generation they belong to.
    pub generation: u64,
    /// Bricks classified so far.
    pub bricks: HashMap<[usize; 3], Arc<Vec<u8>>>,
}

impl Probs {
    /// Class probabilities of voxel `p` (None before classification reached its brick).
    pub fn at(&self, store: &BrickStore, p: [usize; 3]) -> Option<&[u8]> {
        let b = store.info().brick;
        let br = store.brick(p.map(|v| v / b)).ok()?;
        let data = self.bricks.get(&br.index)?;
        let l = [0, 1, 2].map(|k| p[k] - br.origin[k]);
        let i = (l[2] * br.size[1] + l[1]) * br.size[0] + l[0];
        let c = self.ids.len();
        data.get(i * c..(i + 1) * c)
    }
}

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
    /// Render state (the renderer keeps the last frame for incremental updates).
    pub renderer: Mutex<Option<RenderState>>,
    /// The INR the features come from, with a version bumped by every snapshot the trainer
    /// publishes (`None` until one is trained).
    pub model: RwLock<Option<VersionedModel>>,
    /// Feature bricks shared by every classification and recommendation of this session (in
    /// the server's one cache, under one budget for all sessions).
    pub features: SessionFeatures,
    /// The session's transfer function (JSON as sent, and parsed); `None` uses a preset.
    pub tf: RwLock<Option<(serde_json::Value, neuvolex_render::TfFile)>>,
    /// The newest training preview: reconstruction beside the input, as PNG, and its PSNR.
    pub preview: RwLock<Option<(Vec<u8>, f64)>>,
}

/// A session's renderer and what its last frame was.
pub struct RenderState {
    /// The renderer (keeps the last frame's accumulators).
    pub renderer: neuvolex_render::Renderer<SessionSource>,
    /// Parameters, transfer function and classes of the last frame.
    pub key: String,
}

impl Session {
    /// A session over an opened store, with a feature cache of its own holding at most
    /// `cache_bytes` (the server shares one cache: [`Session::with_cache`]).
    pub fn new(
        id: String,
        name: String,
        store: Arc<BrickStore>,
        cache_bytes: usize,
    ) -> Arc<Session> {
        Self::with_cache(id, name, store, &Arc::new(FeatureCache::new(cache_bytes)))
    }

    /// A session over an opened store, reading features through the shared `cache`.
    pub fn with_cache(
        id: String,
        name: String,
        store: Arc<BrickStore>,
        cache: &Arc<FeatureCache>,
    ) -> Arc<Session> {
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
        // A model trained earlier (by `neuvolex train` or a previous session) on this grid.
        let model =
            neuvolex_features::checkpoint::load(neuvolex_features::train::model_path(&store))
                .ok()
                .filter(|l| l.model.dims == store.info().dims)
                .map(|l| (1, Arc::new(l.model)));
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
            renderer: Mutex::new(None),
            model: RwLock::new(model),
            features,
            tf: RwLock::new(None),
            preview: RwLock::new(None),
        })
    }

    /// Replaces the strokes (validated against the grid); returns the new generation.
    pub fn set_strokes(&self, strokes: Vec<Stroke>) -> ApiResult<u64> {
        let _writer = self.stroke_writer.lock().unwrap_or_else(|p| p.into_inner());
        self.check_strokes(&strokes)?;
        *self.strokes.write().unwrap_or_else(|p| p.into_inner()) = strokes;
        Ok(self.generation.fetch_add(1, Ordering::SeqCst) + 1)
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

    /// The feature set interactive work uses: `inr` (learned + local) once a model exists,
    /// else `local`; with the model version it is computed from.
    pub fn feature_source(&self) -> ApiResult<(FeatureSet, Option<VersionedModel>)> {
        let model = self.current_model();
        let set: FeatureSet = if model.is_some() { "inr" } else { "local" }
            .parse()
            .map_err(ApiError::Internal)?;
        Ok((set, model))
    }

    /// The scribbled voxels of the current strokes (class 0 strokes erase).
    pub fn scribbles(&self) -> ApiResult<Scribbles> {
        let strokes = self
            .strokes
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        let mut s = rasterise(&strokes, self.store.info().dims)
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

    /// Trains a forest on the current scribbles and classifies every brick in `shards`
    /// parallel shards (each a contiguous range of bricks), storing probabilities as bricks
    /// finish and calling `on_brick` for each. Stops early, as `cancelled`, once a newer stroke
    /// generation exists. Returns the bricks classified.
    pub fn classify(
        &self,
        generation: u64,
        trees: usize,
        shards: usize,
        on_brick: &(dyn Fn([usize; 3], usize, usize) + Sync),
    ) -> ApiResult<usize> {
        let scr = self.scribbles()?;
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
        // (shown to cost no F1), so both see the same values.
        let fx = BrickFeatures::new(&self.store, set.clone(), model.map(|m| m.1), false)?;
        self.set_status(|s| {
            s.generation = generation;
            s.state = "training".into();
            s.features = set.to_string();
            s.message.clear();
        });
        let name = set.to_string();
        let ts = training_set_with(&fx, &scr, BACKGROUND, &|b| {
            self.features.get(&name, version, &fx, b)
        })?;
        let forest = fit(
            &ts,
            &neuvolex_classify::ForestConfig {
                trees,
                ..Default::default()
            },
        )?;
        let out_labels: Vec<u16> = ts
            .labels
            .iter()
            .map(|&l| if l == BACKGROUND { 0 } else { l as u16 })
            .collect();
        let bricks: Vec<_> = self.store.bricks().collect();
        let total = bricks.len();
        {
            let mut p = self.probs.write().unwrap_or_else(|p| p.into_inner());
            if !self.current(generation) || p.generation > generation {
                self.set_status(|s| s.state = "cancelled".into());
                return Ok(0);
            }
            if p.ids != ts.labels {
                p.bricks.clear();
            }
            p.ids = ts.labels.clone();
            p.generation = generation;
        }
        self.set_status(|s| {
            s.state = "classifying".into();
            s.done = 0;
            s.total = total;
        });
        let done = AtomicU64::new(0);
        let cancelled = AtomicBool::new(false);
        let per = total.div_ceil(shards.max(1)).max(1);
        let c = ts.labels.len();
        let result: ApiResult<()> = bricks.par_chunks(per).try_for_each(|shard| {
            for b in shard {
                if !self.current(generation) {
                    cancelled.store(true, Ordering::SeqCst);
                    return Ok(());
                }
                let u8s: Vec<u8> = if self.store.is_occupied(b, None) {
                    let f = self.features.get(&name, version, &fx, b)?;
                    let (p, _) = predict_brick(&forest, &f, &out_labels, 0.5)?;
                    p.iter()
                        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                        .collect()
                } else {
                    // Empty brick: background with certainty.
                    let mut v = vec![0u8; b.voxels() * c];
                    if let Some(bg) = ts.labels.iter().position(|&l| l == BACKGROUND) {
                        for px in v.chunks_exact_mut(c) {
                            px[bg] = 255;
                        }
                    }
                    v
                };
                {
                    let mut p = self.probs.write().unwrap_or_else(|p| p.into_inner());
                    if p.generation != generation {
                        cancelled.store(true, Ordering::SeqCst);
                        return Ok(());
                    }
                    p.bricks.insert(b.index, Arc::new(u8s));
                }
                self.dirty
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(b.index);
                let n = done.fetch_add(1, Ordering::SeqCst) as usize + 1;
                self.set_status(|s| s.done = n);
                on_brick(b.index, n, total);
            }
            Ok(())
        });
        result?;
        let n = done.load(Ordering::SeqCst) as usize;
        let cancelled = cancelled.load(Ordering::SeqCst);
        self.set_status(|s| s.state = if cancelled { "cancelled" } else { "done" }.into());
        Ok(n)
    }

    /// The render source over this session's store and streamed probabilities.
    pub fn source(self: &Arc<Self>) -> SessionSource {
        SessionSource {
            inner: StoreSource::new(self.store.clone()),
            session: self.clone(),
        }
    }
}

/// Intensity from the store, probabilities from the session's streamed bricks.
pub struct SessionSource {
    inner: StoreSource,
    session: Arc<Session>,
}

impl BrickSource for SessionSource {
    fn geom(&self) -> VolumeGeom {
        self.inner.geom()
    }

    fn normaliser(&self) -> Normaliser {
        self.inner.normaliser()
    }

    fn classes(&self) -> Vec<ChannelClass> {
        let ids = self
            .session
            .probs
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .ids
            .clone();
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
        let p = assemble(&geom, index, ch, |n| Ok(pr.bricks.get(&n).cloned()))?;
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
