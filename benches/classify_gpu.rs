//! A whole round of classification on the GPU (`cargo bench -p neuvolex-benches --features gpu
//! --bench classify_gpu -- [options]`, or the built binary run directly on a device): the
//! generated CT-like phantom (512x512x452 by default, 118.5 M voxels) in a brick store,
//! streamed through the library's ring (`neuvolex-classify-gpu`'s `predict_stream`, what
//! `neuvolex classify --gpu` and the service's rounds run: blocks of bricks read from the store,
//! upload -> filter bank -> forest -> read back, a bounded number in flight), against the CPU
//! path (`neuvolex_filters::compute` + `Forest::predict_proba`, the session's per-brick work) on
//! the same machine in the same run.
//!
//! Steps, each printed as it ends (a run cut short by a time limit still shows the rest):
//! 1. the phantom, generated in memory (rayon over slices) and written as a brick store of
//!    `--brick` (default 64, the CLI's) in a temporary folder (not timed as classification);
//! 2. a forest of `--trees` trees (default 32: the session's `trees_for` a volume this size)
//!    trained on `--train-rows` voxels of nine bricks spread over the volume (CPU features,
//!    the phantom's labels);
//! 3. the GPU path over every brick: blocks of up to `--block` voxels a side (default 128) with
//!    the filter bank's halo, read from the store and normalised on the host ahead of the GPU,
//!    `--in-flight` blocks (default 2) in the ring, the u8 probabilities and labels back per
//!    brick; voxels/s, whole-volume seconds, peak GPU buffer bytes, and the first block's time
//!    (the warm-up: pipelines, the ring's allocation);
//! 4. the CPU path on `--cpu-bricks` of the same bricks (default 4; `all` for every brick),
//!    timed, its voxels/s and the whole volume's seconds extrapolated from them (marked so), and
//!    the labels' agreement with the GPU's on those bricks.
//!
//! Options: `--dims X,Y,Z` (default 512,512,452), `--brick B`, `--block V`, `--in-flight K`,
//! `--trees T`,
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
    use neuvolex_bricks::BrickStore;
    use neuvolex_classify::accel::{AccelOptions, Accelerator};
    use neuvolex_classify::stable::to_u8;
    use neuvolex_classify::{Dataset, Forest, ForestConfig};
    use neuvolex_classify_gpu::{AdapterKind, GpuAccelerator, GpuDevice, StreamConfig};
    use neuvolex_filters::{compute, filter_halo, pos, Classic};
    use neuvolex_formats::VolumeSource;
    use rayon::prelude::*;
    use serde_json::{json, Value};
    use std::sync::Arc;
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
        let brick: usize = arg(&args, "--brick", 64usize).max(8);
        let block: usize = arg(&args, "--block", 128usize).max(8);
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
            "dims": dims, "voxels": voxels, "brick": brick, "block": block, "halo": filter_halo(),
            "in_flight": in_flight, "trees": trees, "features": "filters+xyz",
            "threads": rayon::current_num_threads(),
        });
        println!(
            "classify_gpu: {dims:?} ({:.1} M voxels), bricks of {brick} in blocks of up to \
             {block} + halo {}, {in_flight} in flight, {trees} trees, {} CPU threads",
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
        let dir = tempfile::tempdir().expect("temporary folder");
        let sp = dir.path().join("phantom.zarr");
        let mut mem = neuvolex_formats::MemVolume::from_f32(dims, &vol);
        neuvolex_ingest::ingest(
            &mut mem,
            &sp,
            &neuvolex_ingest::IngestOptions {
                brick,
                ..Default::default()
            },
            &mut |_| {},
        )
        .expect("the phantom's store");
        drop(mem);
        let store = Arc::new(BrickStore::open(&sp).expect("the phantom's store"));
        // The store's normaliser, which the GPU path reads: the CPU path uses it too.
        let norm = store.normaliser();
        let gen_s = t.elapsed().as_secs_f64();
        println!(
            "phantom generated and stored in {gen_s:.1} s; normaliser {:.1}..{:.1}",
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

        // The store's bricks, in z-major order.
        let bricks: Vec<neuvolex_bricks::Brick> = store.bricks().collect();

        // 3. The GPU path: the library's stream over every brick.
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
            let gpu_result = (|| -> Result<Value, neuvolex_classify::ClassifyError> {
                let accel = GpuAccelerator::new(dev.clone()).with_stream(StreamConfig {
                    in_flight,
                    block,
                    ..StreamConfig::default()
                });
                let set = "filters+xyz".parse().expect("feature set");
                let pred =
                    accel.prepare(store.clone(), &set, &forest, &AccelOptions::tau(f32::MIN))?;
                let mut put = |b: &neuvolex_bricks::Brick, classes: &[u8]| {
                    for (row, l) in b.rows(dims).zip(classes.chunks_exact(b.size[0])) {
                        labels_gpu[row..row + b.size[0]].copy_from_slice(l);
                    }
                };
                // The warm-up: the first brick's block (pipelines, the ring's allocation).
                let t = Instant::now();
                pred.predict_stream(&bricks[..1], &mut |b, a| {
                    put(b, &a.classes);
                    true
                })?;
                let first_s = t.elapsed().as_secs_f64();
                println!("first block (warm-up) in {:.1} ms", first_s * 1e3);
                dev.reset_peak();
                let t = Instant::now();
                let (mut done, mut last_print) = (0usize, Instant::now());
                pred.predict_stream(&bricks, &mut |b, a| {
                    put(b, &a.classes);
                    done += 1;
                    if last_print.elapsed().as_secs_f64() > 2.0 {
                        println!(
                            "  GPU: {done}/{} bricks in {:.1} s",
                            bricks.len(),
                            t.elapsed().as_secs_f64()
                        );
                        last_print = Instant::now();
                    }
                    true
                })?;
                let secs = t.elapsed().as_secs_f64();
                let peak = dev.peak_bytes();
                println!(
                    "GPU path: {} bricks, {:.1} M voxels in {secs:.2} s = {:.1} M voxels/s; peak \
                     GPU buffers {:.0} MiB (budget {:.0} MiB)",
                    bricks.len(),
                    voxels as f64 / 1e6,
                    voxels as f64 / secs / 1e6,
                    peak as f64 / (1u64 << 20) as f64,
                    accel.stream().budget as f64 / (1u64 << 20) as f64
                );
                Ok(json!({
                    "seconds": secs, "voxels_per_s": voxels as f64 / secs,
                    "peak_gpu_buffer_bytes": peak, "budget_bytes": accel.stream().budget,
                    "bricks": bricks.len(), "first_block_s": first_s,
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
            let (o, s) = (bricks[bi].origin, bricks[bi].size);
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
