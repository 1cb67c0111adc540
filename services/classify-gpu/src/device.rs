//! The device is [`neuvolex_gpu::GpuDevice`] (adapter choice, hardware first and software
//! lavapipe where nothing else exists; buffer accounting; error capture), shared with the INR
//! engine where a process opens one ([`crate::GpuAccelerator::new`]). This module adds the
//! kernels' limits and workgroup grid.

pub use neuvolex_gpu::{adapters_named, AdapterKind, GpuDevice, Tracked};

/// Storage buffers one kernel binds at most.
pub(crate) const STORAGE_BUFFERS: u32 = 4;

/// Workgroups `(x, y)` covering `groups` within `max` per dimension.
pub(crate) fn grid(groups: u32, max: u32) -> (u32, u32) {
    let x = groups.clamp(1, max.max(1));
    (x, groups.div_ceil(x).max(1))
}
