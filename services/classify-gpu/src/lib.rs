//! # neuvolex-classify-gpu
//!
//! Classification on the GPU (issue 49): the trained random forest of `neuvolex-classify`
//! walked per voxel ([`GpuForest`]), and the classic filter bank of `neuvolex-filters` per brick
//! with its halo ([`GpuFilterBank`]), as WGSL compute kernels on wgpu. Both are checked against
//! the CPU paths on any adapter, Mesa's software lavapipe included (`tests/`).
//!
//! The CPU paths stay the reference and the fallback: nothing here changes them.

#![warn(missing_docs)]

pub mod device;
pub mod error;
pub mod filters;
pub mod forest;
pub mod stage;
pub mod stream;

/// The wgpu this crate builds on (for callers that record its dispatches into their own encoders).
pub use wgpu;

pub use device::{adapters_named, AdapterKind, GpuDevice, Tracked};
pub use error::{GpuError, Result};
pub use filters::GpuFilterBank;
pub use forest::{
    FeatureLayout, GpuForest, Prediction, BELOW_TAU, FOREST_WGSL, GROUP, MAX_CLASSES,
};
/// The shared device's errors, which [`GpuError::Gpu`] carries.
pub use neuvolex_gpu::GpuError as DeviceError;
pub use stage::{gpu_features, GpuAccelerator, GPU_FEATURE_SETS};
pub use stream::{plan_blocks, Block, StreamConfig, DEFAULT_BUDGET};
