//! A few distinct, informative views to show a user: greedy by score, each pick at least
//! `min_angle` degrees from every earlier one, with the reason it was picked in words.
//!
//! **Score of a step.** As in [`crate::scores::select`]: a candidate's uncovered visible mass
//! `M(d) = sum_c weight_c max(0, v_c(d) - cov_c)` over the clusters still below their coverage
//! target, times `(1 + H) / 2` with `H` the normalised entropy of that remainder. Once every
//! cluster is covered (no candidate left adds anything), the view's own informativeness
//! `mass(d) * (1 + H(d)) / 2` times its spread from the picks, `min_c (1 - |c . d|)` (1 a
//! right angle from every pick, 0 on a pick or its back), ranks the rest, so the list still
//! fills up to `count` with views that differ.
//!
//! **Separation.** A candidate nearer than `min_angle` to a picked view is never taken, so no
//! two picks are nearer than that. A candidate nearer than `min_angle` to the *opposite* of a
//! picked view (its back: a semi-transparent rendering from there is nearly the same picture,
//! mirrored) is taken only when no other candidate is left, so front/back pairs do not fill the
//! list while distinct views exist.
//!
//! **Reasons** come from the components that decided the pick: the first view is the best
//! single view (most boundary surface over the most clusters, evenly); a later view either
//! brings feature clusters into view that the earlier ones show poorly, or, once all are
//! seen, is another distinct angle. A view with the highest entropy of all candidates (the
//! most feature clusters visible evenly) or the most visible boundary surface says so too.
//! A cluster is *in view* when its visibility reaches `cover` of its best (the coverage
//! target of [`crate::scores::SelectConfig`]).

use crate::scores::{best_visibility, entropy, visibility, ClusterSummary, ViewScores};
use crate::{Result, ViewpointError};
use serde::{Deserialize, Serialize};

/// Settings of [`pick_distinct`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PickConfig {
    /// Views wanted (at least 1); fewer come back only when fewer candidates keep their
    /// distance.
    pub count: usize,
    /// Least angle between two picked views, in degrees, in `[0, 180]`.
    pub min_angle: f32,
    /// Share of its best visibility at which a cluster counts as in view, in `[0, 1]`.
    pub cover: f32,
}

impl Default for PickConfig {
    /// Four views, 30 degrees apart at least, clusters in view at half their best visibility.
    fn default() -> Self {
        PickConfig {
            count: 4,
            min_angle: 30.0,
            cover: 0.5,
        }
    }
}

/// Which score component decided a pick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Why {
    /// The first pick: the most boundary surface over the most clusters, evenly.
    BestSingle,
    /// It shows clusters better that the earlier picks show poorly.
    Reveals,
    /// Every cluster is already in view: the most informative view left at a distinct angle.
    Distinct,
}

/// One picked view and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pick {
    /// Index into the candidate views.
    pub view: usize,
    /// The deciding component.
    pub why: Why,
    /// The view's normalised entropy over its visible clusters.
    pub entropy: f32,
    /// The view's visible boundary mass (share of the total weight).
    pub mass: f32,
    /// Boundary mass the view added over the earlier picks (share of the total weight).
    pub gain: f32,
    /// Weighted clusters in view from here.
    pub in_view: usize,
    /// Weighted clusters in view here that no earlier pick had in view.
    pub new: usize,
    /// Degrees to the nearest earlier pick (`None` for the first).
    pub nearest: Option<f32>,
    /// The reason in words.
    pub reason: String,
}

/// The picked views.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Picks {
    /// The picks, in order.
    pub picks: Vec<Pick>,
    /// Clusters with any weight (the "of N" of the reasons).
    pub clusters: usize,
    /// Weighted clusters no pick has in view.
    pub uncovered: Vec<usize>,
}

/// A coverage gain at or below this counts as none (every cluster already in view).
const GAIN_EPS: f64 = 1e-9;

/// How far `d` lies from the nearest pick's axis: `min (1 - |c . d|)`, 1 with no picks, 0 on
/// a pick or its back.
fn spread(chosen: &[[f32; 3]], d: [f32; 3]) -> f64 {
    chosen
        .iter()
        .map(|&c| 1.0 - dot(c, d).abs())
        .fold(1.0, f64::min)
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f64 {
    a[0] as f64 * b[0] as f64 + a[1] as f64 * b[1] as f64 + a[2] as f64 * b[2] as f64
}

/// The angle in degrees between two unit directions.
pub fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f32 {
    dot(a, b).clamp(-1.0, 1.0).acos().to_degrees() as f32
}

/// Picks up to `cfg.count` views from `scores`, no two nearer than `cfg.min_angle` degrees,
/// greedily by score (see the module notes), each with the reason it was picked.
pub fn pick_distinct(
    summ: &[ClusterSummary],
    scores: &ViewScores,
    cfg: &PickConfig,
) -> Result<Picks> {
    if cfg.count == 0
        || !(0.0..=180.0).contains(&cfg.min_angle)
        || !(0.0..=1.0).contains(&cfg.cover)
    {
        return Err(ViewpointError::Param(format!(
            "count {} must be >= 1, min_angle {} in [0, 180] and cover {} in [0, 1]",
            cfg.count, cfg.min_angle, cfg.cover
        )));
    }
    let n = scores.views.len();
    if n == 0 || scores.entropy.len() != n || scores.mass.len() != n {
        return Err(ViewpointError::Input(format!(
            "{n} candidate views with {} entropies and {} masses",
            scores.entropy.len(),
            scores.mass.len()
        )));
    }
    let kw = summ.iter().filter(|s| s.weight > 0.0).count();
    if kw == 0 {
        return Err(ViewpointError::Input(
            "no cluster has any surface (the volume is constant): no view is better than another"
                .into(),
        ));
    }
    let target: Vec<f32> = summ
        .iter()
        .map(|s| cfg.cover * best_visibility(s))
        .collect();
    let in_view = |d: [f32; 3]| -> Vec<bool> {
        summ.iter()
            .zip(&target)
            .map(|(s, &t)| s.weight > 0.0 && visibility(s, d) >= t)
            .collect()
    };
    // The view's own informativeness, and the best entropy and mass of all candidates.
    let own: Vec<f64> = (0..n)
        .map(|i| scores.mass[i] as f64 * 0.5 * (1.0 + scores.entropy[i] as f64))
        .collect();
    let top_entropy = scores.entropy.iter().copied().fold(f32::MIN, f32::max);
    let top_mass = scores.mass.iter().copied().fold(f32::MIN, f32::max);
    let cos_min = (cfg.min_angle as f64).to_radians().cos();
    let mut cov = vec![0.0f32; summ.len()];
    let mut seen = vec![false; summ.len()];
    let mut picks: Vec<Pick> = Vec::new();
    while picks.len() < cfg.count {
        let chosen: Vec<[f32; 3]> = picks.iter().map(|p| scores.views[p.view]).collect();
        // (tier, gain, own score) of the best candidate: tier 1 keeps clear of the picks'
        // backs too, tier 0 only of the picks.
        // The best candidate and its key: (tier, phase, value). Tier 1 keeps clear of the
        // picks' backs too, tier 0 only of the picks; phase 1 ranks by coverage gain, phase 0
        // (nothing left to cover) by the view's own score times its spread from the picks.
        let mut best: Option<(usize, (u8, u8, f64), f64)> = None;
        for (i, &d) in scores.views.iter().enumerate() {
            if picks.iter().any(|p| p.view == i) || chosen.iter().any(|&c| dot(c, d) > cos_min) {
                continue;
            }
            let tier =
                u8::from(cfg.min_angle <= 0.0 || !chosen.iter().any(|&c| -dot(c, d) > cos_min));
            let w: Vec<f64> = summ
                .iter()
                .zip(&cov)
                .zip(&target)
                .map(|((s, &c), &t)| {
                    if c >= t {
                        0.0
                    } else {
                        s.weight * (visibility(s, d) - c).max(0.0) as f64
                    }
                })
                .collect();
            let m: f64 = w.iter().sum();
            let gain = m * 0.5 * (1.0 + entropy(&w, kw));
            let key = if gain > GAIN_EPS {
                (tier, 1, gain)
            } else {
                (tier, 0, own[i] * spread(&chosen, d))
            };
            let better = match &best {
                None => true,
                Some((_, k, _)) => {
                    (key.0, key.1) > (k.0, k.1) || ((key.0, key.1) == (k.0, k.1) && key.2 > k.2)
                }
            };
            if better {
                best = Some((i, key, gain));
            }
        }
        let Some((i, _, g)) = best else { break };
        let d = scores.views[i];
        let here = in_view(d);
        let new = here.iter().zip(&seen).filter(|(h, s)| **h && !**s).count();
        let added: f64 = summ
            .iter()
            .zip(&cov)
            .map(|(s, &c)| s.weight * (visibility(s, d) - c).max(0.0) as f64)
            .sum();
        let why = if picks.is_empty() {
            Why::BestSingle
        } else if g > GAIN_EPS {
            Why::Reveals
        } else {
            Why::Distinct
        };
        let nearest = chosen
            .iter()
            .map(|&c| angle_deg(c, d))
            .min_by(|a, b| a.total_cmp(b));
        let mut pick = Pick {
            view: i,
            why,
            entropy: scores.entropy[i],
            mass: scores.mass[i],
            gain: added as f32,
            in_view: here.iter().filter(|h| **h).count(),
            new,
            nearest,
            reason: String::new(),
        };
        pick.reason = reason(
            &pick,
            kw,
            scores.entropy[i] >= top_entropy,
            scores.mass[i] >= top_mass,
        );
        for (c, s) in cov.iter_mut().zip(summ) {
            *c = c.max(visibility(s, d));
        }
        for (s, h) in seen.iter_mut().zip(&here) {
            *s |= *h;
        }
        picks.push(pick);
    }
    let uncovered = (0..summ.len())
        .filter(|&c| summ[c].weight > 0.0 && !seen[c])
        .collect();
    Ok(Picks {
        picks,
        clusters: kw,
        uncovered,
    })
}

/// The reason of a pick in words, from its components.
fn reason(p: &Pick, clusters: usize, top_entropy: bool, top_mass: bool) -> String {
    let plural = |n: usize| if n == 1 { "" } else { "s" };
    let mut r = match p.why {
        Why::BestSingle => format!(
            "best single view: {} of {clusters} feature clusters in view",
            p.in_view
        ),
        Why::Reveals if p.new > 0 => format!(
            "brings {} feature cluster{} into view that the views before show poorly",
            p.new,
            plural(p.new)
        ),
        Why::Reveals => format!(
            "shows partly hidden boundaries better (+{:.0} % of the boundary surface)",
            100.0 * p.gain
        ),
        Why::Distinct => format!(
            "another angle, {:.0}° from the nearest view: {} of {clusters} feature clusters in view",
            p.nearest.unwrap_or(0.0),
            p.in_view
        ),
    };
    if top_entropy {
        r.push_str("; the most feature clusters visible evenly");
    }
    if top_mass {
        r.push_str("; the most boundary surface facing the camera");
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scores::score_views;
    use crate::sphere::fibonacci_sphere;

    fn cluster(normal: [f32; 3], coherence: f32, weight: f64) -> ClusterSummary {
        ClusterSummary {
            count: 100,
            normal,
            coherence,
            weight,
        }
    }

    /// A symmetric object: the same surface facing +y and -y (a slab's two faces) and a
    /// closed shell; its score is the same from the front and the back.
    fn slab() -> Vec<ClusterSummary> {
        vec![
            cluster([0.0, 1.0, 0.0], 1.0, 0.4),
            cluster([0.0, -1.0, 0.0], 1.0, 0.4),
            cluster([0.0, 0.0, 0.0], 0.0, 0.2),
        ]
    }

    fn faces() -> Vec<ClusterSummary> {
        [
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
        ]
        .iter()
        .map(|&n| cluster(n, 1.0, 1.0 / 6.0))
        .collect()
    }

    fn min_pairwise(p: &Picks, views: &[[f32; 3]]) -> f32 {
        let mut m = f32::MAX;
        for (a, pa) in p.picks.iter().enumerate() {
            for pb in &p.picks[a + 1..] {
                m = m.min(angle_deg(views[pa.view], views[pb.view]));
            }
        }
        m
    }

    #[test]
    fn picks_keep_the_minimum_angle_apart() {
        let views = fibonacci_sphere(1800);
        for summ in [faces(), slab()] {
            let s = score_views(&summ, &views).unwrap();
            for (count, min_angle) in [(4, 30.0), (12, 30.0), (8, 45.0), (6, 60.0), (3, 100.0)] {
                let cfg = PickConfig {
                    count,
                    min_angle,
                    ..Default::default()
                };
                let p = pick_distinct(&summ, &s, &cfg).unwrap();
                let m = min_pairwise(&p, &views);
                assert!(
                    m >= min_angle - 1e-3,
                    "{count} views {min_angle} apart: two are {m} apart: {p:?}"
                );
                for (k, pk) in p.picks.iter().enumerate().skip(1) {
                    assert!(pk.nearest.unwrap() >= min_angle - 1e-3, "{k}: {pk:?}");
                }
            }
        }
    }

    #[test]
    fn the_count_is_honoured_when_possible() {
        let views = fibonacci_sphere(1800);
        let summ = faces();
        let s = score_views(&summ, &views).unwrap();
        // A cube is covered by two corner views; the list still fills to the count asked.
        for count in 1..=12 {
            let cfg = PickConfig {
                count,
                ..Default::default()
            };
            let p = pick_distinct(&summ, &s, &cfg).unwrap();
            assert_eq!(p.picks.len(), count, "{p:?}");
            assert!(count < 3 || p.uncovered.is_empty(), "{p:?}");
        }
        // Four views 150 degrees apart cannot exist: as many as fit come back.
        let cfg = PickConfig {
            count: 4,
            min_angle: 150.0,
            ..Default::default()
        };
        let p = pick_distinct(&summ, &s, &cfg).unwrap();
        assert_eq!(p.picks.len(), 2, "{p:?}");
        // Fewer candidates than asked: all of them.
        let few = &views[..3];
        let s3 = score_views(&summ, few).unwrap();
        let cfg = PickConfig {
            count: 5,
            min_angle: 0.0,
            ..Default::default()
        };
        assert_eq!(pick_distinct(&summ, &s3, &cfg).unwrap().picks.len(), 3);
    }

    #[test]
    fn front_and_back_do_not_fill_the_list() {
        let views = fibonacci_sphere(1800);
        let summ = slab();
        let s = score_views(&summ, &views).unwrap();
        // The score is symmetric: each face is seen from its side only, equally.
        let p = pick_distinct(&summ, &s, &PickConfig::default()).unwrap();
        assert_eq!(p.picks.len(), 4);
        for (a, pa) in p.picks.iter().enumerate() {
            for pb in &p.picks[a + 1..] {
                let back = 180.0 - angle_deg(views[pa.view], views[pb.view]);
                assert!(back >= 30.0 - 1e-3, "a front/back pair: {p:?}");
            }
        }
        // Only two views wanted 180 degrees apart: the back is the one left, and it is taken.
        let cfg = PickConfig {
            count: 2,
            min_angle: 170.0,
            ..Default::default()
        };
        assert_eq!(pick_distinct(&summ, &s, &cfg).unwrap().picks.len(), 2);
    }

    #[test]
    fn reasons_name_the_deciding_component() {
        let views = fibonacci_sphere(1800);
        let summ = faces();
        let s = score_views(&summ, &views).unwrap();
        let cfg = PickConfig {
            count: 6,
            ..Default::default()
        };
        let p = pick_distinct(&summ, &s, &cfg).unwrap();
        assert_eq!(p.clusters, 6);
        assert_eq!(p.picks[0].why, Why::BestSingle);
        assert!(
            p.picks[0].reason.starts_with("best single view: 3 of 6"),
            "{p:?}"
        );
        // The first corner view shows three faces; the opposite corner (its back) is passed
        // over, so the next views each bring faces still unseen into view.
        assert_eq!(p.picks[1].why, Why::Reveals);
        assert!(p.picks[1].new >= 1, "{p:?}");
        assert!(p.picks[1].reason.contains("into view"), "{p:?}");
        // Once everything is in view the rest are distinct angles.
        let last = p.picks.last().unwrap();
        assert!(p.uncovered.is_empty(), "{p:?}");
        assert_eq!(last.why, Why::Distinct, "{p:?}");
        assert!(last.reason.starts_with("another angle"), "{p:?}");
        assert!(p.picks.iter().all(|k| !k.reason.is_empty()));
    }

    #[test]
    fn bad_settings_name_the_parameter() {
        let views = fibonacci_sphere(50);
        let summ = faces();
        let s = score_views(&summ, &views).unwrap();
        for cfg in [
            PickConfig {
                count: 0,
                ..Default::default()
            },
            PickConfig {
                min_angle: 181.0,
                ..Default::default()
            },
            PickConfig {
                min_angle: f32::NAN,
                ..Default::default()
            },
        ] {
            let e = pick_distinct(&summ, &s, &cfg).unwrap_err().to_string();
            assert!(e.contains("min_angle") && e.contains("count"), "{e}");
        }
        let flat = vec![cluster([0.0; 3], 0.0, 0.0)];
        let s = score_views(&flat, &views).unwrap();
        let e = pick_distinct(&flat, &s, &PickConfig::default()).unwrap_err();
        assert!(e.to_string().contains("constant"), "{e}");
    }
}
