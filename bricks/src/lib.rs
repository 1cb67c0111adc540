//! # neuvolex-bricks
//!
//! Volumes on disk and in memory for neuvolex: readers for NIfTI-1, NRRD, raw and OME-Zarr
//! into one [`VolumeMeta`] model, streaming ingest into an out-of-core OME-Zarr v3
//! [`BrickStore`] with a multiscale pyramid, statistics and per-brick ranges, halo reads, and
//! the per-brick derived quantities (normalised intensity, gradient, 5x5x5 mean/std) that the
//! feature stage trains on.
//!
//! A store lives on a local or shared-POSIX path or at an `s3://bucket/prefix.zarr` URL
//! ([`StoreLocation`]); writes are atomic, the outputs of a step are published together by one commit ([`commit`]), a writer
//! lock keeps two writers apart ([`lock`]) and done markers let a stage resume ([`done`]).
//!
//! ```no_run
//! use neuvolex_bricks::{open_volume, ingest, IngestOptions, BrickStore};
//! let mut src = open_volume("ct.nii.gz".as_ref(), None)?;
//! ingest(src.as_mut(), "ct.zarr", &IngestOptions::default(), &mut |_| {})?;
//! let store = BrickStore::open("ct.zarr")?; // or "s3://bucket/ct.zarr"
//! for b in store.occupied_bricks(None) {
//!     let d = store.derived(&b)?;
//!     assert_eq!(d.intensity.len(), b.voxels());
//! }
//! # Ok::<(), neuvolex_bricks::BrickError>(())
//! ```

#![warn(missing_docs)]

pub mod backend;
pub mod commit;
pub mod derived;
pub mod done;
pub mod error;
pub mod location;
pub mod lock;
pub mod lru;
pub mod omezarr;
pub mod rng;
pub mod stats;
pub mod store;
pub mod synth;

pub use backend::{store_io, Backend, StoreIo};
pub use commit::Commit;
pub use derived::{DerivedBrick, HaloBrick, Normaliser};
pub use done::{DoneMarkers, StageTag};
pub use error::{BrickError, Result};
pub use location::{S3Options, StoreLocation};
pub use lock::WriterLock;
pub use omezarr::open_volume;
pub use stats::VolumeStats;
pub use store::{
    first_raw_value, ingest, ingest_with_labels, Brick, BrickStore, IngestLabels, IngestOptions,
    IngestTarget, NonFinitePolicy, Progress, Scanner, SlabWriter, StoreInfo, VectorArray,
    VectorEncoding,
};
