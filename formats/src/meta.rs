//! The one volume model every reader produces, and the streaming source trait.

use crate::dtype::{bytes_to_f32, bytes_to_f64, DType};
use crate::error::{FormatError, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest accepted extent of one axis. Larger values are treated as corrupt headers.
pub const MAX_DIM: usize = 1 << 20;
/// Largest accepted voxel count (2^40, about a terabyte of u8).
pub const MAX_VOXELS: u64 = 1 << 40;

/// Grid, geometry and type of a volume. Axes are (x, y, z) with x varying fastest in memory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeMeta {
    /// Voxel counts along x, y, z.
    pub dims: [usize; 3],
    /// Voxel size along x, y, z (millimetres for medical images).
    pub spacing: [f64; 3],
    /// Row-major 4x4 voxel-index -> world affine (last row 0 0 0 1).
    pub affine: [[f64; 4]; 4],
    /// Voxel type as stored in the source.
    pub dtype: DType,
    /// Linear intensity scaling `(slope, intercept)` applied on read (NIfTI `scl_*`); identity if `None`.
    pub scaling: Option<(f64, f64)>,
    /// The NIfTI sform and qform codes (and qform) of a volume read from NIfTI, so that files
    /// written for it carry the same frames; `None` for other sources.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nifti: Option<crate::geometry::NiftiFrame>,
}

impl VolumeMeta {
    /// A volume with unit spacing and an identity-scaled axis-aligned affine.
    pub fn new(dims: [usize; 3], dtype: DType) -> Self {
        VolumeMeta {
            dims,
            spacing: [1.0; 3],
            affine: crate::geometry::diag_affine([1.0; 3], [0.0; 3]),
            dtype,
            scaling: None,
            nifti: None,
        }
    }

    /// Number of voxels.
    pub fn voxels(&self) -> u64 {
        self.dims.iter().map(|&d| d as u64).product()
    }

    /// Voxels in one z-slice.
    pub fn slice_len(&self) -> usize {
        self.dims[0] * self.dims[1]
    }

    /// World origin (the affine's translation).
    pub fn origin(&self) -> [f64; 3] {
        [self.affine[0][3], self.affine[1][3], self.affine[2][3]]
    }

    /// Applies the intensity scaling to a raw value.
    pub fn scale(&self, raw: f64) -> f64 {
        match self.scaling {
            Some((s, i)) => raw * s + i,
            None => raw,
        }
    }

    /// Checks that the grid is non-empty and not absurdly large.
    pub fn validate(&self, path: &Path) -> Result<()> {
        validate_dims(path, self.dims)?;
        for (i, s) in self.spacing.iter().enumerate() {
            if !s.is_finite() || *s <= 0.0 {
                return Err(FormatError::header(
                    path,
                    format!("spacing along axis {i} is {s}; it must be finite and positive"),
                ));
            }
        }
        if self.affine.iter().flatten().any(|v| !v.is_finite()) {
            return Err(FormatError::header(path, "affine contains NaN or Inf"));
        }
        Ok(())
    }

    /// Errors unless `other` (a label volume at `path`) lies on the same grid.
    pub fn check_same_grid(&self, other: &VolumeMeta, path: &Path) -> Result<()> {
        if self.dims != other.dims {
            return Err(FormatError::GridMismatch {
                path: path.to_path_buf(),
                detail: format!(
                    "dims {:?} differ from the image's {:?}",
                    other.dims, self.dims
                ),
            });
        }
        for i in 0..3 {
            let (a, b) = (self.spacing[i], other.spacing[i]);
            if (a - b).abs() > 1e-3 * a.abs().max(b.abs()) {
                return Err(FormatError::GridMismatch {
                    path: path.to_path_buf(),
                    detail: format!(
                        "spacing {:?} differs from the image's {:?}",
                        other.spacing, self.spacing
                    ),
                });
            }
        }
        Ok(())
    }
}

/// Validates grid dimensions: each in 1..=MAX_DIM and the product at most MAX_VOXELS.
pub fn validate_dims(path: &Path, dims: [usize; 3]) -> Result<()> {
    for (i, &d) in dims.iter().enumerate() {
        if d == 0 {
            return Err(FormatError::BadDims {
                path: path.to_path_buf(),
                detail: format!(
                    "axis {} has size 0 (empty volume)",
                    "xyz".as_bytes()[i] as char
                ),
            });
        }
        if d > MAX_DIM {
            return Err(FormatError::BadDims {
                path: path.to_path_buf(),
                detail: format!(
                    "axis {} has size {d}, above the limit {MAX_DIM}",
                    "xyz".as_bytes()[i] as char
                ),
            });
        }
    }
    let n = dims.iter().map(|&d| d as u64).product::<u64>();
    if n > MAX_VOXELS {
        return Err(FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!("{n} voxels exceeds the limit {MAX_VOXELS}"),
        });
    }
    Ok(())
}

/// Parses signed header dimensions (as NIfTI/NRRD write them) into a validated grid.
pub fn dims_from_i64(path: &Path, raw: [i64; 3]) -> Result<[usize; 3]> {
    let mut dims = [0usize; 3];
    for i in 0..3 {
        if raw[i] < 0 {
            return Err(FormatError::BadDims {
                path: path.to_path_buf(),
                detail: format!(
                    "axis {} has negative size {}",
                    "xyz".as_bytes()[i] as char,
                    raw[i]
                ),
            });
        }
        dims[i] = usize::try_from(raw[i]).map_err(|_| FormatError::BadDims {
            path: path.to_path_buf(),
            detail: format!("axis size {} overflows", raw[i]),
        })?;
    }
    validate_dims(path, dims)?;
    Ok(dims)
}

/// A contiguous run of z-slices in the source's native voxel type (native byte order).
#[derive(Debug, Clone)]
pub struct Slab {
    /// First z-slice.
    pub z0: usize,
    /// Number of slices.
    pub depth: usize,
    /// Voxel type of `bytes`.
    pub dtype: DType,
    /// Native-endian voxel bytes, x fastest, then y, then z.
    pub bytes: Vec<u8>,
}

impl Slab {
    /// Number of voxels.
    pub fn len(&self) -> usize {
        self.bytes.len() / self.dtype.size()
    }

    /// True when the slab holds no voxels.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Raw values as f64 (scaling not applied).
    pub fn to_f64(&self) -> Vec<f64> {
        let mut v = vec![0.0; self.len()];
        bytes_to_f64(&self.bytes, self.dtype, &mut v);
        v
    }

    /// Values as f32 with `meta`'s scaling applied.
    pub fn to_f32_scaled(&self, meta: &VolumeMeta) -> Vec<f32> {
        let mut v = vec![0.0f32; self.len()];
        bytes_to_f32(&self.bytes, self.dtype, &mut v);
        if let Some((s, i)) = meta.scaling {
            v.iter_mut().for_each(|x| *x = (*x as f64 * s + i) as f32);
        }
        v
    }
}

/// A volume that can be read slab by slab, front to back, without holding it whole.
///
/// Readers over compressed streams read sequentially; asking for an earlier slab restarts them.
pub trait VolumeSource: Send {
    /// The volume's grid, geometry and type.
    fn meta(&self) -> &VolumeMeta;
    /// The file or store the volume comes from (for error messages).
    fn path(&self) -> &Path;
    /// Reads z-slices `z0..z0+depth`.
    fn read_slab(&mut self, z0: usize, depth: usize) -> Result<Slab>;
    /// Releases cached pages of already-read data (memory-mapped sources); a no-op elsewhere.
    fn release(&mut self, _z0: usize, _depth: usize) {}
}

/// A whole volume held in memory (tests, synthetic scenes, small previews).
#[derive(Debug, Clone)]
pub struct MemVolume {
    /// Grid and geometry. `dtype` describes `bytes`.
    pub meta: VolumeMeta,
    /// Native-endian voxel bytes.
    pub bytes: Vec<u8>,
    /// A name used in error messages.
    pub name: PathBuf,
}

impl MemVolume {
    /// Builds an f32 volume from values (x fastest).
    pub fn from_f32(dims: [usize; 3], values: &[f32]) -> Self {
        assert_eq!(values.len(), dims.iter().product::<usize>());
        MemVolume {
            meta: VolumeMeta::new(dims, DType::F32),
            bytes: bytemuck::cast_slice(values).to_vec(),
            name: PathBuf::from("<memory>"),
        }
    }

    /// Builds a volume of `dtype` from f64 values (rounded and saturated for integer types).
    pub fn from_f64(dims: [usize; 3], dtype: DType, values: &[f64]) -> Self {
        assert_eq!(values.len(), dims.iter().product::<usize>());
        MemVolume {
            meta: VolumeMeta::new(dims, dtype),
            bytes: crate::dtype::f64_to_bytes(values, dtype),
            name: PathBuf::from("<memory>"),
        }
    }

    /// Reads every voxel of `source` into memory (for small volumes only).
    pub fn read_all(source: &mut dyn VolumeSource) -> Result<Self> {
        let meta = source.meta().clone();
        let slab = source.read_slab(0, meta.dims[2])?;
        Ok(MemVolume {
            meta,
            bytes: slab.bytes,
            name: source.path().to_path_buf(),
        })
    }

    /// Values as f32 with scaling applied.
    pub fn to_f32(&self) -> Vec<f32> {
        let slab = Slab {
            z0: 0,
            depth: self.meta.dims[2],
            dtype: self.meta.dtype,
            bytes: self.bytes.clone(),
        };
        slab.to_f32_scaled(&self.meta)
    }
}

impl VolumeSource for MemVolume {
    fn meta(&self) -> &VolumeMeta {
        &self.meta
    }
    fn path(&self) -> &Path {
        &self.name
    }
    fn read_slab(&mut self, z0: usize, depth: usize) -> Result<Slab> {
        slab_of(&self.meta, &self.name, &self.bytes, z0, depth)
    }
}

/// Z-slices `z0..z0+depth` of a whole volume held as bytes (`meta.dtype`, x fastest), copied:
/// the `read_slab` of in-memory sources.
pub fn slab_of(
    meta: &VolumeMeta,
    name: &Path,
    bytes: &[u8],
    z0: usize,
    depth: usize,
) -> Result<Slab> {
    check_slab_range(meta, name, z0, depth)?;
    let sl = meta.slice_len() * meta.dtype.size();
    Ok(Slab {
        z0,
        depth,
        dtype: meta.dtype,
        bytes: bytes[z0 * sl..(z0 + depth) * sl].to_vec(),
    })
}

/// Errors unless `z0..z0+depth` lies inside the volume.
pub fn check_slab_range(meta: &VolumeMeta, path: &Path, z0: usize, depth: usize) -> Result<()> {
    if depth == 0 || z0.checked_add(depth).is_none_or(|e| e > meta.dims[2]) {
        return Err(FormatError::InvalidArgument(format!(
            "{}: slab z={z0}..{} outside 0..{}",
            path.display(),
            z0.saturating_add(depth),
            meta.dims[2]
        )));
    }
    Ok(())
}
