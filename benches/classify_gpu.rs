//! A whole round of classification on the GPU (`cargo bench -p neuvolex-benches --features gpu
//! --bench classify_gpu -- [options]`, or the built binary run directly on a device): the
//! generated CT-like phantom (512x512x452 by default, 118.5 M voxels) streamed brick by brick
//! through upload -> filter bank -> forest -> read back with a bounded number of bricks in
//! flight, against the CPU path (`neuvolex_filters::compute` + `Forest::predict_proba`, the
//! session's per-brick work) on the same machine in the same run.
//!
//! Steps, each printed as it ends (a run cut short by a time limit still shows the rest):
//! 1. the phantom, generated in memory (rayon over slices; not timed as classification);
//! 2. a forest of `--trees` trees (default 32: the session's `trees_for` a volume this size)
//!    trained on `--train-rows` voxels of nine bricks spread over the volume (CPU features,
//!    the phantom's labels);
//! 3. the GPU path over every brick: bricks of `--brick` voxels (default 128) with the filter
//!    bank's halo, padded to whole bricks at the volume's far ends; the host reads and normalises
//!    each halo brick (rayon) ahead of the GPU, `--in-flight` bricks (default 2) share the GPU
//!    ring, the u8 probabilities and labels come back per brick; voxels/s, whole-volume seconds,
//!    peak GPU buffer bytes, and one brick's filter and forest times apart;
//! 4. the CPU path on `--cpu-bricks` of the same bricks (default 4; `all` for every brick),
//!    timed, its voxels/s and the whole volume's seconds extrapolated from them (marked so), and
//!    the labels' agreement with the GPU's on those bricks.
//!
//! Options: `--dims X,Y,Z` (default 512,512,452), `--brick B`, `--in-flight K`, `--trees T`,
//! `--train-rows R` (default 20000), `--cpu-bricks N|all`, `--software` (allow a software
//! adapter: lavapipe, for a dry run; its times are no evidence of speed; without a GPU the GPU
//! path is skipped and the CPU path still runs), `--out FILE` (the JSON report, written after
//! each step). No data files are read. `NEUVOLEX_GPU_ADAPTER`
//! picks an adapter by name.

#[cfg(feature = "gpu")]
fn main() {
    gpu::main()
}

#[cfg(not(feature = "gpu"))]
fn main() {
    println!("SKIP: classify_gpu needs --features gpu");
}

#[cfg(feature = "gpu")]
mod gpu {
    use neuvolex_bricks::derived::{halo_from_volume, Normaliser};
    use neuvolex_bricks::rng::Rng;
    use neuvolex_bricks::synth::{phantom_at, Phantom, PhantomChannel, PhantomParams};
    use neuvolex_classify::stable::to_u8;
    use neuvolex_classify::{Dataset, Forest, ForestConfig};
    use neuvolex_classify_gpu::{
        wgpu, AdapterKind, FeatureLayout, GpuDevice, GpuFilterBank, GpuForest,
    };
    use neuvolex_filters::{compute, filter_halo, pos, Classic};
    use neuvolex_formats::VolumeSource;
    use rayon::prelude::*;
    use serde_json::{json, Value};
    use std::sync::mpsc::sync_channel;
    use std::time::Instant;

    fn arg<T: std::str::FromStr>(args: &[String], flag: &str, default: T) -> T {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    }

    fn write(out: &Option<String>, report: &Value) {
        if let Some(p) = out {
            match serde_json::to_string_pretty(report) {
                Ok(s) => {
                    if let Err(e) = std::fs::write(p, s) {
                        eprintln!("cannot write {p}: {e}");
                    }
                }
                Err(e) => eprintln!("report: {e}"),
            }
        }
    }

    /// The phantom's intensities (and labels where asked) over slices `z0..z1`, x fastest.
    fn slices(params: PhantomParams, ch: PhantomChannel, z0: usize, z1: usize) -> Vec<f32> {
        let d = params.dims;
        let mut v = vec![0.0f32; d[0] * d[1] * (z1 - z0)];
        v.par_chunks_mut(d[0] * d[1])
            .enumerate()
            .for_each(|(k, s)| {
                let mut src = Phantom::new(params, ch);
                let slab = src.read_slab(z0 + k, 1).expect("phantom slice");
                s.copy_from_slice(&slab.to_f32_scaled(src.meta()));
            });
        v
    }

    /// A strided sample's 0.5 and 99.5 percentiles, as the store's robust normaliser.
    fn normaliser(v: &[f32]) -> Normaliser {
        let mut s: Vec<f32> = v.iter().step_by(61).copied().collect();
        s.sort_by(|a, b| a.total_cmp(b));
        let q = |f: f64| s[((s.len() - 1) as f64 * f) as usize] as f64;
        let (lo, hi) = (q(0.005), q(0.995));
        if hi > lo {
            Normaliser { lo, hi }
        } else {
            Normaliser {
                lo: s[0] as f64,
                hi: s[s.len() - 1] as f64,
            }
        }
    }

    /// `filters+xyz` of a brick on the CPU (voxel-major), as the session computes it.
    fn cpu_features(
        v: &[f32],
        dims: [usize; 3],
        o: [usize; 3],
        s: [usize; 3],
        norm: &Normaliser,
    ) -> Vec<f32> {
        let hb = halo_from_volume(v, dims, o, s, filter_halo());
        let bank = compute(Classic::Filters, &hb, norm, dims);
        let ch = Classic::Filters.channels();
        let mut out = Vec::with_capacity(bank.len() / ch * (ch + 3));
        let mut i = 0;
        for z in 0..s[2] {
            for y in 0..s[1] {
                for x in 0..s[0] {
                    out.extend_from_slice(&bank[i * ch..(i + 1) * ch]);
                    out.extend([
                        pos(o[0] + x, dims[0]),
                        pos(o[1] + y, dims[1]),
                        pos(o[2] + z, dims[2]),
                    ]);
                    i += 1;
                }
            }
        }
        out
    }

    pub fn main() {
        let args: Vec<String> = std::env::args().collect();
        let dims: Vec<usize> = arg(&args, "--dims", "512,512,452".to_string())
            .split(',')
            .filter_map(|v| v.trim().parse().ok())
            .collect();
        let dims: [usize; 3] = match dims.as_slice() {
            &[x, y, z] if x > 0 && y > 0 && z > 0 => [x, y, z],
            _ => {
                eprintln!("--dims wants X,Y,Z");
                std::process::exit(2);
            }
        };
        let brick: usize = arg(&args, "--brick", 128usize).max(8);
        let in_flight: usize = arg(&args, "--in-flight", 2usize).max(1);
        let trees: usize = arg(&args, "--trees", 32usize).max(1);
        let train_rows: usize = arg(&args, "--train-rows", 20000usize).max(100);
        let cpu_all = args
            .iter()
            .position(|a| a == "--cpu-bricks")
            .and_then(|i| args.get(i + 1))
            .is_some_and(|v| v == "all");
        let cpu_bricks: usize = arg(&args, "--cpu-bricks", 4usize);
        let software = args.iter().any(|a| a == "--software");
        let out: Option<String> = args
            .iter()
            .position(|a| a == "--out")
            .and_then(|i| args.get(i + 1))
            .cloned();
        let voxels: usize = dims.iter().product();
        let mut report = json!({
            "bench": "classify_gpu",
            "dims": dims, "voxels": voxels, "brick": brick, "halo": filter_halo(),
            "in_flight": in_flight, "trees": trees, "features": "filters+xyz",
            "threads": rayon::current_num_threads(),
        });
        println!(
            "classify_gpu: {dims:?} ({:.1} M voxels), bricks of {brick} + halo {}, {in_flight} \
             in flight, {trees} trees, {} CPU threads",
            voxels as f64 / 1e6,
            filter_halo(),
            rayon::current_num_threads()
        );

        // 1. The phantom.
        let t = Instant::now();
        let params = PhantomParams {
            dims,
            seed: 0,
            noise: 18.0,
        };
        let vol = slices(params, PhantomChannel::Image, 0, dims[2]);
        let norm = normaliser(&vol);
        let gen_s = t.elapsed().as_secs_f64();
        println!(
            "phantom generated in {gen_s:.1} s; normaliser {:.1}..{:.1}",
            norm.lo, norm.hi
        );
        report["phantom_s"] = json!(gen_s);
        write(&out, &report);

        // 2. The forest, trained on nine bricks spread over the volume (the centre and the
        // corners of its middle third), with the phantom's labels.
        let t = Instant::now();
        let s = dims.map(|d| d.min(24));
        let label_at = |p: [usize; 3]| -> u8 {
            // The phantom source's coordinates (y flipped).
            let c = |i: usize, n: usize| {
                if n <= 1 {
                    0.0
                } else {
                    2.0 * (i as f64 + 0.5) / n as f64 - 1.0
                }
            };
            phantom_at([c(p[0], dims[0]), -c(p[1], dims[1]), c(p[2], dims[2])]).1
        };
        let mut x = Vec::new();
        let mut y_all = Vec::new();
        let at = |a: usize, f: usize| (dims[a] - s[a]) * f / 6;
        let mut origins = vec![[at(0, 3), at(1, 3), at(2, 3)]];
        for k in 0..8 {
            origins.push(std::array::from_fn(|a| {
                at(a, if k >> a & 1 == 1 { 4 } else { 2 })
            }));
        }
        for o in origins {
            x.extend(cpu_features(&vol, dims, o, s, &norm));
            for z in 0..s[2] {
                for yy in 0..s[1] {
                    for xx in 0..s[0] {
                        y_all.push(label_at([o[0] + xx, o[1] + yy, o[2] + z]));
                    }
                }
            }
        }
        let mut seen: Vec<u8> = Vec::new();
        let y_idx: Vec<u16> = y_all
            .iter()
            .map(|l| match seen.iter().position(|s| s == l) {
                Some(k) => k as u16,
                None => {
                    seen.push(*l);
                    seen.len() as u16 - 1
                }
            })
            .collect();
        let d = Classic::Filters.channels() + 3;
        let mut rng = Rng::new(1);
        let n0 = y_idx.len();
        let pick: Vec<usize> = (0..train_rows.min(n0)).map(|_| rng.below(n0)).collect();
        let xs: Vec<f32> = pick
            .iter()
            .flat_map(|&r| x[r * d..(r + 1) * d].iter().copied())
            .collect();
        let ys: Vec<u16> = pick.iter().map(|&r| y_idx[r]).collect();
        let classes = seen.len().max(2);
        let forest = match Forest::fit(
            Dataset {
                x: &xs,
                y: &ys,
                d,
                classes,
            },
            &ForestConfig {
                trees,
                ..Default::default()
            },
        ) {
            Ok(f) => f,
            Err(e) => {
                eprintln!("training: {e}");
                std::process::exit(1);
            }
        };
        forest.prepare();
        let train_s = t.elapsed().as_secs_f64();
        println!(
            "forest: {trees} trees, {classes} classes, {} nodes, trained on {} rows in {train_s:.1} s",
            forest.nodes(),
            ys.len()
        );
        report["classes"] = json!(classes);
        report["forest_nodes"] = json!(forest.nodes());
        report["train_s"] = json!(train_s);
        write(&out, &report);

        // The bricks, in z-major order.
        let nb = dims.map(|d| d.div_ceil(brick));
        let mut bricks = Vec::new();
        for bz in 0..nb[2] {
            for by in 0..nb[1] {
                for bx in 0..nb[0] {
                    bricks.push([bx * brick, by * brick, bz * brick]);
                }
            }
        }
        let cube = [brick; 3];
        let inside =
            |o: [usize; 3]| -> [usize; 3] { std::array::from_fn(|a| (dims[a] - o[a]).min(brick)) };

        // 3. The GPU path.
        let kind = if software {
            AdapterKind::Any
        } else {
            AdapterKind::Hardware
        };
        let mut labels_gpu = vec![0u8; voxels];
        let mut gpu_ok = false;
        let dev = match GpuDevice::new(kind) {
            Ok(d) => Some(d),
            Err(e) => {
                println!("SKIP: the GPU path: {e}");
                report["gpu"] = json!({ "skipped": e.to_string() });
                None
            }
        };
        if let Some(dev) = dev {
            println!("device: {}", dev.describe());
            report["device"] = json!(dev.describe());
            report["software_adapter"] = json!(dev.is_software());
            let gpu_result = (|| -> neuvolex_classify_gpu::Result<Value> {
                let bank = GpuFilterBank::new(dev.clone(), true)?;
                let gf = GpuForest::new(dev.clone(), &forest)?;
                let core = brick * brick * brick;
                let obytes = gf.output_bytes(core);
                let lo = gf.labels_offset(core) as usize;
                let h = filter_halo();
                struct Slot {
                    filt: neuvolex_classify_gpu::filters::FilterSlot,
                    out: neuvolex_classify_gpu::Tracked,
                    staging: neuvolex_classify_gpu::Tracked,
                }
                let ring: Vec<Slot> = (0..in_flight)
                    .map(|_| -> neuvolex_classify_gpu::Result<Slot> {
                        Ok(Slot {
                            filt: bank.slot(cube, h)?,
                            out: dev.buffer(
                                "forest out",
                                obytes,
                                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                            )?,
                            staging: dev.buffer(
                                "staging",
                                obytes,
                                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                            )?,
                        })
                    })
                    .collect::<neuvolex_classify_gpu::Result<_>>()?;
                println!(
                    "GPU ring: {in_flight} x {:.0} MiB, forest {:.1} MiB",
                    (ring[0].filt.bytes() + 2 * obytes) as f64 / (1u64 << 20) as f64,
                    gf.bytes() as f64 / (1u64 << 20) as f64
                );
                // One brick's phases apart (also the warm-up: pipelines, first allocation).
                // The normalised halo brick (as `halo_from_volume` then `Normaliser::apply`), planes
                // in parallel.
                let pad_of = |o: [usize; 3]| -> Vec<f32> {
                    let p = cube.map(|c| c + 2 * h);
                    let at = |a: usize, i: usize| {
                        (o[a] as isize + i as isize - h as isize).clamp(0, dims[a] as isize - 1)
                            as usize
                    };
                    let mut g = vec![0.0f32; p[0] * p[1] * p[2]];
                    g.par_chunks_mut(p[0] * p[1])
                        .enumerate()
                        .for_each(|(z, plane)| {
                            let gz = at(2, z);
                            for (y, row) in plane.chunks_exact_mut(p[0]).enumerate() {
                                let src = &vol[(gz * dims[1] + at(1, y)) * dims[0]..][..dims[0]];
                                for (x, v) in row.iter_mut().enumerate() {
                                    *v = norm.apply(src[at(0, x)]);
                                }
                            }
                        });
                    g
                };
                let first = pad_of(bricks[0]);
                let time = |f: &dyn Fn(
                    &mut wgpu::CommandEncoder,
                ) -> neuvolex_classify_gpu::Result<()>|
                 -> neuvolex_classify_gpu::Result<f64> {
                    let t = Instant::now();
                    let mut enc = dev.device.create_command_encoder(&Default::default());
                    f(&mut enc)?;
                    dev.queue.submit([enc.finish()]);
                    dev.wait()?;
                    Ok(t.elapsed().as_secs_f64())
                };
                let s0 = &ring[0];
                time(&|e| bank.encode_normalised(&s0.filt, e, &first, bricks[0], dims))?;
                let filter_s =
                    time(&|e| bank.encode_normalised(&s0.filt, e, &first, bricks[0], dims))?;
                let forest_s = time(&|e| {
                    gf.encode(
                        e,
                        s0.filt.features(),
                        FeatureLayout::planes(core),
                        core,
                        &s0.out,
                    )
                })?;
                println!(
                "one brick of {brick}^3 ({:.2} M voxels): filter bank {:.1} ms, forest {:.1} ms \
                 (upload and read back apart)",
                core as f64 / 1e6,
                filter_s * 1e3,
                forest_s * 1e3
            );
                dev.reset_peak();
                // The stream: a producer thread reads and normalises bricks ahead; the GPU ring holds
                // `in_flight` bricks; a brick's results are read when its slot comes round again.
                let t = Instant::now();
                let (tx, rx) = sync_channel::<(usize, Vec<f32>)>(in_flight);
                let mut pending: Vec<Option<(usize, wgpu::SubmissionIndex)>> =
                    (0..in_flight).map(|_| None).collect();
                let mut done = 0usize;
                let mut last_print = Instant::now();
                let collect = |slot: &Slot,
                               bi: usize,
                               idx: wgpu::SubmissionIndex,
                               labels: &mut [u8]|
                 -> neuvolex_classify_gpu::Result<()> {
                    let bytes = dev.map_read_after(&slot.staging, obytes, Some(idx))?;
                    let o = bricks[bi];
                    let s = inside(o);
                    for z in 0..s[2] {
                        for yy in 0..s[1] {
                            let src = lo + (z * brick + yy) * brick;
                            let dst = ((o[2] + z) * dims[1] + o[1] + yy) * dims[0] + o[0];
                            labels[dst..dst + s[0]].copy_from_slice(&bytes[src..src + s[0]]);
                        }
                    }
                    Ok(())
                };
                std::thread::scope(|sc| -> neuvolex_classify_gpu::Result<()> {
                    // Owned here, so an early return drops it and the producer stops.
                    let rx = rx;
                    let prod = sc.spawn(|| {
                        for (bi, &o) in bricks.iter().enumerate() {
                            if tx.send((bi, pad_of(o))).is_err() {
                                return;
                            }
                        }
                        drop(tx);
                    });
                    for (k, (bi, padded)) in rx.iter().enumerate() {
                        let si = k % in_flight;
                        if let Some((prev, idx)) = pending[si].take() {
                            collect(&ring[si], prev, idx, &mut labels_gpu)?;
                            done += 1;
                        }
                        let slot = &ring[si];
                        let mut enc = dev.device.create_command_encoder(&Default::default());
                        bank.encode_normalised(&slot.filt, &mut enc, &padded, bricks[bi], dims)?;
                        gf.encode(
                            &mut enc,
                            slot.filt.features(),
                            FeatureLayout::planes(core),
                            core,
                            &slot.out,
                        )?;
                        enc.copy_buffer_to_buffer(&slot.out, 0, &slot.staging, 0, obytes);
                        let idx = dev.queue.submit([enc.finish()]);
                        pending[si] = Some((bi, idx));
                        if last_print.elapsed().as_secs_f64() > 2.0 {
                            println!(
                                "  GPU: {done}/{} bricks in {:.1} s",
                                bricks.len(),
                                t.elapsed().as_secs_f64()
                            );
                            last_print = Instant::now();
                        }
                    }
                    for si in 0..in_flight {
                        if let Some((prev, idx)) = pending[si].take() {
                            collect(&ring[si], prev, idx, &mut labels_gpu)?;
                            done += 1;
                        }
                    }
                    let _ = prod.join();
                    Ok(())
                })?;
                dev.check()?;
                let secs = t.elapsed().as_secs_f64();
                let peak = dev.peak_bytes();
                println!(
                "GPU path: {} bricks, {:.1} M voxels in {secs:.2} s = {:.1} M voxels/s; peak GPU \
                 buffers {:.0} MiB",
                bricks.len(),
                voxels as f64 / 1e6,
                voxels as f64 / secs / 1e6,
                peak as f64 / (1u64 << 20) as f64
            );
                Ok(json!({
                    "seconds": secs, "voxels_per_s": voxels as f64 / secs,
                    "peak_gpu_buffer_bytes": peak, "bricks": bricks.len(),
                    "one_brick_filter_s": filter_s, "one_brick_forest_s": forest_s,
                    "label_histogram": (0..classes).map(|k| labels_gpu.iter().filter(|&&l| l as usize == k).count()).collect::<Vec<_>>(),
                }))
            })();
            match gpu_result {
                Ok(v) => {
                    report["gpu"] = v;
                    gpu_ok = true;
                }
                Err(e) => {
                    println!("GPU path failed: {e}");
                    report["gpu"] = json!({ "error": e.to_string() });
                }
            }
        }
        write(&out, &report);

        // 4. The CPU path on the same bricks.
        let take = if cpu_all {
            bricks.len()
        } else {
            cpu_bricks.min(bricks.len())
        };
        // Spread over the volume: every k-th brick.
        let step = (bricks.len() / take.max(1)).max(1);
        let chosen: Vec<usize> = (0..bricks.len()).step_by(step).take(take).collect();
        let t = Instant::now();
        let (mut cpu_vox, mut agree) = (0usize, 0usize);
        for (k, &bi) in chosen.iter().enumerate() {
            let o = bricks[bi];
            let s = inside(o);
            let x = cpu_features(&vol, dims, o, s, &norm);
            let p = match forest.predict_proba(&x) {
                Ok(p) => p,
                Err(e) => {
                    eprintln!("CPU prediction: {e}");
                    break;
                }
            };
            let u8s: Vec<u8> = p.iter().map(|&v| to_u8(v)).collect();
            std::hint::black_box(&u8s);
            let mut i = 0;
            for z in 0..s[2] {
                for yy in 0..s[1] {
                    for xx in 0..s[0] {
                        let (lab, _) =
                            neuvolex_classify::shard::argmax(&p[i * classes..(i + 1) * classes]);
                        let at = ((o[2] + z) * dims[1] + o[1] + yy) * dims[0] + o[0] + xx;
                        agree += (labels_gpu[at] as usize == lab) as usize;
                        i += 1;
                    }
                }
            }
            cpu_vox += i;
            println!(
                "  CPU: {}/{} bricks, {:.1} M voxels in {:.1} s",
                k + 1,
                chosen.len(),
                cpu_vox as f64 / 1e6,
                t.elapsed().as_secs_f64()
            );
            let secs = t.elapsed().as_secs_f64();
            report["cpu"] = json!({
                "bricks": k + 1, "voxels": cpu_vox, "seconds": secs,
                "voxels_per_s": cpu_vox as f64 / secs,
                "whole_volume_s": voxels as f64 / (cpu_vox as f64 / secs),
                "whole_volume_extrapolated": k + 1 < bricks.len(),
                "labels_agreeing_with_gpu": gpu_ok.then(|| agree as f64 / cpu_vox.max(1) as f64),
            });
            write(&out, &report);
        }
        if let (Some(g), Some(c)) = (
            report["gpu"]["seconds"].as_f64(),
            report["cpu"]["whole_volume_s"].as_f64(),
        ) {
            println!(
                "whole volume: GPU {g:.2} s, CPU {c:.1} s{} ({:.1}x); labels agreeing on the \
                 CPU's bricks: {:.4}",
                if report["cpu"]["whole_volume_extrapolated"] == json!(true) {
                    " (extrapolated)"
                } else {
                    ""
                },
                c / g,
                report["cpu"]["labels_agreeing_with_gpu"]
                    .as_f64()
                    .unwrap_or(0.0)
            );
        }
        write(&out, &report);
    }
}
