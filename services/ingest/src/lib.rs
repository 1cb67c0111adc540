//! # neuvolex-ingest
//!
//! The one ingest of neuvolex (formats → **ingest** → bricks): a volume file, or any
//! [`VolumeSource`](neuvolex_formats::VolumeSource), into a new brick store with its image
//! pyramid, statistics and per-brick ranges. One coordinator prepares the target,
//! runs two rounds of per-slab work ([`SlabWriter::write`] with a [`Scanner`], then
//! [`SlabWriter::fine_histogram`] for wide types), finishes the statistics and publishes. The
//! rounds run either way with the same per-slab functions:
//!
//! - streamed in this process from one source, front to back ([`ingest`],
//!   [`ingest_with_labels`]: `neuvolex ingest`, the server's open, the embedded phantom);
//! - as slab tasks of [`IngestStage`] on any executor ([`ingest_on`]: in process, in the
//!   server's actors, on cluster workers with `neuvolex ingest --cluster`), writing the same
//!   store byte for byte.
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

mod options;
mod run;
mod scan;
mod stage;
pub mod stats;
mod target;
mod writer;

pub use options::{IngestOptions, NonFinitePolicy};
pub use run::{ingest, ingest_on, ingest_with_labels, IngestLabels};
pub use scan::{background_threshold, first_raw_value, scan_volume, ScanReport, Scanner};
pub use stage::{IngestParams, IngestPartial, IngestStage};
pub use target::IngestTarget;
pub use writer::{downsample_mean, SlabWriter};

use neuvolex_bricks::BrickError;
use neuvolex_tasks::TaskError;

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

/// Writes the labelled phantom as a brick store at `path`: the image, plus its ground truth
/// under `labels/ground_truth` with the class table (the embedded default scene).
pub fn phantom_store(
    path: &std::path::Path,
    params: neuvolex_bricks::synth::PhantomParams,
    opts: &IngestOptions,
    progress: &mut dyn FnMut(neuvolex_bricks::Progress),
) -> neuvolex_bricks::Result<neuvolex_bricks::BrickStore> {
    use neuvolex_bricks::synth::{phantom_classes, Phantom, PhantomChannel};
    ingest_with_labels(
        &mut Phantom::new(params, PhantomChannel::Image),
        Some(IngestLabels {
            name: "ground_truth",
            source: &mut Phantom::new(params, PhantomChannel::Labels),
            classes: &phantom_classes(),
        }),
        path,
        opts,
        progress,
    )?;
    neuvolex_bricks::BrickStore::open(path)
}
