//! Errors of opening and using the device.

/// Everything that can fail while opening or using a [`crate::GpuDevice`].
///
/// ```
/// let e = neuvolex_gpu::GpuError::NoAdapter("none whose name contains 'x'".into());
/// assert_eq!(e.to_string(), "no GPU adapter: none whose name contains 'x'");
/// ```
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the kind (and name) asked for.
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The adapter lacks a limit or feature a caller needs.
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
    /// A storage buffer larger than the adapter lets one binding hold.
    #[error(
        "buffer '{label}' needs {} MiB, more than the adapter's storage binding limit of {} MiB",
        .bytes >> 20,
        .limit >> 20
    )]
    TooLarge {
        /// The buffer's label.
        label: String,
        /// Bytes asked for.
        bytes: u64,
        /// The largest binding, in bytes.
        limit: u64,
    },
}

/// Result alias.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;
