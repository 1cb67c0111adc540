//! The renderer: analytic cases, mode normalisation, incremental updates, determinism,
//! extremes, bad parameters, and regression images on real data.

use neuvolex_bricks::open_volume;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_formats::MemVolume;
use neuvolex_render::source::ChannelClass;
use neuvolex_render::{
    BrickSource, Camera, Image, MemSource, Mode, Projection, RenderParams, Renderer, StoreSource,
    TfFile, VolumeGeom,
};
use neuvolex_tests::{blobs, shared, store_of, workspace};
use std::path::Path;
use std::sync::Arc;

fn tf(json: &str) -> TfFile {
    TfFile::parse(json, Path::new("test.json")).unwrap()
}

fn geom(dims: [usize; 3], brick: usize) -> VolumeGeom {
    VolumeGeom {
        dims,
        spacing: [1.0; 3],
        brick,
    }
}

fn flat(mode: Mode, size: usize) -> RenderParams {
    RenderParams {
        width: size,
        height: size,
        mode,
        shading: None,
        ert: 1.0,
        camera: Camera {
            azimuth: 90.0,
            elevation: 0.0,
            projection: Projection::Orthographic,
            ..Camera::default()
        },
        ..RenderParams::default()
    }
}

fn render<S: BrickSource>(src: S, p: &RenderParams, t: &TfFile) -> (Image, Renderer<S>) {
    let luts = t.compile(&src.normaliser(), &src.classes());
    let mut r = Renderer::new(src, 64 << 20);
    let img = r.render(p, &luts).unwrap();
    (img, r)
}

fn centre(img: &Image) -> usize {
    (img.height / 2) * img.width + img.width / 2
}

#[test]
fn homogeneous_slab_transmits_one_minus_a_to_the_n_at_any_step() {
    // A constant 20-voxel slab seen along x; opacity 0.1 per voxel length.
    let dims = [20, 24, 24];
    let t = tf(r#"{"space":"normalised","intensity":{"color":[[0,1,0.5,0]],"opacity":[[0,0.1]]}}"#);
    let want = 1.0 - 0.9f32.powi(20);
    for step in [1.0, 0.5, 0.25, 0.125] {
        let src = MemSource::new(geom(dims, 8), vec![7.0; 20 * 24 * 24], vec![], vec![]).unwrap();
        let p = RenderParams {
            step,
            ..flat(Mode::Intensity, 33)
        };
        let (img, _) = render(src, &p, &t);
        let a = img.alpha[centre(&img)];
        assert!((a - want).abs() < 1e-4, "step {step}: alpha {a} vs {want}");
        let c = img.rgb[centre(&img)];
        assert!((c[0] - want).abs() < 1e-4 && (c[1] - 0.5 * want).abs() < 1e-4);
    }
}

#[test]
fn empty_volume_gives_the_background_and_loads_nothing() {
    let src = MemSource::new(geom([40, 30, 20], 16), vec![0.0; 24000], vec![], vec![]).unwrap();
    let t = tf(r#"{"space":"raw","intensity":{"opacity":[[0,0],[0.5,0],[1,1]]}}"#);
    let p = RenderParams {
        background: [0.2, 0.3, 0.4],
        ..RenderParams::default()
    };
    let (img, r) = render(src, &p, &t);
    assert!(img.rgb.iter().all(|c| *c == [0.2, 0.3, 0.4]));
    let s = r.stats();
    assert_eq!(s.marched, 0, "{s:?}");
    assert_eq!(
        s.skipped_unloaded, s.bricks,
        "empty bricks are skipped unloaded"
    );
}

#[test]
fn a_single_opaque_voxel_lands_at_its_projected_pixel() {
    let dims = [33, 29, 31];
    let v = [21usize, 9, 17];
    for projection in [Projection::Perspective, Projection::Orthographic] {
        let mut vals = vec![0.0; dims.iter().product()];
        vals[(v[2] * dims[1] + v[1]) * dims[0] + v[0]] = 1.0;
        let src = MemSource::new(geom(dims, 8), vals, vec![], vec![]).unwrap();
        let t = tf(r#"{"space":"normalised","intensity":{"opacity":[[0.3,0],[0.31,1]]}}"#);
        let p = RenderParams {
            width: 96,
            height: 80,
            shading: None,
            camera: Camera {
                azimuth: 33.0,
                elevation: 24.0,
                distance: 2.5,
                projection,
                ..Camera::default()
            },
            ..RenderParams::default()
        };
        let luts = t.compile(&src.normaliser(), &[]);
        let frame = neuvolex_render::march::Frame::new(p, src.geom(), &luts).unwrap();
        let (px, py) = frame
            .view
            .project(frame.world(v.map(|x| x as f32)))
            .unwrap();
        let (img, _) = render(src, &p, &t);
        let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
        for j in 0..img.height {
            for i in 0..img.width {
                let a = img.alpha[j * img.width + i];
                sx += a * (i as f32 + 0.5);
                sy += a * (j as f32 + 0.5);
                sw += a;
            }
        }
        assert!(sw > 0.5, "{projection:?}: the voxel is visible");
        let (cx, cy) = (sx / sw, sy / sw);
        assert!(
            (cx - px).abs() < 1.0 && (cy - py).abs() < 1.0,
            "{projection:?}: centroid ({cx}, {cy}) vs projection ({px}, {py})"
        );
    }
}

fn two_classes() -> Vec<ChannelClass> {
    vec![(1, [1.0, 0.0, 0.0], false), (2, [0.0, 1.0, 0.0], false)]
}

#[test]
fn probability_modes_follow_the_paper_formulas() {
    // Constant intensity and probabilities p1 = 0.6, p2 = 0.4 everywhere.
    let dims = [16, 12, 12];
    let n = 16 * 12 * 12;
    let probs: Vec<u8> = (0..n).flat_map(|_| [153u8, 102]).collect();
    let mk = || MemSource::new(geom(dims, 8), vec![3.0; n], two_classes(), probs.clone()).unwrap();
    let slab = |alpha: f32| 1.0 - (1.0 - alpha).powi(16);
    // Probabilistic: alpha = sum a_n(p_n) p_n with a constant per-class opacity.
    let t = tf(r#"{"classes":[
        {"id":1,"probability":{"color":[[0,1,0,0]],"opacity":[[0,0.2]]}},
        {"id":2,"probability":{"color":[[0,0,1,0]],"opacity":[[0,0.4]]}}]}"#);
    let (img, _) = render(mk(), &flat(Mode::Probabilistic, 17), &t);
    let a = 0.2 * 0.6 + 0.4 * 0.4;
    let c = img.rgb[centre(&img)];
    assert!((img.alpha[centre(&img)] - slab(a)).abs() < 1e-3);
    // C = sum TF_c(p) p, composited with weight alpha: red 0.6, green 0.4 of the opacity.
    assert!((c[0] / c[1] - 1.5).abs() < 0.02, "{c:?}");
    // Probability-intensity, both pass: normalised by W = 1.
    let t = tf(r#"{"classes":[
        {"id":1,"tau":0.3,"intensity":{"color":[[0,1,0,0]],"opacity":[[0,0.2]]}},
        {"id":2,"tau":0.3,"intensity":{"color":[[0,0,1,0]],"opacity":[[0,0.4]]}}]}"#);
    let (img, _) = render(mk(), &flat(Mode::ProbIntensity, 17), &t);
    assert!((img.alpha[centre(&img)] - slab(0.28)).abs() < 1e-3);
    // Only class 1 passes: W = 0.6, so colour and opacity are exactly class 1's.
    let t = tf(r#"{"classes":[
        {"id":1,"tau":0.5,"intensity":{"color":[[0,1,0,0]],"opacity":[[0,0.2]]}},
        {"id":2,"tau":0.5,"intensity":{"color":[[0,0,1,0]],"opacity":[[0,0.4]]}}]}"#);
    let (img, _) = render(mk(), &flat(Mode::ProbIntensity, 17), &t);
    let c = img.rgb[centre(&img)];
    assert!((img.alpha[centre(&img)] - slab(0.2)).abs() < 1e-3);
    assert!(c[1] == 0.0 && (c[0] - slab(0.2)).abs() < 1e-3, "{c:?}");
    // No class passes: nothing is drawn.
    let t = tf(r#"{"classes":[{"id":1,"tau":0.9},{"id":2,"tau":0.9}]}"#);
    let (img, r) = render(mk(), &flat(Mode::ProbIntensity, 17), &t);
    assert!(img.alpha.iter().all(|&a| a == 0.0));
    assert_eq!(r.stats().marched, 0, "bricks below tau are skipped");
}

/// A scene with structure and two classes split at x = 20.
fn scene(dims: [usize; 3]) -> (Vec<f32>, Vec<u8>) {
    let v = blobs(dims);
    let mut p = Vec::with_capacity(v.len() * 2);
    for (i, &x) in v.iter().enumerate() {
        let xi = i % dims[0];
        let on = x > 40.0;
        p.extend([(on && xi < 20) as u8 * 230, (on && xi >= 20) as u8 * 200]);
    }
    (v, p)
}

#[test]
fn updating_changed_bricks_equals_a_full_render_and_touches_fewer_pixels() {
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let t = TfFile::preset("grey").unwrap();
    let params = RenderParams {
        width: 96,
        height: 96,
        mode: Mode::Probabilistic,
        ..RenderParams::default()
    };
    let src = MemSource::new(geom(dims, 8), v.clone(), two_classes(), p.clone()).unwrap();
    let luts = t.compile(&src.normaliser(), &src.classes());
    let mut r = Renderer::new(src, 64 << 20);
    let before = r.render(&params, &luts).unwrap();
    let full_pixels = r.stats().pixels;
    // New probabilities in brick (1, 1, 1) only: class 2 everywhere in it.
    let p2 = class2_in_brick_111(&p, dims);
    let changed = [1usize, 1, 1];
    r.source_mut().set_probs(p2.clone()).unwrap();
    let updated = r.update_bricks(&[changed]).unwrap().unwrap();
    let touched = r.stats().pixels;
    let fresh_src = MemSource::new(geom(dims, 8), v, two_classes(), p2).unwrap();
    let mut fresh = Renderer::new(fresh_src, 64 << 20);
    let want = fresh.render(&params, &luts).unwrap();
    assert_eq!(updated, want, "the update equals a full render");
    assert_ne!(updated, before, "the change is visible");
    assert!(
        touched * 3 < full_pixels,
        "re-rendered {touched} of {full_pixels} pixels"
    );
    assert!(r.update_bricks(&[[9, 9, 9]]).is_err(), "outside the grid");
}

#[test]
fn one_renderer_across_tables_modes_and_views_draws_what_a_fresh_one_draws() {
    // A renderer keeps each brick's cell map (empty-space skipping) from frame to frame; a
    // map made under other tables or another mode must not be used.
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let low = tf(
        r#"{"space":"normalised","intensity":{"opacity":[[0.1,0],[0.15,0.3],[0.3,0.3],[0.31,0]]}}"#,
    );
    let high = tf(r#"{"space":"normalised","intensity":{"opacity":[[0.5,0],[0.55,0.6]]}}"#);
    let grey = TfFile::preset("grey").unwrap();
    let src = || MemSource::new(geom(dims, 8), v.clone(), two_classes(), p.clone()).unwrap();
    let mut kept = Renderer::new(src(), 64 << 20);
    let base = RenderParams {
        width: 64,
        height: 64,
        ..RenderParams::default()
    };
    let turned = RenderParams {
        camera: Camera {
            azimuth: 75.0,
            elevation: -20.0,
            ..Camera::default()
        },
        ..base
    };
    let mut seen = Vec::new();
    for (t, params) in [
        (&low, base),
        (&low, turned),
        (&high, turned),
        (&high, base),
        (
            &grey,
            RenderParams {
                mode: Mode::Probabilistic,
                ..base
            },
        ),
        (&grey, base),
        (&low, base),
    ] {
        let luts = t.compile(&kept.source().normaliser(), &kept.source().classes());
        let img = kept.render(&params, &luts).unwrap();
        let mut fresh = Renderer::new(src(), 64 << 20);
        let want = fresh.render(&params, &luts).unwrap();
        assert_eq!(img, want, "{:?} {:?}", params.mode, params.camera);
        seen.push(img);
    }
    // The tables show different parts of the volume (else a stale map could pass unseen).
    assert_ne!(seen[1], seen[2]);
    assert_ne!(seen[0], seen[3]);
    assert_eq!(seen[0], seen[6]);
}

#[test]
fn a_frame_of_one_batch_stops_at_the_next_row_once_cancelled() {
    // 3x3x2 bricks of 16: one batch, so only the row-by-row poll can stop the frame.
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let src = MemSource::new(geom(dims, 16), v, two_classes(), p).unwrap();
    let t = TfFile::preset("grey").unwrap();
    let luts = t.compile(&src.normaliser(), &src.classes());
    let params = RenderParams {
        width: 128,
        height: 128,
        ..RenderParams::default()
    };
    let mut r = Renderer::new(src, 64 << 20);
    let want = r.render(&params, &luts).unwrap();
    let polls = Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let seen = polls.clone();
    r.set_cancel(Some(Arc::new(move || {
        seen.fetch_add(1, std::sync::atomic::Ordering::SeqCst) >= 3
    })));
    let e = r.render(&params, &luts).unwrap_err();
    assert!(matches!(e, neuvolex_render::RenderError::Cancelled), "{e}");
    // Polled once before the batch, then per row until the fourth poll said stop.
    let n = polls.load(std::sync::atomic::Ordering::SeqCst);
    assert!((4..=8).contains(&n), "{n} polls");
    // The next frame renders from scratch, whole.
    r.set_cancel(None);
    assert_eq!(r.render(&params, &luts).unwrap(), want);
}

#[test]
fn progressive_passes_refine_to_the_full_render() {
    let dims = [40, 36, 32];
    let src = MemSource::new(geom(dims, 16), blobs(dims), vec![], vec![]).unwrap();
    let t = TfFile::preset("grey").unwrap();
    let luts = t.compile(&src.normaliser(), &[]);
    let params = RenderParams {
        width: 64,
        height: 48,
        ..RenderParams::default()
    };
    let mut r = Renderer::new(src, 64 << 20);
    let mut sizes = Vec::new();
    let last = r
        .progressive(&params, &luts, &[4, 2, 1], |pass, img| {
            sizes.push((pass.divisor, img.width, img.height, pass.stats.samples))
        })
        .unwrap();
    assert_eq!(sizes.len(), 3);
    assert_eq!((sizes[0].1, sizes[0].2), (16, 12));
    assert_eq!((sizes[2].1, sizes[2].2), (64, 48));
    assert!(
        sizes[0].3 * 8 < sizes[2].3,
        "coarse passes are cheap: {sizes:?}"
    );
    assert_eq!(last, r.render(&params, &luts).unwrap());
}

#[test]
fn renders_are_identical_across_thread_counts_and_projections_differ() {
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let t = TfFile::preset("grey").unwrap();
    let run = |threads: usize, projection| {
        let src = MemSource::new(geom(dims, 8), v.clone(), two_classes(), p.clone()).unwrap();
        let params = RenderParams {
            width: 64,
            height: 64,
            mode: Mode::ProbIntensity,
            camera: Camera {
                projection,
                ..Camera::default()
            },
            ..RenderParams::default()
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| render(src, &params, &t).0)
    };
    let a = run(1, Projection::Perspective);
    assert_eq!(a, run(2, Projection::Perspective));
    assert!(a.alpha.iter().any(|&x| x > 0.5), "something is drawn");
    assert_ne!(a, run(1, Projection::Orthographic));
}

#[test]
fn extreme_values_and_constant_volumes_render_finite_images() {
    let dims = [24, 20, 16];
    let base = blobs(dims);
    let t = TfFile::preset("grey").unwrap();
    for (name, scale, offset) in [
        ("huge", 1e30f32, 0.0f32),
        ("tiny", 1e-30, 0.0),
        ("offset", 1.0, 1e7),
        ("constant", 0.0, 5.0),
        ("constant huge", 0.0, -3e38),
    ] {
        let vals: Vec<f32> = base.iter().map(|x| x * scale + offset).collect();
        let src = MemSource::new(geom(dims, 8), vals, vec![], vec![]).unwrap();
        for shading in [None, Some(neuvolex_render::Shading::default())] {
            let p = RenderParams {
                width: 40,
                height: 40,
                shading,
                ..RenderParams::default()
            };
            let luts = t.compile(&src.normaliser(), &[]);
            let mut r = Renderer::new(&src, 1 << 20);
            let img = r.render(&p, &luts).unwrap();
            assert!(
                img.rgb
                    .iter()
                    .flatten()
                    .all(|c| c.is_finite() && (0.0..=1.0001).contains(c)),
                "{name}: non-finite or out-of-range pixels"
            );
        }
    }
    // Extreme sample budgets: a tiny step and a 16-voxel step both give finite images.
    let src = MemSource::new(geom(dims, 8), base, vec![], vec![]).unwrap();
    let luts = t.compile(&src.normaliser(), &[]);
    let mut r = Renderer::new(&src, 1 << 20);
    for step in [0.01, 16.0] {
        let p = RenderParams {
            width: 16,
            height: 16,
            step,
            ..RenderParams::default()
        };
        let img = r.render(&p, &luts).unwrap();
        assert!(img.rgb.iter().flatten().all(|c| c.is_finite()));
    }
}

#[test]
fn bad_parameters_and_volumes_get_clear_errors() {
    let dims = [16, 16, 16];
    let src = MemSource::new(geom(dims, 8), vec![1.0; 4096], vec![], vec![]).unwrap();
    let t = TfFile::preset("grey").unwrap();
    let luts = t.compile(&src.normaliser(), &[]);
    let mut r = Renderer::new(&src, 1 << 20);
    let cases: Vec<(RenderParams, &str)> = vec![
        (
            RenderParams {
                width: 0,
                ..Default::default()
            },
            "at least 1x1",
        ),
        (
            RenderParams {
                width: 100_000,
                ..Default::default()
            },
            "exceeds",
        ),
        (
            RenderParams {
                step: 0.0,
                ..Default::default()
            },
            "step",
        ),
        (
            RenderParams {
                step: f32::NAN,
                ..Default::default()
            },
            "step",
        ),
        (
            RenderParams {
                background: [2.0, 0.0, 0.0],
                ..Default::default()
            },
            "background",
        ),
        (
            RenderParams {
                camera: Camera {
                    elevation: 120.0,
                    ..Camera::default()
                },
                ..Default::default()
            },
            "elevation",
        ),
        (
            RenderParams {
                camera: Camera {
                    azimuth: f32::INFINITY,
                    ..Camera::default()
                },
                ..Default::default()
            },
            "finite",
        ),
        (
            RenderParams {
                camera: Camera {
                    fov: 0.0,
                    ..Camera::default()
                },
                ..Default::default()
            },
            "field of view",
        ),
        (
            RenderParams {
                camera: Camera {
                    distance: -1.0,
                    ..Camera::default()
                },
                ..Default::default()
            },
            "distance",
        ),
    ];
    for (p, want) in cases {
        let e = r.render(&p, &luts).unwrap_err().to_string();
        assert!(e.contains(want), "{want}: {e}");
    }
    for (g, vals, want) in [
        (geom([0, 4, 4], 8), vec![], "empty volume"),
        (geom([4, 4, 4], 8), vec![1.0; 10], "values for a"),
        (geom([4, 4, 4], 8), vec![f32::NAN; 64], "not finite"),
        (geom([4, 4, 4], 2), vec![1.0; 64], "too small"),
        (
            VolumeGeom {
                spacing: [1.0, 0.0, 1.0],
                ..geom([4, 4, 4], 8)
            },
            vec![1.0; 64],
            "spacing",
        ),
    ] {
        let e = MemSource::new(g, vals, vec![], vec![])
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(want), "{want}: {e}");
    }
    let e = MemSource::new(geom([4, 4, 4], 8), vec![1.0; 64], two_classes(), vec![0; 5])
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("probabilities"), "{e}");
}

/// The emission-absorption integral along one ray through a field `f(s)` of arc length `s` in
/// `[0, len]` voxels, with opacity `alpha(f)` per voxel length and colour `colour(f)`: front to
/// back, `C = sum T a c`, `T *= 1 - a`, over `n` sub-steps (as `n` grows this is the continuous
/// integral `C = int T(s) sigma(s) c(s) ds` with `sigma = -ln(1 - alpha)`). Returns (RGB, alpha).
fn emission_absorption(
    len: f64,
    n: usize,
    f: impl Fn(f64) -> f64,
    alpha: impl Fn(f64) -> f64,
    colour: impl Fn(f64) -> [f64; 3],
) -> ([f64; 3], f64) {
    let ds = len / n as f64;
    let (mut c, mut t) = ([0.0f64; 3], 1.0f64);
    for k in 0..n {
        let v = f((k as f64 + 0.5) * ds);
        let a = 1.0 - (1.0 - alpha(v)).powf(ds);
        let e = colour(v);
        for (ck, ek) in c.iter_mut().zip(e) {
            *ck += t * a * ek;
        }
        t *= 1.0 - a;
    }
    (c, 1.0 - t)
}

/// An analytic scene whose image is computed here, independently of the renderer: a field
/// linear in x, y and z, seen orthographically along +y (azimuth 0, elevation 0: x to the
/// right, z up, as `camera.rs` documents), with a transfer function linear in the value. Every
/// pixel's ray crosses `ny` voxels, the field along it is linear (edge-clamped in the outer half
/// voxel), and its image is the emission-absorption integral of that field
/// ([`emission_absorption`], 20 000 sub-steps), placed with the documented camera model,
/// within 2e-3 per channel.
#[test]
fn analytic_scene_renders_its_emission_absorption_integral() {
    let dims = [24usize, 32, 20];
    let [nx, ny, nz] = dims;
    let lin = |v: f64, n: usize| v.clamp(0.0, (n - 1) as f64) / (n - 1) as f64;
    let field = |x: f64, y: f64, z: f64| 0.3 * lin(x, nx) + 0.4 * lin(y, ny) + 0.3 * lin(z, nz);
    let mut vals = Vec::with_capacity(nx * ny * nz);
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                vals.push(field(x as f64, y as f64, z as f64) as f32);
            }
        }
    }
    // Opacity 0.1 per voxel length at value 1; colour from (1, 0, 0) to (0, 0.5, 1).
    let t = tf(
        r#"{"space":"raw","intensity":{"color":[[0,1,0,0],[1,0,0.5,1]],"opacity":[[0,0],[1,0.1]]}}"#,
    );
    let alpha = |v: f64| 0.1 * v;
    let colour = |v: f64| [1.0 - v, 0.5 * v, v];
    let (w, h) = (64usize, 64usize);
    let camera = Camera {
        azimuth: 0.0,
        elevation: 0.0,
        distance: 2.4,
        fov: 30.0,
        projection: Projection::Orthographic,
    };
    // The documented orthographic view: half the view height is tan(fov / 2) x distance x the
    // bounding radius (half the box diagonal); voxel v sits at v - (dims - 1) / 2.
    let radius = 0.5 * dims.iter().map(|&d| (d * d) as f64).sum::<f64>().sqrt();
    let half = (15f64).to_radians().tan() * 2.4 * radius;
    for step in [0.5f32, 0.25] {
        let src = MemSource::new(geom(dims, 8), vals.clone(), vec![], vec![]).unwrap();
        let p = RenderParams {
            width: w,
            height: h,
            camera,
            step,
            ..flat(Mode::Intensity, w)
        };
        let (img, _) = render(src, &p, &t);
        let (mut worst, mut sum, mut inside, mut lo, mut hi) = (0.0f64, 0.0f64, 0, 1.0f64, 0.0f64);
        for j in 0..h {
            for i in 0..w {
                let x = ((i as f64 + 0.5) / w as f64 * 2.0 - 1.0) * half + (nx - 1) as f64 / 2.0;
                let z = (1.0 - (j as f64 + 0.5) / h as f64 * 2.0) * half + (nz - 1) as f64 / 2.0;
                let k = j * w + i;
                // The box is [-0.5, n - 0.5] per axis; rays within 0.75 voxel of a side face
                // graze it and are not compared.
                let margin = |v: f64, n: usize| (v + 0.5).min(n as f64 - 0.5 - v);
                let (mx, mz) = (margin(x, nx), margin(z, nz));
                if mx < -0.75 || mz < -0.75 {
                    assert_eq!(img.alpha[k], 0.0, "pixel ({i}, {j}) misses the volume");
                    continue;
                }
                if mx < 0.75 || mz < 0.75 {
                    continue;
                }
                let (c, a) =
                    emission_absorption(ny as f64, 20_000, |s| field(x, s - 0.5, z), alpha, colour);
                let got = img.rgb[k];
                let err = (0..3)
                    .map(|q| (got[q] as f64 - c[q]).abs())
                    .fold((img.alpha[k] as f64 - a).abs(), f64::max);
                assert!(
                    err < 2e-3,
                    "step {step}, pixel ({i}, {j}): rgb {got:?} alpha {} vs {c:?} {a}",
                    img.alpha[k]
                );
                worst = worst.max(err);
                sum += err;
                inside += 1;
                lo = lo.min(a);
                hi = hi.max(a);
            }
        }
        let mean = sum / inside as f64;
        eprintln!("step {step}: {inside} pixels, max error {worst:.5}, mean {mean:.5}, alpha {lo:.3}-{hi:.3}");
        // Most of the image is compared, and the scene is not flat. The bound, 2e-3 per channel
        // (half an 8-bit level), is far below the spread of alpha across the image (over 0.4),
        // and above what sampling a linear field at step 0.5 leaves (measured: 1e-5).
        assert!(inside > w * h / 2, "{inside} pixels compared");
        assert!(hi - lo > 0.1, "alpha spans {lo}-{hi}");
        assert!(mean < 5e-4, "step {step}: mean error {mean}");
    }
}

/// Compares with a committed reference image: a regression check (the references were
/// rendered by this renderer; its correctness is checked against independent references by
/// the analytic tests above). With NEUVOLEX_BLESS=1 a reference that fails the check is
/// rewritten and the test still fails, naming it, so a blessing run never passes silently.
fn regression(name: &str, img: &Image) {
    let path = workspace()
        .join("tests/data/render")
        .join(format!("{name}.png"));
    let bless = std::env::var("NEUVOLEX_BLESS").is_ok_and(|v| v == "1");
    let want = match Image::load_png(&path) {
        Ok(w) => w,
        Err(e) if bless => {
            img.save_png(&path).unwrap();
            panic!(
                "{name}: reference missing ({e}); written to {}",
                path.display()
            );
        }
        Err(e) => panic!("reference missing: {e}"),
    };
    let (max, mean) = img.diff(&want).unwrap();
    eprintln!(
        "{name}: max {max:.4}, mean {mean:.5} against {}",
        path.display()
    );
    // 8-bit references; a mean under 0.5% and no pixel off by more than 12%.
    let ok = mean < 0.005 && max < 0.12;
    if !ok && bless {
        img.save_png(&path).unwrap();
        panic!(
            "{name}: max {max}, mean {mean}; reference rewritten (NEUVOLEX_BLESS=1) at {}",
            path.display()
        );
    }
    assert!(ok, "{name}: max {max}, mean {mean}");
}

#[test]
fn real_abdomen_ct_renders_like_its_reference_images() {
    let (Some(img), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let mut src = open_volume(&img, None).unwrap();
    let (_d, mut store) = store_of(&mut *src, 32);
    let mut l = open_volume(&lab, None).unwrap();
    let classes: Vec<ClassInfo> = ["bone", "kidney_left", "kidney_right", "aorta"]
        .iter()
        .enumerate()
        .map(|(i, n)| ClassInfo {
            id: i as u32 + 1,
            name: n.to_string(),
            color: neuvolex_bricks::synth::palette(i as u32 + 1),
        })
        .collect();
    store
        .add_labels("truth", &mut *l, &classes, &mut |_| {})
        .unwrap();
    let store = Arc::new(store);
    let params = RenderParams {
        width: 128,
        height: 128,
        camera: Camera {
            azimuth: 20.0,
            elevation: 10.0,
            ..Camera::default()
        },
        ..RenderParams::default()
    };
    let bone = TfFile::preset("ct-bone").unwrap();
    let (a, r) = render(StoreSource::new(store.clone()), &params, &bone);
    assert!(
        r.stats().skipped_unloaded + r.stats().skipped_empty > 0,
        "air bricks skipped"
    );
    regression("abdomen_ct_bone", &a);
    // The ground truth as one-hot probabilities, both probability modes.
    for mode in [Mode::Probabilistic, Mode::ProbIntensity] {
        let src = StoreSource::new(store.clone())
            .with_labels("truth")
            .unwrap();
        let soft = TfFile::preset("ct-soft-tissue").unwrap();
        let p = RenderParams { mode, ..params };
        let (img, _) = render(src, &p, &soft);
        regression(&format!("abdomen_ct_truth_{mode:?}").to_lowercase(), &img);
    }
}

#[test]
fn real_neghip_renders_like_its_reference_image() {
    let Some(raw) = shared("scivis/neghip_64x64x64_uint8.raw") else {
        return;
    };
    let bytes = std::fs::read(&raw).unwrap();
    let vol = MemVolume::from_f64(
        [64, 64, 64],
        neuvolex_formats::DType::U8,
        &bytes.iter().map(|&b| b as f64).collect::<Vec<_>>(),
    );
    let mut vol = vol;
    let (_d, store) = store_of(&mut vol, 16);
    let params = RenderParams {
        width: 96,
        height: 96,
        ..RenderParams::default()
    };
    let (img, _) = render(
        StoreSource::new(Arc::new(store)),
        &params,
        &TfFile::preset("grey").unwrap(),
    );
    regression("neghip_grey", &img);
}

/// The GPU renderer, where a wgpu adapter exists (software ones count). Skips where none is
/// found, and fails under CI=true, whose set-up installs lavapipe.
#[cfg(feature = "gpu")]
fn gpu<S: BrickSource>(src: S) -> Option<neuvolex_render::gpu::GpuRenderer<S>> {
    match neuvolex_render::gpu::GpuRenderer::new(src) {
        Ok(r) => {
            eprintln!("gpu adapter: {}", r.adapter());
            Some(r)
        }
        Err(e) if std::env::var("CI").is_ok_and(|v| v == "true") => {
            panic!("no wgpu adapter under CI=true: {e}")
        }
        Err(e) => {
            eprintln!("SKIP: {e}");
            None
        }
    }
}

#[cfg(feature = "gpu")]
#[test]
fn gpu_and_cpu_images_agree() {
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let t = TfFile::preset("grey").unwrap();
    let src = Arc::new(MemSource::new(geom(dims, 8), v, two_classes(), p).unwrap());
    let luts = t.compile(&src.normaliser(), &src.classes());
    let Some(mut g) = gpu(src.clone()) else {
        return;
    };
    let mut c = Renderer::new(src.clone(), 64 << 20);
    let mut worst = (0.0f32, 0.0f32);
    for (mode, projection, shading, batch) in [
        (Mode::Intensity, Projection::Perspective, true, None),
        (Mode::Intensity, Projection::Orthographic, false, None),
        (Mode::Probabilistic, Projection::Perspective, true, None),
        (Mode::ProbIntensity, Projection::Perspective, true, None),
        // Atlases of about two bricks each: many batches, as for a volume beyond GPU memory.
        (
            Mode::ProbIntensity,
            Projection::Perspective,
            true,
            Some(100_000u64),
        ),
    ] {
        let params = RenderParams {
            width: 80,
            height: 64,
            mode,
            shading: shading.then(neuvolex_render::Shading::default),
            camera: Camera {
                azimuth: 40.0,
                elevation: 25.0,
                projection,
                ..Camera::default()
            },
            background: [0.1, 0.1, 0.2],
            ..RenderParams::default()
        };
        if let Some(b) = batch {
            g.set_max_batch_bytes(b);
        }
        let a = c.render(&params, &luts).unwrap();
        let b = g.render(&params, &luts).unwrap();
        let (max, mean) = a.diff(&b).unwrap();
        eprintln!("{mode:?} {projection:?} shading {shading} batch {batch:?}: max {max:.5}, mean {mean:.6}");
        assert!(
            a.alpha.iter().any(|&x| x > 0.3),
            "{mode:?}: something is drawn"
        );
        worst = (worst.0.max(max), worst.1.max(mean));
    }
    // The stated bound: no channel off by more than 2/255, and a mean under 1e-4.
    assert!(
        worst.0 < 2.0 / 255.0 && worst.1 < 1e-4,
        "CPU and GPU differ: max {}, mean {}",
        worst.0,
        worst.1
    );
}

/// Two-class probabilities `p` of a `dims` volume with brick (1, 1, 1) of 8^3 set to class 2.
fn class2_in_brick_111(p: &[u8], dims: [usize; 3]) -> Vec<u8> {
    let mut p2 = p.to_vec();
    for z in 8..16 {
        for y in 8..16 {
            for x in 8..16 {
                let i = (z * dims[1] + y) * dims[0] + x;
                p2[2 * i] = 0;
                p2[2 * i + 1] = 255;
            }
        }
    }
    p2
}

/// The GPU renderer keeps bricks resident between frames: over a moving camera, changed
/// transfer functions and modes, and new probabilities (invalidated by brick), every frame
/// equals a fresh renderer's, bit for bit; a repeated frame uploads no brick, and a change of
/// one brick's probabilities uploads only it and its neighbours. The same holds with pages of
/// about a dozen bricks and a budget of nine (evicting within frames).
#[cfg(feature = "gpu")]
#[test]
fn gpu_resident_frames_equal_fresh_renders() {
    let dims = [40, 36, 32];
    let (v, p) = scene(dims);
    let mk =
        |p: &[u8]| MemSource::new(geom(dims, 8), v.clone(), two_classes(), p.to_vec()).unwrap();
    // New probabilities in brick (1, 1, 1): class 2 everywhere in it.
    let p2 = class2_in_brick_111(&p, dims);
    let grey = TfFile::preset("grey").unwrap();
    let other = tf(r#"{"space":"normalised",
        "intensity":{"color":[[0,1,0.5,0],[1,0,0.5,1]],"opacity":[[0.2,0],[1,0.6]]},
        "classes":[
        {"id":1,"tau":0.3,"probability":{"opacity":[[0,0],[1,0.5]]},"intensity":{"opacity":[[0,0.1],[1,0.8]]}},
        {"id":2,"tau":0.3,"probability":{"opacity":[[0,0],[1,0.9]]},"intensity":{"opacity":[[0.3,0],[1,0.5]]}}]}"#);
    let frame = |mode, azimuth, elevation, projection| RenderParams {
        width: 80,
        height: 64,
        mode,
        shading: Some(neuvolex_render::Shading::default()),
        camera: Camera {
            azimuth,
            elevation,
            projection,
            ..Camera::default()
        },
        background: [0.1, 0.1, 0.2],
        ..RenderParams::default()
    };
    let (pi, pr, it) = (Mode::ProbIntensity, Mode::Probabilistic, Mode::Intensity);
    let (persp, ortho) = (Projection::Perspective, Projection::Orthographic);
    // (params, transfer function, new probabilities before the frame)
    let frames = [
        (frame(pi, 40.0, 25.0, persp), &grey, false),
        (frame(pi, 40.0, 25.0, persp), &grey, false),
        (frame(pi, 75.0, 10.0, persp), &grey, false),
        (frame(pi, 75.0, 10.0, persp), &other, false),
        (frame(pr, 110.0, -20.0, ortho), &other, false),
        (frame(it, 110.0, -20.0, persp), &grey, false),
        (frame(pi, 110.0, -20.0, persp), &other, true),
        (frame(pi, 110.0, -20.0, persp), &other, false),
    ];
    for small in [false, true] {
        let Some(mut g) = gpu(mk(&p)) else {
            return;
        };
        if small {
            g.set_max_batch_bytes(50_000);
            g.set_resident_bytes(100_000);
        }
        let mut probs = &p;
        let mut evicted = 0;
        for (n, (params, t, change)) in frames.iter().enumerate() {
            if *change {
                g.source_mut().set_probs(p2.clone()).unwrap();
                g.invalidate(&[[1, 1, 1]]).unwrap();
                probs = &p2;
            }
            let luts = t.compile(&g.source().normaliser(), &g.source().classes());
            let img = g.render(params, &luts).unwrap();
            let s = g.last_stats;
            eprintln!("small {small} frame {n}: {s:?}");
            evicted += s.evicted;
            let want = gpu(mk(probs)).unwrap().render(params, &luts).unwrap();
            assert!(
                img.alpha.iter().any(|&a| a > 0.3),
                "frame {n}: something is drawn"
            );
            assert!(
                img == want,
                "small {small} frame {n}: differs from a fresh renderer's: {:?}",
                img.diff(&want)
            );
            if !small && n == 1 {
                assert_eq!(
                    (s.loaded, s.uploaded, s.brick_bytes),
                    (0, 0, 0),
                    "a repeated frame uploads nothing"
                );
                assert_eq!(s.batches, 1);
            }
            if !small && *change {
                assert!(
                    s.uploaded > 0 && s.uploaded <= 27,
                    "re-uploaded {} bricks",
                    s.uploaded
                );
            }
        }
        assert!(g.invalidate(&[[9, 9, 9]]).is_err(), "outside the grid");
        if small {
            assert!(evicted > 0, "a budget of nine bricks evicts");
        }
    }
}
