//! The INR's kernels on a [`neuvolex_gpu::GpuDevice`] (adapter choice, GPU-memory accounting
//! and error capture live there). One context serves any number of engines, one after another
//! or side by side, and its device can serve other GPU crates too ([`GpuContext::on`]).

use crate::error::{GpuError, Result};
pub use neuvolex_gpu::{
    adapters, adapters_named, hardware_adapter, is_software, AdapterKind, GpuDevice, MemoryReport,
    Tracked,
};
use std::sync::{Arc, Mutex};

/// The shared WGSL header (bindings and helpers) and the kernel modules.
pub const COMMON_WGSL: &str = include_str!("../../../shaders/inr_common.wgsl");
/// The layer arithmetic (GEMM tile, FiLM, loss) shared by the layered and fused kernels.
pub const LAYERS_WGSL: &str = include_str!("../../../shaders/inr_layers.wgsl");
/// The layered path's GEMM: one dispatch per dense layer, forward and backward.
pub const GEMM_WGSL: &str = include_str!("../../../shaders/inr_gemm.wgsl");
/// The fused path: a micro-batch's whole forward, loss and backward in one dispatch.
pub const FUSED_WGSL: &str = include_str!("../../../shaders/inr_fused.wgsl");
/// The fused kernel's entry point and GEMM tile on f32 units (f32 or f16-rounded inputs).
pub const FUSED_F32_WGSL: &str = include_str!("../../../shaders/inr_fused_f32.wgsl");
/// The fused kernel's entry point and GEMM tile on cooperative matrices (tensor cores).
pub const FUSED_TC_WGSL: &str = include_str!("../../../shaders/inr_fused_tc.wgsl");
/// Sample staging, the hash-grid gather and the fixed-point table-gradient scatter.
pub const GRID_WGSL: &str = include_str!("../../../shaders/inr_grid.wgsl");
/// FiLM, loss, reductions, Adam and the feature gather.
pub const OPS_WGSL: &str = include_str!("../../../shaders/inr_ops.wgsl");

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
    /// Per-voxel feature gather into packed f16 (inference engines).
    GatherF16,
    /// A list of layer operations run per block of samples in one dispatch.
    Fused,
}

const KERNELS: [(Kernel, usize, &str); 13] = [
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
    (Kernel::GatherF16, 2, "gather_f16"),
    (Kernel::Fused, 3, "fused"),
];

/// Samples per workgroup of the fused kernel that every context compiles (`FB` in
/// `shaders/inr_fused.wgsl`); [`FUSED_BLOCKS`] lists the others, compiled on first use.
pub const DEFAULT_FUSED_BLOCK: usize = 64;
/// The fused kernel's possible blocks of samples per workgroup: 64 (the default), 32 and 16.
/// A smaller block launches more, smaller workgroups for the same micro-batch (4x as many at
/// 16), each computing 64 x block GEMM tiles with fewer outputs per invocation.
pub const FUSED_BLOCKS: [usize; 3] = [64, 32, 16];

/// How the fused kernel's GEMM tiles compute.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TileArith {
    /// f32 inputs and sums on the f32 units (the reference).
    F32,
    /// Inputs rounded to f16 as they are staged, products and sums in f32 on the f32 units:
    /// the tensor cores' arithmetic (f16 products are exact in f32) where there are none.
    HalfRounded,
    /// 16 x 16 x 16 cooperative matrices of f16 inputs and f32 accumulators (tensor cores).
    TensorCores,
}

impl TileArith {
    /// `f32`, `f16-rounded` or `f16-tensor-cores`.
    pub fn name(self) -> &'static str {
        match self {
            TileArith::F32 => "f32",
            TileArith::HalfRounded => "f16-rounded",
            TileArith::TensorCores => "f16-tensor-cores",
        }
    }
}

/// The tensor-core module's uniformity directive. Cooperative-matrix operations must run in
/// control flow that is uniform across their subgroup; naga's analysis knows only workgroup
/// uniformity, so it rejects the tile's loop over its subgroup's sub-tiles (bounded by the
/// subgroup's id: the same in every invocation of a subgroup). The directive lowers that rule
/// off for this module only.
const TC_UNIFORMITY: &str = "diagnostic(off, derivative_uniformity);";

/// The fused module's WGSL for `block` samples per workgroup and tile arithmetic `arith`: the
/// layer arithmetic with its tile width `BN` set to `block` (the fused kernel's `FB` is `BN`),
/// the program runner, and the entry point with its tile. `None` if `block` is not one of
/// [`FUSED_BLOCKS`] (or the sources lost a line this rewrites).
///
/// ```
/// use neuvolex_features_gpu::{fused_source, TileArith};
/// let tc = fused_source(32, TileArith::TensorCores).unwrap();
/// assert!(tc.starts_with("enable f16;") && tc.contains("const BN: u32 = 32u;"));
/// assert!(fused_source(8, TileArith::F32).is_none());
/// ```
pub fn fused_source(block: usize, arith: TileArith) -> Option<String> {
    const LINE: &str = "const BN: u32 = 64u;";
    const HALF: &str = "const HALF_INPUTS: bool = false;";
    if !FUSED_BLOCKS.contains(&block)
        || LAYERS_WGSL.matches(LINE).count() != 1
        || LAYERS_WGSL.matches(HALF).count() != 1
    {
        return None;
    }
    let mut layers = LAYERS_WGSL.replace(LINE, &format!("const BN: u32 = {block}u;"));
    if arith == TileArith::HalfRounded {
        layers = layers.replace(HALF, "const HALF_INPUTS: bool = true;");
    }
    Some(match arith {
        TileArith::TensorCores => format!(
            "enable f16;\nenable wgpu_cooperative_matrix;\n{TC_UNIFORMITY}\n{COMMON_WGSL}\n{layers}\n{FUSED_WGSL}\n{FUSED_TC_WGSL}"
        ),
        _ => format!("{COMMON_WGSL}\n{layers}\n{FUSED_WGSL}\n{FUSED_F32_WGSL}"),
    })
}

/// Bytes of one dispatch's arguments (every kernel's uniform struct fits).
pub const ARGS_BYTES: u64 = 96;
/// Operations in one fused dispatch (`shaders/inr_fused.wgsl` `MAX_OPS`).
pub const FUSED_OPS: usize = 64;
/// Bytes of the uniform window bound per dispatch: the fused program (a 16-byte header and
/// [`FUSED_OPS`] records of [`ARGS_BYTES`]), which every other kernel's arguments fit in.
pub const WINDOW_BYTES: u64 = 16 + FUSED_OPS as u64 * ARGS_BYTES;

/// The INR's compiled kernels on a device that other engines of the process may share
/// ([`GpuContext::gpu`], [`GpuContext::on`]).
pub struct GpuContext {
    pub(crate) gpu: Arc<GpuDevice>,
    pub(crate) layout: wgpu::BindGroupLayout,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// Fused kernels other than the f32 one for [`DEFAULT_FUSED_BLOCK`], compiled on first use.
    fused_variants: Mutex<Vec<((usize, TileArith), wgpu::ComputePipeline)>>,
    pipeline_layout: wgpu::PipelineLayout,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.describe())
            .finish()
    }
}

/// Storage buffers per shader stage the INR kernels bind.
const STORAGE_BUFFERS: u32 = 8;

impl GpuContext {
    /// Opens the best adapter of `kind` (narrowed by `NEUVOLEX_GPU_ADAPTER` where set) and
    /// compiles the kernels.
    pub fn new(kind: AdapterKind) -> Result<Arc<Self>> {
        Self::on(GpuDevice::new(kind)?)
    }

    /// Opens the best adapter of `kind` whose name contains `name` (any where `None`).
    pub fn open(kind: AdapterKind, name: Option<&str>) -> Result<Arc<Self>> {
        Self::on(GpuDevice::open(kind, name)?)
    }

    /// Opens `adapter` and compiles the kernels.
    pub fn with_adapter(adapter: wgpu::Adapter) -> Result<Arc<Self>> {
        Self::on(GpuDevice::with_adapter(adapter)?)
    }

    /// Compiles the kernels on an open device, which other engines (GPU classification, say)
    /// may share: one card, one memory account.
    ///
    /// ```no_run
    /// use neuvolex_features_gpu::{AdapterKind, GpuContext, GpuDevice};
    /// let dev = GpuDevice::new(AdapterKind::Any)?;
    /// let ctx = GpuContext::on(dev.clone())?;
    /// assert!(std::sync::Arc::ptr_eq(ctx.gpu(), &dev));
    /// # Ok::<(), neuvolex_features_gpu::GpuError>(())
    /// ```
    pub fn on(gpu: Arc<GpuDevice>) -> Result<Arc<Self>> {
        gpu.require_storage_buffers(STORAGE_BUFFERS)?;
        let device = &gpu.device;
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
        ]
        .iter()
        .map(|(name, layers, src)| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(format!("{COMMON_WGSL}\n{layers}\n{src}").into()),
            })
        })
        .chain(std::iter::once(
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("inr_fused.wgsl"),
                source: wgpu::ShaderSource::Wgsl(
                    fused_source(DEFAULT_FUSED_BLOCK, TileArith::F32)
                        .unwrap_or_default()
                        .into(),
                ),
            }),
        ))
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
            return Err(
                neuvolex_gpu::GpuError::Device(format!("compiling the INR kernels: {e}")).into(),
            );
        }
        Ok(Arc::new(GpuContext {
            gpu,
            layout,
            pipelines,
            fused_variants: Mutex::default(),
            pipeline_layout: pl,
        }))
    }

    /// The device the kernels run on, to share with other engines.
    pub fn gpu(&self) -> &Arc<GpuDevice> {
        &self.gpu
    }

    /// The adapter's description.
    pub fn info(&self) -> &wgpu::AdapterInfo {
        self.gpu.info()
    }

    /// Whether the adapter is a software rasteriser.
    pub fn is_software(&self) -> bool {
        self.gpu.is_software()
    }

    /// "name (backend, type)".
    pub fn describe(&self) -> String {
        self.gpu.describe()
    }

    /// Whether the device has GPU timestamp queries (`wgpu::Features::TIMESTAMP_QUERY`), which
    /// [`crate::GpuInr::set_profile`] times kernels with.
    pub fn has_timestamps(&self) -> bool {
        self.gpu.has_timestamps()
    }

    /// The largest buffer one binding may hold.
    pub fn max_binding(&self) -> u64 {
        self.gpu.max_binding()
    }

    /// Workgroups one dispatch dimension may hold.
    pub(crate) fn max_groups(&self) -> u32 {
        self.gpu.max_groups()
    }

    pub(crate) fn pipeline(&self, k: Kernel) -> &wgpu::ComputePipeline {
        let i = KERNELS.iter().position(|&(kk, _, _)| kk == k).unwrap_or(0);
        &self.pipelines[i]
    }

    /// The context for the f16 paths: the kernels compiled on a second device on this
    /// context's adapter, opened for the tensor cores, where the adapter has them
    /// ([`GpuDevice::reopen_for_tensor_cores`]); else this context. The f32 paths stay on a
    /// device whose other shaders are compiled as before.
    pub fn for_tensor_cores(self: &Arc<Self>) -> Result<Arc<Self>> {
        let dev = self.gpu.reopen_for_tensor_cores()?;
        if Arc::ptr_eq(&dev, &self.gpu) {
            return Ok(self.clone());
        }
        Self::on(dev)
    }

    /// Whether the fused kernel's tiles can run on cooperative matrices here: the device was
    /// opened with wgpu's cooperative-matrix extension, f16 in shaders and subgroups, and the
    /// adapter reports 16 x 16 x 16 matrices of f16 inputs with f32 accumulators
    /// ([`GpuDevice::tensor_cores`]).
    pub fn has_tensor_cores(&self) -> bool {
        self.gpu.tensor_cores()
    }

    /// The tile arithmetic of a fused path here: [`TileArith::F32`] for f32 inputs; for f16
    /// inputs (`half`), [`TileArith::TensorCores`] where the device has them, else
    /// [`TileArith::HalfRounded`] (the same arithmetic on the f32 units).
    pub fn tile_arith_for(&self, half: bool) -> TileArith {
        match (half, self.has_tensor_cores()) {
            (false, _) => TileArith::F32,
            (true, true) => TileArith::TensorCores,
            (true, false) => TileArith::HalfRounded,
        }
    }

    /// The fused kernel for `block` samples per workgroup (one of [`FUSED_BLOCKS`]) with tile
    /// arithmetic `arith`: the context's own for f32 at [`DEFAULT_FUSED_BLOCK`], else
    /// compiled on first use and kept. [`TileArith::TensorCores`] needs
    /// [`GpuContext::has_tensor_cores`].
    pub fn fused_pipeline(&self, block: usize, arith: TileArith) -> Result<wgpu::ComputePipeline> {
        if block == DEFAULT_FUSED_BLOCK && arith == TileArith::F32 {
            return Ok(self.pipeline(Kernel::Fused).clone());
        }
        if arith == TileArith::TensorCores && !self.has_tensor_cores() {
            return Err(GpuError::Config(format!(
                "{} has no cooperative matrices of 16 x 16 f16 with f32 accumulators (or no \
                 f16 in shaders, or no subgroups): the tensor-core kernel cannot run there",
                self.describe()
            )));
        }
        let mut v = self
            .fused_variants
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some((_, p)) = v.iter().find(|(k, _)| *k == (block, arith)) {
            return Ok(p.clone());
        }
        let src = fused_source(block, arith).ok_or_else(|| {
            GpuError::Config(format!(
                "the fused kernel has blocks of {FUSED_BLOCKS:?} samples, not {block}"
            ))
        })?;
        let device = &self.gpu.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("inr_fused.wgsl"),
            source: wgpu::ShaderSource::Wgsl(src.into()),
        });
        let p = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("fused"),
            layout: Some(&self.pipeline_layout),
            module: &module,
            entry_point: Some("fused"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(neuvolex_gpu::GpuError::Device(format!(
                "compiling the fused kernel for blocks of {block} ({}): {e}",
                arith.name()
            ))
            .into());
        }
        v.push(((block, arith), p.clone()));
        Ok(p)
    }

    /// A zeroed buffer, counted in the device's memory accounting.
    pub(crate) fn buffer(
        &self,
        label: &str,
        size: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<Tracked> {
        Ok(self.gpu.buffer(label, size, usage)?)
    }

    /// Records the allocator's current reservation in the peak (where the backend reports it).
    pub fn sample_memory(&self) {
        self.gpu.sample_memory()
    }

    /// GPU memory use so far (of the whole device, other engines on it included).
    pub fn memory(&self) -> MemoryReport {
        self.gpu.memory()
    }

    /// Resets the peaks to the current use (so a run reports its own peak).
    pub fn reset_peak(&self) {
        self.gpu.reset_peak()
    }

    /// The first error wgpu reported since the device was opened (validation, out of memory,
    /// device lost), as an error.
    pub fn check(&self) -> Result<()> {
        Ok(self.gpu.check()?)
    }

    /// Blocks until the queue is idle.
    pub fn wait(&self) -> Result<()> {
        Ok(self.gpu.wait()?)
    }

    /// Copies `size` bytes at `offset` of `src` back to the host (blocking).
    pub(crate) fn read(&self, src: &wgpu::Buffer, offset: u64, size: u64) -> Result<Vec<u8>> {
        Ok(self.gpu.read_at(src, offset, size)?)
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
        Ok(self
            .gpu
            .map_with(staging, size, after, bytemuck::pod_collect_to_vec)?)
    }

    /// The first `values` f16 values of `staging` (written packed two to a word, as
    /// [`crate::FeatureFormat::F16`]), once submission `after` is done.
    pub(crate) fn map_read_f16(
        &self,
        staging: &wgpu::Buffer,
        values: usize,
        after: Option<wgpu::SubmissionIndex>,
    ) -> Result<Vec<half::f16>> {
        let bytes = crate::FeatureFormat::F16.bytes(values);
        Ok(self.gpu.map_with(staging, bytes, after, |b| {
            bytemuck::cast_slice::<u8, half::f16>(b)[..values].to_vec()
        })?)
    }

    /// [`GpuContext::map_read_f32`] for u64 values (timestamps).
    pub(crate) fn map_read_u64(
        &self,
        staging: &wgpu::Buffer,
        size: u64,
        after: Option<wgpu::SubmissionIndex>,
    ) -> Result<Vec<u64>> {
        Ok(self
            .gpu
            .map_with(staging, size, after, bytemuck::pod_collect_to_vec)?)
    }
}
