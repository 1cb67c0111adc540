//! Next-slice suggestion: where a stroke is worth the most to the score the user cares about.
//!
//! Each voxel's doubt is `u = 1 - max_c p_c` (least confidence), shared among the classes in
//! proportion to their probabilities (`p_c u`). [`SliceMass::of_brick`] sums these shares per
//! class over the slices a brick crosses, along all three axes, with each class's soft size
//! (`sum p_c`); partials add up in any order, so the sums stream with the classification.
//!
//! A slice's score is `sum_c mass_c(slice) / size_c`: the share of each class's predicted
//! extent that is in doubt on the slice, summed over classes. Two reasons it beats the plain
//! doubt mass, neither tied to an anatomy:
//! - mean F1 weighs every class alike, so doubt on a small structure is worth more than the same
//!   doubt spread over the background (the plain mass follows the large uncertain background);
//! - a slice next to one already scribbled mostly repeats what its strokes taught the forest
//!   (the features are smooth over a few voxels), so a slice's score is damped by
//!   `1 - exp(-d² / 2σ²)` with `d` its distance to the nearest visited slice on that axis and
//!   `σ` one thirty-second of the axis (at least 2 slices).

use serde::{Deserialize, Serialize};

/// Per-class doubt summed per slice along x, y and z, and each class's soft size (mergeable
/// by addition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SliceMass {
    /// Number of classes.
    pub classes: usize,
    /// Per axis x, y, z: `slice * classes + class` → `sum p_c (1 - max p)` over the slice.
    pub axes: [Vec<f64>; 3],
    /// Per class: `sum p_c` over every voxel seen.
    pub size: Vec<f64>,
}

/// A suggested slice.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Suggestion {
    /// Axis: 0 = x (sagittal), 1 = y (coronal), 2 = z (axial).
    pub axis: usize,
    /// Slice index along the axis.
    pub slice: usize,
    /// Its score: the doubtful share of each class's extent on the slice, summed over classes
    /// (after the damping near visited slices).
    pub mass: f64,
    /// Its share of the axis's total score.
    pub share: f64,
}

/// A class probability as stored: f32 in 0..1, or u8 with 255 = 1.
pub trait Probability: Copy {
    /// The probability as f64 in 0..1.
    fn value(self) -> f64;
}

impl Probability for f32 {
    fn value(self) -> f64 {
        self as f64
    }
}

impl Probability for u8 {
    fn value(self) -> f64 {
        self as f64 / 255.0
    }
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

/// Width (σ, slices) of the damping around visited slices on an axis of `n` slices.
pub fn damping_width(n: usize) -> f64 {
    (n as f64 / 32.0).max(2.0)
}

impl SliceMass {
    /// No mass, for a volume of `dims` and `classes` classes.
    pub fn zeros(dims: [usize; 3], classes: usize) -> Self {
        SliceMass {
            classes,
            axes: dims.map(|d| vec![0.0; d * classes]),
            size: vec![0.0; classes],
        }
    }

    /// The mass of one brick at `origin` with `size` voxels in a volume of `dims`, from its
    /// `classes` probabilities per voxel (x fastest; f32, or u8 with 255 = 1).
    pub fn of_brick<T: Probability>(
        dims: [usize; 3],
        origin: [usize; 3],
        size: [usize; 3],
        proba: &[T],
        classes: usize,
    ) -> Self {
        Self::of_rows(dims, origin, size, classes, proba.chunks(classes.max(1)))
    }

    fn of_rows<'a, T: Probability + 'a>(
        dims: [usize; 3],
        origin: [usize; 3],
        size: [usize; 3],
        c: usize,
        mut rows: impl Iterator<Item = &'a [T]>,
    ) -> Self {
        let mut m = SliceMass::zeros(dims, c);
        let mut p = vec![0.0f64; c];
        // The slab sums of one z-slice of the brick, added to the axes once per slice.
        let mut zsum = vec![0.0f64; c];
        for z in 0..size[2] {
            zsum.iter_mut().for_each(|v| *v = 0.0);
            for y in 0..size[1] {
                let ys = (origin[1] + y) * c;
                for x in 0..size[0] {
                    let Some(r) = rows.next() else { return m };
                    let mut max = 0.0f64;
                    for (pk, &v) in p.iter_mut().zip(r) {
                        *pk = v.value();
                        max = max.max(*pk);
                    }
                    let u = 1.0 - max;
                    let xs = (origin[0] + x) * c;
                    for k in 0..c {
                        m.size[k] += p[k];
                        let d = p[k] * u;
                        m.axes[0][xs + k] += d;
                        m.axes[1][ys + k] += d;
                        zsum[k] += d;
                    }
                }
            }
            let zs = (origin[2] + z) * c;
            for (a, v) in m.axes[2][zs..zs + c].iter_mut().zip(&zsum) {
                *a += v;
            }
        }
        m
    }

    /// Adds another partial (of the same volume and classes).
    pub fn merge(&mut self, o: &SliceMass) {
        for (a, b) in self.axes.iter_mut().zip(&o.axes) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
        self.size.iter_mut().zip(&o.size).for_each(|(x, y)| *x += y);
    }

    /// Every slice's score along `axis`, damped near the `visited` slices (see the module).
    pub fn scores(&self, axis: usize, visited: &[usize]) -> Vec<f64> {
        let c = self.classes.max(1);
        let v = &self.axes[axis];
        let n = v.len() / c;
        let s2 = 2.0 * damping_width(n).powi(2);
        (0..n)
            .map(|i| {
                let raw: f64 = (0..self.classes)
                    .filter(|&k| self.size[k] > 0.0)
                    .map(|k| v[i * c + k] / self.size[k])
                    .sum();
                let d = visited
                    .iter()
                    .map(|&s| (s as f64 - i as f64).abs())
                    .fold(f64::INFINITY, f64::min);
                if d.is_finite() {
                    raw * (1.0 - (-d * d / s2).exp())
                } else {
                    raw
                }
            })
            .collect()
    }

    /// The slices of `axis`, best first (lowest index on ties), with their scores.
    pub fn ranked(&self, axis: usize, visited: &[usize]) -> Vec<(usize, f64)> {
        let s = self.scores(axis, visited);
        let mut order: Vec<(usize, f64)> = s.into_iter().enumerate().collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        order
    }

    /// The best slice of `axis` away from the `visited` ones, if any has doubt.
    pub fn suggest(&self, axis: usize, visited: &[usize]) -> Option<Suggestion> {
        let s = self.scores(axis, visited);
        let total: f64 = s.iter().sum();
        let (slice, &mass) =
            s.iter()
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

    /// Probabilities of a volume of `dims` with 2 classes from `f(x, y, z)` = p of class 0.
    fn volume(dims: [usize; 3], f: impl Fn(usize, usize, usize) -> f32) -> Vec<f32> {
        (0..dims.iter().product::<usize>())
            .flat_map(|i| {
                let (x, y, z) = (i % dims[0], i / dims[0] % dims[1], i / (dims[0] * dims[1]));
                let p = f(x, y, z);
                [p, 1.0 - p]
            })
            .collect()
    }

    #[test]
    fn bricks_add_up_to_the_whole_and_the_doubtful_slice_wins() {
        let dims = [6, 5, 7];
        // Certain everywhere except slice z = 4 and column x = 2 (half sure).
        let p = volume(dims, |x, _, z| if z == 4 || x == 2 { 0.5 } else { 1.0 });
        let whole = SliceMass::of_brick(dims, [0; 3], dims, &p, 2);
        let mut parts = SliceMass::zeros(dims, 2);
        for (o, s) in [([0, 0, 0], [6, 5, 3]), ([0, 0, 3], [6, 5, 4])] {
            let sub: Vec<f32> = (0..s[2])
                .flat_map(|z| {
                    let p = &p;
                    (0..s[1]).flat_map(move |y| {
                        (0..s[0]).flat_map(move |x| {
                            let i = ((o[2] + z) * 5 + o[1] + y) * 6 + o[0] + x;
                            [p[2 * i], p[2 * i + 1]]
                        })
                    })
                })
                .collect();
            parts.merge(&SliceMass::of_brick(dims, o, s, &sub, 2));
        }
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9);
        for a in 0..3 {
            assert!(close(&parts.axes[a], &whole.axes[a]));
        }
        assert!(close(&parts.size, &whole.size));
        let s = whole.suggest(2, &[]).unwrap();
        assert_eq!((s.axis, s.slice), (2, 4));
        assert_eq!(whole.suggest(0, &[]).unwrap().slice, 2);
        // Quantised probabilities give the same answer.
        let u8s: Vec<u8> = p.iter().map(|v| (v * 255.0).round() as u8).collect();
        let q = SliceMass::of_brick(dims, [0; 3], dims, &u8s, 2);
        assert_eq!(q.suggest(2, &[]).unwrap().slice, 4);
        assert!(uncertainty(&p, 2)
            .iter()
            .zip(uncertainty_u8(&u8s, 2))
            .all(|(a, b)| (a - b).abs() < 0.01));
        assert_eq!(SliceMass::zeros(dims, 2).suggest(1, &[]), None);
    }

    #[test]
    fn doubt_about_a_small_class_outweighs_more_doubt_between_large_ones() {
        // Classes 0 and 1 split the volume at x = 8; class 2 is a 2x2 block on slices 10-11.
        // Slice 3 holds more doubt in voxels (the whole slice torn between 0 and 1), slice 10
        // less (the block torn between 2 and 0).
        let dims = [16, 16, 20];
        let p: Vec<f32> = (0..dims.iter().product::<usize>())
            .flat_map(|i| {
                let (x, y, z) = (i % 16, i / 16 % 16, i / 256);
                let big = if x < 8 {
                    [1.0, 0.0, 0.0]
                } else {
                    [0.0, 1.0, 0.0]
                };
                match z {
                    3 => [0.6, 0.4, 0.0],
                    10 | 11 if x < 2 && y < 2 => [0.3, 0.0, 0.7],
                    _ => big,
                }
            })
            .collect();
        let m = SliceMass::of_brick(dims, [0; 3], dims, &p, 3);
        let plain = uncertainty(&p, 3);
        let per_slice = |z: usize| plain[z * 256..(z + 1) * 256].iter().sum::<f32>();
        assert!(
            per_slice(3) > 10.0 * per_slice(10),
            "the plain mass prefers slice 3"
        );
        assert_eq!(m.suggest(2, &[]).unwrap().slice, 10);
    }

    #[test]
    fn visited_slices_and_their_neighbours_are_damped() {
        // One doubtful band over slices 8..=12, peaking at 10.
        let dims = [8, 8, 64];
        let p = volume(dims, |_, _, z| {
            let d = (z as f32 - 10.0).abs();
            if d <= 2.0 {
                0.5 + 0.1 * d
            } else if z == 40 {
                0.6
            } else {
                1.0
            }
        });
        let m = SliceMass::of_brick(dims, [0; 3], dims, &p, 2);
        assert_eq!(m.suggest(2, &[]).unwrap().slice, 10);
        // After a visit to slice 10, its neighbours 9 and 11 lose to the distinct slice 40.
        assert_eq!(m.suggest(2, &[10]).unwrap().slice, 40);
        let s = m.scores(2, &[10]);
        assert_eq!(s[10], 0.0);
        assert!(s[9] < s[8] || s[8] == 0.0);
        let r = m.ranked(2, &[10]);
        assert_eq!(r[0].0, 40);
        assert!(r.windows(2).all(|w| w[0].1 >= w[1].1));
    }
}
