//! The store's on-disk layout: the root attributes ([`StoreInfo`]), the brick grid
//! ([`Brick`]), how arrays are made (zstd, optional sharding, `c.z.y.x` keys) and the pyramid's
//! chunking. Every writer of a store (ingest, label images, vector arrays) builds through here.

use crate::error::{BrickError, Result};
use crate::omezarr::{multiscales, zarr_dtype, ZArray};
use crate::stats::VolumeStats;
use neuvolex_formats::dtype::DType;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;
use zarrs::array::ArrayBuilder;
use zarrs::group::GroupBuilder;
use zarrs::storage::ReadableWritableListableStorage;

/// Version of the store layout written by this crate.
pub const STORE_VERSION: u32 = 1;

/// zstd level of arrays written with default options.
pub const DEFAULT_ZSTD_LEVEL: i32 = 3;

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
    /// The source's NIfTI sform and qform codes and qform (a NIfTI source only), so exports
    /// carry the same frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nifti: Option<neuvolex_formats::geometry::NiftiFrame>,
}

impl StoreInfo {
    /// Bricks per axis (x, y, z).
    pub fn grid(&self) -> [usize; 3] {
        grid_of(self.dims, self.brick)
    }
}

/// Bricks per axis (x, y, z) of a grid of `dims` in bricks of edge `brick`.
pub fn grid_of(dims: [usize; 3], brick: usize) -> [usize; 3] {
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

    /// Where each x-row of the brick starts in a volume of `dims` (x fastest), in the brick's
    /// own voxel order (z, then y); each row is `size[0]` voxels long.
    pub fn rows(&self, dims: [usize; 3]) -> impl Iterator<Item = usize> + '_ {
        (0..self.size[2]).flat_map(move |z| {
            (0..self.size[1]).map(move |y| {
                ((self.origin[2] + z) * dims[1] + self.origin[1] + y) * dims[0] + self.origin[0]
            })
        })
    }
}

/// The (z, y, x) ranges of the box at `origin` (x, y, z) of `size`.
pub fn zyx(origin: [usize; 3], size: [usize; 3]) -> Vec<Range<u64>> {
    (0..3)
        .rev()
        .map(|i| origin[i] as u64..(origin[i] + size[i]) as u64)
        .collect()
}

/// Creates the Zarr array `path` (z, y, x; zstd at `zstd_level`, `shard` chunks per shard edge
/// when sharded) and stores its metadata.
#[allow(clippy::too_many_arguments)]
pub fn build_array(
    storage: &ReadableWritableListableStorage,
    root: &Path,
    path: &str,
    shape_zyx: Vec<u64>,
    chunk_zyx: Vec<u64>,
    dtype: DType,
    shard: Option<usize>,
    zstd_level: i32,
) -> Result<ZArray> {
    let names: Vec<Option<String>> = vec![Some("z".into()), Some("y".into()), Some("x".into())];
    let (outer, inner) = match shard {
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
        zstd_level.clamp(1, 22),
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

/// Chunk (brick) extent (x, y, z) of pyramid level `k`: `brick` in x and y, `brick >> k` in z,
/// so that every level-0 slab of `brick` slices fills whole chunks at every level.
pub fn level_chunk(brick: usize, k: usize) -> [usize; 3] {
    [brick, brick, (brick >> k).max(1)]
}

/// 2x mode downsampling for labels; ties go to the smallest label.
pub fn downsample_mode(src: &[u32], dims: [usize; 3]) -> Vec<u32> {
    let od = [
        dims[0].div_ceil(2),
        dims[1].div_ceil(2),
        dims[2].div_ceil(2),
    ];
    let mut out = vec![0u32; od[0] * od[1] * od[2]];
    // Output planes in parallel (each is written by one task).
    out.par_chunks_mut(od[0] * od[1])
        .enumerate()
        .for_each(|(z, plane)| {
            let mut vals = [0u32; 8];
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
                    // Most of a label image is uniform: no sort where the eight agree.
                    if v.iter().all(|&a| a == v[0]) {
                        plane[y * od[0] + x] = v[0];
                        continue;
                    }
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
                    plane[y * od[0] + x] = best;
                }
            }
        });
    out
}

/// Writes the root group with [`root_attrs`] (last, when publishing a store).
pub fn write_root_attrs(
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
pub fn root_attrs(root: &Path, info: &StoreInfo) -> Result<serde_json::Map<String, Value>> {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The mode of each 2x2x2 block (ties to the smallest label), counted the slow way.
    fn mode_reference(src: &[u32], d: [usize; 3]) -> Vec<u32> {
        let od = d.map(|n| n.div_ceil(2));
        let mut out = Vec::new();
        for z in 0..od[2] {
            for y in 0..od[1] {
                for x in 0..od[0] {
                    let mut counts = std::collections::BTreeMap::<u32, usize>::new();
                    for (sx, sy, sz) in
                        (0..8).map(|k| (2 * x + k % 2, 2 * y + k / 2 % 2, 2 * z + k / 4))
                    {
                        if sx < d[0] && sy < d[1] && sz < d[2] {
                            *counts.entry(src[(sz * d[1] + sy) * d[0] + sx]).or_default() += 1;
                        }
                    }
                    let top = counts.values().copied().max().unwrap();
                    out.push(*counts.iter().find(|(_, &n)| n == top).unwrap().0);
                }
            }
        }
        out
    }

    /// Odd extents (partial blocks at every edge), uniform regions and mixed blocks with
    /// ties all match the reference.
    #[test]
    fn mode_downsampling_matches_the_reference_on_odd_grids_and_ties() {
        for d in [[7, 5, 3], [16, 9, 11], [1, 1, 1], [2, 3, 1]] {
            let n = d.iter().product::<usize>();
            let mut s = 12345u64;
            let src: Vec<u32> = (0..n)
                .map(|i| {
                    s = s
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    // A uniform half and a noisy half with few labels (frequent ties).
                    if i < n / 2 {
                        3
                    } else {
                        (s >> 60) as u32 % 4
                    }
                })
                .collect();
            assert_eq!(downsample_mode(&src, d), mode_reference(&src, d), "{d:?}");
        }
    }
}
