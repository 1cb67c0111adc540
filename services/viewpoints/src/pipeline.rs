//! The whole recommendation over a bricked volume, given how to read a brick's features and
//! gradients: k-means, progressive aggregation of cluster normals, view scores and selection.

use crate::kmeans::{KMeans, KMeansConfig};
use crate::scores::{
    score_views, select, Aggregator, ClusterSummary, SelectConfig, Selection, ViewScores,
};
use crate::{fibonacci_sphere, ClusterPartial, Result};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Settings of a recommendation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RecommendConfig {
    /// Clustering.
    pub kmeans: KMeansConfig,
    /// Candidate views on the sphere.
    pub views: usize,
    /// Greedy selection.
    pub select: SelectConfig,
}

impl Default for RecommendConfig {
    fn default() -> Self {
        RecommendConfig {
            kmeans: KMeansConfig::default(),
            views: 1800,
            select: SelectConfig::default(),
        }
    }
}

/// What a recommendation found.
#[derive(Debug, Clone)]
pub struct Recommendation {
    /// The clustering.
    pub kmeans: KMeans,
    /// Per-cluster normals, coherence and weights.
    pub summary: Vec<ClusterSummary>,
    /// Every candidate view's scores.
    pub scores: ViewScores,
    /// The selected views.
    pub selection: Selection,
    /// Seconds of k-means.
    pub kmeans_seconds: f64,
    /// Seconds of aggregation, scoring and selection.
    pub scoring_seconds: f64,
}

/// Recommends views over `bricks` bricks: `features(i)` gives brick `i`'s feature rows (`dim`
/// per voxel) and `gradients(i)` its voxels' intensity gradients in voxel units. `progress` sees
/// the aggregation after every brick (for progressive entropy maps).
pub fn recommend<F, R, G>(
    bricks: usize,
    dim: usize,
    features: F,
    gradients: G,
    spacing: [f64; 3],
    cfg: &RecommendConfig,
    progress: &mut dyn FnMut(usize, &Aggregator),
) -> Result<Recommendation>
where
    F: Fn(usize) -> Result<R> + Sync,
    R: AsRef<[f32]>,
    G: Fn(usize) -> Result<Vec<[f32; 3]>>,
{
    let t = Instant::now();
    let km = KMeans::fit(bricks, dim, &features, &cfg.kmeans)?;
    let kmeans_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let views = fibonacci_sphere(cfg.views);
    let mut agg = Aggregator::new(km.k());
    for i in 0..bricks {
        let rows = features(i)?;
        let labels = km.assign(rows.as_ref());
        agg.add(&ClusterPartial::from_brick(
            km.k(),
            &labels,
            &gradients(i)?,
            spacing,
        )?);
        progress(i + 1, &agg);
    }
    let summary = agg.partial().summary();
    let scores = score_views(&summary, &views)?;
    let selection = select(&summary, &scores, &cfg.select)?;
    Ok(Recommendation {
        kmeans: km,
        summary,
        scores,
        selection,
        kmeans_seconds,
        scoring_seconds: t.elapsed().as_secs_f64(),
    })
}
