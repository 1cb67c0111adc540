//! K-means on per-voxel feature rows that stream brick by brick: seeded k-means++
//! initialisation on a sample, then either Lloyd iterations whose per-brick partial sums merge
//! in brick order (deterministic for any thread count), or mini-batch updates with one brick per
//! batch.
//!
//! The single-process Lloyd ([`KMeans::fit`]) keeps Hamerly's bounds per row (the assigned
//! cluster, an upper bound on the distance to it and a lower bound on the distance to every
//! other centroid; 10 bytes a row, within [`KMeansConfig::bounds_mib`]), so most rows skip the
//! distance product once the centroids settle. The bounds carry margins for the rounding of the
//! distance product, so a row is only skipped when the product would assign it to the same
//! cluster: every pass's statistics equal the sum of [`KMeans::partial`] over the bricks (the
//! step a distributed run merges) bit for bit. `bounds_mib: 0` turns the bounds off: plain
//! Lloyd, every distance every pass, the same result. [`KMeansConfig::bounds`] says whether
//! passes use them always or only where they measure faster ([`BoundsUse::Auto`], the default:
//! with the fused assignment kernel of `crate::nearest`, plain passes are usually faster at
//! k = 50).
//!
//! [`KMeans::fit_from`] starts from given centroids instead of k-means++ (for comparisons
//! against another implementation from the same start); [`KMeans::init_centroids`] gives the
//! centroids [`KMeans::fit`] would start from.

use crate::nearest::{Packed, Path};
use crate::{Result, ViewpointError};
use neuvolex_bricks::rng::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Rows per parallel task of [`KMeans::assign`].
const BLOCK: usize = 2048;

/// Rows a plain pass assigns before it tallies them (64 KiB of 64-D rows: still in the core's
/// cache when the tally reads them again).
const TALLY_BLOCK: usize = 256;

/// Bytes of bounds per row: the cluster (u16) and two f32 bounds.
const BOUND_BYTES: usize = 10;

/// How centroids are updated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Algorithm {
    /// Full Lloyd iterations; every iteration streams every brick once.
    Lloyd,
    /// Sculley's mini-batch k-means with one brick per batch, for `epochs` passes over the
    /// bricks in a seeded random order.
    MiniBatch {
        /// Passes over the bricks.
        epochs: usize,
    },
}

/// K-means settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct KMeansConfig {
    /// Clusters.
    pub k: usize,
    /// Seed of the initialisation sample and k-means++.
    pub seed: u64,
    /// Most Lloyd iterations.
    pub max_iter: usize,
    /// Stop when the centroids move less than `tol` times the mean feature variance (as
    /// scikit-learn's `tol`).
    pub tol: f64,
    /// Rows sampled for k-means++.
    pub init_sample: usize,
    /// Update rule.
    pub algorithm: Algorithm,
    /// Memory for Lloyd's per-row bounds, in MiB (10 bytes a row). Bricks past the budget
    /// run without bounds: the same result, each pass computing every distance. `0` turns
    /// the bounds off (plain Lloyd).
    #[serde(default = "default_bounds_mib")]
    pub bounds_mib: usize,
    /// Whether Lloyd passes use the bounds (within `bounds_mib`): always, or where they
    /// measure faster. The result is the same either way, bit for bit.
    #[serde(default)]
    pub bounds: BoundsUse,
}

/// When Lloyd keeps Hamerly's bounds (which never change the result, only the time).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum BoundsUse {
    /// Measured: the first pass runs without bounds, the next two with them (the first of
    /// those makes them), and the rest run the faster way. With the fused assignment kernel a
    /// pass without bounds is usually the faster on low-k features (k = 50 on 11-D or 64-D
    /// features: 1.6–1.7x in `benches/kmeans.rs`); the bounds can pay off where the distance
    /// product is large (`k x dim`) and most rows settle.
    #[default]
    Auto,
    /// Every pass with bounds (Hamerly's algorithm).
    Always,
}

fn default_bounds_mib() -> usize {
    1024
}

impl Default for KMeansConfig {
    fn default() -> Self {
        KMeansConfig {
            k: 50,
            seed: 0,
            max_iter: 100,
            tol: 1e-4,
            init_sample: 20_000,
            algorithm: Algorithm::Lloyd,
            bounds_mib: default_bounds_mib(),
            bounds: BoundsUse::Auto,
        }
    }
}

/// A fitted clustering.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KMeans {
    /// Feature dimension.
    pub dim: usize,
    /// `k x dim` centroids.
    pub centroids: Vec<f32>,
    /// Sum of squared distances of every row to its centroid.
    pub inertia: f64,
    /// Lloyd iterations (or mini-batch epochs) run.
    pub iterations: usize,
    /// Rows per cluster.
    pub counts: Vec<u64>,
}

/// Per-brick sufficient statistics of an assignment: rows, feature sums and squared distances
/// per cluster. Partials merge by addition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Partial {
    /// Rows per cluster.
    pub counts: Vec<u64>,
    /// `k x dim` feature sums.
    pub sums: Vec<f64>,
    /// Summed squared distances.
    pub inertia: f64,
}

impl Partial {
    /// Empty statistics.
    pub fn new(k: usize, dim: usize) -> Self {
        Partial {
            counts: vec![0; k],
            sums: vec![0.0; k * dim],
            inertia: 0.0,
        }
    }

    /// Adds another partial.
    pub fn merge(&mut self, o: &Partial) {
        for (a, b) in self.counts.iter_mut().zip(&o.counts) {
            *a += b;
        }
        for (a, b) in self.sums.iter_mut().zip(&o.sums) {
            *a += b;
        }
        self.inertia += o.inertia;
    }
}

/// Squared Euclidean distance, summed in 8 interleaved partial sums (which compile to vector
/// lanes; one running sum is a chain of dependent additions, and LLVM may not reorder it).
/// Every path (bounds, plain passes, assignment) uses this one function, so they agree bit for
/// bit; the bounds' error margin holds for any order of summation.
#[inline(always)]
fn sq_dist(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let mut tail = 0.0f32;
    for (x, y) in ca.remainder().iter().zip(cb.remainder()) {
        tail += (x - y) * (x - y);
    }
    for (x, y) in ca.zip(cb) {
        for j in 0..8 {
            let t = x[j] - y[j];
            acc[j] += t * t;
        }
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// Hamerly's bounds of one chunk's rows: the assigned cluster, an upper bound on the distance to
/// its centroid and a lower bound on the distance to every other centroid.
#[derive(Debug, Clone, Default)]
struct Bounds {
    assign: Vec<u16>,
    upper: Vec<f32>,
    lower: Vec<f32>,
}

/// How a chunk runs its Lloyd passes.
#[derive(Debug, Clone)]
enum ChunkState {
    /// Not seen yet.
    Fresh,
    /// Checked by a pass without bounds; no bounds yet.
    Seen,
    /// Past the bounds budget: every distance, every pass.
    Plain,
    /// With bounds.
    Bounded(Bounds),
}

/// What the bounds test needs to know about the current centroids. Every quantity is rounded
/// the safe way (upper bounds up, lower bounds down) by a relative margin above the rounding
/// error of `d`-term sums, so a skipped row is one the distance product would not move.
struct Geometry {
    /// The centroids as the assignment kernel reads them.
    packed: Packed,
    /// Upper bounds of the centroid norms.
    norm: Vec<f32>,
    /// Largest centroid norm (upper bound).
    norm_max: f32,
    /// Lower bound of half the distance from each centroid to its nearest other centroid.
    half_gap: Vec<f32>,
    /// Upper bound of each centroid's move in the last update.
    moved: Vec<f32>,
    /// Upper bound of the largest move of the other centroids.
    moved_other: Vec<f32>,
    /// Relative error bound of a `d`-term sum of products in f32 (doubled).
    gamma: f32,
}

impl Geometry {
    fn new(km: &KMeans, previous: Option<&[f32]>) -> Geometry {
        let (k, d) = (km.k(), km.dim);
        let gamma = 2.0 * (d as f32 + 2.0) * f32::EPSILON * 0.5;
        let up = |x: f32| x * (1.0 + gamma);
        let down = |x: f32| x * (1.0 - gamma);
        let n2 = km.norms2();
        let norm: Vec<f32> = n2.iter().map(|&v| up(up(v).sqrt())).collect();
        let norm_max = norm.iter().cloned().fold(0.0, f32::max);
        let c = |j: usize| &km.centroids[j * d..(j + 1) * d];
        let half_gap = (0..k)
            .map(|j| {
                let m = (0..k)
                    .filter(|&i| i != j)
                    .map(|i| sq_dist(c(i), c(j)))
                    .fold(f32::INFINITY, f32::min);
                down(0.5 * down(m).sqrt())
            })
            .collect();
        let moved: Vec<f32> = match previous {
            Some(p) => (0..k)
                .map(|j| up(up(sq_dist(&p[j * d..(j + 1) * d], c(j))).sqrt()))
                .collect(),
            None => vec![0.0; k],
        };
        // The largest and second largest moves give every centroid's "largest other".
        let (mut m1, mut m2, mut at) = (0.0f32, 0.0f32, usize::MAX);
        for (j, &m) in moved.iter().enumerate() {
            if m > m1 {
                (m2, m1, at) = (m1, m, j);
            } else if m > m2 {
                m2 = m;
            }
        }
        let moved_other = (0..k).map(|j| if j == at { m2 } else { m1 }).collect();
        Geometry {
            packed: Packed::new(&km.centroids, d, &n2),
            norm,
            norm_max,
            half_gap,
            moved,
            moved_other,
            gamma,
        }
    }

    #[inline]
    fn up(&self, x: f32) -> f32 {
        x * (1.0 + self.gamma)
    }

    #[inline]
    fn down(&self, x: f32) -> f32 {
        x * (1.0 - self.gamma)
    }

    /// Bound of the distance product's error on `|c|^2 - 2 x.c` for a row of norm at most `x`.
    #[inline]
    fn error(&self, x: f32) -> f32 {
        let s = self.norm_max + x;
        self.gamma * s * s
    }

    /// True when a row assigned to `a`, at distance at most `u` from it and at least `l` from
    /// every other centroid, keeps `a` under the distance product: the squared distances
    /// differ by more than twice the product's error (with a factor of 2 to spare).
    #[inline]
    fn settled(&self, a: usize, u: f32, l: f32) -> bool {
        let lo = self.down(l.max(2.0 * self.half_gap[a] - u));
        // |x| <= |x - c_a| + |c_a|.
        lo > u && (lo - u) * (lo + u) > 4.0 * self.error(u + self.norm[a])
    }
}

fn check_rows(rows: &[f32], dim: usize) -> Result<()> {
    check_shape(rows, dim)?;
    if let Some(i) = rows.iter().position(|v| !v.is_finite()) {
        return Err(ViewpointError::Input(format!(
            "feature value {} at row {} is not finite",
            rows[i],
            i / dim
        )));
    }
    Ok(())
}

/// Whether `rows` make whole rows of `dim` values.
fn check_shape(rows: &[f32], dim: usize) -> Result<()> {
    if dim == 0 || !rows.len().is_multiple_of(dim) {
        return Err(ViewpointError::Input(format!(
            "{} feature values do not make rows of {dim}",
            rows.len()
        )));
    }
    Ok(())
}

impl KMeans {
    /// Clusters.
    pub fn k(&self) -> usize {
        self.centroids.len() / self.dim
    }

    /// Index and squared distance of the centroid nearest to `x`.
    #[inline]
    pub fn nearest(&self, x: &[f32]) -> (usize, f32) {
        let mut best = (0, f32::INFINITY);
        for (c, cen) in self.centroids.chunks_exact(self.dim).enumerate() {
            let mut d = 0.0f32;
            for (a, b) in x.iter().zip(cen) {
                let t = a - b;
                d += t * t;
            }
            if d < best.1 {
                best = (c, d);
            }
        }
        best
    }

    /// Squared norms of the centroids, as the distance product uses them.
    fn norms2(&self) -> Vec<f32> {
        self.centroids
            .chunks_exact(self.dim)
            .map(|c| c.iter().map(|v| v * v).sum())
            .collect()
    }

    /// The centroids as the assignment kernel reads them.
    fn packed(&self) -> Packed {
        Packed::new(&self.centroids, self.dim, &self.norms2())
    }

    /// Nearest centroid of every row by the smallest `|c|^2 - 2 x.c` (`|x - c|^2` less the
    /// row's own `|x|^2`, as scikit-learn computes it; the fused kernel of [`crate::nearest`]).
    /// Ties go to the lower index.
    fn nearest_rows(&self, rows: &[f32], packed: &Packed) -> Vec<u16> {
        let mut out = vec![0u16; rows.len() / self.dim];
        packed.nearest(rows, &mut out, None);
        out
    }

    /// The nearest cluster of every row.
    pub fn assign(&self, rows: &[f32]) -> Vec<u16> {
        let packed = self.packed();
        rows.par_chunks(self.dim * BLOCK)
            .flat_map_iter(|ch| self.nearest_rows(ch, &packed))
            .collect()
    }

    /// The assignment statistics of one brick's rows (the pure per-brick step).
    pub fn partial(&self, rows: &[f32]) -> Partial {
        self.partial_packed(rows, &self.packed())
    }

    /// [`Self::partial`] with the centroids already packed: blocks of [`TALLY_BLOCK`] rows
    /// are assigned and then tallied while they are still in cache (in row order, so the
    /// statistics are those of one assignment of the whole chunk followed by one tally).
    fn partial_packed(&self, rows: &[f32], packed: &Packed) -> Partial {
        let d = self.dim;
        let mut p = Partial::new(self.k(), d);
        let mut labels = vec![0u16; TALLY_BLOCK.min(rows.len() / d)];
        let path = Path::detect();
        for blk in rows.chunks(d * TALLY_BLOCK) {
            let labels = &mut labels[..blk.len() / d];
            packed.nearest_on(path, blk, labels, None, None);
            self.tally_on(path, &mut p, blk, labels, &[]);
        }
        p
    }

    /// Adds the statistics of `rows` under the assignment `assign` to `p`, by the kernels of
    /// the given path (which must be [`Path::available`]: the same operations in the same
    /// order, so the same bits). `known[i]`, when `i` is inside it and it is not NaN, is
    /// already `sq_dist` of row `i` to its centroid (the same value, so the same bits).
    fn tally_on(&self, path: Path, p: &mut Partial, rows: &[f32], assign: &[u16], known: &[f32]) {
        assert!(path.available());
        #[cfg(target_arch = "x86_64")]
        match path {
            Path::Avx512 => {
                /// The body compiled for AVX-512 (wider f64 sums).
                #[target_feature(enable = "avx512f")]
                fn wide(km: &KMeans, p: &mut Partial, rows: &[f32], assign: &[u16], known: &[f32]) {
                    km.tally_body(p, rows, assign, known)
                }
                // SAFETY: AVX-512F is available (asserted above).
                return unsafe { wide(self, p, rows, assign, known) };
            }
            Path::Avx2Fma => {
                /// The body compiled for AVX2 (Rust never contracts `a * b + c` into an FMA,
                /// so enabling it changes no rounding).
                #[target_feature(enable = "avx2,fma")]
                fn wide(km: &KMeans, p: &mut Partial, rows: &[f32], assign: &[u16], known: &[f32]) {
                    km.tally_body(p, rows, assign, known)
                }
                // SAFETY: AVX2 and FMA are available (asserted above).
                return unsafe { wide(self, p, rows, assign, known) };
            }
            Path::Scalar => {}
        }
        self.tally_body(p, rows, assign, known)
    }

    /// The body of [`Self::tally_on`].
    #[inline(always)]
    fn tally_body(&self, p: &mut Partial, rows: &[f32], assign: &[u16], known: &[f32]) {
        let d = self.dim;
        for (i, (x, &c)) in rows.chunks_exact(d).zip(assign).enumerate() {
            let c = c as usize;
            p.counts[c] += 1;
            let e = match known.get(i) {
                Some(&e) if !e.is_nan() => e,
                _ => sq_dist(x, &self.centroids[c * d..(c + 1) * d]),
            };
            p.inertia += e as f64;
            for (s, &v) in p.sums[c * d..(c + 1) * d].iter_mut().zip(x) {
                *s += v as f64;
            }
        }
    }

    /// One Lloyd pass over a chunk with Hamerly's bounds: the same statistics as
    /// [`Self::partial`], computing distances only for rows whose bounds cannot rule out a
    /// change of cluster. `state` is the chunk's bounds (made on the first pass). Also returns
    /// how many rows needed every distance.
    fn bounded_partial(&self, rows: &[f32], state: &mut Bounds, g: &Geometry) -> (Partial, usize) {
        self.bounded_on(Path::detect(), rows, state, g)
    }

    /// [`Self::bounded_partial`] compiled for (and running the kernels of) the given path,
    /// which must be [`Path::available`]: the same operations in the same order, so the same
    /// bits.
    fn bounded_on(
        &self,
        path: Path,
        rows: &[f32],
        state: &mut Bounds,
        g: &Geometry,
    ) -> (Partial, usize) {
        assert!(path.available());
        #[cfg(target_arch = "x86_64")]
        match path {
            Path::Avx512 => {
                /// The body compiled for AVX-512.
                #[target_feature(enable = "avx512f")]
                fn wide(
                    km: &KMeans,
                    rows: &[f32],
                    state: &mut Bounds,
                    g: &Geometry,
                ) -> (Partial, usize) {
                    km.bounded_body(Path::Avx512, rows, state, g)
                }
                // SAFETY: AVX-512F is available (asserted above).
                return unsafe { wide(self, rows, state, g) };
            }
            Path::Avx2Fma => {
                /// The body compiled for AVX2 and FMA (never contracted into).
                #[target_feature(enable = "avx2,fma")]
                fn wide(
                    km: &KMeans,
                    rows: &[f32],
                    state: &mut Bounds,
                    g: &Geometry,
                ) -> (Partial, usize) {
                    km.bounded_body(Path::Avx2Fma, rows, state, g)
                }
                // SAFETY: AVX2 and FMA are available (asserted above).
                return unsafe { wide(self, rows, state, g) };
            }
            Path::Scalar => {}
        }
        self.bounded_body(path, rows, state, g)
    }

    /// The body of [`Self::bounded_partial`].
    #[inline(always)]
    fn bounded_body(
        &self,
        path: Path,
        rows: &[f32],
        state: &mut Bounds,
        g: &Geometry,
    ) -> (Partial, usize) {
        let d = self.dim;
        let n = rows.len() / d;
        let first = state.assign.len() != n;
        if first {
            // First pass: every row gets its distances.
            state.assign = vec![0; n];
            state.upper = vec![0.0; n];
            state.lower = vec![0.0; n];
        }
        // Blocks of TALLY_BLOCK rows, each tested, assigned and tallied while it is in cache
        // (rows are independent and the tally runs in row order, so the blocks give the
        // statistics of one pass over the chunk).
        let zero = vec![0.0f32; d];
        let m = TALLY_BLOCK.min(n);
        let mut gathered = vec![0.0f32; m * d];
        let (mut labels, mut seconds) = (vec![0u16; m], vec![0.0f32; m]);
        // Squared distances to the final centroid where computed (NaN: not computed).
        let mut known = vec![f32::NAN; m];
        let mut pending: Vec<u32> = Vec::with_capacity(m);
        let mut p = Partial::new(self.k(), d);
        let mut full = 0;
        for (bi, blk) in rows.chunks(d * TALLY_BLOCK).enumerate() {
            let o = bi * TALLY_BLOCK;
            let len = blk.len() / d;
            known[..len].fill(f32::NAN);
            pending.clear();
            if first {
                pending.extend(0..len as u32);
            } else {
                for (j, x) in blk.chunks_exact(d).enumerate() {
                    let i = o + j;
                    let a = state.assign[i] as usize;
                    let mut u = g.up(state.upper[i] + g.moved[a]);
                    let l = g.down(state.lower[i] - g.moved_other[a]).max(0.0);
                    state.lower[i] = l;
                    if !g.settled(a, u, l) {
                        // Tighten the upper bound to the distance itself, then test again.
                        let e = sq_dist(x, &self.centroids[a * d..(a + 1) * d]);
                        known[j] = e;
                        u = g.up(e.sqrt());
                        if !g.settled(a, u, l) {
                            pending.push(j as u32);
                        }
                    }
                    state.upper[i] = u;
                }
            }
            full += pending.len();
            // Rows the bounds cannot settle: the full assignment kernel, as `partial` runs
            // it (on the block itself where every row is pending).
            let src: &[f32] = if pending.len() == len {
                blk
            } else {
                for (q, &j) in pending.iter().enumerate() {
                    let j = j as usize;
                    gathered[q * d..(q + 1) * d].copy_from_slice(&blk[j * d..(j + 1) * d]);
                }
                &gathered[..pending.len() * d]
            };
            let np = pending.len();
            g.packed
                .nearest_on(path, src, &mut labels[..np], None, Some(&mut seconds[..np]));
            for (q, &j) in pending.iter().enumerate() {
                let (x, j) = (&src[q * d..(q + 1) * d], j as usize);
                let (a, second) = (labels[q] as usize, seconds[q]);
                let xn = sq_dist(x, &zero);
                // |x|^2 + (|c|^2 - 2 x.c) is the squared distance within the kernel's error.
                let e = g.error(g.up(xn.sqrt()));
                let i = o + j;
                state.assign[i] = a as u16;
                let dist = sq_dist(x, &self.centroids[a * d..(a + 1) * d]);
                known[j] = dist;
                state.upper[i] = g.up(dist.sqrt());
                state.lower[i] = g.down((second + xn - e).max(0.0).sqrt());
            }
            self.tally_on(path, &mut p, blk, &state.assign[o..o + len], &known[..len]);
        }
        (p, full)
    }

    /// Fits on `chunks` chunks of rows (`load(i)` gives chunk `i`, `dim` values per row); chunks
    /// are loaded again for every pass, so only one chunk per thread is in memory (besides
    /// Lloyd's 10 bytes of bounds per row).
    pub fn fit<F, R>(chunks: usize, dim: usize, load: F, cfg: &KMeansConfig) -> Result<KMeans>
    where
        F: Fn(usize) -> Result<R> + Sync,
        R: AsRef<[f32]>,
    {
        Ok(Self::fit_counting(chunks, dim, load, cfg, None)?.0)
    }

    /// [`Self::fit`] from the given `k x dim` centroids `init` (row-major, `k = cfg.k`)
    /// instead of k-means++. The seeded sample is still drawn: it gives the tolerance's mean
    /// feature variance and the rows that re-seed empty clusters. `init` of another length
    /// than `cfg.k * dim`, or with a value that is not finite, is an error.
    pub fn fit_from<F, R>(
        chunks: usize,
        dim: usize,
        load: F,
        cfg: &KMeansConfig,
        init: &[f32],
    ) -> Result<KMeans>
    where
        F: Fn(usize) -> Result<R> + Sync,
        R: AsRef<[f32]>,
    {
        Ok(Self::fit_counting(chunks, dim, load, cfg, Some(init))?.0)
    }

    /// The `k x dim` centroids [`Self::fit`] starts from with `cfg`: k-means++ on the seeded
    /// sample. `fit_from` from them gives `fit`'s result (Lloyd: bit for bit).
    pub fn init_centroids<F, R>(
        chunks: usize,
        dim: usize,
        load: F,
        cfg: &KMeansConfig,
    ) -> Result<Vec<f32>>
    where
        F: Fn(usize) -> Result<R> + Sync,
        R: AsRef<[f32]>,
    {
        check_k(cfg)?;
        let mut rng = Rng::new(cfg.seed);
        let (_, sample) = draw_sample(chunks, dim, &load, cfg, &mut rng)?;
        Ok(KMeans::seed(&sample, dim, cfg, &mut rng).0.centroids)
    }

    /// [`Self::fit`] or [`Self::fit_from`], also returning how many rows had their distances
    /// to every centroid computed, over all passes.
    fn fit_counting<F, R>(
        chunks: usize,
        dim: usize,
        load: F,
        cfg: &KMeansConfig,
        init: Option<&[f32]>,
    ) -> Result<(KMeans, u64)>
    where
        F: Fn(usize) -> Result<R> + Sync,
        R: AsRef<[f32]>,
    {
        check_k(cfg)?;
        if let Some(init) = init {
            check_init(init, cfg.k, dim)?;
        }
        let mut rng = Rng::new(cfg.seed);
        let (mut order, sample) = draw_sample(chunks, dim, &load, cfg, &mut rng)?;
        let (mut km, tol) = match init {
            Some(init) => (
                KMeans {
                    dim,
                    centroids: init.to_vec(),
                    inertia: 0.0,
                    iterations: 0,
                    counts: Vec::new(),
                },
                tolerance(&sample, dim, cfg.tol),
            ),
            None => KMeans::seed(&sample, dim, cfg, &mut rng),
        };
        let full = AtomicU64::new(0);
        let pass = |km: &KMeans| -> Result<Partial> {
            let parts: Vec<Result<Partial>> = (0..chunks)
                .into_par_iter()
                .map(|c| {
                    let rows = load(c)?;
                    check_rows(rows.as_ref(), dim)?;
                    full.fetch_add((rows.as_ref().len() / dim) as u64, Ordering::Relaxed);
                    Ok(km.partial(rows.as_ref()))
                })
                .collect();
            let mut total = Partial::new(km.k(), dim);
            for p in parts {
                total.merge(&p?);
            }
            Ok(total)
        };
        match cfg.algorithm {
            Algorithm::Lloyd => {
                // Rows get bounds while the budget lasts (the reservation order may vary with
                // the threads; the result does not, bounds or not).
                let budget = AtomicUsize::new(cfg.bounds_mib.saturating_mul(1 << 20));
                let mut states = vec![ChunkState::Fresh; chunks];
                // The centroids of the last pass with bounds (their moves since then widen
                // the bounds; passes without bounds leave them as they are).
                let mut previous: Option<Vec<f32>> = None;
                // Auto: [time without bounds, time of the second pass with bounds].
                let mut probe = [f64::NAN; 2];
                let mut pass_no = 0usize;
                let mut bounded = |km: &KMeans| -> Result<Partial> {
                    let use_bounds = cfg.bounds_mib > 0
                        && match cfg.bounds {
                            BoundsUse::Always => true,
                            BoundsUse::Auto => match pass_no {
                                0 => false,
                                1 | 2 => true,
                                _ => probe[1] < probe[0],
                            },
                        };
                    let started = std::time::Instant::now();
                    let g = Geometry::new(km, previous.as_deref());
                    let parts: Vec<Result<Partial>> = states
                        .par_iter_mut()
                        .enumerate()
                        .map(|(c, st)| {
                            let rows = load(c)?;
                            let rows = rows.as_ref();
                            // Values are checked the first time a chunk is seen; later passes
                            // read the same chunk again, so only its shape is checked.
                            if let ChunkState::Fresh = st {
                                check_rows(rows, dim)?;
                                *st = ChunkState::Seen;
                            } else {
                                check_shape(rows, dim)?;
                            }
                            if use_bounds {
                                if let ChunkState::Seen = st {
                                    let bytes = rows.len() / dim * BOUND_BYTES;
                                    let fits = budget
                                        .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |b| {
                                            b.checked_sub(bytes)
                                        })
                                        .is_ok();
                                    *st = if fits {
                                        ChunkState::Bounded(Bounds::default())
                                    } else {
                                        ChunkState::Plain
                                    };
                                }
                            }
                            let (p, n) = match st {
                                ChunkState::Bounded(b) if use_bounds => {
                                    km.bounded_partial(rows, b, &g)
                                }
                                _ => (km.partial_packed(rows, &g.packed), rows.len() / dim),
                            };
                            full.fetch_add(n as u64, Ordering::Relaxed);
                            Ok(p)
                        })
                        .collect();
                    let secs = started.elapsed().as_secs_f64();
                    match pass_no {
                        0 => probe[0] = secs,
                        2 => probe[1] = secs,
                        _ => {}
                    }
                    if cfg.bounds == BoundsUse::Auto && pass_no == 2 {
                        tracing::debug!(
                            plain_s = probe[0],
                            bounded_s = probe[1],
                            "k-means: bounds {}",
                            if probe[1] < probe[0] {
                                "kept"
                            } else {
                                "dropped"
                            }
                        );
                    }
                    pass_no += 1;
                    if use_bounds {
                        previous = Some(km.centroids.clone());
                    }
                    let mut total = Partial::new(km.k(), dim);
                    for p in parts {
                        total.merge(&p?);
                    }
                    Ok(total)
                };
                let km = km.lloyd(&sample, tol, cfg, &mut bounded)?;
                let full = full.into_inner();
                tracing::debug!(iterations = km.iterations, full_rows = full, "k-means");
                Ok((km, full))
            }
            Algorithm::MiniBatch { epochs } => {
                let mut seen = vec![0u64; km.k()];
                for e in 0..epochs.max(1) {
                    rng.shuffle(&mut order);
                    for &c in &order {
                        let rows = load(c)?;
                        check_rows(rows.as_ref(), dim)?;
                        let p = km.partial(rows.as_ref());
                        for (j, &n) in p.counts.iter().enumerate() {
                            if n == 0 {
                                continue;
                            }
                            seen[j] += n;
                            let eta = n as f64 / seen[j] as f64;
                            for t in 0..dim {
                                let mean = p.sums[j * dim + t] / n as f64;
                                let c = &mut km.centroids[j * dim + t];
                                *c = (*c as f64 + eta * (mean - *c as f64)) as f32;
                            }
                        }
                    }
                    km.iterations = e + 1;
                }
                // The reported inertia and counts belong to the final centroids.
                let p = pass(&km)?;
                km.inertia = p.inertia;
                km.counts = p.counts;
                Ok((km, full.into_inner()))
            }
        }
    }

    /// The k-means++ initialisation on `sample` and the convergence tolerance (scikit-learn's:
    /// `tol` times the mean per-feature variance of the sample). `rng` continues from the
    /// sampling.
    pub fn seed(sample: &[f32], dim: usize, cfg: &KMeansConfig, rng: &mut Rng) -> (KMeans, f64) {
        let centroids = kmeanspp(sample, dim, cfg.k, rng);
        let km = KMeans {
            dim,
            centroids,
            inertia: 0.0,
            iterations: 0,
            counts: Vec::new(),
        };
        (km, tolerance(sample, dim, cfg.tol))
    }

    /// Lloyd iterations from the current centroids: `pass` returns the merged partial of every
    /// row for the given centroids (any scheduler: rayon, actors, cluster workers; merged in
    /// chunk order). Stops when the squared centroid shift is at most `tol` or after
    /// `max_iter`; a last pass gives the inertia and counts of the final centroids.
    pub fn lloyd(
        self,
        sample: &[f32],
        tol: f64,
        cfg: &KMeansConfig,
        pass: &mut dyn FnMut(&KMeans) -> Result<Partial>,
    ) -> Result<KMeans> {
        let mut km = self.lloyd_iterations(sample, tol, cfg, pass)?;
        let p = pass(&km)?;
        km.inertia = p.inertia;
        km.counts = p.counts;
        Ok(km)
    }

    /// [`Self::lloyd`] without the last pass (the caller computes the final statistics, e.g.
    /// together with view partials).
    pub fn lloyd_iterations(
        mut self,
        sample: &[f32],
        tol: f64,
        cfg: &KMeansConfig,
        pass: &mut dyn FnMut(&KMeans) -> Result<Partial>,
    ) -> Result<KMeans> {
        for it in 0..cfg.max_iter.max(1) {
            let p = pass(&self)?;
            let shift = self.update(&p, sample);
            self.iterations = it + 1;
            if shift <= tol {
                break;
            }
        }
        Ok(self)
    }

    /// Moves every centroid to the mean of its rows; an empty cluster takes the sample row
    /// farthest from its centroid. Returns the summed squared centroid shift.
    pub fn update(&mut self, p: &Partial, sample: &[f32]) -> f64 {
        let d = self.dim;
        let mut shift = 0.0f64;
        for c in 0..self.k() {
            if p.counts[c] == 0 {
                continue;
            }
            for t in 0..d {
                let v = (p.sums[c * d + t] / p.counts[c] as f64) as f32;
                let o = self.centroids[c * d + t];
                shift += ((v - o) as f64).powi(2);
                self.centroids[c * d + t] = v;
            }
        }
        for c in 0..self.k() {
            if p.counts[c] == 0 {
                let far = sample
                    .chunks_exact(d)
                    .enumerate()
                    .map(|(i, x)| (i, self.nearest(x).1))
                    .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)));
                if let Some((i, dist)) = far {
                    if dist > 0.0 {
                        self.centroids[c * d..(c + 1) * d]
                            .copy_from_slice(&sample[i * d..(i + 1) * d]);
                        shift += dist as f64;
                    }
                }
            }
        }
        shift
    }
}

/// The convergence tolerance on the summed squared centroid shift: `tol` times the mean
/// per-feature variance of `sample` (scikit-learn's rule, which takes the variance of all rows).
fn tolerance(sample: &[f32], dim: usize, tol: f64) -> f64 {
    let ns = sample.len() / dim;
    let mut var = 0.0f64;
    for j in 0..dim {
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for r in 0..ns {
            let v = sample[r * dim + j] as f64;
            s += v;
            s2 += v * v;
        }
        let m = s / ns.max(1) as f64;
        var += (s2 / ns.max(1) as f64 - m * m).max(0.0);
    }
    tol * var / dim as f64
}

fn check_k(cfg: &KMeansConfig) -> Result<()> {
    if cfg.k == 0 || cfg.k > u16::MAX as usize {
        return Err(ViewpointError::Param(format!(
            "k = {} must be 1..=65535",
            cfg.k
        )));
    }
    Ok(())
}

/// Whether `init` holds `k x dim` finite centroid values.
fn check_init(init: &[f32], k: usize, dim: usize) -> Result<()> {
    if dim == 0 || init.len() != k * dim {
        return Err(ViewpointError::Param(format!(
            "initial centroids: {} values, expected k x dim = {k} x {dim} = {}",
            init.len(),
            k * dim
        )));
    }
    if let Some(i) = init.iter().position(|v| !v.is_finite()) {
        return Err(ViewpointError::Param(format!(
            "initial centroid {} has a value that is not finite ({})",
            i / dim,
            init[i]
        )));
    }
    Ok(())
}

/// The seeded order of the chunks and the initialisation sample: rows drawn from the first
/// [`SAMPLE_CHUNKS`] chunks of that order (checked for shape and finiteness).
fn draw_sample<F, R>(
    chunks: usize,
    dim: usize,
    load: &F,
    cfg: &KMeansConfig,
    rng: &mut Rng,
) -> Result<(Vec<usize>, Vec<f32>)>
where
    F: Fn(usize) -> Result<R> + Sync,
    R: AsRef<[f32]>,
{
    if chunks == 0 {
        return Err(ViewpointError::Input(
            "no feature rows to cluster (every brick is empty)".into(),
        ));
    }
    let order = sample_order(chunks, rng);
    let want = sample_want(chunks, cfg);
    let mut sample = Vec::new();
    for &c in order.iter().take(SAMPLE_CHUNKS) {
        let rows = load(c)?;
        let rows = rows.as_ref();
        check_rows(rows, dim)?;
        for r in draw_rows(rng, want, rows.len() / dim) {
            sample.extend_from_slice(&rows[r * dim..(r + 1) * dim]);
        }
    }
    Ok((order, sample))
}

/// Chunks the initialisation sample is drawn from.
pub const SAMPLE_CHUNKS: usize = 64;

/// The seeded order in which chunks are visited (the first [`SAMPLE_CHUNKS`] give the sample).
pub fn sample_order(chunks: usize, rng: &mut Rng) -> Vec<usize> {
    let mut order: Vec<usize> = (0..chunks).collect();
    rng.shuffle(&mut order);
    order
}

/// Rows drawn from each sampled chunk.
pub fn sample_want(chunks: usize, cfg: &KMeansConfig) -> usize {
    (cfg.init_sample / chunks.min(SAMPLE_CHUNKS)).max(1)
}

/// The rows drawn (with replacement) from a chunk of `n` rows.
pub fn draw_rows(rng: &mut Rng, want: usize, n: usize) -> Vec<usize> {
    (0..want.min(n)).map(|_| rng.below(n)).collect()
}

/// Greedy k-means++ on `sample` (as scikit-learn: each step draws `2 + ln k` candidates by D^2
/// sampling and keeps the one that lowers the potential most). Where the sample has fewer than
/// `k` distinct rows, the extra centroids repeat existing ones (they stay empty and the caller
/// sees zero counts).
pub fn kmeanspp(sample: &[f32], dim: usize, k: usize, rng: &mut Rng) -> Vec<f32> {
    let n = sample.len() / dim;
    let mut cent = Vec::with_capacity(k * dim);
    if n == 0 {
        return vec![0.0; k * dim];
    }
    let trials = 2 + (k as f64).ln().floor() as usize;
    let first = rng.below(n);
    cent.extend_from_slice(&sample[first * dim..(first + 1) * dim]);
    let dist =
        |x: &[f32], c: &[f32]| -> f32 { x.iter().zip(c).map(|(a, b)| (a - b) * (a - b)).sum() };
    let mut d2: Vec<f32> = sample
        .chunks_exact(dim)
        .map(|x| dist(x, &cent[..dim]))
        .collect();
    for _ in 1..k {
        let total: f64 = d2.iter().map(|&v| v as f64).sum();
        let draw = |rng: &mut Rng| -> usize {
            if total <= 0.0 {
                return rng.below(n);
            }
            let mut t = rng.f32() as f64 * total;
            for (i, &v) in d2.iter().enumerate() {
                t -= v as f64;
                if t < 0.0 {
                    return i;
                }
            }
            n - 1
        };
        let cands: Vec<usize> = (0..trials).map(|_| draw(rng)).collect();
        // The candidate whose addition leaves the smallest potential.
        let best = cands
            .par_iter()
            .map(|&c| {
                let cr = &sample[c * dim..(c + 1) * dim];
                let pot: f64 = d2
                    .iter()
                    .zip(sample.chunks_exact(dim))
                    .map(|(&v, x)| v.min(dist(x, cr)) as f64)
                    .sum();
                (c, pot)
            })
            .reduce(
                || (usize::MAX, f64::INFINITY),
                |a, b| {
                    if b.1 < a.1 || (b.1 == a.1 && b.0 < a.0) {
                        b
                    } else {
                        a
                    }
                },
            )
            .0;
        let c = sample[best * dim..(best + 1) * dim].to_vec();
        cent.extend_from_slice(&c);
        d2.par_iter_mut()
            .zip(sample.par_chunks_exact(dim))
            .for_each(|(v, x)| *v = v.min(dist(x, &c)));
    }
    cent
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blobs(n: usize, seed: u64) -> Vec<f32> {
        let mut r = Rng::new(seed);
        let centres = [[0.0f32, 0.0], [10.0, 0.0], [0.0, 10.0]];
        (0..n)
            .flat_map(|i| {
                let c = centres[i % 3];
                [c[0] + r.uniform(-1.0, 1.0), c[1] + r.uniform(-1.0, 1.0)]
            })
            .collect()
    }

    #[test]
    fn finds_separated_blobs_deterministically_for_any_thread_count() {
        let rows = blobs(3000, 1);
        let chunks: Vec<Vec<f32>> = rows.chunks(2 * 250).map(|c| c.to_vec()).collect();
        let cfg = KMeansConfig {
            k: 3,
            ..Default::default()
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| KMeans::fit(chunks.len(), 2, |i| Ok(chunks[i].clone()), &cfg).unwrap())
        };
        let a = run(1);
        assert_eq!(a, run(2));
        let mut counts = a.counts.clone();
        counts.sort();
        assert_eq!(counts, vec![1000, 1000, 1000]);
        // Each row is within its blob: mean squared distance about 2/3 (uniform in [-1,1]^2).
        assert!(a.inertia / 3000.0 < 0.8, "{}", a.inertia);
        let mb = KMeans::fit(
            chunks.len(),
            2,
            |i| Ok(chunks[i].clone()),
            &KMeansConfig {
                algorithm: Algorithm::MiniBatch { epochs: 3 },
                ..cfg
            },
        )
        .unwrap();
        assert!(
            mb.inertia < a.inertia * 1.05,
            "{} vs {}",
            mb.inertia,
            a.inertia
        );
    }

    #[test]
    fn bounds_skip_most_distances_and_equal_plain_lloyd_bit_for_bit() {
        // 64-D rows around 20 overlapping centres, so rows keep changing cluster for many
        // iterations, in uneven chunks.
        let (n, d) = (6000, 64);
        let mut r = Rng::new(5);
        let centres: Vec<f32> = (0..20 * d).map(|_| r.uniform(-1.0, 1.0)).collect();
        let mut rows = Vec::with_capacity(n * d);
        for i in 0..n {
            let c = (i * 7) % 20;
            for t in 0..d {
                rows.push(centres[c * d + t] * 3.0 + r.uniform(-2.0, 2.0));
            }
        }
        let mut chunks: Vec<Vec<f32>> = Vec::new();
        let mut at = 0;
        for size in [1, 700, 1500, 37, 2000, 1762] {
            chunks.push(rows[at * d..(at + size) * d].to_vec());
            at += size;
        }
        let cfg = KMeansConfig {
            k: 16,
            max_iter: 60,
            tol: 0.0,
            ..Default::default()
        };
        let run = |bounds_mib: usize, threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    KMeans::fit_counting(
                        chunks.len(),
                        d,
                        |i| Ok(&chunks[i][..]),
                        &KMeansConfig {
                            bounds_mib,
                            bounds: BoundsUse::Always,
                            ..cfg
                        },
                        None,
                    )
                    .unwrap()
                })
        };
        let (plain, all) = run(0, 2);
        let passes = plain.iterations as u64 + 1;
        assert!(passes > 8, "{passes} passes");
        assert_eq!(all, passes * n as u64, "no bounds: every row every pass");
        let (bounded, some) = run(1024, 2);
        assert_eq!(bounded, plain, "bounds change nothing");
        assert!(some < all / 4, "bounds skip most rows: {some} of {all}");
        assert_eq!(run(1024, 1).0, plain);
        // Auto (bounds where they measure faster, either way) changes nothing either.
        let auto = KMeans::fit(
            chunks.len(),
            d,
            |i| Ok(&chunks[i][..]),
            &KMeansConfig {
                bounds: BoundsUse::Auto,
                ..cfg
            },
        )
        .unwrap();
        assert_eq!(auto, plain);
        // Each chunk's final statistics are its plain partial.
        let mut sum = Partial::new(16, d);
        for c in &chunks {
            sum.merge(&plain.partial(c));
        }
        assert_eq!(sum.counts, plain.counts);
        assert_eq!(sum.inertia, plain.inertia);
    }

    /// Every path the CPU has gives the bits of the scalar path in Hamerly's passes and the
    /// tally: labels, bounds, statistics and the rows that needed the kernel.
    #[test]
    fn bounded_passes_and_tally_give_the_same_bits_on_every_path() {
        let (n, d, k) = (1500, 11, 70);
        let mut r = Rng::new(9);
        let centres: Vec<f32> = (0..20 * d).map(|_| r.uniform(-1.0, 1.0)).collect();
        let rows: Vec<f32> = (0..n * d)
            .map(|i| centres[((i / d) * 7) % 20 * d + i % d] * 3.0 + r.uniform(-2.0, 2.0))
            .collect();
        let start = KMeans {
            dim: d,
            centroids: rows[..k * d].to_vec(),
            inertia: 0.0,
            iterations: 0,
            counts: vec![0; k],
        };
        let run = |path: Path| {
            let (mut km, mut state, mut prev) = (start.clone(), Bounds::default(), None);
            let mut out = Vec::new();
            for _ in 0..5 {
                let g = Geometry::new(&km, prev.as_deref());
                let (p, pending) = km.bounded_on(path, &rows, &mut state, &g);
                let mut t = Partial::new(km.k(), d);
                km.tally_on(path, &mut t, &rows, &state.assign, &[]);
                assert_eq!(t, p, "{path:?}: the bounded pass is the plain tally");
                let f = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                out.push((
                    p,
                    pending,
                    state.assign.clone(),
                    f(&state.upper),
                    f(&state.lower),
                ));
                prev = Some(km.centroids.clone());
                km.update(&out.last().unwrap().0, &rows);
            }
            out
        };
        let want = run(Path::Scalar);
        assert!(want.last().unwrap().1 < n, "the bounds skip rows");
        for path in [Path::Avx512, Path::Avx2Fma] {
            if path.available() {
                assert!(run(path) == want, "{path:?}");
            }
        }
    }

    #[test]
    fn fit_from_starts_at_the_given_centroids() {
        let rows = blobs(3000, 2);
        let chunks: Vec<Vec<f32>> = rows.chunks(2 * 300).map(|c| c.to_vec()).collect();
        let load = |i: usize| Ok(chunks[i].as_slice());
        let cfg = KMeansConfig {
            k: 3,
            max_iter: 30,
            tol: 0.0,
            ..Default::default()
        };
        // Two orders of the blob centres: each fitted centroid stays at its own start's blob,
        // so the two fits list the same centroids in different orders (k-means++, which
        // ignoring `init` would use, can match at most one of them).
        let centres = [[0.0f32, 0.0], [10.0, 0.0], [0.0, 10.0]];
        for perm in [[0, 1, 2], [2, 0, 1]] {
            let init: Vec<f32> = perm.iter().flat_map(|&j| centres[j]).collect();
            for bounds_mib in [0, 1024] {
                let km = KMeans::fit_from(
                    chunks.len(),
                    2,
                    load,
                    &KMeansConfig {
                        bounds_mib,
                        bounds: BoundsUse::Always,
                        ..cfg
                    },
                    &init,
                )
                .unwrap();
                for (j, c) in km.centroids.chunks_exact(2).enumerate() {
                    let s = &init[j * 2..j * 2 + 2];
                    let d = (c[0] - s[0]).hypot(c[1] - s[1]);
                    assert!(d < 0.2, "centroid {j} {c:?} left its start {s:?}");
                }
                assert_eq!(km.counts, vec![1000, 1000, 1000]);
            }
        }
        // One iteration from a start that is not a fixed point moves every centroid to the
        // mean of the rows nearest to it: all rows go to the first of two far-apart starts.
        let km = KMeans::fit_from(
            chunks.len(),
            2,
            load,
            &KMeansConfig {
                k: 2,
                max_iter: 1,
                ..cfg
            },
            &[3.0, 3.0, 1000.0, 1000.0],
        )
        .unwrap();
        let mean: Vec<f64> = (0..2)
            .map(|t| {
                rows.iter()
                    .skip(t)
                    .step_by(2)
                    .map(|&v| v as f64)
                    .sum::<f64>()
                    / 3000.0
            })
            .collect();
        assert_eq!(km.iterations, 1);
        assert!((km.centroids[0] as f64 - mean[0]).abs() < 1e-3, "{km:?}");
        assert!((km.centroids[1] as f64 - mean[1]).abs() < 1e-3, "{km:?}");
        // The empty second cluster was re-seeded at a sample row.
        assert!(km.centroids[2] < 20.0, "{km:?}");
        // From k-means++'s own start, `fit_from` is `fit` bit for bit, bounds or not.
        for bounds_mib in [0, 1024] {
            let c = KMeansConfig {
                bounds_mib,
                bounds: BoundsUse::Always,
                ..cfg
            };
            let init = KMeans::init_centroids(chunks.len(), 2, load, &c).unwrap();
            assert_eq!(
                KMeans::fit_from(chunks.len(), 2, load, &c, &init).unwrap(),
                KMeans::fit(chunks.len(), 2, load, &c).unwrap()
            );
        }
        // A start of the wrong shape or with a value that is not finite is refused.
        for (bad, want) in [
            (vec![0.0f32; 5], "expected k x dim = 3 x 2 = 6"),
            (vec![0.0f32; 8], "expected k x dim = 3 x 2 = 6"),
            (vec![], "0 values"),
            (vec![0.0, 0.0, f32::NAN, 1.0, 2.0, 2.0], "centroid 1"),
            (vec![0.0, 0.0, 1.0, 1.0, 2.0, f32::INFINITY], "not finite"),
        ] {
            let e = KMeans::fit_from(chunks.len(), 2, load, &cfg, &bad)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }

    #[test]
    fn degenerate_inputs_give_clear_results_or_errors() {
        // k above the number of distinct rows: the extra clusters stay empty.
        let rows = vec![1.0f32; 200];
        let km = KMeans::fit(
            1,
            2,
            |_| Ok(rows.clone()),
            &KMeansConfig {
                k: 5,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(km.counts.iter().sum::<u64>(), 100);
        assert_eq!(km.inertia, 0.0);
        let e = KMeans::fit(0, 2, |_| Ok(vec![]), &KMeansConfig::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("no feature rows"), "{e}");
        let e = KMeans::fit(1, 2, |_| Ok(vec![f32::NAN; 4]), &KMeansConfig::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("not finite"), "{e}");
        let e = KMeans::fit(
            1,
            2,
            |_| Ok(vec![0.0; 4]),
            &KMeansConfig {
                k: 0,
                ..Default::default()
            },
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("k = 0"), "{e}");
    }
}
