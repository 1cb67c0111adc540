//! # neuvolex-bricks
//!
//! The out-of-core brick store of neuvolex (formats → ingest → **bricks** → stages): an
//! OME-Zarr v3 hierarchy with a multiscale pyramid, per-brick value ranges, label images and
//! per-voxel vector arrays. Every later stage reads and writes through [`BrickStore`]: brick
//! iteration, sub-box and halo reads, the derived per-voxel quantities (normalised intensity,
//! gradient, 5x5x5 mean/std) the feature stage trains on, and an LRU of decoded bricks.
//! `neuvolex-ingest` writes new stores; volume files are read by `neuvolex-formats`.
//!
//! A store lives on a local or shared-POSIX path or at an `s3://bucket/prefix.zarr` URL
//! ([`StoreLocation`], [`Backend`]); writes are atomic, the outputs of a step are published
//! together by one commit ([`commit`]), a writer lock keeps two writers apart ([`lock`]) and
//! done markers let a stage resume ([`done`]).
//!
//! ```no_run
//! use neuvolex_bricks::BrickStore;
//! let store = BrickStore::open("ct.zarr")?; // or "s3://bucket/ct.zarr"
//! for b in store.occupied_bricks(None) {
//!     let d = store.derived(&b)?;
//!     assert_eq!(d.intensity.len(), b.voxels());
//! }
//! # Ok::<(), neuvolex_bricks::BrickError>(())
//! ```

#![warn(missing_docs)]

pub mod atomic;
pub mod backend;
pub mod commit;
pub mod derived;
pub mod done;
pub mod error;
mod fsstore;
mod io;
pub mod labels;
pub mod layout;
pub mod location;
pub mod lock;
pub mod lru;
pub mod omezarr;
pub mod rng;
pub mod stats;
pub mod store;
pub mod synth;
pub mod vectors;

pub use backend::{store_io, Backend, StoreIo};
pub use commit::Commit;
pub use derived::{DerivedBrick, HaloBrick, Normaliser};
pub use done::{DoneMarkers, StageTag};
pub use error::{BrickError, Result};
pub use layout::{Brick, Progress, StoreInfo};
pub use location::{S3Options, StoreLocation};
pub use lock::WriterLock;
pub use omezarr::open_volume;
pub use stats::VolumeStats;
pub use store::BrickStore;
pub use vectors::{VectorArray, VectorEncoding, VectorInfo};
