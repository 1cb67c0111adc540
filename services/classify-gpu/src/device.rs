//! The device: adapter choice (hardware first, software lavapipe where nothing else exists),
//! buffer accounting (live and peak bytes) and error capture.
//!
//! This follows `neuvolex-features-gpu`'s context (the same adapter order and the same
//! `NEUVOLEX_GPU_ADAPTER` filter) but opens its own `wgpu::Device`: the shared context of
//! issue 49 part 1 does not exist yet.

use crate::error::{GpuError, Result};
use std::sync::{Arc, Mutex};

/// Which adapters qualify.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterKind {
    /// Any adapter, software ones (Mesa lavapipe, llvmpipe, SwiftShader) included.
    Any,
    /// Hardware GPUs only.
    Hardware,
}

/// Storage buffers one kernel binds at most.
pub(crate) const STORAGE_BUFFERS: u32 = 4;

#[derive(Debug, Default)]
struct Memory {
    live: u64,
    peak: u64,
}

/// A buffer counted in the device's accounting (live until dropped).
#[derive(Debug)]
pub struct Tracked {
    /// The buffer.
    pub buf: wgpu::Buffer,
    mem: Arc<Mutex<Memory>>,
}

impl Drop for Tracked {
    fn drop(&mut self) {
        let mut m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
        m.live = m.live.saturating_sub(self.buf.size());
    }
}

impl std::ops::Deref for Tracked {
    type Target = wgpu::Buffer;
    fn deref(&self) -> &wgpu::Buffer {
        &self.buf
    }
}

/// A wgpu device and queue with buffer accounting and captured errors.
pub struct GpuDevice {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    mem: Arc<Mutex<Memory>>,
    error: Arc<Mutex<Option<String>>>,
}

impl std::fmt::Debug for GpuDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuDevice")
            .field("adapter", &self.describe())
            .finish()
    }
}

fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

/// Every adapter that runs compute shaders, best first (discrete, integrated, virtual, other,
/// software), keeping only names that contain `name` (case-insensitive) where given.
pub fn adapters_named(name: Option<&str>) -> Vec<wgpu::Adapter> {
    let inst = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let mut all: Vec<wgpu::Adapter> =
        pollster::block_on(inst.enumerate_adapters(wgpu::Backends::PRIMARY))
            .into_iter()
            .filter(|a| {
                a.get_downlevel_capabilities()
                    .flags
                    .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
            })
            .collect();
    if let Some(want) = name {
        let want = want.to_lowercase();
        all.retain(|a| a.get_info().name.to_lowercase().contains(&want));
    }
    all.sort_by_key(|a| rank(a.get_info().device_type));
    all
}

impl GpuDevice {
    /// Opens the best adapter of `kind` (filtered by `NEUVOLEX_GPU_ADAPTER` where set).
    ///
    /// ```no_run
    /// use neuvolex_classify_gpu::{AdapterKind, GpuDevice};
    /// let dev = GpuDevice::new(AdapterKind::Any)?;
    /// println!("{}", dev.describe());
    /// # Ok::<(), neuvolex_classify_gpu::GpuError>(())
    /// ```
    pub fn new(kind: AdapterKind) -> Result<Arc<Self>> {
        Self::open(kind, std::env::var("NEUVOLEX_GPU_ADAPTER").ok().as_deref())
    }

    /// Opens the best adapter of `kind` whose name contains `name` (any where `None`).
    pub fn open(kind: AdapterKind, name: Option<&str>) -> Result<Arc<Self>> {
        let found = adapters_named(name);
        let names: Vec<String> = found
            .iter()
            .map(|a| {
                let i = a.get_info();
                format!("{} ({:?})", i.name, i.device_type)
            })
            .collect();
        let adapter = found
            .into_iter()
            .find(|a| kind == AdapterKind::Any || a.get_info().device_type != wgpu::DeviceType::Cpu)
            .ok_or_else(|| {
                GpuError::NoAdapter(if names.is_empty() {
                    "wgpu found none; install a Vulkan driver (mesa-vulkan-drivers for the \
                     software lavapipe, or the NVIDIA driver)"
                        .into()
                } else {
                    format!("only software adapters were found ({})", names.join(", "))
                })
            })?;
        Self::with_adapter(adapter)
    }

    /// Opens `adapter`, asking for its largest buffers and dispatches.
    pub fn with_adapter(adapter: wgpu::Adapter) -> Result<Arc<Self>> {
        let info = adapter.get_info();
        let have = adapter.limits();
        if have.max_storage_buffers_per_shader_stage < STORAGE_BUFFERS {
            return Err(GpuError::Unsupported {
                adapter: info.name.clone(),
                detail: format!(
                    "needs {STORAGE_BUFFERS} storage buffers per shader stage, has {}",
                    have.max_storage_buffers_per_shader_stage
                ),
            });
        }
        let required = wgpu::Limits {
            max_storage_buffers_per_shader_stage: STORAGE_BUFFERS,
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_compute_workgroups_per_dimension: have.max_compute_workgroups_per_dimension,
            ..wgpu::Limits::downlevel_defaults()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("neuvolex-classify-gpu"),
            required_features: wgpu::Features::empty(),
            required_limits: required.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", info.name)))?;
        let error: Arc<Mutex<Option<String>>> = Arc::default();
        let slot = error.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut s = slot.lock().unwrap_or_else(|p| p.into_inner());
            if s.is_none() {
                *s = Some(e.to_string());
            }
        }));
        let slot = error.clone();
        device.set_device_lost_callback(move |reason, msg| {
            let mut s = slot.lock().unwrap_or_else(|p| p.into_inner());
            if s.is_none() {
                *s = Some(format!("device lost ({reason:?}): {msg}"));
            }
        });
        Ok(Arc::new(GpuDevice {
            device,
            queue,
            info,
            limits: required,
            mem: Arc::default(),
            error,
        }))
    }

    /// "name (backend, type)".
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }

    /// Whether the adapter is a software rasteriser (lavapipe).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// The largest buffer one storage binding may hold, in bytes.
    pub fn max_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Workgroups one dispatch dimension may hold.
    pub fn max_groups(&self) -> u32 {
        self.limits.max_compute_workgroups_per_dimension
    }

    /// A zeroed buffer of at least `size` bytes (a multiple of 4), counted while it lives.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> Result<Tracked> {
        let size = size.max(4).div_ceil(4) * 4;
        if usage.contains(wgpu::BufferUsages::STORAGE) && size > self.max_binding() {
            return Err(GpuError::Input(format!(
                "buffer '{label}' needs {} MiB, more than the adapter's storage binding limit \
                 of {} MiB",
                size >> 20,
                self.max_binding() >> 20
            )));
        }
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage,
            mapped_at_creation: false,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!(
                "allocating '{label}' ({} MiB): {e}",
                size >> 20
            )));
        }
        let mut m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
        m.live += size;
        m.peak = m.peak.max(m.live);
        Ok(Tracked {
            buf,
            mem: self.mem.clone(),
        })
    }

    /// A storage buffer holding `data` (at least 4 bytes), counted while it lives.
    pub fn upload(&self, label: &str, data: &[u8], usage: wgpu::BufferUsages) -> Result<Tracked> {
        let b = self.buffer(
            label,
            data.len() as u64,
            usage | wgpu::BufferUsages::COPY_DST,
        )?;
        if !data.is_empty() {
            let n = data.len() / 4 * 4;
            self.queue.write_buffer(&b, 0, &data[..n]);
            if n < data.len() {
                let mut tail = [0u8; 4];
                tail[..data.len() - n].copy_from_slice(&data[n..]);
                self.queue.write_buffer(&b, n as u64, &tail);
            }
        }
        Ok(b)
    }

    /// Bytes of the buffers alive now.
    pub fn live_bytes(&self) -> u64 {
        self.mem.lock().unwrap_or_else(|p| p.into_inner()).live
    }

    /// The largest sum of live buffers seen since the last [`Self::reset_peak`].
    pub fn peak_bytes(&self) -> u64 {
        self.mem.lock().unwrap_or_else(|p| p.into_inner()).peak
    }

    /// Resets the peak to the bytes alive now.
    pub fn reset_peak(&self) {
        let mut m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
        m.peak = m.live;
    }

    /// The first error wgpu reported (validation, out of memory, device lost), as an error.
    pub fn check(&self) -> Result<()> {
        match self.error.lock().unwrap_or_else(|p| p.into_inner()).clone() {
            Some(e) => Err(GpuError::Device(e)),
            None => Ok(()),
        }
    }

    /// Blocks until the queue is idle.
    pub fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Device(e.to_string()))?;
        self.check()
    }

    /// Compiles `source`'s entry point `entry` with a layout of one uniform (binding 0) and
    /// the storage buffers `read_only` describes (bindings 1, 2, ...).
    pub(crate) fn pipeline(
        &self,
        label: &str,
        source: &str,
        entry: &str,
        read_only: &[bool],
    ) -> Result<(wgpu::ComputePipeline, wgpu::BindGroupLayout)> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
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
        let layout = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries: &entries,
            });
        let pl = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(label),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pipe = self
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
        &self,
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
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout,
            entries: &entries,
        })
    }

    /// Copies the first `size` bytes of `src` back to the host (blocking until done).
    pub fn read(&self, src: &wgpu::Buffer, size: u64) -> Result<Vec<u8>> {
        let padded = size.max(4).div_ceil(4) * 4;
        let staging = self.buffer(
            "readback",
            padded,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )?;
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, padded);
        self.queue.submit([enc.finish()]);
        self.map_read(&staging, size)
    }

    /// The first `size` bytes of a MAP_READ buffer whose copy was submitted (blocking until
    /// all submitted work is done).
    pub fn map_read(&self, staging: &wgpu::Buffer, size: u64) -> Result<Vec<u8>> {
        self.map_read_after(staging, size, None)
    }

    /// [`Self::map_read`], waiting only for submission `after` (and what precedes it), so work
    /// submitted later keeps the GPU busy meanwhile.
    pub fn map_read_after(
        &self,
        staging: &wgpu::Buffer,
        size: u64,
        after: Option<wgpu::SubmissionIndex>,
    ) -> Result<Vec<u8>> {
        let slice = staging.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: after,
                timeout: None,
            })
            .map_err(|e| GpuError::Device(e.to_string()))?;
        self.check()?;
        rx.recv()
            .map_err(|e| GpuError::Device(e.to_string()))?
            .map_err(|e| GpuError::Device(e.to_string()))?;
        let out = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Device(e.to_string()))?[..size as usize]
            .to_vec();
        staging.unmap();
        Ok(out)
    }
}

/// Workgroups `(x, y)` covering `groups` within `max` per dimension.
pub(crate) fn grid(groups: u32, max: u32) -> (u32, u32) {
    let x = groups.clamp(1, max.max(1));
    (x, groups.div_ceil(x).max(1))
}
