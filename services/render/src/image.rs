//! Rendered images: linear RGB plus opacity in f32, PNG out and in, comparisons.

use crate::{RenderError, Result};
use std::path::Path;

/// An RGB image with per-pixel opacity, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// RGB in [0, 1], background composited.
    pub rgb: Vec<[f32; 3]>,
    /// Accumulated opacity of each pixel's ray.
    pub alpha: Vec<f32>,
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> RenderError {
    RenderError::Io {
        path: path.to_path_buf(),
        msg: e.to_string(),
    }
}

/// Encodes 8-bit pixels (`channels`: 1 grey, 3 RGB, 4 RGBA; rows top to bottom) as PNG bytes.
pub fn encode_png(width: usize, height: usize, channels: usize, data: &[u8]) -> Result<Vec<u8>> {
    let err = |e: png::EncodingError| RenderError::Input(format!("PNG encoding: {e}"));
    let color = match channels {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        4 => png::ColorType::Rgba,
        c => {
            return Err(RenderError::Input(format!(
                "{c} channels: PNG needs 1, 3 or 4"
            )))
        }
    };
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width as u32, height as u32);
        enc.set_color(color);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(err)?;
        w.write_image_data(data).map_err(err)?;
        w.finish().map_err(err)?;
    }
    Ok(out)
}

impl Image {
    /// 8-bit RGB bytes.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.rgb
            .iter()
            .flat_map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8))
            .collect()
    }

    /// Writes an 8-bit RGB PNG: to a temporary file renamed into place, so a failed write
    /// leaves any existing file intact.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let bytes = encode_png(self.width, self.height, 3, &self.to_rgb8())?;
        let tmp = path.with_extension("png.partial");
        let r = std::fs::write(&tmp, bytes)
            .and_then(|()| std::fs::rename(&tmp, path))
            .map_err(|e| io_err(path, e));
        if r.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        r
    }

    /// Reads an 8-bit RGB or RGBA PNG (alpha is dropped; opacity reads as 1).
    pub fn load_png(path: &Path) -> Result<Image> {
        let f = std::fs::File::open(path).map_err(|e| io_err(path, e))?;
        let dec = png::Decoder::new(std::io::BufReader::new(f));
        let mut r = dec.read_info().map_err(|e| io_err(path, e))?;
        let size = r
            .output_buffer_size()
            .ok_or_else(|| io_err(path, "image too large"))?;
        let mut buf = vec![0u8; size];
        let info = r.next_frame(&mut buf).map_err(|e| io_err(path, e))?;
        let ch = match (info.color_type, info.bit_depth) {
            (png::ColorType::Rgb, png::BitDepth::Eight) => 3,
            (png::ColorType::Rgba, png::BitDepth::Eight) => 4,
            (c, d) => {
                return Err(io_err(
                    path,
                    format!("unsupported PNG {c:?} {d:?} (need 8-bit RGB or RGBA)"),
                ))
            }
        };
        let (w, h) = (info.width as usize, info.height as usize);
        let rgb = buf[..w * h * ch]
            .chunks_exact(ch)
            .map(|p| [p[0], p[1], p[2]].map(|v| v as f32 / 255.0))
            .collect();
        Ok(Image {
            width: w,
            height: h,
            rgb,
            alpha: vec![1.0; w * h],
        })
    }

    /// `(largest, mean)` absolute channel difference to an image of the same size.
    pub fn diff(&self, other: &Image) -> Result<(f32, f32)> {
        if (self.width, self.height) != (other.width, other.height) {
            return Err(RenderError::Input(format!(
                "image sizes differ: {}x{} vs {}x{}",
                self.width, self.height, other.width, other.height
            )));
        }
        let (mut max, mut sum) = (0.0f32, 0.0f64);
        for (a, b) in self.rgb.iter().zip(&other.rgb) {
            for k in 0..3 {
                let d = (a[k] - b[k]).abs();
                max = max.max(d);
                sum += d as f64;
            }
        }
        Ok((max, (sum / (3 * self.rgb.len().max(1)) as f64) as f32))
    }

    /// Nearest-neighbour resize (to show a coarse progressive pass at full size).
    pub fn resized(&self, width: usize, height: usize) -> Image {
        let mut rgb = Vec::with_capacity(width * height);
        let mut alpha = Vec::with_capacity(width * height);
        for j in 0..height {
            let sj = (j * self.height / height.max(1)).min(self.height - 1);
            for i in 0..width {
                let si = (i * self.width / width.max(1)).min(self.width - 1);
                rgb.push(self.rgb[sj * self.width + si]);
                alpha.push(self.alpha[sj * self.width + si]);
            }
        }
        Image {
            width,
            height,
            rgb,
            alpha,
        }
    }

    /// Places images side by side (same height), e.g. to compare renderers.
    pub fn side_by_side(images: &[&Image]) -> Result<Image> {
        let h = images.first().map_or(0, |i| i.height);
        if images.iter().any(|i| i.height != h) {
            return Err(RenderError::Input("images differ in height".into()));
        }
        let w: usize = images.iter().map(|i| i.width).sum();
        let mut out = Image {
            width: w,
            height: h,
            rgb: Vec::with_capacity(w * h),
            alpha: Vec::with_capacity(w * h),
        };
        for j in 0..h {
            for im in images {
                out.rgb
                    .extend_from_slice(&im.rgb[j * im.width..(j + 1) * im.width]);
                out.alpha
                    .extend_from_slice(&im.alpha[j * im.width..(j + 1) * im.width]);
            }
        }
        Ok(out)
    }
}
