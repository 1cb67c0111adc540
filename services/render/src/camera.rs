//! Orbit cameras around the volume centre, and the rays and projections they define.
//!
//! World space is the volume in physical units (voxel index times spacing), centred on the
//! volume: voxel `v` sits at `(v - (dims - 1) / 2) * spacing`. Azimuth turns about the volume's
//! z axis and elevation lifts towards +z; at azimuth 0 and elevation 0 the camera looks along
//! +y, with x to the right and z up (a coronal view of an RAS/LPS volume).

use crate::{RenderError, Result};
use serde::{Deserialize, Serialize};

/// How rays leave the camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Projection {
    /// Parallel rays; the view height at the centre is what the perspective view would show.
    Orthographic,
    /// Rays from the eye.
    Perspective,
}

/// An orbit camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Degrees about the z axis.
    pub azimuth: f32,
    /// Degrees above the xy plane, in [-90, 90].
    pub elevation: f32,
    /// Eye distance from the centre, in bounding-sphere radii (> 1 keeps the eye outside).
    pub distance: f32,
    /// Vertical field of view in degrees (also sets the orthographic zoom).
    pub fov: f32,
    /// Projection.
    pub projection: Projection,
}

impl Default for Camera {
    fn default() -> Self {
        Camera {
            azimuth: 30.0,
            elevation: 20.0,
            distance: 4.0,
            fov: 30.0,
            projection: Projection::Perspective,
        }
    }
}

type V3 = [f32; 3];

pub(crate) fn dot(a: V3, b: V3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub(crate) fn normalise(a: V3) -> V3 {
    let l = dot(a, a).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

/// A camera resolved against a volume and an image size: eye, basis and scale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Eye position (world).
    pub eye: V3,
    /// Unit viewing direction.
    pub forward: V3,
    /// Unit image-right direction.
    pub right: V3,
    /// Unit image-up direction.
    pub up: V3,
    /// Half the view height: at unit depth (perspective) or absolute (orthographic).
    pub half: f32,
    /// Width over height.
    pub aspect: f32,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Projection.
    pub projection: Projection,
}

impl Camera {
    /// Checks the parameters: finite, elevation in [-90, 90], distance > 0, fov in (0, 180).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(RenderError::Param(m));
        if !(self.azimuth.is_finite() && self.elevation.is_finite()) {
            return bad(format!(
                "view {},{} must be finite degrees",
                self.azimuth, self.elevation
            ));
        }
        if !(-90.0..=90.0).contains(&self.elevation) {
            return bad(format!(
                "elevation {} must be within [-90, 90] degrees",
                self.elevation
            ));
        }
        if !(self.distance.is_finite() && self.distance > 0.0 && self.distance <= 1e4) {
            return bad(format!(
                "distance {} must be in (0, 10000] bounding radii",
                self.distance
            ));
        }
        if !(self.fov.is_finite() && self.fov > 0.0 && self.fov < 180.0) {
            return bad(format!(
                "field of view {} must be in (0, 180) degrees",
                self.fov
            ));
        }
        Ok(())
    }

    /// Unit vector from the centre towards the eye.
    pub fn eye_direction(&self) -> V3 {
        let (a, e) = (self.azimuth.to_radians(), self.elevation.to_radians());
        [a.sin() * e.cos(), -a.cos() * e.cos(), e.sin()]
    }

    /// Resolves the camera for a volume of world `extent` and a `width x height` image.
    pub fn view(&self, extent: V3, width: usize, height: usize) -> View {
        let radius = 0.5 * dot(extent, extent).sqrt().max(f32::MIN_POSITIVE);
        let d = self.eye_direction();
        let eye = [
            d[0] * self.distance * radius,
            d[1] * self.distance * radius,
            d[2] * self.distance * radius,
        ];
        let forward = [-d[0], -d[1], -d[2]];
        // Up is +z unless looking (almost) straight along z; then +y keeps the basis defined.
        let world_up = if forward[2].abs() > 0.999 {
            [0.0, 1.0, 0.0]
        } else {
            [0.0, 0.0, 1.0]
        };
        let right = normalise(cross(forward, world_up));
        let up = cross(right, forward);
        let t = (0.5 * self.fov.to_radians()).tan();
        let half = match self.projection {
            Projection::Perspective => t,
            Projection::Orthographic => t * self.distance * radius,
        };
        View {
            eye,
            forward,
            right,
            up,
            half,
            aspect: width as f32 / height as f32,
            width,
            height,
            projection: self.projection,
        }
    }
}

impl View {
    /// The ray (origin, unit direction) through the centre of pixel `(i, j)`, row 0 at the top.
    #[inline]
    pub fn ray(&self, i: usize, j: usize) -> (V3, V3) {
        let x = ((i as f32 + 0.5) / self.width as f32 * 2.0 - 1.0) * self.aspect * self.half;
        let y = (1.0 - (j as f32 + 0.5) / self.height as f32 * 2.0) * self.half;
        match self.projection {
            Projection::Perspective => {
                let d = [
                    self.forward[0] + self.right[0] * x + self.up[0] * y,
                    self.forward[1] + self.right[1] * x + self.up[1] * y,
                    self.forward[2] + self.right[2] * x + self.up[2] * y,
                ];
                (self.eye, normalise(d))
            }
            Projection::Orthographic => (
                [
                    self.eye[0] + self.right[0] * x + self.up[0] * y,
                    self.eye[1] + self.right[1] * x + self.up[1] * y,
                    self.eye[2] + self.right[2] * x + self.up[2] * y,
                ],
                self.forward,
            ),
        }
    }

    /// Continuous pixel coordinates `(x, y)` of a world point (pixel centres at `i + 0.5`), or
    /// `None` when it is at or behind the eye plane of a perspective camera.
    pub fn project(&self, p: V3) -> Option<(f32, f32)> {
        let r = [p[0] - self.eye[0], p[1] - self.eye[1], p[2] - self.eye[2]];
        let (mut x, mut y) = (dot(r, self.right), dot(r, self.up));
        if self.projection == Projection::Perspective {
            let z = dot(r, self.forward);
            if z <= 1e-6 {
                return None;
            }
            x /= z;
            y /= z;
        }
        let px = (x / (self.aspect * self.half) + 1.0) * 0.5 * self.width as f32;
        let py = (1.0 - y / self.half) * 0.5 * self.height as f32;
        Some((px, py))
    }

    /// Pixel rectangle `[x0, x1) x [y0, y1)` holding every pixel whose ray may cross the world
    /// box `lo..hi` (its corners' projections plus a pixel of margin), or `None` if it is off
    /// screen.
    pub fn footprint(&self, lo: V3, hi: V3) -> Option<[usize; 4]> {
        let (mut x0, mut y0, mut x1, mut y1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
        for c in 0..8 {
            let p = [
                if c & 1 == 0 { lo[0] } else { hi[0] },
                if c & 2 == 0 { lo[1] } else { hi[1] },
                if c & 4 == 0 { lo[2] } else { hi[2] },
            ];
            match self.project(p) {
                Some((x, y)) => {
                    x0 = x0.min(x);
                    x1 = x1.max(x);
                    y0 = y0.min(y);
                    y1 = y1.max(y);
                }
                // A corner behind the eye: the box may cover any pixel.
                None => return Some([0, self.width, 0, self.height]),
            }
        }
        let (w, h) = (self.width as f32, self.height as f32);
        let xa = (x0 - 1.5).floor().max(0.0);
        let xb = (x1 + 1.5).ceil().min(w);
        let ya = (y0 - 1.5).floor().max(0.0);
        let yb = (y1 + 1.5).ceil().min(h);
        if xa >= xb || ya >= yb {
            return None;
        }
        Some([xa as usize, xb as usize, ya as usize, yb as usize])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_hit_what_they_project_to() {
        for projection in [Projection::Perspective, Projection::Orthographic] {
            let cam = Camera {
                azimuth: 37.0,
                elevation: -25.0,
                projection,
                ..Camera::default()
            };
            let v = cam.view([100.0, 80.0, 60.0], 64, 48);
            let p = [10.0, -7.0, 5.0];
            let (x, y) = v.project(p).unwrap();
            let (i, j) = (x.floor() as usize, y.floor() as usize);
            let (o, d) = v.ray(i, j);
            // The ray through that pixel passes within a pixel's width of p.
            let r = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
            let t = dot(r, d);
            let q = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
            let miss = dot(
                [q[0] - p[0], q[1] - p[1], q[2] - p[2]],
                [q[0] - p[0], q[1] - p[1], q[2] - p[2]],
            )
            .sqrt();
            assert!(miss < 5.0, "{projection:?}: {miss}");
        }
    }

    #[test]
    fn looking_straight_down_keeps_a_basis() {
        let cam = Camera {
            elevation: 90.0,
            ..Camera::default()
        };
        let v = cam.view([1.0, 1.0, 1.0], 8, 8);
        assert!(v.right.iter().all(|x| x.is_finite()));
        assert!((dot(v.right, v.up)).abs() < 1e-6);
        assert!(Camera {
            elevation: 91.0,
            ..cam
        }
        .validate()
        .is_err());
    }
}
