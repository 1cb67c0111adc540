//! Headerless raw volumes, memory-mapped with memmap2.
//!
//! The layout comes from explicit parameters ([`RawSpec`]), a JSON sidecar (`X.raw.json` or
//! `X.json`), or a file name of the form `name_WxHxD_dtype.raw` (as the Open SciVis data sets are named).

use crate::dtype::{DType, Endian};
use crate::error::{FormatError, Result};
use crate::geometry::diag_affine;
use crate::meta::{validate_dims, VolumeMeta};
use crate::stream::{ByteStream, FileVolume};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Layout of a raw file: what a sidecar JSON holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RawSpec {
    /// Voxel counts along x, y, z.
    pub dims: [usize; 3],
    /// Voxel type.
    pub dtype: DType,
    /// Byte order.
    #[serde(default)]
    pub endian: Endian,
    /// Voxel size (defaults to 1).
    #[serde(default = "unit_spacing")]
    pub spacing: [f64; 3],
    /// Bytes to skip before the data.
    #[serde(default)]
    pub offset: u64,
}

fn unit_spacing() -> [f64; 3] {
    [1.0; 3]
}

impl RawSpec {
    /// Finds the layout of `path`: a sidecar JSON if one exists, else the file-name pattern.
    pub fn discover(path: &Path) -> Result<Option<RawSpec>> {
        let mut candidates = vec![PathBuf::from(format!("{}.json", path.display()))];
        candidates.push(path.with_extension("json"));
        for c in candidates {
            if c.is_file() {
                let text = std::fs::read_to_string(&c).map_err(|e| FormatError::io(&c, e))?;
                let spec: RawSpec = serde_json::from_str(&text)
                    .map_err(|e| FormatError::header(&c, format!("raw sidecar JSON: {e}")))?;
                return Ok(Some(spec));
            }
        }
        Ok(Self::from_name(path))
    }

    /// Parses `name_WxHxD_dtype.raw`.
    pub fn from_name(path: &Path) -> Option<RawSpec> {
        let stem = path.file_stem()?.to_str()?;
        let parts: Vec<&str> = stem.split('_').collect();
        if parts.len() < 2 {
            return None;
        }
        let dtype = DType::parse(parts[parts.len() - 1])?;
        let d: Vec<usize> = parts[parts.len() - 2]
            .split('x')
            .map(|s| s.parse().ok())
            .collect::<Option<_>>()?;
        if d.len() != 3 {
            return None;
        }
        Some(RawSpec {
            dims: [d[0], d[1], d[2]],
            dtype,
            endian: Endian::Little,
            spacing: [1.0; 3],
            offset: 0,
        })
    }
}

/// Maps a raw file with the given layout. The file size must match exactly.
pub fn open(path: &Path, spec: &RawSpec) -> Result<FileVolume> {
    validate_dims(path, spec.dims)?;
    let meta = VolumeMeta {
        dims: spec.dims,
        spacing: spec.spacing,
        affine: diag_affine(spec.spacing, [0.0; 3]),
        dtype: spec.dtype,
        scaling: None,
        nifti: None,
    };
    meta.validate(path)?;
    let len = meta.voxels() * spec.dtype.size() as u64;
    let stream = ByteStream::plain(path, spec.offset, len, true)?;
    Ok(FileVolume::new(path, meta, spec.endian, stream))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn name_pattern() {
        let s = RawSpec::from_name(Path::new("/d/tooth_103x94x161_uint8.raw")).unwrap();
        assert_eq!(s.dims, [103, 94, 161]);
        assert_eq!(s.dtype, DType::U8);
        assert!(RawSpec::from_name(Path::new("plain.raw")).is_none());
    }
}
