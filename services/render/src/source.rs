//! What the renderer reads: bricks of normalised intensity and u8 class probabilities, padded
//! with an apron so every trilinear sample and gradient inside a brick's box reads only that
//! brick.
//!
//! [`StoreSource`] reads a [`BrickStore`] (probabilities from a vector array such as
//! `classes_proba`, or one-hot from a label image); [`MemSource`] wraps arrays in memory.

use crate::{RenderError, Result};
use neuvolex_bricks::lru::Lru;
use neuvolex_bricks::synth::palette;
use neuvolex_bricks::{Brick, BrickError, BrickStore, Normaliser, VectorArray};
use std::sync::{Arc, OnceLock};

/// Voxels of apron on each side of a brick: trilinear samples in the brick's box reach one voxel
/// beyond it, and their central-difference gradients one more.
pub const APRON: usize = 2;

/// Geometry of a bricked volume.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeGeom {
    /// Voxels (x, y, z).
    pub dims: [usize; 3],
    /// Voxel spacing (x, y, z), physical units.
    pub spacing: [f32; 3],
    /// Brick edge in voxels.
    pub brick: usize,
}

impl VolumeGeom {
    /// Bricks per axis.
    pub fn grid(&self) -> [usize; 3] {
        self.dims.map(|d| d.div_ceil(self.brick))
    }

    /// World extent (dims times spacing).
    pub fn extent(&self) -> [f32; 3] {
        [
            self.dims[0] as f32 * self.spacing[0],
            self.dims[1] as f32 * self.spacing[1],
            self.dims[2] as f32 * self.spacing[2],
        ]
    }

    /// Checks the geometry can be rendered.
    pub fn validate(&self) -> Result<()> {
        if self.dims.contains(&0) {
            return Err(RenderError::Input(format!(
                "empty volume: dims {:?}",
                self.dims
            )));
        }
        if self.brick < 4 {
            return Err(RenderError::Input(format!(
                "brick edge {} is too small to render (at least 4)",
                self.brick
            )));
        }
        if self
            .spacing
            .iter()
            .any(|s| !s.is_finite() || *s <= 0.0 || *s > 1e12)
        {
            return Err(RenderError::Input(format!(
                "voxel spacing {:?} must be finite and positive",
                self.spacing
            )));
        }
        Ok(())
    }

    /// Origin and size of brick `index`.
    pub fn brick_box(&self, index: [usize; 3]) -> ([usize; 3], [usize; 3]) {
        let o = index.map(|i| i * self.brick);
        let s = [0, 1, 2].map(|k| self.brick.min(self.dims[k] - o[k]));
        (o, s)
    }
}

/// A brick ready to march: intensity and probabilities over `size + 2 APRON` voxels per axis.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderBrick {
    /// Brick index.
    pub index: [usize; 3],
    /// Voxel origin of the core.
    pub origin: [usize; 3],
    /// Core size.
    pub size: [usize; 3],
    /// Padded size (`size + 2 APRON`).
    pub padded: [usize; 3],
    /// Normalised intensity, x fastest, edge-clamped at the volume border.
    pub intensity: Vec<f32>,
    /// Probability channels per voxel (0 when none were asked for).
    pub channels: usize,
    /// Probabilities in 1/255, voxel-major (channels fastest).
    pub probs: Vec<u8>,
    /// Intensity range over the padded voxels.
    pub range: (f32, f32),
    /// Largest probability of each channel over the padded voxels, in 1/255.
    pub prob_max: Vec<u8>,
    /// Cells of `CELL`^3 core voxels per axis.
    pub cells: [usize; 3],
    /// Per cell: intensity range over every voxel a sample inside the cell reads.
    pub cell_range: Vec<(f32, f32)>,
    /// Per cell and channel: the largest probability a sample inside the cell reads.
    pub cell_prob_max: Vec<u8>,
    /// Per padded voxel, the central differences of the intensity along x, y and z as f16
    /// bits, and a zero lane (one 8-byte load each); made on first use by a shaded frame.
    differences: Derived<Vec<[u16; 4]>>,
}

/// A value derived from a brick's data on first use; equality ignores it.
#[derive(Debug, Clone, Default)]
struct Derived<T>(OnceLock<T>);

impl<T> PartialEq for Derived<T> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// Edge of the cells inside a brick used for fine empty-space skipping.
pub const CELL: usize = 4;

impl RenderBrick {
    /// Builds a brick from padded arrays, computing its ranges.
    pub fn new(
        index: [usize; 3],
        origin: [usize; 3],
        size: [usize; 3],
        intensity: Vec<f32>,
        channels: usize,
        probs: Vec<u8>,
    ) -> Self {
        let padded = size.map(|s| s + 2 * APRON);
        debug_assert_eq!(intensity.len(), padded.iter().product::<usize>());
        let range = intensity
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        let mut prob_max = vec![0u8; channels];
        for px in probs.chunks_exact(channels.max(1)) {
            for (m, &p) in prob_max.iter_mut().zip(px) {
                *m = (*m).max(p);
            }
        }
        // Per cell, the voxels its samples read: one beyond it on each side (trilinear).
        let cells = size.map(|s| s.div_ceil(CELL));
        let ncell = cells.iter().product();
        let mut cell_range = vec![(f32::MAX, f32::MIN); ncell];
        let mut cell_prob_max = vec![0u8; ncell * channels];
        let span = |c: usize, k: usize| {
            let lo = (c * CELL + APRON).saturating_sub(1);
            let hi = ((c + 1) * CELL + APRON + 1).min(padded[k] - 1);
            lo..=hi
        };
        for cz in 0..cells[2] {
            for cy in 0..cells[1] {
                for cx in 0..cells[0] {
                    let ci = (cz * cells[1] + cy) * cells[0] + cx;
                    let (mut a, mut b) = (f32::MAX, f32::MIN);
                    let pm = &mut cell_prob_max[ci * channels..(ci + 1) * channels];
                    for z in span(cz, 2) {
                        for y in span(cy, 1) {
                            let row = (z * padded[1] + y) * padded[0];
                            let xs = span(cx, 0);
                            for &v in &intensity[row + xs.start()..=row + xs.end()] {
                                a = a.min(v);
                                b = b.max(v);
                            }
                            if channels > 0 {
                                for x in xs {
                                    let q = &probs[(row + x) * channels..(row + x + 1) * channels];
                                    for (m, &p) in pm.iter_mut().zip(q) {
                                        *m = (*m).max(p);
                                    }
                                }
                            }
                        }
                    }
                    cell_range[ci] = (a, b);
                }
            }
        }
        RenderBrick {
            index,
            origin,
            size,
            padded,
            intensity,
            channels,
            probs,
            range,
            prob_max,
            cells,
            cell_range,
            cell_prob_max,
            differences: Derived::default(),
        }
    }

    /// Bytes held (with the central differences once they are made).
    pub fn bytes(&self) -> usize {
        let d = self.differences.0.get().map_or(0, |d| d.len() * 8);
        self.intensity.len() * 4 + self.probs.len() + d + 128
    }

    /// Central differences of the intensity at every padded voxel, `[I(x+1) - I(x-1), ...]`
    /// per axis (one-sided at the padded edge, which samples inside the core never reach),
    /// as IEEE half-precision bits, with a zero fourth lane.
    /// The trilinear interpolation of these equals the central difference of the trilinear
    /// field one voxel either side, the gradient shading uses, at a sixth of the reads. Half
    /// precision (a relative error of 2^-11 in each component, so under 0.1 degree in the
    /// normal) halves the bytes a shaded sample reads, which is what bounds the shaded march
    /// (a 36^3 padded brick's differences fit in L2 at 373 KB where f32 took 746 KB).
    pub fn differences(&self) -> &[[u16; 4]] {
        self.differences.0.get_or_init(|| {
            use half::slice::HalfFloatSliceExt;
            let [nx, ny, nz] = self.padded;
            let v = &self.intensity;
            let mut out = vec![[0u16; 4]; v.len()];
            // A row of differences in f32, then converted to half floats at once (8 lanes
            // a step where the CPU has F16C; the same rounding to nearest either way).
            let mut d = vec![0.0f32; nx * 4];
            for z in 0..nz {
                let (z0, z1) = (z.saturating_sub(1), (z + 1).min(nz - 1));
                for y in 0..ny {
                    let (y0, y1) = (y.saturating_sub(1), (y + 1).min(ny - 1));
                    let row = (z * ny + y) * nx;
                    let (ym, yp) = ((z * ny + y0) * nx, (z * ny + y1) * nx);
                    let (zm, zp) = ((z0 * ny + y) * nx, (z1 * ny + y) * nx);
                    for (x, e) in d.chunks_exact_mut(4).enumerate() {
                        let (x0, x1) = (x.saturating_sub(1), (x + 1).min(nx - 1));
                        e[0] = v[row + x1] - v[row + x0];
                        e[1] = v[yp + x] - v[ym + x];
                        e[2] = v[zp + x] - v[zm + x];
                    }
                    let o: &mut [half::f16] = bytemuck::cast_slice_mut(&mut out[row..row + nx]);
                    o.convert_from_f32_slice(&d);
                }
            }
            out
        })
    }
}

/// A probability channel: class id, display colour and whether it is the background class.
pub type ChannelClass = (u32, [f32; 3], bool);

/// Anything the renderer can draw from.
pub trait BrickSource: Send + Sync {
    /// Volume geometry.
    fn geom(&self) -> VolumeGeom;
    /// Raw-to-normalised intensity map (never degenerate).
    fn normaliser(&self) -> Normaliser;
    /// The probability channels (empty when the source has none).
    fn classes(&self) -> Vec<ChannelClass>;
    /// A normalised intensity range covering every voxel a sample inside brick `index` reads
    /// (its core and neighbours), if known without loading it.
    fn coarse_range(&self, index: [usize; 3]) -> Option<(f32, f32)>;
    /// Loads brick `index`, with probabilities when `probs` is true.
    fn load(&self, index: [usize; 3], probs: bool) -> Result<RenderBrick>;
    /// Forgets anything cached about `bricks`, whose data changed.
    fn invalidate(&self, _bricks: &[[usize; 3]]) {}
}

macro_rules! forward_source {
    ($($t:tt)*) => {
        impl<T: BrickSource + ?Sized> BrickSource for $($t)* {
            fn geom(&self) -> VolumeGeom {
                (**self).geom()
            }
            fn normaliser(&self) -> Normaliser {
                (**self).normaliser()
            }
            fn classes(&self) -> Vec<ChannelClass> {
                (**self).classes()
            }
            fn coarse_range(&self, index: [usize; 3]) -> Option<(f32, f32)> {
                (**self).coarse_range(index)
            }
            fn load(&self, index: [usize; 3], probs: bool) -> Result<RenderBrick> {
                (**self).load(index, probs)
            }
            fn invalidate(&self, bricks: &[[usize; 3]]) {
                (**self).invalidate(bricks)
            }
        }
    };
}

forward_source!(&T);
forward_source!(Arc<T>);

/// `norm` unless it is degenerate (a constant volume): then one raw unit above the value.
pub fn render_normaliser(norm: Normaliser, min: f64) -> Normaliser {
    let w = norm.hi - norm.lo;
    if w.is_finite() && w > 0.0 {
        norm
    } else {
        let lo = if min.is_finite() { min } else { 0.0 };
        Normaliser {
            lo,
            hi: lo + lo.abs().max(1.0),
        }
    }
}

/// Brick `index` and its face, edge and corner neighbours inside a grid of `grid` bricks.
pub fn neighbourhood(index: [usize; 3], grid: [usize; 3]) -> impl Iterator<Item = [usize; 3]> {
    (0..27).filter_map(move |i| {
        let n = [
            (index[0] + i % 3).wrapping_sub(1),
            (index[1] + i / 3 % 3).wrapping_sub(1),
            (index[2] + i / 9).wrapping_sub(1),
        ];
        (0..3).all(|k| n[k] < grid[k]).then_some(n)
    })
}

/// A neighbour's core and its size.
type Core<T> = (Arc<Vec<T>>, [usize; 3]);

/// Assembles a padded brick of `ch` channels from the cores of it and its neighbours
/// (`core(index)` gives a core, voxel-major, or `None` for zeros), edge-clamped at the border.
pub fn assemble<T: Copy + Default>(
    geom: &VolumeGeom,
    index: [usize; 3],
    ch: usize,
    mut core: impl FnMut([usize; 3]) -> Result<Option<Arc<Vec<T>>>>,
) -> Result<Vec<T>> {
    let (o, s) = geom.brick_box(index);
    let p = s.map(|v| v + 2 * APRON);
    let b = geom.brick;
    // Per axis: for each padded position, (neighbour offset 0..3, local coordinate).
    let axis = |k: usize| -> Vec<(usize, usize)> {
        (0..p[k])
            .map(|i| {
                let g = (o[k] as isize + i as isize - APRON as isize)
                    .clamp(0, geom.dims[k] as isize - 1) as usize;
                (g / b + 1 - index[k], g % b)
            })
            .collect()
    };
    let (xs, ys, zs) = (axis(0), axis(1), axis(2));
    let grid = geom.grid();
    let mut cores: [Option<Core<T>>; 27] = std::array::from_fn(|_| None);
    for dz in 0..3 {
        for dy in 0..3 {
            for dx in 0..3 {
                let n = [
                    (index[0] + dx).wrapping_sub(1),
                    (index[1] + dy).wrapping_sub(1),
                    (index[2] + dz).wrapping_sub(1),
                ];
                if (0..3).any(|k| n[k] >= grid[k]) {
                    continue;
                }
                let used = xs.iter().any(|a| a.0 == dx)
                    && ys.iter().any(|a| a.0 == dy)
                    && zs.iter().any(|a| a.0 == dz);
                if !used {
                    continue;
                }
                if let Some(c) = core(n)? {
                    cores[(dz * 3 + dy) * 3 + dx] = Some((c, geom.brick_box(n).1));
                }
            }
        }
    }
    let mut out = vec![T::default(); p[0] * p[1] * p[2] * ch];
    let mut w = 0;
    for &(dz, lz) in &zs {
        for &(dy, ly) in &ys {
            for &(dx, lx) in &xs {
                if let Some((c, cs)) = &cores[(dz * 3 + dy) * 3 + dx] {
                    let r = ((lz * cs[1] + ly) * cs[0] + lx) * ch;
                    out[w..w + ch].copy_from_slice(&c[r..r + ch]);
                }
                w += ch;
            }
        }
    }
    Ok(out)
}

/// Where a store's class probabilities come from.
pub enum ProbSource {
    /// A u8 or f16 vector array of per-class probabilities (e.g. `classes_proba` written by
    /// `neuvolex classify`); bricks it never wrote (skipped as empty) are zero.
    Vectors {
        /// The array.
        array: Box<VectorArray>,
        /// Class id of each channel.
        ids: Vec<u32>,
        /// The background id.
        background: Option<u32>,
    },
    /// One-hot probabilities from a label image (ground truth, or a classification).
    Labels {
        /// Label image name under `labels/`.
        name: String,
        /// Ids drawn, one channel each.
        ids: Vec<u32>,
    },
    /// One-hot probabilities from labels in memory (x fastest), not saved in the store.
    Memory {
        /// The label of every voxel.
        labels: Arc<Vec<u32>>,
        /// Ids drawn, one channel each.
        ids: Vec<u32>,
    },
}

/// A [`BrickStore`] as a render source.
pub struct StoreSource {
    store: Arc<BrickStore>,
    norm: Normaliser,
    probs: Option<ProbSource>,
    colors: Vec<(u32, [u8; 3])>,
    cores: Lru<[usize; 3], Option<Arc<Vec<u8>>>>,
}

impl StoreSource {
    /// Intensity only.
    pub fn new(store: Arc<BrickStore>) -> Self {
        let info = store.info();
        let norm = render_normaliser(store.normaliser(), info.stats.min);
        // Colours of any label image's classes, for channels that match them.
        let mut colors = Vec::new();
        for l in &info.labels {
            for c in store.label_classes(l).unwrap_or_default() {
                if !colors.iter().any(|(id, _)| *id == c.id) {
                    colors.push((c.id, c.color));
                }
            }
        }
        StoreSource {
            store,
            norm,
            probs: None,
            colors,
            cores: Lru::new(256 << 20),
        }
    }

    /// With probabilities from vector array `name` (its metadata must list the class ids, as
    /// `neuvolex classify` writes them).
    pub fn with_vectors(mut self, name: &str) -> Result<Self> {
        let array = self.store.open_vectors(name)?;
        let extra = &array.info().extra;
        let ids: Vec<u32> = extra
            .get("labels")
            .and_then(|v| v.as_array())
            .map(|a| {
                a.iter()
                    .filter_map(|x| x.as_u64().map(|x| x as u32))
                    .collect()
            })
            .unwrap_or_default();
        if ids.len() != array.info().channels {
            return Err(RenderError::Input(format!(
                "{}: vector array '{name}' has {} channels but its metadata lists {} class ids; \
                 it is not a class-probability array",
                self.store.root().display(),
                array.info().channels,
                ids.len()
            )));
        }
        let background = extra
            .get("background")
            .and_then(|v| v.as_u64())
            .map(|b| b as u32);
        self.probs = Some(ProbSource::Vectors {
            array: Box::new(array),
            ids,
            background,
        });
        self.cores.clear();
        Ok(self)
    }

    /// With one-hot probabilities from label image `name`, one channel per class it lists
    /// (0 is not drawn).
    pub fn with_labels(mut self, name: &str) -> Result<Self> {
        if !self.store.info().labels.iter().any(|l| l == name) {
            return Err(RenderError::Input(format!(
                "{}: no label image '{name}' (have {:?})",
                self.store.root().display(),
                self.store.info().labels
            )));
        }
        let mut ids: Vec<u32> = self
            .store
            .label_classes(name)?
            .iter()
            .map(|c| c.id)
            .filter(|&i| i != 0)
            .collect();
        if ids.is_empty() {
            // No class table: the distinct non-zero values of the image are its classes.
            let mut seen = std::collections::BTreeSet::new();
            for b in self.store.bricks() {
                for v in self.store.read_labels_box(name, b.origin, b.size)? {
                    if v != 0 {
                        seen.insert(v);
                    }
                }
                if seen.len() > 255 {
                    return Err(RenderError::Input(format!(
                        "{}: label image '{name}' has over 255 distinct values; too many classes to draw",
                        self.store.root().display()
                    )));
                }
            }
            ids = seen.into_iter().collect();
        }
        ids.sort_unstable();
        ids.dedup();
        if ids.is_empty() {
            return Err(RenderError::Input(format!(
                "{}: label image '{name}' holds no labelled voxel",
                self.store.root().display()
            )));
        }
        self.probs = Some(ProbSource::Labels {
            name: name.to_string(),
            ids,
        });
        self.cores.clear();
        Ok(self)
    }

    /// With one-hot probabilities from `labels` (one per voxel, x fastest; 0 is unlabelled),
    /// held in memory: nothing is written into the store.
    pub fn with_label_array(mut self, labels: Arc<Vec<u32>>) -> Result<Self> {
        let dims = self.store.info().dims;
        if labels.len() != dims.iter().product::<usize>() {
            return Err(RenderError::Input(format!(
                "labels: {} voxels, the store has {dims:?} (x, y, z)",
                labels.len()
            )));
        }
        let ids: std::collections::BTreeSet<u32> =
            labels.iter().copied().filter(|&v| v != 0).collect();
        if ids.len() > 255 {
            return Err(RenderError::Input(format!(
                "labels: {} distinct values; too many classes to draw",
                ids.len()
            )));
        }
        if ids.is_empty() {
            return Err(RenderError::Input(
                "labels: no labelled voxel to draw".into(),
            ));
        }
        self.probs = Some(ProbSource::Memory {
            labels,
            ids: ids.into_iter().collect(),
        });
        self.cores.clear();
        Ok(self)
    }

    /// The store.
    pub fn store(&self) -> &BrickStore {
        &self.store
    }

    fn brick(&self, index: [usize; 3]) -> Result<Brick> {
        Ok(self.store.brick(index)?)
    }

    fn prob_core(&self, index: [usize; 3]) -> Result<Option<Arc<Vec<u8>>>> {
        let Some(ps) = &self.probs else {
            return Ok(None);
        };
        self.cores.get_or_try_insert(&index, || {
            let b = self.brick(index)?;
            let v: Option<Vec<u8>> = match ps {
                ProbSource::Vectors { array, .. } => match array.read_brick(&b) {
                    Ok(v) => Some(
                        v.iter()
                            .map(|p| (p.clamp(0.0, 1.0) * 255.0).round() as u8)
                            .collect(),
                    ),
                    Err(BrickError::MissingChunk { .. }) => None,
                    Err(e) => return Err(e.into()),
                },
                ProbSource::Labels { .. } | ProbSource::Memory { .. } => {
                    let (l, ids) = match ps {
                        ProbSource::Labels { name, ids } => {
                            (self.store.read_labels_box(name, b.origin, b.size)?, ids)
                        }
                        ProbSource::Memory { labels, ids } => {
                            let dims = self.store.info().dims;
                            let mut l = Vec::with_capacity(b.voxels());
                            for row in b.rows(dims) {
                                l.extend_from_slice(&labels[row..row + b.size[0]]);
                            }
                            (l, ids)
                        }
                        ProbSource::Vectors { .. } => unreachable!("matched above"),
                    };
                    let mut v = vec![0u8; l.len() * ids.len()];
                    for (i, &x) in l.iter().enumerate() {
                        if let Some(c) = ids.iter().position(|&id| id == x) {
                            v[i * ids.len() + c] = 255;
                        }
                    }
                    Some(v)
                }
            };
            let cost = v.as_ref().map_or(16, |v| v.len() + 16);
            Ok((v.map(Arc::new), cost))
        })
    }
}

fn unit_rgb(c: [u8; 3]) -> [f32; 3] {
    c.map(|v| v as f32 / 255.0)
}

impl BrickSource for StoreSource {
    fn geom(&self) -> VolumeGeom {
        let i = self.store.info();
        VolumeGeom {
            dims: i.dims,
            spacing: i.spacing.map(|s| s as f32),
            brick: i.brick,
        }
    }

    fn normaliser(&self) -> Normaliser {
        self.norm
    }

    fn classes(&self) -> Vec<ChannelClass> {
        let (ids, bg) = match &self.probs {
            None => return Vec::new(),
            Some(ProbSource::Vectors {
                ids, background, ..
            }) => (ids.clone(), *background),
            Some(ProbSource::Labels { ids, .. } | ProbSource::Memory { ids, .. }) => {
                (ids.clone(), None)
            }
        };
        ids.iter()
            .map(|&id| {
                let c = self
                    .colors
                    .iter()
                    .find(|(i, _)| *i == id)
                    .map_or_else(|| palette(id), |c| c.1);
                (id, unit_rgb(c), Some(id) == bg)
            })
            .collect()
    }

    fn invalidate(&self, bricks: &[[usize; 3]]) {
        for b in bricks {
            self.cores.remove(b);
        }
    }

    fn coarse_range(&self, index: [usize; 3]) -> Option<(f32, f32)> {
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for n in neighbourhood(index, self.geom().grid()) {
            let (a, b) = self.store.brick_range(&self.brick(n).ok()?);
            lo = lo.min(a);
            hi = hi.max(b);
        }
        Some((self.norm.apply(lo as f32), self.norm.apply(hi as f32)))
    }

    fn load(&self, index: [usize; 3], probs: bool) -> Result<RenderBrick> {
        let b = self.brick(index)?;
        let h = self.store.read_halo(&b, APRON)?;
        let intensity: Vec<f32> = h.data.iter().map(|&v| self.norm.apply(v)).collect();
        let (ch, p) = match (&self.probs, probs) {
            (Some(ps), true) => {
                let ch = match ps {
                    ProbSource::Vectors { ids, .. }
                    | ProbSource::Labels { ids, .. }
                    | ProbSource::Memory { ids, .. } => ids.len(),
                };
                let geom = self.geom();
                (ch, assemble(&geom, index, ch, |n| self.prob_core(n))?)
            }
            _ => (0, Vec::new()),
        };
        Ok(RenderBrick::new(index, b.origin, b.size, intensity, ch, p))
    }
}

/// A volume in memory as a render source (tests, generated scenes, previews).
pub struct MemSource {
    geom: VolumeGeom,
    norm: Normaliser,
    values: Arc<Vec<f32>>,
    classes: Vec<ChannelClass>,
    probs: Arc<Vec<u8>>,
    ranges: Vec<(f32, f32)>,
}

impl MemSource {
    /// Wraps `values` (raw, x fastest) and optional probabilities (1/255, voxel-major, one
    /// channel per entry of `classes`). The normaliser maps the value range to [0, 1].
    pub fn new(
        geom: VolumeGeom,
        values: Vec<f32>,
        classes: Vec<ChannelClass>,
        probs: Vec<u8>,
    ) -> Result<Self> {
        geom.validate()?;
        let n: usize = geom.dims.iter().product();
        if values.len() != n {
            return Err(RenderError::Input(format!(
                "{} values for a {:?} grid ({n} voxels)",
                values.len(),
                geom.dims
            )));
        }
        if probs.len() != n * classes.len() {
            return Err(RenderError::Input(format!(
                "{} probabilities for {n} voxels x {} classes",
                probs.len(),
                classes.len()
            )));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(RenderError::Input(format!(
                "value {} at voxel {i} is not finite",
                values[i]
            )));
        }
        let (lo, hi) = values.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| {
            (a.min(v as f64), b.max(v as f64))
        });
        let norm = render_normaliser(Normaliser { lo, hi }, lo);
        let mut s = MemSource {
            geom,
            norm,
            values: Arc::new(values),
            classes,
            probs: Arc::new(probs),
            ranges: Vec::new(),
        };
        let g = geom.grid();
        let mut ranges = Vec::with_capacity(g.iter().product());
        for z in 0..g[2] {
            for y in 0..g[1] {
                for x in 0..g[0] {
                    let (o, sz) = geom.brick_box([x, y, z]);
                    let (mut a, mut b) = (f32::MAX, f32::MIN);
                    for k in 0..sz[2] {
                        for j in 0..sz[1] {
                            let r = ((o[2] + k) * geom.dims[1] + o[1] + j) * geom.dims[0] + o[0];
                            for &v in &s.values[r..r + sz[0]] {
                                a = a.min(v);
                                b = b.max(v);
                            }
                        }
                    }
                    ranges.push((a, b));
                }
            }
        }
        s.ranges = ranges;
        Ok(s)
    }

    /// Replaces the normaliser (e.g. to match a store's).
    pub fn with_normaliser(mut self, norm: Normaliser) -> Self {
        self.norm = render_normaliser(norm, norm.lo);
        self
    }

    /// Replaces the probabilities of every voxel (same layout as [`Self::new`]).
    pub fn set_probs(&mut self, probs: Vec<u8>) -> Result<()> {
        if probs.len() != self.probs.len() {
            return Err(RenderError::Input(format!(
                "{} probabilities, expected {}",
                probs.len(),
                self.probs.len()
            )));
        }
        self.probs = Arc::new(probs);
        Ok(())
    }

    fn core<T: Copy>(&self, data: &[T], ch: usize, index: [usize; 3]) -> Arc<Vec<T>> {
        let (o, s) = self.geom.brick_box(index);
        let d = self.geom.dims;
        let mut v = Vec::with_capacity(s.iter().product::<usize>() * ch);
        for z in 0..s[2] {
            for y in 0..s[1] {
                let r = (((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0]) * ch;
                v.extend_from_slice(&data[r..r + s[0] * ch]);
            }
        }
        Arc::new(v)
    }
}

impl BrickSource for MemSource {
    fn geom(&self) -> VolumeGeom {
        self.geom
    }

    fn normaliser(&self) -> Normaliser {
        self.norm
    }

    fn classes(&self) -> Vec<ChannelClass> {
        self.classes.clone()
    }

    fn coarse_range(&self, index: [usize; 3]) -> Option<(f32, f32)> {
        let g = self.geom.grid();
        let (mut lo, mut hi) = (f32::MAX, f32::MIN);
        for n in neighbourhood(index, g) {
            let (a, b) = self.ranges[(n[2] * g[1] + n[1]) * g[0] + n[0]];
            lo = lo.min(a);
            hi = hi.max(b);
        }
        Some((self.norm.apply(lo), self.norm.apply(hi)))
    }

    fn load(&self, index: [usize; 3], probs: bool) -> Result<RenderBrick> {
        let g = self.geom.grid();
        if (0..3).any(|k| index[k] >= g[k]) {
            return Err(RenderError::Input(format!(
                "brick {index:?} outside the {g:?} grid"
            )));
        }
        let raw = assemble(&self.geom, index, 1, |n| {
            Ok(Some(self.core(&self.values, 1, n)))
        })?;
        let intensity = raw.iter().map(|&v| self.norm.apply(v)).collect();
        let ch = if probs { self.classes.len() } else { 0 };
        let p = if ch > 0 {
            assemble(&self.geom, index, ch, |n| {
                Ok(Some(self.core(&self.probs, ch, n)))
            })?
        } else {
            Vec::new()
        };
        let (o, s) = self.geom.brick_box(index);
        Ok(RenderBrick::new(index, o, s, intensity, ch, p))
    }
}
