//! The device: adapter choice, limits, buffer accounting (live and peak bytes) and error
//! capture.

use crate::error::{GpuError, Result};
use std::sync::{Arc, Mutex};

/// The environment variable that narrows adapters by name (case-insensitive substring):
/// [`adapters`] and [`GpuDevice::new`] read it.
pub const ADAPTER_ENV: &str = "NEUVOLEX_GPU_ADAPTER";

/// Storage buffers per shader stage the device asks for where the adapter has them: the most
/// any NeuVolEx kernel binds (the INR's). An adapter with fewer still opens, with its own
/// number; callers check theirs with [`GpuDevice::require_storage_buffers`].
pub const STORAGE_BUFFERS: u32 = 8;

/// Which adapters qualify.
///
/// ```
/// use neuvolex_gpu::AdapterKind;
/// assert_ne!(AdapterKind::Any, AdapterKind::Hardware);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterKind {
    /// Any adapter, software ones (Mesa lavapipe, llvmpipe, SwiftShader) included.
    Any,
    /// Hardware GPUs only: an adapter whose type is `Cpu` counts as no GPU.
    Hardware,
}

#[derive(Debug, Default)]
struct Memory {
    live: u64,
    peak: u64,
    reserved_peak: u64,
}

impl Memory {
    fn add(&mut self, bytes: u64) {
        self.live += bytes;
        self.peak = self.peak.max(self.live);
    }

    fn sub(&mut self, bytes: u64) {
        self.live = self.live.saturating_sub(bytes);
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// GPU memory use: bytes of the tracked buffers (live and peak) and the peak of the
/// allocator's reserved blocks, where the backend reports it (Vulkan, D3D12).
///
/// ```
/// let r = neuvolex_gpu::MemoryReport::default();
/// assert_eq!((r.live_bytes, r.peak_bytes, r.reserved_peak_bytes), (0, 0, None));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MemoryReport {
    /// Bytes of buffers alive now.
    pub live_bytes: u64,
    /// Largest sum of live buffers seen.
    pub peak_bytes: u64,
    /// Largest allocator reservation seen (includes staging and allocator slack), if reported.
    pub reserved_peak_bytes: Option<u64>,
}

/// A buffer counted in its device's accounting while it lives ([`GpuDevice::buffer`]).
///
/// It dereferences to the [`wgpu::Buffer`].
#[derive(Debug)]
pub struct Tracked {
    /// The buffer.
    pub buf: wgpu::Buffer,
    mem: Arc<Mutex<Memory>>,
}

impl Drop for Tracked {
    fn drop(&mut self) {
        lock(&self.mem).sub(self.buf.size());
    }
}

impl std::ops::Deref for Tracked {
    type Target = wgpu::Buffer;
    fn deref(&self) -> &wgpu::Buffer {
        &self.buf
    }
}

/// A wgpu device and its queue, with buffer accounting and captured errors. Share it as an
/// `Arc<GpuDevice>` between the engines of one process.
pub struct GpuDevice {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    adapter: wgpu::Adapter,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    timestamps: bool,
    tensor_cores: bool,
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

/// The variable that opens every device for tensor-core kernels (`1`) or none (`0`); unset,
/// only [`GpuDevice::reopen_for_tensor_cores`] asks for them.
pub const TENSOR_CORES_ENV: &str = "NEUVOLEX_GPU_TENSOR_CORES";

/// The features tensor-core kernels need, where `adapter` has all of them and a 16 x 16 x 16
/// cooperative-matrix configuration of f16 inputs with f32 accumulators (else none), unless
/// `NEUVOLEX_GPU_TENSOR_CORES=0`.
fn tensor_core_features(adapter: &wgpu::Adapter) -> wgpu::Features {
    let need = wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX
        | wgpu::Features::SHADER_F16
        | wgpu::Features::SUBGROUP;
    let off = std::env::var(TENSOR_CORES_ENV).is_ok_and(|v| v.trim() == "0");
    if off || !adapter.features().contains(need) {
        return wgpu::Features::empty();
    }
    let f16_f32 = adapter.cooperative_matrix_properties().iter().any(|p| {
        (p.m_size, p.n_size, p.k_size) == (16, 16, 16)
            && p.ab_type == wgpu::CooperativeScalarType::F16
            && p.cr_type == wgpu::CooperativeScalarType::F32
    });
    if f16_f32 {
        need
    } else {
        wgpu::Features::empty()
    }
}

/// Whether an adapter is a software rasteriser rather than a GPU.
///
/// ```no_run
/// let soft = neuvolex_gpu::adapters().iter().filter(|a| neuvolex_gpu::is_software(&a.get_info())).count();
/// println!("{soft} software adapters");
/// ```
pub fn is_software(info: &wgpu::AdapterInfo) -> bool {
    info.device_type == wgpu::DeviceType::Cpu
}

/// Every adapter wgpu finds that can run compute shaders (Vulkan, Metal, D3D12), best first:
/// discrete, integrated, virtual, other, software. [`ADAPTER_ENV`] keeps only adapters whose
/// name contains it (case-insensitive).
///
/// ```no_run
/// for a in neuvolex_gpu::adapters() {
///     println!("{}", a.get_info().name);
/// }
/// ```
pub fn adapters() -> Vec<wgpu::Adapter> {
    adapters_named(std::env::var(ADAPTER_ENV).ok().as_deref())
}

/// [`adapters`] whose name contains `name` (case-insensitive), all where `None`.
///
/// ```no_run
/// let nvidia = neuvolex_gpu::adapters_named(Some("nvidia"));
/// println!("{} NVIDIA adapters", nvidia.len());
/// ```
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

/// The name of the best hardware GPU adapter, if there is one.
///
/// ```no_run
/// println!("{:?}", neuvolex_gpu::hardware_adapter());
/// ```
pub fn hardware_adapter() -> Option<String> {
    adapters()
        .into_iter()
        .map(|a| a.get_info())
        .find(|i| !is_software(i))
        .map(|i| i.name)
}

impl GpuDevice {
    /// Compiles `source`'s entry point `entry` with a layout of one uniform (binding 0) and
    /// the storage buffers `read_only` describes (bindings 1, 2, ...); a compile or validation
    /// error is a [`GpuError::Device`].
    pub fn compute_pipeline(
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
    pub fn bind(
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

    /// Opens the best adapter of `kind` (narrowed by [`ADAPTER_ENV`] where set).
    ///
    /// ```no_run
    /// use neuvolex_gpu::{AdapterKind, GpuDevice};
    /// let dev = GpuDevice::new(AdapterKind::Any)?;
    /// println!("{}", dev.describe());
    /// # Ok::<(), neuvolex_gpu::GpuError>(())
    /// ```
    pub fn new(kind: AdapterKind) -> Result<Arc<Self>> {
        Self::open(kind, std::env::var(ADAPTER_ENV).ok().as_deref())
    }

    /// Opens the best adapter of `kind` whose name contains `name` (any where `None`).
    ///
    /// ```no_run
    /// use neuvolex_gpu::{AdapterKind, GpuDevice};
    /// let dev = GpuDevice::open(AdapterKind::Hardware, Some("nvidia"))?;
    /// # Ok::<(), neuvolex_gpu::GpuError>(())
    /// ```
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
            .find(|a| kind == AdapterKind::Any || !is_software(&a.get_info()))
            .ok_or_else(|| {
                GpuError::NoAdapter(match name {
                    Some(want) if names.is_empty() => {
                        format!("none whose name contains '{want}'")
                    }
                    _ if names.is_empty() => "wgpu found none; install a Vulkan driver (for \
                                              example mesa-vulkan-drivers for the software \
                                              lavapipe, or the NVIDIA driver)"
                        .into(),
                    _ => format!("only software adapters were found ({})", names.join(", ")),
                })
            })?;
        Self::with_adapter(adapter)
    }

    /// Opens `adapter`, asking for its largest buffers, dispatches and workgroup memory, up to
    /// [`STORAGE_BUFFERS`] storage buffers per stage, and timestamp queries where it has them
    /// (and tensor cores with `NEUVOLEX_GPU_TENSOR_CORES=1`, see
    /// [`GpuDevice::with_adapter_for`]).
    ///
    /// ```no_run
    /// let a = neuvolex_gpu::adapters().into_iter().next().expect("an adapter");
    /// let dev = neuvolex_gpu::GpuDevice::with_adapter(a)?;
    /// # Ok::<(), neuvolex_gpu::GpuError>(())
    /// ```
    pub fn with_adapter(adapter: wgpu::Adapter) -> Result<Arc<Self>> {
        let want = std::env::var(TENSOR_CORES_ENV).is_ok_and(|v| v.trim() == "1");
        Self::with_adapter_for(adapter, want)
    }

    /// A device for tensor-core kernels: a second one on this one's adapter, opened for them,
    /// where the adapter has what they need (its buffers and errors are its own); this one
    /// where it already has them, or where the adapter lacks them or
    /// `NEUVOLEX_GPU_TENSOR_CORES=0` (a second device would bring nothing).
    /// [`GpuDevice::tensor_cores`] says which.
    pub fn reopen_for_tensor_cores(self: &Arc<Self>) -> Result<Arc<Self>> {
        if self.tensor_cores || tensor_core_features(&self.adapter).is_empty() {
            return Ok(self.clone());
        }
        Self::with_adapter_for(self.adapter.clone(), true)
    }

    /// [`GpuDevice::with_adapter`], and, with `tensor_cores`, wgpu's experimental
    /// cooperative-matrix extension, f16 in shaders and subgroups where the adapter has them
    /// with a 16 x 16 x 16 f16 / f32 configuration. Asked for only by the kernels that use it:
    /// with the extension on, wgpu compiles every shader of the device under the Vulkan memory
    /// model, so the other kernels run on a device opened without it.
    pub fn with_adapter_for(adapter: wgpu::Adapter, tensor_cores: bool) -> Result<Arc<Self>> {
        let info = adapter.get_info();
        let have = adapter.limits();
        let required = wgpu::Limits {
            max_storage_buffers_per_shader_stage: have
                .max_storage_buffers_per_shader_stage
                .min(STORAGE_BUFFERS),
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_compute_workgroups_per_dimension: have.max_compute_workgroups_per_dimension,
            max_compute_workgroup_storage_size: have.max_compute_workgroup_storage_size,
            ..wgpu::Limits::downlevel_defaults()
        };
        let tensor = if tensor_cores {
            tensor_core_features(&adapter)
        } else {
            wgpu::Features::empty()
        };
        let features = (adapter.features() & wgpu::Features::TIMESTAMP_QUERY) | tensor;
        // SAFETY: the one experimental feature requested is the cooperative-matrix extension,
        // and only where the adapter reports the configuration its one kernel uses
        // (`tensor_core_features`); its shader compiles under wgpu's validation like any other.
        let experimental = if tensor.is_empty() {
            wgpu::ExperimentalFeatures::disabled()
        } else {
            unsafe { wgpu::ExperimentalFeatures::enabled() }
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("neuvolex"),
            required_features: features,
            required_limits: required.clone(),
            experimental_features: experimental,
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", info.name)))?;
        let error: Arc<Mutex<Option<String>>> = Arc::default();
        let slot = error.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            lock(&slot).get_or_insert_with(|| e.to_string());
        }));
        let slot = error.clone();
        device.set_device_lost_callback(move |reason, msg| {
            lock(&slot).get_or_insert_with(|| format!("device lost ({reason:?}): {msg}"));
        });
        Ok(Arc::new(GpuDevice {
            device,
            queue,
            adapter,
            info,
            limits: required,
            timestamps: features.contains(wgpu::Features::TIMESTAMP_QUERY),
            tensor_cores: !tensor.is_empty(),
            mem: Arc::default(),
            error,
        }))
    }

    /// The adapter's description.
    pub fn info(&self) -> &wgpu::AdapterInfo {
        &self.info
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
        is_software(&self.info)
    }

    /// The limits the device was opened with.
    pub fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }

    /// Whether the device has GPU timestamp queries (`wgpu::Features::TIMESTAMP_QUERY`).
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// Whether the device was opened for cooperative-matrix kernels (tensor cores): wgpu's
    /// experimental cooperative-matrix extension with 16 x 16 x 16 matrices of f16 inputs and
    /// f32 accumulators at subgroup scope, f16 in shaders, and subgroups
    /// ([`GpuDevice::reopen_for_tensor_cores`], or every device with
    /// `NEUVOLEX_GPU_TENSOR_CORES=1`). Never on lavapipe, which has no
    /// `VK_KHR_cooperative_matrix`; `NEUVOLEX_GPU_TENSOR_CORES=0` turns it off.
    pub fn tensor_cores(&self) -> bool {
        self.tensor_cores
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

    /// An [`GpuError::Unsupported`] error unless kernels may bind `n` storage buffers per
    /// shader stage on this device.
    pub fn require_storage_buffers(&self, n: u32) -> Result<()> {
        let has = self.limits.max_storage_buffers_per_shader_stage;
        if has < n {
            return Err(GpuError::Unsupported {
                adapter: self.info.name.clone(),
                detail: format!("needs {n} storage buffers per shader stage, has {has}"),
            });
        }
        Ok(())
    }

    /// A zeroed buffer of at least `size` bytes (a multiple of 4), counted while it lives.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> Result<Tracked> {
        let size = size.max(4).div_ceil(4) * 4;
        if usage.contains(wgpu::BufferUsages::STORAGE) && size > self.max_binding() {
            return Err(GpuError::TooLarge {
                label: label.into(),
                bytes: size,
                limit: self.max_binding(),
            });
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
        lock(&self.mem).add(size);
        Ok(Tracked {
            buf,
            mem: self.mem.clone(),
        })
    }

    /// A buffer holding `data` (at least 4 bytes, zero-padded), counted while it lives.
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

    /// Bytes of the tracked buffers alive now.
    pub fn live_bytes(&self) -> u64 {
        lock(&self.mem).live
    }

    /// The largest sum of live buffers seen since the last [`Self::reset_peak`].
    pub fn peak_bytes(&self) -> u64 {
        lock(&self.mem).peak
    }

    /// Records the allocator's current reservation in the peak (where the backend reports it).
    pub fn sample_memory(&self) {
        if let Some(r) = self.device.generate_allocator_report() {
            let mut m = lock(&self.mem);
            m.reserved_peak = m.reserved_peak.max(r.total_reserved_bytes);
        }
    }

    /// GPU memory use so far.
    pub fn memory(&self) -> MemoryReport {
        self.sample_memory();
        let m = lock(&self.mem);
        MemoryReport {
            live_bytes: m.live,
            peak_bytes: m.peak,
            reserved_peak_bytes: (m.reserved_peak > 0).then_some(m.reserved_peak),
        }
    }

    /// Resets the peaks to the current use (so a run reports its own peak).
    pub fn reset_peak(&self) {
        let mut m = lock(&self.mem);
        m.peak = m.live;
        m.reserved_peak = 0;
    }

    /// The first error wgpu reported since the device was opened (validation, out of memory,
    /// device lost), as an error.
    pub fn check(&self) -> Result<()> {
        match lock(&self.error).clone() {
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

    /// Copies the first `size` bytes of `src` back to the host (blocking until done).
    pub fn read(&self, src: &wgpu::Buffer, size: u64) -> Result<Vec<u8>> {
        self.read_at(src, 0, size)
    }

    /// Copies `size` bytes at `offset` (a multiple of 4) of `src` back to the host (blocking).
    pub fn read_at(&self, src: &wgpu::Buffer, offset: u64, size: u64) -> Result<Vec<u8>> {
        let padded = size.max(4).div_ceil(4) * 4;
        let staging = self.buffer(
            "readback",
            padded,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )?;
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, offset, &staging, 0, padded);
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
        self.map_with(staging, size, after, |b| b.to_vec())
    }

    /// Maps `staging` (a MAP_READ buffer whose copy was submitted) once submission `after` is
    /// done (all work where `None`), applies `read` to its first `size` bytes and unmaps it.
    pub fn map_with<T>(
        &self,
        staging: &wgpu::Buffer,
        size: u64,
        after: Option<wgpu::SubmissionIndex>,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T> {
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
        let out = read(
            &slice
                .get_mapped_range()
                .map_err(|e| GpuError::Device(e.to_string()))?[..size as usize],
        );
        staging.unmap();
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unknown_adapter_name_is_named_in_the_error() {
        let e = GpuDevice::open(AdapterKind::Any, Some("no-such-adapter-4711")).unwrap_err();
        assert!(matches!(e, GpuError::NoAdapter(_)), "{e}");
        assert!(e.to_string().contains("no-such-adapter-4711"), "{e}");
    }

    #[test]
    fn accounting_follows_live_buffers() {
        let mut m = Memory::default();
        m.add(100);
        m.add(50);
        m.sub(100);
        assert_eq!((m.live, m.peak), (50, 150));
        m.sub(80);
        assert_eq!((m.live, m.peak), (0, 150));
    }

    #[test]
    fn tracked_buffers_count_while_they_live() {
        let dev = match GpuDevice::new(AdapterKind::Any) {
            Ok(d) => d,
            Err(e) => {
                eprintln!("SKIP: no wgpu adapter: {e}");
                return;
            }
        };
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let a = dev.buffer("a", 1000, usage).unwrap();
        let b = dev.upload("b", &[1, 2, 3, 4, 5], usage).unwrap();
        assert_eq!(dev.live_bytes(), 1000 + 8);
        drop(a);
        assert_eq!((dev.live_bytes(), dev.peak_bytes()), (8, 1008));
        // The read's staging buffer (8 bytes) lives only during the read.
        assert_eq!(dev.read(&b, 5).unwrap(), vec![1, 2, 3, 4, 5]);
        assert_eq!((dev.live_bytes(), dev.peak_bytes()), (8, 1008));
        dev.reset_peak();
        assert_eq!(dev.memory().peak_bytes, 8);
        drop(b);
        assert_eq!(dev.live_bytes(), 0);
        let e = dev
            .buffer("huge", dev.max_binding() + 4, wgpu::BufferUsages::STORAGE)
            .unwrap_err();
        assert!(e.to_string().contains("'huge'"), "{e}");
        assert!(dev.require_storage_buffers(u32::MAX).is_err());
        dev.check().unwrap();
    }
}
