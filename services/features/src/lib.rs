//! # neuvolex-features
//!
//! The NeuVolEx volume-exploration INR and the per-voxel features it yields: a multiresolution
//! hash-grid encoding of position, a structural encoder on the raw 5x5x5 patch fused by FiLM,
//! a 4x64 MLP with a residual projection, and heads for intensity, gradient, local mean and
//! local std. Training draws batches brick by brick from a [`neuvolex_bricks::BrickStore`];
//! extraction writes f16 feature bricks back into the store or computes them on demand.

#![warn(missing_docs)]

pub mod adam;
pub mod checkpoint;
pub mod config;
pub mod distributed;
pub mod error;
pub mod extract;
pub mod hashgrid;
pub mod model;
pub mod stage;
/// The seeded generator, shared with the rest of neuvolex.
pub use neuvolex_bricks::rng;
pub mod tile;
pub mod train;

pub use config::{Ablation, Backend, Budget, InrConfig, Preset, TableAdam, TrainConfig};
pub use error::{FeatureError, Result};
pub use extract::{write_features, FeatureCache, FeatureSource};
pub use model::{FeatureKind, InrModel};
pub use train::{train, TrainEvent, Trained};
