//! Viewpoint recommendation as brick stages, so any executor (rayon, the service's actors,
//! cluster workers) runs it: the k-means initialisation sample ([`SampleStage`]), one Lloyd
//! pass per iteration whose tasks return per-brick [`Partial`]s merged in brick order
//! ([`PassStage`]; bit for bit the single-process sums), and the final pass that also returns
//! each brick's [`ClusterPartial`] for the view entropy ([`ViewStage`]). The coordinator keeps
//! the centroids, updates them between rounds and broadcasts them as a blob.

use crate::kmeans::{
    draw_rows, sample_order, sample_want, Algorithm, KMeans, Partial, SAMPLE_CHUNKS,
};
use crate::pipeline::{RecommendConfig, Recommendation};
use crate::scores::{score_views, select, Aggregator};
use crate::{fibonacci_sphere, ClusterPartial, Result, ViewpointError};
use neuvolex_bricks::lru::Lru;
use neuvolex_bricks::rng::Rng;
use neuvolex_classify::pipeline::{FeatureSpec, OpenedFeatures};
use neuvolex_tasks::{
    codec, execute_ordered, fingerprint, Blob, Blobs, DynStage, Executor, RunEvent, RunReport,
    Stage, Task, TaskCtx, TaskError,
};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

/// Name of the sampling stage.
pub const SAMPLE: &str = "kmeans-sample";
/// Name of the Lloyd pass stage.
pub const PASS: &str = "kmeans-pass";
/// Name of the final pass with view partials.
pub const VIEWS: &str = "view-partials";

type FeatureLru = Lru<(u64, [usize; 3]), Arc<Vec<f32>>>;
static CACHE: OnceLock<FeatureLru> = OnceLock::new();

/// Sets the budget of the process-wide cache of feature bricks that k-means passes share
/// (effective before its first use; otherwise `NEUVOLEX_FEATURE_CACHE_MIB`, default 1024).
pub fn set_feature_cache_mib(mib: usize) {
    let _ = CACHE.set(Lru::new(mib.max(1) << 20));
}

/// Feature bricks a process keeps between rounds, keyed by feature spec and brick.
fn cache() -> &'static FeatureLru {
    CACHE.get_or_init(|| {
        let mib = std::env::var("NEUVOLEX_FEATURE_CACHE_MIB")
            .ok()
            .and_then(|v| v.parse::<usize>().ok())
            .unwrap_or(1024);
        Lru::new(mib << 20)
    })
}

/// The features of one brick through the process-wide cache, checked finite.
fn brick_rows(
    src: &OpenedFeatures,
    key: u64,
    b: [usize; 3],
) -> neuvolex_tasks::Result<Arc<Vec<f32>>> {
    cache().get_or_try_insert(&(key, b), || {
        let fx = src.features().map_err(TaskError::failed)?;
        let brick = src.store.brick(b)?;
        let rows = fx
            .brick(&brick)
            .map_err(|e| TaskError::Failed(format!("brick {b:?}: {e}")))?;
        let cost = rows.len() * 4;
        Ok::<_, TaskError>((Arc::new(rows), cost))
    })
}

fn spec_key(s: &FeatureSpec) -> u64 {
    fingerprint(serde_json::to_string(s).unwrap_or_default().as_bytes())
}

fn decode_blob<T: serde::de::DeserializeOwned>(
    blobs: &dyn Blobs,
    key: &str,
) -> neuvolex_tasks::Result<T> {
    codec::decode(&blobs.get(key)?)
}

fn blob_of<T: Serialize>(prefix: &str, v: &T) -> Result<Blob> {
    let bytes = codec::encode(v).map_err(|e| ViewpointError::Input(e.to_string()))?;
    Ok(Blob {
        key: format!("{prefix}-{:016x}", fingerprint(&bytes)),
        bytes: Arc::new(bytes),
    })
}

/// Parameters of the sampling stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SampleParams {
    /// Where the features come from.
    pub source: FeatureSpec,
    /// Blob of the rows to draw per brick (`BTreeMap<[usize; 3], Vec<usize>>`).
    pub picks: String,
}

/// Draws the initialisation rows of its bricks.
pub struct SampleStage {
    params: SampleParams,
    src: OpenedFeatures,
    key: u64,
    picks: BTreeMap<[usize; 3], Vec<usize>>,
    blob: Option<Blob>,
}

impl SampleStage {
    /// Rebuilds the stage on a worker.
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let params: SampleParams = neuvolex_tasks::codec::params(v)?;
        let picks: Vec<([usize; 3], Vec<usize>)> = decode_blob(blobs, &params.picks)?;
        let src = params.source.open_with(blobs).map_err(TaskError::failed)?;
        Ok(Arc::new(SampleStage {
            key: spec_key(&params.source),
            picks: picks.into_iter().collect(),
            params,
            src,
            blob: None,
        }))
    }
}

impl Stage for SampleStage {
    type Output = Vec<Vec<f32>>;
    fn name(&self) -> &'static str {
        SAMPLE
    }
    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }
    fn blobs(&self) -> Vec<Blob> {
        let mut v: Vec<Blob> = self.blob.iter().cloned().collect();
        v.extend(self.src.blobs());
        v
    }
    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<Vec<Vec<f32>>> {
        let dim = self.src.features().map_err(TaskError::failed)?.channels();
        task.bricks
            .iter()
            .map(|b| {
                ctx.check()?;
                let rows = brick_rows(&self.src, self.key, *b)?;
                let mut out = Vec::new();
                for &r in self.picks.get(b).map(Vec::as_slice).unwrap_or(&[]) {
                    out.extend_from_slice(&rows[r * dim..(r + 1) * dim]);
                }
                Ok(out)
            })
            .collect()
    }
}

/// Parameters of a Lloyd pass (and of the final pass with view partials).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PassParams {
    /// Where the features come from.
    pub source: FeatureSpec,
    /// Blob of the centroids (`KMeans`).
    pub centroids: String,
}

/// One Lloyd pass: each brick's assignment statistics for the broadcast centroids.
pub struct PassStage {
    params: PassParams,
    src: OpenedFeatures,
    key: u64,
    km: KMeans,
    blob: Option<Blob>,
}

/// The final pass: assignment statistics and cluster partials (gradients) of each brick.
pub struct ViewStage(PassStage);

impl PassStage {
    fn from_params(v: &serde_json::Value, blobs: &dyn Blobs) -> neuvolex_tasks::Result<PassStage> {
        let params: PassParams = neuvolex_tasks::codec::params(v)?;
        let km: KMeans = decode_blob(blobs, &params.centroids)?;
        let src = params.source.open_with(blobs).map_err(TaskError::failed)?;
        Ok(PassStage {
            key: spec_key(&params.source),
            params,
            src,
            km,
            blob: None,
        })
    }

    /// Rebuilds a Lloyd pass on a worker.
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        Ok(Arc::new(Self::from_params(v, blobs)?))
    }

    fn partial(&self, b: [usize; 3]) -> neuvolex_tasks::Result<(Arc<Vec<f32>>, Partial)> {
        let rows = brick_rows(&self.src, self.key, b)?;
        Ok((rows.clone(), self.km.partial(&rows)))
    }
}

impl ViewStage {
    /// Rebuilds the final pass on a worker.
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        Ok(Arc::new(ViewStage(PassStage::from_params(v, blobs)?)))
    }
}

impl Stage for PassStage {
    type Output = Vec<Partial>;
    fn name(&self) -> &'static str {
        PASS
    }
    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }
    fn blobs(&self) -> Vec<Blob> {
        let mut v: Vec<Blob> = self.blob.iter().cloned().collect();
        v.extend(self.src.blobs());
        v
    }
    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<Vec<Partial>> {
        task.bricks
            .iter()
            .map(|&b| {
                ctx.check()?;
                Ok(self.partial(b)?.1)
            })
            .collect()
    }
}

impl Stage for ViewStage {
    type Output = Vec<(Partial, ClusterPartial)>;
    fn name(&self) -> &'static str {
        VIEWS
    }
    fn params(&self) -> serde_json::Value {
        self.0.params()
    }
    fn blobs(&self) -> Vec<Blob> {
        self.0.blobs()
    }
    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<Self::Output> {
        let s = &self.0;
        task.bricks
            .iter()
            .map(|&b| {
                ctx.check()?;
                let (rows, p) = s.partial(b)?;
                let labels = s.km.assign(&rows);
                let brick = s.src.store.brick(b)?;
                let g = s.src.store.derived(&brick)?.gradient;
                let cp =
                    ClusterPartial::from_brick(s.km.k(), &labels, &g, s.src.store.info().spacing)
                        .map_err(TaskError::failed)?;
                Ok((p, cp))
            })
            .collect()
    }
}

/// Recommends views with every per-brick step run as tasks on `exec` (Lloyd k-means only:
/// mini-batch updates are sequential). Equals [`crate::recommend`] over the same features bit
/// for bit. `on_brick` sees the aggregation as view partials arrive.
pub fn recommend_on<E: Executor + ?Sized>(
    exec: &E,
    src: OpenedFeatures,
    cfg: &RecommendConfig,
    bricks_per_task: usize,
    progress: &mut dyn FnMut(RunEvent),
    on_brick: &mut dyn FnMut(usize, &Aggregator),
) -> Result<(Recommendation, RunReport)> {
    let kc = &cfg.kmeans;
    if kc.algorithm != Algorithm::Lloyd {
        return Err(ViewpointError::Param(
            "distributed k-means runs Lloyd iterations (mini-batch updates are sequential)".into(),
        ));
    }
    if kc.k == 0 || kc.k > u16::MAX as usize {
        return Err(ViewpointError::Param(format!(
            "k = {} must be 1..=65535",
            kc.k
        )));
    }
    let bricks: Vec<[usize; 3]> = src
        .store
        .occupied_bricks(None)
        .iter()
        .map(|b| b.index)
        .collect();
    if bricks.is_empty() {
        return Err(ViewpointError::Input(
            "no feature rows to cluster (every brick is empty)".into(),
        ));
    }
    let dim = src
        .features()
        .map_err(|e| ViewpointError::Input(e.to_string()))?
        .channels();
    let err = |e: TaskError| ViewpointError::Input(e.to_string());
    let mut total = RunReport::default();
    let mut check = |r: &RunReport| -> Result<()> {
        total.absorb(r);
        if let Some(d) = r.dead.first() {
            return Err(ViewpointError::Input(format!(
                "{}: task {} (bricks {:?}) failed after {} deliveries: {}",
                r.stage, d.task, d.bricks, d.deliveries, d.error
            )));
        }
        if r.cancelled {
            return Err(ViewpointError::Input("cancelled".into()));
        }
        Ok(())
    };
    // 1. The initialisation sample: the same bricks and rows as the single-process fit.
    let t0 = Instant::now();
    let mut rng = Rng::new(kc.seed);
    let order = sample_order(bricks.len(), &mut rng);
    let want = sample_want(bricks.len(), kc);
    let store = src.store.clone();
    let picks: Vec<([usize; 3], Vec<usize>)> = order
        .iter()
        .take(SAMPLE_CHUNKS)
        .map(|&c| {
            let n = store.brick(bricks[c]).map(|b| b.voxels()).unwrap_or(0);
            (bricks[c], draw_rows(&mut rng, want, n))
        })
        .collect();
    let key = spec_key(&src.spec);
    let pick_blob = blob_of("picks", &picks)?;
    let sample_stage = SampleStage {
        params: SampleParams {
            source: src.spec.clone(),
            picks: pick_blob.key.clone(),
        },
        picks: picks.iter().cloned().collect(),
        key,
        src,
        blob: Some(pick_blob),
    };
    let order_bricks: Vec<[usize; 3]> = picks.iter().map(|p| p.0).collect();
    let tasks = neuvolex_tasks::plan(&order_bricks, bricks_per_task, 0);
    let (outs, rep) = execute_ordered(exec, &sample_stage, &tasks, progress).map_err(err)?;
    check(&rep)?;
    let sample: Vec<f32> = outs.into_iter().flatten().flatten().flatten().collect();
    if let Some(i) = sample.iter().position(|v| !v.is_finite()) {
        return Err(ViewpointError::Input(format!(
            "feature value {} at row {} is not finite",
            sample[i],
            i / dim
        )));
    }
    let src = sample_stage.src;
    let (km, tol) = KMeans::seed(&sample, dim, kc, &mut rng);
    // 2. Lloyd passes: per-brick partials merged in brick order. On a cluster, passes batch
    // more bricks per task when the queue's round trip is a large share of a task's work
    // (`adapt_per_task`); tasks stay runs of bricks in order, so the merge is the same.
    let mut per_task = bricks_per_task.max(1);
    let mut round = 0u32;
    let km = km.lloyd_iterations(&sample, tol, kc, &mut |km: &KMeans| {
        round += 1;
        let blob = blob_of("centroids", km)?;
        let stage = PassStage {
            params: PassParams {
                source: src.spec.clone(),
                centroids: blob.key.clone(),
            },
            src: src.share(),
            key,
            km: km.clone(),
            blob: Some(blob),
        };
        let t = neuvolex_tasks::plan(&bricks, per_task, round);
        let (outs, rep) = execute_ordered(exec, &stage, &t, progress).map_err(err)?;
        check(&rep)?;
        per_task = neuvolex_tasks::adapt_per_task(per_task, &rep, bricks.len());
        let mut total = Partial::new(km.k(), dim);
        for p in outs.into_iter().flatten().flatten() {
            total.merge(&p);
        }
        Ok(total)
    })?;
    let kmeans_seconds = t0.elapsed().as_secs_f64();
    // 3. The final assignment with view partials, merged as they arrive.
    let t1 = Instant::now();
    let blob = blob_of("centroids", &km)?;
    let stage = ViewStage(PassStage {
        params: PassParams {
            source: src.spec.clone(),
            centroids: blob.key.clone(),
        },
        key,
        km: km.clone(),
        src,
        blob: Some(blob),
    });
    let mut agg = Aggregator::new(km.k());
    let mut arrived = 0usize;
    let tasks: Vec<Task> = neuvolex_tasks::plan(&bricks, per_task, round + 1);
    let mut per: Vec<Option<Vec<(Partial, ClusterPartial)>>> = vec![None; tasks.len()];
    let rep = exec
        .execute(&stage, &tasks, &mut |e| {
            if let neuvolex_tasks::Event::Done(d) = e {
                for (_, cp) in &d.output {
                    agg.add(cp);
                    arrived += 1;
                    on_brick(arrived, &agg);
                }
                per[d.task as usize] = Some(d.output);
            }
        })
        .map_err(err)?;
    check(&rep)?;
    // The reported inertia and counts: the final partials merged in brick order.
    let mut fin = Partial::new(km.k(), dim);
    for (p, _) in per.into_iter().flatten().flatten() {
        fin.merge(&p);
    }
    let mut km = km;
    km.inertia = fin.inertia;
    km.counts = fin.counts;
    let views = fibonacci_sphere(cfg.views);
    let summary = agg.partial().summary();
    let scores = score_views(&summary, &views)?;
    let selection = select(&summary, &scores, &cfg.select)?;
    Ok((
        Recommendation {
            kmeans: km,
            summary,
            scores,
            selection,
            kmeans_seconds,
            scoring_seconds: t1.elapsed().as_secs_f64(),
        },
        total,
    ))
}
