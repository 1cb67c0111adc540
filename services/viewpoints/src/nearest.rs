//! The assignment kernel of k-means: for each row `x`, the centroid with the smallest
//! `|c|^2 - 2 x.c` (`|x - c|^2` less the row's own `|x|^2`, as scikit-learn computes it) and
//! the smallest value over the other centroids, with the distance product and the argmin fused
//! so the products never leave registers.
//!
//! Every value is defined by one scalar rule, whatever the CPU: it starts at `|c|^2` and adds
//! `x[t] * (-2 c[t])` for `t` in order, each step one fused multiply-add (one rounding), then
//! `+ 0.0` (a negative zero, from a product that underflows, becomes `+0`, so values that
//! compare equal have equal bits and a minimum's bits never depend on the order it is taken
//! in). The AVX-512 kernel computes 4 rows x 64 centroids at a time, the AVX2+FMA kernel 4 rows
//! x 16 centroids (each with a narrower last tile where the last centroids fit half of it),
//! with the same per-lane operations, so both give the bits of the scalar rule
//! ([`Packed::nearest_reference`]; a test compares every [`Path`] the CPU has), and a result
//! never depends on the CPU, the block size or the thread count. Ties go to the lowest index.

/// The kernels, in the order [`Path::detect`] prefers them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
pub(crate) enum Path {
    /// AVX-512F: 16 lanes, 4 rows x 64 centroids a tile.
    Avx512,
    /// AVX2 and FMA: 8 lanes, 4 rows x 16 centroids a tile.
    Avx2Fma,
    /// The scalar rule ([`Packed::nearest_reference`]).
    Scalar,
}

impl Path {
    /// The fastest path this CPU has (the feature tests are cached by the standard library).
    #[inline]
    pub(crate) fn detect() -> Path {
        if Path::Avx512.available() {
            Path::Avx512
        } else if Path::Avx2Fma.available() {
            Path::Avx2Fma
        } else {
            Path::Scalar
        }
    }

    /// Whether this CPU runs the path.
    #[inline]
    pub(crate) fn available(self) -> bool {
        match self {
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => std::is_x86_feature_detected!("avx512f"),
            #[cfg(target_arch = "x86_64")]
            Path::Avx2Fma => {
                std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
            }
            Path::Scalar => true,
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }
}

/// Centroids laid out for the kernel: `-2 c` transposed (`d x kp`, `kp` is `k` rounded up to a
/// multiple of 16 lanes, padding 0) and the squared norms (padding `+inf`, so a padded column
/// never wins).
#[derive(Debug, Clone)]
pub(crate) struct Packed {
    k: usize,
    d: usize,
    kp: usize,
    /// `m2c[t * kp + j] = -2 c_j[t]`.
    m2c: Vec<f32>,
    /// `n2[j] = |c_j|^2`, `+inf` past `k`.
    n2: Vec<f32>,
}

/// Lanes of an AVX-512 register.
const LANES: usize = 16;

/// Columns (centroids) of one register tile: 4 registers.
const PANEL: usize = 4 * LANES;

impl Packed {
    /// Packs `k x d` row-major `centroids` with their squared norms `n2` (as the caller's
    /// bounds use them).
    pub(crate) fn new(centroids: &[f32], d: usize, n2: &[f32]) -> Packed {
        let k = centroids.len() / d;
        assert!(d > 0 && k * d == centroids.len() && n2.len() == k);
        let kp = k.div_ceil(LANES) * LANES;
        let mut m2c = vec![0.0f32; d * kp];
        for (j, c) in centroids.chunks_exact(d).enumerate() {
            for (t, &v) in c.iter().enumerate() {
                m2c[t * kp + j] = -2.0 * v;
            }
        }
        let mut n2p = vec![f32::INFINITY; kp];
        n2p[..k].copy_from_slice(n2);
        Packed {
            k,
            d,
            kp,
            m2c,
            n2: n2p,
        }
    }

    /// For each row of `rows` (`d` values each): `labels[i]`, the index of the smallest
    /// `|c|^2 - 2 x.c` (the lowest on ties), and where `second` is given, `second[i]`, the
    /// smallest value over the other centroids (`+inf` for one centroid).
    pub(crate) fn nearest(&self, rows: &[f32], labels: &mut [u16], second: Option<&mut [f32]>) {
        self.nearest_on(Path::detect(), rows, labels, None, second);
    }

    /// [`Self::nearest`] by the given path (which must be [`Path::available`]), also giving
    /// the smallest value itself where `best` is given.
    pub(crate) fn nearest_on(
        &self,
        path: Path,
        rows: &[f32],
        labels: &mut [u16],
        best: Option<&mut [f32]>,
        second: Option<&mut [f32]>,
    ) {
        let n = rows.len() / self.d;
        assert!(rows.len() == n * self.d && labels.len() >= n);
        for s in [&best, &second].into_iter().flatten() {
            assert!(s.len() >= n);
        }
        assert!(path.available(), "{path:?} is not available on this CPU");
        let best = best.unwrap_or(&mut []);
        #[cfg(target_arch = "x86_64")]
        match (path, second) {
            // SAFETY: AVX-512F is available (asserted above).
            (Path::Avx512, Some(s)) => unsafe {
                avx512::nearest::<true>(self, rows, labels, best, s)
            },
            // SAFETY: AVX-512F is available (asserted above).
            (Path::Avx512, None) => unsafe {
                avx512::nearest::<false>(self, rows, labels, best, &mut [])
            },
            // SAFETY: AVX2 and FMA are available (asserted above).
            (Path::Avx2Fma, Some(s)) => unsafe {
                avx2::nearest::<true>(self, rows, labels, best, s)
            },
            // SAFETY: AVX2 and FMA are available (asserted above).
            (Path::Avx2Fma, None) => unsafe {
                avx2::nearest::<false>(self, rows, labels, best, &mut [])
            },
            (Path::Scalar, second) => self.nearest_reference(rows, labels, best, second),
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.nearest_reference(rows, labels, best, second);
    }

    /// [`Self::nearest`] by the scalar rule, one value at a time (the definition the vector
    /// kernels reproduce bit for bit, and the kernel of CPUs without AVX2+FMA); `best[i]`, where
    /// `i` is inside it, is the smallest value.
    fn nearest_reference(
        &self,
        rows: &[f32],
        labels: &mut [u16],
        best_out: &mut [f32],
        mut second: Option<&mut [f32]>,
    ) {
        let (d, kp) = (self.d, self.kp);
        let mut acc = vec![0.0f32; kp];
        for (i, x) in rows.chunks_exact(d).enumerate() {
            acc.copy_from_slice(&self.n2);
            for (t, &xt) in x.iter().enumerate() {
                for (a, &c) in acc.iter_mut().zip(&self.m2c[t * kp..(t + 1) * kp]) {
                    *a = xt.mul_add(c, *a);
                }
            }
            let mut best = (0, f32::INFINITY);
            let mut next = f32::INFINITY;
            for (j, &v) in acc[..self.k].iter().enumerate() {
                let v = v + 0.0;
                if v < best.1 {
                    next = best.1;
                    best = (j, v);
                } else if v < next {
                    next = v;
                }
            }
            labels[i] = best.0 as u16;
            if let Some(b) = best_out.get_mut(i) {
                *b = best.1;
            }
            if let Some(s) = second.as_deref_mut() {
                s[i] = next;
            }
        }
    }
}

/// Widens a group's results to 4 entries.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn pad<const R: usize>(v: [(u32, f32, f32); R]) -> [(u32, f32, f32); 4] {
    let mut o = [(0, 0.0, 0.0); 4];
    o[..R].copy_from_slice(&v);
    o
}

/// Writes a group's `(label, smallest, second)` results for rows from `i`: `best` where
/// inside it, `second` with `SECOND`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn store<const SECOND: bool>(
    out: &[(u32, f32, f32)],
    i: usize,
    labels: &mut [u16],
    best: &mut [f32],
    second: &mut [f32],
) {
    for (q, &(l, b, s)) in out.iter().enumerate() {
        labels[i + q] = l as u16;
        if let Some(o) = best.get_mut(i + q) {
            *o = b;
        }
        if SECOND {
            second[i + q] = s;
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{pad, store, Packed, LANES, PANEL};
    use std::arch::x86_64::*;

    /// [`Packed::nearest_on`] with AVX-512: rows in groups of 4, centroids in panels of up to
    /// 64; `best[i]` is written where `i` is inside it, `second[i]` with `SECOND`.
    #[target_feature(enable = "avx512f")]
    pub(super) fn nearest<const SECOND: bool>(
        p: &Packed,
        rows: &[f32],
        labels: &mut [u16],
        best: &mut [f32],
        second: &mut [f32],
    ) {
        let d = p.d;
        let n = rows.len() / d;
        let mut i = 0;
        while i < n {
            let r = (n - i).min(4);
            let x = &rows[i * d..(i + r) * d];
            let out = match r {
                4 => rows_group::<4, SECOND>(p, x),
                3 => pad(rows_group::<3, SECOND>(p, x)),
                2 => pad(rows_group::<2, SECOND>(p, x)),
                _ => pad(rows_group::<1, SECOND>(p, x)),
            };
            store::<SECOND>(&out[..r], i, labels, best, second);
            i += r;
        }
    }

    /// The label, smallest and second-smallest value of `R` rows (`x`, `R x d`) over every
    /// panel; panels merge in order, an equal value keeping the earlier (lower) index.
    #[target_feature(enable = "avx512f")]
    fn rows_group<const R: usize, const SECOND: bool>(
        p: &Packed,
        x: &[f32],
    ) -> [(u32, f32, f32); R] {
        let mut best = [(0u32, f32::INFINITY, f32::INFINITY); R];
        let mut j0 = 0;
        // Up to 64 columns a tile; where the last columns fit half a register, that half is
        // an 8-lane AVX register (half the work on CPUs that split 512-bit operations). The
        // columns past `k` are padding (`+inf`), so a tile may stop anywhere past them.
        while j0 < p.k {
            let res = match p.k - j0 {
                1..=8 => panel::<R, 0, true, SECOND>(p, x, j0),
                9..=16 => panel::<R, 1, false, SECOND>(p, x, j0),
                17..=24 => panel::<R, 1, true, SECOND>(p, x, j0),
                25..=32 => panel::<R, 2, false, SECOND>(p, x, j0),
                33..=40 => panel::<R, 2, true, SECOND>(p, x, j0),
                41..=48 => panel::<R, 3, false, SECOND>(p, x, j0),
                49..=56 => panel::<R, 3, true, SECOND>(p, x, j0),
                _ => panel::<R, 4, false, SECOND>(p, x, j0),
            };
            for (b, (l, v, s)) in best.iter_mut().zip(res) {
                if v < b.1 {
                    *b = (j0 as u32 + l, v, b.1.min(s));
                } else {
                    b.2 = b.2.min(v);
                }
            }
            j0 += PANEL;
        }
        best
    }

    /// One register tile: `R` rows against the `16 NV` centroid columns from `j0`, and with
    /// `HALF` the next 8 in an AVX register (the same per-lane operations); per row the lowest
    /// column of the smallest value (relative to `j0`), that value, and (with `SECOND`) the
    /// smallest value over the tile's other columns.
    #[target_feature(enable = "avx512f")]
    fn panel<const R: usize, const NV: usize, const HALF: bool, const SECOND: bool>(
        p: &Packed,
        x: &[f32],
        j0: usize,
    ) -> [(u32, f32, f32); R] {
        let (d, kp) = (p.d, p.kp);
        let cols = NV * LANES + if HALF { LANES / 2 } else { 0 };
        assert!(
            x.len() == R * d && j0 + cols <= kp && p.m2c.len() == d * kp && NV + HALF as usize <= 4
        );
        let mut acc = [[_mm512_setzero_ps(); NV]; R];
        let mut half = [_mm256_setzero_ps(); R];
        for v in 0..NV {
            // SAFETY: j0 + 16 NV <= kp = n2.len() (asserted above).
            let n2 = unsafe { _mm512_loadu_ps(p.n2.as_ptr().add(j0 + v * LANES)) };
            for a in acc.iter_mut() {
                a[v] = n2;
            }
        }
        if HALF {
            // SAFETY: j0 + 16 NV + 8 <= kp = n2.len() (asserted above).
            let n2 = unsafe { _mm256_loadu_ps(p.n2.as_ptr().add(j0 + NV * LANES)) };
            half = [n2; R];
        }
        let m2c = p.m2c.as_ptr();
        for t in 0..d {
            let mut c = [_mm512_setzero_ps(); NV];
            for (v, cv) in c.iter_mut().enumerate() {
                // SAFETY: t < d and j0 + 16 NV <= kp, so the 16 values lie in m2c (d x kp).
                *cv = unsafe { _mm512_loadu_ps(m2c.add(t * kp + j0 + v * LANES)) };
            }
            let ch = if HALF {
                // SAFETY: t < d and j0 + 16 NV + 8 <= kp, so the 8 values lie in m2c.
                unsafe { _mm256_loadu_ps(m2c.add(t * kp + j0 + NV * LANES)) }
            } else {
                _mm256_setzero_ps()
            };
            for (r, a) in acc.iter_mut().enumerate() {
                // SAFETY: r < R and t < d, and x holds R x d values (asserted above).
                let xv = _mm512_set1_ps(unsafe { *x.get_unchecked(r * d + t) });
                for v in 0..NV {
                    a[v] = _mm512_fmadd_ps(xv, c[v], a[v]);
                }
                if HALF {
                    half[r] = _mm256_fmadd_ps(_mm512_castps512_ps256(xv), ch, half[r]);
                }
            }
        }
        // `+ 0.0`: -0 becomes +0 (the scalar rule). The half register is widened with `+inf`
        // lanes, which never win. The sums go to a new array by value: borrowing `acc` itself
        // keeps it in memory, a store after every product (2.2x slower at 64 features).
        let inf = _mm512_set1_ps(f32::INFINITY);
        let mut wide = [[inf; 4]; R];
        for (w, (a, h)) in wide.iter_mut().zip(acc.iter().zip(&half)) {
            for v in 0..NV {
                w[v] = _mm512_add_ps(a[v], _mm512_setzero_ps());
            }
            if HALF {
                let h = _mm512_castps256_ps512(_mm256_add_ps(*h, _mm256_setzero_ps()));
                w[NV] = _mm512_mask_mov_ps(inf, 0x00ff, h);
            }
        }
        let nw = NV + HALF as usize;
        let mut out = [(0u32, 0.0f32, f32::INFINITY); R];
        for (o, w) in out.iter_mut().zip(&wide) {
            let a = &w[..nw];
            let mut m = a[0];
            for &v in &a[1..] {
                m = _mm512_min_ps(m, v);
            }
            let best = _mm512_reduce_min_ps(m);
            let b = _mm512_set1_ps(best);
            let mut mask = 0u64;
            for (v, &av) in a.iter().enumerate() {
                mask |= (_mm512_cmpeq_ps_mask(av, b) as u64) << (v * LANES);
            }
            let l = mask.trailing_zeros();
            o.0 = l;
            o.1 = best;
            if SECOND {
                let mut s = _mm512_set1_ps(f32::INFINITY);
                for (v, &av) in a.iter().enumerate() {
                    let keep = if v == l as usize / LANES {
                        !(1u16 << (l as usize % LANES))
                    } else {
                        u16::MAX
                    };
                    s = _mm512_mask_min_ps(s, keep, s, av);
                }
                o.2 = _mm512_reduce_min_ps(s);
            }
        }
        out
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{pad, store, Packed};
    use std::arch::x86_64::*;

    /// Lanes of an AVX2 register.
    const LANES: usize = 8;

    /// Columns (centroids) of one register tile: 2 registers (4 rows x 2 registers of
    /// accumulators, the centroid values and the broadcast feature use 11 of the 16; 3
    /// registers a row measured slower at 64 features). `kp` is a multiple of 16, so every
    /// panel lies inside the packed columns.
    const PANEL: usize = 2 * LANES;

    /// [`Packed::nearest_on`] with AVX2 and FMA: rows in groups of 4, centroids in panels of up
    /// to 16; `best[i]` is written where `i` is inside it, `second[i]` with `SECOND`.
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn nearest<const SECOND: bool>(
        p: &Packed,
        rows: &[f32],
        labels: &mut [u16],
        best: &mut [f32],
        second: &mut [f32],
    ) {
        let d = p.d;
        let n = rows.len() / d;
        let mut i = 0;
        while i < n {
            let r = (n - i).min(4);
            let x = &rows[i * d..(i + r) * d];
            let out = match r {
                4 => rows_group::<4, SECOND>(p, x),
                3 => pad(rows_group::<3, SECOND>(p, x)),
                2 => pad(rows_group::<2, SECOND>(p, x)),
                _ => pad(rows_group::<1, SECOND>(p, x)),
            };
            store::<SECOND>(&out[..r], i, labels, best, second);
            i += r;
        }
    }

    /// The label, smallest and second-smallest value of `R` rows (`x`, `R x d`) over every
    /// panel; panels merge in order, an equal value keeping the earlier (lower) index.
    #[target_feature(enable = "avx2,fma")]
    fn rows_group<const R: usize, const SECOND: bool>(
        p: &Packed,
        x: &[f32],
    ) -> [(u32, f32, f32); R] {
        let mut best = [(0u32, f32::INFINITY, f32::INFINITY); R];
        let mut j0 = 0;
        // The columns past `k` are padding (`+inf`): a last panel of at most 8 columns takes
        // one register.
        while j0 < p.k {
            let res = if p.k - j0 <= LANES {
                panel::<R, 1, SECOND>(p, x, j0)
            } else {
                panel::<R, 2, SECOND>(p, x, j0)
            };
            for (b, (l, v, s)) in best.iter_mut().zip(res) {
                if v < b.1 {
                    *b = (j0 as u32 + l, v, b.1.min(s));
                } else {
                    b.2 = b.2.min(v);
                }
            }
            j0 += PANEL;
        }
        best
    }

    /// The smallest of the 8 lanes (the values have no NaN and no -0, so the order of the
    /// minimum does not show in its bits).
    #[target_feature(enable = "avx2,fma")]
    fn reduce_min(m: __m256) -> f32 {
        let m4 = _mm_min_ps(_mm256_castps256_ps128(m), _mm256_extractf128_ps::<1>(m));
        let m2 = _mm_min_ps(m4, _mm_movehl_ps(m4, m4));
        let m1 = _mm_min_ss(m2, _mm_shuffle_ps::<1>(m2, m2));
        _mm_cvtss_f32(m1)
    }

    /// One register tile: `R` rows against the `8 NV` centroid columns from `j0`; per row
    /// the lowest column of the smallest value (relative to `j0`), that value, and (with
    /// `SECOND`) the smallest value over the tile's other columns.
    #[target_feature(enable = "avx2,fma")]
    fn panel<const R: usize, const NV: usize, const SECOND: bool>(
        p: &Packed,
        x: &[f32],
        j0: usize,
    ) -> [(u32, f32, f32); R] {
        let (d, kp) = (p.d, p.kp);
        assert!(x.len() == R * d && j0 + NV * LANES <= kp && p.m2c.len() == d * kp);
        let mut acc = [[_mm256_setzero_ps(); NV]; R];
        for v in 0..NV {
            // SAFETY: j0 + 8 NV <= kp = n2.len() (asserted above).
            let n2 = unsafe { _mm256_loadu_ps(p.n2.as_ptr().add(j0 + v * LANES)) };
            for a in acc.iter_mut() {
                a[v] = n2;
            }
        }
        let m2c = p.m2c.as_ptr();
        for t in 0..d {
            let mut c = [_mm256_setzero_ps(); NV];
            for (v, cv) in c.iter_mut().enumerate() {
                // SAFETY: t < d and j0 + 8 NV <= kp, so the 8 values lie in m2c (d x kp).
                *cv = unsafe { _mm256_loadu_ps(m2c.add(t * kp + j0 + v * LANES)) };
            }
            for (r, a) in acc.iter_mut().enumerate() {
                // SAFETY: r < R and t < d, and x holds R x d values (asserted above).
                let xv = _mm256_set1_ps(unsafe { *x.get_unchecked(r * d + t) });
                for v in 0..NV {
                    a[v] = _mm256_fmadd_ps(xv, c[v], a[v]);
                }
            }
        }
        // `+ 0.0`: -0 becomes +0 (the scalar rule). The sums go to a new array by value:
        // borrowing `acc` itself keeps it in memory, a store after every product.
        let mut fin = [[_mm256_setzero_ps(); NV]; R];
        for r in 0..R {
            for v in 0..NV {
                fin[r][v] = _mm256_add_ps(acc[r][v], _mm256_setzero_ps());
            }
        }
        let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let inf = _mm256_set1_ps(f32::INFINITY);
        let mut out = [(0u32, 0.0f32, f32::INFINITY); R];
        for (o, a) in out.iter_mut().zip(&fin) {
            let mut m = a[0];
            for &v in &a[1..] {
                m = _mm256_min_ps(m, v);
            }
            let best = reduce_min(m);
            let b = _mm256_set1_ps(best);
            let mut mask = 0u32;
            for (v, &av) in a.iter().enumerate() {
                let eq = _mm256_cmp_ps::<_CMP_EQ_OQ>(av, b);
                mask |= (_mm256_movemask_ps(eq) as u32) << (v * LANES);
            }
            let l = mask.trailing_zeros();
            o.0 = l;
            o.1 = best;
            if SECOND {
                let at = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                    lane,
                    _mm256_set1_epi32((l as usize % LANES) as i32),
                ));
                let mut s = inf;
                for (v, &av) in a.iter().enumerate() {
                    let av = if v == l as usize / LANES {
                        _mm256_blendv_ps(av, inf, at)
                    } else {
                        av
                    };
                    s = _mm256_min_ps(s, av);
                }
                o.2 = reduce_min(s);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_bricks::rng::Rng;

    #[test]
    fn the_kernel_gives_the_bits_of_the_scalar_rule() {
        let mut r = Rng::new(3);
        for (n, d, k) in [
            (37, 64, 50),
            (9, 11, 50),
            (5, 3, 1),
            (64, 7, 16),
            (13, 5, 17),
            (11, 20, 130),
            (6, 2, 64),
        ] {
            let rows: Vec<f32> = (0..n * d).map(|_| r.uniform(-3.0, 3.0)).collect();
            let mut cent: Vec<f32> = (0..k * d).map(|_| r.uniform(-3.0, 3.0)).collect();
            // Exact ties: duplicated centroids, in two panels where k allows.
            if k > 1 {
                let c0 = cent[..d].to_vec();
                cent[(k - 1) * d..].copy_from_slice(&c0);
            }
            let n2: Vec<f32> = cent
                .chunks_exact(d)
                .map(|c| c.iter().map(|v| v * v).sum())
                .collect();
            let p = Packed::new(&cent, d, &n2);
            let (mut la, mut sa) = (vec![0u16; n], vec![0.0f32; n]);
            let (mut lb, mut sb) = (vec![0u16; n], vec![0.0f32; n]);
            p.nearest(&rows, &mut la, Some(&mut sa));
            p.nearest_on(Path::Scalar, &rows, &mut lb, None, Some(&mut sb));
            assert_eq!(la, lb, "n {n} d {d} k {k}");
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&sa), bits(&sb), "n {n} d {d} k {k}");
            let mut lc = vec![0u16; n];
            p.nearest(&rows, &mut lc, None);
            assert_eq!(lc, la);
            // The rule is the distance less |x|^2, to rounding: each label is a nearest
            // centroid by direct distances within a small tolerance.
            for (i, x) in rows.chunks_exact(d).enumerate() {
                let dist = |j: usize| -> f32 {
                    x.iter()
                        .zip(&cent[j * d..(j + 1) * d])
                        .map(|(a, b)| (a - b) * (a - b))
                        .sum()
                };
                let m = (0..k).map(dist).fold(f32::INFINITY, f32::min);
                assert!(dist(la[i] as usize) <= m + 1e-3 * (1.0 + m));
            }
            // The duplicated first centroid ties with the last: the lower index wins and the
            // second-smallest value equals the smallest.
            if k > 1 {
                assert!(la.iter().all(|&l| l as usize != k - 1));
            }
        }
    }

    /// Every path this CPU has gives the (label, smallest, second) bits of the scalar rule,
    /// with and without the second value.
    #[test]
    fn every_path_gives_the_same_bits() {
        let paths: Vec<Path> = [Path::Avx512, Path::Avx2Fma, Path::Scalar]
            .into_iter()
            .filter(|p| p.available())
            .collect();
        eprintln!("paths: {paths:?}");
        let mut r = Rng::new(11);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut cases = 0;
        for d in [1, 2, 11, 17, 64] {
            // Every width of the AVX-512 kernel's last tile (whole registers and a half).
            for k in [1, 2, 5, 8, 12, 17, 24, 30, 40, 45, 50, 64, 65, 100, 130] {
                for grid in [false, true] {
                    let n = 1 + (d * 7 + k * 3) % 23 + 8 * grid as usize;
                    // On a coarse grid of small integers and halves every product and sum is
                    // exact, so many values tie exactly; otherwise uniform values, with the
                    // first centroid repeated at a few places (ties across tiles).
                    let mut val = |s: f32| {
                        if grid {
                            (r.uniform(-2.0, 2.0) * s).round() / s
                        } else {
                            r.uniform(-3.0, 3.0)
                        }
                    };
                    let rows: Vec<f32> = (0..n * d).map(|_| val(1.0)).collect();
                    let mut cent: Vec<f32> = (0..k * d).map(|_| val(2.0)).collect();
                    for j in [k / 3, k / 2, k - 1] {
                        if j > 0 && !grid {
                            let c0 = cent[..d].to_vec();
                            cent[j * d..(j + 1) * d].copy_from_slice(&c0);
                        }
                    }
                    let n2: Vec<f32> = cent
                        .chunks_exact(d)
                        .map(|c| c.iter().map(|v| v * v).sum())
                        .collect();
                    let p = Packed::new(&cent, d, &n2);
                    let run = |path: Path, with_second: bool| {
                        let (mut l, mut b, mut s) = (vec![0u16; n], vec![0.0; n], vec![0.0; n]);
                        let second = if with_second { Some(&mut s[..]) } else { None };
                        p.nearest_on(path, &rows, &mut l, Some(&mut b), second);
                        (l, bits(&b), bits(&s))
                    };
                    let want = run(Path::Scalar, true);
                    for &path in &paths {
                        let got = run(path, true);
                        assert_eq!(got, want, "{path:?} d {d} k {k} grid {grid}");
                        let (l, b, _) = run(path, false);
                        assert_eq!((l, b), (want.0.clone(), want.1.clone()), "{path:?}");
                    }
                    cases += 1;
                }
            }
        }
        assert_eq!(cases, 150);
    }

    /// A product that underflows makes -0 where an exactly zero centroid makes +0: the two tie,
    /// and every path gives the lower index and `+0` for both values.
    #[test]
    fn negative_zero_ties_give_the_same_bits_on_every_path() {
        let d = 3;
        // Centroid 1 is the smallest subnormal (its |c|^2 is +0; x * -2c rounds to -0 for a
        // small positive x), centroid 40 is zero; the rest are far away.
        let k = 70;
        let mut cent = vec![5.0f32; k * d];
        cent[d..2 * d].fill(f32::from_bits(1));
        cent[40 * d..41 * d].fill(0.0);
        let n2: Vec<f32> = cent
            .chunks_exact(d)
            .map(|c| c.iter().map(|v| v * v).sum())
            .collect();
        let rows = vec![0.125f32; 5 * d];
        let p = Packed::new(&cent, d, &n2);
        for path in [Path::Avx512, Path::Avx2Fma, Path::Scalar] {
            if !path.available() {
                continue;
            }
            let (mut l, mut b, mut s) = (vec![0u16; 5], vec![1.0f32; 5], vec![1.0f32; 5]);
            p.nearest_on(path, &rows, &mut l, Some(&mut b), Some(&mut s));
            assert_eq!(l, vec![1; 5], "{path:?}");
            assert!(b.iter().chain(&s).all(|v| v.to_bits() == 0), "{path:?}");
        }
    }
}
