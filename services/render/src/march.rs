//! The pure per-brick step of the ray marcher: march every ray of a pixel rectangle through
//! one brick's box and composite its samples, front to back, into the pixels' accumulators.
//!
//! Samples sit at `t0 + (k + 1/2) dt` along each ray, with `t0` where the ray enters the volume, so a
//! ray's samples are the same whichever bricks it crosses and in whatever order the bricks are
//! visited; a brick takes the samples inside its box (half-open), so each sample is taken once.

use crate::camera::{dot, Camera, View};
use crate::kernel::{floor_index, Kernels, Phong, Scalar, Steps, Trilinear};
#[cfg(target_arch = "x86_64")]
use crate::kernel::{has_avx2, Avx2};
use crate::source::{RenderBrick, VolumeGeom, APRON, CELL};
use crate::tf::{Lut, Luts, Visibility};
use crate::{RenderError, Result};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, OnceLock};

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
    /// The mode named `intensity`, `prob` (or `probabilistic`) or `prob-intensity`; without a
    /// name, `Probabilistic` when there are probabilities (or labels) to draw, else `Intensity`.
    pub fn from_name(name: Option<&str>, has_probs: bool) -> Result<Mode, String> {
        match name {
            None if has_probs => Ok(Mode::Probabilistic),
            None | Some("intensity") => Ok(Mode::Intensity),
            Some("prob") | Some("probabilistic") => Ok(Mode::Probabilistic),
            Some("prob-intensity") => Ok(Mode::ProbIntensity),
            Some(o) => Err(format!("'{o}' must be intensity, prob or prob-intensity")),
        }
    }

    /// True when the mode reads class probabilities.
    pub fn needs_probs(self) -> bool {
        self != Mode::Intensity
    }
}

/// Cells per axis of a block in a [`CellMap`]: a ray crosses an invisible block of
/// `COARSE`^3 cells (16^3 voxels) in one step instead of one step per cell.
pub const COARSE: usize = 4;

/// Which cells of a brick may hold a visible sample, and which blocks of [`COARSE`]^3 cells hold
/// any such cell (two-level empty-space skipping inside a brick).
#[derive(Debug, Clone, PartialEq)]
pub struct CellMap {
    /// Per cell, x fastest ([`Frame::cell_visibility`]).
    pub cells: Vec<bool>,
    /// Per block of cells, x fastest: whether any of its cells is visible.
    pub blocks: Vec<bool>,
    /// Blocks per axis.
    pub blocks_per_axis: [usize; 3],
}

impl CellMap {
    /// The map of `cells` (a brick's per-cell visibility) on a grid of `n` cells per axis.
    pub fn new(cells: Vec<bool>, n: [usize; 3]) -> Self {
        let nb = n.map(|c| c.div_ceil(COARSE));
        let mut blocks = vec![false; nb[0] * nb[1] * nb[2]];
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    if cells[(z * n[1] + y) * n[0] + x] {
                        let b = ((z / COARSE) * nb[1] + y / COARSE) * nb[0] + x / COARSE;
                        blocks[b] = true;
                    }
                }
            }
        }
        CellMap {
            cells,
            blocks,
            blocks_per_axis: nb,
        }
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

impl RenderParams {
    /// The view every benchmark and profile renders: a `size` x `size` image, the default
    /// camera turned to azimuth 30 and elevation 15 degrees, default sampling and shading.
    pub fn bench_view(size: usize) -> Self {
        RenderParams {
            width: size,
            height: size,
            camera: Camera {
                azimuth: 30.0,
                elevation: 15.0,
                ..Camera::default()
            },
            ..RenderParams::default()
        }
    }
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
    /// The intensity table with its opacity corrected for the step (intensity mode).
    corrected: Lut,
    /// The shading constants, when shaded.
    phong: Option<Phong>,
    /// Each image row's rays, resolved on first use (shared with other frames of the same
    /// camera, image size and volume).
    rays: Arc<Rays>,
    /// Which table ranges hold a visible entry (empty-space skipping).
    visible: Visible,
}

/// The [`Visibility`] of every table a frame reads.
struct Visible {
    intensity: Visibility,
    /// Per probability channel: its probability table's and its intensity table's.
    classes: Vec<Option<(Visibility, Visibility)>>,
}

impl Visible {
    fn new(luts: &Luts) -> Self {
        Visible {
            intensity: luts.intensity.visibility(),
            classes: luts
                .classes
                .iter()
                .map(|c| {
                    c.as_ref()
                        .map(|c| (c.probability.visibility(), c.intensity.visibility()))
                })
                .collect(),
        }
    }
}

/// The rays of a frame's pixels, row by row, each row resolved on first use. Frames with the
/// same camera, image size and volume geometry draw the same rays, so a renderer hands them
/// from frame to frame ([`Frame::reusing_rays`]): re-rendering a view (a new transfer
/// function, new class probabilities) does not resolve them again.
pub struct Rays {
    camera: Camera,
    size: [usize; 2],
    geom: VolumeGeom,
    rows: Vec<OnceLock<Box<[Ray]>>>,
}

impl Rays {
    fn new(params: &RenderParams, geom: VolumeGeom) -> Self {
        Rays {
            camera: params.camera,
            size: [params.width, params.height],
            geom,
            rows: (0..params.height).map(|_| OnceLock::new()).collect(),
        }
    }
}

/// A pixel's ray in voxel coordinates: origin, direction, its reciprocal, the `[t0, tend)` it
/// spends inside the volume (empty when it misses) and the headlight direction.
#[derive(Debug, Clone, Copy)]
struct Ray {
    o: [f32; 3],
    d: [f32; 3],
    inv: [f32; 3],
    t0: f32,
    tend: f32,
    light: [f32; 3],
}

/// Opacity correction for a step of `s` voxels, `1 - (1 - a)^s`, with the common steps
/// (1, 1/2 and 2: the default and the progressive passes) in closed form.
#[derive(Debug, Clone, Copy)]
enum Correction {
    Identity,
    Sqrt,
    Square,
    Pow(f32),
}

impl Correction {
    fn new(s: f32) -> Self {
        if s == 1.0 {
            Correction::Identity
        } else if s == 0.5 {
            Correction::Sqrt
        } else if s == 2.0 {
            Correction::Square
        } else {
            Correction::Pow(s)
        }
    }

    /// The corrected opacity of `a` (in `(0, 1]` after clamping).
    #[inline(always)]
    fn apply(self, a: f32) -> f32 {
        let t = 1.0 - a.min(1.0);
        match self {
            Correction::Identity => 1.0 - t,
            Correction::Sqrt => 1.0 - t.sqrt(),
            Correction::Square => 1.0 - t * t,
            Correction::Pow(s) => 1.0 - t.powf(s),
        }
    }
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

/// [`slab`] with the direction's reciprocal given (`inv[k] = 1 / d[k]`): the same result.
#[inline(always)]
fn slab_inv(
    o: [f32; 3],
    d: [f32; 3],
    inv: [f32; 3],
    lo: [f32; 3],
    hi: [f32; 3],
) -> Option<(f32, f32)> {
    let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
    for k in 0..3 {
        if d[k].abs() < 1e-20 {
            if o[k] < lo[k] || o[k] >= hi[k] {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo[k] - o[k]) * inv[k], (hi[k] - o[k]) * inv[k]);
        let (a, b) = if a <= b { (a, b) } else { (b, a) };
        t0 = t0.max(a);
        t1 = t1.min(b);
    }
    (t0 < t1).then_some((t0, t1))
}

/// Where a ray's cell walk goes on once its pending samples are taken.
enum Resume {
    /// Past an invisible block: at the first sample from this index on (at least one on).
    Leap(u64),
    /// Past an invisible cell, or to the ray's end in the brick: at this sample index.
    Skip(u64),
}

/// Samples of a ray computed together (the width of [`Kernels::run4`]).
const RUN: usize = 4;

/// Channels that [`probs_at`] interpolates together.
const FAST_CH: usize = 16;

/// Trilinear probabilities (times 255) of every channel (`ch <= FAST_CH`) from the corners of
/// a sample, each summed as [`prob_at`] sums it.
#[inline(always)]
fn probs_at(probs: &[u8], idx: &[usize; 8], w: &[f32; 8], ch: usize) -> [f32; FAST_CH] {
    match ch {
        1 => probs_n::<1>(probs, idx, w),
        2 => probs_n::<2>(probs, idx, w),
        3 => probs_n::<3>(probs, idx, w),
        4 => probs_n::<4>(probs, idx, w),
        5 => probs_n::<5>(probs, idx, w),
        6 => probs_n::<6>(probs, idx, w),
        7 => probs_n::<7>(probs, idx, w),
        8 => probs_n::<8>(probs, idx, w),
        _ => {
            let mut s = [0.0f32; FAST_CH];
            for c in 0..8 {
                let q = &probs[idx[c] * ch..idx[c] * ch + ch];
                for (a, &v) in s.iter_mut().zip(q) {
                    *a += v as f32 * w[c];
                }
            }
            s
        }
    }
}

/// [`probs_at`] for `N` channels.
#[inline(always)]
fn probs_n<const N: usize>(probs: &[u8], idx: &[usize; 8], w: &[f32; 8]) -> [f32; FAST_CH] {
    let mut s = [0.0f32; FAST_CH];
    assert!(idx[7] * N + N <= probs.len(), "sample outside the brick");
    for c in 0..8 {
        // SAFETY: corner c is at most idx[7] (`Trilinear::last`), in bounds as checked.
        let q = unsafe { &*(probs.as_ptr().add(idx[c] * N) as *const [u8; N]) };
        for n in 0..N {
            s[n] += q[n] as f32 * w[c];
        }
    }
    s
}

/// The smallest whole number at or above `x`, as an index: 0 for negative `x`, and about 10^18
/// (past any ray's last sample) for NaN or larger `x`.
#[inline(always)]
fn ceil_index(x: f32) -> u64 {
    // min sends NaN to 10^18, then max sends negatives to 0 (not clamp, which keeps NaN);
    // floats above 2^24 are whole.
    #[allow(clippy::manual_clamp)]
    let x = x.min(1e18).max(0.0);
    // SAFETY: x is finite and in [0, 10^18], within i64 (a plain conversion, without the
    // saturating checks of `as u64`).
    let t = unsafe { x.to_int_unchecked::<i64>() };
    (t + ((t as f32) < x) as i64) as u64
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
        let correction = Correction::new(params.step);
        let mut corrected = luts.intensity.clone();
        for e in &mut corrected.table {
            if e[3] > 0.0 {
                e[3] = correction.apply(e[3]);
            }
        }
        let inv_spacing = geom.spacing.map(|s| 1.0 / s);
        Ok(Frame {
            params,
            view,
            geom,
            luts,
            inv_spacing,
            centre: geom.dims.map(|d| (d as f32 - 1.0) * 0.5),
            dt,
            alpha_exp: params.step,
            corrected,
            phong: params.shading.map(|s| Phong {
                h: inv_spacing.map(|v| 0.5 * v),
                min_sp: dt / params.step,
                ambient: s.ambient,
                diffuse: s.diffuse,
                specular: s.specular,
                shininess: s.shininess,
            }),
            rays: Arc::new(Rays::new(&params, geom)),
            visible: Visible::new(luts),
        })
    }

    /// This frame with the rays of an earlier frame, where they are this frame's rays (same
    /// camera, image size and volume geometry); unchanged otherwise.
    pub fn reusing_rays(mut self, rays: Option<Arc<Rays>>) -> Self {
        if let Some(r) = rays {
            if r.camera == self.params.camera
                && r.size == [self.params.width, self.params.height]
                && r.geom == self.geom
            {
                self.rays = r;
            }
        }
        self
    }

    /// The frame's rays, to hand to the next frame ([`Self::reusing_rays`]).
    pub fn rays(&self) -> Arc<Rays> {
        self.rays.clone()
    }

    /// The intensity table the intensity mode reads: opacity already corrected for the step
    /// (`1 - (1 - a)^step` per entry, as VTK's casters do), so no sample pays for a power.
    pub fn intensity_lut(&self) -> &Lut {
        &self.corrected
    }

    /// The rays of image row `j`, resolved on first use.
    fn row_rays(&self, j: usize) -> &[Ray] {
        self.rays.rows[j].get_or_init(|| {
            (0..self.params.width)
                .map(|i| match self.voxel_ray(i, j) {
                    Some((o, d, t0, tend)) => Ray {
                        o,
                        d,
                        inv: d.map(|v| 1.0 / v),
                        t0,
                        tend,
                        light: self.view.forward_of(d, self.inv_spacing),
                    },
                    None => Ray {
                        o: [0.0; 3],
                        d: [0.0; 3],
                        inv: [0.0; 3],
                        t0: 0.0,
                        tend: 0.0,
                        light: [0.0; 3],
                    },
                })
                .collect()
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
        let (l, v) = (self.luts, &self.visible);
        match self.params.mode {
            Mode::Intensity => v.intensity.any(&l.intensity, range.0, range.1),
            Mode::ProbIntensity => l.classes.iter().zip(&v.classes).any(|(c, cv)| {
                c.as_ref()
                    .zip(cv.as_ref())
                    .is_some_and(|(c, cv)| cv.1.any(&c.intensity, range.0, range.1))
            }),
            Mode::Probabilistic => true,
        }
    }

    /// False when nothing in a loaded brick can be visible (empty-space skipping).
    pub fn visible(&self, b: &RenderBrick) -> bool {
        self.range_visible(b.range, &b.prob_max)
    }

    /// [`Self::cell_visibility`] of a brick with its blocks of [`COARSE`]^3 cells, for
    /// [`Self::march_row`].
    pub fn cell_map(&self, b: &RenderBrick) -> CellMap {
        CellMap::new(self.cell_visibility(b), b.cells)
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
        let (l, v) = (self.luts, &self.visible);
        let classes = || l.classes.iter().zip(&v.classes).zip(prob_max);
        match self.params.mode {
            Mode::Intensity => v.intensity.any(&l.intensity, range.0, range.1),
            Mode::Probabilistic => classes().any(|((c, cv), &m)| {
                c.as_ref()
                    .zip(cv.as_ref())
                    .is_some_and(|(c, cv)| m > 0 && cv.0.any(&c.probability, 0.0, m as f32 / 255.0))
            }),
            Mode::ProbIntensity => classes().any(|((c, cv), &m)| {
                c.as_ref().zip(cv.as_ref()).is_some_and(|(c, cv)| {
                    m > 0 && m as f32 / 255.0 >= c.tau && cv.1.any(&c.intensity, range.0, range.1)
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
    /// if given, picks the pixels to march; `cells` is [`Self::cell_map`] of `b`).
    /// Returns the samples taken.
    pub fn march_row(
        &self,
        b: &RenderBrick,
        j: usize,
        xs: std::ops::Range<usize>,
        row: &mut [Accum],
        mask: Option<&[bool]>,
        cells: &CellMap,
    ) -> u64 {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has the features the function is compiled for.
            return unsafe { self.march_row_avx2(b, j, xs, row, mask, cells) };
        }
        self.march_row_as::<Scalar>(b, j, xs, row, mask, cells)
    }

    /// [`Self::march_row`] compiled for AVX2 and F16C, with the [`Avx2`] kernels (the same
    /// arithmetic in the same order, so the same pixels).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,f16c")]
    fn march_row_avx2(
        &self,
        b: &RenderBrick,
        j: usize,
        xs: std::ops::Range<usize>,
        row: &mut [Accum],
        mask: Option<&[bool]>,
        cells: &CellMap,
    ) -> u64 {
        self.march_row_as::<Avx2>(b, j, xs, row, mask, cells)
    }

    /// [`Self::march_row`] with the kernels `H`.
    #[inline(always)]
    fn march_row_as<H: Kernels>(
        &self,
        b: &RenderBrick,
        j: usize,
        xs: std::ops::Range<usize>,
        row: &mut [Accum],
        mask: Option<&[bool]>,
        cells: &CellMap,
    ) -> u64 {
        let diffs = self.params.shading.map(|_| b.differences());
        match self.params.mode {
            Mode::Intensity => {
                self.march_rows_with(b, j, xs, row, mask, cells, |s, k, _, light| {
                    self.samples_intensity::<H>(b, diffs, s, k, light)
                })
            }
            Mode::Probabilistic | Mode::ProbIntensity => {
                let c = Correction::new(self.alpha_exp);
                self.march_rows_with(b, j, xs, row, mask, cells, |s, k, n, light| {
                    let mut out = [[0.0; 4]; RUN];
                    for (l, o) in out.iter_mut().enumerate().take(n) {
                        *o = self.sample_with::<H>(b, diffs, s.pos(k + l as u64), light);
                        if o[3] > 0.0 {
                            o[3] = c.apply(o[3]);
                        }
                    }
                    out
                })
            }
        }
    }

    /// The march of [`Self::march_row`] with `run(steps, k, n, light)` giving the shaded
    /// colour and corrected opacity of samples `k .. k + n` (`n` at most [`RUN`]) of a ray.
    /// Samples sit at `t0 + (k + 1/2) dt`; the ray walks the brick's cells in order, leaping
    /// over invisible ones whole and sampling visible ones, up to [`RUN`] samples at a time.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn march_rows_with(
        &self,
        b: &RenderBrick,
        j: usize,
        xs: std::ops::Range<usize>,
        row: &mut [Accum],
        mask: Option<&[bool]>,
        map: &CellMap,
        run: impl Fn(&Steps, u64, usize, [f32; 3]) -> [[f32; 4]; RUN],
    ) -> u64 {
        let rays = self.row_rays(j);
        let (lo, hi) = self.brick_bounds(b.index);
        let base = b.origin.map(|o| o as f32 - APRON as f32);
        let (ncx, ncxy) = (b.cells[0], b.cells[0] * b.cells[1]);
        let (nbx, nbxy) = (
            map.blocks_per_axis[0],
            map.blocks_per_axis[0] * map.blocks_per_axis[1],
        );
        let cells = &map.cells;
        let last = [b.cells[0] - 1, b.cells[1] - 1, b.cells[2] - 1];
        let (dt, ert) = (self.dt, self.params.ert);
        let inv_dt = 1.0 / dt;
        let mut samples = 0;
        for i in xs {
            let px = &mut row[i];
            if px[3] >= ert || mask.is_some_and(|m| !m[i]) {
                continue;
            }
            let r = &rays[i];
            if r.t0 >= r.tend {
                continue;
            }
            let Some((ta, tb)) = slab_inv(r.o, r.d, r.inv, lo, hi) else {
                continue;
            };
            let (ta, tb) = (ta.max(r.t0), tb.min(r.tend));
            if ta >= tb {
                continue;
            }
            let (o, d, t0) = (r.o, r.d, r.t0);
            // Midpoint samples: sample k stands for [t0 + k dt, t0 + (k + 1) dt).
            let k0 = ceil_index((ta - t0) / dt - 0.5);
            let k1 = ceil_index((tb - t0) / dt - 0.5);
            let ol = [o[0] - base[0], o[1] - base[1], o[2] - base[2]];
            // The far face of a cell along each axis: one cell on when the ray goes up.
            let up = |a: usize| if d[a] > 0.0 { CELL as f32 } else { 0.0 };
            let exit = [up(0), up(1), up(2)];
            let steps = Steps { o, d, base, t0, dt };
            // One cell on along each axis, in the ray's direction (0 where it is parallel).
            // (Written out per axis: `map` here would be a call.)
            let sign = |a: usize| (d[a] > 0.0) as i64 - (d[a] < 0.0) as i64;
            let dir = [sign(0), sign(1), sign(2)];
            let step = |a: usize| {
                if dir[a] == 0 {
                    f32::INFINITY
                } else {
                    CELL as f32 * r.inv[a].abs()
                }
            };
            let delta = [step(0), step(1), step(2)];
            // Samples k .. pend are visible-cell samples not yet taken (adjacent visible
            // cells make one span, so runs of RUN samples cross cell faces).
            let mut k = k0;
            let mut pend = k0;
            'ray: while k < k1 {
                // Enter the cell of sample k: its index, and the t of its exit face per axis.
                let p = steps.pos(k);
                let mut cc = [0usize; 3];
                let mut tmax = [f32::INFINITY; 3];
                for a in 0..3 {
                    // max then min (not clamp): a NaN coordinate goes to cell 0.
                    #[allow(clippy::manual_clamp)]
                    let c = (floor_index((p[a] - APRON as f32 + 0.5).max(0.0).min(1e9)) / CELL)
                        .min(last[a]);
                    cc[a] = c;
                    if dir[a] != 0 {
                        let face = (c * CELL + APRON) as f32 - 0.5 + exit[a];
                        tmax[a] = (face - ol[a]) * r.inv[a];
                    }
                }
                // Then from cell to cell (a 3-D DDA): the samples before the cell's exit are
                // its samples. Exits found by stepping differ from the exact faces by
                // rounding only, and a sample off by a little at a face still reads only the
                // voxels the cell's range covers (one voxel beyond it each side), so the
                // visibility of the cell holds for it; the reciprocal of `dt` may stand for
                // the division likewise. The walk stops where pending samples must be taken
                // first: before an invisible block or cell, and at the ray's end.
                let resume = loop {
                    let bc = [cc[0] / COARSE, cc[1] / COARSE, cc[2] / COARSE];
                    if !map.blocks[bc[2] * nbxy + bc[1] * nbx + bc[0]] {
                        // A block of invisible cells: leap to its exit at once (the same
                        // rounding argument holds at its faces, which are its cells').
                        let mut tb = f32::INFINITY;
                        for a in 0..3 {
                            let c = if d[a] > 0.0 {
                                ((bc[a] + 1) * COARSE).min(last[a] + 1)
                            } else {
                                bc[a] * COARSE
                            };
                            tb = tb.min(((c * CELL + APRON) as f32 - 0.5 - ol[a]) * r.inv[a]);
                        }
                        samples += 1;
                        break Resume::Leap(ceil_index((tb - t0) * inv_dt - 0.5));
                    }
                    let te = tmax[0].min(tmax[1]).min(tmax[2]);
                    let end = ceil_index((te - t0) * inv_dt - 0.5).clamp(k, k1);
                    if cells[cc[2] * ncxy + cc[1] * ncx + cc[0]] {
                        pend = pend.max(end);
                    } else if pend > k {
                        samples += 1;
                        break Resume::Skip(end);
                    } else {
                        samples += 1;
                        k = k.max(end);
                        pend = k;
                    }
                    if end >= k1 {
                        break Resume::Skip(k1);
                    }
                    // Step across the nearest face; at the brick's boundary the ray stays in
                    // its last cell (what rounding leaves of it there is that cell's).
                    let a = if tmax[0] <= tmax[1] && tmax[0] <= tmax[2] {
                        0
                    } else if tmax[1] <= tmax[2] {
                        1
                    } else {
                        2
                    };
                    let c = cc[a] as i64 + dir[a];
                    if dir[a] == 0 || c < 0 || c > last[a] as i64 {
                        tmax[a] = f32::INFINITY;
                    } else {
                        cc[a] = c as usize;
                        tmax[a] += delta[a];
                    }
                };
                // The pending samples, front to back (one place, so the sampling code is
                // expanded once), then on past the invisible cell or block.
                while k < pend {
                    let n = ((pend - k) as usize).min(RUN);
                    let run = run(&steps, k, n, r.light);
                    for &[cr, cg, cb, a] in &run[..n] {
                        samples += 1;
                        k += 1;
                        if a <= 0.0 {
                            continue;
                        }
                        let wgt = (1.0 - px[3]) * a;
                        px[0] += wgt * cr;
                        px[1] += wgt * cg;
                        px[2] += wgt * cb;
                        px[3] += wgt;
                        if px[3] >= ert {
                            break 'ray;
                        }
                    }
                }
                k = match resume {
                    Resume::Leap(next) if next > k => next.min(k1),
                    Resume::Leap(_) => k + 1,
                    Resume::Skip(end) => k.max(end),
                };
                pend = k;
            }
        }
        samples
    }

    /// Shaded colours and corrected opacities of intensity-mode samples `k .. k + RUN` of a
    /// ray (`diffs`: the brick's central differences when shading), [`Kernels::samples4`].
    #[inline(always)]
    fn samples_intensity<H: Kernels>(
        &self,
        b: &RenderBrick,
        diffs: Option<&[[u16; 4]]>,
        s: &Steps,
        k: u64,
        light: [f32; 3],
    ) -> [[f32; 4]; RUN] {
        let shading = self.phong.as_ref().zip(diffs);
        H::samples4(
            &b.intensity,
            b.padded,
            s,
            k,
            &self.corrected,
            shading,
            light,
        )
    }

    /// Colour (shaded) and uncorrected opacity of a sample at local padded coordinates `p`.
    #[inline]
    pub fn sample(&self, b: &RenderBrick, p: [f32; 3], light: [f32; 3]) -> [f32; 4] {
        let diffs = self.params.shading.map(|_| b.differences());
        self.sample_with::<Scalar>(b, diffs, p, light)
    }

    #[inline(always)]
    fn sample_with<H: Kernels>(
        &self,
        b: &RenderBrick,
        diffs: Option<&[[u16; 4]]>,
        p: [f32; 3],
        light: [f32; 3],
    ) -> [f32; 4] {
        let dims = b.padded;
        let luts = self.luts;
        let t = Trilinear::new(p, dims);
        let (idx, w) = (t.idx(), t.w8());
        let (rgb, a) = match self.params.mode {
            Mode::Intensity => {
                let e = luts.intensity.get(H::value(&b.intensity, &t));
                ([e[0], e[1], e[2]], e[3])
            }
            Mode::Probabilistic => {
                let ch = b.channels;
                let all = (ch <= FAST_CH).then(|| probs_at(&b.probs, &idx, &w, ch));
                let (mut rgb, mut a) = ([0.0f32; 3], 0.0f32);
                for (n, l) in luts.classes.iter().enumerate().take(ch) {
                    let Some(l) = l else { continue };
                    let pn = match &all {
                        Some(s) => s[n] * (1.0 / 255.0),
                        None => prob_at(&b.probs, &idx, &w, ch, n),
                    };
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
                let ch = b.channels;
                let iv = H::value(&b.intensity, &t);
                let all = (ch <= FAST_CH).then(|| probs_at(&b.probs, &idx, &w, ch));
                let (mut rgb, mut a, mut wsum) = ([0.0f32; 3], 0.0f32, 0.0f32);
                for (n, l) in luts.classes.iter().enumerate().take(ch) {
                    let Some(l) = l else { continue };
                    let pn = match &all {
                        Some(s) => s[n] * (1.0 / 255.0),
                        None => prob_at(&b.probs, &idx, &w, ch, n),
                    };
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
        let rgb = match (&self.phong, diffs) {
            (Some(p), Some(g)) => p.shade(H::gradient(g, &t), rgb, light),
            _ => rgb,
        };
        [rgb[0], rgb[1], rgb[2], a]
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ceil_index_is_the_saturating_ceiling() {
        // The saturating conversion it replaces, for every class of input.
        let reference = |x: f32| {
            let x = x.min(1e18);
            let t = x as u64;
            t + ((t as f32) < x) as u64
        };
        for x in [
            0.0,
            -0.0,
            0.5,
            1.0,
            1.0001,
            2.9999,
            -1.5,
            16777215.5,
            16777217.0,
            3.0e9,
            1e18,
            1e19,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE,
        ] {
            assert_eq!(ceil_index(x), reference(x), "{x}");
        }
        assert_eq!(ceil_index(2.5), 3);
        assert_eq!(ceil_index(-3.0), 0);
        assert_eq!(ceil_index(f32::NAN), 1e18f32 as u64);
    }

    #[test]
    fn a_block_is_visible_exactly_when_one_of_its_cells_is() {
        // 9 x 5 x 6 cells: blocks of 4^3 give 3 x 2 x 2, the last ones partial.
        let n = [9, 5, 6];
        let mut cells = vec![false; 9 * 5 * 6];
        let at = |x: usize, y: usize, z: usize| (z * 5 + y) * 9 + x;
        cells[at(8, 4, 5)] = true; // the last, partial block
        cells[at(1, 2, 3)] = true; // the first block
        let m = CellMap::new(cells.clone(), n);
        assert_eq!(m.blocks_per_axis, [3, 2, 2]);
        let on: Vec<usize> = (0..m.blocks.len()).filter(|&i| m.blocks[i]).collect();
        assert_eq!(on, vec![0, (2 + 1) * 3 + 2]);
        assert_eq!(m.cells, cells);
        let empty = CellMap::new(vec![false; 9 * 5 * 6], n);
        assert!(empty.blocks.iter().all(|&b| !b));
    }
}
