//! Errors of the GPU engine.

/// Everything that can fail on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the kind asked for.
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The adapter lacks a limit or feature the kernels need.
    #[error("GPU adapter {adapter}: {detail}")]
    Unsupported {
        /// The adapter.
        adapter: String,
        /// What is missing.
        detail: String,
    },
    /// wgpu reported an error (validation, out of memory, device lost, mapping).
    #[error("GPU: {0}")]
    Device(String),
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

impl From<neuvolex_gpu::GpuError> for GpuError {
    /// The device's error as this crate's: a buffer past the binding limit is a [`GpuError::Config`].
    fn from(e: neuvolex_gpu::GpuError) -> Self {
        use neuvolex_gpu::GpuError as G;
        match e {
            G::NoAdapter(s) => GpuError::NoAdapter(s),
            G::Unsupported { adapter, detail } => GpuError::Unsupported { adapter, detail },
            G::Device(s) => GpuError::Device(s),
            e @ G::TooLarge { .. } => GpuError::Config(e.to_string()),
        }
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
