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

/// Result alias.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;
