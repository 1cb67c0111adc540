//! The per-slab writer of an ingest's image pyramid, and the pyramid's mean downsampling.

use crate::options::IngestOptions;
use crate::scan::{background_threshold, Scanner};
use crate::stats::FineHistogram;
use crate::target::IngestTarget;
use neuvolex_bricks::layout::{
    build_array, grid_of, level_chunk, write_root_attrs, zyx, StoreInfo, STORE_VERSION,
};
use neuvolex_bricks::omezarr::{read_bytes, write_bytes, write_slab_chunks, ZArray};
use neuvolex_bricks::{Backend, BrickError, Result};
use neuvolex_formats::dtype::DType;
use neuvolex_formats::meta::VolumeMeta;
use std::path::{Path, PathBuf};
use zarrs::array::Array;
use zarrs::group::GroupBuilder;
use zarrs::storage::ReadableWritableListableStorage;

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
fn downsample_slab(slab: &neuvolex_formats::Slab, meta: &VolumeMeta) -> Vec<f32> {
    let (nx, ny) = (meta.dims[0], meta.dims[1]);
    let sl = nx * ny * slab.dtype.size();
    let mut out = Vec::with_capacity(nx.div_ceil(2) * ny.div_ceil(2) * slab.depth.div_ceil(2));
    let mut z = 0;
    while z < slab.depth {
        let d = 2.min(slab.depth - z);
        let pair = neuvolex_formats::Slab {
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
                    opts.shard,
                    opts.zstd_level,
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

    /// The brick edge.
    pub fn brick(&self) -> usize {
        self.opts.brick
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
        slab: &mut neuvolex_formats::Slab,
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
                None,
                opts.zstd_level,
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
            nifti: meta.nifti.clone(),
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
