//! Multi-scale context from the store's 2x mean pyramid: the Gaussian-smoothed normalised
//! intensity at scale `sigma` and its scale-normalised gradient magnitude, for any level-0
//! position near a brick.
//!
//! Scale `sigma` (level-0 voxels) is read from pyramid level `k = floor(log2 sigma)` (the
//! coarsest the store has, if fewer), whose 2^k box mean already blurs with variance
//! `(4^k - 1) / 12`; a Gaussian of the remaining `sqrt(sigma^2 - (4^k - 1)/12) / 2^k` level-k
//! voxels completes the scale (about 1 voxel, a 7-tap kernel, whatever `sigma`). Values are
//! trilinear between level-k voxel centres. So a brick's context at sigma 8 reads a box of a few
//! thousand voxels instead of a level-0 halo of 24 voxels, and the result is a pure function of
//! the pyramid: per-brick fields equal a whole-volume computation (tested).

use crate::{radius, smooth};
use neuvolex_bricks::derived::Normaliser;

/// Pyramid level and residual Gaussian sigma (in level voxels) that give scale `sigma` from a
/// pyramid of `levels` levels.
pub fn plan(sigma: f32, levels: usize) -> (usize, f32) {
    let want = if sigma >= 1.0 {
        sigma.log2().floor() as usize
    } else {
        0
    };
    let k = want.min(levels.saturating_sub(1));
    let f = (1usize << k) as f32;
    let box_var = (f * f - 1.0) / 12.0;
    let rest = (sigma * sigma - box_var).max(0.0).sqrt() / f;
    (k, rest)
}

/// The smoothed intensity and scale-normalised gradient magnitude at one scale over a box of
/// one pyramid level, enough to sample every level-0 position of a region.
#[derive(Debug, Clone)]
pub struct ScaleField {
    /// Scale in level-0 voxels.
    pub sigma: f32,
    level: usize,
    level_dims: [usize; 3],
    dims: [usize; 3],
    /// Level coordinates of the box's first voxel (may lie outside the level; edge-clamped).
    lo: [isize; 3],
    size: [usize; 3],
    smooth: Vec<f32>,
    grad: Vec<f32>,
}

impl ScaleField {
    /// Computes the field for level-0 positions in `lo0..=hi0` (clamped into the volume) from a
    /// pyramid whose level grids are `levels` (level 0 first). `read(level, origin, size)`
    /// returns raw intensities of an in-bounds box of a level (x fastest); `norm` maps them to
    /// the normalised range.
    pub fn compute<E>(
        sigma: f32,
        levels: &[[usize; 3]],
        norm: &Normaliser,
        lo0: [isize; 3],
        hi0: [isize; 3],
        mut read: impl FnMut(usize, [usize; 3], [usize; 3]) -> Result<Vec<f32>, E>,
    ) -> Result<Self, E> {
        let (k, rest) = plan(sigma, levels.len());
        let ld = levels[k];
        let dims = levels[0];
        let f = (1usize << k) as f32;
        let r = if rest > 0.0 { radius(rest) } else { 0 } as isize;
        let mut lo = [0isize; 3];
        let mut size = [0usize; 3];
        for a in 0..3 {
            let c = |p: isize| p.clamp(0, dims[a] as isize - 1) as f32;
            let q0 = ((c(lo0[a]) + 0.5) / f - 0.5).floor() as isize;
            let q1 = ((c(hi0[a]) + 0.5) / f - 0.5).floor() as isize + 1;
            lo[a] = q0 - 1 - r;
            size[a] = (q1 + 1 + r - lo[a] + 1) as usize;
        }
        // The in-bounds part of the box, then edge-clamped padding around it.
        let ilo: [usize; 3] = std::array::from_fn(|a| lo[a].clamp(0, ld[a] as isize - 1) as usize);
        let ihi: [usize; 3] = std::array::from_fn(|a| {
            (lo[a] + size[a] as isize - 1).clamp(0, ld[a] as isize - 1) as usize
        });
        let isz: [usize; 3] = std::array::from_fn(|a| ihi[a] - ilo[a] + 1);
        let inner = read(k, ilo, isz)?;
        let mut raw = vec![0.0f32; size.iter().product()];
        let cl = |a: usize, i: usize| {
            (lo[a] + i as isize).clamp(ilo[a] as isize, ihi[a] as isize) as usize - ilo[a]
        };
        let xs: Vec<usize> = (0..size[0]).map(|x| cl(0, x)).collect();
        for z in 0..size[2] {
            let sz = cl(2, z);
            for y in 0..size[1] {
                let sy = cl(1, y);
                let src = (sz * isz[1] + sy) * isz[0];
                let dst = (z * size[1] + y) * size[0];
                for (x, &sx) in xs.iter().enumerate() {
                    raw[dst + x] = norm.apply(inner[src + sx]);
                }
            }
        }
        let smooth = if rest > 0.0 {
            smooth(&raw, size, rest)
        } else {
            raw
        };
        // Central differences between clamped global neighbours (as a whole-volume computation
        // at the level's border), in level-0 voxel units, scale-normalised by sigma.
        let mut grad = vec![0.0f32; smooth.len()];
        let stride = [1, size[0], size[0] * size[1]];
        for z in 0..size[2] {
            for y in 0..size[1] {
                for x in 0..size[0] {
                    let c = [x, y, z];
                    let i = (z * size[1] + y) * size[0] + x;
                    let mut g2 = 0.0f32;
                    for a in 0..3 {
                        let gpos = lo[a] + c[a] as isize;
                        let gm = (gpos - 1).max(0);
                        let gp = (gpos + 1).min(ld[a] as isize - 1);
                        let (im, ip) = (gm - lo[a], gp - lo[a]);
                        if im < 0 || ip >= size[a] as isize || gp <= gm {
                            continue;
                        }
                        let d = (smooth[i - c[a] * stride[a] + im as usize * stride[a]]
                            - smooth[i - c[a] * stride[a] + ip as usize * stride[a]])
                            / (gp - gm) as f32;
                        g2 += d * d;
                    }
                    grad[i] = sigma * g2.sqrt() / f;
                }
            }
        }
        Ok(ScaleField {
            sigma,
            level: k,
            level_dims: ld,
            dims,
            lo,
            size,
            smooth,
            grad,
        })
    }

    /// Pyramid level the field was computed on.
    pub fn level(&self) -> usize {
        self.level
    }

    /// Smoothed intensity and scale-normalised gradient magnitude at level-0 position `p`
    /// (clamped into the volume; it must lie in the region the field was computed for).
    #[inline]
    pub fn sample(&self, p: [isize; 3]) -> (f32, f32) {
        let (mut v, mut g) = (0.0f32, 0.0f32);
        self.corners(p, |i, w| {
            v += w * self.smooth[i];
            g += w * self.grad[i];
        });
        (v, g)
    }

    /// The smoothed intensity alone at level-0 position `p` ([`Self::sample`]'s first value,
    /// the same bits).
    #[inline]
    pub fn smooth_at(&self, p: [isize; 3]) -> f32 {
        let mut v = 0.0f32;
        self.corners(p, |i, w| v += w * self.smooth[i]);
        v
    }

    /// Per ray of `rays`, the largest and smallest smoothed intensity ([`Self::smooth_at`]) at
    /// the level-0 positions `p + o` for `o` in the ray, into `out` (one per ray): the same bits
    /// as folding `smooth_at` over them.
    ///
    /// An offset of whole level voxels moves a position's trilinear corners by whole voxels and
    /// keeps its weights: where neither the position nor its corners meet the volume's or the
    /// level's edge, the 8 weights of `p`, found once, serve every sample of every ray and only
    /// the corner index moves (the enclosure's rays: 100 samples per voxel). Elsewhere each
    /// sample goes through `smooth_at`.
    pub fn extremes(&self, p: [isize; 3], rays: &[Vec<[isize; 3]>], out: &mut [(f32, f32)]) {
        let step = 1isize << self.level;
        let fl = step as f32;
        // Per axis: p's level coordinate (unclamped) and its lower corner; none off the edges.
        let mut g0 = [0isize; 3];
        let mut t = [0.0f32; 3];
        let mut fast = true;
        for a in 0..3 {
            let q = (p[a] as f32 + 0.5) / fl - 0.5;
            fast &= p[a] >= 0 && p[a] < self.dims[a] as isize && q >= 0.0;
            g0[a] = q.floor() as isize;
            t[a] = q - q.floor();
        }
        let s = self.size;
        let (sy, sz) = (s[0], s[0] * s[1]);
        let mut w = [0.0f32; 8];
        let mut k = 0;
        for wz in [1.0 - t[2], t[2]] {
            for wy in [1.0 - t[1], t[1]] {
                for wx in [1.0 - t[0], t[0]] {
                    w[k] = wx * wy * wz;
                    k += 1;
                }
            }
        }
        let corner = [0, 1, sy, sy + 1, sz, sz + 1, sz + sy, sz + sy + 1];
        // The sample at `p + o` from the shared weights, when no edge is met.
        let shared = |o: &[isize; 3]| -> Option<f32> {
            let mut at = [0usize; 3];
            for a in 0..3 {
                let pa = p[a] + o[a];
                let g = g0[a] + (o[a] >> self.level);
                let ok = o[a] & (step - 1) == 0
                    && pa >= 0
                    && pa < self.dims[a] as isize
                    && g >= 0
                    && g < self.level_dims[a] as isize - 1;
                if !ok {
                    return None;
                }
                at[a] = (g - self.lo[a]) as usize;
            }
            let base = (at[2] * s[1] + at[1]) * s[0] + at[0];
            let mut v = 0.0f32;
            for (wc, c) in w.iter().zip(corner) {
                v += wc * self.smooth[base + c];
            }
            Some(v)
        };
        for (r, e) in rays.iter().zip(out.iter_mut()) {
            *e =
                r.iter()
                    .fold((f32::NEG_INFINITY, f32::INFINITY), |(hi, lo), o| {
                        let v = fast.then(|| shared(o)).flatten().unwrap_or_else(|| {
                            self.smooth_at([p[0] + o[0], p[1] + o[1], p[2] + o[2]])
                        });
                        (hi.max(v), lo.min(v))
                    });
        }
    }

    /// Calls `f(index, weight)` for the 8 trilinear corners of level-0 position `p`, in a fixed
    /// order.
    #[inline]
    fn corners(&self, p: [isize; 3], mut f: impl FnMut(usize, f32)) {
        let fl = (1usize << self.level) as f32;
        let mut i0 = [0usize; 3];
        let mut i1 = [0usize; 3];
        let mut t = [0.0f32; 3];
        for a in 0..3 {
            let pc = p[a].clamp(0, self.dims[a] as isize - 1) as f32;
            let q = ((pc + 0.5) / fl - 0.5).clamp(0.0, (self.level_dims[a] - 1) as f32);
            let g0 = q.floor() as isize;
            let g1 = (g0 + 1).min(self.level_dims[a] as isize - 1);
            i0[a] = (g0 - self.lo[a]) as usize;
            i1[a] = (g1 - self.lo[a]) as usize;
            t[a] = q - q.floor();
        }
        let s = self.size;
        for (cz, wz) in [(i0[2], 1.0 - t[2]), (i1[2], t[2])] {
            for (cy, wy) in [(i0[1], 1.0 - t[1]), (i1[1], t[1])] {
                for (cx, wx) in [(i0[0], 1.0 - t[0]), (i1[0], t[0])] {
                    f((cz * s[1] + cy) * s[0] + cx, wx * wy * wz);
                }
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use neuvolex_ingest::downsample_mean;

    /// A smooth test volume of `d` voxels (x fastest) with structure at several scales.
    pub(crate) fn waves(d: [usize; 3]) -> Vec<f32> {
        (0..d.iter().product::<usize>())
            .map(|i| {
                let (x, y, z) = (i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1]));
                ((0.3 * x as f32).sin() * (0.11 * y as f32).cos() + 0.02 * z as f32) * 100.0
            })
            .collect()
    }

    /// Checks that `compute(origin, size)` (`voxels x ch`, x fastest) over bricks of `bs`
    /// equals its whole-volume result on a grid of `d` voxels: `close(brick, whole)` for every
    /// value (`what` names the case in a failure). Returns the whole-volume result.
    pub(crate) fn bricks_equal_whole(
        what: &str,
        d: [usize; 3],
        ch: usize,
        bs: [usize; 3],
        close: impl Fn(f32, f32) -> bool,
        compute: impl Fn([usize; 3], [usize; 3]) -> Vec<f32>,
    ) -> Vec<f32> {
        let whole = compute([0; 3], d);
        assert_eq!(whole.len(), d.iter().product::<usize>() * ch, "{what}");
        for bz in (0..d[2]).step_by(bs[2]) {
            for by in (0..d[1]).step_by(bs[1]) {
                for bx in (0..d[0]).step_by(bs[0]) {
                    let s = [
                        bs[0].min(d[0] - bx),
                        bs[1].min(d[1] - by),
                        bs[2].min(d[2] - bz),
                    ];
                    let part = compute([bx, by, bz], s);
                    for z in 0..s[2] {
                        for y in 0..s[1] {
                            for x in 0..s[0] {
                                let pi = (z * s[1] + y) * s[0] + x;
                                let wi = ((z + bz) * d[1] + y + by) * d[0] + x + bx;
                                for c in 0..ch {
                                    let (a, b) = (part[pi * ch + c], whole[wi * ch + c]);
                                    assert!(
                                        close(a, b),
                                        "{what} channel {c} at {:?}: {a} vs {b}",
                                        [x + bx, y + by, z + bz]
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
        whole
    }

    /// A pyramid of `n` levels over `v`.
    pub(crate) fn pyramid(v: &[f32], d: [usize; 3], n: usize) -> (Vec<Vec<f32>>, Vec<[usize; 3]>) {
        let mut data = vec![v.to_vec()];
        let mut dims = vec![d];
        for _ in 1..n {
            let pd = *dims.last().unwrap();
            data.push(downsample_mean(data.last().unwrap(), pd));
            dims.push([pd[0].div_ceil(2), pd[1].div_ceil(2), pd[2].div_ceil(2)]);
        }
        (data, dims)
    }

    pub(crate) fn reader<'a>(
        data: &'a [Vec<f32>],
        dims: &'a [[usize; 3]],
    ) -> impl FnMut(usize, [usize; 3], [usize; 3]) -> Result<Vec<f32>, ()> + 'a {
        move |k, o, s| {
            let d = dims[k];
            let mut out = Vec::with_capacity(s.iter().product());
            for z in o[2]..o[2] + s[2] {
                for y in o[1]..o[1] + s[1] {
                    let row = (z * d[1] + y) * d[0];
                    out.extend_from_slice(&data[k][row + o[0]..row + o[0] + s[0]]);
                }
            }
            Ok(out)
        }
    }

    #[test]
    fn plan_picks_the_level_and_completes_the_scale() {
        assert_eq!(plan(1.0, 4), (0, 1.0));
        let (k, r) = plan(8.0, 4);
        assert_eq!(k, 3);
        // Box variance of 8 voxels (63/12) plus the residual gives 64.
        assert!(((r * 8.0).powi(2) + 63.0 / 12.0 - 64.0).abs() < 1e-3);
        // A shallow pyramid: the residual does the rest at the coarsest level.
        let (k, r) = plan(8.0, 2);
        assert_eq!(k, 1);
        assert!(((r * 2.0).powi(2) + 0.25 - 64.0).abs() < 1e-3);
    }

    #[test]
    fn per_region_fields_equal_a_whole_volume_field() {
        let d = [23, 19, 17];
        let v: Vec<f32> = (0..d.iter().product::<usize>())
            .map(|i| {
                let (x, y, z) = (i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1]));
                ((0.4 * x as f32).sin() + (0.23 * y as f32 * z as f32).cos()) * 10.0
            })
            .collect();
        let (data, dims) = pyramid(&v, d, 3);
        let norm = Normaliser {
            lo: -10.0,
            hi: 10.0,
        };
        for sigma in [1.0, 2.0, 4.0, 8.0] {
            let whole = ScaleField::compute(
                sigma,
                &dims,
                &norm,
                [0; 3],
                [d[0] as isize - 1, d[1] as isize - 1, d[2] as isize - 1],
                reader(&data, &dims),
            )
            .unwrap();
            for (lo, hi) in [([-6, 3, 0], [9, 12, 7]), ([15, 0, 10], [30, 18, 25])] {
                let part =
                    ScaleField::compute(sigma, &dims, &norm, lo, hi, reader(&data, &dims)).unwrap();
                for z in lo[2]..=hi[2] {
                    for y in lo[1]..=hi[1] {
                        for x in lo[0]..=hi[0] {
                            let (a, b) = (part.sample([x, y, z]), whole.sample([x, y, z]));
                            assert!(
                                (a.0 - b.0).abs() < 1e-5 && (a.1 - b.1).abs() < 1e-5,
                                "sigma {sigma} at {:?}: {a:?} vs {b:?}",
                                [x, y, z]
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn constant_volumes_give_their_value_and_no_gradient() {
        let d = [20, 20, 20];
        let v = vec![3.0f32; 8000];
        let (data, dims) = pyramid(&v, d, 3);
        let norm = Normaliser { lo: 1.0, hi: 5.0 };
        let f =
            ScaleField::compute(4.0, &dims, &norm, [0; 3], [19; 3], reader(&data, &dims)).unwrap();
        for p in [[0, 0, 0], [19, 5, 7], [10, 10, 10]] {
            let (v, g) = f.sample(p);
            assert!((v - 0.5).abs() < 1e-6 && g.abs() < 1e-6);
        }
    }

    #[test]
    fn a_ramp_has_its_slope_at_every_scale() {
        // Intensity rising 1 per voxel along x: smoothing keeps the ramp inside, and the
        // scale-normalised gradient is sigma times the slope.
        let d = [64, 8, 8];
        let v: Vec<f32> = (0..d.iter().product::<usize>())
            .map(|i| (i % 64) as f32)
            .collect();
        let (data, dims) = pyramid(&v, d, 4);
        let norm = Normaliser { lo: 0.0, hi: 1.0 };
        for sigma in [1.0f32, 2.0, 4.0] {
            let f = ScaleField::compute(
                sigma,
                &dims,
                &norm,
                [0; 3],
                [63, 7, 7],
                reader(&data, &dims),
            )
            .unwrap();
            let (v, g) = f.sample([32, 4, 4]);
            assert!((v - 32.0).abs() < 0.6, "sigma {sigma}: {v}");
            assert!((g / sigma - 1.0).abs() < 0.05, "sigma {sigma}: {g}");
        }
    }
}
