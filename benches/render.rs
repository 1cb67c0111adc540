//! Milliseconds per frame of the renderer on real volumes, against VTK's ray casters on the same
//! volume, views and transfer function (`cargo bench -p neuvolex-benches --bench render
//! [--features gpu] -- [--size 512] [--frames 7] [--only bonsai|abdomen_ct] [--no-vtk-gpu]`).
//!
//! Volumes: CT-Bonsai (256^3, uint8) and the abdomen CT (122x101x112, 3 mm, int32 in the file),
//! from ../shared/data. Two camera series, each `--frames` rounds: a *still* camera (the bench
//! view every frame: a renderer may reuse its rays, as when a TF or the probabilities change)
//! and an *orbit* (every frame a new view, 360/frames degrees further in azimuth: nothing
//! view-dependent can be reused, as when a user turns the volume). Per volume: the first frame
//! (bricks read and decompressed from the store), then the frames of both series, for the
//! intensity mode with shading and, on the abdomen, the probabilistic mode over its
//! ground-truth labels; the wgpu renderer where built with `--features gpu`; and VTK's
//! vtkFixedPointVolumeRayCastMapper and vtkGPUVolumeRayCastMapper where `NEUVOLEX_VTK_PYTHON`
//! (or `python3`) imports vtk and nibabel (`NEUVOLEX_VTK_SCRIPT` names `render_vtk.py` where the
//! binary runs away from its source tree, as on the device: `benches/gpu_device.sh`).
//!
//! Like for like, by construction:
//! - VTK gets each volume in the file's integer type, narrowed without loss to 8 or 16 bits
//!   (the fixed-point caster's fast path; bonsai uint8, the abdomen int16), the same camera,
//!   TF control points (in data units), opacity unit distance, sample distance (automatic
//!   adjustment off, full image resolution) and thread count (`render_vtk.py`), and our rays
//!   end where its rays end (opacity 1 - 255/32767, its early termination, not our 0.99);
//! - timed regions: ours is the whole `Renderer::render` call (per-frame ray set-up, the march,
//!   compositing into an RGB image in memory); VTK's is its ray cast alone, between the mapper's
//!   render start and end events (without its per-frame set-up and the OpenGL blit), so the
//!   ratio leans, if at all, towards VTK. VTK's whole `Render()` (with the blit through
//!   OpenGL) is reported beside it as what a VTK user waits for;
//! - rounds interleave: one frame of each renderer of ours, then one of each VTK mapper, each
//!   timed in wall and process CPU time (getrusage here, `time.process_time` there), and the
//!   ratio is taken per round, so a load change on a shared machine hits both sides alike;
//! - images: ours against VTK's for the same view, as the mean and largest absolute channel
//!   difference and SSIM of the luma (7x7 windows), with the still view's and the last orbit
//!   view's images.
//!
//! Images go to `target/bench-render/`, with a side-by-side PNG per volume.

use neuvolex_benches::{arg, load_average, machine, ratio_spread, shared, spread, JsonChild};
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_render::camera::View;
use neuvolex_render::tf::Space;
use neuvolex_render::{
    BrickSource, Camera, Image, Mode, RenderParams, Renderer, StoreSource, TfFile,
};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

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
    child: JsonChild,
    /// The mappers set up, by name.
    mappers: Vec<String>,
    /// The type the volume went to VTK in.
    dtype: String,
}

impl Vtk {
    /// Starts the script on `job`; `None` (with the reason on stderr) where Python, VTK or
    /// nibabel is missing.
    fn start(job: &serde_json::Value, out: &Path) -> Option<Vtk> {
        let py = std::env::var("NEUVOLEX_VTK_PYTHON").unwrap_or_else(|_| "python3".into());
        let jp = out.with_extension("job.json");
        std::fs::write(&jp, job.to_string()).expect("job");
        // NEUVOLEX_VTK_SCRIPT names the script where the binary runs away from its source
        // tree (benches/gpu_device.sh carries it to the device).
        let script = std::env::var_os("NEUVOLEX_VTK_SCRIPT").map_or_else(
            || Path::new(env!("CARGO_MANIFEST_DIR")).join("render_vtk.py"),
            std::path::PathBuf::from,
        );
        let child = JsonChild::start(
            "vtk",
            &py,
            &script,
            &[jp.display().to_string()],
            &[("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")],
        )?;
        let r = &child.ready;
        let mappers = r["ready"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|m| m.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default();
        let dtype = format!(
            "{} (VTK {})",
            r["dtype"].as_str().unwrap_or("?"),
            r["vtk"].as_str().unwrap_or("?")
        );
        Some(Vtk {
            child,
            mappers,
            dtype,
        })
    }

    /// One frame of `mapper` from `view`'s eye and up: the whole `Render()` and, for the
    /// fixed-point caster, its ray cast alone, in wall and process CPU milliseconds.
    fn frame(&mut self, mapper: &str, view: &View) -> VtkTiming {
        let (e, u) = (view.eye, view.up);
        let r = self
            .child
            .send(&format!(
                "frame {mapper} {} {} {} {} {} {}",
                e[0], e[1], e[2], u[0], u[1], u[2]
            ))
            .expect("vtk frame");
        let f = |k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        VtkTiming {
            render: Timing {
                ms: f("ms"),
                cpu_ms: f("cpu_ms"),
            },
            cast: Timing {
                ms: f("cast_ms"),
                cpu_ms: f("cast_cpu_ms"),
            },
        }
    }

    /// Writes `mapper`'s last image to `path`.
    fn save(&mut self, mapper: &str, path: &Path) {
        self.child
            .send(&format!("save {mapper} {}", path.display()));
    }
}

/// Wall and process CPU time of one frame, in milliseconds.
#[derive(Clone, Copy)]
struct Timing {
    ms: f64,
    cpu_ms: f64,
}

/// One VTK frame: the whole `Render()` and the ray cast alone (NaN where the mapper has no
/// cast events).
#[derive(Clone, Copy)]
struct VtkTiming {
    render: Timing,
    cast: Timing,
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

/// `median [min-max]` in whole milliseconds.
fn spread0(v: &[f64]) -> String {
    spread(v, 0)
}

/// One renderer of ours in the interleaved run.
struct Entry<'a> {
    mode: Mode,
    label: String,
    gpu: bool,
    render: Box<dyn FnMut(&Camera) -> Image + 'a>,
    first: f64,
    image: Image,
}

/// The camera series a run times: the bench view every frame, or an orbit.
#[derive(Clone, Copy, PartialEq)]
enum Series {
    Still,
    Orbit,
}

impl Series {
    fn name(self) -> &'static str {
        match self {
            Series::Still => "still",
            Series::Orbit => "orbit",
        }
    }

    /// The camera of frame `i` of `frames` (the orbit's views lie half a step off the still
    /// one, so none repeats it).
    fn camera(self, base: Camera, i: usize, frames: usize) -> Camera {
        match self {
            Series::Still => base,
            Series::Orbit => Camera {
                azimuth: base.azimuth + 360.0 * (i as f32 + 0.5) / frames.max(1) as f32,
                ..base
            },
        }
    }
}

/// The largest mean absolute channel difference from VTK fixed-point's image that counts as the
/// same picture: its 15-bit compositing and encoded-normal shading tables make it darker than
/// a float renderer's, by about 0.01–0.02 on these views.
const MAX_MEAN_DIFF: f32 = 0.03;
/// The smallest SSIM against VTK fixed-point's image that counts as the same picture.
const MIN_SSIM: f32 = 0.85;

/// The mean and largest absolute channel difference and the SSIM of `a` against `b`.
fn compare(a: &Image, b: &Image) -> Result<(f32, f32, f32), neuvolex_render::RenderError> {
    let (max, mean) = a.diff(b)?;
    Ok((mean, max, a.ssim(b)?))
}

/// [`compare`]'s figures as the three cells of the equivalence table.
fn cells(c: &Result<(f32, f32, f32), neuvolex_render::RenderError>) -> String {
    match c {
        Ok((mean, max, ssim)) => format!("{mean:.4} | {max:.3} | {ssim:.3}"),
        Err(e) => format!("{e} | - | -"),
    }
}

/// The opacity at which VTK's fixed-point caster ends a ray: its remaining opacity (15-bit
/// fixed point, 0x7fff for 1) below 0xff.
const VTK_ERT: f32 = 1.0 - 255.0 / 32767.0;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size = arg(&args, "--size", 512);
    let frames = arg(&args, "--frames", 7);
    // `--no-vtk-gpu` leaves out VTK's OpenGL mapper (on llvmpipe it takes seconds a frame).
    let vtk_gpu = !args.iter().any(|a| a == "--no-vtk-gpu");
    println!(
        "machine: {}, {size}x{size}, {frames} rounds per camera series interleaved with VTK's, rayon threads {}, {}",
        machine(),
        rayon::current_num_threads(),
        load_average()
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
    println!("Per renderer: median [min-max] over the rounds. Ratios are per round, median [min-max]: VTK fixed-point's ray cast alone / this renderer's whole frame (the like-for-like ratio), and VTK's whole Render() with its OpenGL blit / this (what a VTK user waits for). Above 1: this renderer is faster.");
    println!(
        "| volume | camera | mode | renderer | first frame ms | ms/frame | CPU ms/frame | VTK cast / this (wall) | (CPU time) | VTK Render() / this (wall) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut equivalence: Vec<String> = Vec::new();
    let mut summaries: Vec<String> = Vec::new();
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
        // Rays stop where VTK's fixed-point caster stops them: at a remaining opacity below
        // 255 / 32767 (its `VTKKWRCHelper_CompositeColorAndCheckEarlyTermination`), not at
        // our default 0.99, so both sides composite the same samples.
        let params = RenderParams {
            ert: VTK_ERT,
            ..RenderParams::bench_view(size)
        };
        let source = StoreSource::new(st.clone());
        let norm = source.normaliser();
        let it = tf.intensity.clone().expect("intensity tf");
        let raw = |x: f64| match tf.space {
            Space::Raw => x,
            Space::Normalised => norm.lo + x * (norm.hi - norm.lo),
        };
        let geom = source.geom();
        let extent = geom.extent();
        let view_of = |c: &Camera| c.view(extent, size, size);
        let view = view_of(&params.camera);
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
        if let Some(v) = &vtk {
            println!(
                "| {name} | | | VTK gets the volume as {} | | | | | | |",
                v.dtype
            );
        }
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
                gpu: false,
                render: Box::new(move |c| {
                    r.render(&RenderParams { camera: *c, ..p }, &luts)
                        .expect("render")
                }),
                first,
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
                            gpu: true,
                            render: Box::new(move |c| {
                                g.render(&RenderParams { camera: *c, ..p }, &luts)
                                    .expect("gpu render")
                            }),
                            first,
                            image: image.expect("image"),
                        });
                    }
                    Err(e) => eprintln!("SKIP gpu: {e}"),
                }
            }
        }
        let mappers = vtk.as_ref().map_or(Vec::new(), |v| v.mappers.clone());
        let mut side_by_side: Vec<Image> = Vec::new();
        for series in [Series::Still, Series::Orbit] {
            // Interleaved rounds: one frame of each renderer of ours, then one of each VTK
            // mapper, all from the round's camera.
            let mut ours: Vec<Vec<Timing>> = vec![Vec::new(); entries.len()];
            let mut theirs: Vec<Vec<VtkTiming>> = vec![Vec::new(); mappers.len()];
            for i in 0..frames {
                let cam = series.camera(params.camera, i, frames);
                let v_cam = view_of(&cam);
                for (e, t) in entries.iter_mut().zip(&mut ours) {
                    let mut img = None;
                    t.push(timed(|| img = Some((e.render)(&cam))));
                    e.image = img.expect("image");
                }
                if let Some(v) = vtk.as_mut() {
                    for (m, t) in mappers.iter().zip(&mut theirs) {
                        t.push(v.frame(m, &v_cam));
                    }
                }
            }
            let fixed = mappers
                .iter()
                .position(|m| m == "vtk-fixedpoint-cpu")
                .map(|i| &theirs[i]);
            let col = |t: &[Timing], f: fn(&Timing) -> f64| t.iter().map(f).collect::<Vec<_>>();
            let ratios = |t: &[Timing]| match fixed {
                Some(f) => {
                    let cast: Vec<Timing> = f.iter().map(|x| x.cast).collect();
                    let whole: Vec<Timing> = f.iter().map(|x| x.render).collect();
                    (
                        ratio_spread(&col(&cast, |x| x.ms), &col(t, |x| x.ms)),
                        ratio_spread(&col(&cast, |x| x.cpu_ms), &col(t, |x| x.cpu_ms)),
                        ratio_spread(&col(&whole, |x| x.ms), &col(t, |x| x.ms)),
                    )
                }
                None => ("-".into(), "-".into(), "-".into()),
            };
            let s = series.name();
            // The summary row for `benches/compare.sh`: our CPU intensity frame against VTK
            // fixed-point's ray cast, with the image check added below.
            let mut summary = None;
            if let (Some(f), Some((_, t))) = (
                fixed,
                entries
                    .iter()
                    .zip(&ours)
                    .find(|(e, _)| !e.gpu && e.mode == Mode::Intensity),
            ) {
                let cast: Vec<Timing> = f.iter().map(|x| x.cast).collect();
                summary = Some(format!(
                    "| renderer: {name} {size}^2, {} camera | VTK fixed-point CPU caster, volume as {}; ours: whole render() into memory, VTK: ray cast alone; {} threads each; {frames} rounds | {} ms | {} ms | {} |",
                    if series == Series::Still { "still (our rays reused)" } else { "orbiting (every frame a new view)" },
                    vtk.as_ref().map_or("?", |v| v.dtype.as_str()),
                    rayon::current_num_threads(),
                    spread0(&col(t, |t| t.ms)),
                    spread0(&col(&cast, |t| t.ms)),
                    ratio_spread(&col(&cast, |x| x.ms), &col(t, |x| x.ms)),
                ));
            }
            for (e, t) in entries.iter().zip(&ours) {
                let (rw, rc, rr) = if e.mode == Mode::Intensity {
                    ratios(t)
                } else {
                    ("-".into(), "-".into(), "-".into())
                };
                let first = if series == Series::Still {
                    format!("{:.0}", e.first)
                } else {
                    "-".into()
                };
                println!(
                    "| {name} | {s} | {:?} | {} | {first} | {} | {} | {rw} | {rc} | {rr} |",
                    e.mode,
                    e.label,
                    spread0(&col(t, |t| t.ms)),
                    spread0(&col(t, |t| t.cpu_ms)),
                );
            }
            for (m, t) in mappers.iter().zip(&theirs) {
                let cast: Vec<Timing> = t.iter().map(|x| x.cast).collect();
                let whole: Vec<Timing> = t.iter().map(|x| x.render).collect();
                if cast.iter().any(|x| x.ms.is_finite()) {
                    println!(
                        "| {name} | {s} | Intensity | {m}, ray cast alone | - | {} | {} | 1 | 1 | - |",
                        spread0(&col(&cast, |t| t.ms)),
                        spread0(&col(&cast, |t| t.cpu_ms)),
                    );
                }
                println!(
                    "| {name} | {s} | Intensity | {m}, whole Render() | - | {} | {} | - | - | 1 |",
                    spread0(&col(&whole, |t| t.ms)),
                    spread0(&col(&whole, |t| t.cpu_ms)),
                );
            }
            // Images of the series' last view, ours against VTK's.
            let Some(cpu) = entries
                .iter()
                .find(|e| !e.gpu && e.mode == Mode::Intensity)
                .map(|e| e.image.clone())
            else {
                continue;
            };
            cpu.save_png(&out.join(format!("{name}-{s}-neuvolex-Intensity.png")))
                .expect("png");
            for e in entries
                .iter()
                .filter(|e| e.gpu && e.mode == Mode::Intensity)
            {
                equivalence.push(format!(
                    "| {name} | {s} | {} against neuvolex CPU | {} |",
                    e.label,
                    cells(&compare(&e.image, &cpu))
                ));
            }
            if series == Series::Still {
                side_by_side.push(cpu.clone());
            }
            for m in &mappers {
                let png = PathBuf::from(format!("{}{s}-{m}.png", prefix.display()));
                if let Some(v) = vtk.as_mut() {
                    v.save(m, &png);
                }
                match Image::load_png(&png) {
                    Ok(i) => {
                        let c = compare(&cpu, &i);
                        equivalence.push(format!(
                            "| {name} | {s} | neuvolex CPU against {m} | {} |",
                            cells(&c)
                        ));
                        if m == "vtk-fixedpoint-cpu" {
                            if let (Some(row), Ok((mean, _, ssim))) = (summary.take(), c) {
                                summaries.push(format!(
                                    "{row} image mean abs diff {mean:.4}, SSIM {ssim:.3} (bound: mean abs diff <= {MAX_MEAN_DIFF}, SSIM >= {MIN_SSIM}: {}) |",
                                    if mean <= MAX_MEAN_DIFF && ssim >= MIN_SSIM { "within" } else { "EXCEEDED" }
                                ));
                            }
                        }
                        if series == Series::Still {
                            side_by_side.push(i);
                        }
                    }
                    Err(e) => eprintln!("no VTK image {}: {e}", png.display()),
                }
            }
            if series == Series::Still {
                for e in entries
                    .iter()
                    .filter(|e| !e.gpu && e.mode != Mode::Intensity)
                {
                    e.image
                        .save_png(&out.join(format!("{name}-neuvolex-{:?}.png", e.mode)))
                        .expect("png");
                }
            }
        }
        drop(vtk);
        if side_by_side.len() > 1 {
            let refs: Vec<&Image> = side_by_side.iter().collect();
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
    if !equivalence.is_empty() {
        println!();
        println!("Images of the same view (the still view, and the orbit's last): mean and largest absolute difference of the RGB channels in [0, 1], and SSIM of the luma (7x7 windows, as scikit-image).");
        println!("| volume | camera | images | mean abs diff | max abs diff | SSIM |");
        println!("|---|---|---|---|---|---|");
        for l in equivalence {
            println!("{l}");
        }
    }
    for l in summaries {
        println!("summary: {l}");
    }
}
