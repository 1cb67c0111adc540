//! The GPU engine: the model's parameters, optimiser state and activations in GPU buffers,
//! and the kernel sequence of a training step, a forward pass and feature extraction.
//!
//! A step is recorded as a list of dispatches whose arguments go into one uniform buffer,
//! bound at a dynamic offset per dispatch, and submitted without waiting: the host runs ahead
//! of the GPU and reads the step's loss back later (see `train`).

use crate::context::{GpuContext, Kernel, TileArith, Tracked, ARGS_BYTES, FUSED_OPS, WINDOW_BYTES};
use crate::error::{GpuError, Result};
use crate::plan::{Mat, Plan, FUSED_BLOCK, STATS_RING, WG};
use neuvolex_features::adam::Adam;
use neuvolex_features::hashgrid::HashGrid;
use neuvolex_features::model::{DenseLayout, FeatureKind, InrModel, LayerSpec, TARGETS};
use neuvolex_features::tile::Tile;
use neuvolex_features::{InrConfig, TableAdam};
use std::sync::Arc;

const F_BIAS: u32 = 1;
const F_RELU: u32 = 2;
const F_ACC: u32 = 4;
const F_MASK: u32 = 8;
const F_A_KCONTIG: u32 = 16;
const F_B_NCONTIG: u32 = 32;
const TILE: u32 = 64;
/// Words of a ring slot's header.
const HEADER: usize = 16;

/// The per-output loss weights of the heads: intensity 1, each gradient component
/// `lambda_grad / 3`, local mean and std `lambda_stat` (the CPU engine's loss).
pub fn loss_weights(cfg: &InrConfig, outputs: usize) -> Vec<f32> {
    let mut w = vec![1.0f32; outputs];
    for (k, v) in w.iter_mut().enumerate().skip(1) {
        *v = match k {
            1..=3 => cfg.lambda_grad / 3.0,
            4 | 5 => cfg.lambda_stat,
            _ => 1.0,
        };
    }
    w
}

/// How the dense layers of a micro-batch are launched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MlpPath {
    /// One dispatch per layer operation over the whole micro-batch (about 35 for the paper's
    /// model), each a tiled GEMM or an element-wise kernel: the reference path.
    Layered,
    /// The forward pass, the loss and the backward pass in one dispatch: each workgroup runs
    /// every operation on its own block of 64 samples, with a barrier between operations
    /// (tiny-cuda-nn's fully fused MLP). The same arithmetic per operation; the weight
    /// gradients and losses are summed over blocks of 64 instead of 256.
    #[default]
    Fused,
    /// The fused path with blocks of 32 samples per workgroup: twice the workgroups of
    /// [`MlpPath::Fused`] for the same micro-batch (512 at 16 384 samples), each computing
    /// 64 x 32 GEMM tiles, 2 x 4 outputs per invocation. The same outputs per operation; the
    /// weight gradients and losses are summed over blocks of 32.
    Fused32,
    /// The fused path with blocks of 16 samples: four times the workgroups of
    /// [`MlpPath::Fused`] (1024 at 16 384 samples), 64 x 16 tiles, 1 x 4 outputs per
    /// invocation; partials over blocks of 16.
    Fused16,
    /// [`MlpPath::Fused`] with the GEMMs' inputs in f16 and their sums in f32: on tensor
    /// cores where the device has cooperative matrices ([`GpuContext::has_tensor_cores`]),
    /// else rounded to f16 on the f32 units (the same arithmetic). The loss is scaled so that
    /// the backward pass's gradients stay in f16's normal range ([`GpuInr::loss_scale_exp`]).
    FusedF16,
    /// [`MlpPath::Fused32`] with f16 inputs ([`MlpPath::FusedF16`]).
    Fused32F16,
    /// [`MlpPath::Fused16`] with f16 inputs ([`MlpPath::FusedF16`]).
    Fused16F16,
}

impl MlpPath {
    /// Every f32 path: the layered reference, then the fused path with blocks of 64 (the
    /// default), 32 and 16.
    pub const ALL: [MlpPath; 4] = [
        MlpPath::Layered,
        MlpPath::Fused,
        MlpPath::Fused32,
        MlpPath::Fused16,
    ];

    /// The fused paths with f16 GEMM inputs, blocks of 64, 32 and 16.
    pub const HALF: [MlpPath; 3] = [MlpPath::FusedF16, MlpPath::Fused32F16, MlpPath::Fused16F16];

    /// `layered`, `fused` (blocks of 64), `fused32`, `fused16`, or one of those fused names
    /// with `-f16`.
    pub fn name(self) -> &'static str {
        match self {
            MlpPath::Layered => "layered",
            MlpPath::Fused => "fused",
            MlpPath::Fused32 => "fused32",
            MlpPath::Fused16 => "fused16",
            MlpPath::FusedF16 => "fused-f16",
            MlpPath::Fused32F16 => "fused32-f16",
            MlpPath::Fused16F16 => "fused16-f16",
        }
    }

    /// The path called `name` (see [`MlpPath::name`]).
    ///
    /// ```
    /// use neuvolex_features_gpu::MlpPath;
    /// assert_eq!(MlpPath::from_name("fused32").unwrap(), MlpPath::Fused32);
    /// assert_eq!(MlpPath::from_name("fused-f16").unwrap(), MlpPath::FusedF16);
    /// assert!(MlpPath::from_name("fused8").is_err());
    /// ```
    pub fn from_name(name: &str) -> Result<MlpPath> {
        MlpPath::ALL
            .into_iter()
            .chain(MlpPath::HALF)
            .find(|p| p.name() == name)
            .ok_or_else(|| {
                GpuError::Config(format!(
                    "unknown MLP path '{name}' (one of {}, {})",
                    MlpPath::ALL.map(|p| p.name()).join(", "),
                    MlpPath::HALF.map(|p| p.name()).join(", ")
                ))
            })
    }

    /// Samples per workgroup of a fused path (64, 32, 16); `None` for the layered path.
    pub fn block(self) -> Option<usize> {
        match self {
            MlpPath::Layered => None,
            MlpPath::Fused | MlpPath::FusedF16 => Some(FUSED_BLOCK),
            MlpPath::Fused32 | MlpPath::Fused32F16 => Some(32),
            MlpPath::Fused16 | MlpPath::Fused16F16 => Some(16),
        }
    }

    /// Whether the GEMMs take f16 inputs (one of [`MlpPath::HALF`]).
    pub fn half(self) -> bool {
        MlpPath::HALF.contains(&self)
    }
}

/// How an engine is sized.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineOptions {
    /// Samples per optimiser step (training) or per pass (inference).
    pub batch: usize,
    /// Samples per micro-batch (activations are held for this many); `None` = as many as fit.
    pub micro_batch: Option<usize>,
    /// With the backward pass and optimiser state.
    pub train: bool,
    /// Tile slots resident in the ring.
    pub slots: usize,
    /// Largest brick edge of the store.
    pub brick: usize,
    /// Sample pairs per half of the order buffer (a tile group's voxels).
    pub order_pairs: usize,
    /// How the dense layers are launched.
    pub mlp: MlpPath,
}

impl EngineOptions {
    /// Inference on bricks of edge `brick`: two ring slots, passes of up to 32768 voxels.
    pub fn inference(brick: usize) -> Self {
        EngineOptions {
            batch: 32768,
            micro_batch: None,
            train: false,
            slots: 2,
            brick,
            order_pairs: 0,
            mlp: MlpPath::default(),
        }
    }
}

/// How extracted features are written: f32, or f16 as the store keeps them (half the bytes
/// to copy back and to map, and no conversion on the host). f16 needs an inference engine
/// (its features are packed where a training engine keeps the table gradient).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FeatureFormat {
    /// 4 bytes a value.
    F32,
    /// IEEE binary16, two values to a 32-bit word, voxel-major (the store's encoding).
    F16,
}

impl FeatureFormat {
    /// Bytes of `values` values (f16: whole 4-byte words, a last odd value padded).
    pub fn bytes(self, values: usize) -> u64 {
        match self {
            FeatureFormat::F32 => values as u64 * 4,
            FeatureFormat::F16 => values.div_ceil(2) as u64 * 4,
        }
    }
}

/// Adam's learning rates and table mode for one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepRates {
    /// Dense learning rate.
    pub lr: f32,
    /// Table learning rate.
    pub lr_table: f32,
    /// Lazy or dense table update.
    pub mode: TableAdam,
}

/// One step's gradients, read back (for the equivalence tests).
#[derive(Debug, Clone)]
pub struct Gradients {
    /// Loss (sum of the per-workgroup partials, in order).
    pub loss: f64,
    /// Sum of squared intensity errors.
    pub sse: f64,
    /// Dense gradient, in the model's layout.
    pub dense: Vec<f32>,
    /// Table gradient, level-major.
    pub table: Vec<f32>,
    /// Table parameters marked as touched.
    pub touched: Vec<bool>,
}

/// Codes of the fused program's operations (`shaders/inr_fused.wgsl`).
#[derive(Debug, Clone, Copy)]
enum Op {
    /// A GEMM over the block's columns (forward, backward data).
    Cols = 0,
    /// A weight gradient into the block's partial.
    Wgrad = 1,
    FilmFwd = 2,
    FilmBwd = 3,
    Loss = 4,
    /// A bias gradient into the block's partial.
    Bias = 5,
}

#[derive(Default)]
struct Program {
    args: Vec<u8>,
    calls: Vec<(Kernel, u32, [u32; 3])>,
    stride: usize,
    /// Samples per workgroup of the fused kernel.
    block: usize,
    /// While fusing: the operations recorded since `begin_fuse`.
    fusing: Option<Vec<[u32; 24]>>,
}

impl Program {
    fn push(&mut self, k: Kernel, a: [u32; 24], groups: [u32; 3]) {
        self.push_words(k, &a, groups);
    }

    fn push_words(&mut self, k: Kernel, a: &[u32], groups: [u32; 3]) {
        let off = self.args.len();
        self.args.extend_from_slice(bytemuck::cast_slice(a));
        self.args
            .resize(off + (a.len() * 4).div_ceil(self.stride) * self.stride, 0);
        if groups.iter().all(|&g| g > 0) {
            self.calls.push((k, off as u32, groups));
        }
    }

    /// A layer operation: recorded into the fused program while fusing, else dispatched.
    fn op(&mut self, op: Op, k: Kernel, mut a: [u32; 24], groups: [u32; 3]) {
        match &mut self.fusing {
            Some(ops) => {
                a[23] = op as u32;
                ops.push(a);
            }
            None => self.push(k, a, groups),
        }
    }

    /// An operation only the fused program has (no kernel of its own); only while fusing.
    fn fused_only(&mut self, op: Op, mut a: [u32; 24]) {
        debug_assert!(self.fusing.is_some(), "{op:?} outside a fused program");
        if let Some(ops) = &mut self.fusing {
            a[23] = op as u32;
            ops.push(a);
        }
    }

    /// From here until `end_fuse`, layer operations go into one fused program.
    fn begin_fuse(&mut self) {
        self.fusing = Some(Vec::new());
    }

    /// Dispatches the operations recorded since `begin_fuse` over `n` samples, in programs of
    /// at most [`FUSED_OPS`] operations (a dispatch boundary is a full barrier, so a longer
    /// list split in two computes the same).
    fn end_fuse(&mut self, n: usize) {
        let Some(ops) = self.fusing.take() else {
            return;
        };
        for chunk in ops.chunks(FUSED_OPS) {
            let mut w = vec![chunk.len() as u32, n as u32, 0, 0];
            for a in chunk {
                w.extend_from_slice(a);
            }
            self.push_words(Kernel::Fused, &w, [n.div_ceil(self.block) as u32, 1, 1]);
        }
    }
}

fn f(v: f32) -> u32 {
    v.to_bits()
}

/// The pipeline of kernel `k`: the engine's own fused kernel (its block) for `Fused`.
fn pick<'a>(
    ctx: &'a GpuContext,
    fused: &'a Option<wgpu::ComputePipeline>,
    k: Kernel,
) -> &'a wgpu::ComputePipeline {
    match (k, fused) {
        (Kernel::Fused, Some(p)) => p,
        _ => ctx.pipeline(k),
    }
}

/// The INR on a GPU.
pub struct GpuInr {
    ctx: Arc<GpuContext>,
    /// Architecture.
    pub cfg: InrConfig,
    /// Hash-grid geometry.
    pub grid: HashGrid,
    /// Dense layout.
    pub layout: DenseLayout,
    /// The volume grid.
    pub dims: [usize; 3],
    plan: Plan,
    opts: EngineOptions,
    arena: Tracked,
    table: Tracked,
    acc_lo: Tracked,
    acc_hi: Tracked,
    m_table: Tracked,
    v_table: Tracked,
    ring: Tracked,
    order: Tracked,
    args: Tracked,
    bind: wgpu::BindGroup,
    marks: u32,
    misc: u32,
    slot_words: usize,
    adam: Adam,
    profile: Option<Vec<(Kernel, u64, f64)>>,
    /// How the last profiled submission was timed.
    profile_timer: &'static str,
    /// The fused kernel of this engine's block (on a fused path).
    fused_pipe: Option<wgpu::ComputePipeline>,
    /// How the fused kernel's tiles compute.
    arith: TileArith,
    /// The loss-scale exponent where set by [`GpuInr::set_loss_scale_exp`].
    loss_scale: Option<u32>,
}

fn bytes(v: &[f32]) -> &[u8] {
    bytemuck::cast_slice(v)
}

impl GpuInr {
    /// Places `model` (and, for training, fresh or given optimiser state) on the device.
    pub fn new(
        ctx: &Arc<GpuContext>,
        model: &InrModel,
        adam: Option<&Adam>,
        opts: EngineOptions,
    ) -> Result<Self> {
        if model.cfg.features_per_level == 0 {
            return Err(GpuError::Config(
                "features_per_level must be positive".into(),
            ));
        }
        if !model.cfg.context_sigmas.is_empty() {
            return Err(GpuError::Config(format!(
                "the GPU engine has the paper's six heads only; this model has {} context heads: use --backend cpu",
                2 * model.cfg.context_sigmas.len()
            )));
        }
        let max = ctx.max_binding() as usize / 4;
        // Both paths launch one workgroup per 64 samples (GEMM column tiles) or per fused
        // block along x, so a micro-batch is at most that x the adapter's workgroups per
        // dimension.
        let per_group = opts.mlp.block().unwrap_or(TILE as usize).min(TILE as usize);
        let most = per_group * ctx.max_groups().max(1) as usize;
        let arith = ctx.tile_arith_for(opts.mlp.half());
        let fused_pipe = match opts.mlp.block() {
            Some(b) => Some(ctx.fused_pipeline(b, arith)?),
            None => None,
        };
        let mut mb = opts
            .micro_batch
            .unwrap_or(if opts.train { 16384 } else { 32768 })
            .min(opts.batch.max(1))
            .min(most)
            .max(1);
        let plan = loop {
            let p = Plan::with_block(model, mb, opts.batch, opts.train, opts.mlp.block());
            if p.len <= max {
                break p;
            }
            if mb <= 256 {
                return Err(GpuError::Config(format!(
                    "the activations of {mb} samples ({} MiB) exceed the adapter's binding limit",
                    p.bytes() >> 20
                )));
            }
            mb /= 2;
        };
        let s = wgpu::BufferUsages::STORAGE;
        let cd = wgpu::BufferUsages::COPY_DST;
        let cs = wgpu::BufferUsages::COPY_SRC;
        let tlen = model.table.len() as u64 * 4;
        let train = opts.train;
        let small = 16;
        let arena = ctx.buffer("arena", plan.bytes(), s | cd | cs)?;
        let table = ctx.buffer("table", tlen, s | cd | cs)?;
        let entries = model.grid.levels.len() * model.grid.t;
        let marks = (tlen / 4) as u32;
        let mark_words = entries.div_ceil(32) as u64;
        let misc = marks + mark_words as u32;
        let (acc_lo, acc_hi, m_table, v_table) = if train {
            (
                ctx.buffer("table gradient (low words)", tlen, s | cd | cs)?,
                ctx.buffer(
                    "table gradient (high words), marks",
                    tlen + 4 * mark_words + 64,
                    s | cd | cs,
                )?,
                ctx.buffer("table Adam m", tlen, s | cd | cs)?,
                ctx.buffer("table Adam v", tlen, s | cd | cs)?,
            )
        } else {
            // No table gradient: its binding (u32 words) holds a micro-batch's features packed
            // as f16 (`gather_f16`), for the widest feature kind.
            let widest = FeatureKind::Concat.channels_of(
                &model.cfg,
                model.grid.out_dim(),
                model.layout.mlp_in(),
            );
            (
                ctx.buffer(
                    "features (f16)",
                    FeatureFormat::F16.bytes(mb * widest).max(small),
                    s | cs,
                )?,
                ctx.buffer("unused", small, s)?,
                ctx.buffer("unused", small, s)?,
                ctx.buffer("unused", small, s)?,
            )
        };
        let halo = neuvolex_bricks::derived::DERIVED_HALO.max(model.cfg.patch / 2);
        let b = opts.brick.max(1);
        let slot_words = (b + 2 * halo).pow(3) + b.pow(3) * TARGETS;
        let ring = ctx.buffer(
            "tile ring",
            4 * (HEADER * opts.slots + slot_words * opts.slots) as u64,
            s | cd,
        )?;
        let order = ctx.buffer(
            "sample order",
            (16 * opts.order_pairs as u64).max(small),
            s | cd,
        )?;
        let align = ctx
            .gpu
            .limits()
            .min_uniform_buffer_offset_alignment
            .max(ARGS_BYTES as u32) as u64;
        let args = ctx.buffer(
            "arguments",
            64 * align + WINDOW_BYTES,
            wgpu::BufferUsages::UNIFORM | cd,
        )?;
        let bind = Self::bind_group(
            ctx,
            &[
                &args, &arena, &table, &acc_lo, &acc_hi, &m_table, &v_table, &ring, &order,
            ],
        );
        let mut e = GpuInr {
            ctx: ctx.clone(),
            cfg: model.cfg.clone(),
            grid: model.grid.clone(),
            layout: model.layout.clone(),
            dims: model.dims,
            plan,
            opts,
            arena,
            table,
            acc_lo,
            acc_hi,
            m_table,
            v_table,
            ring,
            order,
            args,
            bind,
            marks,
            misc,
            slot_words,
            adam: Adam::new(0, 0),
            profile: None,
            profile_timer: "host",
            fused_pipe,
            arith,
            loss_scale: None,
        };
        e.upload_model(model);
        if train {
            let fresh;
            let a = match adam {
                Some(a) => a,
                None => {
                    fresh = Adam::new(model.dense.len(), model.table.len());
                    &fresh
                }
            };
            e.upload_adam(a)?;
        }
        ctx.check()?;
        Ok(e)
    }

    fn bind_group(ctx: &GpuContext, b: &[&Tracked; 9]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = b
            .iter()
            .enumerate()
            .map(|(i, buf)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: if i == 0 {
                    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &buf.buf,
                        offset: 0,
                        size: wgpu::BufferSize::new(WINDOW_BYTES),
                    })
                } else {
                    buf.as_entire_binding()
                },
            })
            .collect();
        ctx.gpu
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("inr"),
                layout: &ctx.layout,
                entries: &entries,
            })
    }

    /// The context.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Samples per micro-batch.
    pub fn micro_batch(&self) -> usize {
        self.plan.mb
    }

    /// Times every dispatch from now on, or stops. Where the adapter has timestamp queries
    /// ([`GpuContext::has_timestamps`]) each dispatch runs in a compute pass of its own with
    /// GPU timestamps at its start and end, the step in one submission (the kernels' own
    /// times); elsewhere each dispatch is submitted alone and waited for (host time, which
    /// includes the submission's overhead).
    pub fn set_profile(&mut self, on: bool) {
        self.profile = on.then(Vec::new);
    }

    /// Per kernel: dispatches and seconds, since profiling began.
    pub fn profile(&self) -> Vec<(Kernel, u64, f64)> {
        self.profile.clone().unwrap_or_default()
    }

    /// How the last profiled submission was timed: `gpu timestamps` or `host`.
    pub fn profile_timer(&self) -> &'static str {
        self.profile_timer
    }

    /// How the fused kernel's GEMM tiles compute on this engine ([`TileArith::F32`] on the
    /// f32 paths; on the f16 paths, tensor cores where the device has them, else f16-rounded
    /// inputs on the f32 units).
    pub fn tile_arith(&self) -> TileArith {
        self.arith
    }

    /// Runs the fused kernel's tiles with `arith` from now on: on an f16 path,
    /// [`TileArith::HalfRounded`] or (where the device has them) [`TileArith::TensorCores`],
    /// to check one against the other on the same engine; on an f32 path only
    /// [`TileArith::F32`].
    pub fn set_tile_arith(&mut self, arith: TileArith) -> Result<()> {
        let Some(block) = self.opts.mlp.block() else {
            return Err(GpuError::Config(
                "the layered path has no fused tiles to change".into(),
            ));
        };
        if self.opts.mlp.half() == (arith == TileArith::F32) {
            return Err(GpuError::Config(format!(
                "the {} path cannot run {} tiles",
                self.opts.mlp.name(),
                arith.name()
            )));
        }
        self.fused_pipe = Some(self.ctx.fused_pipeline(block, arith)?);
        self.arith = arith;
        Ok(())
    }

    /// The loss-scale exponent `e` of a step of `len` samples: the output gradient is
    /// `2 w (y - t) 2^e / len` instead of `2 w (y - t) / len`, every gradient of the backward
    /// pass is `2^e` times the true one, and the optimisers divide it back out (exactly: a
    /// power of two). 0 on the f32 paths; on the f16 paths `ceil(log2(len))`, so the output
    /// gradient is about `2 w (y - t)`, whose size follows the error rather than the batch:
    /// at batch 16 384 an error of 0.01 would give 1.2e-6 unscaled, below f16's smallest
    /// normal value (6.1e-5), and 0.02 scaled. An explicit [`GpuInr::set_loss_scale_exp`]
    /// wins.
    pub fn loss_scale_exp(&self, len: usize) -> u32 {
        self.loss_scale.unwrap_or(if self.opts.mlp.half() {
            len.max(1).next_power_of_two().trailing_zeros()
        } else {
            0
        })
    }

    /// Sets the loss-scale exponent for every later step (`None`: the path's own, see
    /// [`GpuInr::loss_scale_exp`]); at most 60, so the fixed-point table gradient keeps its range.
    pub fn set_loss_scale_exp(&mut self, e: Option<u32>) -> Result<()> {
        if let Some(e) = e.filter(|&e| e > 60) {
            return Err(GpuError::Config(format!(
                "a loss scale of 2^{e} is past the largest, 2^60"
            )));
        }
        self.loss_scale = e;
        Ok(())
    }

    /// The MLP launch path.
    pub fn mlp_path(&self) -> MlpPath {
        self.opts.mlp
    }

    /// Adam steps taken.
    pub fn steps(&self) -> u64 {
        self.adam.t
    }

    /// Writes the model's parameters and fixed tables (levels, coordinates, loss weights).
    pub fn upload_model(&mut self, model: &InrModel) {
        let q = &self.ctx.gpu.queue;
        let p = &self.plan;
        q.write_buffer(&self.table, 0, bytes(&model.table));
        q.write_buffer(&self.arena, p.params as u64 * 4, bytes(&model.dense));
        let w = loss_weights(&model.cfg, model.layout.head.out);
        q.write_buffer(&self.arena, p.weights as u64 * 4, bytes(&w));
        let lv: Vec<u32> = model
            .grid
            .levels
            .iter()
            .flat_map(|l| [l.res, l.dense as u32])
            .collect();
        q.write_buffer(&self.arena, p.levels as u64 * 4, bytemuck::cast_slice(&lv));
        // The exact coordinates the CPU tiles use: (i / d) + (0.5 / d), in f32.
        let axes: Vec<f32> = (0..3)
            .flat_map(|a| {
                let d = model.dims[a];
                (0..d).map(move |i| i as f32 / d as f32 + 0.5 / d as f32)
            })
            .collect();
        q.write_buffer(&self.arena, p.axes as u64 * 4, bytes(&axes));
    }

    /// Writes Adam's moments and step count.
    pub fn upload_adam(&mut self, a: &Adam) -> Result<()> {
        if !self.opts.train {
            return Err(GpuError::Config(
                "an inference engine has no optimiser".into(),
            ));
        }
        let (dl, tl) = (self.layout.len, self.grid.table_len());
        if a.m_dense.len() != dl
            || a.v_dense.len() != dl
            || a.m_table.len() != tl
            || a.v_table.len() != tl
        {
            return Err(GpuError::Config(
                "optimiser state does not match the model".into(),
            ));
        }
        let q = &self.ctx.gpu.queue;
        q.write_buffer(&self.m_table, 0, bytes(&a.m_table));
        q.write_buffer(&self.v_table, 0, bytes(&a.v_table));
        q.write_buffer(&self.arena, self.plan.m as u64 * 4, bytes(&a.m_dense));
        q.write_buffer(&self.arena, self.plan.v as u64 * 4, bytes(&a.v_dense));
        self.adam = Adam {
            m_dense: vec![],
            v_dense: vec![],
            m_table: vec![],
            v_table: vec![],
            ..a.clone()
        };
        Ok(())
    }

    fn floats(&self, buf: &wgpu::Buffer, off: u64, n: usize) -> Result<Vec<f32>> {
        let b = self.ctx.read(buf, off * 4, n as u64 * 4)?;
        Ok(bytemuck::pod_collect_to_vec(&b))
    }

    /// The model with the device's current parameters.
    pub fn download_model(&self) -> Result<InrModel> {
        let table = self.floats(&self.table, 0, self.grid.table_len())?;
        let dense = self.floats(&self.arena, self.plan.params as u64, self.layout.len)?;
        Ok(InrModel {
            cfg: self.cfg.clone(),
            grid: self.grid.clone(),
            layout: self.layout.clone(),
            table,
            dense,
            dims: self.dims,
        })
    }

    /// Adam's state on the device.
    pub fn download_adam(&self) -> Result<Adam> {
        let (dl, tl) = (self.layout.len, self.grid.table_len());
        Ok(Adam {
            m_table: self.floats(&self.m_table, 0, tl)?,
            v_table: self.floats(&self.v_table, 0, tl)?,
            m_dense: self.floats(&self.arena, self.plan.m as u64, dl)?,
            v_dense: self.floats(&self.arena, self.plan.v as u64, dl)?,
            ..self.adam.clone()
        })
    }

    fn program(&self) -> Program {
        Program {
            stride: self
                .ctx
                .gpu
                .limits()
                .min_uniform_buffer_offset_alignment
                .max(ARGS_BYTES as u32) as usize,
            block: self.opts.mlp.block().unwrap_or(FUSED_BLOCK),
            ..Default::default()
        }
    }

    /// Submits `prog`, then whatever `after` records outside the compute pass.
    fn submit(
        &mut self,
        prog: Program,
        after: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> Result<wgpu::SubmissionIndex> {
        // Every dispatch binds a window of WINDOW_BYTES at its offset.
        if prog.args.len() as u64 + WINDOW_BYTES > self.args.size() {
            let size = (prog.args.len() as u64 + WINDOW_BYTES).next_power_of_two();
            self.args = self.ctx.buffer(
                "arguments",
                size,
                wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            )?;
            self.bind = Self::bind_group(
                &self.ctx,
                &[
                    &self.args,
                    &self.arena,
                    &self.table,
                    &self.acc_lo,
                    &self.acc_hi,
                    &self.m_table,
                    &self.v_table,
                    &self.ring,
                    &self.order,
                ],
            );
        }
        if !prog.args.is_empty() {
            self.ctx.gpu.queue.write_buffer(&self.args, 0, &prog.args);
        }
        if let Some(prof) = &mut self.profile {
            let n = prog.calls.len();
            if self.ctx.has_timestamps() && n > 0 && 2 * n <= wgpu::QUERY_SET_MAX_QUERIES as usize {
                // Every dispatch in a compute pass of its own with timestamps at its start and
                // end, all in one submission: the kernels' own times on the GPU.
                let q = 2 * n as u32;
                let qs = self
                    .ctx
                    .gpu
                    .device
                    .create_query_set(&wgpu::QuerySetDescriptor {
                        label: Some("profile"),
                        ty: wgpu::QueryType::Timestamp,
                        count: q,
                    });
                let size = 8 * q as u64;
                let resolve = self.ctx.buffer(
                    "timestamps",
                    size,
                    wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                )?;
                let read = self.ctx.buffer(
                    "timestamps (readback)",
                    size,
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                )?;
                let mut enc = self
                    .ctx
                    .gpu
                    .device
                    .create_command_encoder(&Default::default());
                for (i, &(k, off, g)) in prog.calls.iter().enumerate() {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: None,
                        timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                            query_set: &qs,
                            beginning_of_pass_write_index: Some(2 * i as u32),
                            end_of_pass_write_index: Some(2 * i as u32 + 1),
                        }),
                    });
                    pass.set_pipeline(pick(&self.ctx, &self.fused_pipe, k));
                    pass.set_bind_group(0, &self.bind, &[off]);
                    pass.dispatch_workgroups(g[0], g[1], g[2]);
                }
                enc.resolve_query_set(&qs, 0..q, &resolve, 0);
                enc.copy_buffer_to_buffer(&resolve, 0, &read, 0, size);
                after(&mut enc);
                let idx = self.ctx.gpu.queue.submit([enc.finish()]);
                let ticks = self.ctx.map_read_u64(&read, size, Some(idx.clone()))?;
                let period = self.ctx.gpu.queue.get_timestamp_period() as f64 * 1e-9;
                for (i, &(k, _, _)) in prog.calls.iter().enumerate() {
                    let s = ticks[2 * i + 1].saturating_sub(ticks[2 * i]) as f64 * period;
                    match prof.iter_mut().find(|e| e.0 == k) {
                        Some(e) => {
                            e.1 += 1;
                            e.2 += s;
                        }
                        None => prof.push((k, 1, s)),
                    }
                }
                self.profile_timer = "gpu timestamps";
                return Ok(idx);
            }
            self.profile_timer = "host";
            // One dispatch per submission, waited for and timed (kernel costs, not speed).
            for &(k, off, g) in &prog.calls {
                let t = std::time::Instant::now();
                let mut enc = self
                    .ctx
                    .gpu
                    .device
                    .create_command_encoder(&Default::default());
                {
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    pass.set_pipeline(pick(&self.ctx, &self.fused_pipe, k));
                    pass.set_bind_group(0, &self.bind, &[off]);
                    pass.dispatch_workgroups(g[0], g[1], g[2]);
                }
                self.ctx.gpu.queue.submit([enc.finish()]);
                self.ctx.wait()?;
                let s = t.elapsed().as_secs_f64();
                match prof.iter_mut().find(|e| e.0 == k) {
                    Some(e) => {
                        e.1 += 1;
                        e.2 += s;
                    }
                    None => prof.push((k, 1, s)),
                }
            }
            let mut enc = self
                .ctx
                .gpu
                .device
                .create_command_encoder(&Default::default());
            after(&mut enc);
            return Ok(self.ctx.gpu.queue.submit([enc.finish()]));
        }
        let mut enc = self
            .ctx
            .gpu
            .device
            .create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            let mut cur: Option<Kernel> = None;
            for &(k, off, g) in &prog.calls {
                if cur != Some(k) {
                    pass.set_pipeline(pick(&self.ctx, &self.fused_pipe, k));
                    cur = Some(k);
                }
                pass.set_bind_group(0, &self.bind, &[off]);
                pass.dispatch_workgroups(g[0], g[1], g[2]);
            }
        }
        after(&mut enc);
        Ok(self.ctx.gpu.queue.submit([enc.finish()]))
    }

    /// Workgroups for `n` invocations of a 1-D kernel, spread over x and y.
    fn groups_1d(&self, n: usize) -> [u32; 3] {
        let g = n.div_ceil(WG);
        let maxd = self.ctx.max_groups().max(1) as usize;
        let x = g.min(maxd);
        [x as u32, g.div_ceil(x.max(1)) as u32, 1]
    }

    #[allow(clippy::too_many_arguments)]
    fn gemm(
        &self,
        p: &mut Program,
        dims: [usize; 3],
        flags: u32,
        a: [u32; 3],
        b: [u32; 4],
        c: [u32; 4],
        e: [u32; 4],
        s: [u32; 2],
        splits: usize,
        op: Op,
    ) {
        let [m, n, k] = dims;
        let args = [
            m as u32, n as u32, k as u32, flags, a[0], a[1], a[2], 0, b[0], b[1], b[2], b[3], c[0],
            c[1], c[2], c[3], e[0], e[1], e[2], e[3], s[0], s[1], 0, 0,
        ];
        p.op(
            op,
            Kernel::Gemm,
            args,
            [
                n.div_ceil(TILE as usize) as u32,
                m.div_ceil(TILE as usize) as u32,
                splits as u32,
            ],
        );
    }

    /// Y = act(W X + b) (+ Y when accumulating).
    #[allow(clippy::too_many_arguments)]
    fn fwd(&self, p: &mut Program, l: &LayerSpec, x: Mat, y: Mat, n: usize, relu: bool, acc: bool) {
        let w = self.plan.params + l.w as u32;
        let mut flags = F_A_KCONTIG | F_B_NCONTIG;
        if l.b.is_some() {
            flags |= F_BIAS;
        }
        if relu {
            flags |= F_RELU;
        }
        if acc {
            flags |= F_ACC;
        }
        let bias = self.plan.params + l.b.unwrap_or(0) as u32;
        self.gemm(
            p,
            [l.out, n, l.inp],
            flags,
            [w, l.inp as u32, 1],
            [x.off, x.stride, 1, n as u32],
            [y.off, y.stride, 1, 0],
            [bias, 0, 0, 0],
            [l.inp as u32, 0],
            1,
            Op::Cols,
        );
    }

    /// dX = (W^T dY) masked by `mask > 0` from row `from` (+ dX when accumulating).
    #[allow(clippy::too_many_arguments)]
    fn bwd(
        &self,
        p: &mut Program,
        l: &LayerSpec,
        dy: Mat,
        dx: Mat,
        n: usize,
        mask: Option<(Mat, usize)>,
        acc: bool,
    ) {
        let w = self.plan.params + l.w as u32;
        let mut flags = F_B_NCONTIG;
        if acc {
            flags |= F_ACC;
        }
        let (mo, ms, mf) = match mask {
            Some((m, from)) => {
                flags |= F_MASK;
                (m.off, m.stride, from as u32)
            }
            None => (0, 0, 0),
        };
        self.gemm(
            p,
            [l.inp, n, l.out],
            flags,
            [w, 1, l.inp as u32],
            [dy.off, dy.stride, 1, n as u32],
            [dx.off, dx.stride, 1, 0],
            [0, mo, ms, mf],
            [l.out as u32, 0],
            1,
            Op::Cols,
        );
    }

    /// dW = dY X^T and db = sum dY, one partial per split of the samples.
    /// On the fused path the bias gradient is its own operation (a row sum over the block)
    /// rather than the GEMM's column of ones, which costs a whole 64-wide tile when the layer's
    /// input is a multiple of 64 wide.
    fn wgrad(&self, p: &mut Program, l: &LayerSpec, dy: Mat, x: Mat, n: usize) {
        let parts = self.plan.parts;
        let fused = self.fused();
        let cols = l.inp + (l.b.is_some() && !fused) as usize;
        self.gemm(
            p,
            [l.out, cols, n],
            F_A_KCONTIG,
            [dy.off, dy.stride, 1],
            [x.off, 1, x.stride, l.inp as u32],
            [parts + l.w as u32, l.inp as u32, 1, self.layout.len as u32],
            [0; 4],
            [self.plan.split as u32, parts + l.b.unwrap_or(0) as u32],
            self.plan.splits(n),
            Op::Wgrad,
        );
        if let (Some(b), true) = (l.b, fused) {
            let mut a = [0u32; 24];
            a[..4].copy_from_slice(&[l.out as u32, n as u32, dy.off, dy.stride]);
            a[4..7].copy_from_slice(&[
                parts + b as u32,
                self.layout.len as u32,
                self.plan.split as u32,
            ]);
            p.fused_only(Op::Bias, a);
        }
    }

    fn grid_args(&self, n: usize, coords: Mat, m: Mat) -> [u32; 24] {
        let mut a = [0u32; 24];
        a[..4].copy_from_slice(&[
            n as u32,
            self.grid.levels.len() as u32,
            self.grid.f as u32,
            self.grid.t as u32,
        ]);
        a[4..8].copy_from_slice(&[coords.off, coords.stride, 0, self.plan.axes]);
        a[8..12].copy_from_slice(&[m.off, m.stride, 0, self.plan.levels]);
        a
    }

    /// Stages `n` samples of micro-batch `j`: from the order buffer at `pairs` (pairs of a
    /// group), or (`slot` given) consecutive voxels of one slot from voxel `first`.
    fn stage(&self, p: &mut Program, j: usize, n: usize, src: Source) {
        let pl = &self.plan;
        let c = pl.coords.at(j, pl.mb);
        let (mode, x, y) = match src {
            Source::Order(o) => (0, o as u32, 0),
            Source::Slot(s, first) => (1, s as u32, first as u32),
        };
        let args = [
            n as u32,
            mode,
            x,
            y,
            c.off,
            c.stride,
            0,
            pl.axes,
            pl.patch.off,
            pl.patch.stride,
            self.cfg.patch as u32,
            TARGETS as u32,
            pl.target.off,
            pl.target.stride,
            self.dims[0] as u32,
            self.dims[1] as u32,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
        ];
        p.push(Kernel::Stage, args, [n.div_ceil(WG) as u32, 1, 1]);
    }

    /// Whether the dense layers run fused.
    fn fused(&self) -> bool {
        self.opts.mlp.block().is_some()
    }

    /// The hash-grid encoding of micro-batch `j` (`n` samples, already staged).
    fn encode(&self, p: &mut Program, j: usize, n: usize) {
        let pl = &self.plan;
        let nl = self.grid.levels.len();
        let coords = pl.coords.at(j, pl.mb);
        p.push(
            Kernel::Encode,
            self.grid_args(n, coords, pl.pos),
            [n.div_ceil(WG) as u32, nl as u32, 1],
        );
    }

    /// The layer operations of micro-batch `j` (`n` samples): the forward pass (up to the
    /// heads with `heads`) and, with `train_len` (the step's samples), the loss and the
    /// backward pass; one fused dispatch on the fused path.
    fn mlp(&self, p: &mut Program, j: usize, n: usize, heads: bool, train_len: Option<usize>) {
        let fused = self.fused();
        if fused {
            p.begin_fuse();
        }
        self.forward(p, n, heads);
        if let Some(len) = train_len {
            self.backward(p, j, n, len);
        }
        if fused {
            p.end_fuse(n);
        }
    }

    /// The forward pass of a micro-batch of `n` samples (encoded), up to the heads.
    fn forward(&self, p: &mut Program, n: usize, heads: bool) {
        let pl = &self.plan;
        let lay = &self.layout;
        let a = self.cfg.ablation;
        if a.structural() {
            self.fwd(p, &lay.structural[0], pl.patch, pl.s[0], n, true, false);
            self.fwd(p, &lay.structural[1], pl.s[0], pl.s[1], n, true, false);
        }
        if let Some(fl) = &lay.film {
            self.fwd(p, fl, pl.s[1], pl.gb, n, false, false);
            let e = self.grid.out_dim();
            let mut args = [0u32; 24];
            args[..4].copy_from_slice(&[n as u32, e as u32, 0, 0]);
            args[4..8].copy_from_slice(&[pl.pos.off, pl.pos.stride, pl.gb.off, pl.gb.stride]);
            args[8..10].copy_from_slice(&[pl.inp.off, pl.inp.stride]);
            p.op(
                Op::FilmFwd,
                Kernel::FilmFwd,
                args,
                [n.div_ceil(WG) as u32, e as u32, 1],
            );
        }
        for k in 0..lay.main.len() {
            let x = if k == 0 { pl.inp } else { pl.h[k - 1] };
            if k == lay.residual_at {
                self.fwd(p, &lay.proj, pl.inp, pl.h[k], n, false, false);
                self.fwd(p, &lay.main[k], x, pl.h[k], n, true, true);
            } else {
                self.fwd(p, &lay.main[k], x, pl.h[k], n, true, false);
            }
        }
        if heads {
            self.fwd(
                p,
                &lay.head,
                pl.h[lay.main.len() - 1],
                pl.y,
                n,
                false,
                false,
            );
        }
    }

    /// Loss and backward pass of micro-batch `j` (`n` samples of a step of `len`).
    fn backward(&self, p: &mut Program, j: usize, n: usize, len: usize) {
        let pl = &self.plan;
        let lay = &self.layout;
        let a = self.cfg.ablation;
        let enc = self.grid.out_dim();
        let last = lay.main.len() - 1;
        let mut args = [0u32; 24];
        args[..4].copy_from_slice(&[n as u32, lay.head.out as u32, pl.y.off, pl.y.stride]);
        args[4..8].copy_from_slice(&[pl.target.off, pl.target.stride, pl.dy.off, pl.dy.stride]);
        args[8..10].copy_from_slice(&[
            pl.weights,
            pl.loss_parts + (2 * j * pl.loss_groups(pl.mb)) as u32,
        ]);
        args[16] = f(1.0 / len as f32);
        args[17] = f((2.0f32).powi(self.loss_scale_exp(len) as i32) / len as f32);
        p.op(Op::Loss, Kernel::Loss, args, [n.div_ceil(WG) as u32, 1, 1]);
        self.wgrad(p, &lay.head, pl.dy, pl.h[last], n);
        self.bwd(
            p,
            &lay.head,
            pl.dy,
            pl.dh[0],
            n,
            Some((pl.h[last], 0)),
            false,
        );
        let dinp = pl.dinp.at(j, pl.mb);
        // Concatenation: the structural half of dL/dinp is masked by the structural ReLU.
        let dinp_mask = (a.structural() && !a.film()).then_some((pl.inp, enc));
        let mut cur = 0;
        let mut dinp_written = false;
        for k in (0..=last).rev() {
            let x = if k == 0 { pl.inp } else { pl.h[k - 1] };
            self.wgrad(p, &lay.main[k], pl.dh[cur], x, n);
            if k == lay.residual_at {
                self.wgrad(p, &lay.proj, pl.dh[cur], pl.inp, n);
                self.bwd(p, &lay.proj, pl.dh[cur], dinp, n, dinp_mask, false);
                dinp_written = true;
            }
            if k > 0 {
                self.bwd(
                    p,
                    &lay.main[k],
                    pl.dh[cur],
                    pl.dh[1 - cur],
                    n,
                    Some((pl.h[k - 1], 0)),
                    false,
                );
                cur = 1 - cur;
            } else {
                self.bwd(
                    p,
                    &lay.main[0],
                    pl.dh[cur],
                    dinp,
                    n,
                    dinp_mask,
                    dinp_written,
                );
            }
        }
        let ds0 = if let Some(fl) = &lay.film {
            let dpos = pl.dpos.at(j, pl.mb);
            let mut args = [0u32; 24];
            args[..4].copy_from_slice(&[n as u32, enc as u32, 0, 0]);
            args[4..8].copy_from_slice(&[pl.pos.off, pl.pos.stride, pl.gb.off, pl.gb.stride]);
            args[8..10].copy_from_slice(&[dinp.off, dinp.stride]);
            args[12..16].copy_from_slice(&[dpos.off, dpos.stride, pl.dgb.off, pl.dgb.stride]);
            p.op(
                Op::FilmBwd,
                Kernel::FilmBwd,
                args,
                [n.div_ceil(WG) as u32, enc as u32, 1],
            );
            self.wgrad(p, fl, pl.dgb, pl.s[1], n);
            self.bwd(p, fl, pl.dgb, pl.ds[0], n, Some((pl.s[1], 0)), false);
            pl.ds[0]
        } else {
            pl.ds[0].at(j, pl.mb)
        };
        if a.structural() {
            self.wgrad(p, &lay.structural[1], ds0, pl.s[0], n);
            self.bwd(
                p,
                &lay.structural[1],
                ds0,
                pl.ds[1],
                n,
                Some((pl.s[0], 0)),
                false,
            );
            self.wgrad(p, &lay.structural[0], pl.ds[1], pl.patch, n);
        }
    }

    /// Sums micro-batch `j`'s partials into the step's dense gradient; on the last micro-batch
    /// with `adam`, updates the dense parameters and writes the loss into stats slot `slot`.
    #[allow(clippy::too_many_arguments)]
    fn reduce(
        &self,
        p: &mut Program,
        j: usize,
        n: usize,
        n_mb: usize,
        len: usize,
        adam: Option<(f32, [f32; 2])>,
        slot: usize,
    ) {
        let pl = &self.plan;
        let last = j + 1 == n_mb && adam.is_some();
        let flags = (j == 0) as u32 | if last { 2 } else { 0 };
        let groups = (n_mb - 1) * pl.loss_groups(pl.mb)
            + pl.loss_groups(len.saturating_sub((n_mb - 1) * pl.mb));
        let (lr, c) = adam.unwrap_or((0.0, [1.0, 1.0]));
        let dl = self.layout.len;
        let args = [
            dl as u32,
            pl.splits(n) as u32,
            pl.parts,
            dl as u32,
            pl.g,
            flags,
            pl.params,
            pl.m,
            pl.v,
            pl.loss_parts,
            groups as u32,
            pl.stats + 2 * (slot % STATS_RING) as u32,
            self.loss_scale_exp(len),
            0,
            0,
            0,
            f(lr),
            f(self.adam.b1),
            f(self.adam.b2),
            f(self.adam.eps),
            f(c[0]),
            f(c[1]),
            0,
            0,
        ];
        p.push(Kernel::ReduceAdam, args, self.groups_1d(dl));
    }

    /// Micro-batches of a step of `len` samples: (index, first sample, samples).
    fn micro(&self, len: usize) -> Vec<(usize, usize, usize)> {
        let mb = self.plan.mb;
        (0..len.div_ceil(mb).max(1))
            .map(|j| (j, j * mb, mb.min(len - (j * mb).min(len))))
            .collect()
    }

    /// The table scatter of a step of `len` samples (after every micro-batch's backward).
    fn table_scatter(&self, p: &mut Program, len: usize) {
        let pl = &self.plan;
        let nl = self.grid.levels.len();
        let enc = self.grid.out_dim();
        let mut a = [0u32; 24];
        a[0] = len as u32;
        a[3] = self.misc;
        a[4..6].copy_from_slice(&[pl.dpos.off, pl.dpos.stride]);
        p.push(Kernel::AbsMax, a, [len.div_ceil(WG) as u32, enc as u32, 1]);
        let mut a = self.grid_args(len, pl.coords, pl.dpos);
        a[12..15].copy_from_slice(&[self.marks, self.misc, len as u32]);
        p.push(Kernel::Scatter, a, [len.div_ceil(WG) as u32, nl as u32, 1]);
    }

    fn check_train(&self, len: usize) -> Result<()> {
        if !self.opts.train {
            return Err(GpuError::Config("an inference engine cannot train".into()));
        }
        if len == 0 || len > self.plan.batch {
            return Err(GpuError::Config(format!(
                "a step of {len} samples does not fit the engine's batch of {}",
                self.plan.batch
            )));
        }
        Ok(())
    }

    /// One optimiser step on the `len` samples at pair `first` of the order buffer; the loss
    /// and intensity error land in stats slot `slot`. Submits without waiting.
    pub fn step(&mut self, first: usize, len: usize, rates: StepRates, slot: usize) -> Result<()> {
        self.check_train(len)?;
        self.adam.t += 1;
        let t = self.adam.t.min(i32::MAX as u64) as i32;
        let c = [1.0 - self.adam.b1.powi(t), 1.0 - self.adam.b2.powi(t)];
        let mut p = self.program();
        let micro = self.micro(len);
        let n_mb = micro.len();
        for &(j, s0, n) in &micro {
            self.stage(&mut p, j, n, Source::Order(first + s0));
            self.encode(&mut p, j, n);
            self.mlp(&mut p, j, n, true, Some(len));
            self.reduce(&mut p, j, n, n_mb, len, Some((rates.lr, c)), slot);
        }
        self.table_scatter(&mut p, len);
        let entries = self.grid.levels.len() * self.grid.t;
        let mut a = [0u32; 24];
        a[..4].copy_from_slice(&[
            entries as u32,
            self.grid.f as u32,
            (rates.mode == TableAdam::Dense) as u32,
            self.marks,
        ]);
        a[4..7].copy_from_slice(&[self.misc, len as u32, self.loss_scale_exp(len)]);
        a[16..20].copy_from_slice(&[
            f(rates.lr_table),
            f(self.adam.b1),
            f(self.adam.b2),
            f(self.adam.eps),
        ]);
        a[20..22].copy_from_slice(&[f(c[0]), f(c[1])]);
        p.push(Kernel::AdamTable, a, self.groups_1d(entries));
        let (acc_hi, from) = (&self.acc_hi.buf.clone(), self.marks as u64 * 4);
        self.submit(p, |enc| enc.clear_buffer(acc_hi, from, None))?;
        Ok(())
    }

    /// The loss and gradients of explicit samples without an optimiser step (for tests):
    /// positions, `patch^3` patches and `TARGETS` targets per sample.
    pub fn gradients(
        &mut self,
        coords: &[[f32; 3]],
        patches: &[f32],
        targets: &[[f32; TARGETS]],
    ) -> Result<Gradients> {
        let len = coords.len();
        self.check_train(len)?;
        let mut p = self.program();
        let micro = self.micro(len);
        let n_mb = micro.len();
        let pl = self.plan.clone();
        let coords_t = transpose(bytemuck::cast_slice(coords), 3);
        for r in 0..3 {
            self.write(pl.coords.row(r).off, &coords_t[r * len..(r + 1) * len]);
        }
        for &(j, s0, n) in &micro {
            // Stage this micro-batch's patches and targets by hand, then run it.
            let p3 = self.cfg.patch.pow(3);
            let pt = transpose(&patches[s0 * p3..(s0 + n) * p3], p3);
            let tt = transpose(bytemuck::cast_slice(&targets[s0..s0 + n]), TARGETS);
            let mut q = self.program();
            for r in 0..p3 {
                self.write(pl.patch.row(r).off, &pt[r * n..(r + 1) * n]);
            }
            for r in 0..TARGETS {
                self.write(pl.target.row(r).off, &tt[r * n..(r + 1) * n]);
            }
            self.encode(&mut q, j, n);
            self.mlp(&mut q, j, n, true, Some(len));
            self.reduce(&mut q, j, n, n_mb, len, None, 0);
            self.submit(q, |_| {})?;
        }
        self.table_scatter(&mut p, len);
        self.submit(p, |_| {})?;
        let groups = (n_mb - 1) * pl.loss_groups(pl.mb) + pl.loss_groups(micro[n_mb - 1].2);
        let lp = self.floats(&self.arena, pl.loss_parts as u64, 2 * groups)?;
        let (mut loss, mut sse) = (0.0f64, 0.0f64);
        for c in lp.chunks(2) {
            loss += c[0] as f64;
            sse += c[1] as f64;
        }
        // The backward pass ran on the loss scaled by 2^e: divide it back out.
        let e = self.loss_scale_exp(len) as i32;
        let dense = self
            .floats(&self.arena, pl.g as u64, self.layout.len)?
            .into_iter()
            .map(|g| g * (2f32).powi(-e))
            .collect();
        let tl = self.grid.table_len();
        let lo: Vec<u32> =
            bytemuck::pod_collect_to_vec(&self.ctx.read(&self.acc_lo, 0, tl as u64 * 4)?);
        let hi_all: Vec<u32> =
            bytemuck::pod_collect_to_vec(&self.ctx.read(&self.acc_hi, 0, self.acc_hi.size())?);
        let maxbits = hi_all[self.misc as usize];
        let s = scale_exp(maxbits, len);
        let table = (0..tl)
            .map(|i| fixed_to_f32(lo[i], hi_all[i]) * (2f32).powi(-s) * (2f32).powi(-e))
            .collect();
        let touched = (0..tl)
            .map(|i| {
                let e = self.marks as usize + (i / self.grid.f) / 32;
                (hi_all[e] >> ((i / self.grid.f) % 32)) & 1 == 1
            })
            .collect();
        // Leave the accumulators clean for the next call.
        let mut enc = self
            .ctx
            .gpu
            .device
            .create_command_encoder(&Default::default());
        enc.clear_buffer(&self.acc_lo, 0, None);
        enc.clear_buffer(&self.acc_hi, 0, None);
        self.ctx.gpu.queue.submit([enc.finish()]);
        self.ctx.check()?;
        Ok(Gradients {
            loss,
            sse,
            dense,
            table,
            touched,
        })
    }

    fn write(&self, off: u32, data: &[f32]) {
        if !data.is_empty() {
            self.ctx
                .gpu
                .queue
                .write_buffer(&self.arena, off as u64 * 4, bytes(data));
        }
    }

    /// Writes `tile` into ring slot `slot`.
    pub fn upload_tile(&self, slot: usize, tile: &Tile) -> Result<()> {
        if slot >= self.opts.slots {
            return Err(GpuError::Config(format!(
                "ring slot {slot} of {}",
                self.opts.slots
            )));
        }
        let s = tile.brick.size;
        let norm_words = tile.norm.len();
        let tgt_words = tile.voxels() * TARGETS;
        if norm_words + tgt_words > self.slot_words {
            return Err(GpuError::Config(format!(
                "a {s:?} tile with halo {} does not fit the ring's slots (brick edge {})",
                tile.halo, self.opts.brick
            )));
        }
        let data = HEADER * self.opts.slots + slot * self.slot_words;
        let o = tile.brick.origin;
        let header: [u32; HEADER] = [
            o[0] as u32,
            o[1] as u32,
            o[2] as u32,
            s[0] as u32,
            s[1] as u32,
            s[2] as u32,
            tile.halo as u32,
            data as u32,
            (data + norm_words) as u32,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
        ];
        let q = &self.ctx.gpu.queue;
        q.write_buffer(
            &self.ring,
            (slot * HEADER) as u64 * 4,
            bytemuck::cast_slice(&header),
        );
        q.write_buffer(&self.ring, data as u64 * 4, bytes(&tile.norm));
        q.write_buffer(
            &self.ring,
            (data + norm_words) as u64 * 4,
            bytemuck::cast_slice(&tile.targets),
        );
        Ok(())
    }

    /// Writes a group's sample order (flat (slot, voxel) pairs) at pair `first`.
    pub fn upload_order(&self, first: usize, pairs: &[u32]) -> Result<()> {
        if (first * 2 + pairs.len()) as u64 * 4 > self.order.size() {
            return Err(GpuError::Config(
                "the sample order does not fit its buffer".into(),
            ));
        }
        self.ctx
            .gpu
            .queue
            .write_buffer(&self.order, first as u64 * 8, bytemuck::cast_slice(pairs));
        Ok(())
    }

    /// Reads stats slots `from..to` (loss, sse) after the steps that wrote them are submitted:
    /// records the copy and returns a buffer to map later.
    pub fn stats_readback(&self) -> Result<Tracked> {
        let buf = self.ctx.buffer(
            "stats readback",
            (STATS_RING * 8) as u64,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )?;
        let mut enc = self
            .ctx
            .gpu
            .device
            .create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(
            &self.arena,
            self.plan.stats as u64 * 4,
            &buf,
            0,
            (STATS_RING * 8) as u64,
        );
        self.ctx.gpu.queue.submit([enc.finish()]);
        Ok(buf)
    }

    /// Head outputs (`n x outputs`) of explicit samples: positions and `patch^3` patches.
    pub fn outputs(&mut self, coords: &[[f32; 3]], patches: &[f32]) -> Result<Vec<f32>> {
        let outs = self.layout.head.out;
        let p3 = self.cfg.patch.pow(3);
        let pl = self.plan.clone();
        let mut out = Vec::with_capacity(coords.len() * outs);
        for start in (0..coords.len()).step_by(pl.mb) {
            let n = pl.mb.min(coords.len() - start);
            let ct = transpose(bytemuck::cast_slice(&coords[start..start + n]), 3);
            let pt = transpose(&patches[start * p3..(start + n) * p3], p3);
            for r in 0..3 {
                self.write(pl.coords.row(r).off, &ct[r * n..(r + 1) * n]);
            }
            for r in 0..p3 {
                self.write(pl.patch.row(r).off, &pt[r * n..(r + 1) * n]);
            }
            let mut p = self.program();
            self.encode(&mut p, 0, n);
            self.mlp(&mut p, 0, n, true, None);
            self.submit(p, |_| {})?;
            let y = self.floats(&self.arena, pl.y.off as u64, outs * pl.mb)?;
            for i in 0..n {
                out.extend((0..outs).map(|k| y[k * pl.mb + i]));
            }
        }
        self.ctx.check()?;
        Ok(out)
    }

    /// The rows (offset, stride, rows) a feature is gathered from.
    fn feature_rows(&self, kind: FeatureKind) -> Vec<(Mat, usize)> {
        let pl = &self.plan;
        let hid = self.cfg.hidden;
        let mi = self.layout.mlp_in();
        let last = pl.h[self.layout.main.len() - 1];
        match kind {
            FeatureKind::Hidden => vec![(last, hid)],
            FeatureKind::Pos => vec![(pl.pos, self.grid.out_dim())],
            FeatureKind::Mod => vec![(pl.inp, mi)],
            FeatureKind::Concat => vec![(last, hid), (pl.inp, mi), (pl.coords, 3)],
            // The coarse half of the hash-grid levels: the first rows of the encoding.
            FeatureKind::Region => {
                vec![(pl.pos, (self.grid.levels.len() / 2).max(1) * self.grid.f)]
            }
        }
    }

    /// Records the forward pass and feature gather of voxels `first..first + n` of ring slot
    /// `slot`, and the copy of the features (as `fmt`) to `dst` at byte `at`.
    #[allow(clippy::too_many_arguments)]
    fn record_features(
        &mut self,
        slot: usize,
        first: usize,
        n: usize,
        kind: FeatureKind,
        fmt: FeatureFormat,
        dst: &wgpu::Buffer,
        at: u64,
    ) -> Result<wgpu::SubmissionIndex> {
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        let mut p = self.program();
        self.stage(&mut p, 0, n, Source::Slot(slot, first));
        self.encode(&mut p, 0, n);
        self.mlp(&mut p, 0, n, false, None);
        let rows = self.feature_rows(kind);
        let mut a = [0u32; 24];
        a[..3].copy_from_slice(&[n as u32, c as u32, self.plan.out]);
        for (i, (m, r)) in rows.iter().enumerate() {
            a[4 + 4 * i..7 + 4 * i].copy_from_slice(&[m.off, m.stride, *r as u32]);
        }
        let bytes = fmt.bytes(n * c);
        let (src, from) = match fmt {
            FeatureFormat::F32 => {
                p.push(Kernel::Gather, a, [n.div_ceil(WG) as u32, c as u32, 1]);
                (self.arena.buf.clone(), self.plan.out as u64 * 4)
            }
            FeatureFormat::F16 => {
                let g = self.groups_1d((n * c).div_ceil(2));
                p.push(Kernel::GatherF16, a, g);
                (self.acc_lo.buf.clone(), 0)
            }
        };
        let dst = dst.clone();
        self.submit(p, |enc| {
            enc.copy_buffer_to_buffer(&src, from, &dst, at, bytes)
        })
    }

    /// Features of every core voxel of `tile` (`voxels x channels`, as the CPU's
    /// `extract_tile`), through ring slot `slot`; `staging` is a MAP_READ buffer large
    /// enough for the tile (see [`Self::staging_for`]). Blocks until read back.
    pub fn extract_tile(&mut self, tile: &Tile, kind: FeatureKind) -> Result<Vec<f32>> {
        let staging = self.staging_for(tile.voxels(), kind)?;
        self.upload_tile(0, tile)?;
        self.record_tile(0, tile.voxels(), kind, &staging)?;
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        self.ctx
            .map_read_f32(&staging, (tile.voxels() * c * 4) as u64, None)
    }

    /// [`Self::extract_tile`] with the features written as f16 on the GPU (an inference
    /// engine's [`FeatureFormat::F16`]), as the store keeps them.
    pub fn extract_tile_f16(&mut self, tile: &Tile, kind: FeatureKind) -> Result<Vec<half::f16>> {
        let fmt = FeatureFormat::F16;
        let staging = self.staging_in(tile.voxels(), kind, fmt)?;
        self.upload_tile(0, tile)?;
        self.record_tile_in(0, tile.voxels(), kind, fmt, &staging)?;
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        self.ctx.map_read_f16(&staging, tile.voxels() * c, None)
    }

    /// A MAP_READ buffer for the f32 features of `voxels` voxels.
    pub fn staging_for(&self, voxels: usize, kind: FeatureKind) -> Result<Tracked> {
        self.staging_in(voxels, kind, FeatureFormat::F32)
    }

    /// A MAP_READ buffer for the features of `voxels` voxels written as `fmt`.
    pub fn staging_in(
        &self,
        voxels: usize,
        kind: FeatureKind,
        fmt: FeatureFormat,
    ) -> Result<Tracked> {
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        self.ctx.buffer(
            "features readback",
            fmt.bytes(voxels * c),
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )
    }

    /// A buffer in device memory for the f32 features of `voxels` voxels (a copy destination
    /// for [`Self::record_tile`] that stays on the GPU, to time extraction without the
    /// transfer into host-mappable memory).
    pub fn device_buffer_for(&self, voxels: usize, kind: FeatureKind) -> Result<Tracked> {
        self.device_buffer_in(voxels, kind, FeatureFormat::F32)
    }

    /// [`Self::device_buffer_for`] for features written as `fmt`.
    pub fn device_buffer_in(
        &self,
        voxels: usize,
        kind: FeatureKind,
        fmt: FeatureFormat,
    ) -> Result<Tracked> {
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        self.ctx.buffer(
            "features (device)",
            fmt.bytes(voxels * c),
            wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST
                | wgpu::BufferUsages::COPY_SRC,
        )
    }

    /// Records the f32 features of all `voxels` voxels of slot `slot` into `staging` (no
    /// wait); returns the last submission.
    pub fn record_tile(
        &mut self,
        slot: usize,
        voxels: usize,
        kind: FeatureKind,
        staging: &wgpu::Buffer,
    ) -> Result<wgpu::SubmissionIndex> {
        self.record_tile_in(slot, voxels, kind, FeatureFormat::F32, staging)
    }

    /// [`Self::record_tile`] with the features written as `fmt` (voxel-major either way; f16
    /// packed two to a word, [`FeatureFormat::bytes`]). f16 needs an inference engine whose
    /// micro-batch holds an even number of values, so that each micro-batch starts on a whole
    /// word (always so for the engine's power-of-two micro-batches).
    pub fn record_tile_in(
        &mut self,
        slot: usize,
        voxels: usize,
        kind: FeatureKind,
        fmt: FeatureFormat,
        staging: &wgpu::Buffer,
    ) -> Result<wgpu::SubmissionIndex> {
        let c = kind.channels_of(&self.cfg, self.grid.out_dim(), self.layout.mlp_in());
        let mb = self.plan.mb;
        if fmt == FeatureFormat::F16 && (self.opts.train || !(mb * c).is_multiple_of(2)) {
            return Err(GpuError::Config(format!(
                "f16 features need an inference engine with an even number of values a \
                 micro-batch (this one: training {}, {mb} samples x {c} channels)",
                self.opts.train
            )));
        }
        let mut last = None;
        for first in (0..voxels.max(1)).step_by(mb) {
            let n = mb.min(voxels - first.min(voxels));
            // Whole words for f16: first * c is even (checked above).
            let at = fmt.bytes(first * c);
            last = Some(self.record_features(slot, first, n, kind, fmt, staging, at)?);
        }
        last.ok_or_else(|| GpuError::Config("nothing to extract".into()))
    }
}

/// Where a micro-batch's samples come from.
#[derive(Debug, Clone, Copy)]
enum Source {
    /// Pairs of the order buffer from this index.
    Order(usize),
    /// Consecutive voxels of a slot from this voxel.
    Slot(usize, usize),
}

/// `[n][c]` to `[c][n]`.
fn transpose(v: &[f32], c: usize) -> Vec<f32> {
    let n = v.len() / c.max(1);
    let mut out = vec![0.0; v.len()];
    for i in 0..n {
        for k in 0..c {
            out[k * n + i] = v[i * c + k];
        }
    }
    out
}

/// The fixed-point scale exponent, as the kernels compute it (`scale_exp` in inr_common.wgsl).
pub fn scale_exp(maxbits: u32, batch: usize) -> i32 {
    let bound = f32::from_bits(maxbits) * batch as f32;
    if !(bound > 0.0 && bound <= 3.0e38) {
        return 0;
    }
    // frexp: bound = m 2^e with m in [0.5, 1).
    let e = if bound.is_normal() {
        ((bound.to_bits() >> 23) & 0xff) as i32 - 126
    } else {
        bound.log2().floor() as i32 + 1
    };
    (61 - e).clamp(-120, 120)
}

/// A 64-bit two's-complement fixed-point value as f32 (`fixed_to_f32` in inr_common.wgsl).
pub fn fixed_to_f32(lo: u32, hi: u32) -> f32 {
    let v = ((hi as u64) << 32 | lo as u64) as i64;
    v as f32
}

/// Channels of a feature kind from the sizes alone.
trait Channels {
    fn channels_of(self, cfg: &InrConfig, enc: usize, mlp_in: usize) -> usize;
}

impl Channels for FeatureKind {
    fn channels_of(self, cfg: &InrConfig, enc: usize, mlp_in: usize) -> usize {
        match self {
            FeatureKind::Hidden => cfg.hidden,
            FeatureKind::Pos => enc,
            FeatureKind::Mod => mlp_in,
            FeatureKind::Concat => cfg.hidden + mlp_in + 3,
            FeatureKind::Region => (cfg.levels / 2).max(1) * cfg.features_per_level,
        }
    }
}
