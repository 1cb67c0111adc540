//! The pure per-brick step of the ray marcher: march every ray of a pixel rectangle through
//! one brick's box and composite its samples, front to back, into the pixels' accumulators.
//!
//! Samples sit at `t0 + (k + 1/2) dt` along each ray, with `t0` where the ray enters the volume, so a
//! ray's samples are the same whichever bricks it crosses and in whatever order the bricks are
//! visited; a brick takes the samples inside its box (half-open), so each sample is taken once.

use crate::camera::{dot, Camera, View};
use crate::source::{RenderBrick, VolumeGeom, APRON, CELL};
use crate::tf::Luts;
use crate::{RenderError, Result};
use serde::{Deserialize, Serialize};

/// What a sample's colour and opacity come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// The conventional 1-D intensity transfer function.
    Intensity,
    /// `C = sum_n TF_c,n(p_n) p_n`, `alpha = sum_n TF_a,n(p_n) p_n`.
    Probabilistic,
    /// Classes with `p_n >= tau_n` contribute `TF_c,n(I) p_n` and `TF_a,n(I) p_n`, divided by
    /// the sum `W` of the passing `p_n`.
    ProbIntensity,
}

impl Mode {
    /// True when the mode reads class probabilities.
    pub fn needs_probs(self) -> bool {
        self != Mode::Intensity
    }
}

/// Blinn-Phong coefficients (a headlight: the light sits at the eye).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Shading {
    /// Ambient weight.
    pub ambient: f32,
    /// Diffuse weight.
    pub diffuse: f32,
    /// Specular weight.
    pub specular: f32,
    /// Specular exponent.
    pub shininess: f32,
}

impl Default for Shading {
    fn default() -> Self {
        Shading {
            ambient: 0.35,
            diffuse: 0.65,
            specular: 0.25,
            shininess: 24.0,
        }
    }
}

/// Everything that defines a frame besides the volume and transfer functions; shared by the
/// CPU and GPU renderers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderParams {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// The camera.
    pub camera: Camera,
    /// Rendering mode.
    pub mode: Mode,
    /// Sample spacing in voxels (of the finest spacing).
    pub step: f32,
    /// Gradient shading, or none.
    pub shading: Option<Shading>,
    /// Background colour (RGB in [0, 1]).
    pub background: [f32; 3],
    /// A ray stops once its opacity reaches this.
    pub ert: f32,
}

impl Default for RenderParams {
    fn default() -> Self {
        RenderParams {
            width: 512,
            height: 512,
            camera: Camera::default(),
            mode: Mode::Intensity,
            step: 0.5,
            shading: Some(Shading::default()),
            background: [0.0; 3],
            ert: 0.99,
        }
    }
}

/// Largest image edge accepted.
pub const MAX_SIZE: usize = 16384;

impl RenderParams {
    /// Checks every parameter, with a message naming the bad one.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(RenderError::Param(m));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size {}x{} must be at least 1x1",
                self.width, self.height
            ));
        }
        if self.width > MAX_SIZE || self.height > MAX_SIZE {
            return bad(format!(
                "image size {}x{} exceeds {MAX_SIZE} pixels per side",
                self.width, self.height
            ));
        }
        if !(self.step.is_finite() && (0.01..=16.0).contains(&self.step)) {
            return bad(format!("step {} must be in [0.01, 16] voxels", self.step));
        }
        if !(self.ert.is_finite() && self.ert > 0.0 && self.ert <= 1.0) {
            return bad(format!(
                "early-termination opacity {} must be in (0, 1]",
                self.ert
            ));
        }
        if self.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return bad(format!(
                "background {:?} must be RGB in [0, 1]",
                self.background
            ));
        }
        if let Some(s) = self.shading {
            let ok = [s.ambient, s.diffuse, s.specular]
                .iter()
                .all(|v| v.is_finite() && (0.0..=4.0).contains(v))
                && s.shininess.is_finite()
                && (0.0..=1024.0).contains(&s.shininess);
            if !ok {
                return bad(format!("shading {s:?} out of range"));
            }
        }
        self.camera.validate()
    }
}

/// A pixel's running front-to-back sum: premultiplied RGB and opacity.
pub type Accum = [f32; 4];

/// A frame resolved against a volume: camera basis, step, tables.
pub struct Frame<'a> {
    /// Parameters.
    pub params: RenderParams,
    /// The resolved camera.
    pub view: View,
    /// Volume geometry.
    pub geom: VolumeGeom,
    /// Transfer-function tables.
    pub luts: &'a Luts,
    inv_spacing: [f32; 3],
    centre: [f32; 3],
    /// World distance between samples.
    pub dt: f32,
    /// Opacity-correction exponent: `dt` over one voxel of the finest spacing.
    pub alpha_exp: f32,
}

/// Entry and exit `t` of the ray `o + t d` through the box `lo..hi`, or `None`.
#[inline]
pub fn slab(o: [f32; 3], d: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    for k in 0..3 {
        if d[k].abs() < 1e-20 {
            if o[k] < lo[k] || o[k] >= hi[k] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d[k];
        let (a, b) = ((lo[k] - o[k]) * inv, (hi[k] - o[k]) * inv);
        let (a, b) = if a <= b { (a, b) } else { (b, a) };
        t0 = t0.max(a);
        t1 = t1.min(b);
    }
    (t0 < t1).then_some((t0, t1))
}

/// The 8 voxels and weights of a trilinear sample at local continuous voxel coordinates.
#[inline(always)]
fn corners(p: [f32; 3], dims: [usize; 3]) -> ([usize; 8], [f32; 8]) {
    let mut f = [0.0f32; 3];
    let mut i = [0usize; 3];
    for k in 0..3 {
        // Non-negative after the clamp, so truncation is floor (and needs no libm call).
        let x = p[k].clamp(0.0, dims[k] as f32 - 1.0001);
        i[k] = x as usize;
        f[k] = x - i[k] as f32;
    }
    let (sx, sy) = (1, dims[0]);
    let sz = dims[0] * dims[1];
    let b = i[2] * sz + i[1] * sy + i[0];
    let idx = [
        b,
        b + sx,
        b + sy,
        b + sy + sx,
        b + sz,
        b + sz + sx,
        b + sz + sy,
        b + sz + sy + sx,
    ];
    let (gx, gy, gz) = (1.0 - f[0], 1.0 - f[1], 1.0 - f[2]);
    let w = [
        gx * gy * gz,
        f[0] * gy * gz,
        gx * f[1] * gz,
        f[0] * f[1] * gz,
        gx * gy * f[2],
        f[0] * gy * f[2],
        gx * f[1] * f[2],
        f[0] * f[1] * f[2],
    ];
    (idx, w)
}

/// Trilinear probability of channel `n` (of `ch`) from the corners of a sample.
#[inline(always)]
fn prob_at(probs: &[u8], idx: &[usize; 8], w: &[f32; 8], ch: usize, n: usize) -> f32 {
    let mut s = 0.0;
    for c in 0..8 {
        s += probs[idx[c] * ch + n] as f32 * w[c];
    }
    s * (1.0 / 255.0)
}

#[inline(always)]
fn trilinear(v: &[f32], p: [f32; 3], dims: [usize; 3]) -> f32 {
    let (idx, w) = corners(p, dims);
    let mut s = 0.0;
    for c in 0..8 {
        s += v[idx[c]] * w[c];
    }
    s
}

impl<'a> Frame<'a> {
    /// Resolves `params` for a volume.
    pub fn new(params: RenderParams, geom: VolumeGeom, luts: &'a Luts) -> Result<Self> {
        params.validate()?;
        geom.validate()?;
        let view = params
            .camera
            .view(geom.extent(), params.width, params.height);
        let min_sp = geom.spacing.iter().cloned().fold(f32::MAX, f32::min);
        let dt = params.step * min_sp;
        Ok(Frame {
            params,
            view,
            geom,
            luts,
            inv_spacing: geom.spacing.map(|s| 1.0 / s),
            centre: geom.dims.map(|d| (d as f32 - 1.0) * 0.5),
            dt,
            alpha_exp: params.step,
        })
    }

    /// Reciprocal voxel spacing.
    pub fn inv_spacing(&self) -> [f32; 3] {
        self.inv_spacing
    }

    /// Continuous voxel coordinates of the volume centre.
    pub fn centre(&self) -> [f32; 3] {
        self.centre
    }

    /// Every brick of the grid in front-to-back order.
    pub fn ordered_bricks(&self) -> Vec<[usize; 3]> {
        let g = self.geom.grid();
        let mut order: Vec<([usize; 3], f32)> = Vec::with_capacity(g.iter().product());
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let i = [x, y, z];
                    order.push((i, self.order_key(i)));
                }
            }
        }
        order.sort_by(|a, b| a.1.total_cmp(&b.1));
        order.into_iter().map(|o| o.0).collect()
    }

    /// World position of continuous voxel coordinates.
    pub fn world(&self, v: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|k| (v[k] - self.centre[k]) * self.geom.spacing[k])
    }

    /// The nominal box of brick `index` in voxel coordinates, clipped to the volume.
    pub fn brick_bounds(&self, index: [usize; 3]) -> ([f32; 3], [f32; 3]) {
        let b = self.geom.brick;
        let lo = index.map(|i| (i * b) as f32 - 0.5);
        let hi = [0, 1, 2].map(|k| ((index[k] + 1) * b).min(self.geom.dims[k]) as f32 - 0.5);
        (lo, hi)
    }

    /// Pixels whose rays may cross brick `index` grown by `grow` voxels.
    pub fn footprint(&self, index: [usize; 3], grow: f32) -> Option<[usize; 4]> {
        let (lo, hi) = self.brick_bounds(index);
        self.view.footprint(
            self.world(lo.map(|v| v - grow)),
            self.world(hi.map(|v| v + grow)),
        )
    }

    /// Sort key giving front-to-back order of a grid's bricks: eye distance of the nominal
    /// centre (perspective) or its depth along the view (orthographic). Visiting bricks by
    /// increasing key composites every ray in order.
    pub fn order_key(&self, index: [usize; 3]) -> f32 {
        let b = self.geom.brick as f32;
        let c = self.world(index.map(|i| i as f32 * b + 0.5 * b - 0.5));
        let r = [
            c[0] - self.view.eye[0],
            c[1] - self.view.eye[1],
            c[2] - self.view.eye[2],
        ];
        match self.view.projection {
            crate::Projection::Perspective => dot(r, r),
            crate::Projection::Orthographic => dot(r, self.view.forward),
        }
    }

    /// False when no sample with normalised intensity in `range` can be visible (intensity and
    /// probability-intensity modes; the probabilistic mode always loads).
    pub fn coarse_visible(&self, range: (f32, f32)) -> bool {
        match self.params.mode {
            Mode::Intensity => self.luts.intensity.max_alpha(range.0, range.1) > 0.0,
            Mode::ProbIntensity => self
                .luts
                .classes
                .iter()
                .flatten()
                .any(|c| c.intensity.max_alpha(range.0, range.1) > 0.0),
            Mode::Probabilistic => true,
        }
    }

    /// False when nothing in a loaded brick can be visible (empty-space skipping).
    pub fn visible(&self, b: &RenderBrick) -> bool {
        self.range_visible(b.range, &b.prob_max)
    }

    /// Per cell of a brick: whether a sample inside it can be visible.
    pub fn cell_visibility(&self, b: &RenderBrick) -> Vec<bool> {
        let ch = b.channels;
        b.cell_range
            .iter()
            .enumerate()
            .map(|(i, &r)| self.range_visible(r, &b.cell_prob_max[i * ch..(i + 1) * ch]))
            .collect()
    }

    /// False when no sample whose voxels span intensity `range` and probabilities at most
    /// `prob_max` can be visible.
    pub fn range_visible(&self, range: (f32, f32), prob_max: &[u8]) -> bool {
        let l = self.luts;
        let b = (range, prob_max);
        match self.params.mode {
            Mode::Intensity => l.intensity.max_alpha(b.0 .0, b.0 .1) > 0.0,
            Mode::Probabilistic => l.classes.iter().zip(b.1).any(|(c, &m)| {
                c.as_ref()
                    .is_some_and(|c| m > 0 && c.probability.max_alpha(0.0, m as f32 / 255.0) > 0.0)
            }),
            Mode::ProbIntensity => l.classes.iter().zip(b.1).any(|(c, &m)| {
                c.as_ref().is_some_and(|c| {
                    m > 0
                        && m as f32 / 255.0 >= c.tau
                        && c.intensity.max_alpha(b.0 .0, b.0 .1) > 0.0
                })
            }),
        }
    }

    /// Ray of pixel `(i, j)` in voxel coordinates and its `[t0, t_end)` inside the volume
    /// (world units), or `None` if it misses.
    #[inline]
    pub fn voxel_ray(&self, i: usize, j: usize) -> Option<([f32; 3], [f32; 3], f32, f32)> {
        let (o, d) = self.view.ray(i, j);
        let ov = [0, 1, 2].map(|k| o[k] * self.inv_spacing[k] + self.centre[k]);
        let dv = [0, 1, 2].map(|k| d[k] * self.inv_spacing[k]);
        let hi = self.geom.dims.map(|n| n as f32 - 0.5);
        let (a, b) = slab(ov, dv, [-0.5; 3], hi)?;
        let t0 = a.max(0.0);
        (t0 < b).then_some((ov, dv, t0, b))
    }

    /// Composites brick `b` into pixels `xs` of image row `j` (`row` is the whole row; `mask`,
    /// if given, picks the pixels to march; `cells` is [`Self::cell_visibility`] of `b`).
    /// Returns the samples taken.
    pub fn march_row(
        &self,
        b: &RenderBrick,
        j: usize,
        xs: std::ops::Range<usize>,
        row: &mut [Accum],
        mask: Option<&[bool]>,
        cells: &[bool],
    ) -> u64 {
        let (lo, hi) = self.brick_bounds(b.index);
        let (cx, cxy) = (b.cells[0], b.cells[0] * b.cells[1]);
        let cell_of = |p: [f32; 3]| {
            // Core coordinates of the sample, rounded to the voxel whose cell owns it.
            let c = p.map(|v| (v - APRON as f32 + 0.5).max(0.0) as usize / CELL);
            let c = [
                c[0].min(b.cells[0] - 1),
                c[1].min(b.cells[1] - 1),
                c[2].min(b.cells[2] - 1),
            ];
            (c[2] * cxy + c[1] * cx + c[0], c)
        };
        let base = b.origin.map(|o| o as f32 - APRON as f32);
        let mut samples = 0;
        {
            for (i, px) in row.iter_mut().enumerate().take(xs.end).skip(xs.start) {
                if px[3] >= self.params.ert || mask.is_some_and(|m| !m[i]) {
                    continue;
                }
                let Some((o, d, t0, tend)) = self.voxel_ray(i, j) else {
                    continue;
                };
                let Some((ta, tb)) = slab(o, d, lo, hi) else {
                    continue;
                };
                let (ta, tb) = (ta.max(t0), tb.min(tend));
                if ta >= tb {
                    continue;
                }
                // Midpoint samples: sample k stands for [t0 + k dt, t0 + (k + 1) dt).
                let k0 = ((ta - t0) / self.dt - 0.5).ceil().max(0.0) as u64;
                let k1 = ((tb - t0) / self.dt - 0.5).ceil().max(0.0) as u64;
                let light = self.view.forward_of(d, self.inv_spacing);
                let ol = [o[0] - base[0], o[1] - base[1], o[2] - base[2]];
                let mut k = k0;
                while k < k1 {
                    let t = t0 + (k as f32 + 0.5) * self.dt;
                    let p = [
                        o[0] + d[0] * t - base[0],
                        o[1] + d[1] * t - base[1],
                        o[2] + d[2] * t - base[2],
                    ];
                    samples += 1;
                    k += 1;
                    let (ci, cc) = cell_of(p);
                    if !cells[ci] {
                        // Leap to the first sample past this cell's box.
                        let lo = cc.map(|c| (c * CELL + APRON) as f32 - 0.5);
                        let hi = cc.map(|c| ((c + 1) * CELL + APRON) as f32 - 0.5);
                        if let Some((_, te)) = slab(ol, d, lo, hi) {
                            let next = ((te - t0) / self.dt - 0.5).ceil();
                            if next.is_finite() && next > k as f32 {
                                k = (next as u64).min(k1);
                            }
                        }
                        continue;
                    }
                    let [cr, cg, cb, a] = self.sample(b, p, light);
                    if a <= 0.0 {
                        continue;
                    }
                    let a = 1.0 - (1.0 - a.min(1.0)).powf(self.alpha_exp);
                    let wgt = (1.0 - px[3]) * a;
                    px[0] += wgt * cr;
                    px[1] += wgt * cg;
                    px[2] += wgt * cb;
                    px[3] += wgt;
                    if px[3] >= self.params.ert {
                        break;
                    }
                }
            }
        }
        samples
    }

    /// Colour (shaded) and uncorrected opacity of a sample at local padded coordinates `p`.
    #[inline]
    pub fn sample(&self, b: &RenderBrick, p: [f32; 3], light: [f32; 3]) -> [f32; 4] {
        let dims = b.padded;
        let luts = self.luts;
        let (rgb, a) = match self.params.mode {
            Mode::Intensity => {
                let e = luts.intensity.get(trilinear(&b.intensity, p, dims));
                ([e[0], e[1], e[2]], e[3])
            }
            Mode::Probabilistic => {
                let (idx, w) = corners(p, dims);
                let ch = b.channels;
                let (mut rgb, mut a) = ([0.0f32; 3], 0.0f32);
                for (n, l) in luts.classes.iter().enumerate().take(ch) {
                    let Some(l) = l else { continue };
                    let pn = prob_at(&b.probs, &idx, &w, ch, n);
                    if pn <= 0.0 {
                        continue;
                    }
                    let e = l.probability.get(pn);
                    rgb[0] += e[0] * pn;
                    rgb[1] += e[1] * pn;
                    rgb[2] += e[2] * pn;
                    a += e[3] * pn;
                }
                (rgb, a)
            }
            Mode::ProbIntensity => {
                let (idx, w) = corners(p, dims);
                let ch = b.channels;
                let mut iv = 0.0;
                for c in 0..8 {
                    iv += b.intensity[idx[c]] * w[c];
                }
                let (mut rgb, mut a, mut wsum) = ([0.0f32; 3], 0.0f32, 0.0f32);
                for (n, l) in luts.classes.iter().enumerate().take(ch) {
                    let Some(l) = l else { continue };
                    let pn = prob_at(&b.probs, &idx, &w, ch, n);
                    if pn <= 0.0 || pn < l.tau {
                        continue;
                    }
                    let e = l.intensity.get(iv);
                    rgb[0] += e[0] * pn;
                    rgb[1] += e[1] * pn;
                    rgb[2] += e[2] * pn;
                    a += e[3] * pn;
                    wsum += pn;
                }
                if wsum > 0.0 {
                    let inv = 1.0 / wsum;
                    ([rgb[0] * inv, rgb[1] * inv, rgb[2] * inv], a * inv)
                } else {
                    ([0.0; 3], 0.0)
                }
            }
        };
        if a <= 0.0 {
            return [0.0; 4];
        }
        let rgb = match self.params.shading {
            Some(s) => self.shade(b, p, rgb, light, s),
            None => rgb,
        };
        [rgb[0], rgb[1], rgb[2], a]
    }

    /// Blinn-Phong with a headlight, the normal from the intensity gradient (central
    /// differences of the trilinear field, in world units); flat regions stay unshaded.
    #[inline]
    fn shade(
        &self,
        b: &RenderBrick,
        p: [f32; 3],
        rgb: [f32; 3],
        light: [f32; 3],
        s: Shading,
    ) -> [f32; 3] {
        let dims = b.padded;
        let mut g = [0.0f32; 3];
        for k in 0..3 {
            let (mut a, mut c) = (p, p);
            a[k] += 1.0;
            c[k] -= 1.0;
            g[k] = (trilinear(&b.intensity, a, dims) - trilinear(&b.intensity, c, dims))
                * 0.5
                * self.inv_spacing[k];
        }
        let len = dot(g, g).sqrt();
        let min_sp = self.dt / self.params.step;
        // Also catches NaN: a flat or degenerate gradient leaves the colour unshaded.
        if (len * min_sp).partial_cmp(&1e-4) != Some(std::cmp::Ordering::Greater) {
            return rgb;
        }
        let ndl = (dot(g, light) / len).abs();
        let spec = s.specular * ndl.powf(s.shininess);
        let k = s.ambient + s.diffuse * ndl;
        rgb.map(|c| (c * k + spec).min(1.0))
    }
}

impl View {
    /// The world direction of a voxel-space ray direction, normalised: the headlight direction
    /// used for shading.
    #[inline]
    pub fn forward_of(&self, dv: [f32; 3], inv_spacing: [f32; 3]) -> [f32; 3] {
        let d = [
            dv[0] / inv_spacing[0],
            dv[1] / inv_spacing[1],
            dv[2] / inv_spacing[2],
        ];
        crate::camera::normalise(d)
    }
}
