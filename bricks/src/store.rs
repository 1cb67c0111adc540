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
use crate::derived::{HaloBrick, Normaliser};
use crate::done::{layout_of, DoneMarkers, StageTag};
use crate::error::{BrickError, Result};
use crate::layout::{level_chunk, zyx, Brick, StoreInfo, STORE_VERSION};
use crate::location::StoreLocation;
use crate::lock::WriterLock;
use crate::lru::Lru;
use crate::omezarr::{check_chunks_exist, read_bytes, read_node, ZArray};
use neuvolex_formats::dtype::DType;
use neuvolex_formats::meta::VolumeMeta;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::Array;
use zarrs::storage::ReadableWritableListableStorage;

/// True if `location` (a path or `s3://` URL) holds a neuvolex brick store, complete or not.
pub fn is_brick_store(location: impl Into<StoreLocation>) -> bool {
    Backend::open(&location.into())
        .and_then(|b| b.get("zarr.json"))
        .ok()
        .flatten()
        .is_some_and(|t| String::from_utf8_lossy(&t).contains("\"neuvolex\""))
}

/// An opened, complete brick store.
pub struct BrickStore {
    pub(crate) root: PathBuf,
    pub(crate) location: StoreLocation,
    pub(crate) backend: Arc<Backend>,
    pub(crate) storage: ReadableWritableListableStorage,
    pub(crate) info: StoreInfo,
    pub(crate) levels: Vec<ZArray>,
    pub(crate) brick_min: Vec<f64>,
    pub(crate) brick_max: Vec<f64>,
    /// Decoded bricks by (level, index); each costs 1, so the budget counts bricks.
    pub(crate) cache: Lru<(usize, [usize; 3]), Arc<Vec<f32>>>,
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
    /// Opens a store written by `neuvolex_ingest::ingest` at a path or `s3://` URL; errors if it is
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
            nifti: self.info.nifti.clone(),
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
        self.read_padded(b.origin, b.size, halo)
    }

    /// Reads the box `origin..origin+size` of level 0 with `halo` voxels on each side, every
    /// voxel outside the grid taking the value of the nearest voxel inside (edge-clamped): as
    /// [`Self::read_halo`] for a box that may be larger than a brick, or pass the grid's far
    /// ends (a block of bricks computed as one; its voxels past the grid are read but unused).
    pub fn read_padded(
        &self,
        origin: [usize; 3],
        size: [usize; 3],
        halo: usize,
    ) -> Result<HaloBrick> {
        let d = self.info.dims;
        if (0..3).any(|k| size[k] == 0 || origin[k] >= d[k]) {
            return Err(BrickError::InvalidArgument(format!(
                "box {origin:?}+{size:?} does not start inside the grid {d:?}"
            )));
        }
        let lo: Vec<usize> = (0..3).map(|k| origin[k].saturating_sub(halo)).collect();
        let hi: Vec<usize> = (0..3)
            .map(|k| (origin[k] + size[k] + halo).min(d[k]))
            .collect();
        let rs = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        let inner = self.read_box(0, [lo[0], lo[1], lo[2]], rs)?;
        let p = size.map(|s| s + 2 * halo);
        let mut data = vec![0.0f32; p[0] * p[1] * p[2]];
        let h = halo as isize;
        let at = |k: usize, i: usize| -> usize {
            ((origin[k] as isize + i as isize - h).clamp(lo[k] as isize, hi[k] as isize - 1)
                as usize)
                - lo[k]
        };
        let xs: Vec<usize> = (0..p[0]).map(|x| at(0, x)).collect();
        for (z, plane) in data.chunks_exact_mut(p[0] * p[1]).enumerate() {
            let sz = at(2, z);
            for (y, row) in plane.chunks_exact_mut(p[0]).enumerate() {
                let src = (sz * rs[1] + at(1, y)) * rs[0];
                for (v, &sx) in row.iter_mut().zip(&xs) {
                    *v = inner[src + sx];
                }
            }
        }
        Ok(HaloBrick {
            origin,
            size,
            halo,
            data,
        })
    }

    /// Derived quantities (normalised intensity, gradient, local mean/std) of a brick.
    pub fn derived(&self, b: &Brick) -> Result<crate::derived::DerivedBrick> {
        let h = self.read_halo(b, crate::derived::DERIVED_HALO)?;
        Ok(crate::derived::compute(&h, &self.normaliser()))
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
