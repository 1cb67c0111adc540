//! Milliseconds per frame of the renderer on real volumes, against VTK's ray casters on the same
//! volume, view and transfer function (`cargo bench -p neuvolex-benches --bench render
//! [--features gpu] -- [--size 512] [--frames 5] [--only bonsai|abdomen_ct]`).
//!
//! Volumes: CT-Bonsai (256^3) and the abdomen CT (122x101x112, 3 mm), from ../shared/data.
//! Reported per volume: the first frame (bricks read and decompressed from the store), then the
//! median of warm frames (bricks cached), for the intensity mode with shading and, on the
//! abdomen, the probabilistic mode over its ground-truth labels; the wgpu renderer where built
//! with `--features gpu`; and VTK's vtkFixedPointVolumeRayCastMapper and vtkGPUVolumeRayCastMapper
//! where `NEUVOLEX_VTK_PYTHON` (or `python3`) imports vtk and nibabel. Images go to
//! `target/bench-render/`, with a side-by-side PNG per volume.

use neuvolex_benches::{machine, median, shared};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{ingest, open_volume, BrickStore, IngestOptions};
use neuvolex_render::tf::Space;
use neuvolex_render::{
    BrickSource, Camera, Image, Mode, RenderParams, Renderer, StoreSource, TfFile,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

fn arg(args: &[String], name: &str, default: usize) -> usize {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn store(src: &Path, labels: Option<&Path>, dir: &Path) -> Arc<BrickStore> {
    let p = dir.join("s.zarr");
    let mut v = open_volume(src, None).expect("open");
    ingest(
        v.as_mut(),
        &p,
        &IngestOptions {
            brick: 32,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    let mut s = BrickStore::open(&p).expect("store");
    if let Some(l) = labels {
        let mut lv = open_volume(l, None).expect("labels");
        let classes: Vec<ClassInfo> = (1..=4)
            .map(|id| ClassInfo {
                id,
                name: format!("class{id}"),
                color: neuvolex_bricks::synth::palette(id),
            })
            .collect();
        s.add_labels("truth", lv.as_mut(), &classes, &mut |_| {})
            .expect("labels");
    }
    Arc::new(s)
}

/// Runs the VTK script; returns `(mapper, ms, image path)` rows.
fn vtk(job: &serde_json::Value, out: &Path) -> Vec<(String, f64, PathBuf)> {
    let py = std::env::var("NEUVOLEX_VTK_PYTHON").unwrap_or_else(|_| "python3".into());
    let jp = out.with_extension("job.json");
    std::fs::write(&jp, job.to_string()).expect("job");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("render_vtk.py");
    let o = std::process::Command::new(&py)
        .arg(&script)
        .arg(&jp)
        .env("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        .output();
    match o {
        Ok(o) if o.status.success() => String::from_utf8_lossy(&o.stdout)
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .map(|v| {
                let m = v["mapper"].as_str().unwrap_or("?").to_string();
                let img = PathBuf::from(format!(
                    "{}{m}.png",
                    job["out_prefix"].as_str().unwrap_or("")
                ));
                (m, v["ms"].as_f64().unwrap_or(f64::NAN), img)
            })
            .collect(),
        Ok(o) => {
            eprintln!(
                "SKIP vtk ({py}): {}",
                String::from_utf8_lossy(&o.stderr)
                    .lines()
                    .last()
                    .unwrap_or("")
            );
            Vec::new()
        }
        Err(e) => {
            eprintln!("SKIP vtk ({py}): {e}");
            Vec::new()
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size = arg(&args, "--size", 512);
    let frames = arg(&args, "--frames", 5);
    println!(
        "machine: {}, {size}x{size}, {frames} warm frames",
        machine()
    );
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/bench-render");
    std::fs::create_dir_all(&out).expect("out dir");
    let cases = [
        ("bonsai", "scivis/bonsai.nii.gz", None, "grey"),
        (
            "abdomen_ct",
            "abdomen_ct/ct.nii.gz",
            Some("abdomen_ct/labels.nii.gz"),
            "ct-bone",
        ),
    ];
    println!(
        "| volume | mode | renderer | first frame ms | warm ms/frame | vs VTK fixed-point (CPU) |"
    );
    println!("|---|---|---|---|---|---|");
    // `--only NAME` runs one volume (for profiling).
    let only = args
        .iter()
        .position(|a| a == "--only")
        .and_then(|i| args.get(i + 1));
    for (name, rel, labels, preset) in cases {
        if only.is_some_and(|o| o != name) {
            continue;
        }
        let Some(src) = shared(rel) else { continue };
        let labels = labels.and_then(shared);
        let dir = tempfile::tempdir().expect("tmp");
        let st = store(&src, labels.as_deref(), dir.path());
        let tf = TfFile::preset(preset).expect("preset");
        let params = RenderParams {
            width: size,
            height: size,
            camera: Camera {
                azimuth: 30.0,
                elevation: 15.0,
                ..Camera::default()
            },
            ..RenderParams::default()
        };
        // VTK first, so its ratio sits in each row.
        let source = StoreSource::new(st.clone());
        let norm = source.normaliser();
        let it = tf.intensity.clone().expect("intensity tf");
        let raw = |x: f64| match tf.space {
            Space::Raw => x,
            Space::Normalised => norm.lo + x * (norm.hi - norm.lo),
        };
        let geom = source.geom();
        let view = params.camera.view(geom.extent(), size, size);
        let prefix = out.join(format!("{name}-"));
        let job = serde_json::json!({
            "volume": src,
            "spacing": geom.spacing,
            "color": it.color.iter().map(|(x, c)| [raw(*x), c[0] as f64, c[1] as f64, c[2] as f64]).collect::<Vec<_>>(),
            "opacity": it.opacity.iter().map(|(x, a)| [raw(*x), *a as f64]).collect::<Vec<_>>(),
            "eye": view.eye, "up": view.up, "fov": params.camera.fov,
            "width": size, "height": size, "step": params.step,
            "shading": params.shading.map(|s| serde_json::json!({"ambient": s.ambient, "diffuse": s.diffuse, "specular": s.specular, "shininess": s.shininess})),
            "frames": frames, "threads": rayon::current_num_threads(),
            "out_prefix": prefix.to_string_lossy(),
        });
        let vt = vtk(&job, &out.join(name));
        let vtk_cpu = vt.iter().find(|v| v.0 == "vtk-fixedpoint-cpu").map(|v| v.1);
        let ratio = |ms: f64| vtk_cpu.map_or("-".into(), |v| format!("{:.2}x faster", v / ms));
        let mut images: Vec<Image> = Vec::new();
        for mode in [Mode::Intensity, Mode::Probabilistic] {
            let source = StoreSource::new(st.clone());
            let source = match (mode, labels.is_some()) {
                (Mode::Intensity, _) => source,
                (_, true) => source.with_labels("truth").expect("labels"),
                (_, false) => continue,
            };
            let luts = tf.compile(&source.normaliser(), &source.classes());
            let p = RenderParams { mode, ..params };
            let mut r = Renderer::new(source, 2 << 30);
            let t = Instant::now();
            let img = r.render(&p, &luts).expect("render");
            let first = t.elapsed().as_secs_f64() * 1e3;
            let warm = median(frames, || {
                r.render(&p, &luts).expect("render");
            })
            .as_secs_f64()
                * 1e3;
            let s = r.stats();
            println!(
                "| {name} | {mode:?} | CPU ({} of {} bricks marched) | {first:.0} | {warm:.0} | {} |",
                s.marched,
                s.bricks,
                if mode == Mode::Intensity { ratio(warm) } else { "-".into() }
            );
            img.save_png(&out.join(format!("{name}-neuvolex-{mode:?}.png")))
                .expect("png");
            if mode == Mode::Intensity {
                images.push(img.clone());
            }
            #[cfg(feature = "gpu")]
            {
                let source = StoreSource::new(st.clone());
                let source = if mode == Mode::Intensity {
                    source
                } else {
                    source.with_labels("truth").expect("labels")
                };
                match neuvolex_render::gpu::GpuRenderer::new(source) {
                    Ok(mut g) => {
                        let t = Instant::now();
                        let gi = g.render(&p, &luts).expect("gpu render");
                        let first = t.elapsed().as_secs_f64() * 1e3;
                        let warm = median(frames, || {
                            g.render(&p, &luts).expect("gpu render");
                        })
                        .as_secs_f64()
                            * 1e3;
                        let (max, mean) = gi.diff(&img).unwrap_or((f32::NAN, f32::NAN));
                        println!(
                            "| {name} | {mode:?} | wgpu on {} (GPU part {:.0} ms; vs CPU image max {max:.4} mean {mean:.5}) | {first:.0} | {warm:.0} | {} |",
                            g.adapter(),
                            g.last_seconds.1 * 1e3,
                            if mode == Mode::Intensity { ratio(warm) } else { "-".into() }
                        );
                    }
                    Err(e) => eprintln!("SKIP gpu: {e}"),
                }
            }
        }
        for (m, ms, img) in &vt {
            println!(
                "| {name} | Intensity | {m} | - | {ms:.0} | {} |",
                ratio(*ms)
            );
            if let Ok(i) = Image::load_png(img) {
                images.push(i);
            }
        }
        if images.len() > 1 {
            let refs: Vec<&Image> = images.iter().collect();
            if let Ok(s) = Image::side_by_side(&refs) {
                let p = out.join(format!("{name}-side-by-side.png"));
                s.save_png(&p).expect("png");
                println!(
                    "images: {} (neuvolex CPU | VTK fixed-point | VTK GPU)",
                    p.display()
                );
            }
        }
    }
}
