//! Errors of the GPU classification path.

/// Everything that can fail on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the kind asked for.
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The adapter lacks a limit the kernels need.
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
    /// The input cannot be run on this device (too many classes, a buffer past the binding
    /// limit, rows that do not match the forest).
    #[error("GPU classification: {0}")]
    Input(String),
    /// The forest cannot be flattened (a damaged forest).
    #[error(transparent)]
    Forest(#[from] neuvolex_classify::ForestError),
}

impl From<neuvolex_gpu::GpuError> for GpuError {
    /// The device's error as this crate's: a buffer past the binding limit is a
    /// [`GpuError::Input`].
    fn from(e: neuvolex_gpu::GpuError) -> Self {
        use neuvolex_gpu::GpuError as G;
        match e {
            G::NoAdapter(s) => GpuError::NoAdapter(s),
            G::Unsupported { adapter, detail } => GpuError::Unsupported { adapter, detail },
            G::Device(s) => GpuError::Device(s),
            e @ G::TooLarge { .. } => GpuError::Input(e.to_string()),
        }
    }
}

/// Result alias.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;
