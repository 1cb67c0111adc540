//! Scribble-based classification: end to end on the phantom and on the real abdomen CT (F1
//! against ground truth), determinism, and every bad input the issue lists.

use neuvolex_bricks::synth::{Phantom, PhantomChannel, PhantomParams};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::features::Quantise;
use neuvolex_classify::{
    classify_brick, classify_volume, f1_scores, fit, load_scribbles, output_labels, simulate,
    training_set, BrickFeatures, ClassTable, ClassifyConfig, ClassifyError, FeatureSet,
    ForestConfig, Level, Scribbles, SimConfig,
};
use neuvolex_features::extract::write_features;
use neuvolex_features::{train, Budget, FeatureKind, InrConfig, TrainConfig};
use neuvolex_formats::{MemVolume, VolumeSource};
use neuvolex_tests::{shared, store_of};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn truth_of(src: &mut dyn VolumeSource) -> Vec<u32> {
    MemVolume::read_all(src)
        .unwrap()
        .to_f32()
        .iter()
        .map(|&v| v as u32)
        .collect()
}

fn cfg(trees: usize) -> ClassifyConfig {
    ClassifyConfig {
        forest: ForestConfig {
            trees,
            ..ClassifyConfig::default().forest
        },
        ..Default::default()
    }
}

fn run(
    store: &BrickStore,
    set: &str,
    scr: &Scribbles,
    c: &ClassifyConfig,
) -> Result<neuvolex_classify::Classified, ClassifyError> {
    let fx = BrickFeatures::new(store, set.parse::<FeatureSet>().unwrap(), None, false)?;
    let ts = training_set(&fx, scr, c.background)?;
    let f = fit(&ts, &c.forest)?;
    classify_volume(&fx, &f, &ts, c, None, &|_| {})
}

#[test]
fn phantom_classification_is_accurate_and_deterministic() {
    let p = PhantomParams::with_size(64, 1);
    let (_d, store) = store_of(&mut Phantom::new(p, PhantomChannel::Image), 16);
    let truth = truth_of(&mut Phantom::new(p, PhantomChannel::Labels));
    let (_, scr) = simulate(
        &mut Phantom::new(p, PhantomChannel::Labels),
        &SimConfig {
            level: Level::S4,
            ..Default::default()
        },
    )
    .unwrap();
    eprintln!("scribbled {:?}", scr.counts());
    let c = cfg(40);
    let a = run(&store, "local", &scr, &c).unwrap();
    let f1 = f1_scores(&a.labels, &truth, &[1, 2, 3, 4, 5]);
    eprintln!("phantom local S4: {f1:?}");
    // Bone and liver are intensity-distinct; the kidneys need position.
    assert!(f1[0].f1 > 0.6, "bone F1 {}", f1[0].f1);
    assert!(f1[4].f1 > 0.6, "liver F1 {}", f1[4].f1);
    // Intensity alone cannot tell the kidneys apart: position must beat it.
    let i = run(&store, "intensity", &scr, &c).unwrap();
    let fi = f1_scores(&i.labels, &truth, &[2, 3]);
    let fl = &f1[1..3];
    assert!(
        fl[0].f1 + fl[1].f1 > fi[0].f1 + fi[1].f1,
        "local {fl:?} vs intensity {fi:?}"
    );
    // Same inputs, same labels, whatever the thread count.
    let b = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| run(&store, "local", &scr, &c).unwrap());
    assert_eq!(a.labels, b.labels);
    // Empty bricks were skipped, not predicted: exactly the bricks whose every voxel lies below
    // the store's background threshold and that hold no ROI scribble, found here from the
    // phantom's voxels and the scribbles themselves.
    let image = truth_of_f32(&mut Phantom::new(p, PhantomChannel::Image));
    let empty = empty_bricks(&image, p.dims, 16, store.info().background, &scr, 255);
    let total = store.bricks().count();
    eprintln!("{} of {total} bricks empty", empty.len());
    assert!(scr.counts().contains_key(&255), "background is scribbled");
    assert!(
        !empty.is_empty() && empty.len() < total,
        "the phantom has empty and occupied bricks: {} of {total}",
        empty.len()
    );
    assert!(a.bricks_skipped > 0);
    assert_eq!(a.bricks_skipped, empty.len());
    assert_eq!(a.bricks_predicted, total - empty.len());
    let all = run(
        &store,
        "local",
        &scr,
        &ClassifyConfig {
            skip_empty: false,
            ..c.clone()
        },
    )
    .unwrap();
    assert_eq!((all.bricks_skipped, all.bricks_predicted), (0, total));
    // Brick by brick, the skipped ones are the empty ones.
    let fx = BrickFeatures::new(&store, "local".parse().unwrap(), None, false).unwrap();
    let ts = training_set(&fx, &scr, c.background).unwrap();
    let forest = fit(&ts, &c.forest).unwrap();
    let out = output_labels(&ts.labels, c.background);
    for b in store.bricks() {
        let r = classify_brick(&fx, &forest, &ts.labels, &out, &ts.roi_bricks, &c, &b).unwrap();
        assert_eq!(r.skipped, empty.contains(&b.index), "brick {:?}", b.index);
    }
    // A skipped brick is background; every other voxel is labelled as without skipping.
    let dims = p.dims;
    for (i, (&x, &y)) in a.labels.iter().zip(&all.labels).enumerate() {
        let v = [
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        ];
        if empty.contains(&v.map(|k| k / 16)) {
            assert_eq!(x, 0, "voxel {v:?} of a skipped brick");
        } else {
            assert_eq!(x, y, "voxel {v:?} of a predicted brick");
        }
    }
}

fn truth_of_f32(src: &mut dyn VolumeSource) -> Vec<f32> {
    MemVolume::read_all(src).unwrap().to_f32()
}

/// Grid indices of the bricks of side `brick` whose voxels all lie below `threshold` and that
/// hold no scribble other than `background`.
fn empty_bricks(
    image: &[f32],
    dims: [usize; 3],
    brick: usize,
    threshold: f64,
    scr: &Scribbles,
    background: u32,
) -> std::collections::BTreeSet<[usize; 3]> {
    let of = |i: usize| {
        [
            i % dims[0] / brick,
            (i / dims[0]) % dims[1] / brick,
            i / (dims[0] * dims[1]) / brick,
        ]
    };
    let grid = dims.map(|d| d.div_ceil(brick));
    let mut empty: std::collections::BTreeSet<[usize; 3]> = (0..grid[2])
        .flat_map(|z| (0..grid[1]).flat_map(move |y| (0..grid[0]).map(move |x| [x, y, z])))
        .collect();
    for (i, &v) in image.iter().enumerate() {
        if v as f64 >= threshold {
            empty.remove(&of(i));
        }
    }
    for &(i, c) in &scr.voxels {
        if c != background {
            empty.remove(&of(i as usize));
        }
    }
    empty
}

#[test]
fn learned_features_classify_and_stored_equal_on_demand() {
    let p = PhantomParams::with_size(48, 2);
    let (_d, store) = store_of(&mut Phantom::new(p, PhantomChannel::Image), 16);
    let m = small_model(&store, 8, 14, 2048, 60_000);
    let (_, scr) = simulate(
        &mut Phantom::new(p, PhantomChannel::Labels),
        &SimConfig {
            level: Level::S4,
            ..Default::default()
        },
    )
    .unwrap();
    eprintln!("scribbled {:?}", scr.counts());
    let c = cfg(20);
    let set: FeatureSet = "inr".parse().unwrap();
    let fx = BrickFeatures::new(&store, set.clone(), Some(m.clone()), false).unwrap();
    let ts = training_set(&fx, &scr, 255).unwrap();
    assert_eq!(ts.d, fx.channels());
    assert!(ts.x.iter().all(|v| v.is_finite()));
    let f = fit(&ts, &c.forest).unwrap();
    let a = classify_volume(&fx, &f, &ts, &c, None, &|_| {}).unwrap();
    let truth = truth_of(&mut Phantom::new(p, PhantomChannel::Labels));
    let f1 = f1_scores(&a.labels, &truth, &[1, 5]);
    eprintln!("phantom inr S4: {f1:?}");
    assert!(f1[0].f1 > 0.4 && f1[1].f1 > 0.5, "{f1:?}");
    // Stored f16 features (all bricks) give the f16-quantised on-demand features exactly.
    write_features(&store, &m, FeatureKind::Concat, true, &mut |_| {}).unwrap();
    let mut od = BrickFeatures::new(&store, set.clone(), Some(m.clone()), false).unwrap();
    od.set_quantise(Quantise::F16);
    let st = BrickFeatures::new(&store, set, Some(m), true).unwrap();
    let b = store.bricks().nth(3).unwrap();
    let (x, y) = (od.brick(&b).unwrap(), st.brick(&b).unwrap());
    let ch = od.channels();
    let local = neuvolex_filters::Classic::Local.channels();
    for (r0, r1) in x.chunks(ch).zip(y.chunks(ch)) {
        assert_eq!(&r0[..ch - local], &r1[..ch - local]);
    }
}

#[test]
fn real_abdomen_ct_local_features_find_bone_and_kidneys() {
    let (Some(img), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let mut src = neuvolex_bricks::open_volume(&img, None).unwrap();
    let (_d, store) = store_of(&mut *src, 64);
    let mut l = neuvolex_bricks::open_volume(&lab, None).unwrap();
    let truth = truth_of(&mut *l);
    let mut l = neuvolex_bricks::open_volume(&lab, None).unwrap();
    let (_, scr) = simulate(
        &mut *l,
        &SimConfig {
            level: Level::S4,
            ..Default::default()
        },
    )
    .unwrap();
    let a = run(&store, "local", &scr, &cfg(50)).unwrap();
    let f1 = f1_scores(&a.labels, &truth, &[1, 2, 3, 4]);
    let mean = f1.iter().map(|f| f.f1).sum::<f64>() / 4.0;
    eprintln!("abdomen_ct local S4, 50 trees: {f1:?} mean {mean:.3}");
    assert!(f1[0].f1 > 0.65, "bone F1 {}", f1[0].f1);
    assert!(mean > 0.4, "mean F1 {mean}");
}

/// Trains a small INR on `store` for `samples` samples.
fn small_model(
    store: &BrickStore,
    levels: usize,
    log2_table: u32,
    batch: usize,
    samples: u64,
) -> Arc<neuvolex_features::InrModel> {
    let inr = InrConfig {
        levels,
        log2_table,
        ..Default::default()
    };
    let tc = TrainConfig {
        batch,
        budget: Budget {
            samples: Some(samples),
            ..Default::default()
        },
        preview_every: 0,
        checkpoint_every: 0,
        ..TrainConfig::default()
    };
    let t = train(
        store,
        &inr,
        &tc,
        None,
        None,
        &AtomicBool::new(false),
        &mut |_| {},
    );
    Arc::new(t.expect("train").model)
}

fn phantom_store() -> (tempfile::TempDir, BrickStore, PhantomParams) {
    let p = PhantomParams::with_size(24, 3);
    let (d, s) = store_of(&mut Phantom::new(p, PhantomChannel::Image), 16);
    (d, s, p)
}

fn err_text(r: Result<neuvolex_classify::Classified, ClassifyError>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn bad_scribbles_give_clear_errors() {
    let (_d, store, _) = phantom_store();
    let dims = store.info().dims;
    let c = cfg(5);
    // No labelled voxels.
    let empty = Scribbles {
        dims,
        voxels: vec![],
    };
    assert!(err_text(run(&store, "local", &empty, &c)).contains("no voxel"));
    // One class only.
    let one = Scribbles {
        dims,
        voxels: vec![(10, 1), (11, 1)],
    };
    let e = err_text(run(&store, "local", &one, &c));
    assert!(e.contains("one class only"), "{e}");
    // A grid mismatch.
    let off = Scribbles {
        dims: [dims[0] + 1, dims[1], dims[2]],
        voxels: vec![(10, 1), (11, 255)],
    };
    let e = err_text(run(&store, "local", &off, &c));
    assert!(e.contains("grid"), "{e}");
    // INR features without a trained model.
    let two = Scribbles {
        dims,
        voxels: vec![(10, 1), (11, 255)],
    };
    let e = err_text(run(&store, "paper", &two, &c));
    assert!(e.contains("need a trained INR"), "{e}");
    assert!("local+bogus".parse::<FeatureSet>().is_err());
    assert!("local+local".parse::<FeatureSet>().is_err());
}

#[test]
fn bad_scribble_files_and_class_tables_give_clear_errors() {
    let (d, store, _) = phantom_store();
    let meta = store.meta();
    // Strokes outside the grid.
    let sp = d.path().join("strokes.json");
    std::fs::write(
        &sp,
        r#"[{"class": 1, "axis": "z", "slice": 999, "points": [[1, 1], [5, 5]], "radius": 1}]"#,
    )
    .unwrap();
    let e = load_scribbles(&sp, &meta).unwrap_err().to_string();
    assert!(e.contains("strokes.json") && e.contains("slice 999"), "{e}");
    // Malformed strokes.
    std::fs::write(&sp, r#"[{"class": "bone"}]"#).unwrap();
    let e = load_scribbles(&sp, &meta).unwrap_err().to_string();
    assert!(e.contains("not a stroke list"), "{e}");
    // Good strokes round-trip.
    std::fs::write(
        &sp,
        r#"[{"class": 1, "axis": "z", "slice": 3, "points": [[4, 4], [8, 8]], "radius": 1},
            {"class": 255, "axis": "x", "slice": 2, "points": [[1, 1], [1, 6]], "radius": 0}]"#,
    )
    .unwrap();
    let s = load_scribbles(&sp, &meta).unwrap();
    assert_eq!(s.counts().len(), 2);
    // A scribble volume on another grid.
    let np = d.path().join("wrong.nii");
    neuvolex_tests::write_nifti_values(
        &np,
        [meta.dims[0], meta.dims[1], meta.dims[2] + 2],
        neuvolex_formats::DType::U8,
        &vec![0.0; meta.dims[0] * meta.dims[1] * (meta.dims[2] + 2)],
        None,
    );
    let e = load_scribbles(&np, &meta).unwrap_err().to_string();
    assert!(e.contains("wrong.nii") && e.contains("dims"), "{e}");
    // Non-integer scribble labels.
    let n: usize = meta.dims.iter().product();
    let mut v = vec![0.0; n];
    v[7] = 1.5;
    let fp = d.path().join("frac.nii");
    let mut vol = MemVolume::from_f64(meta.dims, neuvolex_formats::DType::F32, &v);
    vol.meta.spacing = meta.spacing;
    neuvolex_formats::nifti::write_nifti(&fp, &mut vol, 8).unwrap();
    let e = load_scribbles(&fp, &meta).unwrap_err().to_string();
    assert!(e.contains("frac.nii") && e.contains("1.5"), "{e}");
    // Class ids missing from the class table.
    let tp = d.path().join("classes.json");
    std::fs::write(
        &tp,
        r#"{"classes": [{"id": 1, "name": "bone", "color": [255, 255, 255]}], "background": 255}"#,
    )
    .unwrap();
    let t = ClassTable::load(&tp).unwrap();
    assert!(t.check(&[1, 255]).is_ok());
    let e = t.check(&[1, 3, 255]).unwrap_err().to_string();
    assert!(e.contains("[3]"), "{e}");
    for bad in [
        "{",
        r#"{"classes": [{"id": 1, "name": "a", "color": [1, 2, 3]}, {"id": 1, "name": "b", "color": [1, 2, 3]}]}"#,
        r#"{"classes": [{"id": 255, "name": "a", "color": [1, 2, 3]}]}"#,
    ] {
        std::fs::write(&tp, bad).unwrap();
        let e = ClassTable::load(&tp).unwrap_err().to_string();
        assert!(e.contains("classes.json"), "{e}");
    }
}

#[test]
fn features_missing_for_a_brick_is_an_error_naming_it() {
    let (_d, store, p) = phantom_store();
    let m = small_model(&store, 4, 12, 1024, 4096);
    write_features(&store, &m, FeatureKind::Hidden, true, &mut |_| {}).unwrap();
    // Remove one brick's chunk.
    let dir = store.root().join("neuvolex/vectors/inr_hidden");
    let chunk = walk(&dir)
        .into_iter()
        .find(|p| p.file_name().is_some_and(|n| n != "zarr.json"))
        .expect("a chunk file");
    std::fs::remove_file(&chunk).unwrap();
    let fx = BrickFeatures::new(&store, "paper".parse().unwrap(), Some(m), true).unwrap();
    let failing: Vec<_> = store
        .bricks()
        .filter_map(|b| fx.brick(&b).err().map(|e| (b, e.to_string())))
        .collect();
    assert_eq!(
        failing.len(),
        1,
        "exactly the brick whose chunk was removed fails"
    );
    let (gone, e) = &failing[0];
    assert!(e.contains("inr_hidden") && e.contains("brick"), "{e}");
    // Training reads the features of the bricks the scribbles touch: two classes scribbled
    // inside the brick without features give an error naming the array, the same two classes
    // scribbled in another brick give the training set.
    let dims = p.dims;
    let at = |v: [usize; 3]| ((v[2] * dims[1] + v[1]) * dims[0] + v[0]) as u64;
    let inside = |o: [usize; 3], k: usize| [o[0] + k, o[1], o[2]];
    let other = store.bricks().find(|b| b.index != gone.index).unwrap();
    for (b, missing) in [(*gone, true), (other, false)] {
        let scr = Scribbles {
            dims,
            voxels: vec![(at(inside(b.origin, 0)), 1), (at(inside(b.origin, 1)), 255)],
        };
        match training_set(&fx, &scr, 255) {
            Err(e) if missing => assert!(e.to_string().contains("inr_hidden"), "{e}"),
            Err(e) => panic!("brick {:?} has its features, yet: {e}", b.index),
            Ok(_) if missing => panic!("brick {:?} has no features, yet training read it", b.index),
            Ok(ts) => assert_eq!((ts.y.len(), ts.labels.clone()), (2, vec![1, 255])),
        }
    }
}

fn walk(d: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(d).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn extreme_volumes_classify_without_nan() {
    // Constant, huge-range and tiny-range volumes: features stay finite, classification runs.
    let dims = [20, 18, 16];
    let n: usize = dims.iter().product();
    for (i, scale) in [0.0f32, 1e30, 1e-30].into_iter().enumerate() {
        let v: Vec<f32> = (0..n)
            .map(|k| {
                if scale == 0.0 {
                    5.0
                } else {
                    scale * ((k % 97) as f32 - 40.0)
                }
            })
            .collect();
        let (_d, store) = store_of(&mut MemVolume::from_f32(dims, &v), 8);
        let scr = Scribbles {
            dims,
            voxels: vec![(100, 1), (101, 1), (2000, 255), (2001, 255), (4000, 2)],
        };
        for set in ["intensity", "local", "filters"] {
            let c = ClassifyConfig {
                skip_empty: false,
                ..cfg(5)
            };
            let r = run(&store, set, &scr, &c).unwrap_or_else(|e| panic!("case {i} {set}: {e}"));
            assert_eq!(r.labels.len(), n);
        }
    }
}

/// The slice preview is the full classification's slice (before the prior), on every axis and
/// at brick borders, and reads only the bricks crossing it.
#[test]
fn the_slice_preview_equals_the_full_classification_on_that_slice() {
    use neuvolex_classify::preview::preview_plane;
    let p = PhantomParams::with_size(40, 2);
    let (_d, store) = store_of(&mut Phantom::new(p, PhantomChannel::Image), 16);
    let (_, scr) = simulate(
        &mut Phantom::new(p, PhantomChannel::Labels),
        &SimConfig {
            level: Level::S2,
            ..Default::default()
        },
    )
    .unwrap();
    let c = cfg(20);
    let full = run(&store, "filters+xyz", &scr, &c).unwrap();
    let fx = BrickFeatures::new(&store, "filters+xyz".parse().unwrap(), None, false).unwrap();
    let dims = store.info().dims;
    for (axis, index) in [(2, 0), (2, 17), (1, 15), (1, 16), (0, dims[0] - 1)] {
        let pl = preview_plane(&fx, &scr, &c, axis, index, &|| false).unwrap();
        let [u, v] = match axis {
            0 => [1, 2],
            1 => [0, 2],
            _ => [0, 1],
        };
        assert_eq!(pl.size, [dims[u], dims[v]]);
        for j in 0..dims[v] {
            for i in 0..dims[u] {
                let mut q = [0; 3];
                q[axis] = index;
                q[u] = i;
                q[v] = j;
                let at = (q[2] * dims[1] + q[1]) * dims[0] + q[0];
                assert_eq!(
                    pl.labels[j * dims[u] + i],
                    full.labels[at],
                    "axis {axis} plane {index} voxel {q:?}"
                );
            }
        }
    }
    let e = preview_plane(&fx, &scr, &c, 2, dims[2], &|| false).unwrap_err();
    assert!(e.to_string().contains("outside the grid"), "{e}");
    assert!(preview_plane(&fx, &scr, &c, 2, 3, &|| true).is_err());
}

#[test]
fn tube_measures_come_from_the_same_filter_bank_in_any_set() {
    // A bright tube along z through a noisy background: the tube measures read from one filter
    // bank beside `filters` equal those of `tubes` alone, and lineness marks the tube's axis.
    let d = [24, 24, 20];
    let mut v = neuvolex_tests::noise(d.iter().product(), 3, 0.0, 0.1);
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let r2 = (x as f32 - 11.5).powi(2) + (y as f32 - 11.5).powi(2);
                v[(z * d[1] + y) * d[0] + x] += 2.0 * (-r2 / (2.0 * 1.5 * 1.5)).exp();
            }
        }
    }
    let (_d, store) = store_of(&mut MemVolume::from_f32(d, &v), 16);
    let both = BrickFeatures::new(&store, "filters+tubes".parse().unwrap(), None, false).unwrap();
    let bank = BrickFeatures::new(&store, "filters".parse().unwrap(), None, false).unwrap();
    let tubes = BrickFeatures::new(&store, "tubes".parse().unwrap(), None, false).unwrap();
    assert_eq!(both.channels(), bank.channels() + tubes.channels());
    let (cb, ct) = (bank.channels(), tubes.channels());
    for b in store.bricks() {
        let (x, f, t) = (
            both.brick(&b).unwrap(),
            bank.brick(&b).unwrap(),
            tubes.brick(&b).unwrap(),
        );
        for ((row, fr), tr) in x.chunks(cb + ct).zip(f.chunks(cb)).zip(t.chunks(ct)) {
            assert_eq!(&row[..cb], fr);
            assert_eq!(&row[cb..], tr);
        }
    }
    // Lineness at sigma 1.6 (the third scale) on the axis against 6 voxels off it.
    let b = store.brick([0, 0, 0]).unwrap();
    let t = tubes.brick(&b).unwrap();
    let at = |x: usize, y: usize| t[((8 * b.size[1] + y) * b.size[0] + x) * ct + 2 * 2];
    assert!(at(11, 11) > 0.5, "on the axis: {}", at(11, 11));
    assert!(at(11, 11) > at(4, 11) + 0.3, "{} {}", at(11, 11), at(4, 11));
    assert!("tubes+tubes".parse::<FeatureSet>().is_err());
}

#[test]
fn enclosure_reads_the_stores_pyramid_and_marks_what_a_shell_closes_in() {
    // A bright spherical shell in a noisy dark volume, stored in bricks of 16 (with its
    // pyramid): the `encl` part of `filters+xyz+encl` equals `encl` alone and one whole-volume
    // computation from the store's levels, and the shell's inside is closed in on every side
    // while the same dark tissue outside it is not.
    let d = [40, 36, 34];
    let mut v = neuvolex_tests::noise(d.iter().product(), 5, 0.0, 0.05);
    let c = [20.0f32, 18.0, 17.0];
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let r = ((x as f32 - c[0]).powi(2)
                    + (y as f32 - c[1]).powi(2)
                    + (z as f32 - c[2]).powi(2))
                .sqrt();
                if (7.0..=9.0).contains(&r) {
                    v[(z * d[1] + y) * d[0] + x] += 1.0;
                }
            }
        }
    }
    let (_d, store) = store_of(&mut MemVolume::from_f32(d, &v), 16);
    let set = BrickFeatures::new(&store, "filters+xyz+encl".parse().unwrap(), None, false).unwrap();
    let encl = BrickFeatures::new(&store, "encl".parse().unwrap(), None, false).unwrap();
    let ce = neuvolex_filters::enclosure::CHANNELS;
    assert_eq!(encl.channels(), ce);
    assert_eq!(
        set.channels(),
        neuvolex_filters::Classic::Filters.channels() + 3 + ce
    );
    let whole = neuvolex_filters::enclosure::compute(
        &store.info().levels,
        &store.normaliser(),
        [0; 3],
        d,
        |k, o, s| store.read_box(k, o, s),
    )
    .unwrap();
    let at_whole = |p: [usize; 3], ch: usize| whole[((p[2] * d[1] + p[1]) * d[0] + p[0]) * ce + ch];
    let cs = set.channels();
    for b in store.bricks() {
        let (x, e) = (set.brick(&b).unwrap(), encl.brick(&b).unwrap());
        for (i, (row, er)) in x.chunks(cs).zip(e.chunks(ce)).enumerate() {
            assert_eq!(&row[cs - ce..], er);
            let q = [
                b.origin[0] + i % b.size[0],
                b.origin[1] + (i / b.size[0]) % b.size[1],
                b.origin[2] + i / (b.size[0] * b.size[1]),
            ];
            for (ch, &val) in er.iter().enumerate() {
                assert!((val - at_whole(q, ch)).abs() < 1e-5, "{q:?} channel {ch}");
            }
        }
    }
    let inside = at_whole([20, 18, 17], 0);
    let outside = at_whole([20, 4, 2], 0);
    assert!(inside > outside + 0.2, "inside {inside}, outside {outside}");
    assert!("encl+encl".parse::<FeatureSet>().is_err());
}
