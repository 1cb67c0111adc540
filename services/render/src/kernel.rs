//! The per-sample arithmetic of the CPU ray marcher: trilinear corners and weights, the
//! interpolated intensity and the interpolated half-precision central differences.
//!
//! Two implementations give the same bits: [`Scalar`] for any target, and `Avx2` (x86-64 with
//! AVX2 and F16C, chosen at run time) with the same operations in the same order on 4- and 8-wide
//! registers. IEEE arithmetic is the same in either, and no operation is fused, so images do not
//! depend on the CPU they were drawn on.

/// A trilinear sample: its first corner (lowest x, y, z) as a padded-brick index, the y and z
/// strides, and the eight weights: corners 0-3 lie at z and 4-7 at z + 1, each four in the order
/// x, x + 1, (x, y + 1), (x + 1, y + 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Trilinear {
    /// Index of corner 0.
    pub b: usize,
    /// Stride of y.
    pub sy: usize,
    /// Stride of z.
    pub sz: usize,
    /// Weights of corners 0-3 and 4-7.
    pub w: [[f32; 4]; 2],
}

impl Trilinear {
    /// The corners and weights of local continuous voxel coordinates `p` in a brick of `dims`
    /// voxels per axis, each coordinate clamped inside the brick first.
    #[inline(always)]
    pub fn new(p: [f32; 3], dims: [usize; 3]) -> Self {
        let mut f = [0.0f32; 3];
        let mut i = [0usize; 3];
        for k in 0..3 {
            // Non-negative after the clamp, so truncation is floor (and needs no libm call).
            let x = p[k].max(0.0).min(dims[k] as f32 - 1.0001);
            i[k] = floor_index(x);
            f[k] = x - i[k] as f32;
        }
        let (sy, sz) = (dims[0], dims[0] * dims[1]);
        let (gx, gy, gz) = (1.0 - f[0], 1.0 - f[1], 1.0 - f[2]);
        // (x weight * y weight) * z weight, the four in-plane products made once.
        let xy = [gx * gy, f[0] * gy, gx * f[1], f[0] * f[1]];
        Trilinear {
            b: i[2] * sz + i[1] * sy + i[0],
            sy,
            sz,
            w: [
                [xy[0] * gz, xy[1] * gz, xy[2] * gz, xy[3] * gz],
                [xy[0] * f[2], xy[1] * f[2], xy[2] * f[2], xy[3] * f[2]],
            ],
        }
    }

    /// The eight corner indices, in weight order.
    #[inline(always)]
    pub fn idx(&self) -> [usize; 8] {
        let (b, sy, sz) = (self.b, self.sy, self.sz);
        [
            b,
            b + 1,
            b + sy,
            b + sy + 1,
            b + sz,
            b + sz + 1,
            b + sz + sy,
            b + sz + sy + 1,
        ]
    }

    /// The eight weights, in corner order.
    #[inline(always)]
    pub fn w8(&self) -> [f32; 8] {
        let [a, b] = self.w;
        [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]]
    }

    /// The largest corner index (corner 7): every corner is at most this.
    #[inline(always)]
    pub fn last(&self) -> usize {
        self.b + self.sz + self.sy + 1
    }
}

/// A ray's samples in a brick's padded voxel coordinates: sample `k` lies at
/// `o + d t - base` with `t = t0 + (k + 1/2) dt`, the same for every brick the ray crosses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Steps {
    /// Ray origin (volume voxel coordinates).
    pub o: [f32; 3],
    /// Ray direction (voxels per world unit).
    pub d: [f32; 3],
    /// The brick's padded origin in volume voxel coordinates.
    pub base: [f32; 3],
    /// Where the ray enters the volume.
    pub t0: f32,
    /// World distance between samples.
    pub dt: f32,
}

impl Steps {
    /// Local padded coordinates of sample `k` (`k` below 2^24, so `k` as f32 is exact).
    #[inline(always)]
    pub fn pos(&self, k: u64) -> [f32; 3] {
        let (o, d, base) = (self.o, self.d, self.base);
        let t = self.t0 + (k as f32 + 0.5) * self.dt;
        [
            o[0] + d[0] * t - base[0],
            o[1] + d[1] * t - base[1],
            o[2] + d[2] * t - base[2],
        ]
    }
}

/// `x` truncated, for `x` from `max(0).min(hi)` with `hi` below 2^31 (so never NaN, negative
/// or too large): a bare conversion without the saturating checks of `as`.
#[inline(always)]
pub(crate) fn floor_index(x: f32) -> usize {
    debug_assert!((0.0..2147483648.0).contains(&x));
    // SAFETY: x is finite and within i32 (every caller clamps it with max(0).min(hi), which
    // also maps NaN to 0).
    unsafe { x.to_int_unchecked::<i32>() as usize }
}

/// The interpolations a sample needs, with one order of operations for every implementation.
pub(crate) trait Kernels {
    /// The trilinear intensity: per lane `k` of 0-3, `s_k = q_k w_k + q_(k+4) w_(k+4)`, then
    /// `(s_0 + s_2) + (s_1 + s_3)`.
    fn value(v: &[f32], t: &Trilinear) -> f32;
    /// The trilinear central differences (lanes 0-2; lane 3 is the zero lane): the even
    /// corners summed in order from zero, the odd ones likewise, then even + odd.
    fn gradient(g: &[[u16; 4]], t: &Trilinear) -> [f32; 4];
    /// Samples `k .. k + 4` of a ray: each one's corners and weights,
    /// `Trilinear::new(s.pos(k + l), dims)`, and its intensity `value(v, ..)` (`v` holds the
    /// padded brick of `dims`).
    fn run4(v: &[f32], dims: [usize; 3], s: &Steps, k: u64) -> Run4 {
        let t = [0, 1, 2, 3].map(|l| Trilinear::new(s.pos(k + l), dims));
        Run4 {
            values: [0, 1, 2, 3].map(|l| Self::value(v, &t[l])),
            t,
        }
    }
}

/// Four consecutive samples of a ray ([`Kernels::run4`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Run4 {
    /// Each sample's corners and weights.
    pub t: [Trilinear; 4],
    /// Each sample's interpolated intensity.
    pub values: [f32; 4],
}

/// [`Kernels`] in plain Rust, for any target.
pub(crate) struct Scalar;

impl Kernels for Scalar {
    #[inline(always)]
    fn value(v: &[f32], t: &Trilinear) -> f32 {
        let q = corner_values(v, t);
        let w = t.w8();
        let s0 = q[0] * w[0] + q[4] * w[4];
        let s1 = q[1] * w[1] + q[5] * w[5];
        let s2 = q[2] * w[2] + q[6] * w[6];
        let s3 = q[3] * w[3] + q[7] * w[7];
        (s0 + s2) + (s1 + s3)
    }

    #[inline(always)]
    fn gradient(g: &[[u16; 4]], t: &Trilinear) -> [f32; 4] {
        let q = corner_values(g, t);
        let w = t.w8();
        let mut even = [0.0f32; 4];
        let mut odd = [0.0f32; 4];
        for c in (0..8).step_by(2) {
            let (a, b) = (widen(&q[c]), widen(&q[c + 1]));
            for k in 0..4 {
                even[k] += a[k] * w[c];
                odd[k] += b[k] * w[c + 1];
            }
        }
        [
            even[0] + odd[0],
            even[1] + odd[1],
            even[2] + odd[2],
            even[3] + odd[3],
        ]
    }
}

/// Four IEEE half-precision lanes as f32 (exact).
#[inline(always)]
fn widen(h: &[u16; 4]) -> [f32; 4] {
    let f = |b: u16| half::f16::from_bits(b).to_f32();
    [f(h[0]), f(h[1]), f(h[2]), f(h[3])]
}

/// The 8 corner values of a sample, with one bounds check: the last corner is the largest
/// index.
#[inline(always)]
pub(crate) fn corner_values<T: Copy>(v: &[T], t: &Trilinear) -> [T; 8] {
    let idx = t.idx();
    assert!(t.last() < v.len(), "sample outside the brick");
    // SAFETY: every corner is at most `t.last()`, which is in bounds (checked above).
    unsafe {
        [
            *v.get_unchecked(idx[0]),
            *v.get_unchecked(idx[1]),
            *v.get_unchecked(idx[2]),
            *v.get_unchecked(idx[3]),
            *v.get_unchecked(idx[4]),
            *v.get_unchecked(idx[5]),
            *v.get_unchecked(idx[6]),
            *v.get_unchecked(idx[7]),
        ]
    }
}

/// [`Kernels`] on AVX2 and F16C registers. Only code compiled with those features (the
/// marcher's `march_row_avx2`, entered after a run-time check) may use it.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Avx2;

#[cfg(target_arch = "x86_64")]
impl Kernels for Avx2 {
    #[inline(always)]
    fn value(v: &[f32], t: &Trilinear) -> f32 {
        use std::arch::x86_64::*;
        assert!(t.last() < v.len(), "sample outside the brick");
        // SAFETY: the four 8-byte reads end at corners 1, 3, 5 and 7, all at most `t.last()`
        // (checked); the caller runs on a CPU with AVX2 (see the type).
        unsafe {
            let (wlo, whi) = (_mm_loadu_ps(t.w[0].as_ptr()), _mm_loadu_ps(t.w[1].as_ptr()));
            value_at(v.as_ptr(), t.b, t.sy, t.sz, wlo, whi)
        }
    }

    #[inline(always)]
    fn gradient(g: &[[u16; 4]], t: &Trilinear) -> [f32; 4] {
        use std::arch::x86_64::*;
        assert!(t.last() < g.len(), "sample outside the brick");
        // SAFETY: the four 16-byte reads are corner pairs (c, c + 1) ending at corners 1, 3,
        // 5 and 7, all at most `t.last()` (checked); the CPU has AVX2 and F16C (see the type).
        unsafe {
            let p = g.as_ptr();
            let w = t.w8();
            // Corner pairs (c, c + 1) with their weights [w_c x4, w_(c+1) x4] (no closures:
            // see `run4_simd`).
            let (b, sy, sz) = (t.b, t.sy, t.sz);
            let mut acc = _mm256_setzero_ps();
            let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b) as *const __m128i));
            let ws = _mm256_setr_m128(_mm_set1_ps(w[0]), _mm_set1_ps(w[1]));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(q, ws));
            let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sy) as *const __m128i));
            let ws = _mm256_setr_m128(_mm_set1_ps(w[2]), _mm_set1_ps(w[3]));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(q, ws));
            let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sz) as *const __m128i));
            let ws = _mm256_setr_m128(_mm_set1_ps(w[4]), _mm_set1_ps(w[5]));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(q, ws));
            let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sz + sy) as *const __m128i));
            let ws = _mm256_setr_m128(_mm_set1_ps(w[6]), _mm_set1_ps(w[7]));
            acc = _mm256_add_ps(acc, _mm256_mul_ps(q, ws));
            let sum = _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps::<1>(acc));
            std::mem::transmute::<__m128, [f32; 4]>(sum)
        }
    }

    #[inline(always)]
    fn run4(v: &[f32], dims: [usize; 3], s: &Steps, k: u64) -> Run4 {
        if k + 4 < 1 << 24 && dims.iter().all(|&n| (2..1 << 20).contains(&n)) {
            Self::run4_simd(v, dims, s, k)
        } else {
            // Beyond the lanes' exact integer range (or a degenerate brick): one at a time.
            let t = [0, 1, 2, 3].map(|l| Trilinear::new(s.pos(k + l), dims));
            Run4 {
                values: [0, 1, 2, 3].map(|l| Self::value(v, &t[l])),
                t,
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
impl Avx2 {
    /// [`Kernels::run4`] on 4-wide registers: positions, floors, fractions and weights for the
    /// four samples at once (lane by lane the operations of [`Steps::pos`] and
    /// [`Trilinear::new`]), then each sample's weights and corners side by side for
    /// [`Kernels::value`]'s sums (corner pairs read 8 bytes at a time: gathers are slow here).
    #[inline(always)]
    fn run4_simd(v: &[f32], dims: [usize; 3], s: &Steps, k: u64) -> Run4 {
        use std::arch::x86_64::*;
        assert!(
            v.len() == dims[0] * dims[1] * dims[2],
            "sample outside the brick"
        );
        // SAFETY: the CPU has AVX2 (see the type); the caller checked `k + 4 < 2^24` and
        // 2 <= dims < 2^20. Each coordinate is clamped to [0, dims - 1.0001], so its floor is at
        // most dims - 2 and corner 7 of every lane lies inside `v` (its length checked above).
        // No closures here: a closure does not inherit the caller's target features, so the
        // intrinsics inside it would become calls.
        unsafe {
            let kf = _mm_cvtepi32_ps(_mm_add_epi32(
                _mm_set1_epi32(k as i32),
                _mm_setr_epi32(0, 1, 2, 3),
            ));
            let t = _mm_add_ps(
                _mm_set1_ps(s.t0),
                _mm_mul_ps(_mm_add_ps(kf, _mm_set1_ps(0.5)), _mm_set1_ps(s.dt)),
            );
            let lo = _mm_setzero_ps();
            let px = _mm_sub_ps(
                _mm_add_ps(_mm_set1_ps(s.o[0]), _mm_mul_ps(_mm_set1_ps(s.d[0]), t)),
                _mm_set1_ps(s.base[0]),
            );
            let py = _mm_sub_ps(
                _mm_add_ps(_mm_set1_ps(s.o[1]), _mm_mul_ps(_mm_set1_ps(s.d[1]), t)),
                _mm_set1_ps(s.base[1]),
            );
            let pz = _mm_sub_ps(
                _mm_add_ps(_mm_set1_ps(s.o[2]), _mm_mul_ps(_mm_set1_ps(s.d[2]), t)),
                _mm_set1_ps(s.base[2]),
            );
            // max(p, 0) sends NaN to 0, as f32::max does.
            let x = _mm_min_ps(_mm_max_ps(px, lo), _mm_set1_ps(dims[0] as f32 - 1.0001));
            let y = _mm_min_ps(_mm_max_ps(py, lo), _mm_set1_ps(dims[1] as f32 - 1.0001));
            let z = _mm_min_ps(_mm_max_ps(pz, lo), _mm_set1_ps(dims[2] as f32 - 1.0001));
            let (ix, iy, iz) = (
                _mm_cvttps_epi32(x),
                _mm_cvttps_epi32(y),
                _mm_cvttps_epi32(z),
            );
            let fx = _mm_sub_ps(x, _mm_cvtepi32_ps(ix));
            let fy = _mm_sub_ps(y, _mm_cvtepi32_ps(iy));
            let fz = _mm_sub_ps(z, _mm_cvtepi32_ps(iz));
            let one = _mm_set1_ps(1.0);
            let (gx, gy, gz) = (
                _mm_sub_ps(one, fx),
                _mm_sub_ps(one, fy),
                _mm_sub_ps(one, fz),
            );
            let (sy, sz) = (dims[0], dims[0] * dims[1]);
            let b = _mm_add_epi32(
                _mm_add_epi32(
                    _mm_mullo_epi32(iz, _mm_set1_epi32(sz as i32)),
                    _mm_mullo_epi32(iy, _mm_set1_epi32(sy as i32)),
                ),
                ix,
            );
            // The weights, corner by corner across the lanes, then lane by lane.
            let xy0 = _mm_mul_ps(gx, gy);
            let xy1 = _mm_mul_ps(fx, gy);
            let xy2 = _mm_mul_ps(gx, fy);
            let xy3 = _mm_mul_ps(fx, fy);
            let (mut w0, mut w1, mut w2, mut w3) = (
                _mm_mul_ps(xy0, gz),
                _mm_mul_ps(xy1, gz),
                _mm_mul_ps(xy2, gz),
                _mm_mul_ps(xy3, gz),
            );
            let (mut w4, mut w5, mut w6, mut w7) = (
                _mm_mul_ps(xy0, fz),
                _mm_mul_ps(xy1, fz),
                _mm_mul_ps(xy2, fz),
                _mm_mul_ps(xy3, fz),
            );
            _MM_TRANSPOSE4_PS(&mut w0, &mut w1, &mut w2, &mut w3);
            _MM_TRANSPOSE4_PS(&mut w4, &mut w5, &mut w6, &mut w7);
            let mut bs = [0i32; 4];
            _mm_storeu_si128(bs.as_mut_ptr() as *mut __m128i, b);
            let p = v.as_ptr();
            let mut out = Run4 {
                t: [Trilinear {
                    b: 0,
                    sy,
                    sz,
                    w: [[0.0; 4]; 2],
                }; 4],
                values: [0.0; 4],
            };
            let wl = [w0, w1, w2, w3];
            let wh = [w4, w5, w6, w7];
            for l in 0..4 {
                let b = bs[l] as usize;
                out.values[l] = value_at(p, b, sy, sz, wl[l], wh[l]);
                out.t[l].b = b;
                _mm_storeu_ps(out.t[l].w[0].as_mut_ptr(), wl[l]);
                _mm_storeu_ps(out.t[l].w[1].as_mut_ptr(), wh[l]);
            }
            out
        }
    }
}

/// [`Kernels::value`] of the sample whose corner 0 is `p[b]`, with the weights of corners
/// 0-3 and 4-7 in `wlo` and `whi`: the corner pairs (c, c + 1) read 8 bytes at a time,
/// `s_c = q_c w_c + q_(c+4) w_(c+4)`, then `(s0 + s2) + (s1 + s3)`.
///
/// # Safety
/// Corner 7, `p[b + sz + sy + 1]`, must be readable, and the CPU must have AVX2. (An
/// `#[inline(always)]` function without closures: its intrinsics are inlined where it is, in
/// code compiled for AVX2.)
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn value_at(
    p: *const f32,
    b: usize,
    sy: usize,
    sz: usize,
    wlo: std::arch::x86_64::__m128,
    whi: std::arch::x86_64::__m128,
) -> f32 {
    use std::arch::x86_64::*;
    let lo = _mm_movelh_ps(
        _mm_castpd_ps(_mm_load_sd(p.add(b) as *const f64)),
        _mm_castpd_ps(_mm_load_sd(p.add(b + sy) as *const f64)),
    );
    let hi = _mm_movelh_ps(
        _mm_castpd_ps(_mm_load_sd(p.add(b + sz) as *const f64)),
        _mm_castpd_ps(_mm_load_sd(p.add(b + sz + sy) as *const f64)),
    );
    let s = _mm_add_ps(_mm_mul_ps(lo, wlo), _mm_mul_ps(hi, whi));
    // [s0 + s2, s1 + s3], then their sum.
    let h = _mm_add_ps(s, _mm_movehl_ps(s, s));
    _mm_cvtss_f32(_mm_add_ss(h, _mm_shuffle_ps::<0b01>(h, h)))
}

/// Whether this CPU runs the [`Avx2`] kernels.
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx2() -> bool {
    std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("f16c")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A seeded stream of f32 in [-1, 1) and the padded brick it fills.
    fn brick(n: [usize; 3], seed: u64) -> (Vec<f32>, Vec<[u16; 4]>) {
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        let len = n.iter().product();
        let v: Vec<f32> = (0..len).map(|_| next()).collect();
        let g = (0..len)
            .map(|_| {
                let h = |x: f32| half::f16::from_f32(x).to_bits();
                [h(next()), h(next() * 1e-3), h(next() * 30.0), 0]
            })
            .collect();
        (v, g)
    }

    #[test]
    fn weights_are_the_products_of_the_axis_weights_and_sum_to_one() {
        let t = Trilinear::new([1.25, 2.5, 0.75], [4, 5, 6]);
        assert_eq!((t.b, t.sy, t.sz), (2 * 4 + 1, 4, 20));
        let w = t.w8();
        let want = [
            0.75 * 0.5 * 0.25,
            0.25 * 0.5 * 0.25,
            0.75 * 0.5 * 0.25,
            0.25 * 0.5 * 0.25,
            0.75 * 0.5 * 0.75,
            0.25 * 0.5 * 0.75,
            0.75 * 0.5 * 0.75,
            0.25 * 0.5 * 0.75,
        ];
        assert_eq!(w, want);
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        // Outside the brick, and NaN, clamp to its corners.
        let t = Trilinear::new([-3.0, f32::NAN, 1e9], [4, 5, 6]);
        assert!(t.last() < 4 * 5 * 6);
        assert_eq!(Scalar::value(&[1.0; 120], &t), 1.0);
    }

    #[test]
    fn the_scalar_kernels_interpolate_trilinearly() {
        // f(x, y, z) = 2x - 3y + z + 1 is reproduced exactly by trilinear interpolation.
        let n = [5, 4, 3];
        let f = |x: usize, y: usize, z: usize| 2.0 * x as f32 - 3.0 * y as f32 + z as f32 + 1.0;
        let mut v = Vec::new();
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    v.push(f(x, y, z));
                }
            }
        }
        let p = [2.5, 1.25, 0.5];
        let t = Trilinear::new(p, n);
        let want = 2.0 * p[0] - 3.0 * p[1] + p[2] + 1.0;
        assert!((Scalar::value(&v, &t) - want).abs() < 1e-5);
        let one = half::f16::from_f32(1.0).to_bits();
        let g = vec![[one, 0, one, 0]; v.len()];
        let d = Scalar::gradient(&g, &t);
        assert!((d[0] - 1.0).abs() < 1e-6 && d[1] == 0.0 && (d[2] - 1.0).abs() < 1e-6);
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_kernels_give_the_scalar_bits() {
        if !has_avx2() {
            eprintln!("SKIP: this CPU has no AVX2/F16C");
            return;
        }
        #[target_feature(enable = "avx2,f16c")]
        fn both(v: &[f32], g: &[[u16; 4]], t: &Trilinear) -> (f32, [f32; 4]) {
            (Avx2::value(v, t), Avx2::gradient(g, t))
        }
        let n = [9, 7, 8];
        for seed in 0..4 {
            let (v, g) = brick(n, seed);
            let mut s = seed;
            for _ in 0..5000 {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                let p = [0, 1, 2].map(|k| {
                    let u = ((s >> (10 + 15 * k)) & 0x7fff) as f32 / 32768.0;
                    u * (n[k] as f32 + 2.0) - 1.0
                });
                let t = Trilinear::new(p, n);
                // SAFETY: the features were detected above.
                let (a, ga) = unsafe { both(&v, &g, &t) };
                let (b, gb) = (Scalar::value(&v, &t), Scalar::gradient(&g, &t));
                assert_eq!(a.to_bits(), b.to_bits(), "value at {p:?}");
                assert_eq!(
                    ga.map(f32::to_bits),
                    gb.map(f32::to_bits),
                    "gradient at {p:?}"
                );
            }
        }
        // Four samples of a ray at once, as four single samples; the ray crosses the brick
        // and leaves it (the clamp), in every direction, and a NaN origin.
        #[target_feature(enable = "avx2,f16c")]
        fn four(v: &[f32], n: [usize; 3], s: &Steps, k: u64) -> Run4 {
            Avx2::run4(v, n, s, k)
        }
        let (v, _) = brick(n, 9);
        for (q, o) in [[-2.0, 3.0, 1.0], [4.5, 3.5, 4.0], [f32::NAN, 1.0, 1.0]]
            .into_iter()
            .enumerate()
        {
            for dir in 0..27 {
                let d = [dir % 3, dir / 3 % 3, dir / 9].map(|c| (c as f32 - 1.0) * 0.37 + 0.01);
                let s = Steps {
                    o,
                    d,
                    base: [-0.25, 0.5, 0.0],
                    t0: 0.3 * q as f32,
                    dt: 0.5,
                };
                for k in 0..40 {
                    // SAFETY: the features were detected above.
                    let a = unsafe { four(&v, n, &s, k) };
                    let b = Scalar::run4(&v, n, &s, k);
                    assert_eq!(a.t, b.t, "{o:?} {d:?} {k}");
                    let bits = |r: Run4| r.values.map(f32::to_bits);
                    assert_eq!(bits(a), bits(b), "{o:?} {d:?} {k}");
                }
            }
        }
    }
}
