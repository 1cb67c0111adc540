//! The classic filter bank of `neuvolex-filters` ([`neuvolex_filters::Classic::Filters`], and
//! the voxel's position for the default `filters+xyz` set) on the GPU, per brick with its halo
//! (`filters.wgsl`).
//!
//! The brick's padded grid is normalised on the host (in f64, as the CPU does) and uploaded; on
//! the GPU every Gaussian is three separable passes, each over the box of the padded grid that
//! the core's features read (as the CPU restricts its steps), clamped at the grid's ends with the CPU's f32 kernels ([`neuvolex_filters::gaussian_kernel`]) taken in the same
//! order; the structure tensor's gradient products use the CPU's one-sided differences at the
//! grid's ends; the eigenvalues use the same trigonometric closed form, in f32 on the matrix
//! scaled by the power of two of its largest entry (the CPU's is f64). The features land in one plane per channel
//! ([`crate::FeatureLayout::planes`]), ready for [`crate::GpuForest::encode`].

use crate::device::{grid, GpuDevice, Tracked, STORAGE_BUFFERS};
use crate::error::{GpuError, Result};
use neuvolex_bricks::derived::{HaloBrick, Normaliser};
use neuvolex_filters::{filter_halo, gaussian_kernel, pos, radius, PER_SIGMA, SIGMAS};
use std::sync::Arc;

/// The kernels.
pub const FILTERS_WGSL: &str = include_str!("filters.wgsl");

/// Invocations per workgroup of every filter kernel.
const WG: u64 = 64;

/// Ratio of the DoG's inner Gaussian (`neuvolex_filters`' `DOG_RATIO`).
const DOG_RATIO: f32 = 0.66;

/// Bytes between dispatch records in the uniform buffer (the largest offset alignment wgpu
/// asks of any adapter).
const RECORD: u64 = 256;

/// One dispatch's arguments (`Params` in `filters.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    px: u32,
    py: u32,
    pz: u32,
    total: u32,
    groups_x: u32,
    src: u32,
    dst: u32,
    axis: u32,
    taps_at: u32,
    radius: u32,
    cx: u32,
    cy: u32,
    cz: u32,
    halo: u32,
    base: u32,
    xyz: u32,
    s_at: u32,
    s_in_at: u32,
    st_at: u32,
    pos_at: u32,
    lo: [u32; 3],
    rx: u32,
    ry: u32,
    pad: [u32; 3],
}

/// A box of the padded grid, `lo..hi` per axis: the voxels a step computes (as
/// `neuvolex_filters`' `Region`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Region {
    lo: [usize; 3],
    hi: [usize; 3],
}

impl Region {
    /// Grown by `r` along the axes in `axes`, within the grid `p`.
    fn grow(self, r: usize, p: [usize; 3], axes: [bool; 3]) -> Region {
        Region {
            lo: std::array::from_fn(|k| {
                if axes[k] {
                    self.lo[k].saturating_sub(r)
                } else {
                    self.lo[k]
                }
            }),
            hi: std::array::from_fn(|k| {
                if axes[k] {
                    (self.hi[k] + r).min(p[k])
                } else {
                    self.hi[k]
                }
            }),
        }
    }

    /// Grown by `r` along every axis.
    fn grow_all(self, r: usize, p: [usize; 3]) -> Region {
        self.grow(r, p, [true; 3])
    }

    /// `prm` computing this box, and its voxels.
    fn args(self, prm: Params) -> (Params, u64) {
        let n: [u64; 3] = std::array::from_fn(|k| (self.hi[k] - self.lo[k]) as u64);
        (
            Params {
                lo: self.lo.map(|v| v as u32),
                rx: n[0] as u32,
                ry: n[1] as u32,
                ..prm
            },
            n.iter().product(),
        )
    }
}

#[derive(Debug, Clone, Copy)]
enum Kernel {
    Conv,
    Product,
    Assemble,
}

/// The filter-bank kernels, compiled.
pub struct GpuFilterBank {
    dev: Arc<GpuDevice>,
    layout: wgpu::BindGroupLayout,
    conv: wgpu::ComputePipeline,
    product: wgpu::ComputePipeline,
    assemble: wgpu::ComputePipeline,
    xyz: bool,
}

impl std::fmt::Debug for GpuFilterBank {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuFilterBank")
            .field("xyz", &self.xyz)
            .finish()
    }
}

/// The GPU buffers and recorded dispatches of one brick shape: reused brick after brick (one
/// per brick in flight).
pub struct FilterSlot {
    size: [usize; 3],
    halo: usize,
    arena: Tracked,
    features: Tracked,
    taps: Tracked,
    uniform: Tracked,
    bind: wgpu::BindGroup,
    calls: Vec<(Kernel, u32, u32, u32)>,
    pos_at: u64,
}

impl std::fmt::Debug for FilterSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FilterSlot")
            .field("size", &self.size)
            .field("halo", &self.halo)
            .field("bytes", &self.bytes())
            .finish()
    }
}

impl FilterSlot {
    /// The core size and halo it serves.
    pub fn shape(&self) -> ([usize; 3], usize) {
        (self.size, self.halo)
    }

    /// The features of the last brick run through it: one plane of the core's voxels per
    /// channel ([`crate::FeatureLayout::planes`]).
    pub fn features(&self) -> &wgpu::Buffer {
        &self.features
    }

    /// Bytes of its GPU buffers.
    pub fn bytes(&self) -> u64 {
        self.arena.size() + self.features.size() + self.taps.size() + self.uniform.size()
    }
}

/// Grids of the arena: the input, two scratch grids, the smoothed image, the DoG's inner
/// Gaussian, the inner-scale image, a gradient product and the six structure-tensor grids.
const GRIDS: u64 = 13;
const N: u64 = 0;
const A: u64 = 1;
const B: u64 = 2;
const S: u64 = 3;
const SIN: u64 = 4;
const G: u64 = 5;
const PR: u64 = 6;
const ST: u64 = 7;

impl GpuFilterBank {
    /// Compiles the kernels; `xyz` adds the voxel's normalised position as three more
    /// channels after the bank's (the default `filters+xyz` set).
    pub fn new(dev: Arc<GpuDevice>, xyz: bool) -> Result<Self> {
        dev.require_storage_buffers(STORAGE_BUFFERS)?;
        let scope = dev.device.push_error_scope(wgpu::ErrorFilter::Validation);
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
        let layout = dev
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("filters"),
                entries: &[
                    wgpu::BindGroupLayoutEntry {
                        binding: 0,
                        visibility: wgpu::ShaderStages::COMPUTE,
                        ty: wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Uniform,
                            has_dynamic_offset: true,
                            min_binding_size: wgpu::BufferSize::new(
                                std::mem::size_of::<Params>() as u64
                            ),
                        },
                        count: None,
                    },
                    storage(1, true),
                    storage(2, false),
                    storage(3, false),
                ],
            });
        let pl = dev
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("filters"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let module = dev
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("filters.wgsl"),
                source: wgpu::ShaderSource::Wgsl(FILTERS_WGSL.into()),
            });
        let pipe = |entry: &str| {
            dev.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(entry),
                    layout: Some(&pl),
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: None,
                })
        };
        let (conv, product, assemble) = (pipe("conv"), pipe("product"), pipe("assemble"));
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(
                neuvolex_gpu::GpuError::Device(format!("compiling the filter bank: {e}")).into(),
            );
        }
        Ok(GpuFilterBank {
            dev,
            layout,
            conv,
            product,
            assemble,
            xyz,
        })
    }

    /// Channels per voxel: the bank's 50, and 3 more with the position.
    pub fn channels(&self) -> usize {
        SIGMAS.len() * PER_SIGMA + if self.xyz { 3 } else { 0 }
    }

    /// The device.
    pub fn device(&self) -> &Arc<GpuDevice> {
        &self.dev
    }

    /// GPU bytes of a slot for a brick of `size` voxels with `halo`.
    pub fn slot_bytes(&self, size: [usize; 3], halo: usize) -> u64 {
        let p: u64 = size.iter().map(|&s| (s + 2 * halo) as u64).product();
        let core: u64 = size.iter().map(|&s| s as u64).product();
        GRIDS * p * 4 + self.channels() as u64 * core * 4
    }

    /// Buffers and recorded dispatches for bricks of `size` voxels with `halo` (at least
    /// [`filter_halo`]).
    pub fn slot(&self, size: [usize; 3], halo: usize) -> Result<FilterSlot> {
        if halo < filter_halo() {
            return Err(GpuError::Input(format!(
                "the filter bank needs a halo of {}, got {halo}",
                filter_halo()
            )));
        }
        if size.contains(&0) {
            return Err(GpuError::Input(format!("an empty brick {size:?}")));
        }
        let p = size.map(|s| s + 2 * halo);
        let plane: u64 = p.iter().map(|&v| v as u64).product();
        let core: u64 = size.iter().map(|&v| v as u64).product();
        if GRIDS * plane >= u32::MAX as u64 || self.channels() as u64 * core >= u32::MAX as u64 {
            return Err(GpuError::Input(format!(
                "a brick of {size:?} with a halo of {halo} is too large for one slot"
            )));
        }
        let dev = &self.dev;
        let arena = dev.buffer(
            "filters arena",
            GRIDS * plane * 4,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        )?;
        let features = dev.buffer(
            "features",
            self.channels() as u64 * core * 4,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        )?;
        // Taps: every scale's three kernels, then the positions of the core's voxels.
        let mut taps: Vec<f32> = Vec::new();
        let mut kernels = Vec::new();
        for &sigma in &SIGMAS {
            let mut at = [(0u32, 0u32); 3];
            for (k, s) in [sigma, DOG_RATIO * sigma, 0.5 * sigma]
                .into_iter()
                .enumerate()
            {
                let w = gaussian_kernel(s);
                at[k] = (taps.len() as u32, (w.len() / 2) as u32);
                taps.extend_from_slice(&w);
            }
            kernels.push(at);
        }
        let pos_at = taps.len();
        taps.resize(pos_at + size.iter().sum::<usize>(), 0.0);
        let tbuf = dev.upload(
            "filters taps",
            bytemuck::cast_slice(&taps),
            wgpu::BufferUsages::STORAGE,
        )?;
        let w = |g: u64| (g * plane) as u32;
        let base = Params {
            px: p[0] as u32,
            py: p[1] as u32,
            pz: p[2] as u32,
            cx: size[0] as u32,
            cy: size[1] as u32,
            cz: size[2] as u32,
            halo: halo as u32,
            pos_at: pos_at as u32,
            ..Default::default()
        };
        let mut records: Vec<Params> = Vec::new();
        let mut calls = Vec::new();
        let max = dev.max_groups();
        let mut push = |k: Kernel, mut prm: Params, total: u64| {
            let groups = total.div_ceil(WG) as u32;
            let (gx, gy) = grid(groups, max);
            prm.total = total as u32;
            prm.groups_x = gx;
            calls.push((k, records.len() as u32, gx, gy));
            records.push(prm);
        };
        // Each step computes only what the core's features read, as the CPU's filter bank does:
        // the smoothed image one voxel around the core, the products a kernel radius around it,
        // the inner-scale image one more; a Gaussian's passes each over what the next reads.
        let inner = Region {
            lo: [halo; 3],
            hi: std::array::from_fn(|k| halo + size[k]),
        };
        let smooth = |push: &mut dyn FnMut(Kernel, Params, u64),
                      src: u64,
                      dst: u64,
                      k: (u32, u32),
                      out: Region| {
            let r = k.1 as usize;
            let boxes = [
                out.grow(r, p, [false, true, true]),
                out.grow(r, p, [false, false, true]),
                out,
            ];
            for ((axis, from, to), reg) in
                [(0, src, A), (1, A, B), (2, B, dst)].into_iter().zip(boxes)
            {
                let (prm, n) = reg.args(Params {
                    src: w(from),
                    dst: w(to),
                    axis,
                    taps_at: k.0,
                    radius: k.1,
                    ..base
                });
                push(Kernel::Conv, prm, n);
            }
        };
        for (si, at) in kernels.iter().enumerate() {
            let around = inner.grow_all(radius(SIGMAS[si]), p);
            smooth(&mut push, N, S, at[0], inner.grow_all(1, p));
            smooth(&mut push, N, SIN, at[1], inner);
            smooth(&mut push, N, G, at[2], around.grow_all(1, p));
            for comp in 0..6u32 {
                let (prm, n) = around.args(Params {
                    src: w(G),
                    dst: w(PR),
                    axis: comp,
                    ..base
                });
                push(Kernel::Product, prm, n);
                smooth(&mut push, PR, ST + comp as u64, at[0], inner);
            }
            push(
                Kernel::Assemble,
                Params {
                    base: (si * PER_SIGMA) as u32,
                    xyz: if self.xyz && si == 0 {
                        (SIGMAS.len() * PER_SIGMA) as u32
                    } else {
                        0
                    },
                    s_at: w(S),
                    s_in_at: w(SIN),
                    st_at: w(ST),
                    ..base
                },
                core,
            );
        }
        let mut ubytes = vec![0u8; records.len() * RECORD as usize];
        for (i, r) in records.iter().enumerate() {
            let b = bytemuck::bytes_of(r);
            ubytes[i * RECORD as usize..][..b.len()].copy_from_slice(b);
        }
        let uniform = dev.upload("filters args", &ubytes, wgpu::BufferUsages::UNIFORM)?;
        let bind = dev.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("filters"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &uniform,
                        offset: 0,
                        size: wgpu::BufferSize::new(std::mem::size_of::<Params>() as u64),
                    }),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: tbuf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: arena.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: features.as_entire_binding(),
                },
            ],
        });
        Ok(FilterSlot {
            size,
            halo,
            arena,
            features,
            taps: tbuf,
            uniform,
            bind,
            calls,
            pos_at: pos_at as u64 * 4,
        })
    }

    /// Queues the upload of brick `b` (normalised by `norm`, positions from its origin in a
    /// volume of `dims`) into `slot` and records the bank's dispatches into `enc`. The
    /// features are in [`FilterSlot::features`] once `enc` has run.
    pub fn encode(
        &self,
        slot: &FilterSlot,
        enc: &mut wgpu::CommandEncoder,
        b: &HaloBrick,
        norm: &Normaliser,
        dims: [usize; 3],
    ) -> Result<()> {
        if (b.size, b.halo) != slot.shape() {
            return Err(GpuError::Input(format!(
                "a brick of {:?} with a halo of {} in a slot for {:?} with {}",
                b.size, b.halo, slot.size, slot.halo
            )));
        }
        let p = b.padded();
        if b.data.len() != p.iter().product::<usize>() {
            return Err(GpuError::Input(format!(
                "a padded brick of {p:?} holds {} values",
                b.data.len()
            )));
        }
        let n: Vec<f32> = b.data.iter().map(|&v| norm.apply(v)).collect();
        self.encode_normalised(slot, enc, &n, b.origin, dims)
    }

    /// [`Self::encode`] of a padded grid already normalised (`n`, the slot's padded size).
    pub fn encode_normalised(
        &self,
        slot: &FilterSlot,
        enc: &mut wgpu::CommandEncoder,
        n: &[f32],
        origin: [usize; 3],
        dims: [usize; 3],
    ) -> Result<()> {
        let p = slot.size.map(|s| s + 2 * slot.halo);
        if n.len() != p.iter().product::<usize>() {
            return Err(GpuError::Input(format!(
                "a padded grid of {p:?} cannot hold {} values",
                n.len()
            )));
        }
        let q = &self.dev.queue;
        q.write_buffer(&slot.arena, N * 4 * n.len() as u64, bytemuck::cast_slice(n));
        let posv: Vec<f32> = (0..3)
            .flat_map(|a| (0..slot.size[a]).map(move |i| pos(origin[a] + i, dims[a])))
            .collect();
        q.write_buffer(&slot.taps, slot.pos_at, bytemuck::cast_slice(&posv));
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("filters"),
            timestamp_writes: None,
        });
        for &(k, rec, gx, gy) in &slot.calls {
            pass.set_pipeline(match k {
                Kernel::Conv => &self.conv,
                Kernel::Product => &self.product,
                Kernel::Assemble => &self.assemble,
            });
            pass.set_bind_group(0, &slot.bind, &[rec * RECORD as u32]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        Ok(())
    }

    /// The features of brick `b` as [`neuvolex_filters::compute`] gives them for
    /// [`neuvolex_filters::Classic::Filters`] (then the position with `xyz`): `voxels x
    /// channels`, voxel-major, x fastest. Blocking; for tests and one-off bricks.
    pub fn compute(&self, b: &HaloBrick, norm: &Normaliser, dims: [usize; 3]) -> Result<Vec<f32>> {
        let slot = self.slot(b.size, b.halo)?;
        let mut enc = self.dev.device.create_command_encoder(&Default::default());
        self.encode(&slot, &mut enc, b, norm, dims)?;
        self.dev.queue.submit([enc.finish()]);
        let bytes = self.dev.read(&slot.features, slot.features.size())?;
        let planes: Vec<f32> = bytemuck::pod_collect_to_vec(&bytes);
        let core: usize = b.size.iter().product();
        let ch = self.channels();
        let mut out = vec![0.0f32; core * ch];
        for (c, plane) in planes.chunks_exact(core).take(ch).enumerate() {
            for (v, &x) in plane.iter().enumerate() {
                out[v * ch + c] = x;
            }
        }
        Ok(out)
    }
}
