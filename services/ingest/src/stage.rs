//! The ingest as a stage of the task model: slab tasks that any executor runs (in process,
//! in the server's actors, on cluster workers), each calling the same per-slab functions as
//! the in-process runner ([`SlabWriter::write`], [`SlabWriter::fine_histogram`]).

use crate::options::IngestOptions;
use crate::scan::Scanner;
use crate::stats::FineHistogram;
use crate::writer::SlabWriter;
use crate::{IngestError, Result, STAGE};
use neuvolex_bricks::{open_volume, Backend, StoreLocation};
use neuvolex_formats::{RawSpec, VolumeMeta, VolumeSource};
use neuvolex_tasks::{Blobs, DynStage, RunReport, Stage, Task, TaskCtx, TaskError};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

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
    /// [`crate::first_raw_value`]).
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
pub(crate) fn dead_error(report: &RunReport, what: &str) -> IngestError {
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
