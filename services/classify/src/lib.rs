//! # neuvolex-classify
//!
//! Scribble-based classification for neuvolex. This first part is the random forest that
//! turns per-voxel features into class probabilities, with the paper's settings as defaults
//! (1000 trees, min samples split 8, sqrt features per split, no bootstrap, Gini,
//! predict_proba).

#![warn(missing_docs)]

pub mod forest;

pub use forest::{ClassWeight, Dataset, Forest, ForestConfig, ForestError, MaxFeatures};
