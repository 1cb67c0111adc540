//! # neuvolex-viewpoints
//!
//! The paper's adaptation of iView: cluster the per-voxel features with k-means (k = 50), give
//! each cluster a representative normal from its gradients, score 1800 candidate views on a
//! Fibonacci sphere by the entropy of the clusters they show, and greedily pick a compact set of
//! complementary views; [`pick::pick_distinct`] picks a few distinct ones for a user, each
//! with its reason.
//!
//! Everything per brick is a pure function returning a mergeable partial
//! ([`kmeans::Partial`], [`scores::ClusterPartial`]); schedulers merge partials as bricks finish,
//! and the merged result equals the one-shot computation exactly (integer accumulators).

#![warn(missing_docs)]

pub mod distributed;
pub mod kmeans;
mod nearest;
pub mod pick;
pub mod pipeline;
pub mod scores;
pub mod sphere;

pub use kmeans::{KMeans, KMeansConfig};
pub use pick::{pick_distinct, Pick, PickConfig, Picks, Why};
pub use pipeline::{recommend, RecommendConfig, Recommendation};
pub use scores::{ClusterPartial, ClusterSummary, Selection, ViewScores};
pub use sphere::{direction_to_view, fibonacci_sphere, view_to_direction};

/// Errors of viewpoint recommendation.
#[derive(Debug, thiserror::Error)]
pub enum ViewpointError {
    /// A parameter is out of range.
    #[error("invalid parameter: {0}")]
    Param(String),
    /// The input cannot be clustered or scored.
    #[error("{0}")]
    Input(String),
    /// Reading bricks failed.
    #[error(transparent)]
    Bricks(#[from] neuvolex_bricks::BrickError),
}

impl From<neuvolex_formats::FormatError> for ViewpointError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        ViewpointError::Bricks(e.into())
    }
}

/// Result with [`ViewpointError`].
pub type Result<T, E = ViewpointError> = std::result::Result<T, E>;
