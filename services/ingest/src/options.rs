//! What an ingest writes and accepts: brick size, sharding, compression, pyramid levels and
//! the NaN/Inf policy.

use neuvolex_bricks::{BrickError, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// What to do with NaN/Inf voxel values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum NonFinitePolicy {
    /// Fail with [`BrickError::NonFinite`] naming the first offending voxel (default).
    #[default]
    Reject,
    /// Replace with 0 and count them in [`VolumeStats::non_finite_replaced`].
    Zero,
}

/// Options for [`ingest`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IngestOptions {
    /// Brick edge in voxels (a power of two, 8..=512). Default 64.
    pub brick: usize,
    /// Bricks per shard edge (Zarr sharding codec); `None` stores one file per brick.
    pub shard: Option<usize>,
    /// zstd level (1..=22). Default 3.
    pub zstd_level: i32,
    /// NaN/Inf handling.
    pub non_finite: NonFinitePolicy,
    /// Replace an existing output.
    pub overwrite: bool,
    /// Number of pyramid levels including level 0; `None` picks until the coarsest level's
    /// largest axis is below 32 voxels or one brick.
    pub levels: Option<usize>,
}

impl Default for IngestOptions {
    fn default() -> Self {
        IngestOptions {
            brick: 64,
            shard: None,
            zstd_level: neuvolex_bricks::layout::DEFAULT_ZSTD_LEVEL,
            non_finite: NonFinitePolicy::Reject,
            overwrite: false,
            levels: None,
        }
    }
}

/// Refuses a brick size or shard that the store cannot hold.
pub(crate) fn validate_options(out: &Path, opts: &IngestOptions) -> Result<()> {
    if !(8..=512).contains(&opts.brick) || !opts.brick.is_power_of_two() {
        return Err(BrickError::InvalidArgument(format!(
            "{}: brick size {} must be a power of two in 8..=512",
            out.display(),
            opts.brick
        )));
    }
    if let Some(s) = opts.shard {
        if s == 0 || s > 64 {
            return Err(BrickError::InvalidArgument(format!(
                "shard {s} must be 1..=64 bricks per edge"
            )));
        }
    }
    Ok(())
}
