//! # neuvolex-gpu
//!
//! One wgpu device for the NeuVolEx GPU crates (issue 49): the INR engine
//! (`neuvolex-features-gpu`) and classification (`neuvolex-classify-gpu`) open it the same way
//! and can share one [`GpuDevice`], so a process uses one card for features and classification.
//!
//! - Adapter choice: every adapter that runs compute shaders, best first (discrete,
//!   integrated, virtual, other, software), narrowed by name (`NEUVOLEX_GPU_ADAPTER`) and by
//!   [`AdapterKind`].
//! - Limits: the adapter's largest buffers and dispatches, [`STORAGE_BUFFERS`] storage buffers
//!   per shader stage where it has them, timestamp queries where it has them; callers check
//!   what they need with [`GpuDevice::require_storage_buffers`].
//! - Accounting: buffers made by [`GpuDevice::buffer`] are [`Tracked`]; live and peak bytes
//!   ([`MemoryReport`]).
//! - Errors: the first uncaptured wgpu error or device loss is kept for [`GpuDevice::check`].
//!
//! ```no_run
//! use neuvolex_gpu::{AdapterKind, GpuDevice};
//! let dev = GpuDevice::new(AdapterKind::Any)?;
//! let buf = dev.buffer("scratch", 1 << 20, neuvolex_gpu::wgpu::BufferUsages::STORAGE)?;
//! assert_eq!(dev.live_bytes(), 1 << 20);
//! drop(buf);
//! assert_eq!((dev.live_bytes(), dev.peak_bytes()), (0, 1 << 20));
//! # Ok::<(), neuvolex_gpu::GpuError>(())
//! ```

#![warn(missing_docs)]

pub mod device;
pub mod error;

/// The wgpu this crate builds on.
pub use wgpu;

pub use device::{
    adapters, adapters_named, hardware_adapter, is_software, AdapterKind, GpuDevice, MemoryReport,
    Tracked, ADAPTER_ENV, STORAGE_BUFFERS,
};
pub use error::{GpuError, Result};
