//! Data-parallel INR training on any [`Executor`] (in process, or NATS cluster workers), with
//! one model for the whole volume.
//!
//! The single-node trainer consumes one seeded stream of batches (epochs → tile groups →
//! batches, [`epoch_groups`] / [`group_order`]). Distributed training cuts the same stream into
//! rounds of `replicas x sync_steps` batches. In round `r` the coordinator publishes the model
//! and its Adam state (a checkpoint blob); replica `w` (task `w`, on whichever worker takes it)
//! runs `sync_steps` consecutive batches of the round with the trainer's own [`step`], from the
//! published state, and returns its parameters and Adam moments: all dense ones, and the
//! hash-table entries its steps touched. The coordinator merges in replica order:
//!
//! - dense weights and their Adam moments: the plain mean over the replicas;
//! - each hash-table entry (value and moments): the mean over the replicas that touched it
//!   (an entry no replica touched keeps its value; a replica that did not touch an entry does
//!   not pull it back towards the old value);
//! - Adam's step count advances by the longest replica's steps.
//!
//! A task's output depends only on the published state and its batch range, and the merge runs
//! in replica order, so the same seed and replica count give the same model bit for bit,
//! whichever worker process takes which replica. With one replica the merge is the identity
//! and the result equals [`crate::train`] bit for bit.

use crate::adam::{Adam, Rates};
use crate::checkpoint::{self, TrainState};
use crate::config::{InrConfig, TableAdam, TrainConfig};
use crate::error::{FeatureError, Result};
use crate::model::InrModel;
use crate::stage::model_identity;
use crate::tile::Tile;
use crate::train::{
    epoch_groups, group_order, psnr, start, step, training_bricks, StepBuffers, TrainEvent, Trained,
};
use neuvolex_bricks::{Brick, BrickStore};
use neuvolex_tasks::{
    execute_ordered, Blob, Blobs, DynStage, Executor, RunEvent, RunReport, Stage, Task, TaskCtx,
    TaskError,
};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// The stage's name.
pub const STAGE: &str = "train-round";

/// A position in the batch stream: epoch, tile group within it, batch within the group.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Cursor {
    epoch: u64,
    group: usize,
    batch: u64,
}

/// The batch stream of a training run: which tile groups an epoch visits and how many batches
/// each yields. Every replica derives it from the store and the configuration alone.
struct Stream<'a> {
    bricks: &'a [Brick],
    seed: u64,
    tile_bricks: usize,
    batch: u64,
}

impl Stream<'_> {
    /// Voxels of each group of `epoch`.
    fn group_voxels(&self, epoch: u64) -> Vec<u64> {
        epoch_groups(self.bricks, self.seed, epoch, self.tile_bricks)
            .iter()
            .map(|g| g.iter().map(|b| b.voxels() as u64).sum())
            .collect()
    }

    /// Where global batch `n` lies.
    fn locate(&self, mut n: u64) -> Cursor {
        let mut epoch = 0;
        loop {
            for (group, v) in self.group_voxels(epoch).into_iter().enumerate() {
                let nb = v.div_ceil(self.batch);
                if n < nb {
                    return Cursor {
                        epoch,
                        group,
                        batch: n,
                    };
                }
                n -= nb;
            }
            epoch += 1;
        }
    }

    /// Batches until `budget` samples are spent (the single-node trainer stops after the step
    /// that reaches its budget).
    fn batches_for(&self, budget: u64) -> u64 {
        let (mut n, mut samples, mut epoch) = (0u64, 0u64, 0u64);
        loop {
            for v in self.group_voxels(epoch) {
                if samples + v < budget {
                    samples += v;
                    n += v.div_ceil(self.batch);
                } else {
                    return n + (budget - samples).div_ceil(self.batch);
                }
            }
            epoch += 1;
        }
    }
}

/// A replica's result: its parameters and Adam moments after its steps (all dense ones, the
/// hash-table entries it touched), with its loss statistics.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ReplicaUpdate {
    /// Steps taken.
    pub steps: u64,
    /// Samples used.
    pub samples: u64,
    /// Sum of squared intensity errors over those samples.
    pub sse: f64,
    /// Loss of the last step.
    pub loss: f64,
    /// Dense parameters.
    pub dense: Vec<f32>,
    /// Dense first moments.
    pub m_dense: Vec<f32>,
    /// Dense second moments.
    pub v_dense: Vec<f32>,
    /// Touched hash-table entries (global entry index: level x entries + entry), ascending.
    pub rows: Vec<u32>,
    /// Their parameters (`features` per entry).
    pub table: Vec<f32>,
    /// Their first moments.
    pub m_table: Vec<f32>,
    /// Their second moments.
    pub v_table: Vec<f32>,
}

/// Parameters of one round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundParams {
    /// The store (path or URL).
    pub store: String,
    /// The published state (a checkpoint blob with the model, Adam and training settings).
    pub blob: String,
    /// The round.
    pub round: u32,
    /// First global batch of the round.
    pub first_batch: u64,
    /// Batches per replica.
    pub sync_steps: u64,
    /// End of the round's batches (exclusive; the last round may be short).
    pub end_batch: u64,
}

/// The state a round starts from.
struct State {
    model: InrModel,
    adam: Adam,
    tc: TrainConfig,
}

/// One round of data-parallel training: task `w` is replica `w`.
pub struct RoundStage {
    params: RoundParams,
    store: Arc<BrickStore>,
    state: Arc<State>,
    bricks: Vec<Brick>,
}

/// Tile groups a worker process loaded, with their sample order (the next round usually
/// continues in the same group).
type GroupKey = (String, u64, u64, usize, usize, String);
/// A loaded tile group and its seeded sample order.
type Group = Arc<(Vec<Tile>, Vec<(u32, u32)>)>;
static GROUPS: Mutex<Vec<(GroupKey, Group)>> = Mutex::new(Vec::new());

fn blob_key(model: &InrModel, adam: &Adam) -> String {
    let mut h = crc32fast::Hasher::new();
    for a in [&adam.m_dense, &adam.v_dense, &adam.m_table, &adam.v_table] {
        h.update(bytemuck::cast_slice(a));
    }
    format!(
        "inr-train-{}-{:08x}-t{}",
        model_identity(model),
        h.finalize(),
        adam.t
    )
}

impl RoundStage {
    /// Rebuilds the round on a worker from the published state.
    pub fn build(
        v: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let p: RoundParams = neuvolex_tasks::codec::params(v)?;
        let bytes = blobs.get(&p.blob)?;
        let l = checkpoint::from_bytes(&format!("blob {}", p.blob), &bytes)
            .map_err(TaskError::failed)?;
        let (Some(adam), Some(tc)) = (l.adam, l.header.train) else {
            return Err(TaskError::Failed(format!(
                "blob {}: a model without training state",
                p.blob
            )));
        };
        let state = State {
            model: l.model,
            adam,
            tc,
        };
        if blob_key(&state.model, &state.adam) != p.blob {
            return Err(TaskError::Failed(format!(
                "blob {}: its contents are another version",
                p.blob
            )));
        }
        let store = Arc::new(BrickStore::open(Path::new(&p.store))?);
        Ok(Arc::new(RoundStage::new(p, store, Arc::new(state))))
    }

    fn new(params: RoundParams, store: Arc<BrickStore>, state: Arc<State>) -> Self {
        let bricks = training_bricks(&store, state.tc.include_empty);
        RoundStage {
            params,
            store,
            state,
            bricks,
        }
    }

    fn stream(&self) -> Stream<'_> {
        Stream {
            bricks: &self.bricks,
            seed: self.state.tc.seed,
            tile_bricks: self.state.tc.tile_bricks,
            batch: self.state.tc.batch as u64,
        }
    }

    /// The tiles and sample order of group `group` of `epoch` (cached per worker process).
    fn group(&self, epoch: u64, group: usize) -> Result<Group> {
        let tc = &self.state.tc;
        let key: GroupKey = (
            self.params.store.clone(),
            tc.seed,
            epoch,
            group,
            tc.tile_bricks,
            format!("{:?}", self.state.model.cfg),
        );
        if let Some(g) = GROUPS
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .find(|(k, _)| *k == key)
        {
            return Ok(g.1.clone());
        }
        let bricks = &epoch_groups(&self.bricks, tc.seed, epoch, tc.tile_bricks)[group];
        let tiles: Vec<Tile> = bricks
            .iter()
            .map(|b| Tile::load_for(&self.store, b, &self.state.model.cfg))
            .collect::<std::result::Result<_, _>>()?;
        let order = group_order(&tiles, tc.seed, epoch, group);
        let g = Arc::new((tiles, order));
        let mut c = GROUPS.lock().unwrap_or_else(|p| p.into_inner());
        if c.len() >= 4 {
            c.remove(0);
        }
        c.push((key, g.clone()));
        Ok(g)
    }

    /// Replica `w`'s batches (global indices).
    fn range(&self, w: u32) -> (u64, u64) {
        let p = &self.params;
        let a = (p.first_batch + w as u64 * p.sync_steps).min(p.end_batch);
        (a, (a + p.sync_steps).min(p.end_batch))
    }

    /// Runs replica `w`: the trainer's [`step`] on its batches from the published state.
    fn replica(&self, w: u32, ctx: &TaskCtx<'_>) -> Result<ReplicaUpdate> {
        let (a, b) = self.range(w);
        let mut model = self.state.model.clone();
        let mut adam = self.state.adam.clone();
        let tc = &self.state.tc;
        let rates = Rates {
            lr: tc.lr,
            lr_table: tc.lr_table,
            mode: tc.table_adam,
        };
        let mut buf = StepBuffers::new(&model);
        let mut touched = vec![vec![0u64; model.grid.t.div_ceil(64)]; model.grid.levels.len()];
        let stream = self.stream();
        let mut cur = stream.locate(a);
        let (mut samples, mut sse, mut loss) = (0u64, 0f64, 0f64);
        let mut groups = stream.group_voxels(cur.epoch);
        for n in a..b {
            ctx.check().map_err(|_| FeatureError::Cancelled)?;
            let g = self.group(cur.epoch, cur.group)?;
            let (tiles, order) = (&g.0, &g.1);
            let lo = (cur.batch * tc.batch as u64) as usize;
            let batch = &order[lo..(lo + tc.batch).min(order.len())];
            let st = step(
                &mut model,
                &mut adam,
                &mut buf,
                tiles,
                batch,
                rates,
                n,
                Some(&mut touched),
            )?;
            samples += batch.len() as u64;
            sse += st.sse;
            loss = st.loss;
            cur.batch += 1;
            if cur.batch >= groups[cur.group].div_ceil(tc.batch as u64) {
                cur.batch = 0;
                cur.group += 1;
                if cur.group >= groups.len() {
                    cur.group = 0;
                    cur.epoch += 1;
                    groups = stream.group_voxels(cur.epoch);
                }
            }
        }
        let (t, f) = (model.grid.t, model.grid.f);
        let mut up = ReplicaUpdate {
            steps: b - a,
            samples,
            sse,
            loss,
            dense: model.dense,
            m_dense: adam.m_dense,
            v_dense: adam.v_dense,
            rows: Vec::new(),
            table: Vec::new(),
            m_table: Vec::new(),
            v_table: Vec::new(),
        };
        for (l, mark) in touched.iter().enumerate() {
            for (wi, &word) in mark.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let e = wi * 64 + bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let row = l * t + e;
                    up.rows.push(row as u32);
                    let r = row * f..(row + 1) * f;
                    up.table.extend_from_slice(&model.table[r.clone()]);
                    up.m_table.extend_from_slice(&adam.m_table[r.clone()]);
                    up.v_table.extend_from_slice(&adam.v_table[r]);
                }
            }
        }
        Ok(up)
    }
}

impl Stage for RoundStage {
    type Output = ReplicaUpdate;

    fn name(&self) -> &'static str {
        STAGE
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }

    fn blobs(&self) -> Vec<Blob> {
        let s = &self.state;
        let state = TrainState::default();
        match checkpoint::to_bytes(&s.model, Some((&s.tc, &state, &s.adam))) {
            Ok(b) => vec![Blob {
                key: self.params.blob.clone(),
                bytes: Arc::new(b),
            }],
            Err(e) => {
                tracing::error!("cannot encode the model for the workers: {e}");
                Vec::new()
            }
        }
    }

    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<ReplicaUpdate> {
        self.replica(task.index, ctx).map_err(|e| match e {
            FeatureError::Cancelled => TaskError::Cancelled,
            e => TaskError::Failed(format!(
                "training round {} replica {}: {e}",
                self.params.round, task.index
            )),
        })
    }
}

/// Merges the replicas' updates (in replica order) into `model` and `adam`: dense values and
/// moments by the plain mean, each table entry by the mean over the replicas that touched it.
pub fn merge(model: &mut InrModel, adam: &mut Adam, ups: &[ReplicaUpdate]) {
    let n = ups.len();
    if n == 0 {
        return;
    }
    // Sums start from the first replica's value (not from 0, which would turn -0.0 into
    // 0.0), so one replica merges to itself bit for bit.
    let mean = |dst: &mut [f32], get: &dyn Fn(&ReplicaUpdate) -> &[f32]| {
        for (i, d) in dst.iter_mut().enumerate() {
            let mut s = get(&ups[0])[i];
            for u in &ups[1..] {
                s += get(u)[i];
            }
            *d = if n > 1 { s / n as f32 } else { s };
        }
    };
    mean(&mut model.dense, &|u| &u.dense);
    mean(&mut adam.m_dense, &|u| &u.m_dense);
    mean(&mut adam.v_dense, &|u| &u.v_dense);
    let f = model.grid.f;
    let len = model.table.len();
    let (mut sp, mut sm, mut sv) = (vec![0f32; len], vec![0f32; len], vec![0f32; len]);
    let mut count = vec![0u16; len / f];
    for u in ups {
        for (k, &row) in u.rows.iter().enumerate() {
            let row = row as usize;
            let first = count[row] == 0;
            count[row] += 1;
            for c in 0..f {
                let (i, j) = (row * f + c, k * f + c);
                if first {
                    (sp[i], sm[i], sv[i]) = (u.table[j], u.m_table[j], u.v_table[j]);
                } else {
                    sp[i] += u.table[j];
                    sm[i] += u.m_table[j];
                    sv[i] += u.v_table[j];
                }
            }
        }
    }
    for (row, &c) in count.iter().enumerate() {
        if c > 0 {
            let k = if c > 1 { c as f32 } else { 1.0 };
            for i in row * f..(row + 1) * f {
                model.table[i] = if c > 1 { sp[i] / k } else { sp[i] };
                adam.m_table[i] = if c > 1 { sm[i] / k } else { sm[i] };
                adam.v_table[i] = if c > 1 { sv[i] / k } else { sv[i] };
            }
        }
    }
    adam.t += ups.iter().map(|u| u.steps).max().unwrap_or(0);
}

/// How distributed training runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Replication {
    /// Data-parallel replicas (tasks per round); fixed for a run, whatever the worker count.
    pub replicas: u32,
    /// Optimiser steps each replica takes between synchronisations.
    pub sync_steps: u64,
}

/// Trains the INR on `store` with `rep.replicas` data-parallel replicas on `exec`, synchronising
/// every `rep.sync_steps` steps, on the same sample budget as [`crate::train`]. `store_path` is
/// how workers open the store. Emits the trainer's events (a `Step` per round).
#[allow(clippy::too_many_arguments)]
pub fn train_on<E: Executor + ?Sized>(
    exec: &E,
    store: &BrickStore,
    store_path: &str,
    inr: &InrConfig,
    cfg: &TrainConfig,
    rep: Replication,
    progress: &mut dyn FnMut(RunEvent),
    events: &mut dyn FnMut(TrainEvent),
) -> Result<(Trained, RunReport)> {
    if !(1..=1024).contains(&rep.replicas) || !(1..=1_000_000).contains(&rep.sync_steps) {
        return Err(FeatureError::Config(format!(
            "replicas {} must be 1..=1024 and sync steps {} 1..=1000000",
            rep.replicas, rep.sync_steps
        )));
    }
    if cfg.table_adam == TableAdam::Dense {
        return Err(FeatureError::Config(
            "distributed training merges the table entries each replica touched: it needs \
             --table-adam lazy"
                .into(),
        ));
    }
    let run = start(store, inr, cfg, None)?;
    events(run.started(store));
    let t0 = Instant::now();
    let (mut model, mut adam, tc) = (run.model, run.adam, run.tc);
    let stream = Stream {
        bricks: &run.bricks,
        seed: tc.seed,
        tile_bricks: tc.tile_bricks,
        batch: tc.batch as u64,
    };
    let total = match run.budget_samples {
        Some(b) => stream.batches_for(b),
        None => u64::MAX,
    };
    let per_round = rep.replicas as u64 * rep.sync_steps;
    let shared = Arc::new(BrickStore::open(store.location().clone())?);
    let mut state = TrainState::default();
    let mut report = RunReport::default();
    let mut last_psnr = 0.0;
    let mut round = 0u32;
    let stopped_by = loop {
        let first = round as u64 * per_round;
        if first >= total {
            break if tc.budget.samples.is_some_and(|s| state.samples >= s) {
                "samples"
            } else {
                "epochs"
            };
        }
        if tc
            .budget
            .seconds
            .is_some_and(|s| t0.elapsed().as_secs_f64() >= s)
        {
            break "seconds";
        }
        let end = (first + per_round).min(total);
        let tasks: Vec<Task> = (0..rep.replicas)
            .filter(|&w| first + w as u64 * rep.sync_steps < end)
            .map(|w| Task {
                index: w,
                round,
                bricks: Vec::new(),
            })
            .collect();
        let st = Arc::new(State {
            model,
            adam,
            tc: tc.clone(),
        });
        let stage = RoundStage::new(
            RoundParams {
                store: store_path.to_string(),
                blob: blob_key(&st.model, &st.adam),
                round,
                first_batch: first,
                sync_steps: rep.sync_steps,
                end_batch: end,
            },
            shared.clone(),
            st.clone(),
        );
        let (outs, r) = execute_ordered(exec, &stage, &tasks, progress)
            .map_err(|e| FeatureError::Config(e.to_string()))?;
        report.absorb(&r);
        if let Some(d) = r.dead.first() {
            return Err(FeatureError::Config(format!(
                "training round {round}: replica {} failed after {} deliveries: {}",
                d.task, d.deliveries, d.error
            )));
        }
        if r.cancelled {
            return Err(FeatureError::Cancelled);
        }
        let ups: Vec<ReplicaUpdate> = outs.into_iter().flatten().collect();
        // The round's model is superseded: its blob would only fill the store.
        exec.forget_blobs(std::slice::from_ref(&stage.params.blob));
        drop(stage);
        let st = Arc::try_unwrap(st).unwrap_or_else(|a| State {
            model: a.model.clone(),
            adam: a.adam.clone(),
            tc: a.tc.clone(),
        });
        (model, adam) = (st.model, st.adam);
        merge(&mut model, &mut adam, &ups);
        let (n, sse): (u64, f64) = ups
            .iter()
            .fold((0, 0.0), |a, u| (a.0 + u.samples, a.1 + u.sse));
        state.step += ups.iter().map(|u| u.steps).sum::<u64>();
        state.samples += n;
        state.seconds = t0.elapsed().as_secs_f64();
        last_psnr = psnr(sse / n.max(1) as f64);
        events(TrainEvent::Step {
            step: state.step,
            epoch: state.samples as f64 / run.voxels.max(1) as f64,
            samples: state.samples,
            loss: ups.last().map(|u| u.loss).unwrap_or(0.0),
            psnr: last_psnr,
            samples_per_sec: state.samples as f64 / state.seconds.max(1e-9),
            seconds: state.seconds,
        });
        round += 1;
    };
    events(TrainEvent::Finished {
        steps: state.step,
        samples: state.samples,
        seconds: state.seconds,
        psnr: last_psnr,
        stopped_by: stopped_by.into(),
    });
    Ok((
        Trained {
            model,
            state,
            psnr: last_psnr,
        },
        report,
    ))
}
