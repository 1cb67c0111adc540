//! The out-of-core brick store: an OME-Zarr 0.5 / Zarr v3 hierarchy written with zarrs.
//!
//! Layout of `X.zarr`:
//! - `zarr.json`: root group; `ome.multiscales` plus `neuvolex` attributes ([`StoreInfo`]).
//! - `0`, `1`, ...: intensity pyramid (z, y, x), chunked in bricks, zstd; level 0 keeps the
//!   source type (f32 when the source has intensity scaling), coarser levels are f32 means.
//! - `labels/NAME/0..`: OME label images (mode-downsampled pyramids).
//! - `neuvolex/brick_min`, `neuvolex/brick_max`: per-brick value range (f64, z, y, x grid).
//! - `neuvolex/vectors/NAME`: per-voxel vectors (z, y, x, c) in f16 or u8, one chunk a brick.
//!
//! A store is a local or shared-POSIX path or an `s3://bucket/prefix.zarr` URL
//! ([`StoreLocation`]); every read and write goes through its [`Backend`].
//!
//! On a file system, stores are written under a temporary name and renamed when complete; on
//! S3 the root metadata is written last. Either way `neuvolex.complete` is set last, so an
//! interrupted ingest never leaves a store that opens as complete.
//!
//! Stage outputs (label images, vector arrays) are written as a new *generation* `vN` beside
//! the current one and published by a [`Commit`]: the new `zarr.json` of each output's node,
//! which points at the generation, for every output of a step at once (one atomic write of a
//! commit record); older generations are deleted after that. A reader sees the previous
//! complete outputs or the new ones, never a mix:
//! - `labels/NAME/zarr.json`: the OME image-label group; its multiscales datasets are
//!   `vN/0`, `vN/1`, ...
//! - `neuvolex/vectors/NAME/zarr.json`: a group whose `neuvolex.current` names the array
//!   `neuvolex/vectors/NAME/vN`.

use crate::backend::Backend;
use crate::commit::{group_doc, Commit};
use crate::derived::{HaloBrick, Normaliser};
use crate::done::{layout_of, DoneMarkers, StageTag};
use crate::error::{BrickError, Result};
use crate::location::StoreLocation;
use crate::lock::WriterLock;
use crate::lru::Lru;
use crate::omezarr::{
    check_chunks_exist, multiscales, read_bytes, read_node, write_bytes, write_slab_chunks,
    zarr_dtype, ZArray,
};
use crate::stats::{FineHistogram, StatsAccumulator, VolumeStats};
use neuvolex_formats::dtype::DType;
use neuvolex_formats::meta::{VolumeMeta, VolumeSource};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{Array, ArrayBuilder};
use zarrs::group::GroupBuilder;
use zarrs::storage::ReadableWritableListableStorage;

/// Version of the store layout written by this crate.
pub const STORE_VERSION: u32 = 1;

/// What to do with NaN/Inf voxel values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum NonFinitePolicy {
    /// Fail with [`BrickError::NonFinite`] naming the first offending voxel (default).
    #[default]
    Reject,
    /// Replace with 0 and count them in [`VolumeStats::non_finite_replaced`].
    Zero,
}

/// Options for [`ingest`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IngestOptions {
    /// Brick edge in voxels (a power of two, 8..=512). Default 64.
    pub brick: usize,
    /// Bricks per shard edge (Zarr sharding codec); `None` stores one file per brick.
    pub shard: Option<usize>,
    /// zstd level (1..=22). Default 3.
    pub zstd_level: i32,
    /// NaN/Inf handling.
    pub non_finite: NonFinitePolicy,
    /// Replace an existing output.
    pub overwrite: bool,
    /// Number of pyramid levels including level 0; `None` picks until the coarsest level's
    /// largest axis is below 32 voxels or one brick.
    pub levels: Option<usize>,
}

impl Default for IngestOptions {
    fn default() -> Self {
        IngestOptions {
            brick: 64,
            shard: None,
            zstd_level: 3,
            non_finite: NonFinitePolicy::Reject,
            overwrite: false,
            levels: None,
        }
    }
}

/// Progress of a long store operation.
#[derive(Debug, Clone, PartialEq)]
pub enum Progress {
    /// A named stage began; `total` units of work follow.
    Stage {
        /// Stage name.
        name: &'static str,
        /// Units of work in the stage.
        total: u64,
    },
    /// `done` units of the current stage are finished.
    Advance {
        /// Units done so far.
        done: u64,
    },
}

/// The `neuvolex` attributes of a store's root group.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoreInfo {
    /// Layout version.
    pub version: u32,
    /// True once every array has been written.
    pub complete: bool,
    /// Voxel grid (x, y, z).
    pub dims: [usize; 3],
    /// Brick edge.
    pub brick: usize,
    /// Bricks per shard edge, if sharded.
    pub shard: Option<usize>,
    /// Grid of every pyramid level (x, y, z).
    pub levels: Vec<[usize; 3]>,
    /// Type of level 0.
    pub dtype: DType,
    /// Type in the source file.
    pub source_dtype: DType,
    /// The source file.
    pub source: String,
    /// Voxel spacing (x, y, z).
    pub spacing: [f64; 3],
    /// Voxel -> world affine.
    pub affine: [[f64; 4]; 4],
    /// Intensity statistics.
    pub stats: VolumeStats,
    /// Default empty-brick threshold: a brick whose maximum is below it holds only background.
    pub background: f64,
    /// Label images under `labels/`.
    #[serde(default)]
    pub labels: Vec<String>,
}

impl StoreInfo {
    /// Bricks per axis (x, y, z).
    pub fn grid(&self) -> [usize; 3] {
        grid_of(self.dims, self.brick)
    }
}

fn grid_of(dims: [usize; 3], brick: usize) -> [usize; 3] {
    [
        dims[0].div_ceil(brick),
        dims[1].div_ceil(brick),
        dims[2].div_ceil(brick),
    ]
}

/// One brick of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Brick {
    /// Brick index (x, y, z).
    pub index: [usize; 3],
    /// Voxel origin (x, y, z).
    pub origin: [usize; 3],
    /// Voxel extent (x, y, z); smaller at the far borders.
    pub size: [usize; 3],
}

impl Brick {
    /// Number of voxels.
    pub fn voxels(&self) -> usize {
        self.size.iter().product()
    }
}

fn zyx(origin: [usize; 3], size: [usize; 3]) -> Vec<Range<u64>> {
    (0..3)
        .rev()
        .map(|i| origin[i] as u64..(origin[i] + size[i]) as u64)
        .collect()
}

fn build_array(
    storage: &ReadableWritableListableStorage,
    root: &Path,
    path: &str,
    shape_zyx: Vec<u64>,
    chunk_zyx: Vec<u64>,
    dtype: DType,
    opts: &IngestOptions,
) -> Result<ZArray> {
    let names: Vec<Option<String>> = vec![Some("z".into()), Some("y".into()), Some("x".into())];
    let (outer, inner) = match opts.shard {
        Some(s) if s > 1 => {
            let mut o = chunk_zyx.clone();
            for v in o.iter_mut().take(3) {
                *v *= s as u64;
            }
            (o, Some(chunk_zyx))
        }
        _ => (chunk_zyx, None),
    };
    let mut b = ArrayBuilder::new(shape_zyx, outer, zarr_dtype(dtype), 0u8);
    // `c.z.y.x` keys: one directory per array instead of one per chunk row (far fewer inodes).
    b.chunk_key_encoding_default_separator(zarrs::array::ChunkKeySeparator::Dot);
    b.bytes_to_bytes_codecs(vec![Arc::new(zarrs::array::codec::ZstdCodec::new(
        opts.zstd_level.clamp(1, 22),
        false,
    ))]);
    if let Some(i) = inner {
        b.subchunk_shape(i);
    }
    b.dimension_names(Some(names));
    let array = b
        .build(storage.clone(), path)
        .map_err(|e| BrickError::zarr(root, e))?;
    array
        .store_metadata()
        .map_err(|e| BrickError::zarr(root, e))?;
    Ok(array)
}

/// Number of pyramid levels for a grid.
fn pick_levels(dims: [usize; 3], brick: usize, want: Option<usize>) -> usize {
    let max_levels = brick.trailing_zeros() as usize + 1;
    if let Some(w) = want {
        return w.clamp(1, max_levels);
    }
    let mut n = 1;
    let mut d = *dims.iter().max().unwrap_or(&1);
    while n < max_levels && d > 32.max(brick / 2) {
        d = d.div_ceil(2);
        n += 1;
    }
    n
}

/// Chunk (brick) extent (x, y, z) of pyramid level `k`: `brick` in x and y, `brick >> k` in z,
/// so that every level-0 slab of `brick` slices fills whole chunks at every level.
pub fn level_chunk(brick: usize, k: usize) -> [usize; 3] {
    [brick, brick, (brick >> k).max(1)]
}

fn level_dims(dims: [usize; 3], k: usize) -> [usize; 3] {
    let f = 1usize << k;
    [
        dims[0].div_ceil(f),
        dims[1].div_ceil(f),
        dims[2].div_ceil(f),
    ]
}

/// 2x mean downsampling of a slab (x fastest) of `dims` into `ceil(dims/2)`; border cells
/// average only the voxels that exist.
pub fn downsample_mean(src: &[f32], dims: [usize; 3]) -> Vec<f32> {
    let od = [
        dims[0].div_ceil(2),
        dims[1].div_ceil(2),
        dims[2].div_ceil(2),
    ];
    let mut out = vec![0.0f32; od[0] * od[1] * od[2]];
    for z in 0..od[2] {
        for y in 0..od[1] {
            for x in 0..od[0] {
                let (mut s, mut n) = (0.0f64, 0u32);
                for dz in 0..2 {
                    for dy in 0..2 {
                        for dx in 0..2 {
                            let (sx, sy, sz) = (2 * x + dx, 2 * y + dy, 2 * z + dz);
                            if sx < dims[0] && sy < dims[1] && sz < dims[2] {
                                s += src[(sz * dims[1] + sy) * dims[0] + sx] as f64;
                                n += 1;
                            }
                        }
                    }
                }
                out[(z * od[1] + y) * od[0] + x] = (s / n as f64) as f32;
            }
        }
    }
    out
}

/// 2x mean downsampling of a native slab, two slices at a time, with scaling applied.
fn downsample_slab(slab: &neuvolex_formats::meta::Slab, meta: &VolumeMeta) -> Vec<f32> {
    let (nx, ny) = (meta.dims[0], meta.dims[1]);
    let sl = nx * ny * slab.dtype.size();
    let mut out = Vec::with_capacity(nx.div_ceil(2) * ny.div_ceil(2) * slab.depth.div_ceil(2));
    let mut z = 0;
    while z < slab.depth {
        let d = 2.min(slab.depth - z);
        let pair = neuvolex_formats::meta::Slab {
            z0: 0,
            depth: d,
            dtype: slab.dtype,
            bytes: slab.bytes[z * sl..(z + d) * sl].to_vec(),
        };
        out.extend(downsample_mean(&pair.to_f32_scaled(meta), [nx, ny, d]));
        z += d;
    }
    out
}

/// 2x mode downsampling for labels; ties go to the smallest label.
pub fn downsample_mode(src: &[u32], dims: [usize; 3]) -> Vec<u32> {
    let od = [
        dims[0].div_ceil(2),
        dims[1].div_ceil(2),
        dims[2].div_ceil(2),
    ];
    let mut out = vec![0u32; od[0] * od[1] * od[2]];
    let mut vals = [0u32; 8];
    for z in 0..od[2] {
        for y in 0..od[1] {
            for x in 0..od[0] {
                let mut n = 0;
                for dz in 0..2 {
                    for dy in 0..2 {
                        for dx in 0..2 {
                            let (sx, sy, sz) = (2 * x + dx, 2 * y + dy, 2 * z + dz);
                            if sx < dims[0] && sy < dims[1] && sz < dims[2] {
                                vals[n] = src[(sz * dims[1] + sy) * dims[0] + sx];
                                n += 1;
                            }
                        }
                    }
                }
                let v = &mut vals[..n];
                v.sort_unstable();
                let (mut best, mut best_n, mut i) = (v[0], 0, 0);
                while i < n {
                    let mut j = i;
                    while j < n && v[j] == v[i] {
                        j += 1;
                    }
                    if j - i > best_n {
                        best = v[i];
                        best_n = j - i;
                    }
                    i = j;
                }
                out[(z * od[1] + y) * od[0] + x] = best;
            }
        }
    }
    out
}

fn validate_options(out: &Path, opts: &IngestOptions) -> Result<()> {
    if !(8..=512).contains(&opts.brick) || !opts.brick.is_power_of_two() {
        return Err(BrickError::InvalidArgument(format!(
            "{}: brick size {} must be a power of two in 8..=512",
            out.display(),
            opts.brick
        )));
    }
    if let Some(s) = opts.shard {
        if s == 0 || s > 64 {
            return Err(BrickError::InvalidArgument(format!(
                "shard {s} must be 1..=64 bricks per edge"
            )));
        }
    }
    Ok(())
}

/// Moves `tmp` to `out` (replacing `out` only when `overwrite`), keeping the old store until
/// the new one is in place. On Linux a replacement is one atomic exchange of the two names
/// (`renameat2(RENAME_EXCHANGE)`), so `out` is at every instant the old store or the new one,
/// even if the process is killed; the old store then sits under `tmp` and is deleted.
fn commit_dir(tmp: &Path, out: &Path, overwrite: bool) -> Result<()> {
    if out.exists() {
        if !overwrite {
            return Err(BrickError::Exists {
                path: out.to_path_buf(),
            });
        }
        match exchange(tmp, out) {
            Ok(()) => {
                let _ = std::fs::remove_dir_all(tmp);
                return Ok(());
            }
            Err(e) => tracing::debug!("atomic exchange unavailable ({e}); two renames"),
        }
        let old = out.with_file_name(format!(
            ".{}.old-{}",
            out.file_name().unwrap_or_default().to_string_lossy(),
            std::process::id()
        ));
        std::fs::rename(out, &old).map_err(|e| BrickError::io(out, e))?;
        std::fs::rename(tmp, out).map_err(|e| BrickError::io(out, e))?;
        let _ = std::fs::remove_dir_all(&old);
    } else {
        std::fs::rename(tmp, out).map_err(|e| BrickError::io(out, e))?;
    }
    Ok(())
}

/// Atomically swaps the names `a` and `b` (both must exist).
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let ca = CString::new(a.as_os_str().as_bytes())?;
    let cb = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: both arguments are valid NUL-terminated paths that outlive the call.
    let r = unsafe {
        libc::renameat2(
            libc::AT_FDCWD,
            ca.as_ptr(),
            libc::AT_FDCWD,
            cb.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Atomically swaps the names `a` and `b`: not available on this platform.
#[cfg(not(target_os = "linux"))]
fn exchange(_a: &Path, _b: &Path) -> std::io::Result<()> {
    Err(std::io::ErrorKind::Unsupported.into())
}

/// Deletes what killed writers left beside `out`: `.NAME.partial-PID` and `.NAME.old-PID`
/// folders whose process is gone (Linux; elsewhere they are left).
fn remove_stale_siblings(out: &Path) {
    let (Some(dir), Some(name)) = (out.parent(), out.file_name()) else {
        return;
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let name = name.to_string_lossy();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let f = e.file_name().to_string_lossy().into_owned();
        // `.NAME.partial-PID`, `.NAME.old-PID`, or with a sequence number `-PID-N`.
        let pid = [".partial-", ".old-"].iter().find_map(|tag| {
            f.strip_prefix(&format!(".{name}{tag}"))
                .and_then(|p| p.split('-').next())
                .and_then(|p| p.parse::<u32>().ok())
        });
        if let Some(pid) = pid {
            let gone = cfg!(target_os = "linux") && !Path::new(&format!("/proc/{pid}")).exists();
            if gone && pid != std::process::id() {
                tracing::info!(path = %e.path().display(), "removing what an interrupted writer left");
                let p = e.path();
                let _ = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
            }
        }
    }
}

/// Replaces the file at `path` with `bytes` atomically: written to a hidden sibling
/// temporary (`.NAME.partial-PID-N`), synced, then renamed over it, so a crash leaves the
/// previous file or the new one, never a part. Temporaries that killed writers left beside
/// it are removed first.
pub fn replace_file(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    use std::sync::atomic::{AtomicU64, Ordering};
    static SEQ: AtomicU64 = AtomicU64::new(0);
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| BrickError::io(d, e))?;
    }
    remove_stale_siblings(path);
    let t = neuvolex_formats::nifti::tmp_name(path);
    let tmp = t.with_file_name(format!(
        "{}-{}",
        t.file_name().unwrap_or_default().to_string_lossy(),
        SEQ.fetch_add(1, Ordering::SeqCst)
    ));
    let r = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if r.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    r.map_err(|e| BrickError::io(path, e))
}

/// One streaming pass over slabs: statistics, per-brick ranges and the NaN/Inf policy.
///
/// Scanners of disjoint parts of a volume merge ([`Scanner::merge`]) into exactly the scanner
/// of the whole, whatever the split, the order or the thread count: counts, extremes and
/// per-brick ranges combine exactly, and the shifted f64 sums of wide and float types are kept
/// per z-slice and added in slice order by [`Scanner::finish`]. This is what lets a cluster
/// ingest (slab tasks on several workers) write the same statistics as a local one.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Scanner {
    meta: VolumeMeta,
    brick: usize,
    grid: [usize; 3],
    acc: StatsAccumulator,
    bmin: Vec<f64>,
    bmax: Vec<f64>,
    /// Shifted (sum, sum of squares) of each z-slice (wide and float types).
    slice_sums: Vec<[f64; 2]>,
}

impl Scanner {
    /// A scanner for a volume of `meta` with bricks of edge `brick`. The shift of the shifted
    /// sums is the first value of the first slab added.
    pub fn new(meta: &VolumeMeta, brick: usize) -> Self {
        let grid = grid_of(meta.dims, brick);
        let nb = grid.iter().product::<usize>();
        Scanner {
            meta: meta.clone(),
            brick,
            grid,
            acc: StatsAccumulator::new(meta.dtype, meta.scaling),
            bmin: vec![f64::INFINITY; nb],
            bmax: vec![f64::NEG_INFINITY; nb],
            slice_sums: vec![[0.0; 2]; meta.dims[2]],
        }
    }

    /// A scanner for a part of a volume whose first raw value (after the NaN/Inf policy, see
    /// [`first_raw_value`]) is `first_raw`: every part of one volume must use the same.
    pub fn with_shift(meta: &VolumeMeta, brick: usize, first_raw: f64) -> Self {
        let mut s = Scanner::new(meta, brick);
        s.acc.set_shift_if_unset(first_raw);
        s
    }

    /// Adds the scanner of another, disjoint part of the same volume (same grid and shift).
    pub fn merge(&mut self, o: Scanner) -> Result<()> {
        if o.meta.dims != self.meta.dims || o.brick != self.brick {
            return Err(BrickError::InvalidArgument(format!(
                "statistics of a {:?} volume in {}-voxel bricks cannot merge into those of a {:?} \
                 volume in {}-voxel bricks",
                o.meta.dims, o.brick, self.meta.dims, self.brick
            )));
        }
        self.acc.merge(o.acc);
        for (i, (lo, hi)) in o.bmin.into_iter().zip(o.bmax).enumerate() {
            self.bmin[i] = self.bmin[i].min(lo);
            self.bmax[i] = self.bmax[i].max(hi);
        }
        // Parts are disjoint in z: a slice's sums come from one part (the other adds 0).
        for (a, b) in self.slice_sums.iter_mut().zip(o.slice_sums) {
            a[0] += b[0];
            a[1] += b[1];
        }
        Ok(())
    }

    /// Applies the NaN/Inf policy to `slab` (rewriting it for [`NonFinitePolicy::Zero`]) and
    /// accumulates it. Slabs must arrive front to back.
    pub fn add_slab(
        &mut self,
        slab: &mut neuvolex_formats::meta::Slab,
        policy: NonFinitePolicy,
        path: &Path,
    ) -> Result<()> {
        let meta = &self.meta;
        let slice = meta.slice_len();
        if meta.dtype.is_float() {
            let vals = slab.to_f64();
            let bad: Vec<usize> = vals
                .iter()
                .enumerate()
                .filter(|(_, v)| !v.is_finite())
                .map(|(i, _)| i)
                .collect();
            if !bad.is_empty() {
                match policy {
                    NonFinitePolicy::Reject => {
                        let i = bad[0];
                        return Err(BrickError::NonFinite {
                            path: path.to_path_buf(),
                            count: bad.len() as u64,
                            x: i % meta.dims[0],
                            y: (i / meta.dims[0]) % meta.dims[1],
                            z: slab.z0 + i / slice,
                        });
                    }
                    NonFinitePolicy::Zero => {
                        let mut vals = vals;
                        for &i in &bad {
                            vals[i] = 0.0;
                        }
                        self.acc.non_finite_replaced += bad.len() as u64;
                        slab.bytes = neuvolex_formats::dtype::f64_to_bytes(&vals, meta.dtype);
                    }
                }
            }
        }
        let (b, grid) = (self.brick, self.grid);
        let esize = meta.dtype.size();
        if slab.depth == 0 {
            return Ok(());
        }
        let mut first = [0.0f64];
        neuvolex_formats::dtype::bytes_to_f64(&slab.bytes[..esize], meta.dtype, &mut first);
        self.acc.set_shift_if_unset(first[0]);
        // Brick layers touched by this slab; each worker keeps its own ranges for them.
        let bz0 = slab.z0 / b;
        let layers = (slab.z0 + slab.depth - 1) / b - bz0 + 1;
        let per_layer = grid[0] * grid[1];
        let workers = rayon::current_num_threads().clamp(1, slab.depth);
        let per = slab.depth.div_ceil(workers);
        use rayon::prelude::*;
        type Part = (StatsAccumulator, Vec<f64>, Vec<f64>, Vec<[f64; 2]>);
        let parts: Vec<Part> = slab
            .bytes
            .par_chunks(per * slice * esize)
            .enumerate()
            .map(|(w, bytes)| {
                let mut acc = self.acc.fork();
                let mut lmin = vec![f64::INFINITY; layers * per_layer];
                let mut lmax = vec![f64::NEG_INFINITY; layers * per_layer];
                let mut sums = Vec::new();
                let mut raw = vec![0.0f64; slice];
                let mut ints = vec![0i32; slice];
                let small = meta.dtype.is_small_int();
                for (dz, sl) in bytes.chunks_exact(slice * esize).enumerate() {
                    let layer = (slab.z0 + w * per + dz) / b - bz0;
                    let mut range = |i: usize, lo: f64, hi: f64| {
                        lmin[i] = lmin[i].min(lo);
                        lmax[i] = lmax[i].max(hi);
                    };
                    if small {
                        neuvolex_formats::dtype::small_ints_to_i32(sl, meta.dtype, &mut ints);
                        acc.add_ints(&ints);
                        for y in 0..meta.dims[1] {
                            let row = &ints[y * meta.dims[0]..(y + 1) * meta.dims[0]];
                            for (bx, seg) in row.chunks(b).enumerate() {
                                let (lo, hi) = seg
                                    .iter()
                                    .fold((i32::MAX, i32::MIN), |(a, c), &v| (a.min(v), c.max(v)));
                                range(
                                    layer * per_layer + (y / b) * grid[0] + bx,
                                    lo as f64,
                                    hi as f64,
                                );
                            }
                        }
                    } else {
                        neuvolex_formats::dtype::bytes_to_f64(sl, meta.dtype, &mut raw);
                        acc.add_raw(&raw);
                        // Per-slice sums: added in slice order at the end, whatever the split.
                        let (a, q) = acc.take_sums();
                        sums.push([a, q]);
                        for y in 0..meta.dims[1] {
                            let row = &raw[y * meta.dims[0]..(y + 1) * meta.dims[0]];
                            for (bx, seg) in row.chunks(b).enumerate() {
                                let (lo, hi) = seg
                                    .iter()
                                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, c), &v| {
                                        (a.min(v), c.max(v))
                                    });
                                range(layer * per_layer + (y / b) * grid[0] + bx, lo, hi);
                            }
                        }
                    }
                }
                (acc, lmin, lmax, sums)
            })
            .collect();
        for (w, (acc, lmin, lmax, sums)) in parts.into_iter().enumerate() {
            self.acc.merge(acc);
            for (dz, s) in sums.into_iter().enumerate() {
                self.slice_sums[slab.z0 + w * per + dz] = s;
            }
            for i in 0..layers * per_layer {
                if lmin[i] > lmax[i] {
                    continue;
                }
                // Scaling may be negative: map both ends.
                let (lo, hi) = (meta.scale(lmin[i]), meta.scale(lmax[i]));
                let g = bz0 * per_layer + i;
                self.bmin[g] = self.bmin[g].min(lo.min(hi));
                self.bmax[g] = self.bmax[g].max(lo.max(hi));
            }
        }
        Ok(())
    }

    /// True when percentiles need a second pass over the data (types wider than 16 bits).
    pub fn needs_second_pass(&self) -> bool {
        self.acc.needs_second_pass()
    }

    /// Value range seen so far.
    pub fn range(&self) -> (f64, f64) {
        self.acc.range()
    }

    /// Statistics plus per-brick minima and maxima (grid order, x fastest).
    pub fn finish(mut self, fine: Option<FineHistogram>) -> (VolumeStats, Vec<f64>, Vec<f64>) {
        for [a, q] in &self.slice_sums {
            self.acc.add_sums(*a, *q);
        }
        (self.acc.finish(fine), self.bmin, self.bmax)
    }
}

/// The first raw value of a volume as [`Scanner::add_slab`] sees it (a NaN or Inf counts as 0,
/// as the `zero` policy writes it; the `reject` policy fails on it anyway): the shift that
/// every part's [`Scanner::with_shift`] must use. `slab` is the volume's first slab.
pub fn first_raw_value(slab: &neuvolex_formats::meta::Slab) -> f64 {
    let esize = slab.dtype.size();
    if slab.bytes.len() < esize {
        return 0.0;
    }
    let mut first = [0.0f64];
    neuvolex_formats::dtype::bytes_to_f64(&slab.bytes[..esize], slab.dtype, &mut first);
    if first[0].is_finite() {
        first[0]
    } else {
        0.0
    }
}

/// Result of [`scan_volume`]: what `neuvolex info` reports for a file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ScanReport {
    /// Intensity statistics (non-finite values counted and treated as 0).
    pub stats: VolumeStats,
    /// Brick edge used for occupancy.
    pub brick: usize,
    /// Bricks per axis.
    pub grid: [usize; 3],
    /// Empty-brick threshold (as [`StoreInfo::background`]).
    pub background: f64,
    /// Bricks whose maximum reaches the threshold.
    pub occupied: usize,
}

/// Streams a source once (twice for wide types) and reports statistics and brick occupancy.
pub fn scan_volume(
    source: &mut dyn VolumeSource,
    brick: usize,
    progress: &mut dyn FnMut(Progress),
) -> Result<ScanReport> {
    let meta = source.meta().clone();
    let path = source.path().to_path_buf();
    meta.validate(&path)?;
    let brick = brick.clamp(1, 4096);
    let mut scanner = Scanner::new(&meta, brick);
    let nz = meta.dims[2];
    let step = brick.max(16);
    progress(Progress::Stage {
        name: "scan",
        total: nz as u64,
    });
    let mut z = 0;
    while z < nz {
        let d = step.min(nz - z);
        let mut slab = source.read_slab(z, d)?;
        scanner.add_slab(&mut slab, NonFinitePolicy::Zero, &path)?;
        source.release(z, d);
        z += d;
        progress(Progress::Advance { done: z as u64 });
    }
    let fine = if scanner.needs_second_pass() {
        Some(percentile_pass(
            nz,
            step,
            scanner.range(),
            progress,
            |z, d| {
                let mut v = source.read_slab(z, d)?.to_f32_scaled(&meta);
                v.iter_mut()
                    .filter(|x| !x.is_finite())
                    .for_each(|x| *x = 0.0);
                source.release(z, d);
                Ok(v)
            },
        )?)
    } else {
        None
    };
    let grid = scanner.grid;
    let (stats, _, bmax) = scanner.finish(fine);
    let background = background_threshold(&stats);
    let occupied = bmax.iter().filter(|&&m| m >= background).count();
    Ok(ScanReport {
        stats,
        brick,
        grid,
        background,
        occupied,
    })
}

/// Second pass for percentiles of wide types: reads the volume slab by slab through `read(z, depth)`
/// into a fine histogram over the `(min, max)` found by the first pass.
fn percentile_pass(
    nz: usize,
    step: usize,
    range: (f64, f64),
    progress: &mut dyn FnMut(Progress),
    mut read: impl FnMut(usize, usize) -> Result<Vec<f32>>,
) -> Result<FineHistogram> {
    let mut fine = FineHistogram::new(range.0, range.1);
    progress(Progress::Stage {
        name: "percentiles",
        total: nz as u64,
    });
    let mut z = 0;
    while z < nz {
        let d = step.min(nz - z);
        fine.add(&read(z, d)?);
        z += d;
        progress(Progress::Advance { done: z as u64 });
    }
    Ok(fine)
}

/// The default empty-brick threshold: 5% of the way from the 0.5th to the 99.5th percentile.
/// Bricks whose maximum is below it hold only background (air, zeroed haze).
pub fn background_threshold(stats: &VolumeStats) -> f64 {
    stats.p0_5 + 0.05 * (stats.p99_5 - stats.p0_5)
}

/// Streams `source` into a new brick store at `out` (a path or an `s3://` URL). Peak memory
/// is about one slab of `brick` z-slices in the source type plus one coarser slab per pyramid
/// level.
///
/// On a file system the store is written under a temporary name and renamed into place, so an
/// existing store (replaced only with `overwrite`) stays complete until the new one is. On S3
/// the root metadata is written last; an existing store is first marked incomplete, so a
/// reader sees the old store, an "incomplete store" error, or the new store, never a mix.
pub fn ingest(
    source: &mut dyn VolumeSource,
    out: impl Into<StoreLocation>,
    opts: &IngestOptions,
    progress: &mut dyn FnMut(Progress),
) -> Result<StoreInfo> {
    ingest_with_labels(source, None, out, opts, progress)
}

/// A label image ingested with its volume (see [`ingest_with_labels`]).
pub struct IngestLabels<'a> {
    /// Name of the label image (`labels/NAME`).
    pub name: &'a str,
    /// The label volume, on the same grid as the image.
    pub source: &'a mut dyn VolumeSource,
    /// Its class table.
    pub classes: &'a [crate::synth::ClassInfo],
}

/// [`ingest`], with a label image written into the store before it is published: on a file
/// system the store appears (or replaces the old one) with its labels in one rename, so an
/// interruption never leaves the new image without its labels. On S3 the labels are added
/// after the image is published.
pub fn ingest_with_labels(
    source: &mut dyn VolumeSource,
    labels: Option<IngestLabels<'_>>,
    out: impl Into<StoreLocation>,
    opts: &IngestOptions,
    progress: &mut dyn FnMut(Progress),
) -> Result<StoreInfo> {
    let out = out.into();
    if let Some(l) = &labels {
        check_name("label", l.name)?;
        source
            .meta()
            .check_same_grid(l.source.meta(), l.source.path())?;
    }
    let meta = source.meta().clone();
    let src_path = source.path().to_path_buf();
    meta.validate(&src_path)?;
    let target = IngestTarget::begin(&out, opts)?;
    let info = (|| {
        let writer = SlabWriter::create(target.backend(), &meta, opts)?;
        let mut scanner = Scanner::new(&meta, opts.brick);
        let nz = meta.dims[2];
        progress(Progress::Stage {
            name: "ingest",
            total: nz as u64,
        });
        for (z0, depth) in writer.slabs() {
            let mut slab = source.read_slab(z0, depth)?;
            writer.write(&mut scanner, &mut slab, &src_path)?;
            drop(slab);
            source.release(z0, depth);
            progress(Progress::Advance {
                done: (z0 + depth) as u64,
            });
        }
        // Second pass for percentiles of wide types, over the stored level 0.
        let fine = if scanner.needs_second_pass() {
            let mut fine = FineHistogram::new(scanner.range().0, scanner.range().1);
            progress(Progress::Stage {
                name: "percentiles",
                total: nz as u64,
            });
            for (z0, depth) in writer.slabs() {
                fine.merge(&writer.fine_histogram(z0, depth, scanner.range())?);
                progress(Progress::Advance {
                    done: (z0 + depth) as u64,
                });
            }
            Some(fine)
        } else {
            None
        };
        let info = writer.finish(&target, scanner, fine, &src_path)?;
        match labels {
            Some(l) => {
                let mut store = BrickStore::open(target.location().clone())?;
                store.add_labels(l.name, l.source, l.classes, progress)?;
                Ok(store.info().clone())
            }
            None => Ok(info),
        }
    })();
    match info {
        Ok(info) => {
            target.commit()?;
            Ok(info)
        }
        Err(e) => {
            target.abort();
            Err(e)
        }
    }
}

/// Where an ingest writes, from its start to its publication: on a file system a temporary
/// sibling folder renamed into place by [`IngestTarget::commit`] (an existing store stays
/// complete until then, and is locked against other writers meanwhile); on S3 the store itself,
/// marked incomplete and emptied first, whose root metadata is written last.
///
/// Every writer of the ingest (this process, or cluster workers given
/// [`IngestTarget::location`]) writes through it; [`SlabWriter`] does the writing.
pub struct IngestTarget {
    out: StoreLocation,
    at: StoreLocation,
    backend: Arc<Backend>,
    tmp: Option<PathBuf>,
    lock: Option<WriterLock>,
    overwrite: bool,
}

impl IngestTarget {
    /// Prepares `out` for a new store: refuses an existing complete store without
    /// `opts.overwrite`, takes the writer lock and makes the folder (or S3 prefix) to write in.
    pub fn begin(out: &StoreLocation, opts: &IngestOptions) -> Result<Self> {
        out.validate()?;
        validate_options(&out.as_path(), opts)?;
        match out {
            StoreLocation::Local(dir) => {
                if dir.exists() && !opts.overwrite {
                    return Err(BrickError::Exists { path: dir.clone() });
                }
                // Replacing a store: no other writer may be working in it meanwhile.
                let lock = if dir.exists() {
                    Some(WriterLock::acquire(
                        &Backend::open(&StoreLocation::Local(dir.clone()))?,
                        "ingest",
                    )?)
                } else {
                    None
                };
                remove_stale_siblings(dir);
                let tmp = neuvolex_formats::nifti::tmp_name(dir);
                if tmp.exists() {
                    std::fs::remove_dir_all(&tmp).map_err(|e| BrickError::io(&tmp, e))?;
                }
                std::fs::create_dir_all(&tmp).map_err(|e| BrickError::io(&tmp, e))?;
                let at = StoreLocation::Local(tmp.clone());
                Ok(IngestTarget {
                    out: out.clone(),
                    backend: Backend::open(&at)?,
                    at,
                    tmp: Some(tmp),
                    lock,
                    overwrite: opts.overwrite,
                })
            }
            StoreLocation::S3(_) => {
                let backend = Backend::open(out)?;
                if !opts.overwrite {
                    if let Some(bytes) = backend.get("zarr.json")? {
                        // A complete store is kept; leftovers of an interrupted ingest are
                        // replaced.
                        let complete = serde_json::from_slice::<Value>(&bytes)
                            .ok()
                            .and_then(|v| {
                                v.pointer("/attributes/neuvolex/complete")
                                    .and_then(Value::as_bool)
                            })
                            .unwrap_or(false);
                        if complete {
                            return Err(BrickError::Exists {
                                path: out.as_path(),
                            });
                        }
                    }
                }
                let lock = WriterLock::acquire(&backend, "ingest")?;
                backend.put(
                    "zarr.json",
                    serde_json::to_vec_pretty(&json!({"zarr_format": 3, "node_type": "group",
                        "attributes": {"neuvolex": {"complete": false}}}))
                    .unwrap_or_default(),
                )?;
                for name in backend.list_dir("")? {
                    match name.as_str() {
                        "zarr.json" => {}
                        "neuvolex" => {
                            for n in backend.list_dir("neuvolex")? {
                                if format!("neuvolex/{n}") != crate::lock::LOCK_KEY {
                                    delete_node(&backend, &format!("neuvolex/{n}"))?;
                                }
                            }
                        }
                        n => delete_node(&backend, n)?,
                    }
                }
                Ok(IngestTarget {
                    out: out.clone(),
                    at: out.clone(),
                    backend,
                    tmp: None,
                    lock: Some(lock),
                    overwrite: opts.overwrite,
                })
            }
        }
    }

    /// Where the ingest's writers write (the temporary folder on a file system).
    pub fn location(&self) -> &StoreLocation {
        &self.at
    }

    /// The backend of [`Self::location`].
    pub fn backend(&self) -> &Arc<Backend> {
        &self.backend
    }

    /// Publishes the written store at its final location (a rename on a file system; on S3
    /// [`SlabWriter::finish`] already wrote the root metadata last) and releases the lock.
    pub fn commit(self) -> Result<()> {
        if let Some(tmp) = &self.tmp {
            let r = commit_dir(tmp, &self.out.as_path(), self.overwrite);
            if r.is_err() {
                let _ = std::fs::remove_dir_all(tmp);
            }
            r?;
        }
        Ok(())
    }

    /// Gives up: removes the temporary folder (the previous store, if any, is untouched).
    pub fn abort(self) {
        if let Some(tmp) = &self.tmp {
            let _ = std::fs::remove_dir_all(tmp);
        }
    }
}

/// True if `location` (a path or `s3://` URL) holds a neuvolex brick store, complete or not.
pub fn is_brick_store(location: impl Into<StoreLocation>) -> bool {
    Backend::open(&location.into())
        .and_then(|b| b.get("zarr.json"))
        .ok()
        .flatten()
        .is_some_and(|t| String::from_utf8_lossy(&t).contains("\"neuvolex\""))
}

/// Deletes the object or folder `key`.
fn delete_node(backend: &Backend, key: &str) -> Result<()> {
    match key.trim_matches('/').rsplit_once('/') {
        Some((parent, name)) => backend.delete_child(parent, name),
        None => backend.delete_child("", key.trim_matches('/')),
    }
}

struct LevelWriter {
    array: ZArray,
    dims: [usize; 3],
}

/// The writer of an ingest's image pyramid: the pure per-slab step that any scheduler runs
/// (the sequential [`ingest`], or slab tasks on cluster workers, `neuvolex-ingest`).
///
/// A slab is one brick (or one shard) of z-slices, so every slab fills whole chunks at every
/// pyramid level and slabs can be written in any order, by any process, any number of times
/// (the same bytes each time).
pub struct SlabWriter {
    meta: VolumeMeta,
    opts: IngestOptions,
    root: PathBuf,
    storage: ReadableWritableListableStorage,
    store_dtype: DType,
    levels: Vec<LevelWriter>,
}

impl SlabWriter {
    fn layout(
        backend: &Backend,
        meta: &VolumeMeta,
        opts: &IngestOptions,
        create: bool,
    ) -> Result<Self> {
        let storage = backend.zarr();
        let root = backend.path();
        let b = opts.brick;
        let store_dtype = if meta.scaling.is_some() {
            DType::F32
        } else {
            meta.dtype
        };
        let nlevels = pick_levels(meta.dims, b, opts.levels);
        let mut levels = Vec::with_capacity(nlevels);
        for k in 0..nlevels {
            let d = level_dims(meta.dims, k);
            let array = if create {
                build_array(
                    &storage,
                    &root,
                    &format!("/{k}"),
                    vec![d[2] as u64, d[1] as u64, d[0] as u64],
                    level_chunk(b, k).iter().rev().map(|&c| c as u64).collect(),
                    if k == 0 { store_dtype } else { DType::F32 },
                    opts,
                )?
            } else {
                let a = Array::open(storage.clone(), &format!("/{k}"))
                    .map_err(|e| BrickError::zarr(&root, e))?;
                let want = vec![d[2] as u64, d[1] as u64, d[0] as u64];
                if a.shape() != want.as_slice() {
                    return Err(BrickError::corrupt(
                        &root,
                        format!(
                            "level {k} has shape {:?}, this ingest writes {want:?}",
                            a.shape()
                        ),
                    ));
                }
                a
            };
            levels.push(LevelWriter { array, dims: d });
        }
        Ok(SlabWriter {
            meta: meta.clone(),
            opts: opts.clone(),
            root,
            storage,
            store_dtype,
            levels,
        })
    }

    /// Creates the pyramid's arrays (their metadata) for a volume of `meta` in `backend`.
    pub fn create(backend: &Backend, meta: &VolumeMeta, opts: &IngestOptions) -> Result<Self> {
        meta.validate(&backend.path())?;
        Self::layout(backend, meta, opts, true)
    }

    /// Opens the arrays [`Self::create`] made (a cluster worker), checking their shapes.
    pub fn open(backend: &Backend, meta: &VolumeMeta, opts: &IngestOptions) -> Result<Self> {
        meta.validate(&backend.path())?;
        Self::layout(backend, meta, opts, false)
    }

    /// Slices per slab: one brick, or one shard, deep.
    pub fn slab_depth(&self) -> usize {
        self.opts.brick * self.opts.shard.unwrap_or(1).max(1)
    }

    /// The slabs of the volume as `(first z-slice, depth)`, front to back.
    pub fn slabs(&self) -> Vec<(usize, usize)> {
        let (nz, d) = (self.meta.dims[2], self.slab_depth());
        (0..nz).step_by(d).map(|z| (z, d.min(nz - z))).collect()
    }

    /// Scans one slab into `scanner` (applying the NaN/Inf policy; `path` names the source in
    /// errors) and writes it at every pyramid level. `slab` must be one of [`Self::slabs`].
    pub fn write(
        &self,
        scanner: &mut Scanner,
        slab: &mut neuvolex_formats::meta::Slab,
        path: &Path,
    ) -> Result<()> {
        let meta = &self.meta;
        let (b, z0, depth) = (self.opts.brick, slab.z0, slab.depth);
        if !self.slabs().contains(&(z0, depth)) {
            return Err(BrickError::InvalidArgument(format!(
                "{}: slices {z0}..{} are not one slab of this ingest ({} slices a slab)",
                path.display(),
                z0 + depth,
                self.slab_depth()
            )));
        }
        scanner.add_slab(slab, self.opts.non_finite, path)?;
        let root = self.root.as_path();
        // Level 1 from pairs of slices of the native slab (no full-slab f32 copy).
        let mut cur = if self.levels.len() > 1 {
            downsample_slab(slab, meta)
        } else {
            Vec::new()
        };
        // Level 0 in the stored type.
        let level0_bytes = if meta.scaling.is_some() {
            bytemuck::cast_slice(&slab.to_f32_scaled(meta)).to_vec()
        } else {
            std::mem::take(&mut slab.bytes)
        };
        write_slab_chunks(
            &self.levels[0].array,
            &level0_bytes,
            self.store_dtype.size(),
            [meta.dims[0], meta.dims[1], depth],
            z0,
            level_chunk(b, 0),
        )
        .map_err(|e| BrickError::zarr(root, e))?;
        drop(level0_bytes);
        // Coarser levels.
        let mut cur_dims = [
            meta.dims[0].div_ceil(2),
            meta.dims[1].div_ceil(2),
            depth.div_ceil(2),
        ];
        let mut cz = z0 / 2;
        for (k, lvl) in self.levels.iter().enumerate().skip(1) {
            if k > 1 {
                cur = downsample_mean(&cur, cur_dims);
                cur_dims = [lvl.dims[0], lvl.dims[1], cur_dims[2].div_ceil(2)];
                cz /= 2;
            }
            write_slab_chunks(
                &lvl.array,
                bytemuck::cast_slice(&cur),
                4,
                cur_dims,
                cz,
                level_chunk(b, k),
            )
            .map_err(|e| BrickError::zarr(root, e))?;
        }
        Ok(())
    }

    /// The percentile histogram over `range` (the merged scanners' range) of slices
    /// `z0..z0+depth` of the stored level 0 (the second pass of wide and float types).
    pub fn fine_histogram(
        &self,
        z0: usize,
        depth: usize,
        range: (f64, f64),
    ) -> Result<FineHistogram> {
        let meta = &self.meta;
        let bytes = read_bytes(
            &self.levels[0].array,
            &zyx([0, 0, z0], [meta.dims[0], meta.dims[1], depth]),
        )
        .map_err(|e| BrickError::zarr(&self.root, e))?;
        let mut v = vec![0.0f32; bytes.len() / self.store_dtype.size()];
        neuvolex_formats::dtype::bytes_to_f32(&bytes, self.store_dtype, &mut v);
        let mut fine = FineHistogram::new(range.0, range.1);
        fine.add(&v);
        Ok(fine)
    }

    /// Writes the per-brick ranges and the root metadata (last, `complete: true`) from the
    /// scanner of the whole volume (merged) and its percentile histogram.
    pub fn finish(
        self,
        target: &IngestTarget,
        scanner: Scanner,
        fine: Option<FineHistogram>,
        src_path: &Path,
    ) -> Result<StoreInfo> {
        let (meta, opts, root, storage) = (&self.meta, &self.opts, &self.root, &self.storage);
        let grid = grid_of(meta.dims, opts.brick);
        let (stats, bmin, bmax) = scanner.finish(fine);
        for (name, vals) in [("brick_min", &bmin), ("brick_max", &bmax)] {
            let a = build_array(
                storage,
                root,
                &format!("/neuvolex/{name}"),
                vec![grid[2] as u64, grid[1] as u64, grid[0] as u64],
                vec![grid[2] as u64, grid[1] as u64, grid[0] as u64],
                DType::F64,
                &IngestOptions {
                    shard: None,
                    ..opts.clone()
                },
            )?;
            write_bytes(&a, &zyx([0; 3], grid), bytemuck::cast_slice(vals).to_vec())
                .map_err(|e| BrickError::zarr(root, e))?;
        }
        GroupBuilder::new()
            .build(storage.clone(), "/neuvolex")
            .map_err(|e| BrickError::zarr(root, e))?
            .store_metadata()
            .map_err(|e| BrickError::zarr(root, e))?;
        let background = background_threshold(&stats);
        let info = StoreInfo {
            version: STORE_VERSION,
            complete: true,
            dims: meta.dims,
            brick: opts.brick,
            shard: opts.shard,
            levels: self.levels.iter().map(|l| l.dims).collect(),
            dtype: self.store_dtype,
            source_dtype: meta.dtype,
            source: src_path.display().to_string(),
            spacing: meta.spacing,
            affine: meta.affine,
            stats,
            background,
            labels: vec![],
        };
        if target.tmp.is_none() {
            if let Some(l) = &target.lock {
                l.check()?;
            }
        }
        write_root_attrs(storage, root, &info)?;
        Ok(info)
    }
}

fn write_root_attrs(
    storage: &ReadableWritableListableStorage,
    root: &Path,
    info: &StoreInfo,
) -> Result<()> {
    let mut g = GroupBuilder::new();
    g.attributes(root_attrs(root, info)?);
    g.build(storage.clone(), "/")
        .map_err(|e| BrickError::zarr(root, e))?
        .store_metadata()
        .map_err(|e| BrickError::zarr(root, e))
}

/// The root group's attributes: the OME multiscales of the image and [`StoreInfo`].
fn root_attrs(root: &Path, info: &StoreInfo) -> Result<serde_json::Map<String, Value>> {
    let mut attrs = serde_json::Map::new();
    attrs.insert(
        "ome".into(),
        json!({"version": "0.5", "multiscales": multiscales("image", info.levels.len(), info.spacing, [info.affine[0][3], info.affine[1][3], info.affine[2][3]])}),
    );
    attrs.insert(
        "neuvolex".into(),
        serde_json::to_value(info).map_err(|e| BrickError::corrupt(root, e.to_string()))?,
    );
    Ok(attrs)
}

/// How per-voxel vectors are stored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum VectorEncoding {
    /// IEEE half precision.
    F16,
    /// 8-bit linear quantisation of `[lo, hi]` per channel (values are clamped).
    U8 {
        /// Value mapped to 0, per channel.
        lo: Vec<f32>,
        /// Value mapped to 255, per channel.
        hi: Vec<f32>,
    },
}

/// Attributes of a vector array.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VectorInfo {
    /// Channels per voxel.
    pub channels: usize,
    /// Encoding.
    pub encoding: VectorEncoding,
    /// True once every brick has been written (or the writer was finished).
    pub complete: bool,
    /// Free-form provenance set by the writer (e.g. which model and feature).
    #[serde(default)]
    pub extra: Value,
    /// The stage identity of a resumable writer ([`BrickStore::resume_vectors`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity: Option<String>,
}

/// An opened, complete brick store.
pub struct BrickStore {
    root: PathBuf,
    location: StoreLocation,
    backend: Arc<Backend>,
    storage: ReadableWritableListableStorage,
    info: StoreInfo,
    levels: Vec<ZArray>,
    brick_min: Vec<f64>,
    brick_max: Vec<f64>,
    /// Decoded bricks by (level, index); each costs 1, so the budget counts bricks.
    cache: Lru<(usize, [usize; 3]), Arc<Vec<f32>>>,
}

impl std::fmt::Debug for BrickStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BrickStore")
            .field("root", &self.root)
            .field("dims", &self.info.dims)
            .finish()
    }
}

impl BrickStore {
    /// Opens a store written by [`ingest`] at a path or `s3://` URL; errors if it is
    /// incomplete or damaged.
    pub fn open(location: impl Into<StoreLocation>) -> Result<Self> {
        let location = location.into();
        let backend = Backend::open(&location)?;
        let root_path = location.as_path();
        let root = root_path.as_path();
        let node = crate::commit::read_committed_node(&backend, "")?;
        let nv = node
            .pointer("/attributes/neuvolex")
            .ok_or_else(|| BrickError::corrupt(root, "not a neuvolex brick store (no neuvolex attributes); run `neuvolex ingest` on it first"))?;
        if nv.get("complete").and_then(Value::as_bool) != Some(true) {
            return Err(BrickError::Incomplete {
                path: root.to_path_buf(),
                detail: "the store was not completely written (interrupted ingest?)".into(),
            });
        }
        let info: StoreInfo = serde_json::from_value(nv.clone())
            .map_err(|e| BrickError::corrupt(root, format!("neuvolex attributes: {e}")))?;
        if info.version > STORE_VERSION {
            return Err(BrickError::corrupt(
                root,
                format!(
                    "store version {} is newer than this build ({STORE_VERSION})",
                    info.version
                ),
            ));
        }
        neuvolex_formats::meta::validate_dims(root, info.dims)?;
        if !(8..=512).contains(&info.brick) || info.levels.is_empty() {
            return Err(BrickError::corrupt(
                root,
                format!(
                    "brick {} / levels {:?} are invalid",
                    info.brick, info.levels
                ),
            ));
        }
        let storage = backend.zarr();
        let mut levels = Vec::new();
        for (k, d) in info.levels.iter().enumerate() {
            read_node(&backend, &k.to_string())?;
            let a: ZArray = Array::open(storage.clone(), &format!("/{k}"))
                .map_err(|e| BrickError::corrupt(root.join(k.to_string()), e.to_string()))?;
            let want = [d[2] as u64, d[1] as u64, d[0] as u64];
            let have = crate::omezarr::dtype_name(&a);
            let want_type = if k == 0 { info.dtype } else { DType::F32 };
            if DType::parse(&have) != Some(want_type) {
                return Err(BrickError::corrupt(
                    root,
                    format!("level {k} holds {have}, attributes say {want_type}"),
                ));
            }
            if a.shape() != want {
                return Err(BrickError::corrupt(
                    root,
                    format!(
                        "level {k} has shape {:?}, attributes say {want:?}",
                        a.shape()
                    ),
                ));
            }
            levels.push(a);
        }
        let grid = info.grid();
        let mut ranges = Vec::new();
        for name in ["brick_min", "brick_max"] {
            let p = format!("/neuvolex/{name}");
            read_node(&backend, &p)?;
            let a: ZArray = Array::open(storage.clone(), &p)
                .map_err(|e| BrickError::corrupt(root, e.to_string()))?;
            let sub = zyx([0; 3], grid);
            check_chunks_exist(&a, root, &p, &sub)?;
            let n: usize = grid.iter().product();
            if DType::parse(&crate::omezarr::dtype_name(&a)) != Some(DType::F64) {
                return Err(BrickError::corrupt(root, format!("{p} is not float64")));
            }
            let bytes = read_bytes(&a, &sub).map_err(|e| BrickError::corrupt(root, e))?;
            if bytes.len() != n * 8 {
                return Err(BrickError::corrupt(
                    root,
                    format!("{p} holds {} bytes for {n} bricks", bytes.len()),
                ));
            }
            ranges.push(bytemuck::pod_collect_to_vec::<u8, f64>(&bytes));
        }
        let brick_max = ranges.pop().unwrap_or_default();
        let brick_min = ranges.pop().unwrap_or_default();
        let cap = 128;
        Ok(BrickStore {
            root: root.to_path_buf(),
            location,
            backend,
            storage,
            info,
            levels,
            brick_min,
            brick_max,
            cache: Lru::new(cap),
        })
    }

    /// The store's path, or its URL (`s3://bucket/prefix.zarr`) as a path: for messages.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Where the store lives.
    pub fn location(&self) -> &StoreLocation {
        &self.location
    }

    /// The storage under the store, for objects written beside the arrays.
    pub fn backend(&self) -> &Arc<Backend> {
        &self.backend
    }

    /// Takes the store's writer lock for `purpose` (see [`crate::lock`]); fails at once with
    /// [`BrickError::Locked`] naming the holder if another process writes.
    pub fn writer_lock(&self, purpose: &str) -> Result<WriterLock> {
        WriterLock::acquire(&self.backend, purpose)
    }

    /// The done markers of `stage` for this store's brick layout and the stage's `identity`
    /// (model version, parameters hash): opened to resume, or started. Markers written for
    /// another layout or identity are refused with [`BrickError::StageMismatch`].
    pub fn done_markers(&self, stage: &str, identity: &str) -> Result<DoneMarkers> {
        check_name("stage", stage)?;
        DoneMarkers::open_or_create(
            &self.backend,
            &format!("neuvolex/done/{stage}"),
            StageTag {
                stage: stage.to_string(),
                layout: layout_of(self.info.dims, self.info.brick),
                identity: identity.to_string(),
            },
            self.grid(),
        )
    }

    /// Store attributes.
    pub fn info(&self) -> &StoreInfo {
        &self.info
    }

    /// The volume model of level 0 (values are read back as f32).
    pub fn meta(&self) -> VolumeMeta {
        VolumeMeta {
            dims: self.info.dims,
            spacing: self.info.spacing,
            affine: self.info.affine,
            dtype: self.info.dtype,
            scaling: None,
        }
    }

    /// Robust intensity normalisation for derived quantities.
    pub fn normaliser(&self) -> Normaliser {
        Normaliser::robust(&self.info.stats)
    }

    /// Sets how many decoded bricks the read cache keeps (default 128).
    pub fn set_cache_capacity(&self, bricks: usize) {
        self.cache.set_budget(bricks);
    }

    /// Bricks per axis (x, y, z).
    pub fn grid(&self) -> [usize; 3] {
        self.info.grid()
    }

    /// The brick at grid index `i`.
    pub fn brick(&self, i: [usize; 3]) -> Result<Brick> {
        let g = self.grid();
        if (0..3).any(|k| i[k] >= g[k]) {
            return Err(BrickError::InvalidArgument(format!(
                "brick {i:?} outside grid {g:?}"
            )));
        }
        let b = self.info.brick;
        let origin = [i[0] * b, i[1] * b, i[2] * b];
        let size = [
            b.min(self.info.dims[0] - origin[0]),
            b.min(self.info.dims[1] - origin[1]),
            b.min(self.info.dims[2] - origin[2]),
        ];
        Ok(Brick {
            index: i,
            origin,
            size,
        })
    }

    /// All bricks, x fastest.
    pub fn bricks(&self) -> impl Iterator<Item = Brick> + '_ {
        let g = self.grid();
        (0..g[2])
            .flat_map(move |z| (0..g[1]).flat_map(move |y| (0..g[0]).map(move |x| [x, y, z])))
            .filter_map(|i| self.brick(i).ok())
    }

    fn flat(&self, i: [usize; 3]) -> usize {
        let g = self.grid();
        (i[2] * g[1] + i[1]) * g[0] + i[0]
    }

    /// Value range `(min, max)` of a brick.
    pub fn brick_range(&self, b: &Brick) -> (f64, f64) {
        let i = self.flat(b.index);
        (self.brick_min[i], self.brick_max[i])
    }

    /// True when the brick holds something above `threshold` (default: [`StoreInfo::background`]).
    pub fn is_occupied(&self, b: &Brick, threshold: Option<f64>) -> bool {
        self.brick_range(b).1 >= threshold.unwrap_or(self.info.background)
    }

    /// Bricks holding something above the threshold; these are what later stages model.
    pub fn occupied_bricks(&self, threshold: Option<f64>) -> Vec<Brick> {
        self.bricks()
            .filter(|b| self.is_occupied(b, threshold))
            .collect()
    }

    fn load_brick(&self, level: usize, idx: [usize; 3]) -> Result<Arc<Vec<f32>>> {
        self.cache.get_or_try_insert(&(level, idx), || {
            let d = self.info.levels[level];
            let c = level_chunk(self.info.brick, level);
            let origin = [idx[0] * c[0], idx[1] * c[1], idx[2] * c[2]];
            let size = [
                c[0].min(d[0] - origin[0]),
                c[1].min(d[1] - origin[1]),
                c[2].min(d[2] - origin[2]),
            ];
            let sub = zyx(origin, size);
            let a = &self.levels[level];
            check_chunks_exist(a, &self.root, &format!("/{level}"), &sub)?;
            let bytes = read_bytes(a, &sub).map_err(|e| BrickError::corrupt(&self.root, e))?;
            let dt = if level == 0 {
                self.info.dtype
            } else {
                DType::F32
            };
            // Sizes come from the attributes; the array's own type decides the byte count.
            if bytes.len() != size.iter().product::<usize>() * dt.size() {
                return Err(BrickError::corrupt(
                    &self.root,
                    format!(
                        "level {level} brick {idx:?}: {} bytes read, the attributes' {dt} \
                         brick of {size:?} needs {}",
                        bytes.len(),
                        size.iter().product::<usize>() * dt.size()
                    ),
                ));
            }
            let mut v = vec![0.0f32; bytes.len() / dt.size()];
            neuvolex_formats::dtype::bytes_to_f32(&bytes, dt, &mut v);
            Ok((Arc::new(v), 1))
        })
    }

    /// Reads the sub-box `origin..origin+size` (x, y, z) of pyramid `level` as f32, x fastest.
    pub fn read_box(&self, level: usize, origin: [usize; 3], size: [usize; 3]) -> Result<Vec<f32>> {
        let d = *self.info.levels.get(level).ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "level {level} does not exist (store has {})",
                self.info.levels.len()
            ))
        })?;
        for k in 0..3 {
            if size[k] == 0 || origin[k].checked_add(size[k]).is_none_or(|e| e > d[k]) {
                return Err(BrickError::InvalidArgument(format!(
                    "box {origin:?}+{size:?} outside level {level} grid {d:?}"
                )));
            }
        }
        let c = level_chunk(self.info.brick, level);
        let mut out = vec![0.0f32; size.iter().product()];
        for bz in origin[2] / c[2]..=(origin[2] + size[2] - 1) / c[2] {
            for by in origin[1] / c[1]..=(origin[1] + size[1] - 1) / c[1] {
                for bx in origin[0] / c[0]..=(origin[0] + size[0] - 1) / c[0] {
                    let data = self.load_brick(level, [bx, by, bz])?;
                    let bo = [bx * c[0], by * c[1], bz * c[2]];
                    let bs = [
                        c[0].min(d[0] - bo[0]),
                        c[1].min(d[1] - bo[1]),
                        c[2].min(d[2] - bo[2]),
                    ];
                    let lo = [
                        origin[0].max(bo[0]),
                        origin[1].max(bo[1]),
                        origin[2].max(bo[2]),
                    ];
                    let hi = [
                        (origin[0] + size[0]).min(bo[0] + bs[0]),
                        (origin[1] + size[1]).min(bo[1] + bs[1]),
                        (origin[2] + size[2]).min(bo[2] + bs[2]),
                    ];
                    let w = hi[0] - lo[0];
                    for z in lo[2]..hi[2] {
                        for y in lo[1]..hi[1] {
                            let s = ((z - bo[2]) * bs[1] + (y - bo[1])) * bs[0] + (lo[0] - bo[0]);
                            let o = ((z - origin[2]) * size[1] + (y - origin[1])) * size[0]
                                + (lo[0] - origin[0]);
                            out[o..o + w].copy_from_slice(&data[s..s + w]);
                        }
                    }
                }
            }
        }
        Ok(out)
    }

    /// Reads brick `b` of level 0 with `halo` voxels on each side, edge-clamped at the border.
    pub fn read_halo(&self, b: &Brick, halo: usize) -> Result<HaloBrick> {
        let d = self.info.dims;
        let lo: Vec<usize> = (0..3).map(|k| b.origin[k].saturating_sub(halo)).collect();
        let hi: Vec<usize> = (0..3)
            .map(|k| (b.origin[k] + b.size[k] + halo).min(d[k]))
            .collect();
        let rs = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        let inner = self.read_box(0, [lo[0], lo[1], lo[2]], rs)?;
        let p = [
            b.size[0] + 2 * halo,
            b.size[1] + 2 * halo,
            b.size[2] + 2 * halo,
        ];
        let mut data = vec![0.0f32; p[0] * p[1] * p[2]];
        let h = halo as isize;
        let xs: Vec<usize> = (0..p[0] as isize)
            .map(|x| {
                ((b.origin[0] as isize + x - h).clamp(lo[0] as isize, hi[0] as isize - 1) as usize)
                    - lo[0]
            })
            .collect();
        for z in 0..p[2] {
            let sz = (b.origin[2] as isize + z as isize - h)
                .clamp(lo[2] as isize, hi[2] as isize - 1) as usize
                - lo[2];
            for y in 0..p[1] {
                let sy = (b.origin[1] as isize + y as isize - h)
                    .clamp(lo[1] as isize, hi[1] as isize - 1) as usize
                    - lo[1];
                let src = (sz * rs[1] + sy) * rs[0];
                let dst = (z * p[1] + y) * p[0];
                for (x, &sx) in xs.iter().enumerate() {
                    data[dst + x] = inner[src + sx];
                }
            }
        }
        Ok(HaloBrick {
            origin: b.origin,
            size: b.size,
            halo,
            data,
        })
    }

    /// Derived quantities (normalised intensity, gradient, local mean/std) of a brick.
    pub fn derived(&self, b: &Brick) -> Result<crate::derived::DerivedBrick> {
        let h = self.read_halo(b, crate::derived::DERIVED_HALO)?;
        Ok(crate::derived::compute(&h, &self.normaliser()))
    }

    /// Adds a label volume under `labels/NAME` (grid must match; values non-negative integers).
    /// Written as a new generation beside the previous image of that name and published by
    /// one commit, so a reader sees the old image or the new one and an interrupted write
    /// leaves the old one. Takes the writer lock.
    pub fn add_labels(
        &mut self,
        name: &str,
        source: &mut dyn VolumeSource,
        classes: &[crate::synth::ClassInfo],
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        let mut commit = Commit::new();
        self.stage_labels(&mut commit, name, source, classes, progress)?;
        commit.publish(&self.backend)
    }

    /// Writes label image `labels/NAME` as a new generation, as [`Self::add_labels`] does, and
    /// adds its publication to `commit` instead of publishing it, so it appears together with
    /// the step's other outputs ([`Commit::publish`]). The commit holds the writer lock.
    pub fn stage_labels(
        &mut self,
        commit: &mut Commit,
        name: &str,
        source: &mut dyn VolumeSource,
        classes: &[crate::synth::ClassInfo],
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        check_name("label", name)?;
        let lpath = source.path().to_path_buf();
        self.meta().check_same_grid(source.meta(), &lpath)?;
        let sdt = source.meta().dtype;
        let dtype = match sdt {
            DType::U8 | DType::I8 => DType::U8,
            DType::U16 | DType::I16 | DType::F32 | DType::F64 => DType::U16,
            DType::U32 | DType::I32 => DType::U32,
        };
        let lock = self.writer_lock(&format!("labels {name}"))?;
        // Another handle (or process) may have added label images since this one opened.
        if let Ok(node) = crate::commit::read_committed_node(&self.backend, "") {
            if let Some(l) = node
                .pointer("/attributes/neuvolex/labels")
                .and_then(|v| serde_json::from_value::<Vec<String>>(v.clone()).ok())
            {
                for n in l {
                    if !self.info.labels.contains(&n) {
                        self.info.labels.push(n);
                    }
                }
            }
        }
        let node = format!("labels/{name}");
        let gen = next_generation(&self.backend, &node)?;
        let res = self.write_labels(name, &gen, dtype, source, &lpath, progress);
        if let Err(e) = res {
            let _ = delete_node(&self.backend, &format!("{node}/{gen}"));
            return Err(e);
        }
        lock.check()?;
        commit.hold(lock);
        // The image-label group will point at the new generation.
        let mut ms = multiscales(
            name,
            self.info.levels.len(),
            self.info.spacing,
            [
                self.info.affine[0][3],
                self.info.affine[1][3],
                self.info.affine[2][3],
            ],
        );
        ms[0]["type"] = json!("mode");
        for d in ms[0]["datasets"].as_array_mut().into_iter().flatten() {
            let p = d["path"].as_str().unwrap_or("0").to_string();
            d["path"] = json!(format!("{gen}/{p}"));
        }
        let attrs = |v: Value| v.as_object().cloned().unwrap_or_default();
        commit.write(&node, group_doc(attrs(json!({"ome": {"version": "0.5", "multiscales": ms, "image-label": {
            "version": "0.5",
            "source": {"image": "../../"},
            "colors": classes.iter().map(|c| json!({"label-value": c.id, "rgba": [c.color[0], c.color[1], c.color[2], 255]})).collect::<Vec<_>>(),
            "properties": classes.iter().map(|c| json!({"label-value": c.id, "name": c.name})).collect::<Vec<_>>()
        }}}))));
        commit.keep_only(&node, &gen);
        if !self.info.labels.iter().any(|l| l == name) {
            self.info.labels.push(name.to_string());
        }
        commit.write(
            "labels",
            group_doc(attrs(
                json!({"ome": {"version": "0.5", "labels": self.info.labels}}),
            )),
        );
        commit.write("", group_doc(root_attrs(&self.root, &self.info)?));
        Ok(())
    }

    /// Writes the pyramid of a label image as generation `gen` of `labels/NAME`.
    fn write_labels(
        &self,
        name: &str,
        gen: &str,
        dtype: DType,
        source: &mut dyn VolumeSource,
        lpath: &Path,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<()> {
        let base = format!("/labels/{name}/{gen}");
        let opts = IngestOptions {
            brick: self.info.brick,
            shard: self.info.shard,
            ..IngestOptions::default()
        };
        let mut arrays = Vec::new();
        for (k, d) in self.info.levels.iter().enumerate() {
            arrays.push(build_array(
                &self.storage,
                &self.root,
                &format!("{base}/{k}"),
                vec![d[2] as u64, d[1] as u64, d[0] as u64],
                level_chunk(self.info.brick, k)
                    .iter()
                    .rev()
                    .map(|&c| c as u64)
                    .collect(),
                dtype,
                &opts,
            )?);
        }
        let dims = self.info.dims;
        let b = self.info.brick;
        progress(Progress::Stage {
            name: "labels",
            total: dims[2] as u64,
        });
        let mut z0 = 0;
        let max = dtype.range().1;
        while z0 < dims[2] {
            let depth = (b * self.info.shard.unwrap_or(1).max(1)).min(dims[2] - z0);
            let raw = source.read_slab(z0, depth)?.to_f64();
            let meta = source.meta().clone();
            let mut lab = Vec::with_capacity(raw.len());
            for (i, &r) in raw.iter().enumerate() {
                let v = meta.scale(r);
                if !v.is_finite() || v < 0.0 || v.fract() != 0.0 || v > max {
                    let s = meta.slice_len();
                    return Err(neuvolex_formats::FormatError::header(lpath, format!("label value {v} at voxel (x={}, y={}, z={}) is not a non-negative integer", i % dims[0], (i / dims[0]) % dims[1], z0 + i / s)).into());
                }
                lab.push(v as u32);
            }
            let to_bytes = |l: &[u32]| {
                neuvolex_formats::dtype::f64_to_bytes(
                    &l.iter().map(|&v| v as f64).collect::<Vec<_>>(),
                    dtype,
                )
            };
            let esize = dtype.size();
            write_slab_chunks(
                &arrays[0],
                &to_bytes(&lab),
                esize,
                [dims[0], dims[1], depth],
                z0,
                level_chunk(b, 0),
            )
            .map_err(|e| BrickError::zarr(&self.root, e))?;
            let mut cur = lab;
            let mut cd = [dims[0], dims[1], depth];
            let mut cz = z0;
            for (k, a) in arrays.iter().enumerate().skip(1) {
                cur = downsample_mode(&cur, cd);
                cd = [
                    self.info.levels[k][0],
                    self.info.levels[k][1],
                    cd[2].div_ceil(2),
                ];
                cz /= 2;
                write_slab_chunks(a, &to_bytes(&cur), esize, cd, cz, level_chunk(b, k))
                    .map_err(|e| BrickError::zarr(&self.root, e))?;
            }
            z0 += depth;
            progress(Progress::Advance { done: z0 as u64 });
        }
        GroupBuilder::new()
            .build(self.storage.clone(), &base)
            .map_err(|e| BrickError::zarr(&self.root, e))?
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))
    }

    /// The class table stored with label image `name` (empty if none was given).
    pub fn label_classes(&self, name: &str) -> Result<Vec<crate::synth::ClassInfo>> {
        check_name("label", name)?;
        let node = crate::commit::read_committed_node(&self.backend, &format!("labels/{name}"))?;
        let il = node
            .pointer("/attributes/ome/image-label")
            .cloned()
            .unwrap_or(Value::Null);
        let mut out = Vec::new();
        for p in il
            .get("properties")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            let id = p.get("label-value").and_then(Value::as_u64).unwrap_or(0) as u32;
            let name = p
                .get("name")
                .and_then(Value::as_str)
                .unwrap_or("")
                .to_string();
            let color = il
                .get("colors")
                .and_then(Value::as_array)
                .and_then(|cs| {
                    cs.iter()
                        .find(|c| c.get("label-value").and_then(Value::as_u64) == Some(id as u64))
                })
                .and_then(|c| c.get("rgba").and_then(Value::as_array).cloned())
                .map(|a| [0, 1, 2].map(|i| a.get(i).and_then(Value::as_u64).unwrap_or(128) as u8))
                .unwrap_or([128; 3]);
            out.push(crate::synth::ClassInfo { id, name, color });
        }
        Ok(out)
    }

    /// Reads labels `name` in the sub-box of level 0.
    pub fn read_labels_box(
        &self,
        name: &str,
        origin: [usize; 3],
        size: [usize; 3],
    ) -> Result<Vec<u32>> {
        if !self.info.labels.iter().any(|l| l == name) {
            return Err(BrickError::InvalidArgument(format!(
                "{}: no label image '{name}' (have {:?})",
                self.root.display(),
                self.info.labels
            )));
        }
        let d = self.info.dims;
        for k in 0..3 {
            if size[k] == 0 || origin[k] + size[k] > d[k] {
                return Err(BrickError::InvalidArgument(format!(
                    "box {origin:?}+{size:?} outside grid {d:?}"
                )));
            }
        }
        let node = crate::commit::read_committed_node(&self.backend, &format!("labels/{name}"))?;
        let level0 = node
            .pointer("/attributes/ome/multiscales/0/datasets/0/path")
            .and_then(Value::as_str)
            .unwrap_or("0");
        let p = format!("/labels/{name}/{}", level0.trim_matches('/'));
        let a: ZArray = Array::open(self.storage.clone(), &p)
            .map_err(|e| BrickError::corrupt(&self.root, e.to_string()))?;
        let sub = zyx(origin, size);
        check_chunks_exist(&a, &self.root, &p, &sub)?;
        let bytes = read_bytes(&a, &sub).map_err(|e| BrickError::corrupt(&self.root, e))?;
        let dt = DType::parse(&crate::omezarr::dtype_name(&a)).unwrap_or(DType::U8);
        let mut v = vec![0.0f64; bytes.len() / dt.size()];
        neuvolex_formats::dtype::bytes_to_f64(&bytes, dt, &mut v);
        Ok(v.into_iter().map(|x| x as u32).collect())
    }

    /// Creates (or replaces) the per-voxel vector array `name` with `channels` channels.
    ///
    /// The new array is a pending generation beside the current one: readers keep seeing the
    /// previous complete array until [`VectorArray::finish`] publishes this one. The returned
    /// writer holds the store's writer lock until it is finished or dropped.
    pub fn create_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
    ) -> Result<VectorArray> {
        check_name("vector", name)?;
        let lock = self.writer_lock(&format!("vectors {name}"))?;
        self.new_vectors(name, channels, encoding, None, lock)
    }

    /// Opens the pending (unpublished) generation of vector array `name` written for stage
    /// `identity` (model version, parameters hash) to resume it, or starts one. The writer
    /// carries done markers ([`VectorArray::pending`], [`VectorArray::mark_done`]) and holds
    /// the writer lock. A pending generation of another identity, channel count or encoding
    /// is refused with [`BrickError::StageMismatch`]; [`Self::discard_pending_vectors`] drops
    /// it.
    pub fn resume_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
        identity: &str,
    ) -> Result<VectorArray> {
        check_name("vector", name)?;
        let lock = self.writer_lock(&format!("vectors {name}"))?;
        if let Some(mut va) = self.find_pending(name, identity)? {
            if va.info.channels != channels || va.info.encoding != encoding {
                return Err(BrickError::stage_mismatch(
                    self.backend.key_path(&va.path),
                    &format!("the pending vector array '{name}'"),
                    &format!("{} channels, {:?}", va.info.channels, va.info.encoding),
                    &format!("{channels} channels, {encoding:?}"),
                    "discard it to start over",
                ));
            }
            va.lock = Some(lock);
            return Ok(va);
        }
        let mut va = self.new_vectors(name, channels, encoding, Some(identity), lock)?;
        va.done = Some(self.vector_markers(name, &va.generation, identity)?);
        Ok(va)
    }

    /// Opens the pending generation of `name` written for `identity`, for a cluster worker
    /// that writes and marks bricks while the stage's coordinator (which called
    /// [`Self::resume_vectors`]) holds the lock. It cannot publish.
    pub fn open_pending_vectors(&self, name: &str, identity: &str) -> Result<VectorArray> {
        check_name("vector", name)?;
        self.find_pending(name, identity)?.ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "{}: no pending vector array '{name}' for '{identity}' (the coordinator starts it)",
                self.root.display()
            ))
        })
    }

    /// Deletes every unpublished generation of vector array `name` (takes the writer lock).
    pub fn discard_pending_vectors(&self, name: &str) -> Result<()> {
        check_name("vector", name)?;
        let _lock = self.writer_lock(&format!("vectors {name}"))?;
        let node = format!("neuvolex/vectors/{name}");
        let current = self.current_vectors(name)?.unwrap_or_default();
        drop_other_generations(&self.backend, &node, &current)
    }

    fn vector_markers(&self, name: &str, gen: &str, identity: &str) -> Result<DoneMarkers> {
        DoneMarkers::open_or_create(
            &self.backend,
            &format!("neuvolex/vectors/{name}/{gen}.done"),
            StageTag {
                stage: format!("vectors/{name}"),
                layout: layout_of(self.info.dims, self.info.brick),
                identity: identity.to_string(),
            },
            self.grid(),
        )
    }

    /// The published generation of vector array `name` ("" for an array written before
    /// generations), `None` if there is none.
    fn current_vectors(&self, name: &str) -> Result<Option<String>> {
        let node = format!("neuvolex/vectors/{name}");
        let v: Value = match crate::commit::committed_doc(&self.backend, &node)? {
            Some(v) => v,
            None => {
                let Some(bytes) = self.backend.get(&format!("{node}/zarr.json"))? else {
                    return Ok(None);
                };
                serde_json::from_slice(&bytes).map_err(|e| {
                    BrickError::corrupt(self.backend.key_path(&node), format!("zarr.json: {e}"))
                })?
            }
        };
        if v.get("node_type").and_then(Value::as_str) == Some("array") {
            return Ok(Some(String::new()));
        }
        v.pointer("/attributes/neuvolex/current")
            .and_then(Value::as_str)
            .map(|s| Some(s.to_string()))
            .ok_or_else(|| {
                BrickError::corrupt(
                    self.backend.key_path(&node),
                    "vector group names no current generation",
                )
            })
    }

    fn find_pending(&self, name: &str, identity: &str) -> Result<Option<VectorArray>> {
        let node = format!("neuvolex/vectors/{name}");
        let current = self.current_vectors(name)?.unwrap_or_default();
        let mut gens: Vec<(u64, String)> = self
            .backend
            .list_dir(&node)?
            .into_iter()
            .filter(|g| *g != current)
            .filter_map(|g| generation_number(&g).map(|n| (n, g)))
            .collect();
        gens.sort();
        for (_, gen) in gens.into_iter().rev() {
            let Ok(mut va) = self.open_vector_array(name, &gen) else {
                continue;
            };
            if va.info.complete {
                continue;
            }
            match va.info.identity.clone() {
                Some(id) if id == identity => {
                    va.done = Some(self.vector_markers(name, &gen, identity)?);
                    return Ok(Some(va));
                }
                Some(id) => {
                    return Err(BrickError::stage_mismatch(
                        self.backend.key_path(&va.path),
                        &format!("the pending vector array '{name}'"),
                        &format!("stage identity '{id}'"),
                        &format!("'{identity}'"),
                        "discard it (discard_pending_vectors, or --restart) to start \
                               over, or resume with the model and parameters it was written for",
                    ))
                }
                None => {}
            }
        }
        Ok(None)
    }

    fn new_vectors(
        &self,
        name: &str,
        channels: usize,
        encoding: VectorEncoding,
        identity: Option<&str>,
        lock: WriterLock,
    ) -> Result<VectorArray> {
        if channels == 0 || channels > 4096 {
            return Err(BrickError::InvalidArgument(format!(
                "{channels} channels: must be 1..=4096"
            )));
        }
        if let VectorEncoding::U8 { lo, hi } = &encoding {
            if lo.len() != channels
                || hi.len() != channels
                || lo
                    .iter()
                    .zip(hi)
                    .any(|(a, b)| !a.is_finite() || !b.is_finite() || b <= a)
            {
                return Err(BrickError::InvalidArgument(
                    "u8 quantisation needs finite lo < hi for every channel".into(),
                ));
            }
        }
        let node = format!("neuvolex/vectors/{name}");
        let gen = next_generation(&self.backend, &node)?;
        let d = self.info.dims;
        let b = self.info.brick as u64;
        let dtype_name = match encoding {
            VectorEncoding::F16 => zarrs::array::data_type::float16(),
            VectorEncoding::U8 { .. } => zarrs::array::data_type::uint8(),
        };
        let path = format!("/{node}/{gen}");
        let vinfo = VectorInfo {
            channels,
            encoding,
            complete: false,
            extra: Value::Null,
            identity: identity.map(str::to_string),
        };
        let mut builder = ArrayBuilder::new(
            vec![d[2] as u64, d[1] as u64, d[0] as u64, channels as u64],
            vec![b, b, b, channels as u64],
            dtype_name,
            0u8,
        );
        builder.bytes_to_bytes_codecs(vec![Arc::new(zarrs::array::codec::ZstdCodec::new(
            3, false,
        ))]);
        builder.dimension_names(Some(
            ["z", "y", "x", "c"].map(|s| Some(s.to_string())).to_vec(),
        ));
        builder.attributes(
            json!({"neuvolex": vinfo})
                .as_object()
                .cloned()
                .unwrap_or_default(),
        );
        let array = builder
            .build(self.storage.clone(), &path)
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        array
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        Ok(VectorArray {
            root: self.root.clone(),
            path,
            array,
            info: vinfo,
            brick: self.info.brick,
            dims: d,
            backend: self.backend.clone(),
            name: name.to_string(),
            generation: gen,
            lock: Some(lock),
            done: None,
        })
    }

    fn open_vector_array(&self, name: &str, gen: &str) -> Result<VectorArray> {
        let path = if gen.is_empty() {
            format!("/neuvolex/vectors/{name}")
        } else {
            format!("/neuvolex/vectors/{name}/{gen}")
        };
        read_node(&self.backend, &path)?;
        let dir = self.backend.key_path(&path);
        let array: ZArray = Array::open(self.storage.clone(), &path)
            .map_err(|e| BrickError::corrupt(&dir, e.to_string()))?;
        let info: VectorInfo = array
            .attributes()
            .get("neuvolex")
            .cloned()
            .and_then(|v| serde_json::from_value(v).ok())
            .ok_or_else(|| {
                BrickError::corrupt(&dir, "vector array has no valid neuvolex attributes")
            })?;
        Ok(VectorArray {
            root: self.root.clone(),
            path,
            array,
            info,
            brick: self.info.brick,
            dims: self.info.dims,
            backend: self.backend.clone(),
            name: name.to_string(),
            generation: gen.to_string(),
            lock: None,
            done: None,
        })
    }

    /// True if the store has a published vector array `name`.
    pub fn has_vectors(&self, name: &str) -> Result<bool> {
        check_name("vector", name)?;
        Ok(self.current_vectors(name)?.is_some())
    }

    /// Opens the published vector array `name` (its current generation).
    pub fn open_vectors(&self, name: &str) -> Result<VectorArray> {
        check_name("vector", name)?;
        match self.current_vectors(name)? {
            Some(gen) => self.open_vector_array(name, &gen),
            None => Err(BrickError::corrupt(
                self.backend.key_path(&format!("neuvolex/vectors/{name}")),
                format!(
                    "no zarr.json metadata: the store has no vector array '{name}' \
                     (run the stage that writes it)"
                ),
            )),
        }
    }
}

/// The generation number of a child name `vN`.
fn generation_number(name: &str) -> Option<u64> {
    name.strip_prefix('v')
        .filter(|d| !d.is_empty() && d.bytes().all(|c| c.is_ascii_digit()))
        .and_then(|d| d.parse().ok())
}

/// The next free generation name (`v1`, `v2`, ...) under node `node`.
fn next_generation(backend: &Backend, node: &str) -> Result<String> {
    let n = backend
        .list_dir(node)?
        .iter()
        .filter_map(|c| generation_number(c.strip_suffix(".done").unwrap_or(c)))
        .max()
        .unwrap_or(0);
    Ok(format!("v{}", n + 1))
}

/// Deletes every child of `node` except its `zarr.json` and generation `keep`: older
/// generations, abandoned pending ones, their markers, and the arrays of the layout before
/// generations.
pub(crate) fn drop_other_generations(backend: &Backend, node: &str, keep: &str) -> Result<()> {
    for child in backend.list_dir(node)? {
        if child == "zarr.json" || (!keep.is_empty() && child == keep) || child.starts_with('.') {
            continue;
        }
        let key = format!("{node}/{child}");
        if !child.ends_with(".done") {
            delete_node(backend, &key)?;
            continue;
        }
        // Done markers of a finished generation: a cluster worker running a late duplicate of a
        // task (redelivered after its first worker went quiet) may still add one while they are
        // deleted. They are no longer read, so a folder that will not go is left, with a warning.
        let mut tries = 0;
        while let Err(e) = delete_node(backend, &key) {
            tries += 1;
            if tries == 5 {
                tracing::warn!("{}: left in place: {e}", backend.key_path(&key).display());
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }
    Ok(())
}

/// A per-voxel vector array (features, class probabilities) in the store: a published
/// generation opened for reading, or a pending one being written.
pub struct VectorArray {
    root: PathBuf,
    path: String,
    array: ZArray,
    info: VectorInfo,
    brick: usize,
    dims: [usize; 3],
    backend: Arc<Backend>,
    name: String,
    generation: String,
    lock: Option<WriterLock>,
    done: Option<DoneMarkers>,
}

impl std::fmt::Debug for VectorArray {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VectorArray")
            .field("array", &self.backend.key_path(&self.path))
            .field("channels", &self.info.channels)
            .field("complete", &self.info.complete)
            .finish()
    }
}

impl VectorArray {
    /// Channels and encoding.
    pub fn info(&self) -> &VectorInfo {
        &self.info
    }

    fn chunk_of(&self, b: &Brick) -> Result<[u64; 4]> {
        let g = grid_of(self.dims, self.brick);
        if (0..3).any(|k| b.index[k] >= g[k])
            || b.origin
                != [
                    b.index[0] * self.brick,
                    b.index[1] * self.brick,
                    b.index[2] * self.brick,
                ]
        {
            return Err(BrickError::InvalidArgument(format!(
                "brick {:?} does not belong to this store's grid",
                b.index
            )));
        }
        Ok([b.index[2] as u64, b.index[1] as u64, b.index[0] as u64, 0])
    }

    /// Writes one brick of vectors: `values` has `brick.voxels() * channels` entries, voxel-major
    /// (channels fastest), voxels x fastest.
    pub fn write_brick(&self, b: &Brick, values: &[f32]) -> Result<()> {
        let c = self.info.channels;
        if values.len() != b.voxels() * c {
            return Err(BrickError::InvalidArgument(format!(
                "brick {:?} needs {} values ({} voxels x {c}), got {}",
                b.index,
                b.voxels() * c,
                b.voxels(),
                values.len()
            )));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(BrickError::InvalidArgument(format!(
                "vector value {} at index {i} of brick {:?} is not finite",
                values[i], b.index
            )));
        }
        let _ = self.chunk_of(b)?;
        let mut sub = zyx(b.origin, b.size);
        sub.push(0..c as u64);
        let r = match &self.info.encoding {
            VectorEncoding::F16 => {
                let v: Vec<half::f16> = values.iter().map(|&x| half::f16::from_f32(x)).collect();
                write_bytes(&self.array, &sub, bytemuck::cast_slice(&v).to_vec())
            }
            VectorEncoding::U8 { lo, hi } => {
                let v: Vec<u8> = values
                    .iter()
                    .enumerate()
                    .map(|(i, &x)| {
                        let (l, h) = (lo[i % c], hi[i % c]);
                        (((x - l) / (h - l)).clamp(0.0, 1.0) * 255.0).round() as u8
                    })
                    .collect();
                write_bytes(&self.array, &sub, v)
            }
        };
        r.map_err(|e| BrickError::zarr(&self.root, e))
    }

    /// Reads one brick of vectors (voxel-major, channels fastest). A brick never written is an
    /// error ([`BrickError::MissingChunk`]).
    pub fn read_brick(&self, b: &Brick) -> Result<Vec<f32>> {
        let _ = self.chunk_of(b)?;
        let c = self.info.channels;
        let mut sub = zyx(b.origin, b.size);
        sub.push(0..c as u64);
        check_chunks_exist(&self.array, &self.root, &self.path, &sub)?;
        let bytes =
            read_bytes(&self.array, &sub).map_err(|e| BrickError::corrupt(&self.root, e))?;
        Ok(match &self.info.encoding {
            VectorEncoding::F16 => bytemuck::pod_collect_to_vec::<u8, half::f16>(&bytes)
                .iter()
                .map(|h| h.to_f32())
                .collect(),
            VectorEncoding::U8 { lo, hi } => bytes
                .iter()
                .enumerate()
                .map(|(i, &q)| lo[i % c] + (hi[i % c] - lo[i % c]) * q as f32 / 255.0)
                .collect(),
        })
    }

    /// Sets the provenance recorded with the array (stored by [`Self::finish`]).
    pub fn set_extra(&mut self, extra: Value) {
        self.info.extra = extra;
    }

    /// The generation this handle reads or writes (`v1`, `v2`, ...).
    pub fn generation(&self) -> &str {
        &self.generation
    }

    /// The done markers of a resumable writer ([`BrickStore::resume_vectors`]).
    pub fn markers(&self) -> Option<&DoneMarkers> {
        self.done.as_ref()
    }

    fn need_markers(&self) -> Result<&DoneMarkers> {
        self.done.as_ref().ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "{}: vector array '{}' has no done markers (open it with resume_vectors)",
                self.root.display(),
                self.name
            ))
        })
    }

    /// True if brick `b` is marked done (resumable writers).
    pub fn is_done(&self, b: &Brick) -> Result<bool> {
        self.need_markers()?.is_done(b)
    }

    /// Marks brick `b` done; call it after [`Self::write_brick`] returned (the chunk is then
    /// durable).
    pub fn mark_done(&self, b: &Brick) -> Result<()> {
        self.need_markers()?.mark_done(b)
    }

    /// The bricks of `bricks` not yet marked done, in their order (resumable writers).
    pub fn pending(&self, bricks: impl IntoIterator<Item = Brick>) -> Result<Vec<Brick>> {
        self.need_markers()?.pending(bricks)
    }

    /// Marks the array complete and publishes it: one commit makes this generation the
    /// current one, then the previous generation and the done markers are deleted and the
    /// writer lock is released. Only the writer that holds the lock (from
    /// [`BrickStore::create_vectors`] or [`BrickStore::resume_vectors`]) can publish.
    pub fn finish(&mut self) -> Result<()> {
        let mut commit = Commit::new();
        self.finish_into(&mut commit)?;
        commit.publish(&self.backend)
    }

    /// Marks the array complete and adds its publication to `commit` (with the writer lock),
    /// so it appears together with the step's other outputs when the commit is published.
    pub fn finish_into(&mut self, commit: &mut Commit) -> Result<()> {
        let Some(lock) = self.lock.take() else {
            return Err(BrickError::InvalidArgument(format!(
                "{}: vector array '{}' was opened for reading or as a worker; only its                  writer publishes it",
                self.root.display(),
                self.name
            )));
        };
        self.info.complete = true;
        self.array.attributes_mut().insert(
            "neuvolex".into(),
            serde_json::to_value(&self.info)
                .map_err(|e| BrickError::corrupt(&self.root, e.to_string()))?,
        );
        self.array
            .store_metadata()
            .map_err(|e| BrickError::zarr(&self.root, e))?;
        lock.check()?;
        commit.hold(lock);
        let node = format!("neuvolex/vectors/{}", self.name);
        commit.write(
            &node,
            group_doc(
                json!({"neuvolex": {"current": self.generation}})
                    .as_object()
                    .cloned()
                    .unwrap_or_default(),
            ),
        );
        commit.keep_only(&node, &self.generation);
        self.done = None;
        Ok(())
    }
}

/// Checks the name of a label image or vector array (`what`): non-empty, letters, digits, `_`
/// or `-` only, so it is one safe path component.
pub fn check_name(what: &str, name: &str) -> Result<()> {
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        return Err(BrickError::InvalidArgument(format!(
            "{what} name '{name}' must be alphanumeric, '_' or '-'"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod scanner_tests {
    use super::*;
    use neuvolex_formats::meta::MemVolume;

    fn volume() -> MemVolume {
        let dims = [23, 17, 41];
        let v: Vec<f32> = (0..dims.iter().product::<usize>())
            .map(|i| ((i as f32) * 0.37).sin() * 1e3 + (i % 13) as f32 * 1e-3 + 7.5)
            .collect();
        MemVolume::from_f32(dims, &v)
    }

    /// Scans `parts` (ranges of z-slices, in any order) into separate scanners and merges them.
    fn scan(src: &mut MemVolume, parts: &[(usize, usize)]) -> (VolumeStats, Vec<f64>, Vec<f64>) {
        let meta = src.meta.clone();
        let first = first_raw_value(&src.read_slab(0, 1).unwrap());
        let mut total = Scanner::with_shift(&meta, 8, first);
        for &(z0, d) in parts {
            let mut s = Scanner::with_shift(&meta, 8, first);
            s.add_slab(
                &mut src.read_slab(z0, d).unwrap(),
                NonFinitePolicy::Reject,
                Path::new("m"),
            )
            .unwrap();
            total.merge(s).unwrap();
        }
        let (lo, hi) = total.range();
        let mut fine = FineHistogram::new(lo, hi);
        for &(z0, d) in parts.iter().rev() {
            let mut f = FineHistogram::new(lo, hi);
            f.add(&src.read_slab(z0, d).unwrap().to_f32_scaled(&meta));
            fine.merge(&f);
        }
        total.finish(Some(fine))
    }

    #[test]
    fn merged_parts_equal_one_scan_bit_for_bit() {
        let mut src = volume();
        let whole = scan(&mut src, &[(0, 41)]);
        let split = scan(&mut src, &[(24, 17), (0, 8), (8, 16)]);
        let bits =
            |s: &VolumeStats| [s.min, s.max, s.mean, s.std, s.p0_5, s.p99_5].map(f64::to_bits);
        assert_eq!(bits(&whole.0), bits(&split.0));
        assert_eq!(whole.0, split.0);
        assert_eq!(whole.1, split.1);
        assert_eq!(whole.2, split.2);
        // The scan through `Scanner::new` (the shift from the first slab) is the same too.
        let mut s = Scanner::new(&src.meta, 8);
        s.add_slab(
            &mut src.read_slab(0, 41).unwrap(),
            NonFinitePolicy::Reject,
            Path::new("m"),
        )
        .unwrap();
        let (lo, hi) = s.range();
        let mut fine = FineHistogram::new(lo, hi);
        fine.add(&src.read_slab(0, 41).unwrap().to_f32_scaled(&src.meta));
        assert_eq!(s.finish(Some(fine)).0, whole.0);
    }

    #[test]
    fn scanners_of_different_grids_do_not_merge() {
        let src = volume();
        let mut a = Scanner::new(&src.meta, 8);
        let b = Scanner::new(&src.meta, 16);
        assert!(a.merge(b).is_err());
    }
}
