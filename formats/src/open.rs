//! Opening a volume file by path: format detection and the readers of this crate.
//!
//! OME-Zarr is detected here but read by the store crate (`neuvolex_bricks::open_volume`
//! opens any supported volume, Zarr included), because reading Zarr needs its storage
//! backends.

use crate::error::{FormatError, Result};
use crate::meta::VolumeSource;
use crate::raw::RawSpec;
use std::path::Path;

/// The on-disk formats neuvolex reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// NIfTI-1, optionally gzipped.
    Nifti,
    /// NRRD with attached or detached header.
    Nrrd,
    /// Headerless raw.
    Raw,
    /// OME-Zarr 0.5 (Zarr v3) image or label group, or a bare Zarr v3 array.
    OmeZarr,
}

/// Guesses the format of `path` from its name and content; an `s3://` URL is an OME-Zarr store.
pub fn detect_format(path: &Path) -> Result<Format> {
    if path.to_string_lossy().starts_with("s3://") {
        return Ok(Format::OmeZarr);
    }
    if !path.exists() {
        return Err(FormatError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or directory"),
        ));
    }
    let name = path.to_string_lossy().to_ascii_lowercase();
    let name = name.trim_end_matches('/');
    if path.is_dir() || name.ends_with(".zarr") {
        return Ok(Format::OmeZarr);
    }
    if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        return Ok(Format::Nifti);
    }
    if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        return Ok(Format::Nrrd);
    }
    if name.ends_with(".raw") || name.ends_with(".bin") || name.ends_with(".dat") {
        return Ok(Format::Raw);
    }
    // Sniff the content.
    let mut head = [0u8; 352];
    let n = {
        use std::io::Read;
        let mut f = std::fs::File::open(path).map_err(|e| FormatError::io(path, e))?;
        f.read(&mut head).map_err(|e| FormatError::io(path, e))?
    };
    if head[..n].starts_with(b"NRRD000") {
        return Ok(Format::Nrrd);
    }
    if n >= 348 && &head[344..348] == b"n+1\0" {
        return Ok(Format::Nifti);
    }
    Err(FormatError::UnknownFormat {
        path: path.to_path_buf(),
        detail: "expected .nii, .nii.gz, .nrrd, .nhdr, .raw (with --dims/--dtype or a sidecar) or a .zarr store".into(),
    })
}

/// Opens the file `path` (NIfTI, NRRD or raw) as a volume source. `raw` gives the layout of
/// headerless files; without it a sidecar JSON or a `name_WxHxD_dtype.raw` file name is
/// required. An OME-Zarr store is refused with [`FormatError::UnknownFormat`]: open it with
/// `neuvolex_bricks::open_volume`.
pub fn open_file(path: &Path, raw: Option<&RawSpec>) -> Result<Box<dyn VolumeSource>> {
    if let Some(spec) = raw {
        return Ok(Box::new(crate::raw::open(path, spec)?));
    }
    Ok(match detect_format(path)? {
        Format::Nifti => Box::new(crate::nifti::open(path)?),
        Format::Nrrd => Box::new(crate::nrrd::open(path)?),
        Format::OmeZarr => {
            return Err(FormatError::UnknownFormat {
                path: path.to_path_buf(),
                detail: "an OME-Zarr store is not a file: open it with the store crate".into(),
            })
        }
        Format::Raw => {
            let spec = RawSpec::discover(path)?.ok_or_else(|| FormatError::UnknownFormat {
                path: path.to_path_buf(),
                detail:
                    "raw file without layout: pass --dims X,Y,Z --dtype T [--endian big|little], \
                         add a JSON sidecar (X.raw.json), or name it name_WxHxD_dtype.raw"
                        .into(),
            })?;
            Box::new(crate::raw::open(path, &spec)?)
        }
    })
}
