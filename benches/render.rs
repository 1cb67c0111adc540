//! Milliseconds per frame of the renderer on real volumes, against VTK's ray casters on the same
//! volume, view and transfer function (`cargo bench -p neuvolex-benches --bench render
//! [--features gpu] -- [--size 512] [--frames 5] [--only bonsai|abdomen_ct] [--no-vtk-gpu]`).
//!
//! Volumes: CT-Bonsai (256^3) and the abdomen CT (122x101x112, 3 mm), from ../shared/data.
//! Reported per volume: the first frame (bricks read and decompressed from the store), then the
//! warm frames (bricks cached), for the intensity mode with shading and, on the abdomen, the
//! probabilistic mode over its ground-truth labels; the wgpu renderer where built with
//! `--features gpu`; and VTK's vtkFixedPointVolumeRayCastMapper and vtkGPUVolumeRayCastMapper
//! where `NEUVOLEX_VTK_PYTHON` (or `python3`) imports vtk and nibabel. VTK runs in a Python
//! process that renders a frame per request: the warm frames interleave (one of each renderer per
//! round), each timed in wall and process CPU time (getrusage here, `time.process_time` there),
//! and the ratio is taken per round, so a load change on a shared machine hits both sides alike.
//! Images go to `target/bench-render/`, with a side-by-side PNG per volume.

use neuvolex_benches::{machine, shared};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_render::tf::Space;
use neuvolex_render::{BrickSource, Image, Mode, RenderParams, Renderer, StoreSource, TfFile};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
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

/// VTK's mappers in a Python process (`render_vtk.py`) that renders one frame per request, so
/// that its frames interleave with ours and a load change on the machine hits both sides alike.
struct Vtk {
    child: Child,
    stdin: ChildStdin,
    out: BufReader<ChildStdout>,
    /// The mappers set up, by name.
    mappers: Vec<String>,
}

impl Vtk {
    /// Starts the script on `job`; `None` (with the reason on stderr) where Python, VTK or
    /// nibabel is missing.
    fn start(job: &serde_json::Value, out: &Path) -> Option<Vtk> {
        let py = std::env::var("NEUVOLEX_VTK_PYTHON").unwrap_or_else(|_| "python3".into());
        let jp = out.with_extension("job.json");
        std::fs::write(&jp, job.to_string()).expect("job");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("render_vtk.py");
        let spawned = Command::new(&py)
            .arg(&script)
            .arg(&jp)
            .env("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn();
        let mut child = match spawned {
            Ok(c) => c,
            Err(e) => {
                eprintln!("SKIP vtk ({py}): {e}");
                return None;
            }
        };
        let stdin = child.stdin.take().expect("piped stdin");
        let out = BufReader::new(child.stdout.take().expect("piped stdout"));
        let mut v = Vtk {
            child,
            stdin,
            out,
            mappers: Vec::new(),
        };
        match v.reply() {
            Some(r) => {
                v.mappers = r["ready"]
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .filter_map(|m| m.as_str().map(String::from))
                            .collect()
                    })
                    .unwrap_or_default();
                Some(v)
            }
            None => {
                eprintln!("SKIP vtk ({py}): the script did not start (its error is above)");
                let _ = v.child.wait();
                None
            }
        }
    }

    /// The next JSON line the script prints.
    fn reply(&mut self) -> Option<serde_json::Value> {
        let mut line = String::new();
        loop {
            line.clear();
            if self.out.read_line(&mut line).ok()? == 0 {
                return None;
            }
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
                return Some(v);
            }
        }
    }

    fn send(&mut self, cmd: &str) -> Option<serde_json::Value> {
        writeln!(self.stdin, "{cmd}").ok()?;
        self.stdin.flush().ok()?;
        self.reply()
    }

    /// One frame of `mapper`: wall and process CPU milliseconds.
    fn frame(&mut self, mapper: &str) -> Timing {
        let r = self.send(&format!("frame {mapper}")).expect("vtk frame");
        Timing {
            ms: r["ms"].as_f64().unwrap_or(f64::NAN),
            cpu_ms: r["cpu_ms"].as_f64().unwrap_or(f64::NAN),
        }
    }

    /// Writes `mapper`'s last image to `path`.
    fn save(&mut self, mapper: &str, path: &Path) {
        self.send(&format!("save {mapper} {}", path.display()));
    }
}

impl Drop for Vtk {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "quit");
        let _ = self.stdin.flush();
        let _ = self.child.wait();
    }
}

/// Wall and process CPU time of one frame, in milliseconds.
#[derive(Clone, Copy)]
struct Timing {
    ms: f64,
    cpu_ms: f64,
}

/// This process's CPU time (user + system, all threads), in milliseconds.
fn cpu_ms() -> f64 {
    // SAFETY: getrusage only writes the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 * 1e-3;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Times `f` in wall and process CPU time.
fn timed(f: impl FnOnce()) -> Timing {
    let (c, t) = (cpu_ms(), Instant::now());
    f();
    Timing {
        ms: t.elapsed().as_secs_f64() * 1e3,
        cpu_ms: cpu_ms() - c,
    }
}

/// `median [min-max]` of some values.
fn spread(v: &[f64]) -> String {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return "-".into();
    }
    s.sort_by(f64::total_cmp);
    format!("{:.0} [{:.0}-{:.0}]", s[s.len() / 2], s[0], s[s.len() - 1])
}

/// Median and range of per-round ratios `a[i] / b[i]`.
fn ratio_spread(a: &[f64], b: &[f64]) -> String {
    let mut r: Vec<f64> = a
        .iter()
        .zip(b)
        .map(|(x, y)| x / y)
        .filter(|x| x.is_finite())
        .collect();
    if r.is_empty() {
        return "-".into();
    }
    r.sort_by(f64::total_cmp);
    format!("{:.2}x [{:.2}-{:.2}]", r[r.len() / 2], r[0], r[r.len() - 1])
}

/// One renderer of ours in the interleaved run.
struct Entry<'a> {
    mode: Mode,
    label: String,
    render: Box<dyn FnMut() -> Image + 'a>,
    first: f64,
    times: Vec<Timing>,
    image: Image,
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size = arg(&args, "--size", 512);
    let frames = arg(&args, "--frames", 5);
    // `--no-vtk-gpu` leaves out VTK's OpenGL mapper (on llvmpipe it takes seconds a frame).
    let vtk_gpu = !args.iter().any(|a| a == "--no-vtk-gpu");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "machine: {}, {size}x{size}, {frames} warm frames interleaved with VTK's, load average {}",
        machine(),
        load.split_whitespace()
            .take(3)
            .collect::<Vec<_>>()
            .join(" ")
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
    println!("Per renderer: median [min-max] over the warm frames; VTK / this: the per-round ratio of VTK fixed-point's frame to this renderer's, median [min-max], in wall and in process CPU time.");
    println!(
        "| volume | mode | renderer | first frame ms | warm ms/frame | CPU ms/frame | VTK fixed-point / this (wall) | (CPU time) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
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
        let params = RenderParams::bench_view(size);
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
            "threads": rayon::current_num_threads(),
            "gpu": vtk_gpu,
        });
        let mut vtk = Vtk::start(&job, &out.join(name));
        let mut entries: Vec<Entry> = Vec::new();
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
            let mut image = None;
            let first = timed(|| image = Some(r.render(&p, &luts).expect("render"))).ms;
            let s = r.stats();
            entries.push(Entry {
                mode,
                label: format!(
                    "neuvolex CPU ({} of {} bricks marched)",
                    s.marched, s.bricks
                ),
                render: Box::new(move || r.render(&p, &luts).expect("render")),
                first,
                times: Vec::new(),
                image: image.expect("image"),
            });
            #[cfg(feature = "gpu")]
            {
                let source = StoreSource::new(st.clone());
                let source = if mode == Mode::Intensity {
                    source
                } else {
                    source.with_labels("truth").expect("labels")
                };
                let luts = tf.compile(&source.normaliser(), &source.classes());
                match neuvolex_render::gpu::GpuRenderer::new(source) {
                    Ok(mut g) => {
                        let mut image = None;
                        let first =
                            timed(|| image = Some(g.render(&p, &luts).expect("gpu render"))).ms;
                        entries.push(Entry {
                            mode,
                            label: format!("wgpu on {}", g.adapter()),
                            render: Box::new(move || g.render(&p, &luts).expect("gpu render")),
                            first,
                            times: Vec::new(),
                            image: image.expect("image"),
                        });
                    }
                    Err(e) => eprintln!("SKIP gpu: {e}"),
                }
            }
        }
        // Interleaved rounds: one frame of each renderer of ours, then one of each VTK mapper.
        let mappers = vtk.as_ref().map_or(Vec::new(), |v| v.mappers.clone());
        let mut vtk_times: Vec<Vec<Timing>> = vec![Vec::new(); mappers.len()];
        for _ in 0..frames {
            for e in &mut entries {
                let mut img = None;
                e.times.push(timed(|| img = Some((e.render)())));
                e.image = img.expect("image");
            }
            if let Some(v) = vtk.as_mut() {
                for (m, t) in mappers.iter().zip(&mut vtk_times) {
                    t.push(v.frame(m));
                }
            }
        }
        let fixed = mappers
            .iter()
            .position(|m| m == "vtk-fixedpoint-cpu")
            .map(|i| &vtk_times[i]);
        let ratios = |t: &[Timing]| match fixed {
            Some(f) => (
                ratio_spread(
                    &f.iter().map(|x| x.ms).collect::<Vec<_>>(),
                    &t.iter().map(|x| x.ms).collect::<Vec<_>>(),
                ),
                ratio_spread(
                    &f.iter().map(|x| x.cpu_ms).collect::<Vec<_>>(),
                    &t.iter().map(|x| x.cpu_ms).collect::<Vec<_>>(),
                ),
            ),
            None => ("-".into(), "-".into()),
        };
        let cpu_image = entries.first().map(|e| e.image.clone());
        let mut images: Vec<Image> = Vec::new();
        for e in &entries {
            let (rw, rc) = if e.mode == Mode::Intensity {
                ratios(&e.times)
            } else {
                ("-".into(), "-".into())
            };
            let diff = match (&cpu_image, e.label.starts_with("wgpu")) {
                (Some(c), true) if e.mode == Mode::Intensity => {
                    e.image.diff(c).map_or(String::new(), |(max, mean)| {
                        format!("; vs CPU image max {max:.4} mean {mean:.5}")
                    })
                }
                _ => String::new(),
            };
            println!(
                "| {name} | {:?} | {}{diff} | {:.0} | {} | {} | {rw} | {rc} |",
                e.mode,
                e.label,
                e.first,
                spread(&e.times.iter().map(|t| t.ms).collect::<Vec<_>>()),
                spread(&e.times.iter().map(|t| t.cpu_ms).collect::<Vec<_>>()),
            );
            if !e.label.starts_with("wgpu") {
                e.image
                    .save_png(&out.join(format!("{name}-neuvolex-{:?}.png", e.mode)))
                    .expect("png");
                if e.mode == Mode::Intensity {
                    images.push(e.image.clone());
                }
            }
        }
        for (m, t) in mappers.iter().zip(&vtk_times) {
            let (rw, rc) = ratios(t);
            println!(
                "| {name} | Intensity | {m} | - | {} | {} | {rw} | {rc} |",
                spread(&t.iter().map(|t| t.ms).collect::<Vec<_>>()),
                spread(&t.iter().map(|t| t.cpu_ms).collect::<Vec<_>>()),
            );
            let png = PathBuf::from(format!("{}{m}.png", prefix.display()));
            if let Some(v) = vtk.as_mut() {
                v.save(m, &png);
            }
            if let Ok(i) = Image::load_png(&png) {
                images.push(i);
            }
        }
        drop(vtk);
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
