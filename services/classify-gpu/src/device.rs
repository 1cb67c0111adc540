//! The device is [`neuvolex_gpu::GpuDevice`] (adapter choice, hardware first and software
//! lavapipe where nothing else exists; buffer accounting; error capture), shared with the INR
//! engine where a process opens one ([`crate::GpuAccelerator::new`]). This module adds the
//! kernels' layout helpers.

use crate::error::{GpuError, Result};
pub use neuvolex_gpu::{adapters_named, AdapterKind, GpuDevice, Tracked};

/// Storage buffers one kernel binds at most.
pub(crate) const STORAGE_BUFFERS: u32 = 4;

/// Compiles `source`'s entry point `entry` with a layout of one uniform (binding 0) and
/// the storage buffers `read_only` describes (bindings 1, 2, ...).
pub(crate) fn pipeline(
    dev: &GpuDevice,
    label: &str,
    source: &str,
    entry: &str,
    read_only: &[bool],
) -> Result<(wgpu::ComputePipeline, wgpu::BindGroupLayout)> {
    let scope = dev.device.push_error_scope(wgpu::ErrorFilter::Validation);
    let mut entries = vec![wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }];
    entries.extend(
        read_only
            .iter()
            .enumerate()
            .map(|(i, &ro)| wgpu::BindGroupLayoutEntry {
                binding: i as u32 + 1,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: ro },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }),
    );
    let layout = dev
        .device
        .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(label),
            entries: &entries,
        });
    let pl = dev
        .device
        .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
    let module = dev
        .device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
    let pipe = dev
        .device
        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(label),
            layout: Some(&pl),
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        });
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Device(format!("compiling '{label}': {e}")));
    }
    Ok((pipe, layout))
}

/// A bind group of `layout` over `uniform` (binding 0) and `storage` (bindings 1, 2, ...).
pub(crate) fn bind(
    dev: &GpuDevice,
    layout: &wgpu::BindGroupLayout,
    uniform: &wgpu::Buffer,
    storage: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let mut entries = vec![wgpu::BindGroupEntry {
        binding: 0,
        resource: uniform.as_entire_binding(),
    }];
    entries.extend(
        storage
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32 + 1,
                resource: b.as_entire_binding(),
            }),
    );
    dev.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout,
        entries: &entries,
    })
}

/// Workgroups `(x, y)` covering `groups` within `max` per dimension.
pub(crate) fn grid(groups: u32, max: u32) -> (u32, u32) {
    let x = groups.clamp(1, max.max(1));
    (x, groups.div_ceil(x).max(1))
}
