//! Per-voxel quantities computed per brick from its halo: normalised intensity, gradient by
//! central differences, and 5x5x5 local mean and standard deviation.
//!
//! Every quantity uses edge clamping at the volume border, so a brick computed from a
//! halo read equals the same voxels of a whole-volume computation ([`reference`]).

use serde::{Deserialize, Serialize};

/// Halo needed by [`compute`]: 2 voxels for the 5x5x5 window (the gradient needs 1).
pub const DERIVED_HALO: usize = 2;

/// An affine map of raw intensities to a normalised range.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Normaliser {
    /// Value mapped to 0.
    pub lo: f64,
    /// Value mapped to 1.
    pub hi: f64,
}

impl Normaliser {
    /// Robust normalisation between the 0.5 and 99.5 percentiles, falling back to min/max
    /// when the percentiles coincide (e.g. mostly-constant volumes).
    pub fn robust(stats: &crate::stats::VolumeStats) -> Self {
        if stats.p99_5 > stats.p0_5 {
            Normaliser {
                lo: stats.p0_5,
                hi: stats.p99_5,
            }
        } else {
            Normaliser {
                lo: stats.min,
                hi: stats.max,
            }
        }
    }

    /// Maps a value; a degenerate range (constant volume) maps everything to 0. Values outside
    /// `[lo, hi]` are not clipped, so bright structures beyond the 99.5th percentile stay ordered.
    #[inline]
    pub fn apply(&self, v: f32) -> f32 {
        let w = self.hi - self.lo;
        if !w.is_finite() || w <= 0.0 {
            return 0.0;
        }
        ((v as f64 - self.lo) / w) as f32
    }
}

/// A brick plus `halo` voxels on every side (edge-clamped at the volume border), f32, x fastest.
#[derive(Debug, Clone)]
pub struct HaloBrick {
    /// Voxel origin of the core in the volume.
    pub origin: [usize; 3],
    /// Core size (x, y, z).
    pub size: [usize; 3],
    /// Halo width.
    pub halo: usize,
    /// `(size + 2 halo)` voxels per axis, x fastest.
    pub data: Vec<f32>,
}

impl HaloBrick {
    /// Extent including the halo.
    pub fn padded(&self) -> [usize; 3] {
        [
            self.size[0] + 2 * self.halo,
            self.size[1] + 2 * self.halo,
            self.size[2] + 2 * self.halo,
        ]
    }

    /// The core voxels (without halo), x fastest.
    pub fn core(&self) -> Vec<f32> {
        let p = self.padded();
        let h = self.halo;
        let mut out = Vec::with_capacity(self.size.iter().product());
        for z in 0..self.size[2] {
            for y in 0..self.size[1] {
                let row = ((z + h) * p[1] + y + h) * p[0] + h;
                out.extend_from_slice(&self.data[row..row + self.size[0]]);
            }
        }
        out
    }
}

/// Derived quantities of one brick's core voxels, each x fastest.
#[derive(Debug, Clone, PartialEq)]
pub struct DerivedBrick {
    /// Normalised intensity.
    pub intensity: Vec<f32>,
    /// Gradient (d/dx, d/dy, d/dz) of the normalised intensity in voxel units, per voxel.
    pub gradient: Vec<[f32; 3]>,
    /// Mean of the normalised intensity over the 5x5x5 window.
    pub mean: Vec<f32>,
    /// Standard deviation over the 5x5x5 window.
    pub std: Vec<f32>,
}

/// Computes the derived quantities of a halo brick (halo >= [`DERIVED_HALO`]).
pub fn compute(b: &HaloBrick, norm: &Normaliser) -> DerivedBrick {
    assert!(
        b.halo >= DERIVED_HALO,
        "derived quantities need a halo of 2"
    );
    let p = b.padded();
    let n: Vec<f32> = b.data.iter().map(|&v| norm.apply(v)).collect();
    let idx = |x: usize, y: usize, z: usize| (z * p[1] + y) * p[0] + x;
    let h = b.halo;
    let core = b.size.iter().product::<usize>();
    let mut intensity = Vec::with_capacity(core);
    let mut gradient = Vec::with_capacity(core);
    for z in h..h + b.size[2] {
        for y in h..h + b.size[1] {
            for x in h..h + b.size[0] {
                intensity.push(n[idx(x, y, z)]);
                gradient.push([
                    0.5 * (n[idx(x + 1, y, z)] - n[idx(x - 1, y, z)]),
                    0.5 * (n[idx(x, y + 1, z)] - n[idx(x, y - 1, z)]),
                    0.5 * (n[idx(x, y, z + 1)] - n[idx(x, y, z - 1)]),
                ]);
            }
        }
    }
    // Separable 5-wide box sums of v and v^2 in f64 (no cancellation trouble for std).
    let box_sum = |src: &[f64], dims: [usize; 3], axis: usize| -> (Vec<f64>, [usize; 3]) {
        let mut od = dims;
        od[axis] -= 4;
        let mut out = vec![0.0; od[0] * od[1] * od[2]];
        let stride = [1, dims[0], dims[0] * dims[1]][axis];
        for z in 0..od[2] {
            for y in 0..od[1] {
                for x in 0..od[0] {
                    let base = (z * dims[1] + y) * dims[0] + x;
                    let mut s = 0.0;
                    for k in 0..5 {
                        s += src[base + k * stride];
                    }
                    out[(z * od[1] + y) * od[0] + x] = s;
                }
            }
        }
        (out, od)
    };
    // Restrict to core +- 2 before filtering.
    let h2 = h - 2;
    let w = [b.size[0] + 4, b.size[1] + 4, b.size[2] + 4];
    let mut v1 = Vec::with_capacity(w[0] * w[1] * w[2]);
    for z in 0..w[2] {
        for y in 0..w[1] {
            for x in 0..w[0] {
                v1.push(n[idx(x + h2, y + h2, z + h2)] as f64);
            }
        }
    }
    let v2: Vec<f64> = v1.iter().map(|v| v * v).collect();
    let sep = |v: Vec<f64>| {
        let (a, d) = box_sum(&v, w, 0);
        let (b, d) = box_sum(&a, d, 1);
        box_sum(&b, d, 2).0
    };
    let s1 = sep(v1);
    let s2 = sep(v2);
    let mean: Vec<f32> = s1.iter().map(|s| (s / 125.0) as f32).collect();
    let std: Vec<f32> = s1
        .iter()
        .zip(&s2)
        .map(|(a, b)| {
            let m = a / 125.0;
            ((b / 125.0 - m * m).max(0.0)).sqrt() as f32
        })
        .collect();
    DerivedBrick {
        intensity,
        gradient,
        mean,
        std,
    }
}

/// Whole-volume reference implementation (direct loops, clamped indexing). For tests.
pub fn reference(values: &[f32], dims: [usize; 3], norm: &Normaliser) -> DerivedBrick {
    let n: Vec<f32> = values.iter().map(|&v| norm.apply(v)).collect();
    let at = |x: isize, y: isize, z: isize| {
        let c = |v: isize, d: usize| v.clamp(0, d as isize - 1) as usize;
        n[(c(z, dims[2]) * dims[1] + c(y, dims[1])) * dims[0] + c(x, dims[0])]
    };
    let mut out = DerivedBrick {
        intensity: vec![],
        gradient: vec![],
        mean: vec![],
        std: vec![],
    };
    for z in 0..dims[2] as isize {
        for y in 0..dims[1] as isize {
            for x in 0..dims[0] as isize {
                out.intensity.push(at(x, y, z));
                out.gradient.push([
                    0.5 * (at(x + 1, y, z) - at(x - 1, y, z)),
                    0.5 * (at(x, y + 1, z) - at(x, y - 1, z)),
                    0.5 * (at(x, y, z + 1) - at(x, y, z - 1)),
                ]);
                let mut vals = Vec::with_capacity(125);
                for dz in -2..=2 {
                    for dy in -2..=2 {
                        for dx in -2..=2 {
                            vals.push(at(x + dx, y + dy, z + dz) as f64);
                        }
                    }
                }
                let m = vals.iter().sum::<f64>() / 125.0;
                let var = vals.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / 125.0;
                out.mean.push(m as f32);
                out.std.push(var.sqrt() as f32);
            }
        }
    }
    out
}

/// Pads a whole in-memory volume's sub-box into a halo brick with edge clamping (for tests
/// and in-memory pipelines; the store does the same from disk).
pub fn halo_from_volume(
    values: &[f32],
    dims: [usize; 3],
    origin: [usize; 3],
    size: [usize; 3],
    halo: usize,
) -> HaloBrick {
    let mut data =
        Vec::with_capacity((size[0] + 2 * halo) * (size[1] + 2 * halo) * (size[2] + 2 * halo));
    let c = |v: isize, d: usize| v.clamp(0, d as isize - 1) as usize;
    let h = halo as isize;
    for z in 0..(size[2] + 2 * halo) as isize {
        for y in 0..(size[1] + 2 * halo) as isize {
            for x in 0..(size[0] + 2 * halo) as isize {
                let gx = c(origin[0] as isize + x - h, dims[0]);
                let gy = c(origin[1] as isize + y - h, dims[1]);
                let gz = c(origin[2] as isize + z - h, dims[2]);
                data.push(values[(gz * dims[1] + gy) * dims[0] + gx]);
            }
        }
    }
    HaloBrick {
        origin,
        size,
        halo,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_volume_has_zero_gradient_and_std() {
        let dims = [6, 5, 4];
        let v = vec![1e30f32; 120];
        let norm = Normaliser { lo: 1e30, hi: 1e30 };
        let b = halo_from_volume(&v, dims, [0, 0, 0], dims, 2);
        let d = compute(&b, &norm);
        assert!(d.intensity.iter().all(|&x| x == 0.0));
        assert!(d.std.iter().all(|&x| x == 0.0));
        assert!(d.gradient.iter().all(|g| g == &[0.0; 3]));
    }

    #[test]
    fn one_voxel_volume() {
        let b = halo_from_volume(&[3.0], [1, 1, 1], [0; 3], [1, 1, 1], 2);
        let d = compute(&b, &Normaliser { lo: 0.0, hi: 6.0 });
        assert_eq!(d.intensity, vec![0.5]);
        assert_eq!(d.mean, vec![0.5]);
        assert_eq!(d.std, vec![0.0]);
    }
}
