//! Slices and overlays as PNG bytes.

use crate::error::{ApiError, ApiResult};

/// Encodes 8-bit pixels (`channels` 1, 3 or 4) as PNG.
pub fn png(width: usize, height: usize, channels: usize, data: &[u8]) -> ApiResult<Vec<u8>> {
    neuvolex_render::image::encode_png(width, height, channels, data)
        .map_err(|e| ApiError::Internal(e.to_string()))
}

/// Slice geometry: which axis is fixed, and the image's (column, row) volume axes. Rows run
/// from high to low on the vertical axis for coronal and sagittal slices (superior up).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SliceAxes {
    /// Fixed axis (0 x, 1 y, 2 z).
    pub fixed: usize,
    /// Volume axis along image columns.
    pub u: usize,
    /// Volume axis along image rows.
    pub v: usize,
    /// Rows count down the volume axis.
    pub flip_v: bool,
}

impl SliceAxes {
    /// Parses `x`, `y` or `z`.
    pub fn parse(axis: &str) -> ApiResult<SliceAxes> {
        Ok(match axis {
            "z" => SliceAxes {
                fixed: 2,
                u: 0,
                v: 1,
                flip_v: false,
            },
            "y" => SliceAxes {
                fixed: 1,
                u: 0,
                v: 2,
                flip_v: true,
            },
            "x" => SliceAxes {
                fixed: 0,
                u: 1,
                v: 2,
                flip_v: true,
            },
            o => {
                return Err(ApiError::BadRequest(format!(
                    "axis '{}' must be x, y or z",
                    o.escape_debug()
                )))
            }
        })
    }

    /// Volume voxel of image pixel `(i, j)` on slice `s`.
    pub fn voxel(&self, dims: [usize; 3], s: usize, i: usize, j: usize) -> [usize; 3] {
        let mut p = [0; 3];
        p[self.fixed] = s;
        p[self.u] = i;
        p[self.v] = if self.flip_v { dims[self.v] - 1 - j } else { j };
        p
    }
}

/// Maps raw values through a window (width) and level (centre) to 8-bit grey.
pub fn window(values: &[f32], level: f64, width: f64) -> Vec<u8> {
    let w = if width.is_finite() && width > 0.0 {
        width
    } else {
        1.0
    };
    let lo = level - w / 2.0;
    values
        .iter()
        .map(|&v| (((v as f64 - lo) / w).clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// A training preview as a grey PNG: the reconstruction (left) beside the input (right), both
/// normalised to [0, 1] (values outside are clamped).
pub fn preview_png(
    width: usize,
    height: usize,
    recon: &[f32],
    truth: &[f32],
) -> ApiResult<Vec<u8>> {
    let n = width * height;
    if recon.len() != n || truth.len() != n || n == 0 {
        return Err(ApiError::Internal(format!(
            "preview of {width}x{height} has {} and {} values",
            recon.len(),
            truth.len()
        )));
    }
    let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut px = vec![0u8; 2 * n];
    for y in 0..height {
        for x in 0..width {
            px[y * 2 * width + x] = to_u8(recon[y * width + x]);
            px[y * 2 * width + width + x] = to_u8(truth[y * width + x]);
        }
    }
    png(2 * width, height, 1, &px)
}

/// Whether a volume's stored intensities look like CT Hounsfield units (so its window presets
/// and readout are in HU). The store keeps the source's values after NIfTI `scl_slope` and
/// `scl_inter`, and no modality tag survives ingest, so this decides from the data: CT holds air
/// at about -1000 HU (scanners pad with -1024, -2048 or -3024), and MRI, PET and microscopy
/// hold no values below -500. A minimum in [-3100, -500] therefore means CT.
pub fn looks_like_ct(min: f64) -> bool {
    (-3100.0..=-500.0).contains(&min)
}

/// The unit of a volume's stored intensities: `HU` for CT ([`looks_like_ct`]), else empty
/// (arbitrary scanner units).
pub fn intensity_unit(min: f64) -> &'static str {
    if looks_like_ct(min) {
        "HU"
    } else {
        ""
    }
}
