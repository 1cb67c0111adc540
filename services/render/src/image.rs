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

    /// Structural similarity of the two images' luma (Rec. 601 weights, RGB in [0, 1]), as
    /// Wang et al. (2004) define it and scikit-image computes it by default: 7x7 uniform
    /// windows, sample covariances, K1 = 0.01, K2 = 0.03, data range 1, the mean over the
    /// windows that lie inside the image. 1 for equal images; images smaller than a window
    /// compare as one window.
    pub fn ssim(&self, other: &Image) -> Result<f32> {
        if (self.width, self.height) != (other.width, other.height) {
            return Err(RenderError::Input(format!(
                "image sizes differ: {}x{} vs {}x{}",
                self.width, self.height, other.width, other.height
            )));
        }
        let (w, h) = (self.width, self.height);
        if w == 0 || h == 0 {
            return Err(RenderError::Input("empty images".into()));
        }
        let luma = |p: &[f32; 3]| (0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2]) as f64;
        // Summed-area tables of x, y, x^2, y^2 and xy, one row and column of zeros in front.
        let (sw, sh) = (w + 1, h + 1);
        let mut t = vec![[0.0f64; 5]; sw * sh];
        for j in 0..h {
            let mut row = [0.0f64; 5];
            for i in 0..w {
                let (x, y) = (luma(&self.rgb[j * w + i]), luma(&other.rgb[j * w + i]));
                for (r, v) in row.iter_mut().zip([x, y, x * x, y * y, x * y]) {
                    *r += v;
                }
                let above = t[j * sw + i + 1];
                let cell = &mut t[(j + 1) * sw + i + 1];
                for k in 0..5 {
                    cell[k] = above[k] + row[k];
                }
            }
        }
        let win = 7.min(w).min(h);
        let n = (win * win) as f64;
        let cov_norm = if n > 1.0 { n / (n - 1.0) } else { 1.0 };
        let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
        let mut sum = 0.0;
        let mut count = 0usize;
        for j in 0..=h - win {
            for i in 0..=w - win {
                let (a, b, c, d) = (
                    t[j * sw + i],
                    t[j * sw + i + win],
                    t[(j + win) * sw + i],
                    t[(j + win) * sw + i + win],
                );
                let s: [f64; 5] = std::array::from_fn(|k| (d[k] - b[k] - c[k] + a[k]) / n);
                let (mx, my) = (s[0], s[1]);
                let vx = cov_norm * (s[2] - mx * mx);
                let vy = cov_norm * (s[3] - my * my);
                let vxy = cov_norm * (s[4] - mx * my);
                sum += ((2.0 * mx * my + c1) * (2.0 * vxy + c2))
                    / ((mx * mx + my * my + c1) * (vx + vy + c2));
                count += 1;
            }
        }
        Ok((sum / count as f64) as f32)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Image {
        Image {
            width: w,
            height: h,
            rgb: (0..w * h).map(|p| [f(p % w, p / w); 3]).collect(),
            alpha: vec![1.0; w * h],
        }
    }

    #[test]
    fn ssim_is_one_for_equal_images_and_follows_the_formula_on_flat_ones() {
        let a = flat(20, 16, |i, j| ((i * 7 + j * 3) % 11) as f32 / 10.0);
        assert!((a.ssim(&a).unwrap() - 1.0).abs() < 1e-6);
        // Flat images: no variance, so SSIM is the luminance term alone.
        let (x, y) = (0.6f64, 0.3f64);
        let c1 = 0.01f64.powi(2);
        let want = (2.0 * x * y + c1) / (x * x + y * y + c1);
        let got = flat(9, 9, |_, _| x as f32)
            .ssim(&flat(9, 9, |_, _| y as f32))
            .unwrap();
        assert!((got as f64 - want).abs() < 1e-5, "{got} vs {want}");
        // Structure lost (the pattern against its mean) scores far below 1.
        let mean = flat(20, 16, |_, _| 0.5);
        assert!(a.ssim(&mean).unwrap() < 0.2);
        // Inverted structure is negatively correlated.
        let inv = flat(20, 16, |i, j| 1.0 - ((i * 7 + j * 3) % 11) as f32 / 10.0);
        assert!(a.ssim(&inv).unwrap() < 0.0);
    }

    #[test]
    fn ssim_refuses_images_of_other_sizes() {
        let e = flat(8, 8, |_, _| 0.0)
            .ssim(&flat(8, 9, |_, _| 0.0))
            .unwrap_err();
        assert!(e.to_string().contains("8x8 vs 8x9"), "{e}");
    }
}
