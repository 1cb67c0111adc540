//! K-means on per-voxel feature rows that stream brick by brick: seeded k-means++
//! initialisation on a sample, then either Lloyd iterations whose per-brick partial sums merge
//! in brick order (deterministic for any thread count), or mini-batch updates with one brick per
//! batch.

use crate::{Result, ViewpointError};
use neuvolex_bricks::rng::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Rows per matrix-product block.
const BLOCK: usize = 2048;

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

fn check_rows(rows: &[f32], dim: usize) -> Result<()> {
    if dim == 0 || !rows.len().is_multiple_of(dim) {
        return Err(ViewpointError::Input(format!(
            "{} feature values do not make rows of {dim}",
            rows.len()
        )));
    }
    if let Some(i) = rows.iter().position(|v| !v.is_finite()) {
        return Err(ViewpointError::Input(format!(
            "feature value {} at row {} is not finite",
            rows[i],
            i / dim
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

    /// Nearest centroid and squared distance of every row, through one matrix product per
    /// block (`|x|^2 - 2 x.c + |c|^2`, as scikit-learn computes it).
    fn nearest_rows(&self, rows: &[f32]) -> Vec<(usize, f32)> {
        let (k, d) = (self.k(), self.dim);
        let cn: Vec<f32> = self
            .centroids
            .chunks_exact(d)
            .map(|c| c.iter().map(|v| v * v).sum())
            .collect();
        let mut out = Vec::with_capacity(rows.len() / d);
        let mut dots = vec![0.0f32; BLOCK * k];
        for blk in rows.chunks(BLOCK * d) {
            let n = blk.len() / d;
            // SAFETY: `blk` holds n x d values, the centroids k x d, `dots` at least n x k.
            unsafe {
                matrixmultiply::sgemm(
                    n,
                    d,
                    k,
                    1.0,
                    blk.as_ptr(),
                    d as isize,
                    1,
                    self.centroids.as_ptr(),
                    1,
                    d as isize,
                    0.0,
                    dots.as_mut_ptr(),
                    k as isize,
                    1,
                );
            }
            for (x, row) in blk.chunks_exact(d).zip(dots.chunks_exact(k)) {
                let mut best = (0, f32::INFINITY);
                for (c, (&dot, &n2)) in row.iter().zip(&cn).enumerate() {
                    let v = n2 - 2.0 * dot;
                    if v < best.1 {
                        best = (c, v);
                    }
                }
                let xn: f32 = x.iter().map(|v| v * v).sum();
                out.push((best.0, (best.1 + xn).max(0.0)));
            }
        }
        out
    }

    /// The nearest cluster of every row.
    pub fn assign(&self, rows: &[f32]) -> Vec<u16> {
        rows.par_chunks(self.dim * BLOCK)
            .flat_map_iter(|ch| self.nearest_rows(ch).into_iter().map(|(c, _)| c as u16))
            .collect()
    }

    /// The assignment statistics of one brick's rows (the pure per-brick step).
    pub fn partial(&self, rows: &[f32]) -> Partial {
        let (k, d) = (self.k(), self.dim);
        let mut p = Partial::new(k, d);
        for (x, (c, dist)) in rows.chunks_exact(d).zip(self.nearest_rows(rows)) {
            p.counts[c] += 1;
            p.inertia += dist as f64;
            for (s, &v) in p.sums[c * d..(c + 1) * d].iter_mut().zip(x) {
                *s += v as f64;
            }
        }
        p
    }

    /// Fits on `chunks` chunks of rows (`load(i)` gives chunk `i`, `dim` values per row); chunks
    /// are loaded again for every pass, so only one chunk per thread is in memory.
    pub fn fit<F, R>(chunks: usize, dim: usize, load: F, cfg: &KMeansConfig) -> Result<KMeans>
    where
        F: Fn(usize) -> Result<R> + Sync,
        R: AsRef<[f32]>,
    {
        if cfg.k == 0 || cfg.k > u16::MAX as usize {
            return Err(ViewpointError::Param(format!(
                "k = {} must be 1..=65535",
                cfg.k
            )));
        }
        if chunks == 0 {
            return Err(ViewpointError::Input(
                "no feature rows to cluster (every brick is empty)".into(),
            ));
        }
        let mut rng = Rng::new(cfg.seed);
        // The initialisation sample: rows of a seeded subset of chunks.
        let mut order = sample_order(chunks, &mut rng);
        let want = sample_want(chunks, cfg);
        let mut sample = Vec::new();
        for &c in order.iter().take(SAMPLE_CHUNKS) {
            let rows = load(c)?;
            let rows = rows.as_ref();
            check_rows(rows, dim)?;
            for r in draw_rows(&mut rng, want, rows.len() / dim) {
                sample.extend_from_slice(&rows[r * dim..(r + 1) * dim]);
            }
        }
        let (mut km, tol) = KMeans::seed(&sample, dim, cfg, &mut rng);
        let pass = |km: &KMeans| -> Result<Partial> {
            let parts: Vec<Result<Partial>> = (0..chunks)
                .into_par_iter()
                .map(|c| {
                    let rows = load(c)?;
                    check_rows(rows.as_ref(), dim)?;
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
            Algorithm::Lloyd => km.lloyd(&sample, tol, cfg, &mut |k| pass(k)),
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
                Ok(km)
            }
        }
    }

    /// The k-means++ initialisation on `sample` and the convergence tolerance (scikit-learn's:
    /// `tol` times the mean per-feature variance of the sample). `rng` continues from the
    /// sampling.
    pub fn seed(sample: &[f32], dim: usize, cfg: &KMeansConfig, rng: &mut Rng) -> (KMeans, f64) {
        let centroids = kmeanspp(sample, dim, cfg.k, rng);
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
        let km = KMeans {
            dim,
            centroids,
            inertia: 0.0,
            iterations: 0,
            counts: Vec::new(),
        };
        (km, cfg.tol * var / dim as f64)
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
