//! The trained forest on the GPU: [`neuvolex_classify::Forest::flat`] packed into one storage
//! buffer, one invocation per voxel walking every tree (`forest.wgsl`), class probabilities
//! written as u8 as the session stores them ([`neuvolex_classify::stable::to_u8`]) and the
//! label (the first most probable class) as u8.
//!
//! The leaves' fractions add in tree order in f32 and are scaled by `1 / trees` computed on the
//! host, as the CPU forest does, so on a device with IEEE f32 addition and multiplication the
//! probabilities are the CPU's bits and the labels equal [`neuvolex_classify::Forest::predict`].

use crate::device::{grid, GpuDevice, Tracked, STORAGE_BUFFERS};
use crate::error::{GpuError, Result};
use neuvolex_classify::{Forest, LEAF_FEATURE};
use std::sync::Arc;

/// The kernel.
pub const FOREST_WGSL: &str = include_str!("forest.wgsl");

/// Classes the kernel holds per voxel (its accumulators live in registers).
pub const MAX_CLASSES: usize = 16;

/// The label of a voxel whose top probability is below the forest's `tau`
/// ([`GpuForest::with_tau`]).
pub const BELOW_TAU: u8 = 255;

/// Voxels per workgroup: output is written in whole groups.
pub const GROUP: usize = 64;

/// Where a voxel's features lie in a feature buffer, in f32 words: feature `f` of voxel `v`
/// is at `base + v * stride_voxel + f * stride_feature`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FeatureLayout {
    /// Word of voxel 0's feature 0.
    pub base: u32,
    /// Words between consecutive voxels.
    pub stride_voxel: u32,
    /// Words between consecutive features.
    pub stride_feature: u32,
}

impl FeatureLayout {
    /// Voxel-major rows of `d` features (the CPU layout: `rows x d`).
    pub fn rows(d: usize) -> Self {
        FeatureLayout {
            base: 0,
            stride_voxel: d as u32,
            stride_feature: 1,
        }
    }

    /// Feature-major planes of `n` voxels (`d x n`: what the GPU filter bank writes).
    pub fn planes(n: usize) -> Self {
        FeatureLayout {
            base: 0,
            stride_voxel: 1,
            stride_feature: n as u32,
        }
    }
}

/// The kernel's uniform arguments (`Params` in `forest.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    n: u32,
    stride_v: u32,
    stride_f: u32,
    base: u32,
    trees: u32,
    classes: u32,
    depth: u32,
    inv: f32,
    nodes_at: u32,
    probs_at: u32,
    labels_at: u32,
    groups: u32,
    groups_x: u32,
    width: u32,
    tau: f32,
    f16: u32,
}

/// What one prediction gives back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Prediction {
    /// Class probabilities as u8 (255 = 1), `voxels x classes`.
    pub probs: Vec<u8>,
    /// The first most probable class of each voxel.
    pub labels: Vec<u8>,
}

/// A forest resident on the GPU, ready to predict voxels.
pub struct GpuForest {
    dev: Arc<GpuDevice>,
    forest: Tracked,
    pipe: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    d: usize,
    classes: usize,
    trees: u32,
    depth: u32,
    inv: f32,
    nodes_at: u32,
    probs_at: u32,
    tau: f32,
    f16: bool,
}

impl std::fmt::Debug for GpuForest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuForest")
            .field("features", &self.d)
            .field("classes", &self.classes)
            .field("trees", &self.trees)
            .field("bytes", &self.forest.size())
            .finish()
    }
}

impl GpuForest {
    /// Packs `forest` into one storage buffer on `dev` and compiles the kernel. Fails for a
    /// damaged forest, more than [`MAX_CLASSES`] classes, or a forest past the binding limit.
    ///
    /// ```no_run
    /// # use neuvolex_classify::{Dataset, Forest, ForestConfig};
    /// use neuvolex_classify_gpu::{AdapterKind, GpuDevice, GpuForest};
    /// let x = [0.0f32, 1.0, 2.0, 3.0];
    /// let data = Dataset { x: &x, y: &[0, 0, 1, 1], d: 1, classes: 2 };
    /// let forest = Forest::fit(data, &ForestConfig { trees: 4, ..Default::default() }).unwrap();
    /// let gpu = GpuForest::new(GpuDevice::new(AdapterKind::Any)?, &forest)?;
    /// let p = gpu.predict(&[0.5, 2.5])?;
    /// assert_eq!(p.labels, [0, 1]);
    /// # Ok::<(), neuvolex_classify_gpu::GpuError>(())
    /// ```
    pub fn new(dev: Arc<GpuDevice>, forest: &Forest) -> Result<Self> {
        dev.require_storage_buffers(STORAGE_BUFFERS)?;
        let flat = forest.flat()?;
        let c = flat.classes;
        if c > MAX_CLASSES {
            return Err(GpuError::Input(format!(
                "{c} classes; the GPU forest holds at most {MAX_CLASSES}"
            )));
        }
        let width = c.next_multiple_of(4);
        let trees = flat.roots.len();
        let nodes = flat.feature.len();
        let leaves = flat.probs.len() / c;
        let words = trees + 3 * nodes + leaves * width;
        let nodes_at = trees;
        let probs_at = trees + 3 * nodes;
        let too_big = || GpuError::Input(format!("a forest of {words} words"));
        if u32::try_from(words).is_err() {
            return Err(too_big());
        }
        let mut buf: Vec<u32> = Vec::with_capacity(words);
        buf.extend_from_slice(&flat.roots);
        for i in 0..nodes {
            let next = if flat.feature[i] == LEAF_FEATURE {
                // Leaf offsets into the padded fractions.
                flat.next[i] / c as u32 * width as u32
            } else {
                flat.next[i]
            };
            buf.extend_from_slice(&[flat.feature[i], flat.threshold[i].to_bits(), next]);
        }
        for p in flat.probs.chunks_exact(c) {
            buf.extend(p.iter().map(|v| v.to_bits()));
            buf.extend(std::iter::repeat_n(0u32, width - c));
        }
        debug_assert_eq!(buf.len(), words);
        let fbuf = dev.upload(
            "forest",
            bytemuck::cast_slice(&buf),
            wgpu::BufferUsages::STORAGE,
        )?;
        let (pipe, layout) =
            dev.compute_pipeline("forest", FOREST_WGSL, "predict", &[true, true, false])?;
        Ok(GpuForest {
            dev,
            forest: fbuf,
            pipe,
            layout,
            d: flat.features,
            classes: c,
            trees: trees as u32,
            depth: flat.depth,
            inv: 1.0 / trees as f32,
            nodes_at: nodes_at as u32,
            probs_at: probs_at as u32,
            tau: f32::MIN,
            f16: false,
        })
    }

    /// Labels a voxel [`BELOW_TAU`] where its top probability is below `tau` (the f32
    /// probability, compared as `neuvolex_classify::shard::predict_brick` does); by default
    /// (`f32::MIN`) every voxel takes its first most probable class.
    pub fn with_tau(mut self, tau: f32) -> Self {
        self.tau = tau;
        self
    }

    /// Rounds every feature through f16 before comparing it (`true`), as the service's cache
    /// holds features for [`neuvolex_classify::Forest::predict_proba_f16`]
    /// ([`neuvolex_classify::features::f16_saturating`]: clamped to f16's largest finite
    /// magnitude, then to the nearest f16; WGSL leaves a tie's direction to the device where the
    /// CPU rounds ties to even). Default false.
    pub fn with_f16(mut self, f16: bool) -> Self {
        self.f16 = f16;
        self
    }

    /// The device.
    pub fn device(&self) -> &Arc<GpuDevice> {
        &self.dev
    }

    /// Features per voxel.
    pub fn features(&self) -> usize {
        self.d
    }

    /// Classes.
    pub fn classes(&self) -> usize {
        self.classes
    }

    /// Bytes of the forest on the GPU.
    pub fn bytes(&self) -> u64 {
        self.forest.size()
    }

    /// Bytes of the output buffer [`Self::encode`] writes for `n` voxels: the u8
    /// probabilities (`n x classes`, padded to whole groups of [`GROUP`] voxels), then the u8
    /// labels from [`Self::labels_offset`].
    pub fn output_bytes(&self, n: usize) -> u64 {
        let g = n.div_ceil(GROUP).max(1) as u64;
        g * GROUP as u64 * (self.classes as u64 + 1)
    }

    /// Byte offset of the labels in an output buffer for `n` voxels.
    pub fn labels_offset(&self, n: usize) -> u64 {
        n.div_ceil(GROUP).max(1) as u64 * GROUP as u64 * self.classes as u64
    }

    /// Records the prediction of `n` voxels whose features lie in `features` as `layout`
    /// says into `out` (at least [`Self::output_bytes`] bytes, STORAGE). Checks that the
    /// layout's last word lies inside `features`.
    pub fn encode(
        &self,
        enc: &mut wgpu::CommandEncoder,
        features: &wgpu::Buffer,
        layout: FeatureLayout,
        n: usize,
        out: &wgpu::Buffer,
    ) -> Result<()> {
        if n == 0 {
            return Ok(());
        }
        let last = layout.base as u64
            + (n as u64 - 1) * layout.stride_voxel as u64
            + (self.d as u64).saturating_sub(1) * layout.stride_feature as u64;
        if (last + 1) * 4 > features.size() || last >= u32::MAX as u64 {
            return Err(GpuError::Input(format!(
                "{n} voxels of {} features do not fit a feature buffer of {} bytes",
                self.d,
                features.size()
            )));
        }
        if out.size() < self.output_bytes(n) {
            return Err(GpuError::Input(format!(
                "{n} voxels need an output of {} bytes, got {}",
                self.output_bytes(n),
                out.size()
            )));
        }
        let groups = n.div_ceil(GROUP) as u32;
        let (gx, gy) = grid(groups, self.dev.max_groups());
        let p = Params {
            n: n as u32,
            stride_v: layout.stride_voxel,
            stride_f: layout.stride_feature,
            base: layout.base,
            trees: self.trees,
            classes: self.classes as u32,
            depth: self.depth,
            inv: self.inv,
            nodes_at: self.nodes_at,
            probs_at: self.probs_at,
            labels_at: (self.labels_offset(n) / 4) as u32,
            groups,
            groups_x: gx,
            width: self.classes.next_multiple_of(4) as u32,
            tau: self.tau,
            f16: self.f16 as u32,
        };
        let ubuf = self.dev.upload(
            "forest args",
            bytemuck::bytes_of(&p),
            wgpu::BufferUsages::UNIFORM,
        )?;
        let bind = self
            .dev
            .bind(&self.layout, &ubuf, &[&self.forest, features, out]);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("forest"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipe);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
        Ok(())
    }

    /// Predicts the voxel-major rows of `x` (`rows x features`, as
    /// [`neuvolex_classify::Forest::predict_proba`] takes them): uploads them in chunks that fit
    /// a binding, runs the kernel and reads the results back.
    pub fn predict(&self, x: &[f32]) -> Result<Prediction> {
        let d = self.d;
        if d == 0 || !x.len().is_multiple_of(d) {
            return Err(GpuError::Input(format!(
                "{} values are not whole rows of {d} features",
                x.len()
            )));
        }
        let rows = x.len() / d;
        let c = self.classes;
        let per_row = (d * 4).max(c + 1) as u64;
        let chunk =
            ((self.dev.max_binding() / per_row) as usize / GROUP * GROUP).clamp(GROUP, 1 << 22);
        let mut out = Prediction {
            probs: Vec::with_capacity(rows * c),
            labels: Vec::with_capacity(rows),
        };
        for part in x.chunks(chunk * d) {
            let n = part.len() / d;
            let fb = self.dev.upload(
                "features",
                bytemuck::cast_slice(part),
                wgpu::BufferUsages::STORAGE,
            )?;
            let ob = self.dev.buffer(
                "forest out",
                self.output_bytes(n),
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            )?;
            let mut enc = self.dev.device.create_command_encoder(&Default::default());
            self.encode(&mut enc, &fb, FeatureLayout::rows(d), n, &ob)?;
            self.dev.queue.submit([enc.finish()]);
            let bytes = self.dev.read(&ob, self.output_bytes(n))?;
            let lo = self.labels_offset(n) as usize;
            out.probs.extend_from_slice(&bytes[..n * c]);
            out.labels.extend_from_slice(&bytes[lo..lo + n]);
        }
        self.dev.check()?;
        Ok(out)
    }
}
