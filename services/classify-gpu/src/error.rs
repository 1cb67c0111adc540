//! Errors of the GPU classification path.

/// Everything that can fail on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// Opening or using the device failed ([`neuvolex_gpu::GpuError`]: no adapter, a missing
    /// limit, a wgpu error, a buffer past the binding limit).
    #[error(transparent)]
    Gpu(#[from] neuvolex_gpu::GpuError),
    /// The input cannot be run on this device (too many classes, a buffer past the binding
    /// limit, rows that do not match the forest).
    #[error("GPU classification: {0}")]
    Input(String),
    /// The forest cannot be flattened (a damaged forest).
    #[error(transparent)]
    Forest(#[from] neuvolex_classify::ForestError),
}

/// Result alias.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;
