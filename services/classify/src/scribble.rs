//! Scribbles: strokes drawn on slices, their rasterisation into a sparse label volume, and a
//! deterministic simulator that draws S1–S4 scribbles from a ground-truth label volume.
//!
//! Label convention: 0 = unlabelled, 1..N = ROI classes, `background` (255 by default) =
//! background/other.

use neuvolex_bricks::rng::Rng;
use neuvolex_bricks::BrickError;
use neuvolex_formats::meta::{check_slab_range, Slab, VolumeMeta, VolumeSource};
use neuvolex_formats::DType;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Slice orientation of a stroke.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    /// A sagittal slice (x fixed); points are (y, z).
    X,
    /// A coronal slice (y fixed); points are (x, z).
    Y,
    /// An axial slice (z fixed); points are (x, y).
    Z,
}

impl Axis {
    /// The grid axes (0 = x, 1 = y, 2 = z) of a slice's two in-slice coordinates and of the
    /// slice index.
    pub fn grid_axes(self) -> (usize, usize, usize) {
        match self {
            Axis::X => (1, 2, 0),
            Axis::Y => (0, 2, 1),
            Axis::Z => (0, 1, 2),
        }
    }
}

/// One brush stroke on a slice.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stroke {
    /// Label painted (1..N, or the background label).
    pub class: u32,
    /// Slice orientation.
    pub axis: Axis,
    /// Slice index along `axis`.
    pub slice: usize,
    /// Polyline in in-slice voxel coordinates.
    pub points: Vec<[f32; 2]>,
    /// Brush radius in voxels.
    pub radius: f32,
}

/// Errors of scribble handling.
#[derive(Debug, thiserror::Error)]
pub enum ScribbleError {
    /// A volume could not be read.
    #[error(transparent)]
    Volume(#[from] BrickError),
    /// A stroke that cannot be drawn.
    #[error("stroke {index}: {detail}")]
    Stroke {
        /// Position in the list.
        index: usize,
        /// What is wrong.
        detail: String,
    },
    /// A label volume that cannot be simulated from.
    #[error("{0}")]
    Labels(String),
}

impl From<neuvolex_formats::FormatError> for ScribbleError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        ScribbleError::Volume(e.into())
    }
}

/// Scribbled voxels: sorted linear indices (x fastest) and their labels.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scribbles {
    /// Grid (x, y, z).
    pub dims: [usize; 3],
    /// `(voxel index, label)`, sorted by index, one entry per voxel.
    pub voxels: Vec<(u64, u32)>,
}

impl Scribbles {
    /// Number of scribbled voxels per label.
    pub fn counts(&self) -> std::collections::BTreeMap<u32, u64> {
        let mut m = std::collections::BTreeMap::new();
        for &(_, c) in &self.voxels {
            *m.entry(c).or_insert(0) += 1;
        }
        m
    }

    /// Fraction of the volume that is scribbled.
    pub fn fraction(&self) -> f64 {
        self.voxels.len() as f64 / self.dims.iter().map(|&d| d as f64).product::<f64>()
    }
}

/// Each stroke copied onto the `depth` slices on either side of its own (those inside `dims`):
/// a structure marked on one slice continues through its neighbours. The copies come first,
/// farthest first, so where strokes overlap the user's own strokes win ([`rasterise`] lets later
/// strokes win).
pub fn thicken(strokes: &[Stroke], depth: usize, dims: [usize; 3]) -> Vec<Stroke> {
    // No copy lies farther away than the grid is long.
    let depth = depth.min(dims.into_iter().max().unwrap_or(0));
    let mut out = Vec::with_capacity(strokes.len() * (2 * depth + 1));
    for j in (1..=depth).rev() {
        for s in strokes {
            let n = dims[s.axis.grid_axes().2];
            let near = [s.slice.checked_sub(j), Some(s.slice + j).filter(|&z| z < n)];
            out.extend(
                near.into_iter()
                    .flatten()
                    .map(|slice| Stroke { slice, ..s.clone() }),
            );
        }
    }
    out.extend_from_slice(strokes);
    out
}

/// Most distinct voxels strokes may cover (4 Mi, 16 fully painted 512x512 slices); more is
/// refused rather than held in memory.
pub const MAX_SCRIBBLED_VOXELS: usize = 1 << 22;
/// Most brush-row evaluations one rasterisation may spend (each stamp of the brush costs one
/// per slice row it touches); more is refused rather than tying up a core.
pub const MAX_RASTER_WORK: u64 = 1 << 24;

/// Rasterises strokes (a disc of `radius` swept along each polyline). Later strokes win.
///
/// The brush is stamped every half voxel along each segment; a voxel is painted when its centre
/// lies within `radius` of a stamp. Each stamp's rows are computed as intervals and merged per
/// segment, so a wide brush costs one interval per row instead of one test per pixel. Strokes
/// covering more than [`MAX_SCRIBBLED_VOXELS`] voxels, or costing more than [`MAX_RASTER_WORK`],
/// get an error instead of exhausting memory or time.
pub fn rasterise(strokes: &[Stroke], dims: [usize; 3]) -> Result<Scribbles, ScribbleError> {
    /// Voxel indices hash well with one multiplication (Fibonacci hashing).
    #[derive(Default, Clone, Copy)]
    struct VoxelHasher(u64);
    impl std::hash::Hasher for VoxelHasher {
        fn finish(&self) -> u64 {
            self.0
        }
        fn write(&mut self, bytes: &[u8]) {
            for &b in bytes {
                self.0 = (self.0.rotate_left(8) ^ b as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            }
        }
        fn write_u64(&mut self, v: u64) {
            self.0 = v.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }
    let mut map: std::collections::HashMap<u64, u32, std::hash::BuildHasherDefault<VoxelHasher>> =
        Default::default();
    let mut work = 0u64;
    // (row, first, last) runs of the segment being stamped, and the run still growing on each
    // row (consecutive stamps overlap, so most extend it).
    let mut runs: Vec<(usize, usize, usize)> = Vec::new();
    let mut open: std::collections::HashMap<usize, (usize, usize)> = Default::default();
    const FLUSH: usize = 1 << 20;
    for (si, s) in strokes.iter().enumerate() {
        let bad = |detail: String| ScribbleError::Stroke { index: si, detail };
        let (ua, va, wa) = s.axis.grid_axes();
        if s.slice >= dims[wa] {
            return Err(bad(format!("slice {} outside 0..{}", s.slice, dims[wa])));
        }
        if s.class == 0 {
            return Err(bad("class 0 means unlabelled and cannot be painted".into()));
        }
        if !(s.radius >= 0.0 && s.radius <= 64.0) {
            return Err(bad(format!("brush radius {} must be 0..=64", s.radius)));
        }
        if s.points.is_empty() {
            return Err(bad("no points".into()));
        }
        for p in &s.points {
            if !p[0].is_finite()
                || !p[1].is_finite()
                || p[0] < -0.5
                || p[1] < -0.5
                || p[0] > dims[ua] as f32 - 0.5
                || p[1] > dims[va] as f32 - 0.5
            {
                return Err(bad(format!(
                    "point ({}, {}) outside the {} x {} slice",
                    p[0], p[1], dims[ua], dims[va]
                )));
            }
        }
        let r = s.radius;
        let rr = r * r + 1e-6;
        let (nu, nv) = (dims[ua], dims[va]);
        // Inside the brush centred at (cu, cv): the test every stamp applies to a voxel centre.
        let inside = |u: usize, v: usize, cu: f32, cv: f32| {
            (u as f32 - cu).powi(2) + (v as f32 - cv).powi(2) <= rr
        };
        // Stamps the brush at (cu, cv), adding its runs; returns the rows it cost.
        let stamp = |cu: f32,
                     cv: f32,
                     runs: &mut Vec<(usize, usize, usize)>,
                     open: &mut std::collections::HashMap<usize, (usize, usize)>|
         -> u64 {
            let (u0, u1) = (
                (cu - r).floor().max(0.0) as usize,
                ((cu + r).ceil() as usize).min(nu - 1),
            );
            let (v0, v1) = (
                (cv - r).floor().max(0.0) as usize,
                ((cv + r).ceil() as usize).min(nv - 1),
            );
            for v in v0..=v1 {
                let dv = (v as f32 - cv).powi(2);
                if dv > rr {
                    continue;
                }
                // The covered voxels of a row are one run (the test is monotone in |u - cu|):
                // estimate its ends, then settle them with the exact test.
                let half = (rr - dv).max(0.0).sqrt();
                let mut lo = ((cu - half).ceil().max(u0 as f32) as usize).min(u1);
                let mut hi = ((cu + half).floor().max(u0 as f32) as usize).min(u1);
                while lo > u0 && inside(lo - 1, v, cu, cv) {
                    lo -= 1;
                }
                while lo <= hi && !inside(lo, v, cu, cv) {
                    lo += 1;
                }
                while hi < u1 && inside(hi + 1, v, cu, cv) {
                    hi += 1;
                }
                while hi >= lo && !inside(hi, v, cu, cv) {
                    if hi == 0 {
                        break;
                    }
                    hi -= 1;
                }
                if lo <= hi && inside(lo, v, cu, cv) {
                    match open.get_mut(&v) {
                        Some(o) if lo <= o.1 + 1 && hi + 1 >= o.0 => {
                            *o = (o.0.min(lo), o.1.max(hi));
                        }
                        Some(o) => {
                            runs.push((v, o.0, o.1));
                            *o = (lo, hi);
                        }
                        None => {
                            open.insert(v, (lo, hi));
                        }
                    }
                }
            }
            (v1 - v0 + 1) as u64
        };
        let mut flush = |runs: &mut Vec<(usize, usize, usize)>,
                         open: &mut std::collections::HashMap<usize, (usize, usize)>|
         -> Result<(), ScribbleError> {
            runs.extend(open.drain().map(|(v, (lo, hi))| (v, lo, hi)));
            runs.sort_unstable();
            let mut k = 0;
            while k < runs.len() {
                let (v, lo, mut hi) = runs[k];
                k += 1;
                while k < runs.len() && runs[k].0 == v && runs[k].1 <= hi + 1 {
                    hi = hi.max(runs[k].2);
                    k += 1;
                }
                for u in lo..=hi {
                    let mut c = [0usize; 3];
                    c[ua] = u;
                    c[va] = v;
                    c[wa] = s.slice;
                    map.insert(((c[2] * dims[1] + c[1]) * dims[0] + c[0]) as u64, s.class);
                }
                if map.len() > MAX_SCRIBBLED_VOXELS {
                    return Err(bad(format!(
                        "the strokes cover more than {MAX_SCRIBBLED_VOXELS} voxels; scribble less \
                         (a few strokes per class are enough)"
                    )));
                }
            }
            runs.clear();
            Ok(())
        };
        let too_costly = |work: u64| {
            (work > MAX_RASTER_WORK).then(|| {
                bad(format!(
                    "the strokes are too long or too wide to rasterise (more than \
                     {MAX_RASTER_WORK} brush rows); split them or use a smaller brush"
                ))
            })
        };
        work += stamp(s.points[0][0], s.points[0][1], &mut runs, &mut open);
        for w in s.points.windows(2) {
            let (a, b) = (w[0], w[1]);
            let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            let steps = (len * 2.0).ceil().max(1.0) as usize;
            for k in 1..=steps {
                let t = k as f32 / steps as f32;
                let (cu, cv) = (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
                work += stamp(cu, cv, &mut runs, &mut open);
                if runs.len() >= FLUSH {
                    if let Some(e) = too_costly(work) {
                        return Err(e);
                    }
                    flush(&mut runs, &mut open)?;
                }
            }
            if let Some(e) = too_costly(work) {
                return Err(e);
            }
            flush(&mut runs, &mut open)?;
        }
        if let Some(e) = too_costly(work) {
            return Err(e);
        }
        flush(&mut runs, &mut open)?;
    }
    let mut voxels: Vec<(u64, u32)> = map.into_iter().collect();
    voxels.sort_unstable_by_key(|v| v.0);
    Ok(Scribbles { dims, voxels })
}

/// Scribble density, after the paper: S1 one slice, S2 about 3, S3 about 9, S4 about 27.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Level {
    /// One slice.
    S1,
    /// Three slices.
    S2,
    /// Nine slices.
    S3,
    /// Twenty-seven slices.
    S4,
}

impl Level {
    /// Slices scribbled at this level.
    pub fn slices(self) -> usize {
        match self {
            Level::S1 => 1,
            Level::S2 => 3,
            Level::S3 => 9,
            Level::S4 => 27,
        }
    }
}

impl std::str::FromStr for Level {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_uppercase().as_str() {
            "S1" => Ok(Level::S1),
            "S2" => Ok(Level::S2),
            "S3" => Ok(Level::S3),
            "S4" => Ok(Level::S4),
            _ => Err(format!("unknown scribble level '{s}' (S1, S2, S3, S4)")),
        }
    }
}

/// Reads scribbles from a sparse label volume (NIfTI, NRRD, raw or OME-Zarr; 0 = unlabelled)
/// or a JSON list of strokes (`.json`), on the grid of `like`. The volume is streamed slab by
/// slab; its grid must match and its values must be non-negative integers.
pub fn load_scribbles(path: &Path, like: &VolumeMeta) -> Result<Scribbles, ScribbleError> {
    let is_json = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"));
    if is_json {
        let text = std::fs::read_to_string(path).map_err(|e| BrickError::io(path, e))?;
        let strokes: Vec<Stroke> = serde_json::from_str(&text).map_err(|e| {
            ScribbleError::Labels(format!(
                "{}: not a stroke list ({e}); expected [{{\"class\", \"axis\", \"slice\", \
                 \"points\", \"radius\"}}, ...]",
                path.display()
            ))
        })?;
        return rasterise(&strokes, like.dims).map_err(|e| match e {
            ScribbleError::Stroke { index, detail } => {
                ScribbleError::Labels(format!("{}: stroke {index}: {detail}", path.display()))
            }
            e => e,
        });
    }
    let mut src = neuvolex_bricks::open_volume(path, None)?;
    like.check_same_grid(src.meta(), path)?;
    let dims = like.dims;
    let slice = dims[0] * dims[1];
    let depth = (4 << 20) / slice.max(1) + 1;
    let mut voxels = Vec::new();
    let mut z = 0;
    while z < dims[2] {
        let dz = depth.min(dims[2] - z);
        let v = src.read_slab(z, dz)?.to_f64();
        for (k, &x) in v.iter().enumerate() {
            if x != 0.0 {
                if !(x > 0.0 && x.fract() == 0.0 && x <= u32::MAX as f64) {
                    let i = z * slice + k;
                    return Err(ScribbleError::Labels(format!(
                        "{}: voxel ({}, {}, {}) holds {x}; scribble labels must be \
                         non-negative integers",
                        path.display(),
                        i % dims[0],
                        (i / dims[0]) % dims[1],
                        i / slice
                    )));
                }
                voxels.push(((z * slice + k) as u64, x as u32));
            }
        }
        src.release(z, dz);
        z += dz;
    }
    Ok(Scribbles { dims, voxels })
}

/// Simulator settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimConfig {
    /// Density.
    pub level: Level,
    /// Seed.
    pub seed: u64,
    /// Label written for background strokes.
    pub background: u32,
    /// Erosion of each class region before strokes are placed, in pixels.
    pub erosion: usize,
    /// Brush radius.
    pub radius: f32,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            level: Level::S1,
            seed: 0,
            background: 255,
            erosion: 2,
            radius: 1.0,
        }
    }
}

/// Length of a stroke in a region of `area` pixels: half its diameter, 3 to 60 pixels.
pub fn stroke_length(area: usize) -> f32 {
    (0.5 * (area as f32).sqrt()).clamp(3.0, 60.0)
}

/// The longest straight stroke through `start` that stays inside `inside` (a `w x h` mask), of
/// at most `max_len` pixels each way, along the best of `dirs` (unit vectors): its end points
/// and `start`, rounded to pixel centres.
pub fn longest_stroke(
    inside: &[bool],
    w: usize,
    h: usize,
    start: [f32; 2],
    max_len: f32,
    dirs: &[[f32; 2]],
) -> [[f32; 2]; 3] {
    let [sx, sy] = start;
    let walk = |sign: f32, dx: f32, dy: f32| {
        let mut t = 0.0;
        while t < max_len {
            let (x, y) = (sx + sign * (t + 1.0) * dx, sy + sign * (t + 1.0) * dy);
            let (xi, yi) = (x.round(), y.round());
            if xi < 0.0
                || yi < 0.0
                || xi >= w as f32
                || yi >= h as f32
                || !inside[yi as usize * w + xi as usize]
            {
                break;
            }
            t += 1.0;
        }
        t
    };
    let (mut dx, mut dy, mut a, mut b) = (1.0, 0.0, -1.0, -1.0);
    for &[cx, cy] in dirs {
        let (ca, cb) = (walk(-1.0, cx, cy), walk(1.0, cx, cy));
        if ca + cb > a + b {
            (dx, dy, a, b) = (cx, cy, ca, cb);
        }
    }
    [
        [(sx - a * dx).round(), (sy - a * dy).round()],
        [sx, sy],
        [(sx + b * dx).round(), (sy + b * dy).round()],
    ]
}

/// Erodes a 2-D mask with a (2e+1)^2 square (pixels outside the slice count as outside).
pub fn erode(mask: &[bool], w: usize, h: usize, e: usize) -> Vec<bool> {
    if e == 0 {
        return mask.to_vec();
    }
    let mut tmp = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            tmp[y * w + x] = x >= e && x + e < w && (x - e..=x + e).all(|xx| mask[y * w + xx]);
        }
    }
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            out[y * w + x] = y >= e && y + e < h && (y - e..=y + e).all(|yy| tmp[yy * w + x]);
        }
    }
    out
}

/// Draws S1–S4 scribbles from a ground-truth label volume (0 = background), streaming it one
/// axial slice at a time. Deterministic for a seed.
pub fn simulate(
    labels: &mut dyn VolumeSource,
    cfg: &SimConfig,
) -> Result<(Vec<Stroke>, Scribbles), ScribbleError> {
    let meta = labels.meta().clone();
    let [w, h, nz] = meta.dims;
    // Pass 1: how many foreground classes each slice shows.
    let mut fg_slices = Vec::new();
    let mut richness = Vec::new();
    for z in 0..nz {
        let v = labels.read_slab(z, 1)?.to_f64();
        let mut cls: Vec<u32> = v.iter().filter(|&&x| x > 0.0).map(|&x| x as u32).collect();
        cls.sort_unstable();
        cls.dedup();
        if !cls.is_empty() {
            fg_slices.push(z);
            richness.push(cls.len());
        }
        labels.release(z, 1);
    }
    if fg_slices.is_empty() {
        return Err(ScribbleError::Labels(format!(
            "{}: no foreground label in the volume",
            labels.path().display()
        )));
    }
    let mut rng = Rng(cfg.seed ^ 0x5C21_B0E5);
    // Spread the slices over the foreground range; in each interval take a slice showing the
    // most classes (as a user scribbles where the ROIs are), ties broken by the seed.
    let k = cfg.level.slices().min(fg_slices.len());
    let n = fg_slices.len();
    let mut chosen: Vec<usize> = (0..k)
        .map(|i| {
            let (lo, hi) = (i * n / k, ((i + 1) * n / k).max(i * n / k + 1));
            let best = richness[lo..hi].iter().copied().max().unwrap_or(0);
            let ties: Vec<usize> = (lo..hi).filter(|&j| richness[j] == best).collect();
            fg_slices[ties[rng.below(ties.len())]]
        })
        .collect();
    chosen.dedup();
    let mut strokes = Vec::new();
    for &z in &chosen {
        let v = labels.read_slab(z, 1)?.to_f64();
        let mut classes: Vec<u32> = v.iter().map(|&x| x as u32).collect();
        classes.sort_unstable();
        classes.dedup();
        // A user scribbles every ROI visible on the slice: thin structures (vessels) that
        // vanish under the full erosion are eroded less, never below the brush radius, so
        // every scribbled voxel stays inside its class.
        let min_erosion = (cfg.radius.ceil() as usize).min(cfg.erosion);
        for c in classes {
            let mask: Vec<bool> = v.iter().map(|&x| x as u32 == c).collect();
            let (er, inside) = (min_erosion..=cfg.erosion)
                .rev()
                .map(|e| {
                    let er = erode(&mask, w, h, e);
                    let inside: Vec<usize> = (0..w * h).filter(|&i| er[i]).collect();
                    (er, inside)
                })
                .find(|(_, inside)| !inside.is_empty())
                .unwrap_or_default();
            if inside.is_empty() {
                continue;
            }
            let label = if c == 0 { cfg.background } else { c };
            let n_strokes = if c == 0 { 2 } else { 1 };
            for _ in 0..n_strokes {
                let start = inside[rng.below(inside.len())];
                let (sx, sy) = ((start % w) as f32, (start / w) as f32);
                let max_len = stroke_length(inside.len());
                // A user strokes along the structure: of 8 random directions, the longest.
                let dirs: Vec<[f32; 2]> = (0..8)
                    .map(|_| {
                        let ang = rng.f32() * std::f32::consts::TAU;
                        [ang.cos(), ang.sin()]
                    })
                    .collect();
                let [p0, _, p1] = longest_stroke(&er, w, h, [sx, sy], max_len, &dirs);
                strokes.push(Stroke {
                    class: label,
                    axis: Axis::Z,
                    slice: z,
                    points: vec![p0, [sx, sy], p1],
                    radius: cfg.radius,
                });
            }
        }
    }
    let s = rasterise(&strokes, meta.dims)?;
    Ok((strokes, s))
}

/// A sparse scribble volume as a [`VolumeSource`] (u8, or u16 when labels exceed 255), so it
/// can be written with the NIfTI writer or ingested as a label image.
pub struct ScribbleSource {
    scribbles: Scribbles,
    meta: VolumeMeta,
    name: PathBuf,
}

impl ScribbleSource {
    /// Wraps scribbles on the grid (and geometry) of `like`.
    pub fn new(scribbles: Scribbles, like: &VolumeMeta) -> Self {
        let max = scribbles.voxels.iter().map(|v| v.1).max().unwrap_or(0);
        let dtype = if max <= 255 { DType::U8 } else { DType::U16 };
        let meta = VolumeMeta {
            dtype,
            scaling: None,
            ..like.clone()
        };
        ScribbleSource {
            scribbles,
            meta,
            name: PathBuf::from("<scribbles>"),
        }
    }
}

impl VolumeSource for ScribbleSource {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.name
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> neuvolex_formats::Result<Slab> {
        check_slab_range(&self.meta, &self.name, z0, depth)?;
        let sl = (self.meta.dims[0] * self.meta.dims[1]) as u64;
        let (lo, hi) = (z0 as u64 * sl, (z0 + depth) as u64 * sl);
        let mut vals = vec![0.0f64; (hi - lo) as usize];
        let start = self.scribbles.voxels.partition_point(|v| v.0 < lo);
        for &(i, c) in self.scribbles.voxels[start..]
            .iter()
            .take_while(|v| v.0 < hi)
        {
            vals[(i - lo) as usize] = c as f64;
        }
        Ok(Slab {
            z0,
            depth,
            dtype: self.meta.dtype,
            bytes: neuvolex_formats::dtype::f64_to_bytes(&vals, self.meta.dtype),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_bricks::synth::{Phantom, PhantomChannel, PhantomParams};
    use neuvolex_formats::MemVolume;

    #[test]
    fn rasterise_a_hand_drawn_stroke() {
        let s = Stroke {
            class: 2,
            axis: Axis::Z,
            slice: 1,
            points: vec![[1.0, 1.0], [4.0, 1.0]],
            radius: 0.0,
        };
        let r = rasterise(&[s], [6, 3, 2]).unwrap();
        let idx: Vec<u64> = r.voxels.iter().map(|v| v.0).collect();
        assert_eq!(idx, vec![18 + 6 + 1, 18 + 6 + 2, 18 + 6 + 3, 18 + 6 + 4]);
        assert!(r.voxels.iter().all(|v| v.1 == 2));
        // A sagittal stroke lands on x = slice.
        let s = Stroke {
            class: 1,
            axis: Axis::X,
            slice: 5,
            points: vec![[0.0, 0.0]],
            radius: 0.0,
        };
        assert_eq!(rasterise(&[s], [6, 3, 2]).unwrap().voxels, vec![(5, 1)]);
    }

    #[test]
    fn thickened_strokes_cover_neighbour_slices_and_the_originals_win() {
        let at = |class, axis, slice, x: f32| Stroke {
            class,
            axis,
            slice,
            points: vec![[x, 0.0]],
            radius: 0.0,
        };
        let dims = [4, 1, 5];
        // Class 1 on z = 1 and class 2 on z = 3 at the same pixel; class 3 on x = 3.
        let strokes = [
            at(1, Axis::Z, 1, 0.0),
            at(2, Axis::Z, 3, 0.0),
            at(3, Axis::X, 3, 0.0),
        ];
        let r = rasterise(&thicken(&strokes, 2, dims), dims).unwrap();
        let label = |x: u64, z: u64| r.voxels.iter().find(|v| v.0 == z * 4 + x).map(|v| v.1);
        // z = 0..=4 at x = 0: the user's own slices keep their class; z = 2 lies one slice from
        // both strokes, and the nearer copies come after the farther ones, so the later stroke
        // in the list (class 2) wins there; z = 0 is one from class 1 and three from class 2.
        let column: Vec<_> = (0..5).map(|z| label(0, z)).collect();
        assert_eq!(column, [Some(1), Some(1), Some(2), Some(2), Some(2)]);
        // The sagittal stroke spreads along x only, inside the grid (x = 1, 2, 3).
        assert_eq!(label(1, 0), Some(3));
        assert_eq!(label(2, 0), Some(3));
        assert_eq!(label(3, 0), Some(3));
        // Depth 0 is the strokes as drawn; any depth past the grid covers every slice once.
        assert_eq!(thicken(&strokes, 0, dims), strokes.to_vec());
        assert_eq!(thicken(&strokes, usize::MAX, dims).len(), 5 + 5 + 4);
    }

    /// The per-pixel stamping the interval rasteriser replaces: every stamp tests every pixel
    /// of its bounding box.
    fn rasterise_per_pixel(strokes: &[Stroke], dims: [usize; 3]) -> Vec<(u64, u32)> {
        let mut map = std::collections::BTreeMap::new();
        for s in strokes {
            let (ua, va, wa) = s.axis.grid_axes();
            let r = s.radius;
            let mut stamp = |cu: f32, cv: f32| {
                let u0 = (cu - r).floor().max(0.0) as usize;
                let u1 = ((cu + r).ceil() as usize).min(dims[ua] - 1);
                let v0 = (cv - r).floor().max(0.0) as usize;
                let v1 = ((cv + r).ceil() as usize).min(dims[va] - 1);
                for v in v0..=v1 {
                    for u in u0..=u1 {
                        if (u as f32 - cu).powi(2) + (v as f32 - cv).powi(2) <= r * r + 1e-6 {
                            let mut c = [0usize; 3];
                            c[ua] = u;
                            c[va] = v;
                            c[wa] = s.slice;
                            map.insert(((c[2] * dims[1] + c[1]) * dims[0] + c[0]) as u64, s.class);
                        }
                    }
                }
            };
            stamp(s.points[0][0], s.points[0][1]);
            for w in s.points.windows(2) {
                let (a, b) = (w[0], w[1]);
                let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
                let steps = (len * 2.0).ceil().max(1.0) as usize;
                for k in 1..=steps {
                    let t = k as f32 / steps as f32;
                    stamp(a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
                }
            }
        }
        map.into_iter().collect()
    }

    #[test]
    fn interval_rasteriser_equals_per_pixel_stamping() {
        let mut rng = Rng::new(7);
        let dims = [37, 23, 11];
        for case in 0..400 {
            let n = 1 + rng.below(4);
            let strokes: Vec<Stroke> = (0..n)
                .map(|_| {
                    let axis = [Axis::X, Axis::Y, Axis::Z][rng.below(3)];
                    let (nu, nv, nw) = match axis {
                        Axis::X => (dims[1], dims[2], dims[0]),
                        Axis::Y => (dims[0], dims[2], dims[1]),
                        Axis::Z => (dims[0], dims[1], dims[2]),
                    };
                    let pts = 1 + rng.below(5);
                    // Radii include 0, integers, halves and arbitrary values; points include
                    // voxel centres, half-voxel edges and arbitrary positions.
                    let radius = match rng.below(4) {
                        0 => 0.0,
                        1 => rng.below(6) as f32,
                        2 => rng.below(12) as f32 * 0.5,
                        _ => rng.f32() * 9.0,
                    };
                    let coord = |rng: &mut Rng, n: usize| match rng.below(3) {
                        0 => rng.below(n) as f32,
                        1 => rng.below(n) as f32 - 0.5,
                        _ => rng.f32() * (n as f32 - 0.5),
                    };
                    Stroke {
                        class: 1 + rng.below(3) as u32,
                        axis,
                        slice: rng.below(nw),
                        points: (0..pts)
                            .map(|_| [coord(&mut rng, nu), coord(&mut rng, nv)])
                            .collect(),
                        radius,
                    }
                })
                .collect();
            let fast = rasterise(&strokes, dims).unwrap().voxels;
            assert_eq!(
                fast,
                rasterise_per_pixel(&strokes, dims),
                "case {case}: {strokes:?}"
            );
        }
    }

    #[test]
    fn huge_strokes_are_refused_quickly() {
        let dims = [4096, 4096, 64];
        // 64 full-width zig-zags with the widest brush on every slice: far more than 8 Mi voxels.
        let strokes: Vec<Stroke> = (0..64)
            .map(|z| Stroke {
                class: 1,
                axis: Axis::Z,
                slice: z,
                points: (0..64)
                    .map(|i| [(i % 2) as f32 * 4095.0, i as f32 * 64.0])
                    .collect(),
                radius: 64.0,
            })
            .collect();
        let t = std::time::Instant::now();
        let e = rasterise(&strokes, dims).unwrap_err().to_string();
        assert!(e.contains("more than"), "{e}");
        // A hang guard only (the machine may be loaded): about 1 s on an idle core.
        assert!(t.elapsed().as_secs_f64() < 60.0, "{:?}", t.elapsed());
        // The same path over and over stays within the voxel limit but not the work limit.
        let s = Stroke {
            class: 1,
            axis: Axis::Z,
            slice: 0,
            points: (0..100_000)
                .map(|i| [(i % 2) as f32 * 4095.0, 10.0])
                .collect(),
            radius: 64.0,
        };
        let e = rasterise(&[s], dims).unwrap_err().to_string();
        assert!(e.contains("too long or too wide"), "{e}");
    }

    #[test]
    fn bad_strokes_are_refused() {
        let ok = Stroke {
            class: 1,
            axis: Axis::Z,
            slice: 0,
            points: vec![[0.0, 0.0]],
            radius: 1.0,
        };
        let dims = [4, 4, 2];
        let err = |s: Stroke| rasterise(&[s], dims).unwrap_err().to_string();
        assert!(err(Stroke {
            slice: 2,
            ..ok.clone()
        })
        .contains("outside"));
        assert!(err(Stroke {
            points: vec![[9.0, 0.0]],
            ..ok.clone()
        })
        .contains("outside"));
        assert!(err(Stroke {
            points: vec![[f32::NAN, 0.0]],
            ..ok.clone()
        })
        .contains("outside"));
        assert!(err(Stroke {
            points: vec![],
            ..ok.clone()
        })
        .contains("no points"));
        assert!(err(Stroke {
            class: 0,
            ..ok.clone()
        })
        .contains("unlabelled"));
        assert!(err(Stroke { radius: -1.0, ..ok }).contains("radius"));
    }

    #[test]
    fn simulated_scribbles_lie_inside_their_classes_and_grow_with_the_level() {
        let p = PhantomParams::with_size(64, 0);
        let truth = MemVolume::read_all(&mut Phantom::new(p, PhantomChannel::Labels)).unwrap();
        let mut last = 0;
        for level in [Level::S1, Level::S2, Level::S3, Level::S4] {
            let cfg = SimConfig {
                level,
                ..SimConfig::default()
            };
            let (strokes, s) = simulate(&mut truth.clone(), &cfg).unwrap();
            assert!(!strokes.is_empty());
            for &(i, c) in &s.voxels {
                let gt = truth.bytes[i as usize] as u32;
                assert_eq!(
                    if gt == 0 { 255 } else { gt },
                    c,
                    "voxel {i} painted {c} over truth {gt}"
                );
            }
            assert!(
                s.voxels.len() > last,
                "{level:?} not denser than the previous level"
            );
            last = s.voxels.len();
            if level == Level::S1 {
                assert!(s.fraction() < 0.005, "S1 fraction {}", s.fraction());
                assert!(
                    s.counts().len() >= 3,
                    "S1 should touch several classes: {:?}",
                    s.counts()
                );
            }
        }
        // Deterministic for a seed, different for another.
        let a = simulate(&mut truth.clone(), &SimConfig::default())
            .unwrap()
            .1;
        let b = simulate(&mut truth.clone(), &SimConfig::default())
            .unwrap()
            .1;
        let c = simulate(
            &mut truth.clone(),
            &SimConfig {
                seed: 5,
                ..SimConfig::default()
            },
        )
        .unwrap()
        .1;
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Written out and read back through the NIfTI reader.
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("s.nii.gz");
        neuvolex_formats::nifti::write_nifti(
            &path,
            &mut ScribbleSource::new(a.clone(), &truth.meta),
            8,
        )
        .unwrap();
        let back = MemVolume::read_all(neuvolex_bricks::open_volume(&path, None).unwrap().as_mut())
            .unwrap();
        let nz: Vec<(u64, u32)> = back
            .bytes
            .iter()
            .enumerate()
            .filter(|(_, &v)| v > 0)
            .map(|(i, &v)| (i as u64, v as u32))
            .collect();
        assert_eq!(nz, a.voxels);
    }

    #[test]
    fn empty_labels_are_refused() {
        let mut v = MemVolume::from_f64([4, 4, 4], DType::U8, &[0.0; 64]);
        assert!(simulate(&mut v, &SimConfig::default())
            .unwrap_err()
            .to_string()
            .contains("no foreground"));
    }
}
