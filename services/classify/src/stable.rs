//! Labels that stick between rounds of interactive refinement.
//!
//! Each round retrains the forest on all strokes so far and predicts again. A forest grown
//! anew gives every voxel a slightly different vote: near a tie between two classes that
//! noise alone flips labels anywhere in the volume, far from where the user drew, and the
//! spatial prior can then keep or drop a whole component over it. The user sees a correction
//! in one place change the answer elsewhere.
//!
//! The rule here: beyond `margin` voxels of the round's new strokes, a voxel keeps its previous
//! label unless the new probabilities prefer its new label over the previous one by at least
//! `delta`, more than retraining noise moves a vote. Near the new strokes (where the user is
//! editing) the new labels stand. Evidence that really changed (a stroke of a class elsewhere
//! teaching the forest a new look) still changes labels far away; a wobble does not.
//!
//! The default `delta` is 0.25: in a choice between two classes, the new label must have 5:3
//! odds over the old one. The forest's vote noise alone (two standard errors of a `T`-tree vote
//! at p = 0.5, `1 / sqrt(T)`: 0.1 at 100 trees, 0.18 at 32) is below it, and so are most of the
//! wobbles a stroke's new rows cause far away, which move the forest's splits, not only its
//! seeds. Measured with the robot on both development volumes (BENCHMARKS.md, issue 31):
//! `delta` 0.1 halved the worst one-round drop on the brain MRI, 0.25 brought every round on
//! both volumes but one within 0.03, at a cost of at most one round to 0.7.
//!
//! The functions are pure and per voxel ([`stick`] takes any span of voxels, a brick or a
//! whole volume), so the batch robot, the CLI and the service apply the same rule.

use serde::{Deserialize, Serialize};

/// Settings of the stability rule.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StableConfig {
    /// Voxels (Chebyshev distance) around the new strokes where new labels always stand.
    pub margin: usize,
    /// How much more probable (0..1) the new label must be than the previous one, beyond the
    /// margin, to replace it.
    pub delta: f32,
}

/// The default `delta` (see the module's notes).
pub const DEFAULT_DELTA: f32 = 0.25;

impl Default for StableConfig {
    /// The filter bank's halo as the margin (the image a scribbled voxel's features see) and
    /// [`DEFAULT_DELTA`].
    fn default() -> Self {
        StableConfig {
            margin: neuvolex_filters::filter_halo(),
            delta: DEFAULT_DELTA,
        }
    }
}

/// The voxels within Chebyshev distance `margin` of a marked voxel (a box dilation of
/// `marked` over a `dims` grid, `dims[0]` fastest), one separable pass per axis (x and y plane
/// by plane in parallel, then z).
pub fn near(marked: &[bool], dims: [usize; 3], margin: usize) -> Vec<bool> {
    use rayon::prelude::*;
    let [nx, ny, nz] = dims;
    let mut m = marked.to_vec();
    let plane = nx * ny;
    if m.is_empty() || plane == 0 {
        return m;
    }
    m.par_chunks_mut(plane).for_each(|p| {
        let mut dist = Vec::new();
        for y in 0..ny {
            dilate_line(p, y * nx, 1, nx, margin, &mut dist);
        }
        for x in 0..nx {
            dilate_line(p, x, nx, ny, margin, &mut dist);
        }
    });
    let mut dist = Vec::new();
    for s0 in 0..plane {
        dilate_line(&mut m, s0, plane, nz, margin, &mut dist);
    }
    m
}

/// The voxels within `margin` of a scribbled voxel of `s` ([`near`] over its grid; no passes
/// when nothing is scribbled).
pub fn near_scribbles(s: &crate::Scribbles, margin: usize) -> Vec<bool> {
    let mut marked = vec![false; s.dims.iter().product()];
    s.voxels.iter().for_each(|v| marked[v.0 as usize] = true);
    if s.voxels.is_empty() {
        return marked;
    }
    near(&marked, s.dims, margin)
}

/// Dilates the line `m[s0 + k * stride]`, `k < len`, by `margin` along itself.
fn dilate_line(
    m: &mut [bool],
    s0: usize,
    stride: usize,
    len: usize,
    margin: usize,
    dist: &mut Vec<usize>,
) {
    // Distance to the nearest marked voxel along the line, from both ends.
    dist.clear();
    dist.resize(len, usize::MAX);
    let mut last: Option<usize> = None;
    for (k, d) in dist.iter_mut().enumerate() {
        if m[s0 + k * stride] {
            last = Some(k);
        }
        if let Some(l) = last {
            *d = k - l;
        }
    }
    last = None;
    for k in (0..len).rev() {
        if m[s0 + k * stride] {
            last = Some(k);
        }
        if let Some(l) = last {
            dist[k] = dist[k].min(l - k);
        }
    }
    for (k, &d) in dist.iter().enumerate() {
        m[s0 + k * stride] = d <= margin;
    }
}

/// The probability (u8, 0..=255) that a voxel's class probabilities `px` (one per class index)
/// give output label `l`: its class's (`out_labels[k]` is class `k`'s output label, 0 for the
/// background), for label 0 the background's when it was scribbled, else `255 - max`.
pub fn score(px: &[u8], out_labels: &[u16], bg: Option<usize>, l: u16) -> u8 {
    if l == 0 {
        return match bg {
            Some(k) => px[k],
            None => 255 - px.iter().copied().max().unwrap_or(0),
        };
    }
    out_labels.iter().position(|&o| o == l).map_or(0, |k| px[k])
}

/// Applies the rule to a span of voxels: `labels` (this round's, changed in place), `prev`
/// (the previous round's shown labels), `probs` (this round's u8 probabilities, `out_labels.len()`
/// per voxel), `close` (within the margin of the round's new strokes). `delta` is in u8 steps.
/// Returns the voxels that kept their previous label.
pub fn stick(
    labels: &mut [u16],
    prev: &[u16],
    probs: &[u8],
    out_labels: &[u16],
    bg: Option<usize>,
    close: &[bool],
    delta: u8,
) -> u64 {
    let nc = out_labels.len().max(1);
    let mut kept = 0;
    for (v, (l, &p)) in labels.iter_mut().zip(prev).enumerate() {
        if *l == p || close[v] {
            continue;
        }
        let px = &probs[v * nc..(v + 1) * nc];
        let (new, old) = (score(px, out_labels, bg, *l), score(px, out_labels, bg, p));
        if (new as i32) < old as i32 + delta as i32 {
            *l = p;
            kept += 1;
        }
    }
    kept
}

/// The strokes added since `before`: the voxels of `now` that `before` did not scribble, when
/// `now` keeps every voxel of `before` with its label (a later round of the same user), else
/// `None` (strokes were erased or relabelled: no round to hold to).
pub fn added(before: &crate::Scribbles, now: &crate::Scribbles) -> Option<crate::Scribbles> {
    if before.dims != now.dims {
        return None;
    }
    // Both are sorted by voxel, one entry each: one merge.
    let mut old = before.voxels.iter().peekable();
    let mut new = Vec::new();
    for &(v, l) in &now.voxels {
        match old.peek() {
            Some(&&(ov, ol)) if ov == v => {
                if ol != l {
                    return None;
                }
                old.next();
            }
            Some(&&(ov, _)) if ov < v => return None,
            _ => new.push((v, l)),
        }
    }
    old.next().is_none().then_some(crate::Scribbles {
        dims: now.dims,
        voxels: new,
    })
}

/// A previous result that a new classification holds to with the rule: what it showed and the
/// scribbles it came from (same settings and features; the caller checks).
#[derive(Clone)]
pub struct Hold {
    /// The scribbles of the previous result.
    pub scribbles: crate::Scribbles,
    /// Its output labels per voxel (x fastest), as shown.
    pub labels: Vec<u16>,
    /// The rule's margin and `delta`.
    pub config: StableConfig,
}

impl std::fmt::Debug for Hold {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hold")
            .field("scribbled", &self.scribbles.voxels.len())
            .field("voxels", &self.labels.len())
            .field("config", &self.config)
            .finish()
    }
}

/// A probability (clamped to 0..1) in the u8 steps the service keeps and [`stick`] compares,
/// rounded to the nearest step: the one quantisation of the service, the robot and the pipeline.
pub fn to_u8(p: f32) -> u8 {
    (p.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// `delta` (a probability) in the u8 steps [`stick`] compares.
pub fn delta_u8(delta: f32) -> u8 {
    to_u8(delta)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn added_strokes_are_the_new_voxels_of_a_superset() {
        let s = |v: &[(u64, u32)]| crate::Scribbles {
            dims: [4, 4, 4],
            voxels: v.to_vec(),
        };
        let before = s(&[(3, 1), (9, 2)]);
        assert_eq!(
            added(&before, &s(&[(1, 2), (3, 1), (5, 1), (9, 2), (20, 1)])),
            Some(s(&[(1, 2), (5, 1), (20, 1)]))
        );
        assert_eq!(added(&before, &before), Some(s(&[])));
        assert_eq!(added(&s(&[]), &before), Some(before.clone()));
        assert_eq!(added(&before, &s(&[(3, 1), (9, 1)])), None, "relabelled");
        assert_eq!(added(&before, &s(&[(3, 1)])), None, "erased last");
        assert_eq!(added(&before, &s(&[(4, 1), (9, 2)])), None, "erased first");
        let mut other = before.clone();
        other.dims = [4, 4, 5];
        assert_eq!(added(&before, &other), None, "another grid");
    }

    #[test]
    fn near_is_a_box_dilation() {
        let d = [9, 7, 6];
        let n: usize = d.iter().product();
        let at = |x: usize, y: usize, z: usize| (z * d[1] + y) * d[0] + x;
        let mut marked = vec![false; n];
        marked[at(2, 3, 4)] = true;
        let m = near(&marked, d, 1);
        for z in 0..d[2] {
            for y in 0..d[1] {
                for x in 0..d[0] {
                    let inside = x.abs_diff(2) <= 1 && y.abs_diff(3) <= 1 && z.abs_diff(4) <= 1;
                    assert_eq!(m[at(x, y, z)], inside, "{x} {y} {z}");
                }
            }
        }
        assert!(near(&marked, d, 0) == marked);
        assert!(near(&marked, d, 9).iter().all(|&v| v));
        assert!(!near(&vec![false; n], d, 3).iter().any(|&v| v));
        let scr = crate::Scribbles {
            dims: d,
            voxels: vec![(at(2, 3, 4) as u64, 1)],
        };
        assert_eq!(near_scribbles(&scr, 1), m);
        let none = crate::Scribbles {
            dims: d,
            voxels: Vec::new(),
        };
        assert!(!near_scribbles(&none, 3).iter().any(|&v| v));
        // Random marks against the distance itself.
        let mut rng = neuvolex_bricks::rng::Rng::new(5);
        let marked: Vec<bool> = (0..n).map(|_| rng.f32() < 0.02).collect();
        let pts: Vec<[usize; 3]> = (0..n)
            .filter(|&i| marked[i])
            .map(|i| [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])])
            .collect();
        for margin in [0, 1, 2] {
            let m = near(&marked, d, margin);
            for (i, &got) in m.iter().enumerate() {
                let q = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                let want = pts
                    .iter()
                    .any(|p| (0..3).all(|a| p[a].abs_diff(q[a]) <= margin));
                assert_eq!(got, want, "voxel {q:?}, margin {margin}");
            }
        }
    }

    #[test]
    fn a_wobble_sticks_and_clear_evidence_or_a_near_stroke_changes() {
        // Classes: index 0 = label 1, index 1 = label 2, index 2 = background.
        let out = [1u16, 2, 0];
        let bg = Some(2);
        let probs: Vec<u8> = vec![
            120, 130, 5, // 0: 2 beats 1 by 10 steps: a wobble, 1 sticks
            40, 200, 15, // 1: 2 beats 1 by 160: it changes
            120, 130, 5, // 2: a wobble, but near the new stroke: it changes
            100, 20,
            135, // 3: previous 1, new 0 (background 135 beats 100 by 35 < 40): sticks
            10, 20, 225, // 4: previous 1, new 0 with clear evidence: changes
            128, 127, 0, // 5: unchanged
        ];
        let prev = vec![1u16, 1, 1, 1, 1, 1];
        let mut labels = vec![2u16, 2, 2, 0, 0, 1];
        let close = [false, false, true, false, false, false];
        let kept = stick(&mut labels, &prev, &probs, &out, bg, &close, 40);
        assert_eq!(labels, vec![1, 2, 2, 1, 0, 1]);
        assert_eq!(kept, 2);
        // delta 0: the new labels whenever they are at least as probable.
        let mut labels = vec![2u16, 2, 2, 0, 0, 1];
        assert_eq!(stick(&mut labels, &prev, &probs, &out, bg, &close, 0), 0);
        // Without a scribbled background, label 0 scores 255 - max.
        assert_eq!(score(&[100, 20], &[1, 2], None, 0), 155);
        // A class the new forest does not know scores 0, so it never holds a voxel.
        assert_eq!(score(&[100, 20], &[1, 2], None, 7), 0);
    }

    #[test]
    fn the_default_holds_a_quarter() {
        assert_eq!(delta_u8(0.25), 64);
        assert_eq!(delta_u8(2.0), 255);
        let c = StableConfig::default();
        assert_eq!((c.margin, c.delta), (neuvolex_filters::filter_halo(), 0.25));
    }
}
