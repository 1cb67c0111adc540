//! The statistics pass of an ingest: per-slab scanning that merges exactly whatever the
//! split, the percentile pass of wide types, and `neuvolex info`'s scan of a file.

use crate::options::NonFinitePolicy;
use crate::stats::{FineHistogram, StatsAccumulator};
use neuvolex_bricks::layout::grid_of;
use neuvolex_bricks::stats::VolumeStats;
use neuvolex_bricks::{BrickError, Progress, Result};
use neuvolex_formats::meta::{VolumeMeta, VolumeSource};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One streaming pass over slabs: statistics, per-brick ranges and the NaN/Inf policy.
///
/// Scanners of disjoint parts of a volume merge ([`Scanner::merge`]) into exactly the scanner
/// of the whole, whatever the split, the order or the thread count: counts, extremes and
/// per-brick ranges combine exactly, and the shifted f64 sums of wide and float types are kept
/// per z-slice and added in slice order by [`Scanner::finish`]. This is what lets a cluster
/// ingest (slab tasks on several workers) write the same statistics as a local one.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Scanner {
    meta: VolumeMeta,
    brick: usize,
    grid: [usize; 3],
    acc: StatsAccumulator,
    bmin: Vec<f64>,
    bmax: Vec<f64>,
    /// Shifted (sum, sum of squares) of each z-slice (wide and float types).
    slice_sums: Vec<[f64; 2]>,
}

impl Scanner {
    /// A scanner for a volume of `meta` with bricks of edge `brick`. The shift of the shifted
    /// sums is the first value of the first slab added.
    pub fn new(meta: &VolumeMeta, brick: usize) -> Self {
        let grid = grid_of(meta.dims, brick);
        let nb = grid.iter().product::<usize>();
        Scanner {
            meta: meta.clone(),
            brick,
            grid,
            acc: StatsAccumulator::new(meta.dtype, meta.scaling),
            bmin: vec![f64::INFINITY; nb],
            bmax: vec![f64::NEG_INFINITY; nb],
            slice_sums: vec![[0.0; 2]; meta.dims[2]],
        }
    }

    /// A scanner for a part of a volume whose first raw value (after the NaN/Inf policy, see
    /// [`first_raw_value`]) is `first_raw`: every part of one volume must use the same.
    pub fn with_shift(meta: &VolumeMeta, brick: usize, first_raw: f64) -> Self {
        let mut s = Scanner::new(meta, brick);
        s.acc.set_shift_if_unset(first_raw);
        s
    }

    /// Adds the scanner of another, disjoint part of the same volume (same grid and shift).
    pub fn merge(&mut self, o: Scanner) -> Result<()> {
        if o.meta.dims != self.meta.dims || o.brick != self.brick {
            return Err(BrickError::InvalidArgument(format!(
                "statistics of a {:?} volume in {}-voxel bricks cannot merge into those of a {:?} \
                 volume in {}-voxel bricks",
                o.meta.dims, o.brick, self.meta.dims, self.brick
            )));
        }
        self.acc.merge(o.acc);
        for (i, (lo, hi)) in o.bmin.into_iter().zip(o.bmax).enumerate() {
            self.bmin[i] = self.bmin[i].min(lo);
            self.bmax[i] = self.bmax[i].max(hi);
        }
        // Parts are disjoint in z: a slice's sums come from one part (the other adds 0).
        for (a, b) in self.slice_sums.iter_mut().zip(o.slice_sums) {
            a[0] += b[0];
            a[1] += b[1];
        }
        Ok(())
    }

    /// Applies the NaN/Inf policy to `slab` (rewriting it for [`NonFinitePolicy::Zero`]) and
    /// accumulates it. Slabs must arrive front to back.
    pub fn add_slab(
        &mut self,
        slab: &mut neuvolex_formats::meta::Slab,
        policy: NonFinitePolicy,
        path: &Path,
    ) -> Result<()> {
        let meta = &self.meta;
        let slice = meta.slice_len();
        if meta.dtype.is_float() {
            let vals = slab.to_f64();
            let bad: Vec<usize> = vals
                .iter()
                .enumerate()
                .filter(|(_, v)| !v.is_finite())
                .map(|(i, _)| i)
                .collect();
            if !bad.is_empty() {
                match policy {
                    NonFinitePolicy::Reject => {
                        let i = bad[0];
                        return Err(BrickError::NonFinite {
                            path: path.to_path_buf(),
                            count: bad.len() as u64,
                            x: i % meta.dims[0],
                            y: (i / meta.dims[0]) % meta.dims[1],
                            z: slab.z0 + i / slice,
                        });
                    }
                    NonFinitePolicy::Zero => {
                        let mut vals = vals;
                        for &i in &bad {
                            vals[i] = 0.0;
                        }
                        self.acc.non_finite_replaced += bad.len() as u64;
                        slab.bytes = neuvolex_formats::dtype::f64_to_bytes(&vals, meta.dtype);
                    }
                }
            }
        }
        let (b, grid) = (self.brick, self.grid);
        let esize = meta.dtype.size();
        if slab.depth == 0 {
            return Ok(());
        }
        let mut first = [0.0f64];
        neuvolex_formats::dtype::bytes_to_f64(&slab.bytes[..esize], meta.dtype, &mut first);
        self.acc.set_shift_if_unset(first[0]);
        // Brick layers touched by this slab; each worker keeps its own ranges for them.
        let bz0 = slab.z0 / b;
        let layers = (slab.z0 + slab.depth - 1) / b - bz0 + 1;
        let per_layer = grid[0] * grid[1];
        let workers = rayon::current_num_threads().clamp(1, slab.depth);
        let per = slab.depth.div_ceil(workers);
        use rayon::prelude::*;
        type Part = (StatsAccumulator, Vec<f64>, Vec<f64>, Vec<[f64; 2]>);
        let parts: Vec<Part> = slab
            .bytes
            .par_chunks(per * slice * esize)
            .enumerate()
            .map(|(w, bytes)| {
                let mut acc = self.acc.fork();
                let mut lmin = vec![f64::INFINITY; layers * per_layer];
                let mut lmax = vec![f64::NEG_INFINITY; layers * per_layer];
                let mut sums = Vec::new();
                let mut raw = vec![0.0f64; slice];
                let mut ints = vec![0i32; slice];
                let small = meta.dtype.is_small_int();
                for (dz, sl) in bytes.chunks_exact(slice * esize).enumerate() {
                    let layer = (slab.z0 + w * per + dz) / b - bz0;
                    let mut range = |i: usize, lo: f64, hi: f64| {
                        lmin[i] = lmin[i].min(lo);
                        lmax[i] = lmax[i].max(hi);
                    };
                    if small {
                        neuvolex_formats::dtype::small_ints_to_i32(sl, meta.dtype, &mut ints);
                        acc.add_ints(&ints);
                        for y in 0..meta.dims[1] {
                            let row = &ints[y * meta.dims[0]..(y + 1) * meta.dims[0]];
                            for (bx, seg) in row.chunks(b).enumerate() {
                                let (lo, hi) = seg
                                    .iter()
                                    .fold((i32::MAX, i32::MIN), |(a, c), &v| (a.min(v), c.max(v)));
                                range(
                                    layer * per_layer + (y / b) * grid[0] + bx,
                                    lo as f64,
                                    hi as f64,
                                );
                            }
                        }
                    } else {
                        neuvolex_formats::dtype::bytes_to_f64(sl, meta.dtype, &mut raw);
                        acc.add_raw(&raw);
                        // Per-slice sums: added in slice order at the end, whatever the split.
                        let (a, q) = acc.take_sums();
                        sums.push([a, q]);
                        for y in 0..meta.dims[1] {
                            let row = &raw[y * meta.dims[0]..(y + 1) * meta.dims[0]];
                            for (bx, seg) in row.chunks(b).enumerate() {
                                let (lo, hi) = seg
                                    .iter()
                                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, c), &v| {
                                        (a.min(v), c.max(v))
                                    });
                                range(layer * per_layer + (y / b) * grid[0] + bx, lo, hi);
                            }
                        }
                    }
                }
                (acc, lmin, lmax, sums)
            })
            .collect();
        for (w, (acc, lmin, lmax, sums)) in parts.into_iter().enumerate() {
            self.acc.merge(acc);
            for (dz, s) in sums.into_iter().enumerate() {
                self.slice_sums[slab.z0 + w * per + dz] = s;
            }
            for i in 0..layers * per_layer {
                if lmin[i] > lmax[i] {
                    continue;
                }
                // Scaling may be negative: map both ends.
                let (lo, hi) = (meta.scale(lmin[i]), meta.scale(lmax[i]));
                let g = bz0 * per_layer + i;
                self.bmin[g] = self.bmin[g].min(lo.min(hi));
                self.bmax[g] = self.bmax[g].max(lo.max(hi));
            }
        }
        Ok(())
    }

    /// True when percentiles need a second pass over the data (types wider than 16 bits).
    pub fn needs_second_pass(&self) -> bool {
        self.acc.needs_second_pass()
    }

    /// Value range seen so far.
    pub fn range(&self) -> (f64, f64) {
        self.acc.range()
    }

    /// Statistics plus per-brick minima and maxima (grid order, x fastest).
    pub fn finish(mut self, fine: Option<FineHistogram>) -> (VolumeStats, Vec<f64>, Vec<f64>) {
        for [a, q] in &self.slice_sums {
            self.acc.add_sums(*a, *q);
        }
        (self.acc.finish(fine), self.bmin, self.bmax)
    }
}

/// The first raw value of a volume as [`Scanner::add_slab`] sees it (a NaN or Inf counts as 0,
/// as the `zero` policy writes it; the `reject` policy fails on it anyway): the shift that
/// every part's [`Scanner::with_shift`] must use. `slab` is the volume's first slab.
pub fn first_raw_value(slab: &neuvolex_formats::meta::Slab) -> f64 {
    let esize = slab.dtype.size();
    if slab.bytes.len() < esize {
        return 0.0;
    }
    let mut first = [0.0f64];
    neuvolex_formats::dtype::bytes_to_f64(&slab.bytes[..esize], slab.dtype, &mut first);
    if first[0].is_finite() {
        first[0]
    } else {
        0.0
    }
}

/// Result of [`scan_volume`]: what `neuvolex info` reports for a file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ScanReport {
    /// Intensity statistics (non-finite values counted and treated as 0).
    pub stats: VolumeStats,
    /// Brick edge used for occupancy.
    pub brick: usize,
    /// Bricks per axis.
    pub grid: [usize; 3],
    /// Empty-brick threshold (as [`StoreInfo::background`]).
    pub background: f64,
    /// Bricks whose maximum reaches the threshold.
    pub occupied: usize,
}

/// Streams a source once (twice for wide types) and reports statistics and brick occupancy.
pub fn scan_volume(
    source: &mut dyn VolumeSource,
    brick: usize,
    progress: &mut dyn FnMut(Progress),
) -> Result<ScanReport> {
    let meta = source.meta().clone();
    let path = source.path().to_path_buf();
    meta.validate(&path)?;
    let brick = brick.clamp(1, 4096);
    let mut scanner = Scanner::new(&meta, brick);
    let nz = meta.dims[2];
    let step = brick.max(16);
    progress(Progress::Stage {
        name: "scan",
        total: nz as u64,
    });
    let mut z = 0;
    while z < nz {
        let d = step.min(nz - z);
        let mut slab = source.read_slab(z, d)?;
        scanner.add_slab(&mut slab, NonFinitePolicy::Zero, &path)?;
        source.release(z, d);
        z += d;
        progress(Progress::Advance { done: z as u64 });
    }
    let fine = if scanner.needs_second_pass() {
        Some(percentile_pass(
            nz,
            step,
            scanner.range(),
            progress,
            |z, d| {
                let mut v = source.read_slab(z, d)?.to_f32_scaled(&meta);
                v.iter_mut()
                    .filter(|x| !x.is_finite())
                    .for_each(|x| *x = 0.0);
                source.release(z, d);
                Ok(v)
            },
        )?)
    } else {
        None
    };
    let grid = scanner.grid;
    let (stats, _, bmax) = scanner.finish(fine);
    let background = background_threshold(&stats);
    let occupied = bmax.iter().filter(|&&m| m >= background).count();
    Ok(ScanReport {
        stats,
        brick,
        grid,
        background,
        occupied,
    })
}

/// Second pass for percentiles of wide types: reads the volume slab by slab through `read(z, depth)`
/// into a fine histogram over the `(min, max)` found by the first pass.
fn percentile_pass(
    nz: usize,
    step: usize,
    range: (f64, f64),
    progress: &mut dyn FnMut(Progress),
    mut read: impl FnMut(usize, usize) -> Result<Vec<f32>>,
) -> Result<FineHistogram> {
    let mut fine = FineHistogram::new(range.0, range.1);
    progress(Progress::Stage {
        name: "percentiles",
        total: nz as u64,
    });
    let mut z = 0;
    while z < nz {
        let d = step.min(nz - z);
        fine.add(&read(z, d)?);
        z += d;
        progress(Progress::Advance { done: z as u64 });
    }
    Ok(fine)
}

/// The default empty-brick threshold: 5% of the way from the 0.5th to the 99.5th percentile.
/// Bricks whose maximum is below it hold only background (air, zeroed haze).
pub fn background_threshold(stats: &VolumeStats) -> f64 {
    stats.p0_5 + 0.05 * (stats.p99_5 - stats.p0_5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_formats::meta::MemVolume;

    fn volume() -> MemVolume {
        let dims = [23, 17, 41];
        let v: Vec<f32> = (0..dims.iter().product::<usize>())
            .map(|i| ((i as f32) * 0.37).sin() * 1e3 + (i % 13) as f32 * 1e-3 + 7.5)
            .collect();
        MemVolume::from_f32(dims, &v)
    }

    /// Scans `parts` (ranges of z-slices, in any order) into separate scanners and merges them.
    fn scan(src: &mut MemVolume, parts: &[(usize, usize)]) -> (VolumeStats, Vec<f64>, Vec<f64>) {
        let meta = src.meta.clone();
        let first = first_raw_value(&src.read_slab(0, 1).unwrap());
        let mut total = Scanner::with_shift(&meta, 8, first);
        for &(z0, d) in parts {
            let mut s = Scanner::with_shift(&meta, 8, first);
            s.add_slab(
                &mut src.read_slab(z0, d).unwrap(),
                NonFinitePolicy::Reject,
                Path::new("m"),
            )
            .unwrap();
            total.merge(s).unwrap();
        }
        let (lo, hi) = total.range();
        let mut fine = FineHistogram::new(lo, hi);
        for &(z0, d) in parts.iter().rev() {
            let mut f = FineHistogram::new(lo, hi);
            f.add(&src.read_slab(z0, d).unwrap().to_f32_scaled(&meta));
            fine.merge(&f);
        }
        total.finish(Some(fine))
    }

    #[test]
    fn merged_parts_equal_one_scan_bit_for_bit() {
        let mut src = volume();
        let whole = scan(&mut src, &[(0, 41)]);
        let split = scan(&mut src, &[(24, 17), (0, 8), (8, 16)]);
        let bits =
            |s: &VolumeStats| [s.min, s.max, s.mean, s.std, s.p0_5, s.p99_5].map(f64::to_bits);
        assert_eq!(bits(&whole.0), bits(&split.0));
        assert_eq!(whole.0, split.0);
        assert_eq!(whole.1, split.1);
        assert_eq!(whole.2, split.2);
        // The scan through `Scanner::new` (the shift from the first slab) is the same too.
        let mut s = Scanner::new(&src.meta, 8);
        s.add_slab(
            &mut src.read_slab(0, 41).unwrap(),
            NonFinitePolicy::Reject,
            Path::new("m"),
        )
        .unwrap();
        let (lo, hi) = s.range();
        let mut fine = FineHistogram::new(lo, hi);
        fine.add(&src.read_slab(0, 41).unwrap().to_f32_scaled(&src.meta));
        assert_eq!(s.finish(Some(fine)).0, whole.0);
    }

    #[test]
    fn scanners_of_different_grids_do_not_merge() {
        let src = volume();
        let mut a = Scanner::new(&src.meta, 8);
        let b = Scanner::new(&src.meta, 16);
        assert!(a.merge(b).is_err());
    }
}
