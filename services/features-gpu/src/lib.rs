//! # neuvolex-features-gpu
//!
//! The NeuVolEx INR of `neuvolex-features` on the GPU: the same parameters, checkpoints,
//! presets and [`neuvolex_features::TrainEvent`] stream, computed by WGSL compute kernels on
//! wgpu (Vulkan, Metal, D3D12; Mesa's software lavapipe in CI).
//!
//! - The hash-grid gather, one invocation per (sample, level); the structural encoder, FiLM,
//!   the residual MLP and the heads as one tiled GEMM kernel with fused bias, ReLU,
//!   accumulation and ReLU-mask epilogues; the loss; the backward pass as the same GEMM
//!   (data and weight gradients, the bias gradient as a column of ones).
//! - The table gradient is scattered in 64-bit fixed point with 32-bit integer atomics (a
//!   scale chosen per step from the largest encoding gradient), so its sum does not depend
//!   on the order the GPU runs the samples in: a seed gives one result, bit for bit. Dense
//!   gradients are summed from per-split partials in a fixed order.
//! - Adam on the dense parameters and on the table, lazy (touched rows, marked by the
//!   scatter) or dense, as the CPU engine offers.
//! - Out of core: tiles come from the brick store through the CPU trainer's tile code, are
//!   prepared on host threads while the GPU trains on the previous group, and are written
//!   into a ring of two tile groups; GPU memory is the model plus that ring, whatever the
//!   volume's size ([`context::MemoryReport`]).
//! - The device is a [`neuvolex_gpu::GpuDevice`], which other GPU crates (classification) can
//!   share: [`GpuContext::on`] compiles the kernels on an open one, [`GpuContext::gpu`] gives it.

#![warn(missing_docs)]

pub mod context;
pub mod engine;
pub mod error;
pub mod extract;
pub mod plan;
pub mod train;

/// The wgpu this crate builds on (for callers that use the shared [`GpuDevice`] directly).
pub use neuvolex_gpu::wgpu;

pub use context::{
    fused_source, hardware_adapter, AdapterKind, GpuContext, GpuDevice, MemoryReport, TileArith,
};
pub use engine::{EngineOptions, FeatureFormat, GpuInr, MlpPath, StepRates};
pub use error::{GpuError, Result};
pub use extract::write_features_gpu;
/// The shared device's errors, which [`GpuError::Gpu`] carries.
pub use neuvolex_gpu::GpuError as DeviceError;
pub use train::{train_gpu, train_gpu_tuned, GpuTrained, GpuTune};

use neuvolex_features::Backend;
use std::sync::Arc;

/// Resolves a backend choice: `Cpu` gives `None`; `Gpu` opens any adapter (software ones
/// included) or fails; `Auto` opens a hardware GPU when there is one, else gives `None`.
pub fn resolve(backend: Backend) -> Result<Option<Arc<GpuContext>>> {
    match backend {
        Backend::Cpu => Ok(None),
        Backend::Gpu => GpuContext::new(AdapterKind::Any).map(Some),
        Backend::Auto => match GpuContext::new(AdapterKind::Hardware) {
            Ok(c) => Ok(Some(c)),
            Err(GpuError::Gpu(DeviceError::NoAdapter(_))) => Ok(None),
            Err(e) => {
                tracing::warn!("no usable GPU ({e}); using the CPU engine");
                Ok(None)
            }
        },
    }
}
