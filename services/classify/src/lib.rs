//! # neuvolex-classify
//!
//! Scribble-based classification for neuvolex: scribbles (strokes, rasterisation and the S1–S4
//! simulator) and the random forest that turns per-voxel features into class probabilities, with the paper's settings as defaults
//! (1000 trees, min samples split 8, sqrt features per split, no bootstrap, Gini,
//! predict_proba).

#![warn(missing_docs)]

pub mod forest;
pub mod scribble;

pub use forest::{ClassWeight, Dataset, Forest, ForestConfig, ForestError, MaxFeatures};
pub use scribble::{
    rasterise, simulate, Level, ScribbleError, ScribbleSource, Scribbles, SimConfig, Stroke,
};
