//! Long-range context: the smoothed intensity at displaced positions (Criminisi et al.,
//! decision forests with long-range spatial context), computed per brick from the pyramid.
//!
//! At each scale `s` in [`CONTEXT_SCALES`], the Gaussian-smoothed intensity of scale `s` is
//! sampled at offsets of `2 s` voxels from the voxel: along the 3 axes both ways
//! ([`Offsets::Axes`], 6 per scale) or in the axial plane in 8 directions ([`Offsets::Plane`], 8
//! per scale). The feature is the difference to the smoothed value at the voxel itself, so it
//! describes the surroundings relative to the voxel (what lies brighter or darker 4, 8, 16
//! voxels away) rather than the absolute position. The smoothed value at the voxel is added
//! once per scale. Offsets are edge-clamped.

use crate::scale::ScaleField;
use neuvolex_bricks::derived::Normaliser;
use serde::{Deserialize, Serialize};

/// Scales of the context, in level-0 voxels; offsets are twice the scale.
pub const CONTEXT_SCALES: [f32; 3] = [2.0, 4.0, 8.0];

/// Which displaced positions are sampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Offsets {
    /// `±2s` along x, y and z: 6 per scale.
    Axes,
    /// 8 directions in the axial (x, y) plane at distance `2s`: 8 per scale.
    Plane,
}

impl Offsets {
    /// Unit offset directions (x, y, z).
    pub fn directions(self) -> Vec<[f32; 3]> {
        match self {
            Offsets::Axes => vec![
                [-1.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, -1.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, -1.0],
                [0.0, 0.0, 1.0],
            ],
            Offsets::Plane => (0..8)
                .map(|k| {
                    let a = k as f32 * std::f32::consts::FRAC_PI_4;
                    [a.cos(), a.sin(), 0.0]
                })
                .collect(),
        }
    }

    /// Channels: per scale, the smoothed value at the voxel and one per direction.
    pub fn channels(self) -> usize {
        CONTEXT_SCALES.len() * (1 + self.directions().len())
    }

    /// A name per channel.
    pub fn names(self) -> Vec<String> {
        let dirs = self.directions();
        CONTEXT_SCALES
            .iter()
            .flat_map(|s| {
                std::iter::once(format!("ctx_s{s}"))
                    .chain(
                        dirs.iter().map(move |d| {
                            format!("ctx_s{s}_{:+.0}_{:+.0}_{:+.0}", d[0], d[1], d[2])
                        }),
                    )
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// Largest offset in voxels (the margin a brick's fields must cover).
    pub fn margin(self) -> isize {
        (2.0 * CONTEXT_SCALES[CONTEXT_SCALES.len() - 1]).ceil() as isize
    }
}

/// The context features of the brick at `origin` with `size` voxels: `voxels x channels`,
/// x fastest. `levels` are the pyramid's level grids and `read(level, origin, size)` reads an
/// in-bounds box of raw intensities of a level.
pub fn compute<E>(
    offsets: Offsets,
    levels: &[[usize; 3]],
    norm: &Normaliser,
    origin: [usize; 3],
    size: [usize; 3],
    mut read: impl FnMut(usize, [usize; 3], [usize; 3]) -> Result<Vec<f32>, E>,
) -> Result<Vec<f32>, E> {
    let dirs = offsets.directions();
    let ch = offsets.channels();
    let n: usize = size.iter().product();
    let mut out = vec![0.0f32; n * ch];
    let per = 1 + dirs.len();
    for (si, &s) in CONTEXT_SCALES.iter().enumerate() {
        let m = (2.0 * s).ceil() as isize;
        let lo = origin.map(|o| o as isize - m);
        let hi: [isize; 3] = std::array::from_fn(|a| (origin[a] + size[a]) as isize - 1 + m);
        let field = ScaleField::compute(s, levels, norm, lo, hi, &mut read)?;
        let off: Vec<[isize; 3]> = dirs
            .iter()
            .map(|d| d.map(|c| (2.0 * s * c).round() as isize))
            .collect();
        let mut k = 0;
        for z in 0..size[2] {
            for y in 0..size[1] {
                for x in 0..size[0] {
                    let p = [
                        (origin[0] + x) as isize,
                        (origin[1] + y) as isize,
                        (origin[2] + z) as isize,
                    ];
                    let o = &mut out[k * ch + si * per..k * ch + (si + 1) * per];
                    let c = field.sample(p).0;
                    o[0] = c;
                    for (j, d) in off.iter().enumerate() {
                        o[1 + j] = field.sample([p[0] + d[0], p[1] + d[1], p[2] + d[2]]).0 - c;
                    }
                    k += 1;
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scale::tests::{bricks_equal_whole, pyramid, reader, waves};

    #[test]
    fn bricks_equal_a_whole_volume_computation() {
        let d = [40, 33, 29];
        let (data, dims) = pyramid(&waves(d), d, 3);
        let norm = Normaliser {
            lo: -100.0,
            hi: 100.0,
        };
        for offsets in [Offsets::Axes, Offsets::Plane] {
            let ch = offsets.channels();
            assert_eq!(offsets.names().len(), ch);
            let what = format!("{offsets:?}");
            let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
            bricks_equal_whole(&what, d, ch, [16; 3], close, |o, s| {
                compute(offsets, &dims, &norm, o, s, reader(&data, &dims)).unwrap()
            });
        }
    }

    #[test]
    fn context_sees_a_bright_neighbour_on_the_right_side() {
        // A bright slab at x >= 30: a voxel at x = 20 sees it 8 voxels to +x at scale 4, not
        // to -x; a voxel deep on the dark side sees nothing.
        let d = [48, 16, 16];
        let v: Vec<f32> = (0..d.iter().product::<usize>())
            .map(|i| if i % 48 >= 30 { 1.0 } else { 0.0 })
            .collect();
        let (data, dims) = pyramid(&v, d, 3);
        let norm = Normaliser { lo: 0.0, hi: 1.0 };
        let f = compute(Offsets::Axes, &dims, &norm, [0; 3], d, reader(&data, &dims)).unwrap();
        let ch = Offsets::Axes.channels();
        let at = |x: usize, c: usize| f[((8 * 16 + 8) * 48 + x) * ch + c];
        // Scale 4 is the second block of 7: [centre, -x, +x, -y, +y, -z, +z].
        let b = 7;
        assert!(
            at(20, b + 2) > 0.2,
            "+x offset sees the slab: {}",
            at(20, b + 2)
        );
        assert!(
            at(20, b + 1).abs() < 0.05,
            "-x offset does not: {}",
            at(20, b + 1)
        );
        assert!(at(4, b + 2).abs() < 1e-3 && at(4, b).abs() < 1e-3);
    }
}
