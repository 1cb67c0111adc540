//! Next-slice suggestion: where the current prediction is least sure.
//!
//! Each voxel's uncertainty is `1 - max_c p_c` (least confidence). [`SliceMass::of_brick`] sums
//! it over the slices a brick crosses, along all three axes; partials add up in any order, so
//! the sum streams with the classification. The suggested slice of an axis is the one with the
//! largest mass: the slice where a stroke can correct the most doubtful voxels.

use serde::{Deserialize, Serialize};

/// Uncertainty summed per slice along x, y and z (mergeable by addition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SliceMass {
    /// Mass per slice index, for axes x, y, z.
    pub axes: [Vec<f64>; 3],
}

/// A suggested slice.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Suggestion {
    /// Axis: 0 = x (sagittal), 1 = y (coronal), 2 = z (axial).
    pub axis: usize,
    /// Slice index along the axis.
    pub slice: usize,
    /// Its uncertainty mass (voxels' `1 - max p` summed).
    pub mass: f64,
    /// Its share of the axis's total mass.
    pub share: f64,
}

/// `1 - max p` of each row of `c` class probabilities.
pub fn uncertainty(proba: &[f32], c: usize) -> Vec<f32> {
    proba
        .chunks(c.max(1))
        .map(|r| 1.0 - r.iter().copied().fold(0.0f32, f32::max))
        .collect()
}

/// `1 - max p` of each row of `c` class probabilities quantised to u8 (255 = 1).
pub fn uncertainty_u8(proba: &[u8], c: usize) -> Vec<f32> {
    proba
        .chunks(c.max(1))
        .map(|r| 1.0 - r.iter().copied().max().unwrap_or(0) as f32 / 255.0)
        .collect()
}

impl SliceMass {
    /// No mass, for a volume of `dims`.
    pub fn zeros(dims: [usize; 3]) -> Self {
        SliceMass {
            axes: dims.map(|d| vec![0.0; d]),
        }
    }

    /// The mass of one brick at `origin` with `size` voxels (`uncertainty` per voxel, x
    /// fastest) in a volume of `dims`.
    pub fn of_brick(
        dims: [usize; 3],
        origin: [usize; 3],
        size: [usize; 3],
        uncertainty: &[f32],
    ) -> Self {
        let mut m = SliceMass::zeros(dims);
        let mut k = 0;
        for z in 0..size[2] {
            for y in 0..size[1] {
                for x in 0..size[0] {
                    let u = uncertainty[k] as f64;
                    m.axes[0][origin[0] + x] += u;
                    m.axes[1][origin[1] + y] += u;
                    m.axes[2][origin[2] + z] += u;
                    k += 1;
                }
            }
        }
        m
    }

    /// Adds another partial.
    pub fn merge(&mut self, o: &SliceMass) {
        for (a, b) in self.axes.iter_mut().zip(&o.axes) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
    }

    /// The slice of `axis` with the largest mass (lowest index on ties), if any has mass.
    pub fn suggest(&self, axis: usize) -> Option<Suggestion> {
        let v = &self.axes[axis];
        let total: f64 = v.iter().sum();
        let (slice, &mass) =
            v.iter()
                .enumerate()
                .fold(None, |b: Option<(usize, &f64)>, (i, m)| match b {
                    Some((_, bm)) if bm >= m => b,
                    _ => Some((i, m)),
                })?;
        (mass > 0.0).then_some(Suggestion {
            axis,
            slice,
            mass,
            share: mass / total,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bricks_add_up_to_the_whole_and_the_doubtful_slice_wins() {
        let dims = [6, 5, 7];
        let n: usize = dims.iter().product();
        // Certain everywhere except slice z = 4 and column x = 2 (half sure).
        let p: Vec<f32> = (0..n)
            .flat_map(|i| {
                let (x, z) = (i % 6, i / 30);
                if z == 4 || x == 2 {
                    [0.5, 0.5]
                } else {
                    [1.0, 0.0]
                }
            })
            .collect();
        let u = uncertainty(&p, 2);
        let whole = SliceMass::of_brick(dims, [0; 3], dims, &u);
        let mut parts = SliceMass::zeros(dims);
        for (o, s) in [([0, 0, 0], [6, 5, 3]), ([0, 0, 3], [6, 5, 4])] {
            let sub: Vec<f32> = (0..s[2])
                .flat_map(|z| {
                    let u = &u;
                    (0..s[1]).flat_map(move |y| {
                        (0..s[0]).map(move |x| u[((o[2] + z) * 5 + o[1] + y) * 6 + o[0] + x])
                    })
                })
                .collect();
            parts.merge(&SliceMass::of_brick(dims, o, s, &sub));
        }
        assert_eq!(parts, whole);
        let s = whole.suggest(2).unwrap();
        assert_eq!((s.axis, s.slice), (2, 4));
        assert!((s.mass - 15.0).abs() < 1e-9);
        assert_eq!(whole.suggest(0).unwrap().slice, 2);
        let u8s: Vec<u8> = p.iter().map(|v| (v * 255.0).round() as u8).collect();
        let u2 = uncertainty_u8(&u8s, 2);
        assert!(u.iter().zip(&u2).all(|(a, b)| (a - b).abs() < 0.01));
        assert_eq!(SliceMass::zeros(dims).suggest(1), None);
    }
}
