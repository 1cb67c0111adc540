//! Classic per-voxel features, computed per brick from a halo read: intensity, the explicit
//! local features of Tzeng et al., and an ilastik-style Gaussian filter bank.
//!
//! Every function here is pure: the features of a brick depend only on its halo read, so bricks
//! can be computed in any order, in one process or many, and equal a whole-volume computation.

use neuvolex_bricks::derived::{HaloBrick, Normaliser};
use rayon::prelude::*;

pub mod context;
pub mod enclosure;
pub mod scale;
use serde::{Deserialize, Serialize};

/// Scales of the filter bank (ilastik's default set between 0.7 and 5).
pub const SIGMAS: [f32; 5] = [0.7, 1.0, 1.6, 3.5, 5.0];

/// Filter-bank channels per scale.
pub const PER_SIGMA: usize = 10;

/// Ratio of the inner Gaussian of the difference of Gaussians (ilastik: 0.66).
const DOG_RATIO: f32 = 0.66;

/// Gaussian truncation, in sigmas.
const TRUNCATE: f32 = 3.0;

/// Kernel radius of a Gaussian of `sigma`.
pub fn radius(sigma: f32) -> usize {
    (TRUNCATE * sigma).ceil().max(1.0) as usize
}

/// Halo the filter bank needs: the structure tensor chains a Gaussian of sigma/2, a central
/// difference and a Gaussian of sigma.
pub fn filter_halo() -> usize {
    let s = SIGMAS[SIGMAS.len() - 1];
    radius(0.5 * s) + 1 + radius(s)
}

/// A classic feature set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Classic {
    /// Robust-normalised intensity alone.
    Intensity,
    /// Intensity, gradient magnitude, the 6 face neighbours and normalised position.
    Local,
    /// The Gaussian filter bank at [`SIGMAS`].
    Filters,
    /// Tube and sheet measures of the filter bank's Hessian at each of [`SIGMAS`]
    /// ([`tube_measures`]): what thin vessels, lumens and plates look like, as ratios a forest's
    /// axis-aligned splits cannot form from the eigenvalues themselves.
    Tubes,
}

/// Tube measures per scale: lineness and sheetness.
pub const TUBES_PER_SIGMA: usize = 2;

/// Frangi's shape constants (alpha = beta = 0.5).
const FRANGI: f32 = 0.5;

/// Lineness and sheetness of one voxel from its Hessian eigenvalues (any order), signed +1
/// where the structure is brighter than its surroundings and -1 where darker.
///
/// With the eigenvalues ordered by magnitude (`|l1| <= |l2| <= |l3|`), Frangi's ratios are
/// `ra = |l2| / |l3|` (1 on a line, 0 on a sheet) and `rb = |l1| / sqrt(|l2 l3|)` (0 on a line,
/// 1 on a blob). Lineness is `(1 - exp(-ra^2 / 2a^2)) exp(-rb^2 / 2b^2)` where `l2` and `l3`
/// share their sign (a tube, Frangi's vesselness without its contrast term), sheetness
/// `exp(-ra^2 / 2a^2)` (one strong curvature: a plate, a thin cortex). Both lie in `[-1, 1]`,
/// are invariant to the image's contrast and scale, and are 0 on flat image.
pub fn tube_measures(h: [f32; 3]) -> [f32; 2] {
    let mut l = h;
    l.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
    let [l1, l2, l3] = l;
    if l3.abs() <= f32::EPSILON {
        return [0.0, 0.0];
    }
    let g = |r: f32| (-(r * r) / (2.0 * FRANGI * FRANGI)).exp();
    let ra = l2.abs() / l3.abs();
    let rb = l1.abs() / (l2.abs() * l3.abs()).sqrt().max(f32::MIN_POSITIVE);
    // Bright structures curve down (negative second derivatives).
    let line = if l2 * l3 > 0.0 {
        -l3.signum() * (1.0 - g(ra)) * g(rb)
    } else {
        0.0
    };
    let sheet = -l3.signum() * g(ra);
    [line, sheet]
}

/// The [`Classic::Tubes`] channels of a filter bank's output (`voxels x` [`SIGMAS`]`.len() *`
/// [`PER_SIGMA`], as [`compute`] gives for [`Classic::Filters`]).
pub fn tubes_from_bank(bank: &[f32]) -> Vec<f32> {
    let ch = SIGMAS.len() * PER_SIGMA;
    let mut out = Vec::with_capacity(bank.len() / ch * SIGMAS.len() * TUBES_PER_SIGMA);
    for v in bank.chunks_exact(ch) {
        for s in 0..SIGMAS.len() {
            let h = &v[s * PER_SIGMA + 7..s * PER_SIGMA + 10];
            out.extend_from_slice(&tube_measures([h[0], h[1], h[2]]));
        }
    }
    out
}

impl Classic {
    /// Halo voxels needed around a brick.
    pub fn halo(self) -> usize {
        match self {
            Classic::Intensity => 0,
            Classic::Local => 1,
            Classic::Filters | Classic::Tubes => filter_halo(),
        }
    }

    /// Channels per voxel.
    pub fn channels(self) -> usize {
        match self {
            Classic::Intensity => 1,
            Classic::Local => 11,
            Classic::Filters => SIGMAS.len() * PER_SIGMA,
            Classic::Tubes => SIGMAS.len() * TUBES_PER_SIGMA,
        }
    }

    /// A name per channel.
    pub fn names(self) -> Vec<String> {
        match self {
            Classic::Intensity => vec!["intensity".into()],
            Classic::Local => [
                "intensity",
                "grad_mag",
                "x-1",
                "x+1",
                "y-1",
                "y+1",
                "z-1",
                "z+1",
                "x",
                "y",
                "z",
            ]
            .map(String::from)
            .to_vec(),
            Classic::Filters => SIGMAS
                .iter()
                .flat_map(|s| {
                    [
                        "gauss", "log", "ggm", "dog", "st_e1", "st_e2", "st_e3", "hess_e1",
                        "hess_e2", "hess_e3",
                    ]
                    .map(move |n| format!("{n}_s{s}"))
                })
                .collect(),
            Classic::Tubes => SIGMAS
                .iter()
                .flat_map(|s| ["line", "sheet"].map(move |n| format!("{n}_s{s}")))
                .collect(),
        }
    }
}

impl std::str::FromStr for Classic {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "intensity" => Ok(Classic::Intensity),
            "local" => Ok(Classic::Local),
            "filters" => Ok(Classic::Filters),
            "tubes" => Ok(Classic::Tubes),
            _ => Err(format!(
                "unknown classic feature '{s}' (intensity, local, filters, tubes)"
            )),
        }
    }
}

/// Normalised position of voxel `i` along an axis of `n` voxels, in `[0, 1]`.
#[inline]
pub fn pos(i: usize, n: usize) -> f32 {
    if n <= 1 {
        0.0
    } else {
        i as f32 / (n - 1) as f32
    }
}

/// Computes `kind` for the core voxels of `b` (whose halo must be at least `kind.halo()`), in a
/// volume of `dims` voxels. Returns `voxels x channels`, voxel-major, voxels x fastest.
pub fn compute(kind: Classic, b: &HaloBrick, norm: &Normaliser, dims: [usize; 3]) -> Vec<f32> {
    assert!(
        b.halo >= kind.halo(),
        "{kind:?} needs a halo of {}, got {}",
        kind.halo(),
        b.halo
    );
    let p = b.padded();
    let n: Vec<f32> = b.data.iter().map(|&v| norm.apply(v)).collect();
    match kind {
        Classic::Intensity => core_map(b, |i| [n[i]]),
        Classic::Local => {
            let (sx, sy) = (1, p[0]);
            let sz = p[0] * p[1];
            let h = b.halo;
            let mut out = Vec::with_capacity(b.size.iter().product::<usize>() * 11);
            for z in 0..b.size[2] {
                for y in 0..b.size[1] {
                    for x in 0..b.size[0] {
                        let i = ((z + h) * p[1] + y + h) * p[0] + x + h;
                        let nb = [
                            n[i - sx],
                            n[i + sx],
                            n[i - sy],
                            n[i + sy],
                            n[i - sz],
                            n[i + sz],
                        ];
                        let g = [
                            0.5 * (nb[1] - nb[0]),
                            0.5 * (nb[3] - nb[2]),
                            0.5 * (nb[5] - nb[4]),
                        ];
                        out.push(n[i]);
                        out.push((g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt());
                        out.extend_from_slice(&nb);
                        out.push(pos(b.origin[0] + x, dims[0]));
                        out.push(pos(b.origin[1] + y, dims[1]));
                        out.push(pos(b.origin[2] + z, dims[2]));
                    }
                }
            }
            out
        }
        Classic::Filters => filter_bank(b, &n),
        Classic::Tubes => tubes_from_bank(&filter_bank(b, &n)),
    }
}

/// Maps every core voxel through `f` (given its padded index).
fn core_map<const C: usize>(b: &HaloBrick, f: impl Fn(usize) -> [f32; C]) -> Vec<f32> {
    let p = b.padded();
    let h = b.halo;
    let mut out = Vec::with_capacity(b.size.iter().product::<usize>() * C);
    for z in 0..b.size[2] {
        for y in 0..b.size[1] {
            for x in 0..b.size[0] {
                out.extend_from_slice(&f(((z + h) * p[1] + y + h) * p[0] + x + h));
            }
        }
    }
    out
}

/// A normalised Gaussian kernel of `sigma`, `2 radius + 1` taps.
pub fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let r = radius(sigma) as isize;
    let s2 = 2.0 * (sigma as f64) * (sigma as f64);
    let w: Vec<f64> = (-r..=r).map(|i| (-(i * i) as f64 / s2).exp()).collect();
    let sum: f64 = w.iter().sum();
    w.iter().map(|v| (v / sum) as f32).collect()
}

/// A box of a padded grid, `lo..hi` per axis: the voxels a step computes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Region {
    lo: [usize; 3],
    hi: [usize; 3],
}

impl Region {
    /// The whole grid.
    fn all(p: [usize; 3]) -> Region {
        Region { lo: [0; 3], hi: p }
    }

    /// Grown by `r` along the axes in `axes`, within the grid `p`.
    fn grow(self, r: usize, p: [usize; 3], axes: [bool; 3]) -> Region {
        Region {
            lo: std::array::from_fn(|k| {
                if axes[k] {
                    self.lo[k].saturating_sub(r)
                } else {
                    self.lo[k]
                }
            }),
            hi: std::array::from_fn(|k| {
                if axes[k] {
                    (self.hi[k] + r).min(p[k])
                } else {
                    self.hi[k]
                }
            }),
        }
    }

    /// Grown by `r` along every axis.
    fn grow_all(self, r: usize, p: [usize; 3]) -> Region {
        self.grow(r, p, [true; 3])
    }
}

/// Convolves along x (contiguous rows) over `reg` (reading whole rows of `src`) into `dst`,
/// clamping at the ends of each row; `dst` outside `reg` is left as it was.
fn conv_x_into(src: &[f32], p: [usize; 3], w: &[f32], reg: Region, dst: &mut [f32]) {
    let r = w.len() / 2;
    let plane = p[0] * p[1];
    dst.par_chunks_mut(plane)
        .zip(src.par_chunks(plane))
        .enumerate()
        .filter(|(z, _)| (reg.lo[2]..reg.hi[2]).contains(z))
        .for_each(|(_, (dp, sp))| {
            let mut row = vec![0.0f32; p[0] + 2 * r];
            let (x0, x1) = (reg.lo[0], reg.hi[0]);
            for y in reg.lo[1]..reg.hi[1] {
                let s = &sp[y * p[0]..(y + 1) * p[0]];
                row[..r].fill(s[0]);
                row[r..r + p[0]].copy_from_slice(s);
                row[r + p[0]..].fill(s[p[0] - 1]);
                // Tap by tap over the whole row (vectorised), each output the same sum as
                // `sum` of the products in tap order: from -0.0, as `Iterator::sum` starts.
                let d = &mut dp[y * p[0] + x0..y * p[0] + x1];
                d.fill(-0.0);
                for (t, &wt) in w.iter().enumerate() {
                    let src = &row[x0 + t..x1 + t];
                    d.iter_mut().zip(src).for_each(|(a, b)| *a += wt * b);
                }
            }
        });
}

/// [`conv_x_into`] a new grid (0 outside `reg`).
#[cfg(test)]
fn conv_x(src: &[f32], p: [usize; 3], w: &[f32], reg: Region) -> Vec<f32> {
    let mut dst = vec![0.0f32; src.len()];
    conv_x_into(src, p, w, reg, &mut dst);
    dst
}

/// Convolves along y (`axis` 1) or z (`axis` 2) over `reg` into `dst` as weighted sums of
/// rows, clamping at the grid's ends; `dst` outside `reg` is left as it was. Reads `src` only
/// within `reg` grown by the kernel's radius along `axis`.
fn conv_lines_into(
    src: &[f32],
    p: [usize; 3],
    axis: usize,
    w: &[f32],
    reg: Region,
    dst: &mut [f32],
) {
    let r = w.len() as isize / 2;
    let plane = p[0] * p[1];
    let (x0, x1) = (reg.lo[0], reg.hi[0]);
    dst.par_chunks_mut(plane)
        .enumerate()
        .filter(|(z, _)| (reg.lo[2]..reg.hi[2]).contains(z))
        .for_each(|(z, dp)| {
            for y in reg.lo[1]..reg.hi[1] {
                let d = &mut dp[y * p[0] + x0..y * p[0] + x1];
                d.fill(0.0);
                let (c, n) = if axis == 1 { (y, p[1]) } else { (z, p[2]) };
                for (t, &wt) in w.iter().enumerate() {
                    let j = (c as isize + t as isize - r).clamp(0, n as isize - 1) as usize;
                    let row = if axis == 1 {
                        (z * p[1] + j) * p[0]
                    } else {
                        (j * p[1] + y) * p[0]
                    };
                    let s = &src[row + x0..row + x1];
                    d.iter_mut().zip(s).for_each(|(a, b)| *a += wt * b);
                }
            }
        });
}

/// [`conv_lines_into`] a new grid (0 outside `reg`).
fn conv_lines(src: &[f32], p: [usize; 3], axis: usize, w: &[f32], reg: Region) -> Vec<f32> {
    let mut dst = vec![0.0f32; src.len()];
    conv_lines_into(src, p, axis, w, reg, &mut dst);
    dst
}

/// The row pass as written first: one dot product per output, over the whole grid (the
/// reference path of [`filter_bank_reference`]).
fn conv_x_dot(src: &[f32], p: [usize; 3], w: &[f32]) -> Vec<f32> {
    let r = w.len() / 2;
    let mut dst = vec![0.0f32; src.len()];
    dst.par_chunks_mut(p[0] * p[1])
        .zip(src.par_chunks(p[0] * p[1]))
        .for_each(|(dp, sp)| {
            let mut row = vec![0.0f32; p[0] + 2 * r];
            for (d, s) in dp.chunks_mut(p[0]).zip(sp.chunks(p[0])) {
                row[..r].fill(s[0]);
                row[r..r + p[0]].copy_from_slice(s);
                row[r + p[0]..].fill(s[p[0] - 1]);
                for (i, o) in d.iter_mut().enumerate() {
                    *o = w.iter().zip(&row[i..i + w.len()]).map(|(a, b)| a * b).sum();
                }
            }
        });
    dst
}

/// Two grids of scratch space for [`Scratch::smooth`]: a filter bank allocates its grids once,
/// not per pass (fresh multi-megabyte buffers cost page faults and TLB flushes).
struct Scratch {
    a: Vec<f32>,
    b: Vec<f32>,
}

impl Scratch {
    fn new(len: usize) -> Scratch {
        Scratch {
            a: vec![0.0; len],
            b: vec![0.0; len],
        }
    }

    /// Separable Gaussian smoothing of a `p`-sized grid, clamped at its edges, into `dst` for
    /// the voxels of `out` only (each pass over just what the next one reads; `dst` elsewhere
    /// is left as it was). A voxel's value does not depend on `out`: the same sums in the same
    /// order.
    fn smooth(&mut self, src: &[f32], p: [usize; 3], sigma: f32, out: Region, dst: &mut [f32]) {
        let w = gaussian_kernel(sigma);
        let r = w.len() / 2;
        conv_x_into(src, p, &w, out.grow(r, p, [false, true, true]), &mut self.a);
        conv_lines_into(
            &self.a,
            p,
            1,
            &w,
            out.grow(r, p, [false, false, true]),
            &mut self.b,
        );
        conv_lines_into(&self.b, p, 2, &w, out, dst);
    }
}

/// Separable Gaussian smoothing of a `p`-sized grid, clamped at its edges.
pub fn smooth(src: &[f32], p: [usize; 3], sigma: f32) -> Vec<f32> {
    let mut dst = vec![0.0f32; src.len()];
    Scratch::new(src.len()).smooth(src, p, sigma, Region::all(p), &mut dst);
    dst
}

/// Eigenvalues of the symmetric matrix `(xx, yy, zz, xy, xz, yz)`, descending. Closed form
/// (trigonometric) in f64; finite for finite input.
pub fn sym_eigen3(a: [f64; 6]) -> [f64; 3] {
    let [a11, a22, a33, a12, a13, a23] = a;
    let p1 = a12 * a12 + a13 * a13 + a23 * a23;
    let q = (a11 + a22 + a33) / 3.0;
    let p2 = (a11 - q).powi(2) + (a22 - q).powi(2) + (a33 - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    if p.is_nan() || p <= 1e-300 || !p.is_finite() {
        return [q, q, q];
    }
    if p1 == 0.0 {
        let mut d = [a11, a22, a33];
        d.sort_by(|x, y| y.total_cmp(x));
        return d;
    }
    let (b11, b22, b33) = ((a11 - q) / p, (a22 - q) / p, (a33 - q) / p);
    let (b12, b13, b23) = (a12 / p, a13 / p, a23 / p);
    let det = b11 * (b22 * b33 - b23 * b23) - b12 * (b12 * b33 - b23 * b13)
        + b13 * (b12 * b23 - b22 * b13);
    let r = (0.5 * det).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let e1 = q + 2.0 * p * phi.cos();
    let e3 = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    let e2 = 3.0 * q - e1 - e3;
    [e1, e2.clamp(e3, e1), e3]
}

/// Central difference of `s` along an axis with `stride` at padded coordinate `c` of `n`,
/// clamped at the grid edge.
#[inline]
fn diff(s: &[f32], i: usize, c: usize, n: usize, stride: usize) -> f32 {
    let lo = if c > 0 { i - stride } else { i };
    let hi = if c + 1 < n { i + stride } else { i };
    let span = (hi - lo) / stride;
    if span == 0 {
        0.0
    } else {
        (s[hi] - s[lo]) / span as f32
    }
}

/// The filter bank of one brick (normalised intensities `n` over the padded grid).
fn filter_bank(b: &HaloBrick, n: &[f32]) -> Vec<f32> {
    filter_bank_over(b, n, true)
}

/// The filter bank of `b` with every intermediate step over the whole padded grid: the
/// straightforward algorithm, equal bit for bit to [`compute`]'s (which restricts each step to
/// what the core reads), kept as the reference for tests and benchmarks.
pub fn filter_bank_reference(b: &HaloBrick, norm: &Normaliser) -> Vec<f32> {
    let n: Vec<f32> = b.data.iter().map(|&v| norm.apply(v)).collect();
    filter_bank_over(b, &n, false)
}

/// [`filter_bank`], its intermediate steps computed only where the core reads them
/// (`restrict`) or over the whole padded grid (the reference the restricted steps must equal
/// bit for bit).
fn filter_bank_over(b: &HaloBrick, n: &[f32], restrict: bool) -> Vec<f32> {
    let p = b.padded();
    let (sx, sy, sz) = (1, p[0], p[0] * p[1]);
    let core: usize = b.size.iter().product();
    let ch = SIGMAS.len() * PER_SIGMA;
    let mut out = vec![0.0f32; core * ch];
    let h = b.halo;
    let coord = |i: usize| [i % p[0], (i / p[0]) % p[1], i / sz];
    let core_index = |x: usize, y: usize, z: usize| ((z + h) * p[1] + y + h) * p[0] + x + h;
    // Each step computes only what the core's features read: the smoothed image one voxel
    // around the core (second differences), the structure tensor's products a kernel radius
    // around it, their gradients one more. A thin box (one slice) costs a thin slab, and a
    // brick far less than its whole halo read; every value is the same sum as over the whole grid.
    // The reference smooths every voxel of the grid with the per-output dot product.
    let mut scratch = Scratch::new(if restrict { n.len() } else { 0 });
    let mut smooth_in = |src: &[f32], sigma: f32, out: Region, dst: &mut [f32]| {
        if restrict {
            scratch.smooth(src, p, sigma, out, dst)
        } else {
            let w = gaussian_kernel(sigma);
            let a = conv_x_dot(src, p, &w);
            let a = conv_lines(&a, p, 1, &w, Region::all(p));
            conv_lines_into(&a, p, 2, &w, Region::all(p), dst)
        }
    };
    let core = if restrict {
        Region {
            lo: [h; 3],
            hi: std::array::from_fn(|k| h + b.size[k]),
        }
    } else {
        Region::all(p)
    };
    let grid = || vec![0.0f32; n.len()];
    let (mut s, mut s_in, mut g) = (grid(), grid(), grid());
    let mut prod: [Vec<f32>; 6] = std::array::from_fn(|_| grid());
    let mut st: [Vec<f32>; 6] = std::array::from_fn(|_| grid());
    for (si, &sigma) in SIGMAS.iter().enumerate() {
        let rs = radius(sigma);
        smooth_in(n, sigma, core.grow_all(1, p), &mut s);
        smooth_in(n, DOG_RATIO * sigma, core, &mut s_in);
        // Structure tensor: gradient at the inner scale, products smoothed at the outer scale.
        let around = core.grow_all(rs, p);
        smooth_in(n, 0.5 * sigma, around.grow_all(1, p), &mut g);
        {
            let [pxx, pyy, pzz, pxy, pxz, pyz] = &mut prod;
            let inside = (around.lo[2]..around.hi[2]).flat_map(|z| {
                (around.lo[1]..around.hi[1]).flat_map(move |y| {
                    (around.lo[0]..around.hi[0]).map(move |x| (z * p[1] + y) * p[0] + x)
                })
            });
            for i in inside {
                let c = coord(i);
                let gx = diff(&g, i, c[0], p[0], sx);
                let gy = diff(&g, i, c[1], p[1], sy);
                let gz = diff(&g, i, c[2], p[2], sz);
                pxx[i] = gx * gx;
                pyy[i] = gy * gy;
                pzz[i] = gz * gz;
                pxy[i] = gx * gy;
                pxz[i] = gx * gz;
                pyz[i] = gy * gz;
            }
        }
        for (c, t) in prod.iter().zip(st.iter_mut()) {
            smooth_in(c, sigma, core, t);
        }
        let (s, s_in, st) = (&s, &s_in, &st);
        let base = si * PER_SIGMA;
        out.par_chunks_mut(b.size[0] * b.size[1] * ch)
            .enumerate()
            .for_each(|(z, plane)| {
                for y in 0..b.size[1] {
                    for x in 0..b.size[0] {
                        let i = core_index(x, y, z);
                        let v = s[i];
                        let dxx = s[i + sx] - 2.0 * v + s[i - sx];
                        let dyy = s[i + sy] - 2.0 * v + s[i - sy];
                        let dzz = s[i + sz] - 2.0 * v + s[i - sz];
                        let d2 = |a: usize, c: usize| {
                            0.25 * (s[i + a + c] - s[i + a - c] - s[i - a + c] + s[i - a - c])
                        };
                        let (dxy, dxz, dyz) = (d2(sx, sy), d2(sx, sz), d2(sy, sz));
                        let gx = 0.5 * (s[i + sx] - s[i - sx]);
                        let gy = 0.5 * (s[i + sy] - s[i - sy]);
                        let gz = 0.5 * (s[i + sz] - s[i - sz]);
                        let te = sym_eigen3(std::array::from_fn(|k| st[k][i] as f64));
                        let he = sym_eigen3([dxx, dyy, dzz, dxy, dxz, dyz].map(|v| v as f64));
                        let o = &mut plane[(y * b.size[0] + x) * ch + base..][..PER_SIGMA];
                        o[0] = v;
                        o[1] = dxx + dyy + dzz;
                        o[2] = (gx * gx + gy * gy + gz * gz).sqrt();
                        o[3] = v - s_in[i];
                        for k in 0..3 {
                            o[4 + k] = te[k] as f32;
                            o[7 + k] = he[k] as f32;
                        }
                    }
                }
            });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scale::tests::bricks_equal_whole;
    use neuvolex_bricks::derived::halo_from_volume;

    fn norm() -> Normaliser {
        Normaliser { lo: 0.0, hi: 1.0 }
    }

    #[test]
    fn tube_measures_tell_lines_sheets_and_blobs_apart() {
        // A bright line: two strong negative curvatures, one flat direction.
        let [line, sheet] = tube_measures([-0.02, -4.0, -4.2]);
        assert!(line > 0.8 && sheet < 0.2, "{line} {sheet}");
        // The same line dark (a lumen in bright tissue), eigenvalues in any order.
        let [l, s] = tube_measures([4.2, 0.02, 4.0]);
        assert!((l + line).abs() < 1e-6 && (s + sheet).abs() < 1e-6);
        // A bright sheet: one strong curvature.
        let [line, sheet] = tube_measures([0.01, -0.05, -5.0]);
        assert!(line.abs() < 0.05 && sheet > 0.95, "{line} {sheet}");
        // A blob: three alike.
        let [line, sheet] = tube_measures([-3.0, -3.1, -3.2]);
        assert!(line.abs() < 0.2 && sheet.abs() < 0.2, "{line} {sheet}");
        // A saddle is no tube; flat image is nothing; contrast does not matter.
        assert_eq!(tube_measures([2.0, -3.0, 0.1])[0], 0.0);
        assert_eq!(tube_measures([0.0; 3]), [0.0, 0.0]);
        let a = tube_measures([-0.1, -2.0, -3.0]);
        let b = tube_measures([-10.0, -200.0, -300.0]);
        assert!((a[0] - b[0]).abs() < 1e-5 && (a[1] - b[1]).abs() < 1e-5);
    }

    #[test]
    fn eigenvalues_match_known_matrices() {
        let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-9);
        assert!(close(
            sym_eigen3([3.0, 1.0, 2.0, 0.0, 0.0, 0.0]),
            [3.0, 2.0, 1.0]
        ));
        // [[2,1,0],[1,2,0],[0,0,5]]: 5, 3, 1.
        assert!(close(
            sym_eigen3([2.0, 2.0, 5.0, 1.0, 0.0, 0.0]),
            [5.0, 3.0, 1.0]
        ));
        assert_eq!(sym_eigen3([0.0; 6]), [0.0; 3]);
        // Extreme magnitudes stay finite and ordered.
        for s in [1e-30, 1e30] {
            let e = sym_eigen3([s, -s, 0.5 * s, 0.3 * s, -0.2 * s, 0.1 * s]);
            assert!(e.iter().all(|v| v.is_finite()) && e[0] >= e[1] && e[1] >= e[2]);
            let tr = e.iter().sum::<f64>();
            assert!((tr - 0.5 * s).abs() <= 1e-9 * s);
        }
    }

    #[test]
    fn gaussian_preserves_constants_and_mass() {
        let k = gaussian_kernel(1.6);
        assert_eq!(k.len(), 2 * 5 + 1);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let p = [7, 5, 9];
        let s = smooth(&vec![3.5; 7 * 5 * 9], p, 5.0);
        assert!(s.iter().all(|v| (v - 3.5).abs() < 1e-5));
    }

    /// A smooth test volume with structure at several scales.
    fn volume(d: [usize; 3]) -> Vec<f32> {
        let mut v = Vec::new();
        for z in 0..d[2] {
            for y in 0..d[1] {
                for x in 0..d[0] {
                    let (fx, fy, fz) = (x as f32, y as f32, z as f32);
                    v.push((0.3 * fx).sin() + (0.17 * fy + 0.05 * fz).cos() + 0.01 * fx * fz);
                }
            }
        }
        v
    }

    #[test]
    fn bricks_equal_a_whole_volume_computation() {
        let d = [21, 13, 11];
        let v = volume(d);
        for kind in [Classic::Intensity, Classic::Local, Classic::Filters] {
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-4 * (1.0 + b.abs());
            let whole = bricks_equal_whole(
                &format!("{kind:?}"),
                d,
                kind.channels(),
                [8, 8, 8],
                close,
                |o, s| {
                    compute(
                        kind,
                        &halo_from_volume(&v, d, o, s, kind.halo()),
                        &norm(),
                        d,
                    )
                },
            );
            assert!(whole.iter().all(|x| x.is_finite()));
        }
    }

    #[test]
    fn the_row_pass_is_the_dot_product_in_tap_order_bit_for_bit() {
        // Against the plain per-output dot product (`sum` of the products in tap order), on
        // rows with signed zeros, tiny and huge values.
        let p = [37, 3, 2];
        let mut x = 99u64;
        let src: Vec<f32> = (0..p.iter().product::<usize>())
            .map(|i| {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
                match i % 7 {
                    0 => -0.0,
                    1 => 0.0,
                    2 => u * 1e-30,
                    3 => u * 1e20,
                    _ => u,
                }
            })
            .collect();
        for sigma in [0.35, 1.0, 2.5, 5.0] {
            let w = gaussian_kernel(sigma);
            let r = w.len() / 2;
            let got = conv_x(&src, p, &w, Region::all(p));
            for (k, line) in src.chunks(p[0]).enumerate() {
                let at = |i: isize| line[i.clamp(0, p[0] as isize - 1) as usize];
                for i in 0..p[0] {
                    let want: f32 = w
                        .iter()
                        .enumerate()
                        .map(|(t, wt)| wt * at(i as isize + t as isize - r as isize))
                        .sum();
                    assert_eq!(
                        got[k * p[0] + i].to_bits(),
                        want.to_bits(),
                        "sigma {sigma} row {k} x {i}"
                    );
                }
            }
        }
    }

    #[test]
    fn restricted_steps_give_the_whole_grid_values_bit_for_bit() {
        let d = [40, 37, 45];
        let mut v = volume(d);
        // Some noise and a step, so every channel varies.
        let mut x = 12345u64;
        for (i, e) in v.iter_mut().enumerate() {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *e += ((x >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.3
                + if i % 40 > 20 { 1.0 } else { 0.0 };
        }
        let h = Classic::Filters.halo();
        // A brick inside, one at the volume's corner, a one-slice box, and a wider halo.
        for (o, s, halo) in [
            ([8, 6, 10], [16, 16, 16], h),
            ([0, 0, 0], [12, 9, 7], h),
            ([3, 0, 22], [37, 37, 1], h),
            ([5, 5, 5], [8, 8, 8], h + 3),
        ] {
            let b = halo_from_volume(&v, d, o, s, halo);
            let n: Vec<f32> = b.data.iter().map(|&x| norm().apply(x)).collect();
            let fast = filter_bank_over(&b, &n, true);
            let full = filter_bank_over(&b, &n, false);
            assert_eq!(fast.len(), full.len());
            let same = fast
                .iter()
                .zip(&full)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "box {o:?} {s:?}: restricted steps changed a value");
        }
    }

    #[test]
    fn filters_respond_to_what_they_measure() {
        // A bright ball: the Hessian at its centre is negative definite, the LoG negative,
        // the gradient magnitude peaks on its surface, not at its centre.
        let d = [24, 24, 24];
        let mut v = vec![0.0f32; 24 * 24 * 24];
        for z in 0..24 {
            for y in 0..24 {
                for x in 0..24 {
                    let r2 = [x, y, z]
                        .iter()
                        .map(|&c| (c as f32 - 12.0).powi(2))
                        .sum::<f32>();
                    v[(z * 24 + y) * 24 + x] = if r2 < 16.0 { 1.0 } else { 0.0 };
                }
            }
        }
        let f = compute(
            Classic::Filters,
            &halo_from_volume(&v, d, [0; 3], d, filter_halo()),
            &norm(),
            d,
        );
        let ch = Classic::Filters.channels();
        let at = |x: usize, y: usize, z: usize, c: usize| f[((z * 24 + y) * 24 + x) * ch + c];
        // sigma 1.6 is scale 2.
        let b = 2 * PER_SIGMA;
        assert!(at(12, 12, 12, b + 1) < 0.0, "LoG at the centre");
        assert!(
            at(12, 12, 12, b + 7) < 0.0,
            "largest Hessian eigenvalue at the centre"
        );
        assert!(at(16, 12, 12, b + 2) > 5.0 * at(12, 12, 12, b + 2).max(1e-4));
        assert!(at(12, 12, 12, b) > at(2, 2, 2, b));
    }

    #[test]
    fn extreme_and_constant_inputs_stay_finite() {
        let d = [9, 9, 9];
        for (v, nm) in [
            (vec![7.0f32; 729], Normaliser { lo: 7.0, hi: 7.0 }),
            (
                volume(d).iter().map(|x| x * 1e30).collect(),
                Normaliser {
                    lo: -1e30,
                    hi: 1e30,
                },
            ),
            (
                volume(d).iter().map(|x| x * 1e-30).collect(),
                Normaliser {
                    lo: -1e-30,
                    hi: 1e-30,
                },
            ),
        ] {
            for kind in [Classic::Intensity, Classic::Local, Classic::Filters] {
                let f = compute(
                    kind,
                    &halo_from_volume(&v, d, [0; 3], d, kind.halo()),
                    &nm,
                    d,
                );
                assert!(f.iter().all(|x| x.is_finite()), "{kind:?}");
            }
        }
    }

    #[test]
    fn local_features_are_the_neighbours_and_position() {
        let d = [4, 3, 2];
        let v: Vec<f32> = (0..24).map(|i| i as f32).collect();
        let f = compute(
            Classic::Local,
            &halo_from_volume(&v, d, [0; 3], d, 1),
            &norm(),
            d,
        );
        // Voxel (1, 1, 0) = 5: neighbours 4, 6, 1, 9, 5 (clamped), 17.
        let o = &f[5 * 11..6 * 11];
        assert_eq!(&o[..1], &[5.0]);
        assert_eq!(&o[2..8], &[4.0, 6.0, 1.0, 9.0, 5.0, 17.0]);
        assert_eq!(&o[8..], &[1.0 / 3.0, 0.5, 0.0]);
        assert_eq!(Classic::Local.names().len(), 11);
        assert_eq!(Classic::Filters.names().len(), 50);
        assert_eq!(Classic::Tubes.names().len(), Classic::Tubes.channels());
    }
}
