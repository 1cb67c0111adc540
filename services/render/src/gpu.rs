//! The wgpu renderer: the same brick-ordered algorithm as the CPU renderer, as a compute shader
//! (`shaders/raymarch.wgsl`).
//!
//! Bricks stay resident on the GPU between frames, in an atlas of storage-buffer pages (each
//! within the device's binding limit) cut into slots of one padded brick, under a byte budget
//! with least-recently-used eviction. A frame loads and uploads only the bricks it draws that are
//! not resident; what changes per frame (parameters, the brick list, cell flags, transfer
//! tables) is written into persistent buffers, the accumulators are cleared on the GPU, and the
//! readback buffer and bind groups are reused. Each run of bricks, in visibility order, that
//! shares a page is one dispatch compositing into the same accumulators, so volumes larger than
//! one buffer, or than the budget, still render (evicting as they go).
//!
//! Resident bricks are known by index, as the CPU renderer's cache knows them: after bricks'
//! data changed, [`GpuRenderer::invalidate`] drops them and their neighbours (whose aprons hold
//! their voxels); a change of the source's classes or geometry rebuilds the atlas.
//! It needs no window: any adapter works, including software ones (lavapipe, llvmpipe).

use crate::image::Image;
use crate::march::{Frame, RenderParams};
use crate::source::{neighbourhood, BrickSource, RenderBrick, VolumeGeom, APRON};
use crate::tf::{Luts, LUT_SIZE};
use crate::{Mode, Projection, RenderError, Result};
use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use std::collections::HashMap;
use std::time::Instant;

/// The shader source.
pub const SHADER: &str = include_str!("../../../shaders/raymarch.wgsl");

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    eye: [f32; 4],
    forward: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    inv_spacing: [f32; 4],
    centre: [f32; 4],
    vol_hi: [f32; 4],
    view: [f32; 4],
    misc: [f32; 4],
    shade: [f32; 4],
    size: [u32; 4],
    cfg: [u32; 4],
    geom: [u32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Entry {
    index: [u32; 4],
    size: [u32; 4],
    rect: [u32; 4],
    lo: [f32; 4],
    hi: [f32; 4],
    cells: [u32; 4],
}

fn v4(v: [f32; 3]) -> [f32; 4] {
    [v[0], v[1], v[2], 0.0]
}

/// Bytes of bricks a renderer keeps resident on the GPU by default
/// ([`GpuRenderer::set_resident_bytes`]); fewer where the device runs out of memory first.
pub const DEFAULT_RESIDENT_BYTES: u64 = 4 << 30;

/// What the last frame of a [`GpuRenderer`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GpuStats {
    /// Bricks drawn.
    pub drawn: usize,
    /// Bricks loaded from the source (first seen, not resident, or evicted).
    pub loaded: usize,
    /// Bricks uploaded into the atlas.
    pub uploaded: usize,
    /// Bytes of brick data uploaded (0 when every drawn brick was resident).
    pub brick_bytes: u64,
    /// Bytes of per-frame data written: parameters, brick lists, cell flags, tables.
    pub frame_bytes: u64,
    /// Resident bricks evicted to make room.
    pub evicted: usize,
    /// Dispatches (runs of bricks in one atlas page).
    pub batches: usize,
    /// Bricks resident after the frame.
    pub resident: usize,
}

/// What the atlas was built for; a change rebuilds it.
#[derive(Clone, PartialEq)]
struct Layout {
    geom: VolumeGeom,
    /// Class ids of the probabilities held (empty: intensity only).
    ids: Vec<u32>,
    max_binding: u64,
    budget: u64,
}

/// One storage buffer of intensity slots and one of probability slots.
struct Page {
    ints: wgpu::Buffer,
    probs: wgpu::Buffer,
    /// The brick in each slot.
    owner: Vec<Option<[usize; 3]>>,
    free: Vec<usize>,
    /// Made on first use, dropped when a shared buffer is replaced.
    bind: Option<wgpu::BindGroup>,
}

/// A brick seen by the renderer: its ranges (the voxels taken out) and where it is resident.
struct Known {
    meta: RenderBrick,
    slot: Option<(usize, usize)>,
    /// Clock of the batch that last drew it.
    used: u64,
}

/// Resident bricks.
#[derive(Default)]
struct Atlas {
    layout: Option<Layout>,
    /// f32s of intensity a slot holds.
    islot: u64,
    /// Bytes of probabilities a slot holds (a multiple of 4).
    pslot: u64,
    per_page: usize,
    /// Slots allowed in all (the budget, at most one per brick of the grid).
    max_slots: usize,
    pages: Vec<Page>,
    known: HashMap<[usize; 3], Known>,
}

impl Atlas {
    fn new(layout: Layout) -> Self {
        let g = layout.geom;
        let islot = [0, 1, 2]
            .map(|k| (g.brick.min(g.dims[k]) + 2 * APRON) as u64)
            .iter()
            .product::<u64>();
        let pslot = (islot * layout.ids.len() as u64).div_ceil(4) * 4;
        // Offsets are u32 in the shader (probabilities in bytes).
        let page = layout.max_binding.min(u32::MAX as u64 & !3);
        let fit = |b: u64| page.checked_div(b).map_or(usize::MAX, |n| n as usize);
        let per_page = fit(islot * 4).min(fit(pslot)).max(1);
        let grid: usize = g.grid().iter().product();
        let max_slots = ((layout.budget / (islot * 4 + pslot)) as usize).clamp(1, grid.max(1));
        Atlas {
            layout: Some(layout),
            islot,
            pslot,
            per_page,
            max_slots,
            pages: Vec::new(),
            known: HashMap::new(),
        }
    }

    fn slots(&self) -> usize {
        self.pages.iter().map(|p| p.owner.len()).sum()
    }

    /// Frees the slot of `index` and forgets it.
    fn remove(&mut self, index: &[usize; 3]) {
        if let Some(Known {
            slot: Some((p, s)), ..
        }) = self.known.remove(index)
        {
            self.pages[p].owner[s] = None;
            self.pages[p].free.push(s);
        }
    }

    /// The least recently used resident brick not drawn by the open batch (`clock`).
    fn victim(&self, clock: u64) -> Option<[usize; 3]> {
        self.pages
            .iter()
            .flat_map(|p| p.owner.iter().flatten())
            .filter_map(|i| Some((self.known.get(i)?.used, *i)))
            .filter(|&(u, _)| u < clock)
            .min()
            .map(|(_, i)| i)
    }
}

/// A buffer grown on demand.
struct Grow {
    buf: wgpu::Buffer,
    cap: u64,
    label: &'static str,
}

impl Grow {
    fn new(dev: &wgpu::Device, label: &'static str, usage: wgpu::BufferUsages, cap: u64) -> Self {
        let buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: cap,
            usage,
            mapped_at_creation: false,
        });
        Grow { buf, cap, label }
    }

    /// Makes room for `need` bytes; true when the buffer was replaced (its contents lost).
    fn reserve(&mut self, dev: &wgpu::Device, need: u64) -> bool {
        if need <= self.cap {
            return false;
        }
        let cap = need.next_power_of_two().max(256);
        *self = Grow::new(dev, self.label, self.buf.usage(), cap);
        true
    }
}

/// The persistent per-frame buffers.
struct Buffers {
    params: wgpu::Buffer,
    entries: Grow,
    cells: Grow,
    luts: Grow,
    info: Grow,
    acc: Grow,
    read: Grow,
}

/// A padded brick's voxels, to upload.
type Voxels = (Vec<f32>, Vec<u8>);

/// Splits a loaded brick into its ranges and its voxels.
fn split(mut b: RenderBrick) -> (RenderBrick, Voxels) {
    let v = (
        std::mem::take(&mut b.intensity),
        std::mem::take(&mut b.probs),
    );
    (b, v)
}

/// A wgpu renderer over a brick source, keeping bricks resident on the GPU between frames.
pub struct GpuRenderer<S: BrickSource> {
    source: S,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    adapter: String,
    max_binding: u64,
    budget: u64,
    atlas: Atlas,
    bufs: Buffers,
    /// Advanced per batch: bricks drawn by the open batch are not evicted.
    clock: u64,
    /// Seconds of the last frame: (loading bricks, GPU work with uploads, total).
    pub last_seconds: (f64, f64, f64),
    /// What the last frame did (uploads, evictions, dispatches).
    pub last_stats: GpuStats,
}

fn gpu_err(e: impl std::fmt::Display) -> RenderError {
    RenderError::Gpu(e.to_string())
}

impl<S: BrickSource> GpuRenderer<S> {
    /// Opens the best adapter wgpu finds (hardware preferred; `NEUVOLEX_GPU_ADAPTER` narrows
    /// by name, as for the other GPU engines) and compiles the shader.
    pub fn new(source: S) -> Result<Self> {
        let gpu = neuvolex_gpu::GpuDevice::new(neuvolex_gpu::AdapterKind::Any).map_err(|e| {
            gpu_err(format!(
                "{e}; install a Vulkan driver (e.g. mesa-vulkan-drivers) or use the CPU renderer"
            ))
        })?;
        Self::on(&gpu, source)
    }

    /// Compiles the shader on an open device, which other engines of the process (the INR,
    /// classification) may share.
    pub fn on(gpu: &neuvolex_gpu::GpuDevice, source: S) -> Result<Self> {
        gpu.require_storage_buffers(7).map_err(gpu_err)?;
        let (device, queue) = (gpu.device.clone(), gpu.queue.clone());
        // One uniform (binding 0), then entries, ints, probs, luts, class info (read), the
        // accumulation buffer (written) and the cells (read).
        let (pipeline, layout) = gpu
            .compute_pipeline(
                "raymarch",
                SHADER,
                "main",
                &[true, true, true, true, true, false, true],
            )
            .map_err(gpu_err)?;
        let max_binding = gpu.max_binding();
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let bufs = Buffers {
            params: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("params"),
                size: std::mem::size_of::<Params>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            entries: Grow::new(&device, "entries", storage, 256),
            cells: Grow::new(&device, "cells", storage, 256),
            luts: Grow::new(&device, "luts", storage, 256),
            info: Grow::new(&device, "classinfo", storage, 256),
            acc: Grow::new(
                &device,
                "acc",
                // Cleared on the GPU each frame (`clear_buffer` needs COPY_DST).
                wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
                256,
            ),
            read: Grow::new(
                &device,
                "readback",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                256,
            ),
        };
        Ok(GpuRenderer {
            source,
            device,
            queue,
            pipeline,
            layout,
            adapter: gpu.describe(),
            max_binding,
            budget: DEFAULT_RESIDENT_BYTES,
            atlas: Atlas::default(),
            bufs,
            clock: 0,
            last_seconds: (0.0, 0.0, 0.0),
            last_stats: GpuStats::default(),
        })
    }

    /// Adapter name, backend and type.
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// Caps the bytes of one atlas page (default: the device's binding limit), forcing more
    /// pages and batches; for tests of volumes larger than one buffer. Rebuilds the atlas.
    pub fn set_max_batch_bytes(&mut self, bytes: u64) {
        self.max_binding = bytes.max(1024);
    }

    /// Caps the bytes of bricks kept resident (default [`DEFAULT_RESIDENT_BYTES`], at least one
    /// brick); a frame drawing more evicts as it goes. Rebuilds the atlas.
    pub fn set_resident_bytes(&mut self, bytes: u64) {
        self.budget = bytes;
    }

    /// The source.
    pub fn source(&self) -> &S {
        &self.source
    }

    /// The source, to change it; follow with [`Self::invalidate`] for the bricks whose data
    /// changed.
    pub fn source_mut(&mut self) -> &mut S {
        &mut self.source
    }

    /// Forgets the resident copies of `changed` bricks and of their neighbours (whose aprons
    /// hold their voxels) after their data changed, as [`crate::Renderer::invalidate`]; the
    /// next frame loads and uploads them again.
    pub fn invalidate(&mut self, changed: &[[usize; 3]]) -> Result<()> {
        let g = self.source.geom().grid();
        if let Some(c) = changed.iter().find(|c| (0..3).any(|k| c[k] >= g[k])) {
            return Err(RenderError::Input(format!(
                "changed brick {c:?} outside the {g:?} grid"
            )));
        }
        self.source.invalidate(changed);
        for c in changed {
            for n in neighbourhood(*c, g) {
                self.atlas.remove(&n);
            }
        }
        Ok(())
    }

    /// Renders a frame.
    pub fn render(&mut self, params: &RenderParams, luts: &Luts) -> Result<Image> {
        let t_all = Instant::now();
        let geom = self.source.geom();
        let frame = Frame::new(*params, geom, luts)?;
        let (w, h) = (params.width, params.height);
        let probs = params.mode.needs_probs();
        let mut stats = GpuStats::default();
        let held = self.prepare_atlas(geom, probs);
        let ch = if probs { held } else { 0 };
        // Plan: on-screen, possibly visible bricks in order; those not known, or visible and not
        // resident, are loaded in parallel.
        let t_load = Instant::now();
        let planned: Vec<([usize; 3], [usize; 4])> = frame
            .ordered_bricks()
            .into_iter()
            .filter_map(|i| {
                let r = frame.footprint(i, 0.0)?;
                match self.source.coarse_range(i) {
                    Some(range) if !frame.coarse_visible(range) => None,
                    _ => Some((i, r)),
                }
            })
            .collect();
        let need: Vec<[usize; 3]> = planned
            .iter()
            .map(|p| p.0)
            .filter(|i| {
                self.atlas
                    .known
                    .get(i)
                    .is_none_or(|k| k.slot.is_none() && frame.visible(&k.meta))
            })
            .collect();
        let loaded: Vec<Result<RenderBrick>> =
            need.par_iter().map(|&i| self.load(i, held)).collect();
        let mut fresh: HashMap<[usize; 3], Voxels> = HashMap::new();
        for b in loaded {
            let (meta, vox) = split(b?);
            stats.loaded += 1;
            if frame.visible(&meta) {
                fresh.insert(meta.index, vox);
            }
            match self.atlas.known.get_mut(&meta.index) {
                Some(k) => k.meta = meta,
                None => {
                    let k = Known {
                        meta,
                        slot: None,
                        used: 0,
                    };
                    self.atlas.known.insert(k.meta.index, k);
                }
            }
        }
        let draw: Vec<([usize; 3], [usize; 4])> = planned
            .into_iter()
            .filter(|(i, _)| {
                self.atlas
                    .known
                    .get(i)
                    .is_some_and(|k| frame.visible(&k.meta))
            })
            .collect();
        let load_s = t_load.elapsed().as_secs_f64();
        // Per-frame tables.
        let t_gpu = Instant::now();
        let params_u = self.params(&frame, luts, ch);
        let (lut_data, info) = tables(&frame, luts, ch);
        let acc_bytes = (w * h * 16) as u64;
        let (lut_bytes, info_bytes): (&[u8], &[u8]) =
            (bytemuck::cast_slice(&lut_data), bytemuck::cast_slice(&info));
        let b = &mut self.bufs;
        let dev = &self.device;
        let replaced = b.luts.reserve(dev, lut_bytes.len() as u64)
            | b.info.reserve(dev, info_bytes.len() as u64)
            | b.acc.reserve(dev, acc_bytes);
        b.read.reserve(dev, acc_bytes);
        if replaced {
            self.unbind();
        }
        self.queue.write_buffer(&self.bufs.luts.buf, 0, lut_bytes);
        self.queue.write_buffer(&self.bufs.info.buf, 0, info_bytes);
        stats.frame_bytes += (lut_bytes.len() + info_bytes.len()) as u64;
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&self.bufs.acc.buf, 0, Some(acc_bytes));
        let mut open = Open {
            enc: Some(enc),
            batch: Vec::new(),
            page: None,
        };
        // Runs of bricks in one page, each a dispatch; bricks not resident are uploaded into
        // free slots, new pages, or the least recently used slots.
        self.clock += 1;
        for (i, r) in draw {
            let slot = self.atlas.known.get(&i).and_then(|k| k.slot);
            let (p, s) = match slot {
                Some(ps) => ps,
                None => {
                    let vox = match fresh.remove(&i) {
                        Some(v) => v,
                        // Evicted earlier in this frame (the frame draws more than the budget).
                        None => {
                            stats.loaded += 1;
                            split(self.load(i, held)?).1
                        }
                    };
                    let ps = loop {
                        match self.alloc(open.page, &mut stats)? {
                            Some(ps) => break ps,
                            None if open.batch.is_empty() => {
                                return Err(gpu_err("the brick atlas has no slot"))
                            }
                            // Every slot is drawn by the open batch: dispatch it first.
                            None => self.flush(&frame, params_u, &mut open, &mut stats)?,
                        }
                    };
                    self.upload(i, ps, &vox, &mut stats)?;
                    ps
                }
            };
            if open.page.is_some_and(|q| q != p) {
                self.flush(&frame, params_u, &mut open, &mut stats)?;
            }
            open.page = Some(p);
            open.batch.push((i, r, s));
            if let Some(k) = self.atlas.known.get_mut(&i) {
                k.used = self.clock;
            }
            stats.drawn += 1;
        }
        if !open.batch.is_empty() {
            self.flush(&frame, params_u, &mut open, &mut stats)?;
        }
        let acc = self.read_back(open.enc.take(), acc_bytes)?;
        let gpu_s = t_gpu.elapsed().as_secs_f64();
        let bg = params.background;
        let img = Image {
            width: w,
            height: h,
            rgb: acc
                .iter()
                .map(|a| [0, 1, 2].map(|k| a[k] + (1.0 - a[3]) * bg[k]))
                .collect(),
            alpha: acc.iter().map(|a| a[3]).collect(),
        };
        stats.resident = self
            .atlas
            .known
            .values()
            .filter(|k| k.slot.is_some())
            .count();
        self.last_seconds = (load_s, gpu_s, t_all.elapsed().as_secs_f64());
        self.last_stats = stats;
        tracing::debug!(?stats, load_s, gpu_s, "gpu frame");
        Ok(img)
    }

    /// Keeps the atlas if it fits this frame, else starts an empty one; returns the
    /// probability channels it holds. The atlas holds probabilities of the current classes, or
    /// none; an intensity frame keeps one that holds probabilities (and loads its new bricks
    /// with them).
    fn prepare_atlas(&mut self, geom: VolumeGeom, probs: bool) -> usize {
        let ids: Vec<u32> = self.source.classes().iter().map(|c| c.0).collect();
        let keep = self.atlas.layout.as_ref().is_some_and(|l| {
            l.geom == geom
                && l.max_binding == self.max_binding
                && l.budget == self.budget
                && (l.ids == ids || (!probs && l.ids.is_empty()))
        });
        if !keep {
            self.atlas = Atlas::new(Layout {
                geom,
                ids: if probs { ids } else { Vec::new() },
                max_binding: self.max_binding,
                budget: self.budget,
            });
        }
        self.atlas.layout.as_ref().map_or(0, |l| l.ids.len())
    }

    /// Submits `enc` (or a new encoder) with the copy of the accumulators to the readback
    /// buffer, and returns the first `acc_bytes` of them.
    fn read_back(
        &mut self,
        enc: Option<wgpu::CommandEncoder>,
        acc_bytes: u64,
    ) -> Result<Vec<[f32; 4]>> {
        let mut enc =
            enc.unwrap_or_else(|| self.device.create_command_encoder(&Default::default()));
        enc.copy_buffer_to_buffer(&self.bufs.acc.buf, 0, &self.bufs.read.buf, 0, acc_bytes);
        self.queue.submit([enc.finish()]);
        let slice = self.bufs.read.buf.slice(..acc_bytes);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(gpu_err)?;
        rx.recv().map_err(gpu_err)?.map_err(gpu_err)?;
        let acc: Vec<[f32; 4]> = {
            let view = slice.get_mapped_range().map_err(gpu_err)?;
            bytemuck::cast_slice(&view).to_vec()
        };
        self.bufs.read.buf.unmap();
        Ok(acc)
    }

    /// Brick `index` from the source, with the atlas's `ch` probability channels.
    fn load(&self, index: [usize; 3], ch: usize) -> Result<RenderBrick> {
        let b = self.source.load(index, ch > 0)?;
        if ch > 0 && b.channels != ch {
            return Err(RenderError::Input(format!(
                "brick {index:?} has {} probability channels, the source's classes {ch}; \
                 the classes changed during the frame",
                b.channels
            )));
        }
        Ok(b)
    }

    /// Drops every page's bind group (a shared buffer was replaced).
    fn unbind(&mut self) {
        for p in &mut self.atlas.pages {
            p.bind = None;
        }
    }

    /// A free slot, preferring page `cur`; else a new page within the budget; else the least
    /// recently used slot no open-batch brick holds; `None` when every slot is in the open batch.
    fn alloc(
        &mut self,
        cur: Option<usize>,
        stats: &mut GpuStats,
    ) -> Result<Option<(usize, usize)>> {
        let a = &mut self.atlas;
        let order = cur.into_iter().chain(0..a.pages.len());
        for p in order {
            if let Some(s) = a.pages[p].free.pop() {
                return Ok(Some((p, s)));
            }
        }
        let have = a.slots();
        if have < a.max_slots {
            let n = a.per_page.min(a.max_slots - have);
            let dev = &self.device;
            let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
            let mk = |label, size: u64| {
                dev.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: size.max(4),
                    usage,
                    mapped_at_creation: false,
                })
            };
            let scope = dev.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
            let ints = mk("atlas intensity", n as u64 * a.islot * 4);
            let probs = mk("atlas probabilities", n as u64 * a.pslot);
            if let Some(e) = pollster::block_on(scope.pop()) {
                // The device is full: make do with the pages there are.
                if have == 0 {
                    return Err(gpu_err(format!("no GPU memory for a brick atlas: {e}")));
                }
                tracing::warn!(slots = have, "gpu brick atlas capped by device memory: {e}");
                a.max_slots = have;
            } else {
                a.pages.push(Page {
                    ints,
                    probs,
                    owner: vec![None; n],
                    free: (0..n).rev().collect(),
                    bind: None,
                });
                let p = a.pages.len() - 1;
                let s = a.pages[p].free.pop().expect("a new page has free slots");
                return Ok(Some((p, s)));
            }
        }
        let Some(v) = a.victim(self.clock) else {
            return Ok(None);
        };
        let ps = a.known.get_mut(&v).and_then(|k| k.slot.take());
        let Some((p, s)) = ps else {
            return Ok(None);
        };
        a.pages[p].owner[s] = None;
        stats.evicted += 1;
        Ok(Some((p, s)))
    }

    /// Writes brick `index`'s voxels into slot `(page, slot)` and records it there.
    fn upload(
        &mut self,
        index: [usize; 3],
        (p, s): (usize, usize),
        (ints, probs): &Voxels,
        stats: &mut GpuStats,
    ) -> Result<()> {
        let a = &mut self.atlas;
        let ib: &[u8] = bytemuck::cast_slice(ints);
        if ib.len() as u64 > a.islot * 4 || probs.len() as u64 > a.pslot {
            return Err(gpu_err(format!(
                "brick {index:?} does not fit an atlas slot ({} + {} bytes)",
                ib.len(),
                probs.len()
            )));
        }
        let page = &mut a.pages[p];
        self.queue
            .write_buffer(&page.ints, s as u64 * a.islot * 4, ib);
        if !probs.is_empty() {
            let mut pb = probs.clone();
            pb.resize(pb.len().div_ceil(4) * 4, 0);
            self.queue
                .write_buffer(&page.probs, s as u64 * a.pslot, &pb);
        }
        page.owner[s] = Some(index);
        if let Some(k) = a.known.get_mut(&index) {
            k.slot = Some((p, s));
        }
        stats.uploaded += 1;
        stats.brick_bytes += (ib.len() + probs.len()) as u64;
        Ok(())
    }

    /// Dispatches the open batch: its brick list and cell flags, then one compute pass over
    /// its page; the next batch opens with a new clock.
    fn flush(
        &mut self,
        frame: &Frame<'_>,
        mut params: Params,
        open: &mut Open,
        stats: &mut GpuStats,
    ) -> Result<()> {
        let Some(p) = open.page.take() else {
            return Ok(());
        };
        let a = &self.atlas;
        let vis: Vec<Vec<bool>> = open
            .batch
            .par_iter()
            .map(|(i, _, _)| frame.cell_visibility(&a.known[i].meta))
            .collect();
        let mut entries = Vec::with_capacity(open.batch.len());
        let mut cellvis: Vec<u32> = Vec::new();
        for ((i, r, s), v) in open.batch.iter().zip(vis) {
            let b = &a.known[i].meta;
            let off = cellvis.len() as u32;
            cellvis.extend(v.iter().map(|&v| v as u32));
            let (lo, hi) = frame.brick_bounds(*i);
            entries.push(Entry {
                index: [
                    i[0] as u32,
                    i[1] as u32,
                    i[2] as u32,
                    (*s as u64 * a.islot) as u32,
                ],
                size: [
                    b.padded[0] as u32,
                    b.padded[1] as u32,
                    b.padded[2] as u32,
                    (*s as u64 * a.pslot) as u32,
                ],
                rect: r.map(|v| v as u32),
                lo: v4(lo),
                hi: v4(hi),
                cells: [off, b.cells[0] as u32, b.cells[1] as u32, b.cells[2] as u32],
            });
        }
        params.size[2] = entries.len() as u32;
        let (eb, cb): (&[u8], &[u8]) = (
            bytemuck::cast_slice(&entries),
            bytemuck::cast_slice(&cellvis),
        );
        let dev = &self.device;
        let replaced = self.bufs.entries.reserve(dev, eb.len() as u64)
            | self.bufs.cells.reserve(dev, cb.len() as u64);
        if replaced {
            self.unbind();
        }
        let q = &self.queue;
        q.write_buffer(&self.bufs.params, 0, bytemuck::bytes_of(&params));
        q.write_buffer(&self.bufs.entries.buf, 0, eb);
        if !cb.is_empty() {
            q.write_buffer(&self.bufs.cells.buf, 0, cb);
        }
        stats.frame_bytes += (std::mem::size_of::<Params>() + eb.len() + cb.len()) as u64;
        if self.atlas.pages[p].bind.is_none() {
            let bg = self.bind(p);
            self.atlas.pages[p].bind = Some(bg);
        }
        let bg = self.atlas.pages[p].bind.as_ref().expect("bound above");
        let mut enc = open
            .enc
            .take()
            .unwrap_or_else(|| self.device.create_command_encoder(&Default::default()));
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(params.size[0].div_ceil(8), params.size[1].div_ceil(8), 1);
        }
        // Each batch is its own submission: the next batch's writes to the shared buffers
        // (and to slots this batch read) land after it.
        self.queue.submit([enc.finish()]);
        stats.batches += 1;
        open.batch.clear();
        self.clock += 1;
        Ok(())
    }

    /// The bind group of page `p` with the shared buffers.
    fn bind(&self, p: usize) -> wgpu::BindGroup {
        let page = &self.atlas.pages[p];
        let b = &self.bufs;
        let res = [
            b.params.as_entire_binding(),
            b.entries.buf.as_entire_binding(),
            page.ints.as_entire_binding(),
            page.probs.as_entire_binding(),
            b.luts.buf.as_entire_binding(),
            b.info.buf.as_entire_binding(),
            b.acc.buf.as_entire_binding(),
            b.cells.buf.as_entire_binding(),
        ];
        let entries: Vec<wgpu::BindGroupEntry> = res
            .into_iter()
            .enumerate()
            .map(|(n, resource)| wgpu::BindGroupEntry {
                binding: n as u32,
                resource,
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("raymarch"),
            layout: &self.layout,
            entries: &entries,
        })
    }

    fn params(&self, frame: &Frame<'_>, luts: &Luts, ch: usize) -> Params {
        let v = &frame.view;
        let p = &frame.params;
        let s = p.shading.unwrap_or_default();
        let min_sp = frame.dt / p.step;
        Params {
            eye: v4(v.eye),
            forward: v4(v.forward),
            right: v4(v.right),
            up: v4(v.up),
            inv_spacing: v4(frame.inv_spacing()),
            centre: v4(frame.centre()),
            vol_hi: v4(frame.geom.dims.map(|d| d as f32 - 0.5)),
            view: [v.half, v.aspect, frame.dt, frame.alpha_exp],
            misc: [p.ert, min_sp, luts.intensity.lo, luts.intensity.scale],
            shade: [s.ambient, s.diffuse, s.specular, s.shininess],
            size: [
                p.width as u32,
                p.height as u32,
                0,
                match p.mode {
                    Mode::Intensity => 0,
                    Mode::Probabilistic => 1,
                    Mode::ProbIntensity => 2,
                },
            ],
            cfg: [
                (v.projection == Projection::Perspective) as u32,
                p.shading.is_some() as u32,
                ch as u32,
                LUT_SIZE as u32,
            ],
            geom: [frame.geom.brick as u32, APRON as u32, 0, 0],
        }
    }
}

/// The batch being assembled: its bricks (index, pixel rectangle, slot), its page, and the
/// frame's first commands (the accumulators' clear) until a batch takes them.
/// The frame's lookup tables and per-class parameters for `ch` probability channels: the
/// intensity table (its opacity corrected for the step, as on the CPU), then each class's
/// probability and intensity tables; per class (lo, scale) of both and tau.
fn tables(frame: &Frame<'_>, luts: &Luts, ch: usize) -> (Vec<[f32; 4]>, Vec<[f32; 4]>) {
    let mut lut_data: Vec<[f32; 4]> = frame.intensity_lut().table.clone();
    let mut info: Vec<[f32; 4]> = Vec::new();
    for n in 0..ch.max(1) {
        match luts.classes.get(n).and_then(|c| c.as_ref()) {
            Some(c) => {
                lut_data.extend(&c.probability.table);
                lut_data.extend(&c.intensity.table);
                info.push([
                    c.probability.lo,
                    c.probability.scale,
                    c.intensity.lo,
                    c.intensity.scale,
                ]);
                info.push([c.tau, 1.0, 0.0, 0.0]);
            }
            None => {
                lut_data.extend(std::iter::repeat_n([0.0f32; 4], 2 * LUT_SIZE));
                info.push([0.0, 1.0, 0.0, 1.0]);
                info.push([1.0, 0.0, 0.0, 0.0]);
            }
        }
    }
    (lut_data, info)
}

struct Open {
    enc: Option<wgpu::CommandEncoder>,
    batch: Vec<([usize; 3], [usize; 4], usize)>,
    page: Option<usize>,
}
