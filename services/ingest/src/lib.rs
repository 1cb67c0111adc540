//! # neuvolex-ingest
//!
//! Ingest as a brick stage ([`IngestStage`]), so that `neuvolex ingest --cluster` spreads a
//! volume's ingest over workers and writes the same store, byte for byte, as the sequential
//! [`neuvolex_bricks::ingest`].
//!
//! - A task is a run of slabs (one brick, or one shard, of z-slices each; the task's bricks are
//!   `[0, 0, slab]`). It reads its slabs from the source file, which every worker must be able
//!   to read at the same path (a shared file system), writes them at every pyramid level
//!   ([`neuvolex_bricks::SlabWriter`]: whole chunks, so tasks never share a chunk), and returns
//!   its [`neuvolex_bricks::Scanner`]: counts, extremes, per-brick ranges and per-slice sums.
//! - The coordinator merges the scanners; the merge is exact whatever the split, so the
//!   statistics equal the sequential ingest's. Wide and float types need a second round for
//!   the percentiles: tasks histogram the stored level 0 over the merged range, and the
//!   histograms merge exactly too.
//! - The coordinator then writes the per-brick ranges and the root metadata once, and
//!   publishes the store ([`neuvolex_bricks::IngestTarget`]: a rename on a file system, the
//!   root metadata last on S3).
//! - Tasks are idempotent (a redelivered slab writes the same chunks). An ingest is not
//!   resumable: its partials live only in the coordinator, so a re-run after a crash starts
//!   over, with the previous store untouched until the new one is published.

#![warn(missing_docs)]

use neuvolex_bricks::stats::FineHistogram;
use neuvolex_bricks::{
    first_raw_value, open_volume, Backend, BrickError, IngestLabels, IngestOptions, IngestTarget,
    Scanner, SlabWriter, StoreInfo, StoreLocation,
};
use neuvolex_formats::{RawSpec, VolumeMeta, VolumeSource};
use neuvolex_tasks::{
    execute_ordered, plan, Blobs, DynStage, Executor, RunEvent, RunReport, Stage, Task, TaskCtx,
    TaskError,
};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// The stage's name (what workers dispatch on).
pub const STAGE: &str = "ingest";

/// Errors of a distributed ingest.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// A store or source error.
    #[error(transparent)]
    Bricks(#[from] BrickError),
    /// An executor error.
    #[error(transparent)]
    Tasks(#[from] TaskError),
    /// Tasks failed (the message names them and their errors).
    #[error("{0}")]
    Failed(String),
}

impl From<neuvolex_formats::FormatError> for IngestError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        IngestError::Bricks(e.into())
    }
}

/// Result with [`IngestError`].
pub type Result<T, E = IngestError> = std::result::Result<T, E>;

/// Parameters of the ingest stage: everything a worker needs to rebuild it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IngestParams {
    /// The source file (an absolute path every worker can read, or an `s3://` OME-Zarr).
    pub source: String,
    /// The layout of a headerless raw source.
    pub raw: Option<RawSpec>,
    /// Where the store is being written ([`IngestTarget::location`]); named `store` like every
    /// stage's store, so a worker's `--store-root` applies to it.
    pub store: String,
    /// Brick size, sharding, compression, NaN/Inf policy.
    pub opts: IngestOptions,
    /// The source's grid and type as the coordinator read it: a worker that reads something
    /// else (another file at that path) refuses to write.
    pub meta: VolumeMeta,
    /// The volume's first raw value (the shift of the shifted sums; see
    /// [`neuvolex_bricks::first_raw_value`]).
    pub first_raw: f64,
    /// `None` for the first round (write and scan); the merged value range for the second
    /// round (percentile histograms of wide and float types).
    pub range: Option<(f64, f64)>,
}

/// What one task returns.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub enum IngestPartial {
    /// First round: the statistics of the task's slabs.
    Scan(Box<Scanner>),
    /// Second round: the percentile histogram of the task's slabs.
    Fine(Box<FineHistogram>),
}

/// The ingest stage: slab tasks over one source and one target.
pub struct IngestStage {
    params: IngestParams,
    writer: SlabWriter,
    /// Open sources, reused by later tasks (a gzip stream then reads on instead of restarting).
    sources: Mutex<Vec<Box<dyn VolumeSource>>>,
    source_path: PathBuf,
}

impl IngestStage {
    /// The stage for `params`: opens the target's arrays (made by the coordinator with
    /// [`SlabWriter::create`]) and checks the source.
    pub fn new(params: IngestParams) -> Result<Self> {
        let source_path = PathBuf::from(&params.source);
        let src = open_volume(&source_path, params.raw.as_ref())?;
        if src.meta() != &params.meta {
            return Err(IngestError::Failed(format!(
                "{}: this worker reads a {:?} {:?} volume, the coordinator read a {:?} {:?} one \
                 (is the path the same file on every node?)",
                source_path.display(),
                src.meta().dims,
                src.meta().dtype,
                params.meta.dims,
                params.meta.dtype
            )));
        }
        let backend = Backend::open(&StoreLocation::from(params.store.as_str()))?;
        let writer = SlabWriter::open(&backend, &params.meta, &params.opts)?;
        Ok(IngestStage {
            params,
            writer,
            sources: Mutex::new(vec![src]),
            source_path,
        })
    }

    /// Rebuilds the stage on a worker.
    pub fn build(
        v: &serde_json::Value,
        _: &dyn Blobs,
    ) -> neuvolex_tasks::Result<Arc<dyn DynStage>> {
        let p: IngestParams = neuvolex_tasks::codec::params(v)?;
        Ok(Arc::new(IngestStage::new(p).map_err(TaskError::failed)?))
    }

    fn slab(&self, index: usize) -> neuvolex_tasks::Result<(usize, usize)> {
        self.writer.slabs().get(index).copied().ok_or_else(|| {
            TaskError::Failed(format!(
                "{}: slab {index} is outside the volume ({} slabs)",
                self.source_path.display(),
                self.writer.slabs().len()
            ))
        })
    }

    /// Reads slices `z0..z0+depth` with a pooled source (one is opened when all are in use).
    fn read(&self, z0: usize, depth: usize) -> neuvolex_tasks::Result<neuvolex_formats::Slab> {
        let pooled = self.sources.lock().map(|mut p| p.pop()).unwrap_or(None);
        let mut src = match pooled {
            Some(s) => s,
            None => open_volume(&self.source_path, self.params.raw.as_ref())?,
        };
        let slab = src.read_slab(z0, depth)?;
        src.release(z0, depth);
        if let Ok(mut p) = self.sources.lock() {
            p.push(src);
        }
        Ok(slab)
    }
}

impl Stage for IngestStage {
    type Output = IngestPartial;

    fn name(&self) -> &'static str {
        STAGE
    }

    fn params(&self) -> serde_json::Value {
        serde_json::to_value(&self.params).unwrap_or_default()
    }

    fn run(&self, task: &Task, ctx: &TaskCtx<'_>) -> neuvolex_tasks::Result<IngestPartial> {
        let p = &self.params;
        match p.range {
            None => {
                let mut scanner = Scanner::with_shift(&p.meta, p.opts.brick, p.first_raw);
                for b in &task.bricks {
                    ctx.check()?;
                    let (z0, depth) = self.slab(b[2])?;
                    let mut slab = self.read(z0, depth)?;
                    self.writer
                        .write(&mut scanner, &mut slab, &self.source_path)?;
                }
                Ok(IngestPartial::Scan(Box::new(scanner)))
            }
            Some(range) => {
                let mut fine = FineHistogram::new(range.0, range.1);
                for b in &task.bricks {
                    ctx.check()?;
                    let (z0, depth) = self.slab(b[2])?;
                    fine.merge(&self.writer.fine_histogram(z0, depth, range)?);
                }
                Ok(IngestPartial::Fine(Box::new(fine)))
            }
        }
    }
}

/// Names the tasks a run gave up, with their errors.
fn dead_error(report: &RunReport, what: &str) -> IngestError {
    let list: Vec<String> = report
        .dead
        .iter()
        .map(|d| {
            format!(
                "task {} (slabs {:?}) on {} after {} deliveries: {}",
                d.task,
                d.bricks.iter().map(|b| b[2]).collect::<Vec<_>>(),
                d.worker,
                d.deliveries,
                d.error
            )
        })
        .collect();
    IngestError::Failed(format!(
        "{what}: {} of {} tasks failed, nothing was published: {}",
        report.dead.len().max(1),
        report.tasks,
        list.join("; ")
    ))
}

/// Ingests the file `source` (as the user named it; workers read its absolute path) into a new
/// store at `out` on `exec`, `slabs_per_task` slabs a task, with an optional label image added
/// by this process before the store is published. The store's bytes equal those of the
/// sequential [`neuvolex_bricks::ingest_with_labels`] of the same file and options.
#[allow(clippy::too_many_arguments)]
pub fn ingest_on<E: Executor + ?Sized>(
    exec: &E,
    source: &Path,
    raw: Option<&RawSpec>,
    labels: Option<IngestLabels<'_>>,
    out: &StoreLocation,
    opts: &IngestOptions,
    slabs_per_task: usize,
    progress: &mut dyn FnMut(RunEvent),
) -> Result<(StoreInfo, RunReport)> {
    let mut src = open_volume(source, raw)?;
    let meta = src.meta().clone();
    meta.validate(source)?;
    if let Some(l) = &labels {
        neuvolex_bricks::store::check_name("label", l.name)?;
        meta.check_same_grid(l.source.meta(), l.source.path())?;
    }
    let first_raw = first_raw_value(&src.read_slab(0, 1)?);
    drop(src);
    let shared = neuvolex_bricks::location::shared_path_string;
    let target = IngestTarget::begin(out, opts)?;
    let res = (|| {
        let writer = SlabWriter::create(target.backend(), &meta, opts)?;
        let slabs: Vec<[usize; 3]> = (0..writer.slabs().len()).map(|s| [0, 0, s]).collect();
        let mut params = IngestParams {
            source: shared(source),
            raw: raw.cloned(),
            store: shared(&target.location().as_path()),
            opts: opts.clone(),
            meta: meta.clone(),
            first_raw,
            range: None,
        };
        let mut report = RunReport::default();
        // One round of slab tasks; every task must complete.
        let mut round = |params: &IngestParams, n: u32| -> Result<Vec<IngestPartial>> {
            let tasks = plan(&slabs, slabs_per_task, n);
            let stage = IngestStage::new(params.clone())?;
            let (outs, r) = execute_ordered(exec, &stage, &tasks, progress)?;
            report.absorb(&r);
            if outs.iter().any(Option::is_none) || r.cancelled {
                return Err(dead_error(&r, &source.display().to_string()));
            }
            Ok(outs.into_iter().flatten().collect())
        };
        let outs = round(&params, 0)?;
        let mut scanner = Scanner::with_shift(&meta, opts.brick, first_raw);
        for o in outs {
            match o {
                IngestPartial::Scan(s) => scanner.merge(*s)?,
                IngestPartial::Fine(_) => {
                    return Err(IngestError::Failed(
                        "a scan task returned a histogram".into(),
                    ))
                }
            }
        }
        let fine = if scanner.needs_second_pass() {
            params.range = Some(scanner.range());
            let outs = round(&params, 1)?;
            let range = scanner.range();
            let mut fine = FineHistogram::new(range.0, range.1);
            for o in outs {
                match o {
                    IngestPartial::Fine(f) => fine.merge(&f),
                    IngestPartial::Scan(_) => {
                        return Err(IngestError::Failed(
                            "a percentile task returned a scan".into(),
                        ))
                    }
                }
            }
            Some(fine)
        } else {
            None
        };
        let mut info = writer.finish(&target, scanner, fine, source)?;
        if let Some(l) = labels {
            let mut store = neuvolex_bricks::BrickStore::open(target.location().clone())?;
            store.add_labels(l.name, l.source, l.classes, &mut |_| {})?;
            info = store.info().clone();
        }
        Ok((info, report))
    })();
    match res {
        Ok(r) => {
            target.commit()?;
            Ok(r)
        }
        Err(e) => {
            target.abort();
            Err(e)
        }
    }
}
