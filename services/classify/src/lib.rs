//! # neuvolex-classify
//!
//! Scribble-based classification for neuvolex (image-based transfer-function design):
//! scribbles (strokes, rasterisation and the S1–S4 simulator), feature sets (learned INR
//! features, classic baselines, position), the random forest with the paper's settings as
//! defaults (1000 trees, min samples split 8, sqrt features per split, no bootstrap, Gini,
//! predict_proba), and sharded per-brick classification with F1 scoring.

#![warn(missing_docs)]

pub mod accel;
pub mod cache;
pub mod components;
pub mod features;
pub mod forest;
mod packed;
pub mod persist;
pub mod pipeline;
pub mod preview;
pub mod round;
pub mod scribble;
pub mod shard;
pub mod stable;
pub mod suggest;

pub use components::{Partial, PriorConfig};
pub use features::{BrickFeatures, Component, FeatureMemo, FeatureSet, Quantise, DEFAULT_FEATURES};
pub use forest::{
    ClassWeight, Dataset, FlatForest, Forest, ForestConfig, ForestError, MaxFeatures, LEAF_FEATURE,
};
pub use scribble::{
    load_scribbles, rasterise, simulate, thicken, Level, ScribbleError, ScribbleSource, Scribbles,
    SimConfig, Stroke,
};
pub use shard::{
    classify_brick, classify_volume, f1_scores, fit, output_labels, predict_brick, training_set,
    BrickResult, ClassTable, Classified, ClassifyConfig, TrainingSet, F1,
};
pub use stable::StableConfig;
pub use suggest::{SliceMass, Suggestion};

use std::path::PathBuf;

/// Errors of classification.
#[derive(Debug, thiserror::Error)]
pub enum ClassifyError {
    /// A volume or store error.
    #[error(transparent)]
    Volume(#[from] neuvolex_bricks::BrickError),
    /// A feature (INR) error.
    #[error(transparent)]
    Features(#[from] neuvolex_features::FeatureError),
    /// A forest error.
    #[error(transparent)]
    Forest(#[from] ForestError),
    /// A scribble error.
    #[error(transparent)]
    Scribble(#[from] ScribbleError),
    /// A file that cannot be used.
    #[error("{path}: {detail}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// Inputs that do not fit together.
    #[error("{0}")]
    Input(String),
}

impl From<neuvolex_formats::FormatError> for ClassifyError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        ClassifyError::Volume(e.into())
    }
}
