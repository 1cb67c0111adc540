//! Enclosure: how bright and how dark the tissue is that closes a voxel in on every side,
//! computed per brick from the pyramid (ray features in the manner of Smith et al., "Fast ray
//! features for learning irregular shapes", ICCV 2009).
//!
//! Along each of [`DIRECTIONS`] (the 6 axis directions and the 4 in-plane diagonals) a ray of
//! [`REACH`] voxels samples the intensity smoothed at scale [`SCALE`] every [`SCALE`] voxels and
//! keeps its maximum and its minimum. Sorted over the directions:
//!
//! - the 3 smallest maxima say how bright the tissue is that closes the voxel in on every side,
//!   on all but one, on all but two: marrow inside a shell of cortical bone (CT) has bright
//!   tissue within reach in every direction, soft tissue of the same intensity beside a bone
//!   has it on one side only; a ventricle is closed in by brighter brain (T1);
//! - the 3 largest minima say the same of dark tissue: in T1 MRI the brain is closed in by the
//!   skull's dark cortex, the scalp is not.
//!
//! The 2nd and 3rd allow a shell with a gap or two (a foramen, a slice through a joint). Both
//! polarities are kept, so no modality's contrast is assumed. The order statistics do not
//! depend on which direction the shell is open in, so a few strokes teach the forest one rule
//! for every orientation, where direction-by-direction context ([`crate::context`]) gives it one
//! channel per direction to learn apart.
//!
//! Values are normalised intensities (the filter bank's scale), absolute rather than relative
//! to the voxel, so a split reads "closed in by tissue brighter than t". Rays are edge-clamped:
//! beyond the volume the border voxel continues.

use crate::scale::ScaleField;
use neuvolex_bricks::derived::Normaliser;

/// Scale (level-0 voxels) of the smoothed intensity the rays read, and their step.
pub const SCALE: f32 = 2.0;

/// Length of a ray in level-0 voxels: the filter bank's largest halo (24), the distance within
/// which a stroke's features see the image.
pub const REACH: f32 = 24.0;

/// Ray directions (x, y, z): the 6 axis directions and the 4 diagonals of the axial plane.
pub const DIRECTIONS: [[isize; 3]; 10] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
    [1, 1, 0],
    [-1, -1, 0],
    [1, -1, 0],
    [-1, 1, 0],
];

/// Order statistics kept of each kind (smallest maxima, largest minima).
const KEEP: usize = 3;

/// Channels per voxel: [`KEEP`] smallest ray maxima, then [`KEEP`] largest ray minima.
pub const CHANNELS: usize = 2 * KEEP;

/// A name per channel.
pub fn names() -> Vec<String> {
    (1..=KEEP)
        .map(|k| format!("encl_bright{k}"))
        .chain((1..=KEEP).map(|k| format!("encl_dark{k}")))
        .collect()
}

/// The samples of one ray: offsets (level-0 voxels) of direction `d`, one every [`SCALE`]
/// voxels of path up to [`REACH`].
fn ray(d: [isize; 3]) -> Vec<[isize; 3]> {
    let len = (d.iter().map(|c| (c * c) as f32).sum::<f32>()).sqrt();
    let step = SCALE as isize;
    let n = (REACH / (SCALE * len)).floor() as isize;
    (1..=n).map(|k| d.map(|c| c * step * k)).collect()
}

/// The largest offset of any ray along one axis (the margin a brick's field must cover).
pub fn margin() -> isize {
    DIRECTIONS
        .iter()
        .flat_map(|&d| ray(d))
        .flat_map(|o| o.map(|c| c.abs()))
        .max()
        .unwrap_or(0)
}

/// The enclosure features of the brick at `origin` with `size` voxels: `voxels x CHANNELS`, x
/// fastest. `levels` are the pyramid's level grids and `read(level, origin, size)` reads an
/// in-bounds box of raw intensities of a level.
pub fn compute<E>(
    levels: &[[usize; 3]],
    norm: &Normaliser,
    origin: [usize; 3],
    size: [usize; 3],
    mut read: impl FnMut(usize, [usize; 3], [usize; 3]) -> Result<Vec<f32>, E>,
) -> Result<Vec<f32>, E> {
    let n: usize = size.iter().product();
    let mut out = vec![0.0f32; n * CHANNELS];
    if n == 0 {
        return Ok(out);
    }
    let m = margin();
    let lo = origin.map(|o| o as isize - m);
    let hi: [isize; 3] = std::array::from_fn(|a| (origin[a] + size[a]) as isize - 1 + m);
    let field = ScaleField::compute(SCALE, levels, norm, lo, hi, &mut read)?;
    let rays: Vec<Vec<[isize; 3]>> = DIRECTIONS.iter().map(|&d| ray(d)).collect();
    let mut ext = [(0.0f32, 0.0f32); DIRECTIONS.len()];
    let mut k = 0;
    for z in 0..size[2] {
        for y in 0..size[1] {
            for x in 0..size[0] {
                let p = [
                    (origin[0] + x) as isize,
                    (origin[1] + y) as isize,
                    (origin[2] + z) as isize,
                ];
                field.extremes(p, &rays, &mut ext);
                let mut maxima = ext.map(|(hi, _)| hi);
                let mut minima = ext.map(|(_, lo)| lo);
                maxima.sort_unstable_by(f32::total_cmp);
                minima.sort_unstable_by(|a, b| b.total_cmp(a));
                let o = &mut out[k * CHANNELS..(k + 1) * CHANNELS];
                o[..KEEP].copy_from_slice(&maxima[..KEEP]);
                o[KEEP..].copy_from_slice(&minima[..KEEP]);
                k += 1;
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
        assert_eq!(names().len(), CHANNELS);
        let close = |a: f32, b: f32| (a - b).abs() < 1e-5;
        bricks_equal_whole("encl", d, CHANNELS, [16; 3], close, |o, s| {
            compute(&dims, &norm, o, s, reader(&data, &dims)).unwrap()
        });
    }

    #[test]
    fn shared_weights_give_the_bits_of_each_sample_alone() {
        // Every voxel of an odd grid (so the level's last corner is clamped on every axis),
        // every ray, borders included: `extremes` equals folding `smooth_at`, bit for bit.
        let d = [37, 30, 27];
        let (data, dims) = pyramid(&waves(d), d, 3);
        let norm = Normaliser {
            lo: -100.0,
            hi: 100.0,
        };
        let m = margin();
        let field = ScaleField::compute(
            SCALE,
            &dims,
            &norm,
            [-m; 3],
            d.map(|n| n as isize - 1 + m),
            reader(&data, &dims),
        )
        .unwrap();
        let rays: Vec<_> = DIRECTIONS.iter().map(|&r| ray(r)).collect();
        for z in 0..d[2] as isize {
            for y in 0..d[1] as isize {
                for x in 0..d[0] as isize {
                    let mut ext = vec![(0.0, 0.0); rays.len()];
                    field.extremes([x, y, z], &rays, &mut ext);
                    for (r, &(hi, lo)) in rays.iter().zip(&ext) {
                        let each: Vec<f32> = r
                            .iter()
                            .map(|o| field.smooth_at([x + o[0], y + o[1], z + o[2]]))
                            .collect();
                        let h = each.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                        let l = each.iter().copied().fold(f32::INFINITY, f32::min);
                        assert_eq!((hi.to_bits(), lo.to_bits()), (h.to_bits(), l.to_bits()));
                    }
                }
            }
        }
    }

    #[test]
    fn a_shell_closes_in_its_inside_and_a_slab_does_not() {
        // A bright spherical shell (radius 8 to 10) around (24, 24, 24), and a bright slab at
        // x >= 40 outside it. The shell's centre is closed in by bright tissue on every side;
        // a voxel beside the slab sees it on one side only; both are dark themselves.
        let d = [48, 48, 48];
        let v: Vec<f32> = (0..d.iter().product::<usize>())
            .map(|i| {
                let (x, y, z) = (i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1]));
                let r = [x, y, z]
                    .iter()
                    .map(|&c| (c as f32 - 24.0).powi(2))
                    .sum::<f32>()
                    .sqrt();
                if (8.0..=10.0).contains(&r) || x >= 40 {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let (data, dims) = pyramid(&v, d, 3);
        let norm = Normaliser { lo: 0.0, hi: 1.0 };
        let f = compute(&dims, &norm, [0; 3], d, reader(&data, &dims)).unwrap();
        let at = |p: [usize; 3], c: usize| f[((p[2] * d[1] + p[1]) * d[0] + p[0]) * CHANNELS + c];
        let (inside, beside) = ([24, 24, 24], [37, 4, 40]);
        assert!(at(inside, 0) > 0.3, "shell closes in: {}", at(inside, 0));
        assert!(
            at(beside, 0) < 0.05,
            "slab alone does not: {}",
            at(beside, 0)
        );
        // Three directions reach the slab, seven do not: the smallest maxima miss it.
        assert!(at(beside, KEEP - 1) < 0.05, "{}", at(beside, KEEP - 1));
        // Every ray from the shell's centre crosses its dark inside; towards the slab, every
        // sample is bright.
        assert!(at(inside, KEEP) < 0.05, "{}", at(inside, KEEP));
        assert!(at(beside, KEEP) > 0.3, "{}", at(beside, KEEP));
    }
}
