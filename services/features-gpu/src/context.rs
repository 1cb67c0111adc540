//! The device: adapter choice (hardware or any), the compiled kernels, GPU-memory accounting and
//! error capture. One context serves any number of engines, one after another or side by side.

use crate::error::{GpuError, Result};
use std::sync::{Arc, Mutex};

/// The shared WGSL header (bindings and helpers) and the kernel modules.
pub const COMMON_WGSL: &str = include_str!("../../../shaders/inr_common.wgsl");
/// The layer arithmetic (GEMM tile, FiLM, loss) shared by the layered and fused kernels.
pub const LAYERS_WGSL: &str = include_str!("../../../shaders/inr_layers.wgsl");
/// The layered path's GEMM: one dispatch per dense layer, forward and backward.
pub const GEMM_WGSL: &str = include_str!("../../../shaders/inr_gemm.wgsl");
/// The fused path: a micro-batch's whole forward, loss and backward in one dispatch.
pub const FUSED_WGSL: &str = include_str!("../../../shaders/inr_fused.wgsl");
/// Sample staging, the hash-grid gather and the fixed-point table-gradient scatter.
pub const GRID_WGSL: &str = include_str!("../../../shaders/inr_grid.wgsl");
/// FiLM, loss, reductions, Adam and the feature gather.
pub const OPS_WGSL: &str = include_str!("../../../shaders/inr_ops.wgsl");

/// Which adapters qualify.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterKind {
    /// Any adapter, software ones (Mesa lavapipe, llvmpipe, SwiftShader) included.
    Any,
    /// Hardware GPUs only: an adapter whose type is `Cpu` counts as no GPU.
    Hardware,
}

/// A kernel (one compute entry point).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kernel {
    /// Tiled GEMM.
    Gemm,
    /// Sample staging from the tile ring.
    Stage,
    /// Hash-grid gather.
    Encode,
    /// Table-gradient scatter.
    Scatter,
    /// FiLM forward.
    FilmFwd,
    /// FiLM backward.
    FilmBwd,
    /// Largest |x| of a matrix.
    AbsMax,
    /// Loss and output gradient.
    Loss,
    /// Ordered dense-gradient reduction with Adam.
    ReduceAdam,
    /// Adam on the hash table.
    AdamTable,
    /// Per-voxel feature gather.
    Gather,
    /// A list of layer operations run per block of samples in one dispatch.
    Fused,
}

const KERNELS: [(Kernel, usize, &str); 12] = [
    (Kernel::Gemm, 0, "gemm"),
    (Kernel::Stage, 1, "stage"),
    (Kernel::Encode, 1, "encode"),
    (Kernel::Scatter, 1, "scatter"),
    (Kernel::FilmFwd, 2, "film_fwd"),
    (Kernel::FilmBwd, 2, "film_bwd"),
    (Kernel::AbsMax, 2, "absmax"),
    (Kernel::Loss, 2, "loss"),
    (Kernel::ReduceAdam, 2, "reduce_adam"),
    (Kernel::AdamTable, 2, "adam_table"),
    (Kernel::Gather, 2, "gather"),
    (Kernel::Fused, 3, "fused"),
];

/// Samples per workgroup of the fused kernel that every context compiles (`FB` in
/// `shaders/inr_fused.wgsl`); [`FUSED_BLOCKS`] lists the others, compiled on first use.
pub const DEFAULT_FUSED_BLOCK: usize = 64;
/// The fused kernel's possible blocks of samples per workgroup: 64 (the default), 32 and 16.
/// A smaller block launches more, smaller workgroups for the same micro-batch (4x as many at
/// 16), each computing 64 x block GEMM tiles with fewer outputs per invocation.
pub const FUSED_BLOCKS: [usize; 3] = [64, 32, 16];

/// The fused module's WGSL for `block` samples per workgroup: the layer arithmetic with its
/// tile width `BN` set to `block` (the fused kernel's `FB` is `BN`). `None` if `block` is not
/// one of [`FUSED_BLOCKS`] (or the sources lost the line this rewrites).
pub fn fused_source(block: usize) -> Option<String> {
    const LINE: &str = "const BN: u32 = 64u;";
    if !FUSED_BLOCKS.contains(&block) || LAYERS_WGSL.matches(LINE).count() != 1 {
        return None;
    }
    let layers = LAYERS_WGSL.replace(LINE, &format!("const BN: u32 = {block}u;"));
    Some(format!("{COMMON_WGSL}\n{layers}\n{FUSED_WGSL}"))
}

/// Bytes of one dispatch's arguments (every kernel's uniform struct fits).
pub const ARGS_BYTES: u64 = 96;
/// Operations in one fused dispatch (`shaders/inr_fused.wgsl` `MAX_OPS`).
pub const FUSED_OPS: usize = 64;
/// Bytes of the uniform window bound per dispatch: the fused program (a 16-byte header and
/// [`FUSED_OPS`] records of [`ARGS_BYTES`]), which every other kernel's arguments fit in.
pub const WINDOW_BYTES: u64 = 16 + FUSED_OPS as u64 * ARGS_BYTES;

#[derive(Debug, Default)]
struct Memory {
    live: u64,
    peak: u64,
    reserved_peak: u64,
}

/// GPU memory use: bytes of the engine's buffers (live and peak) and the peak of the
/// allocator's reserved blocks, where the backend reports it (Vulkan, D3D12).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MemoryReport {
    /// Bytes of buffers alive now.
    pub live_bytes: u64,
    /// Largest sum of live buffers seen.
    pub peak_bytes: u64,
    /// Largest allocator reservation seen (includes staging and allocator slack), if reported.
    pub reserved_peak_bytes: Option<u64>,
}

/// A buffer counted in the context's memory accounting.
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

/// The device, its queue, the compiled kernels and the memory accounting.
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    pub(crate) limits: wgpu::Limits,
    pub(crate) layout: wgpu::BindGroupLayout,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// Fused kernels for blocks other than [`DEFAULT_FUSED_BLOCK`], compiled on first use.
    fused_variants: Mutex<Vec<(usize, wgpu::ComputePipeline)>>,
    pipeline_layout: wgpu::PipelineLayout,
    timestamps: bool,
    mem: Arc<Mutex<Memory>>,
    error: Arc<Mutex<Option<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.describe())
            .finish()
    }
}

fn instance() -> wgpu::Instance {
    wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env())
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

/// Whether an adapter is a software rasteriser rather than a GPU.
pub fn is_software(info: &wgpu::AdapterInfo) -> bool {
    info.device_type == wgpu::DeviceType::Cpu
}

/// Every adapter wgpu finds that can run compute shaders (Vulkan, Metal, D3D12), best first:
/// discrete, integrated, virtual, other, software. `NEUVOLEX_GPU_ADAPTER` keeps only adapters
/// whose name contains it (case-insensitive).
pub fn adapters() -> Vec<wgpu::Adapter> {
    adapters_named(std::env::var("NEUVOLEX_GPU_ADAPTER").ok().as_deref())
}

/// [`adapters`] whose name contains `name` (case-insensitive), all where `None`.
pub fn adapters_named(name: Option<&str>) -> Vec<wgpu::Adapter> {
    let inst = instance();
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

/// The name of the best hardware GPU adapter, if there is one (what `--backend auto` uses).
pub fn hardware_adapter() -> Option<String> {
    adapters()
        .into_iter()
        .map(|a| a.get_info())
        .find(|i| !is_software(i))
        .map(|i| i.name)
}

impl GpuContext {
    /// Opens the best adapter of `kind` and compiles the kernels.
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
            .find(|a| kind == AdapterKind::Any || !is_software(&a.get_info()))
            .ok_or_else(|| {
                GpuError::NoAdapter(if names.is_empty() && name.is_some() {
                    format!("none whose name contains '{}'", name.unwrap_or_default())
                } else if names.is_empty() {
                    "wgpu found none; install a Vulkan driver (for example mesa-vulkan-drivers for \
                     the software lavapipe, or the NVIDIA driver)"
                        .into()
                } else {
                    format!("only software adapters were found ({})", names.join(", "))
                })
            })?;
        Self::with_adapter(adapter)
    }

    /// Opens `adapter` and compiles the kernels.
    pub fn with_adapter(adapter: wgpu::Adapter) -> Result<Arc<Self>> {
        let info = adapter.get_info();
        let have = adapter.limits();
        let unsupported = |detail: String| GpuError::Unsupported {
            adapter: info.name.clone(),
            detail,
        };
        if have.max_storage_buffers_per_shader_stage < 8 {
            return Err(unsupported(format!(
                "needs 8 storage buffers per shader stage, has {}",
                have.max_storage_buffers_per_shader_stage
            )));
        }
        let required = wgpu::Limits {
            max_storage_buffers_per_shader_stage: 8,
            max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
            max_buffer_size: have.max_buffer_size,
            max_compute_workgroups_per_dimension: have.max_compute_workgroups_per_dimension,
            ..wgpu::Limits::downlevel_defaults()
        };
        // Timestamp queries where the adapter has them: GpuInr's profile times kernels on the
        // GPU with them.
        let features = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("neuvolex-features-gpu"),
            required_features: features,
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
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: true,
                min_binding_size: wgpu::BufferSize::new(WINDOW_BYTES),
            },
            count: None,
        }];
        entries.extend((1..=6).map(|b| storage(b, false)));
        entries.extend((7..=8).map(|b| storage(b, true)));
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("inr"),
            entries: &entries,
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("inr"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let modules: Vec<wgpu::ShaderModule> = [
            ("inr_gemm.wgsl", LAYERS_WGSL, GEMM_WGSL),
            ("inr_grid.wgsl", "", GRID_WGSL),
            ("inr_ops.wgsl", LAYERS_WGSL, OPS_WGSL),
            ("inr_fused.wgsl", LAYERS_WGSL, FUSED_WGSL),
        ]
        .iter()
        .map(|(name, layers, src)| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(format!("{COMMON_WGSL}\n{layers}\n{src}").into()),
            })
        })
        .collect();
        let pipelines = KERNELS
            .iter()
            .map(|&(_, m, entry)| {
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(entry),
                    layout: Some(&pl),
                    module: &modules[m],
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: None,
                })
            })
            .collect();
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!("compiling the INR kernels: {e}")));
        }
        Ok(Arc::new(GpuContext {
            device,
            queue,
            info,
            limits: required,
            layout,
            pipelines,
            fused_variants: Mutex::default(),
            pipeline_layout: pl,
            timestamps: features.contains(wgpu::Features::TIMESTAMP_QUERY),
            mem: Arc::default(),
            error,
        }))
    }

    /// The adapter's description.
    pub fn info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Whether the adapter is a software rasteriser.
    pub fn is_software(&self) -> bool {
        is_software(&self.info)
    }

    /// "name (backend, type)".
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }

    /// Whether the device has GPU timestamp queries (`wgpu::Features::TIMESTAMP_QUERY`), which
    /// [`crate::GpuInr::set_profile`] times kernels with.
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// The largest buffer one binding may hold.
    pub fn max_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    pub(crate) fn pipeline(&self, k: Kernel) -> &wgpu::ComputePipeline {
        let i = KERNELS.iter().position(|&(kk, _, _)| kk == k).unwrap_or(0);
        &self.pipelines[i]
    }

    /// The fused kernel for `block` samples per workgroup (one of [`FUSED_BLOCKS`]): the
    /// context's own for [`DEFAULT_FUSED_BLOCK`], else compiled on first use and kept.
    pub fn fused_pipeline(&self, block: usize) -> Result<wgpu::ComputePipeline> {
        if block == DEFAULT_FUSED_BLOCK {
            return Ok(self.pipeline(Kernel::Fused).clone());
        }
        let mut v = self
            .fused_variants
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some((_, p)) = v.iter().find(|(b, _)| *b == block) {
            return Ok(p.clone());
        }
        let src = fused_source(block).ok_or_else(|| {
            GpuError::Config(format!(
                "the fused kernel has blocks of {FUSED_BLOCKS:?} samples, not {block}"
            ))
        })?;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("inr_fused.wgsl"),
                source: wgpu::ShaderSource::Wgsl(src.into()),
            });
        let p = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("fused"),
                layout: Some(&self.pipeline_layout),
                module: &module,
                entry_point: Some("fused"),
                compilation_options: Default::default(),
                cache: None,
            });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!(
                "compiling the fused kernel for blocks of {block}: {e}"
            )));
        }
        v.push((block, p.clone()));
        Ok(p)
    }

    /// A zeroed buffer, counted in the memory accounting.
    pub(crate) fn buffer(
        &self,
        label: &str,
        size: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<Tracked> {
        let size = size.max(4).div_ceil(4) * 4;
        if usage.contains(wgpu::BufferUsages::STORAGE) && size > self.max_binding() {
            return Err(GpuError::Config(format!(
                "buffer '{label}' needs {} MiB, more than the adapter's storage binding limit of {} MiB",
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

    /// Records the allocator's current reservation in the peak (where the backend reports it).
    pub fn sample_memory(&self) {
        if let Some(r) = self.device.generate_allocator_report() {
            let mut m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
            m.reserved_peak = m.reserved_peak.max(r.total_reserved_bytes);
        }
    }

    /// GPU memory use so far.
    pub fn memory(&self) -> MemoryReport {
        self.sample_memory();
        let m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
        MemoryReport {
            live_bytes: m.live,
            peak_bytes: m.peak,
            reserved_peak_bytes: (m.reserved_peak > 0).then_some(m.reserved_peak),
        }
    }

    /// Resets the peaks to the current use (so a run reports its own peak).
    pub fn reset_peak(&self) {
        let mut m = self.mem.lock().unwrap_or_else(|p| p.into_inner());
        m.peak = m.live;
        m.reserved_peak = 0;
    }

    /// The first error wgpu reported since the context was made (validation, out of memory,
    /// device lost), as an error.
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

    /// Copies `size` bytes at `offset` of `src` back to the host (blocking).
    pub(crate) fn read(&self, src: &wgpu::Buffer, offset: u64, size: u64) -> Result<Vec<u8>> {
        let staging = self.buffer(
            "readback",
            size,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )?;
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, offset, &staging, 0, size.div_ceil(4) * 4);
        self.queue.submit([enc.finish()]);
        self.map_with(&staging, size, None, |b| b.to_vec())
    }

    /// The first `size` bytes (a multiple of 4) of a MAP_READ buffer whose copy was submitted,
    /// as f32, copied once out of the mapping; waits only for submission `after` (else for all
    /// work).
    pub(crate) fn map_read_f32(
        &self,
        staging: &wgpu::Buffer,
        size: u64,
        after: Option<wgpu::SubmissionIndex>,
    ) -> Result<Vec<f32>> {
        self.map_with(staging, size, after, bytemuck::pod_collect_to_vec)
    }

    /// [`GpuContext::map_read_f32`] for u64 values (timestamps).
    pub(crate) fn map_read_u64(
        &self,
        staging: &wgpu::Buffer,
        size: u64,
        after: Option<wgpu::SubmissionIndex>,
    ) -> Result<Vec<u64>> {
        self.map_with(staging, size, after, bytemuck::pod_collect_to_vec)
    }

    /// Maps `staging` once `after` is done and applies `read` to its first `size` bytes.
    fn map_with<T>(
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
