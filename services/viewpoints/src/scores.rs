//! Cluster normals, view visibility, the entropy map and greedy view selection, with per-brick
//! partials that merge exactly (fixed-point sums), so a progressive aggregation ends equal to the
//! one-shot computation.
//!
//! **Representative normal.** A cluster's gradients (world units) are summed; its normal is the
//! *negated*, normalised sum (gradients point into brighter material, so the outward surface
//! normal of a bright structure is opposite), and its *coherence* is `|sum g| / sum |g|` in
//! [0, 1]: 1 for a flat face, near 0 for a closed shell whose gradients cancel.
//!
//! **Visibility** of a cluster from eye direction `d` (centre to eye) blends the two cases:
//! `v = coherence * max(0, n . d) + (1 - coherence) / 2`. A coherent face is seen only from its
//! side; an incoherent shell is half-visible from everywhere.
//!
//! **Weight.** A cluster counts by `sum |g|`, the gradient magnitude summed over its voxels: a
//! boundary-area estimate, so homogeneous interiors (air, solid cores) weigh nothing.
//!
//! **Entropy** of a view: with `w_c = weight_c * v_c(d)` and `p_c = w_c / sum w`, `H = -sum p_c
//! ln p_c`, normalised by `ln` of the number of weighted clusters; it favours views that show
//! many clusters evenly.
//!
//! **Greedy selection.** Coverage `cov_c` starts at 0. Each step scores every candidate by its
//! uncovered visible mass `M(d) = sum_c weight_c max(0, v_c(d) - cov_c)` over the clusters still
//! below their coverage target (weights sum to 1)
//! times `(1 + H) / 2`, with `H` the normalised entropy of that remainder (so even views win, and
//! a view that alone shows the last uncovered cluster still counts), takes the best, and sets
//! `cov_c = max(cov_c, v_c(d))`.
//! It stops when every weighted cluster has `cov_c >= cover * vmax_c` (`vmax_c`, the
//! visibility from straight along its normal, is `coherence + (1 - coherence) / 2`; with the
//! default `cover = 0.5` a flat face counts as seen within 60 degrees of face-on), when the best
//! gain falls below
//! `min_gain` of the first, or at `max_views`.

use crate::{Result, ViewpointError};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Fixed-point scale of the gradient sums (exact, order-independent merging).
const SCALE: f64 = (1u64 << 24) as f64;

/// Per-brick cluster statistics: voxels, gradient sums and gradient-magnitude sums, in integers.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClusterPartial {
    /// Voxels per cluster.
    pub counts: Vec<u64>,
    /// Gradient sums (world units, fixed point).
    pub grad: Vec<[i64; 3]>,
    /// Gradient-magnitude sums (fixed point).
    pub mag: Vec<i64>,
}

impl ClusterPartial {
    /// Empty statistics for `k` clusters.
    pub fn new(k: usize) -> Self {
        ClusterPartial {
            counts: vec![0; k],
            grad: vec![[0; 3]; k],
            mag: vec![0; k],
        }
    }

    /// Statistics of one brick: the cluster of each voxel and its gradient in voxel units
    /// (converted to world units with `spacing`). Non-finite gradients count as zero.
    pub fn from_brick(
        k: usize,
        labels: &[u16],
        gradients: &[[f32; 3]],
        spacing: [f64; 3],
    ) -> Result<Self> {
        if labels.len() != gradients.len() {
            return Err(ViewpointError::Input(format!(
                "{} cluster labels for {} gradients",
                labels.len(),
                gradients.len()
            )));
        }
        let mut p = ClusterPartial::new(k);
        for (&c, g) in labels.iter().zip(gradients) {
            let c = c as usize;
            if c >= k {
                return Err(ViewpointError::Input(format!(
                    "cluster {c} out of range (k = {k})"
                )));
            }
            let w = [0, 1, 2].map(|a| {
                let v = g[a] as f64 / spacing[a];
                if v.is_finite() {
                    v
                } else {
                    0.0
                }
            });
            p.counts[c] += 1;
            for (s, v) in p.grad[c].iter_mut().zip(w) {
                *s += (v * SCALE).round() as i64;
            }
            p.mag[c] += ((w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt() * SCALE).round() as i64;
        }
        Ok(p)
    }

    /// Adds another brick's statistics.
    pub fn merge(&mut self, o: &ClusterPartial) {
        for c in 0..self.counts.len().min(o.counts.len()) {
            self.counts[c] += o.counts[c];
            self.mag[c] += o.mag[c];
            for a in 0..3 {
                self.grad[c][a] += o.grad[c][a];
            }
        }
    }

    /// Per-cluster normals, coherence and weights.
    pub fn summary(&self) -> Vec<ClusterSummary> {
        let total: f64 = self.mag.iter().map(|&m| m as f64).sum();
        (0..self.counts.len())
            .map(|c| {
                let g = self.grad[c].map(|v| v as f64 / SCALE);
                let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
                let mag = self.mag[c] as f64 / SCALE;
                let (normal, coherence) = if len > 0.0 && mag > 0.0 {
                    (
                        g.map(|v| (-v / len) as f32),
                        (len / mag).clamp(0.0, 1.0) as f32,
                    )
                } else {
                    ([0.0; 3], 0.0)
                };
                ClusterSummary {
                    count: self.counts[c],
                    normal,
                    coherence,
                    weight: if total > 0.0 {
                        self.mag[c] as f64 / total
                    } else {
                        0.0
                    },
                }
            })
            .collect()
    }
}

/// What the scores need of a cluster.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClusterSummary {
    /// Voxels.
    pub count: u64,
    /// Outward unit normal (zero when undefined).
    pub normal: [f32; 3],
    /// `|sum g| / sum |g|`.
    pub coherence: f32,
    /// Share of the total gradient magnitude (0 for interiors).
    pub weight: f64,
}

/// Visibility of a cluster from unit eye direction `d`.
#[inline]
pub fn visibility(s: &ClusterSummary, d: [f32; 3]) -> f32 {
    let nd = s.normal[0] * d[0] + s.normal[1] * d[1] + s.normal[2] * d[2];
    s.coherence * nd.max(0.0) + (1.0 - s.coherence) * 0.5
}

/// The largest visibility any view gives a cluster (looking along its normal).
pub fn best_visibility(s: &ClusterSummary) -> f32 {
    s.coherence + (1.0 - s.coherence) * 0.5
}

/// Normalised Shannon entropy of non-negative weights (0 for one or no positive weight).
pub fn entropy(w: &[f64], norm_by: usize) -> f64 {
    let t: f64 = w.iter().filter(|v| **v > 0.0).sum();
    if t <= 0.0 || norm_by < 2 {
        return 0.0;
    }
    let h: f64 = w
        .iter()
        .filter(|v| **v > 0.0)
        .map(|&v| {
            let p = v / t;
            -p * p.ln()
        })
        .sum();
    h / (norm_by as f64).ln()
}

/// Entropy and visibility of every candidate view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewScores {
    /// Unit eye directions.
    pub views: Vec<[f32; 3]>,
    /// Normalised entropy of each view.
    pub entropy: Vec<f32>,
    /// Visible mass of each view (share of the total weight).
    pub mass: Vec<f32>,
}

fn weighted(summ: &[ClusterSummary]) -> usize {
    summ.iter().filter(|s| s.weight > 0.0).count()
}

/// Scores every candidate view.
pub fn score_views(summ: &[ClusterSummary], views: &[[f32; 3]]) -> Result<ViewScores> {
    if views.is_empty() {
        return Err(ViewpointError::Param("no candidate views".into()));
    }
    let kw = weighted(summ);
    let (entropy_v, mass): (Vec<f32>, Vec<f32>) = views
        .par_iter()
        .map(|&d| {
            let w: Vec<f64> = summ
                .iter()
                .map(|s| s.weight * visibility(s, d) as f64)
                .collect();
            (entropy(&w, kw) as f32, w.iter().sum::<f64>() as f32)
        })
        .unzip();
    Ok(ViewScores {
        views: views.to_vec(),
        entropy: entropy_v,
        mass,
    })
}

/// The entropy over the whole sphere as a `width x height` longitude (azimuth -180..180) by
/// latitude (elevation 90 at the top .. -90) image, row-major.
pub fn entropy_map(summ: &[ClusterSummary], width: usize, height: usize) -> Vec<f32> {
    let kw = weighted(summ);
    (0..width * height)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % width, i / width);
            let az = -180.0 + 360.0 * (x as f32 + 0.5) / width as f32;
            let el = 90.0 - 180.0 * (y as f32 + 0.5) / height as f32;
            let d = crate::sphere::view_to_direction(az, el);
            let w: Vec<f64> = summ
                .iter()
                .map(|s| s.weight * visibility(s, d) as f64)
                .collect();
            entropy(&w, kw) as f32
        })
        .collect()
}

/// Settings of the greedy selection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SelectConfig {
    /// Share of its best visibility at which a cluster counts as seen.
    pub cover: f32,
    /// Stop when a step's gain falls below this share of the first step's.
    pub min_gain: f32,
    /// Most views.
    pub max_views: usize,
}

impl Default for SelectConfig {
    fn default() -> Self {
        SelectConfig {
            cover: 0.5,
            min_gain: 0.02,
            max_views: 12,
        }
    }
}

/// The selected views.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    /// Indices into the candidate views, in order of selection.
    pub views: Vec<usize>,
    /// Informativeness of each pick when it was made.
    pub gains: Vec<f32>,
    /// Final coverage of each cluster.
    pub coverage: Vec<f32>,
    /// Weighted clusters left below the coverage target.
    pub uncovered: Vec<usize>,
}

/// Greedy selection of complementary views (see the module notes).
pub fn select(
    summ: &[ClusterSummary],
    scores: &ViewScores,
    cfg: &SelectConfig,
) -> Result<Selection> {
    if cfg.max_views == 0 || !(0.0..=1.0).contains(&cfg.cover) {
        return Err(ViewpointError::Param(format!(
            "max views {} must be >= 1 and cover {} in [0, 1]",
            cfg.max_views, cfg.cover
        )));
    }
    let kw = weighted(summ);
    if kw == 0 {
        return Err(ViewpointError::Input(
            "no cluster has any surface (the volume is constant): no view is better than another"
                .into(),
        ));
    }
    let k = summ.len();
    let mut cov = vec![0.0f32; k];
    let mut sel = Selection {
        views: Vec::new(),
        gains: Vec::new(),
        coverage: Vec::new(),
        uncovered: Vec::new(),
    };
    let mut first = None;
    while sel.views.len() < cfg.max_views.min(scores.views.len()) {
        let best = scores
            .views
            .par_iter()
            .enumerate()
            .filter(|(i, _)| !sel.views.contains(i))
            .map(|(i, &d)| {
                // Only clusters still below their coverage target count.
                let w: Vec<f64> = summ
                    .iter()
                    .zip(&cov)
                    .map(|(s, &c)| {
                        if c >= cfg.cover * best_visibility(s) {
                            0.0
                        } else {
                            s.weight * (visibility(s, d) - c).max(0.0) as f64
                        }
                    })
                    .collect();
                let m: f64 = w.iter().sum();
                (i, (m * 0.5 * (1.0 + entropy(&w, kw))) as f32)
            })
            .reduce(
                || (usize::MAX, f32::MIN),
                |a, b| {
                    if b.1 > a.1 || (b.1 == a.1 && b.0 < a.0) {
                        b
                    } else {
                        a
                    }
                },
            );
        if best.0 == usize::MAX || best.1 <= 0.0 {
            break;
        }
        let f = *first.get_or_insert(best.1);
        if !sel.views.is_empty() && best.1 < cfg.min_gain * f {
            break;
        }
        let d = scores.views[best.0];
        for (c, s) in cov.iter_mut().zip(summ) {
            *c = c.max(visibility(s, d));
        }
        sel.views.push(best.0);
        sel.gains.push(best.1);
        let done = summ
            .iter()
            .zip(&cov)
            .all(|(s, &c)| s.weight <= 0.0 || c >= cfg.cover * best_visibility(s));
        if done {
            break;
        }
    }
    sel.uncovered = (0..k)
        .filter(|&c| summ[c].weight > 0.0 && cov[c] < cfg.cover * best_visibility(&summ[c]))
        .collect();
    sel.coverage = cov;
    Ok(sel)
}

/// Merges per-brick partials as bricks finish; a snapshot at any time scores the views from what
/// has arrived, and after the last brick it equals the one-shot computation.
#[derive(Debug, Clone)]
pub struct Aggregator {
    partial: ClusterPartial,
    bricks: usize,
}

impl Aggregator {
    /// An empty aggregation over `k` clusters.
    pub fn new(k: usize) -> Self {
        Aggregator {
            partial: ClusterPartial::new(k),
            bricks: 0,
        }
    }

    /// Adds one brick's partial.
    pub fn add(&mut self, p: &ClusterPartial) {
        self.partial.merge(p);
        self.bricks += 1;
    }

    /// Bricks merged so far.
    pub fn bricks(&self) -> usize {
        self.bricks
    }

    /// The merged statistics.
    pub fn partial(&self) -> &ClusterPartial {
        &self.partial
    }

    /// Scores of the views from the bricks merged so far.
    pub fn snapshot(&self, views: &[[f32; 3]]) -> Result<ViewScores> {
        score_views(&self.partial.summary(), views)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn face(normal: [f32; 3], weight: f64) -> ClusterSummary {
        ClusterSummary {
            count: 100,
            normal,
            coherence: 1.0,
            weight,
        }
    }

    #[test]
    fn six_faces_need_complementary_views() {
        let faces: Vec<ClusterSummary> = [
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
        ]
        .iter()
        .map(|&n| face(n, 1.0 / 6.0))
        .collect();
        let views = crate::sphere::fibonacci_sphere(1800);
        let s = score_views(&faces, &views).unwrap();
        let sel = select(&faces, &s, &SelectConfig::default()).unwrap();
        assert!(sel.uncovered.is_empty(), "{sel:?}");
        // Corner views see three faces each: two of them cover a cube.
        assert!(sel.views.len() <= 3, "{:?}", sel.views);
        // The best single view looks at a corner: high entropy over three faces.
        let best = s
            .entropy
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap()
            .0;
        let d = views[best];
        assert!(d.iter().all(|v| v.abs() > 0.4), "{d:?}");
    }

    #[test]
    fn merging_in_any_order_is_exact() {
        let labels: Vec<u16> = (0..1000).map(|i| (i % 7) as u16).collect();
        let grads: Vec<[f32; 3]> = (0..1000)
            .map(|i| {
                let x = i as f32 * 0.37;
                [x.sin(), x.cos() * 1e-3, (x * 3.0).sin() * 1e3]
            })
            .collect();
        let one = ClusterPartial::from_brick(7, &labels, &grads, [1.0, 2.0, 0.5]).unwrap();
        let parts: Vec<ClusterPartial> = labels
            .chunks(64)
            .zip(grads.chunks(64))
            .map(|(l, g)| ClusterPartial::from_brick(7, l, g, [1.0, 2.0, 0.5]).unwrap())
            .collect();
        let mut agg = Aggregator::new(7);
        for p in parts.iter().rev() {
            agg.add(p);
        }
        assert_eq!(agg.partial(), &one);
        assert_eq!(agg.bricks(), parts.len());
    }

    #[test]
    fn constant_volumes_and_bad_settings_are_clear() {
        let flat = vec![ClusterSummary {
            count: 10,
            normal: [0.0; 3],
            coherence: 0.0,
            weight: 0.0,
        }];
        let s = score_views(&flat, &[[0.0, 0.0, 1.0]]).unwrap();
        assert_eq!(s.entropy, vec![0.0]);
        let e = select(&flat, &s, &SelectConfig::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("constant"), "{e}");
        assert!(score_views(&flat, &[]).is_err());
        let one = vec![face([0.0, 0.0, 1.0], 1.0)];
        let s = score_views(&one, &[[0.0, 0.0, 1.0]]).unwrap();
        let sel = select(&one, &s, &SelectConfig::default()).unwrap();
        assert_eq!(sel.views, vec![0], "one candidate view is the answer");
        let bad = SelectConfig {
            max_views: 0,
            ..Default::default()
        };
        assert!(select(&one, &s, &bad).is_err());
    }
}
