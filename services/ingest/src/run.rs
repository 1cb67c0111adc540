//! The one ingest: a coordinator that prepares the target, runs the slab rounds, finishes the
//! statistics and publishes, whichever way the rounds run ([`Rounds`]): streamed in this
//! process from one source, or as slab tasks of [`IngestStage`] on an executor.

use crate::options::IngestOptions;
use crate::scan::{first_raw_value, Scanner};
use crate::stage::{dead_error, IngestParams, IngestPartial, IngestStage};
use crate::stats::FineHistogram;
use crate::target::IngestTarget;
use crate::writer::SlabWriter;
use crate::{IngestError, Result};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{BrickError, BrickStore, Progress, StoreInfo, StoreLocation};
use neuvolex_formats::{RawSpec, VolumeMeta, VolumeSource};
use neuvolex_tasks::{execute_ordered, plan, Executor, RunEvent, RunReport};
use std::path::Path;

/// A label image ingested with its volume (see [`ingest_with_labels`]).
pub struct IngestLabels<'a> {
    /// Name of the label image (`labels/NAME`).
    pub name: &'a str,
    /// The label volume, on the same grid as the image.
    pub source: &'a mut dyn VolumeSource,
    /// Its class table.
    pub classes: &'a [ClassInfo],
}

/// How the two slab rounds of an ingest run. Both ways call the same per-slab functions.
trait Rounds<E> {
    /// First round: writes every slab at every pyramid level and returns the statistics of
    /// the whole volume (the scanners of the slabs, merged).
    fn write(&mut self, target: &IngestTarget, writer: &SlabWriter) -> Result<Scanner, E>;
    /// Second round (wide and float types): the percentile histogram over `range` of the
    /// stored level 0.
    fn histogram(
        &mut self,
        target: &IngestTarget,
        writer: &SlabWriter,
        range: (f64, f64),
    ) -> Result<FineHistogram, E>;
    /// Reports the progress of the label image written after the rounds (nothing by default).
    fn progress(&mut self, _: Progress) {}
}

/// The coordinator: checks, prepares the target, runs the rounds, writes the per-brick ranges
/// and the root metadata, adds the label image, and publishes (or leaves the previous store
/// untouched on any error).
fn run<E: From<BrickError>>(
    meta: &VolumeMeta,
    source_name: &Path,
    labels: Option<IngestLabels<'_>>,
    out: &StoreLocation,
    opts: &IngestOptions,
    rounds: &mut dyn Rounds<E>,
) -> Result<StoreInfo, E> {
    meta.validate(source_name).map_err(BrickError::from)?;
    if let Some(l) = &labels {
        neuvolex_bricks::store::check_name("label", l.name)?;
        meta.check_same_grid(l.source.meta(), l.source.path())
            .map_err(BrickError::from)?;
    }
    let target = IngestTarget::begin(out, opts)?;
    let res = (|| {
        let writer = SlabWriter::create(target.backend(), meta, opts)?;
        let scanner = rounds.write(&target, &writer)?;
        let fine = if scanner.needs_second_pass() {
            Some(rounds.histogram(&target, &writer, scanner.range())?)
        } else {
            None
        };
        let info = writer.finish(&target, scanner, fine, source_name)?;
        match labels {
            Some(l) => {
                let mut store = BrickStore::open(target.location().clone())?;
                store.add_labels(l.name, l.source, l.classes, &mut |p| rounds.progress(p))?;
                Ok(store.info().clone())
            }
            None => Ok(info),
        }
    })();
    match res {
        Ok(info) => {
            target.commit()?;
            Ok(info)
        }
        Err(e) => {
            target.abort();
            Err(e)
        }
    }
}

/// The rounds streamed in this process from one source, slab after slab, front to back (a
/// gzip stream is read once).
struct Stream<'a> {
    source: &'a mut dyn VolumeSource,
    progress: &'a mut dyn FnMut(Progress),
}

impl Rounds<BrickError> for Stream<'_> {
    fn write(&mut self, _: &IngestTarget, writer: &SlabWriter) -> neuvolex_bricks::Result<Scanner> {
        let meta = self.source.meta().clone();
        let path = self.source.path().to_path_buf();
        let mut scanner = Scanner::new(&meta, writer.brick());
        (self.progress)(Progress::Stage {
            name: "ingest",
            total: meta.dims[2] as u64,
        });
        for (z0, depth) in writer.slabs() {
            let mut slab = self.source.read_slab(z0, depth)?;
            writer.write(&mut scanner, &mut slab, &path)?;
            drop(slab);
            self.source.release(z0, depth);
            (self.progress)(Progress::Advance {
                done: (z0 + depth) as u64,
            });
        }
        Ok(scanner)
    }

    fn histogram(
        &mut self,
        _: &IngestTarget,
        writer: &SlabWriter,
        range: (f64, f64),
    ) -> neuvolex_bricks::Result<FineHistogram> {
        let mut fine = FineHistogram::new(range.0, range.1);
        (self.progress)(Progress::Stage {
            name: "percentiles",
            total: self.source.meta().dims[2] as u64,
        });
        for (z0, depth) in writer.slabs() {
            fine.merge(&writer.fine_histogram(z0, depth, range)?);
            (self.progress)(Progress::Advance {
                done: (z0 + depth) as u64,
            });
        }
        Ok(fine)
    }

    fn progress(&mut self, p: Progress) {
        (self.progress)(p)
    }
}

/// Streams `source` into a new brick store at `out` (a path or an `s3://` URL). Peak memory
/// is about one slab of `brick` z-slices in the source type plus one coarser slab per pyramid
/// level.
///
/// On a file system the store is written under a temporary name and renamed into place, so an
/// existing store (replaced only with `overwrite`) stays complete until the new one is. On S3
/// the root metadata is written last; an existing store is first marked incomplete, so a
/// reader sees the old store, an "incomplete store" error, or the new store, never a mix.
pub fn ingest(
    source: &mut dyn VolumeSource,
    out: impl Into<StoreLocation>,
    opts: &IngestOptions,
    progress: &mut dyn FnMut(Progress),
) -> neuvolex_bricks::Result<StoreInfo> {
    ingest_with_labels(source, None, out, opts, progress)
}

/// [`ingest`], with a label image written into the store before it is published: on a file
/// system the store appears (or replaces the old one) with its labels in one rename, so an
/// interruption never leaves the new image without its labels. On S3 the labels are added
/// after the image is published.
pub fn ingest_with_labels(
    source: &mut dyn VolumeSource,
    labels: Option<IngestLabels<'_>>,
    out: impl Into<StoreLocation>,
    opts: &IngestOptions,
    progress: &mut dyn FnMut(Progress),
) -> neuvolex_bricks::Result<StoreInfo> {
    let meta = source.meta().clone();
    let name = source.path().to_path_buf();
    run(
        &meta,
        &name,
        labels,
        &out.into(),
        opts,
        &mut Stream { source, progress },
    )
}

/// The rounds as slab tasks of [`IngestStage`] on an executor; every task must complete.
struct Tasks<'a, E: Executor + ?Sized> {
    exec: &'a E,
    params: IngestParams,
    slabs_per_task: usize,
    report: RunReport,
    progress: &'a mut dyn FnMut(RunEvent),
}

impl<E: Executor + ?Sized> Tasks<'_, E> {
    /// One round: the stage for `params` over every slab, outputs in slab order. Workers
    /// write where the target is being written (its temporary folder on a file system).
    fn round(
        &mut self,
        target: &IngestTarget,
        writer: &SlabWriter,
        n: u32,
    ) -> Result<Vec<IngestPartial>> {
        self.params.store =
            neuvolex_bricks::location::shared_path_string(&target.location().as_path());
        let slabs: Vec<[usize; 3]> = (0..writer.slabs().len()).map(|s| [0, 0, s]).collect();
        let tasks = plan(&slabs, self.slabs_per_task, n);
        let stage = IngestStage::new(self.params.clone())?;
        let (outs, r) = execute_ordered(self.exec, &stage, &tasks, self.progress)?;
        self.report.absorb(&r);
        if outs.iter().any(Option::is_none) || r.cancelled {
            return Err(dead_error(&r, &self.params.source));
        }
        Ok(outs.into_iter().flatten().collect())
    }
}

impl<E: Executor + ?Sized> Rounds<IngestError> for Tasks<'_, E> {
    fn write(&mut self, target: &IngestTarget, writer: &SlabWriter) -> Result<Scanner> {
        let p = &self.params;
        let mut scanner = Scanner::with_shift(&p.meta, p.opts.brick, p.first_raw);
        for o in self.round(target, writer, 0)? {
            match o {
                IngestPartial::Scan(s) => scanner.merge(*s)?,
                IngestPartial::Fine(_) => {
                    return Err(IngestError::Failed(
                        "a scan task returned a histogram".into(),
                    ))
                }
            }
        }
        Ok(scanner)
    }

    fn histogram(
        &mut self,
        target: &IngestTarget,
        writer: &SlabWriter,
        range: (f64, f64),
    ) -> Result<FineHistogram> {
        self.params.range = Some(range);
        let mut fine = FineHistogram::new(range.0, range.1);
        for o in self.round(target, writer, 1)? {
            match o {
                IngestPartial::Fine(f) => fine.merge(&f),
                IngestPartial::Scan(_) => {
                    return Err(IngestError::Failed(
                        "a percentile task returned a scan".into(),
                    ))
                }
            }
        }
        Ok(fine)
    }
}

/// Ingests the file `source` (as the user named it; workers read its absolute path) into a new
/// store at `out` on `exec`, `slabs_per_task` slabs a task, with an optional label image added
/// by this process before the store is published. The store's bytes equal those of
/// [`ingest_with_labels`] of the same file and options: the same coordinator and the same
/// per-slab functions, with the rounds run as tasks.
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
    let mut src = neuvolex_bricks::open_volume(source, raw)?;
    let meta = src.meta().clone();
    meta.validate(source)?;
    let first_raw = first_raw_value(&src.read_slab(0, 1)?);
    drop(src);
    let shared = neuvolex_bricks::location::shared_path_string;
    // `store` is set by each round to where the target is being written.
    let mut rounds = Tasks {
        exec,
        params: IngestParams {
            source: shared(source),
            raw: raw.cloned(),
            store: String::new(),
            opts: opts.clone(),
            meta: meta.clone(),
            first_raw,
            range: None,
        },
        slabs_per_task,
        report: RunReport::default(),
        progress,
    };
    let info = run(&meta, source, labels, out, opts, &mut rounds)?;
    Ok((info, rounds.report))
}
