//! Errors of the GPU engine.

/// Everything that can fail on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// Opening or using the device failed ([`neuvolex_gpu::GpuError`]: no adapter, a missing
    /// limit, a wgpu error, a buffer past the binding limit).
    #[error(transparent)]
    Gpu(#[from] neuvolex_gpu::GpuError),
    /// The model or the run cannot be placed on this device.
    #[error("GPU: {0}")]
    Config(String),
    /// The feature stage failed (store, checkpoint, configuration, cancellation).
    #[error(transparent)]
    Feature(#[from] neuvolex_features::FeatureError),
    /// The brick store failed.
    #[error(transparent)]
    Brick(#[from] neuvolex_bricks::BrickError),
}

impl From<neuvolex_formats::FormatError> for GpuError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        GpuError::Brick(e.into())
    }
}

/// Result alias.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;

impl From<GpuError> for neuvolex_features::FeatureError {
    fn from(e: GpuError) -> Self {
        match e {
            GpuError::Feature(f) => f,
            GpuError::Brick(b) => neuvolex_features::FeatureError::Brick(b),
            o => neuvolex_features::FeatureError::Config(o.to_string()),
        }
    }
}
