//! The per-sample arithmetic of the CPU ray marcher: trilinear corners and weights, the
//! interpolated intensity and the interpolated half-precision central differences, and, for the
//! intensity mode, the transfer-function table and Blinn-Phong shading of four samples at once.
//!
//! Two implementations give the same bits: [`Scalar`] for any target, and `Avx2` (x86-64 with
//! AVX2 and F16C, chosen at run time) with the same operations in the same order on 4- and 8-wide
//! registers. IEEE arithmetic is the same in either, and no operation is fused, so images do not
//! depend on the CPU they were drawn on.

use crate::tf::Lut;

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

    /// Samples `k .. k + 4` of a ray in intensity mode: each one's colour and opacity from
    /// the table `lut` at its intensity (zeros where the opacity is not positive), the colour
    /// shaded with `shading` (the frame's constants and the brick's central differences) and
    /// the headlight `light`, as [`samples4_each`] computes them.
    fn samples4(
        v: &[f32],
        dims: [usize; 3],
        s: &Steps,
        k: u64,
        lut: &Lut,
        shading: Option<(&Phong, &[[u16; 4]])>,
        light: [f32; 3],
    ) -> [[f32; 4]; 4] {
        samples4_each::<Self>(v, dims, s, k, lut, shading, light)
    }
}

/// Blinn-Phong with a headlight, the constants of a frame: the normal is the intensity
/// gradient (the trilinear interpolation of the voxels' central differences, scaled by `h` to
/// world units); a gradient whose length times `min_sp` is not above 1e-4 (or NaN) leaves the
/// colour unshaded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Phong {
    /// Half the reciprocal spacing per axis.
    pub h: [f32; 3],
    /// The finest spacing (world units of one voxel along its finest axis).
    pub min_sp: f32,
    /// Ambient weight.
    pub ambient: f32,
    /// Diffuse weight.
    pub diffuse: f32,
    /// Specular weight.
    pub specular: f32,
    /// Specular exponent.
    pub shininess: f32,
}

impl Phong {
    /// The shaded colour `rgb` of a sample whose interpolated central differences are `acc`
    /// (lanes 0-2), lit along `light`.
    #[inline(always)]
    pub fn shade(&self, acc: [f32; 4], rgb: [f32; 3], light: [f32; 3]) -> [f32; 3] {
        let h = self.h;
        let g = [acc[0] * h[0], acc[1] * h[1], acc[2] * h[2]];
        let len = dot3(g, g).sqrt();
        // Also catches NaN: a flat or degenerate gradient leaves the colour unshaded.
        if (len * self.min_sp).partial_cmp(&1e-4) != Some(std::cmp::Ordering::Greater) {
            return rgb;
        }
        let ndl = (dot3(g, light) / len).abs();
        let spec = self.specular * spec_pow(ndl, self.shininess);
        let k = self.ambient + self.diffuse * ndl;
        rgb.map(|c| (c * k + spec).min(1.0))
    }
}

/// `a . b`, summed left to right.
#[inline(always)]
fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `x^e` for the specular term: repeated squaring for whole exponents up to 256.
#[inline(always)]
fn spec_pow(x: f32, e: f32) -> f32 {
    match whole_exponent(e) {
        Some(n) => powi_inline(x, n),
        None => x.powf(e),
    }
}

/// The exponent [`spec_pow`] takes by repeated squaring: a whole `e` up to 256.
#[inline(always)]
fn whole_exponent(e: f32) -> Option<u32> {
    (e.fract() == 0.0 && e <= 256.0).then_some(e as u32)
}

/// Whether the lanes' integer arithmetic is exact for samples `k .. k + 4` of a brick of
/// `dims` (and the brick is not degenerate).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn lanes_fit(dims: [usize; 3], k: u64) -> bool {
    k + 4 < 1 << 24 && dims.iter().all(|&n| (2..1 << 20).contains(&n))
}

/// `x^n` by repeated squaring.
#[inline(always)]
fn powi_inline(mut x: f32, mut n: u32) -> f32 {
    let mut r = 1.0f32;
    while n > 0 {
        if n & 1 == 1 {
            r *= x;
        }
        x *= x;
        n >>= 1;
    }
    r
}

/// Colour and opacity of a table at `x`, as [`Lut::get`], with the opacity first: a
/// transparent entry returns zeros before the colour is interpolated.
#[inline(always)]
pub(crate) fn lut_get(l: &Lut, x: f32) -> [f32; 4] {
    let n = l.table.len();
    // max(0) also sends NaN to the first entry.
    let u = ((x - l.lo) * l.scale).max(0.0).min((n - 1) as f32);
    let i = floor_index(u).min(n - 2);
    let t = u - i as f32;
    let (a, b) = (l.table[i], l.table[i + 1]);
    let alpha = a[3] + (b[3] - a[3]) * t;
    if alpha <= 0.0 {
        return [0.0; 4];
    }
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
        alpha,
    ]
}

/// [`Kernels::samples4`] one sample at a time with the kernels `H`: the four intensities, the
/// table for each, then the gradients and shading of the visible ones.
#[inline(always)]
pub(crate) fn samples4_each<H: Kernels + ?Sized>(
    v: &[f32],
    dims: [usize; 3],
    s: &Steps,
    k: u64,
    lut: &Lut,
    shading: Option<(&Phong, &[[u16; 4]])>,
    light: [f32; 3],
) -> [[f32; 4]; 4] {
    let run = H::run4(v, dims, s, k);
    let mut out = [[0.0; 4]; 4];
    // The table for every sample first, then the gradients of the visible ones: their reads
    // are then independent of each other and overlap.
    let mut visible = [false; 4];
    for l in 0..4 {
        out[l] = lut_get(lut, run.values[l]);
        visible[l] = out[l][3] > 0.0;
    }
    if let Some((p, g)) = shading {
        let mut grad = [[0.0; 4]; 4];
        for l in 0..4 {
            if visible[l] {
                grad[l] = H::gradient(g, &run.t[l]);
            }
        }
        for l in 0..4 {
            if visible[l] {
                let e = out[l];
                let rgb = p.shade(grad[l], [e[0], e[1], e[2]], light);
                out[l] = [rgb[0], rgb[1], rgb[2], e[3]];
            }
        }
    }
    out
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
        // SAFETY: corner 7 is `t.last()`, in bounds (checked); the CPU has AVX2 and F16C (see
        // the type).
        unsafe {
            let (wlo, whi) = (_mm_loadu_ps(t.w[0].as_ptr()), _mm_loadu_ps(t.w[1].as_ptr()));
            std::mem::transmute::<__m128, [f32; 4]>(gradient_at(
                g.as_ptr(),
                t.b,
                t.sy,
                t.sz,
                wlo,
                whi,
            ))
        }
    }

    #[inline(always)]
    fn run4(v: &[f32], dims: [usize; 3], s: &Steps, k: u64) -> Run4 {
        if lanes_fit(dims, k) {
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

    #[inline(always)]
    fn samples4(
        v: &[f32],
        dims: [usize; 3],
        s: &Steps,
        k: u64,
        lut: &Lut,
        shading: Option<(&Phong, &[[u16; 4]])>,
        light: [f32; 3],
    ) -> [[f32; 4]; 4] {
        use std::arch::x86_64::*;
        let e = match shading {
            Some((p, _)) => match whole_exponent(p.shininess) {
                Some(e) => e,
                // A fractional exponent (powf): sample by sample.
                None => return samples4_each::<Self>(v, dims, s, k, lut, shading, light),
            },
            None => 0,
        };
        if !lanes_fit(dims, k) {
            // Beyond the lanes' exact integer range (or a degenerate brick).
            return samples4_each::<Self>(v, dims, s, k, lut, shading, light);
        }
        let n = lut.table.len();
        assert!(n >= 2, "a lookup table of {n} entries");
        let len = dims[0] * dims[1] * dims[2];
        assert!(
            v.len() == len && shading.is_none_or(|(_, g)| g.len() == len),
            "sample outside the brick"
        );
        // SAFETY: the CPU has AVX2 and F16C (see the type); `k` and `dims` are in the range
        // `lanes4` needs (checked above), so every corner it gives lies inside `v` and the
        // differences (their lengths checked). Each table index is at most n - 2 (the integer
        // min below), so entries i and i + 1 are in the table. No closures (see `lanes4`).
        unsafe {
            let q = lanes4(dims, s, k);
            let x = _mm_setr_ps(
                value_at(v.as_ptr(), q.b[0], q.sy, q.sz, q.wl[0], q.wh[0]),
                value_at(v.as_ptr(), q.b[1], q.sy, q.sz, q.wl[1], q.wh[1]),
                value_at(v.as_ptr(), q.b[2], q.sy, q.sz, q.wl[2], q.wh[2]),
                value_at(v.as_ptr(), q.b[3], q.sy, q.sz, q.wl[3], q.wh[3]),
            );
            // The table, as `lut_get` per lane: the position, its entry and fraction.
            let u = _mm_mul_ps(_mm_sub_ps(x, _mm_set1_ps(lut.lo)), _mm_set1_ps(lut.scale));
            // max(u, 0) sends NaN to 0, as f32::max does.
            let u = _mm_min_ps(_mm_max_ps(u, _mm_setzero_ps()), _mm_set1_ps((n - 1) as f32));
            let i = _mm_min_epi32(_mm_cvttps_epi32(u), _mm_set1_epi32(n as i32 - 2));
            let t = _mm_sub_ps(u, _mm_cvtepi32_ps(i));
            let mut is = [0i32; 4];
            _mm_storeu_si128(is.as_mut_ptr() as *mut __m128i, i);
            let mut ts = [0.0f32; 4];
            _mm_storeu_ps(ts.as_mut_ptr(), t);
            let tab = lut.table.as_ptr() as *const f32;
            let mut rgba = [_mm_setzero_ps(); 4];
            for l in 0..4 {
                let p = tab.add(is[l] as usize * 4);
                let (a, b) = (_mm_loadu_ps(p), _mm_loadu_ps(p.add(4)));
                rgba[l] = _mm_add_ps(a, _mm_mul_ps(_mm_sub_ps(b, a), _mm_set1_ps(ts[l])));
            }
            // Lanes across samples: red, green, blue and opacity of the four.
            let [mut r, mut g, mut b, mut a] = rgba;
            _MM_TRANSPOSE4_PS(&mut r, &mut g, &mut b, &mut a);
            // A transparent sample (opacity not above 0) is zeros, colour too.
            let visible = _mm_cmpgt_ps(a, _mm_setzero_ps());
            let (mut r, mut g, mut b, a) = (
                _mm_and_ps(r, visible),
                _mm_and_ps(g, visible),
                _mm_and_ps(b, visible),
                _mm_and_ps(a, visible),
            );
            let seen = _mm_movemask_ps(visible);
            if let (Some((p, diffs)), true) = (shading, seen != 0) {
                // The visible samples' gradients, then `Phong::shade` across the lanes.
                let mut d = [_mm_setzero_ps(); 4];
                for (l, d) in d.iter_mut().enumerate() {
                    if seen & (1 << l) != 0 {
                        *d = gradient_at(diffs.as_ptr(), q.b[l], q.sy, q.sz, q.wl[l], q.wh[l]);
                    }
                }
                let [mut gx, mut gy, mut gz, mut zero] = d;
                _MM_TRANSPOSE4_PS(&mut gx, &mut gy, &mut gz, &mut zero);
                let gx = _mm_mul_ps(gx, _mm_set1_ps(p.h[0]));
                let gy = _mm_mul_ps(gy, _mm_set1_ps(p.h[1]));
                let gz = _mm_mul_ps(gz, _mm_set1_ps(p.h[2]));
                let len = _mm_sqrt_ps(_mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(gx, gx), _mm_mul_ps(gy, gy)),
                    _mm_mul_ps(gz, gz),
                ));
                // Ordered: false for NaN, as partial_cmp's Greater.
                let lit = _mm_and_ps(
                    visible,
                    _mm_cmpgt_ps(_mm_mul_ps(len, _mm_set1_ps(p.min_sp)), _mm_set1_ps(1e-4)),
                );
                let gl = _mm_add_ps(
                    _mm_add_ps(
                        _mm_mul_ps(gx, _mm_set1_ps(light[0])),
                        _mm_mul_ps(gy, _mm_set1_ps(light[1])),
                    ),
                    _mm_mul_ps(gz, _mm_set1_ps(light[2])),
                );
                let ndl = _mm_andnot_ps(_mm_set1_ps(-0.0), _mm_div_ps(gl, len));
                // powi_inline across the lanes: the same products in the same order.
                let (mut pw, mut xx, mut m) = (_mm_set1_ps(1.0), ndl, e);
                while m > 0 {
                    if m & 1 == 1 {
                        pw = _mm_mul_ps(pw, xx);
                    }
                    xx = _mm_mul_ps(xx, xx);
                    m >>= 1;
                }
                let spec = _mm_mul_ps(_mm_set1_ps(p.specular), pw);
                let kd = _mm_add_ps(
                    _mm_set1_ps(p.ambient),
                    _mm_mul_ps(_mm_set1_ps(p.diffuse), ndl),
                );
                let one = _mm_set1_ps(1.0);
                // min(x, 1) gives 1 for NaN x, as f32::min does.
                let sr = _mm_min_ps(_mm_add_ps(_mm_mul_ps(r, kd), spec), one);
                let sg = _mm_min_ps(_mm_add_ps(_mm_mul_ps(g, kd), spec), one);
                let sb = _mm_min_ps(_mm_add_ps(_mm_mul_ps(b, kd), spec), one);
                r = _mm_blendv_ps(r, sr, lit);
                g = _mm_blendv_ps(g, sg, lit);
                b = _mm_blendv_ps(b, sb, lit);
            }
            let (mut r, mut g, mut b, mut a) = (r, g, b, a);
            _MM_TRANSPOSE4_PS(&mut r, &mut g, &mut b, &mut a);
            let mut out = [[0.0f32; 4]; 4];
            _mm_storeu_ps(out[0].as_mut_ptr(), r);
            _mm_storeu_ps(out[1].as_mut_ptr(), g);
            _mm_storeu_ps(out[2].as_mut_ptr(), b);
            _mm_storeu_ps(out[3].as_mut_ptr(), a);
            out
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
        assert!(
            v.len() == dims[0] * dims[1] * dims[2],
            "sample outside the brick"
        );
        // SAFETY: the CPU has AVX2 (see the type); the caller checked `k + 4 < 2^24` and
        // 2 <= dims < 2^20, and every corner `lanes4` gives lies inside a brick of `dims`,
        // which is `v` (its length checked above).
        unsafe {
            use std::arch::x86_64::*;
            let q = lanes4(dims, s, k);
            let p = v.as_ptr();
            let mut out = Run4 {
                t: [Trilinear {
                    b: 0,
                    sy: q.sy,
                    sz: q.sz,
                    w: [[0.0; 4]; 2],
                }; 4],
                values: [0.0; 4],
            };
            for l in 0..4 {
                let b = q.b[l];
                out.values[l] = value_at(p, b, q.sy, q.sz, q.wl[l], q.wh[l]);
                out.t[l].b = b;
                _mm_storeu_ps(out.t[l].w[0].as_mut_ptr(), q.wl[l]);
                _mm_storeu_ps(out.t[l].w[1].as_mut_ptr(), q.wh[l]);
            }
            out
        }
    }
}

/// Four samples' corners and weights in registers ([`lanes4`]).
#[cfg(target_arch = "x86_64")]
struct Lanes4 {
    /// Each sample's corner 0.
    b: [usize; 4],
    /// Stride of y.
    sy: usize,
    /// Stride of z.
    sz: usize,
    /// Each sample's weights of corners 0-3.
    wl: [std::arch::x86_64::__m128; 4],
    /// Each sample's weights of corners 4-7.
    wh: [std::arch::x86_64::__m128; 4],
}

/// Positions, floors, fractions and weights of samples `k .. k + 4` of a ray on 4-wide
/// registers: lane by lane the operations of [`Steps::pos`] and [`Trilinear::new`].
///
/// # Safety
/// The CPU must have AVX2, `k + 4 < 2^24` and `2 <= dims < 2^20`. Each coordinate is clamped
/// to [0, dims - 1.0001], so its floor is at most dims - 2 and corner 7 of every lane lies
/// inside a brick of `dims`. (No closures here: a closure does not inherit the caller's target
/// features, so the intrinsics inside it would become calls.)
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn lanes4(dims: [usize; 3], s: &Steps, k: u64) -> Lanes4 {
    use std::arch::x86_64::*;
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
    Lanes4 {
        b: bs.map(|b| b as usize),
        sy,
        sz,
        wl: [w0, w1, w2, w3],
        wh: [w4, w5, w6, w7],
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

/// [`Kernels::gradient`] of the sample whose corner 0 is `p[b]`, with the weights of corners
/// 0-3 and 4-7 in `wlo` and `whi`: the corner pairs (c, c + 1) read 16 bytes at a time and
/// widened from half precision, each weighted by `[w_c x4, w_(c+1) x4]`, summed in corner order
/// from zero, then the two halves added.
///
/// # Safety
/// Corner 7, `p[b + sz + sy + 1]`, must be readable, and the CPU must have AVX2 and F16C.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn gradient_at(
    p: *const [u16; 4],
    b: usize,
    sy: usize,
    sz: usize,
    wlo: std::arch::x86_64::__m128,
    whi: std::arch::x86_64::__m128,
) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::*;
    // [w_c x4, w_(c+1) x4] for the pairs (0, 1), (2, 3) of `w`, from registers.
    let w01 = _mm256_setr_m128(
        _mm_shuffle_ps::<0b00_00_00_00>(wlo, wlo),
        _mm_shuffle_ps::<0b01_01_01_01>(wlo, wlo),
    );
    let w23 = _mm256_setr_m128(
        _mm_shuffle_ps::<0b10_10_10_10>(wlo, wlo),
        _mm_shuffle_ps::<0b11_11_11_11>(wlo, wlo),
    );
    let w45 = _mm256_setr_m128(
        _mm_shuffle_ps::<0b00_00_00_00>(whi, whi),
        _mm_shuffle_ps::<0b01_01_01_01>(whi, whi),
    );
    let w67 = _mm256_setr_m128(
        _mm_shuffle_ps::<0b10_10_10_10>(whi, whi),
        _mm_shuffle_ps::<0b11_11_11_11>(whi, whi),
    );
    let mut acc = _mm256_setzero_ps();
    let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b) as *const __m128i));
    acc = _mm256_add_ps(acc, _mm256_mul_ps(q, w01));
    let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sy) as *const __m128i));
    acc = _mm256_add_ps(acc, _mm256_mul_ps(q, w23));
    let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sz) as *const __m128i));
    acc = _mm256_add_ps(acc, _mm256_mul_ps(q, w45));
    let q = _mm256_cvtph_ps(_mm_loadu_si128(p.add(b + sz + sy) as *const __m128i));
    acc = _mm256_add_ps(acc, _mm256_mul_ps(q, w67));
    _mm_add_ps(_mm256_castps256_ps128(acc), _mm256_extractf128_ps::<1>(acc))
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
    fn avx2_samples_give_the_scalar_bits_lit_and_unlit() {
        if !has_avx2() {
            eprintln!("SKIP: this CPU has no AVX2/F16C");
            return;
        }
        #[target_feature(enable = "avx2,f16c")]
        #[allow(clippy::too_many_arguments)]
        fn simd(
            v: &[f32],
            n: [usize; 3],
            s: &Steps,
            k: u64,
            lut: &Lut,
            shading: Option<(&Phong, &[[u16; 4]])>,
            light: [f32; 3],
        ) -> [[f32; 4]; 4] {
            Avx2::samples4(v, n, s, k, lut, shading, light)
        }
        let n = [9, 7, 8];
        let (mut v, g) = brick(n, 3);
        v[40] = f32::NAN;
        // A table with transparent stretches (zero opacity), a ramp, and opaque entries.
        let table: Vec<[f32; 4]> = (0..1024)
            .map(|i| {
                let x = i as f32 / 1023.0;
                let a = if (0.3..0.45).contains(&x) || x > 0.8 {
                    (x - 0.25).min(1.0)
                } else {
                    0.0
                };
                [x, 1.0 - x, 0.5 * x, a]
            })
            .collect();
        let lut = Lut {
            lo: -1.0,
            scale: 1023.0 / 2.0,
            table,
        };
        let mut lit = 0;
        for (shininess, min_sp) in [(24.0, 1.0), (7.0, 0.5), (12.5, 1.0), (1.0, 1e9)] {
            let p = Phong {
                h: [0.5, 0.25, 1.0],
                min_sp,
                ambient: 0.35,
                diffuse: 0.65,
                specular: 0.25,
                shininess,
            };
            for (q, o) in [[-2.0, 3.0, 1.0], [4.5, 3.5, 4.0], [1.0, 1.0, 7.0]]
                .into_iter()
                .enumerate()
            {
                for dir in 0..27 {
                    let d = [dir % 3, dir / 3 % 3, dir / 9].map(|c| (c as f32 - 1.0) * 0.37 + 0.01);
                    let light = crate::camera::normalise(d);
                    let s = Steps {
                        o,
                        d,
                        base: [-0.25, 0.5, 0.0],
                        t0: 0.3 * q as f32,
                        dt: 0.5,
                    };
                    for k in 0..40 {
                        for shading in [Some((&p, &g[..])), None] {
                            // SAFETY: the features were detected above.
                            let a = unsafe { simd(&v, n, &s, k, &lut, shading, light) };
                            let b = Scalar::samples4(&v, n, &s, k, &lut, shading, light);
                            assert_eq!(
                                a.map(|x| x.map(f32::to_bits)),
                                b.map(|x| x.map(f32::to_bits)),
                                "{o:?} {d:?} {k} {shading:?}"
                            );
                            lit += b.iter().filter(|x| x[3] > 0.0).count();
                        }
                    }
                }
            }
        }
        // Most samples lie in the opaque stretches: the comparison covered shaded colours.
        assert!(lit > 10_000, "{lit} visible samples");
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
