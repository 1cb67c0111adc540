//! Feature extraction as a brick stage ([`ExtractStage`]): a task's bricks are extracted with
//! a given model version and written into the store's feature array, each brick marked done
//! once written, so any executor (rayon, cluster workers) runs it and a re-run resumes.

use crate::error::{FeatureError, Result};
use crate::extract::{extract_brick, vectors_name, ExtractReport};
use crate::model::{FeatureKind, InrModel};
use crate::train::{model_path, training_bricks};
use neuvolex_bricks::{Brick, BrickStore, VectorArray, VectorEncoding};
use neuvolex_tasks::{
    execute_ordered, fingerprint, Blobs, DynStage, Executor, RunEvent, RunReport, Stage, Task,
    TaskCtx, TaskError,
};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// The stage's name.
pub const STAGE: &str = "features";

/// The identity of a model version: a CRC of its grid, configuration and parameters.
pub fn model_identity(m: &InrModel) -> String {
    let mut h = crc32fast::Hasher::new();
    h.update(format!("{:?}|{:?}", m.dims, m.cfg).as_bytes());
    h.update(bytemuck::cast_slice(&m.table));
    h.update(bytemuck::cast_slice(&m.dense));
    format!("{:08x}-{}", h.finalize(), m.table.len() + m.dense.len())
}

/// Loads the store's trained model and checks that it is the version `identity` names.
pub fn load_model_checked(store: &BrickStore, identity: &str) -> Result<InrModel> {
    let p = model_path(store);
    if !p.exists() {
        return Err(FeatureError::Config(format!(
            "{}: no trained model; run `neuvolex train {}` first",
            p.display(),
            store.root().display()
        )));
    }
    let m = crate::checkpoint::load(&p)?.model;
    let have = model_identity(&m);
    if have != identity {
        return Err(FeatureError::Config(format!(
            "{}: the trained model is version {have}, this run uses {identity}; was it \
             retrained meanwhile?",
            p.display()
        )));
    }
    Ok(m)
}

/// A model as the bytes of a model file (to publish it as a blob for cluster workers).
pub fn model_to_bytes(m: &InrModel) -> Result<Vec<u8>> {
    let dir = std::env::temp_dir().join(format!("neuvolex-model-{}", std::process::id()));
    let p = dir.join(format!("{}.nvx", model_identity(m)));
    crate::checkpoint::save(&p, m, None)?;
    let b = std::fs::read(&p).map_err(|e| FeatureError::Io {
        path: p.clone(),
        source: e,
    });
    let _ = std::fs::remove_file(&p);
    b
}

/// A model from the bytes of a model file, checked against `identity`.
pub fn model_from_bytes(bytes: &[u8], identity: &str) -> Result<InrModel> {
    let dir = std::env::temp_dir().join(format!("neuvolex-model-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| FeatureError::Io {
        path: dir.clone(),
        source: e,
    })?;
    let p = dir.join(format!("in-{identity}.nvx"));
    std::fs::write(&p, bytes).map_err(|e| FeatureError::Io {
        path: p.clone(),
        source: e,
    })?;
    let m = crate::checkpoint::load(&p);
    let _ = std::fs::remove_file(&p);
    let m = m?.model;
    if model_identity(&m) != identity {
        return Err(FeatureError::Config(format!(
            "model blob: version {} is not the expected {identity}",
            model_identity(&m)
        )));
    }
    Ok(m)
}

/// Parameters of the extraction stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExtractParams {
    /// The store (path or URL).
    pub store: String,
    /// Feature kind (`hidden`, `pos`, `mod`, `concat`).
    pub kind: String,
    /// The model version ([`model_identity`]).
    pub model: String,
    /// Identity of this run (done markers): model version, feature and brick selection.
    pub identity: String,
}

/// Extracts and writes the features of a task's bricks.
pub struct ExtractStage {
    params: ExtractParams,
    store: Arc<BrickStore>,
    model: Arc<InrModel>,
    kind: FeatureKind,
    /// The pending generation the coordinator started (bricks and their done markers).
    va: VectorArray,
}

impl ExtractStage {
    /// The stage over an opened store and model; the pending vector array of this run
    /// (started by [`write_features_on`] with its done markers) must exist.
    pub fn new(
        params: ExtractParams,
        store: Arc<BrickStore>,
        model: Arc<InrModel>,
    ) -> Result<Self> {
        let kind: FeatureKind = params.kind.parse().map_err(FeatureError::Config)?;
        Ok(ExtractStage {
            va: store.open_pending_vectors(&vectors_name(kind), &params.identity)?,
            kind,
            model,
            store,
            params,
        })
    }

    /// Rebuilds the stage on a worker (the model from the store, checked by version).
    pub fn build(
        v: &serde_json::Value,
        _: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let p: ExtractParams = neuvolex_tasks::codec::params(v)?;
        let store = Arc::new(BrickStore::open(Path::new(&p.store))?);
        let model = Arc::new(load_model_checked(&store, &p.model).map_err(TaskError::failed)?);
        Ok(Arc::new(
            ExtractStage::new(p, store, model).map_err(TaskError::failed)?,
        ))
    }
}

impl Stage for ExtractStage {
    type Output = u64;

    fn name(&self) -> &'static str {
        STAGE
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }

    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<u64> {
        let mut voxels = 0u64;
        for &bi in &task.bricks {
            ctx.check()?;
            let b = self.store.brick(bi)?;
            if self.va.is_done(&b)? {
                ctx.skip(1);
                continue;
            }
            let f = extract_brick(&self.model, &self.store, &b, self.kind)
                .map_err(|e| TaskError::Failed(format!("brick {bi:?}: {e}")))?;
            self.va.write_brick(&b, &f)?;
            self.va.mark_done(&b)?;
            voxels += b.voxels() as u64;
        }
        Ok(voxels)
    }
}

/// Extracts `kind` features of the training bricks (or all bricks) into the store as f16, on
/// `exec`. `store_path` is how workers open the store. A run with the same model version
/// resumes where an interrupted one stopped.
#[allow(clippy::too_many_arguments)]
pub fn write_features_on<E: Executor + ?Sized>(
    exec: &E,
    store: &BrickStore,
    store_path: &str,
    model: Arc<InrModel>,
    kind: FeatureKind,
    all_bricks: bool,
    bricks_per_task: usize,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<(ExtractReport, RunReport)> {
    let t = Instant::now();
    let name = vectors_name(kind);
    let c = kind.channels(&model);
    let bricks: Vec<[usize; 3]> = training_bricks(store, all_bricks)
        .iter()
        .map(|b| b.index)
        .collect();
    let version = model_identity(&model);
    let identity = format!(
        "{version}|{name}|{}",
        if all_bricks { "all" } else { "occupied" }
    );
    let identity = format!("{:016x}-{version}", fingerprint(identity.as_bytes()));
    let cfg_err = |e: TaskError| FeatureError::Config(e.to_string());
    // The pending generation of this run (resumed when an interrupted run of the same model
    // and selection left one), published as a whole at the end.
    let mut va = store.resume_vectors(&name, c, VectorEncoding::F16, &identity)?;
    let all: Vec<Brick> = bricks
        .iter()
        .map(|&b| store.brick(b))
        .collect::<std::result::Result<_, _>>()?;
    let pending: Vec<[usize; 3]> = va.pending(all)?.iter().map(|b| b.index).collect();
    let stage = ExtractStage::new(
        ExtractParams {
            store: store_path.to_string(),
            kind: kind_name(kind).into(),
            model: version.clone(),
            identity,
        },
        Arc::new(BrickStore::open(store.location().clone())?),
        model.clone(),
    )?;
    let tasks = neuvolex_tasks::plan(&pending, bricks_per_task, 0);
    let (_, run) = execute_ordered(exec, &stage, &tasks, progress).map_err(cfg_err)?;
    if let Some(d) = run.dead.first() {
        return Err(FeatureError::Config(format!(
            "features: {} task(s) failed, e.g. bricks {:?} after {} deliveries: {}; the rest \
             are written and a re-run finishes only the missing bricks",
            run.dead.len(),
            d.bricks,
            d.deliveries,
            d.error
        )));
    }
    if run.cancelled {
        return Err(FeatureError::Cancelled);
    }
    va.set_extra(serde_json::json!({"kind": kind, "bricks": if all_bricks { "all" } else { "occupied" }, "background": store.info().background, "inr": model.cfg, "model": version}));
    va.finish()?;
    Ok((
        ExtractReport {
            name,
            channels: c,
            bricks: bricks.len(),
            voxels: bricks
                .iter()
                .filter_map(|b| store.brick(*b).ok())
                .map(|b| b.voxels() as u64)
                .sum(),
            seconds: t.elapsed().as_secs_f64(),
        },
        run,
    ))
}

fn kind_name(k: FeatureKind) -> &'static str {
    match k {
        FeatureKind::Hidden => "hidden",
        FeatureKind::Pos => "pos",
        FeatureKind::Mod => "mod",
        FeatureKind::Concat => "concat",
        FeatureKind::Region => "region",
    }
}
