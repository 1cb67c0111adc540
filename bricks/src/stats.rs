//! A store's intensity statistics ([`VolumeStats`], in its root attributes): min, max, mean,
//! std, 0.5/99.5 percentiles and a 256-bin histogram. `neuvolex-ingest` computes them.

use serde::{Deserialize, Serialize};

/// Number of bins in the stored histogram.
pub const HIST_BINS: usize = 256;

/// Summary statistics of a volume's (scaled) intensities.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeStats {
    /// Number of voxels.
    pub voxels: u64,
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
    /// Mean.
    pub mean: f64,
    /// Population standard deviation.
    pub std: f64,
    /// 0.5th percentile (linear interpolation between order statistics).
    pub p0_5: f64,
    /// 99.5th percentile.
    pub p99_5: f64,
    /// 256 equal bins over `[min, max]`.
    pub histogram: Vec<u64>,
    /// NaN/Inf values replaced by 0 during ingest (0 when the policy is to reject them).
    pub non_finite_replaced: u64,
}
