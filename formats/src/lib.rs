//! # neuvolex-formats
//!
//! Volume files, the first layer of neuvolex's data flow (formats → ingest → bricks): readers
//! for NIfTI-1 (`.nii`, `.nii.gz`), NRRD (attached or detached header, raw or gzip) and
//! headerless raw into one [`VolumeMeta`] model, read slab by slab through [`VolumeSource`]
//! so nothing needs the whole volume in memory; writers for NIfTI-1 and NRRD; and the world
//! geometry ([`geometry`]: the voxel → world affine and its conversions between formats).
//!
//! ```no_run
//! use neuvolex_formats::{open_file, VolumeSource};
//! let mut src = open_file("ct.nii.gz".as_ref(), None)?;
//! let slab = src.read_slab(0, 4)?;
//! assert_eq!(slab.depth, 4);
//! # Ok::<(), neuvolex_formats::FormatError>(())
//! ```

#![warn(missing_docs)]

pub mod dtype;
pub mod error;
pub mod geometry;
pub mod meta;
pub mod nifti;
pub mod nrrd;
pub mod open;
pub mod raw;
mod stream;

pub use dtype::{DType, Endian};
pub use error::{FormatError, Result};
pub use meta::{MemVolume, Slab, VolumeMeta, VolumeSource};
pub use open::{detect_format, open_file, Format};
pub use raw::RawSpec;
pub use stream::FileVolume;
