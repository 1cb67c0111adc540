//! The wgpu renderer: the same brick-ordered algorithm as the CPU renderer, as a compute shader
//! (`shaders/raymarch.wgsl`). Bricks are packed into storage-buffer atlases in batches that fit
//! the device's binding limit; each batch is one dispatch compositing into the same
//! accumulators, so volumes larger than one buffer, or than GPU memory, still render.
//! It needs no window: any adapter works, including software ones (lavapipe, llvmpipe).

use crate::image::Image;
use crate::march::{Frame, RenderParams};
use crate::source::{BrickSource, RenderBrick, APRON};
use crate::tf::{Luts, LUT_SIZE};
use crate::{Mode, Projection, RenderError, Result};
use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use std::time::Instant;
use wgpu::util::DeviceExt;

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

/// A wgpu renderer over a brick source.
pub struct GpuRenderer<S: BrickSource> {
    source: S,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    adapter: String,
    max_binding: u64,
    /// Seconds of the last frame: (loading bricks, GPU work, total).
    pub last_seconds: (f64, f64, f64),
}

fn gpu_err(e: impl std::fmt::Display) -> RenderError {
    RenderError::Gpu(e.to_string())
}

impl<S: BrickSource> GpuRenderer<S> {
    /// Opens the first adapter wgpu finds (hardware preferred; set `WGPU_BACKEND` or
    /// `WGPU_ADAPTER_NAME` to choose) and compiles the shader.
    pub fn new(source: S) -> Result<Self> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        }))
        .map_err(|e| {
            gpu_err(format!(
                "no GPU adapter ({e}); install a Vulkan driver (e.g. mesa-vulkan-drivers) or use the CPU renderer"
            ))
        })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let required = wgpu::Limits {
            max_storage_buffer_binding_size: limits.max_storage_buffer_binding_size,
            max_buffer_size: limits.max_buffer_size,
            max_storage_buffers_per_shader_stage: 7,
            ..wgpu::Limits::downlevel_defaults()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("neuvolex-render"),
            required_features: wgpu::Features::empty(),
            required_limits: required,
            ..Default::default()
        }))
        .map_err(gpu_err)?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("raymarch.wgsl"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
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
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("raymarch"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage(1, true),
                storage(2, true),
                storage(3, true),
                storage(4, true),
                storage(5, true),
                storage(6, false),
                storage(7, true),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("raymarch"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("raymarch"),
            layout: Some(&pl),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let max_binding =
            (limits.max_storage_buffer_binding_size as u64).min(limits.max_buffer_size);
        Ok(GpuRenderer {
            source,
            device,
            queue,
            pipeline,
            layout,
            adapter: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
            max_binding,
            last_seconds: (0.0, 0.0, 0.0),
        })
    }

    /// Adapter name, backend and type.
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// Caps the bytes of one brick atlas (default: the device's binding limit), forcing more
    /// batches; for tests of volumes larger than one buffer.
    pub fn set_max_batch_bytes(&mut self, bytes: u64) {
        self.max_binding = bytes.max(1024);
    }

    /// Renders a frame.
    pub fn render(&mut self, params: &RenderParams, luts: &Luts) -> Result<Image> {
        let t_all = Instant::now();
        let frame = Frame::new(*params, self.source.geom(), luts)?;
        let (w, h) = (params.width, params.height);
        let probs = params.mode.needs_probs();
        // Plan: on-screen, possibly visible bricks in order, loaded in parallel.
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
        let loaded: Vec<Result<(RenderBrick, [usize; 4])>> = planned
            .par_iter()
            .map(|&(i, r)| Ok((self.source.load(i, probs)?, r)))
            .collect();
        let mut bricks = Vec::new();
        for b in loaded {
            let (b, r) = b?;
            if frame.visible(&b) {
                bricks.push((b, r));
            }
        }
        let load_s = t_load.elapsed().as_secs_f64();
        let ch = if probs {
            self.source.classes().len()
        } else {
            0
        };
        let params_u = self.params(&frame, luts, ch);
        // Tables.
        // The intensity mode's table has its opacity corrected for the step, as on the CPU.
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
        let dev = &self.device;
        let buf = |label: &str, data: &[u8], usage| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: data,
                usage,
            })
        };
        let ro = wgpu::BufferUsages::STORAGE;
        let lut_buf = buf("luts", bytemuck::cast_slice(&lut_data), ro);
        let info_buf = buf("classinfo", bytemuck::cast_slice(&info), ro);
        let acc_bytes = (w * h * 16) as u64;
        let acc_buf = buf(
            "acc",
            &vec![0u8; acc_bytes as usize],
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let read_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: acc_bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        // Batches that fit one binding.
        let t_gpu = Instant::now();
        let mut start = 0;
        let mut batches = 0;
        while start < bricks.len() || (start == 0 && batches == 0) {
            let (mut ib, mut pb, mut end) = (0u64, 0u64, start);
            while end < bricks.len() {
                let b = &bricks[end].0;
                let (ni, np) = (
                    b.intensity.len() as u64 * 4,
                    b.probs.len().div_ceil(4) as u64 * 4,
                );
                if end > start && (ib + ni > self.max_binding || pb + np > self.max_binding) {
                    break;
                }
                ib += ni;
                pb += np;
                end += 1;
            }
            self.dispatch(
                &bricks[start..end],
                &frame,
                params_u,
                ch,
                &lut_buf,
                &info_buf,
                &acc_buf,
            )?;
            batches += 1;
            start = end;
            if bricks.is_empty() {
                break;
            }
        }
        let mut enc = dev.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(&acc_buf, 0, &read_buf, 0, acc_bytes);
        self.queue.submit([enc.finish()]);
        let slice = read_buf.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        dev.poll(wgpu::PollType::wait_indefinitely())
            .map_err(gpu_err)?;
        rx.recv().map_err(gpu_err)?.map_err(gpu_err)?;
        let acc: Vec<[f32; 4]> =
            bytemuck::cast_slice(&slice.get_mapped_range().map_err(gpu_err)?).to_vec();
        read_buf.unmap();
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
        self.last_seconds = (load_s, gpu_s, t_all.elapsed().as_secs_f64());
        tracing::debug!(batches, bricks = bricks.len(), load_s, gpu_s, "gpu frame");
        Ok(img)
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

    #[allow(clippy::too_many_arguments)]
    fn dispatch(
        &self,
        batch: &[(RenderBrick, [usize; 4])],
        frame: &Frame<'_>,
        mut params: Params,
        ch: usize,
        lut_buf: &wgpu::Buffer,
        info_buf: &wgpu::Buffer,
        acc_buf: &wgpu::Buffer,
    ) -> Result<()> {
        let mut ints: Vec<f32> = Vec::new();
        let mut probs: Vec<u8> = Vec::new();
        let mut entries = Vec::with_capacity(batch.len().max(1));
        let mut cellvis: Vec<u32> = Vec::new();
        for (b, r) in batch {
            let off = cellvis.len() as u32;
            cellvis.extend(frame.cell_visibility(b).iter().map(|&v| v as u32));
            let (lo, hi) = frame.brick_bounds(b.index);
            entries.push(Entry {
                index: [
                    b.index[0] as u32,
                    b.index[1] as u32,
                    b.index[2] as u32,
                    ints.len() as u32,
                ],
                size: [
                    b.padded[0] as u32,
                    b.padded[1] as u32,
                    b.padded[2] as u32,
                    probs.len() as u32,
                ],
                rect: r.map(|v| v as u32),
                lo: v4(lo),
                hi: v4(hi),
                cells: [off, b.cells[0] as u32, b.cells[1] as u32, b.cells[2] as u32],
            });
            ints.extend_from_slice(&b.intensity);
            if ch > 0 {
                probs.extend_from_slice(&b.probs);
                probs.resize(probs.len().div_ceil(4) * 4, 0);
            }
        }
        params.size[2] = batch.len() as u32;
        // Bindings may not be empty.
        if entries.is_empty() {
            entries.push(Entry::zeroed());
        }
        if ints.is_empty() {
            ints.push(0.0);
        }
        if cellvis.is_empty() {
            cellvis.push(0);
        }
        probs.resize(probs.len().max(4).div_ceil(4) * 4, 0);
        let dev = &self.device;
        let buf = |label: &str, data: &[u8], usage| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: data,
                usage,
            })
        };
        let ub = buf(
            "params",
            bytemuck::bytes_of(&params),
            wgpu::BufferUsages::UNIFORM,
        );
        let eb = buf(
            "entries",
            bytemuck::cast_slice(&entries),
            wgpu::BufferUsages::STORAGE,
        );
        let ib = buf(
            "intensity",
            bytemuck::cast_slice(&ints),
            wgpu::BufferUsages::STORAGE,
        );
        let pb = buf("probs", &probs, wgpu::BufferUsages::STORAGE);
        let cb = buf(
            "cells",
            bytemuck::cast_slice(&cellvis),
            wgpu::BufferUsages::STORAGE,
        );
        let bg = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("raymarch"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: ub.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: eb.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: ib.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: pb.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: lut_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: info_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 6,
                    resource: acc_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: cb.as_entire_binding(),
                },
            ],
        });
        let mut enc = dev.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(
                (params.size[0]).div_ceil(8),
                (params.size[1]).div_ceil(8),
                1,
            );
        }
        self.queue.submit([enc.finish()]);
        Ok(())
    }
}
