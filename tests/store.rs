//! The brick store: ingest, pyramid, statistics, halo reads, derived quantities (compared with
//! a direct whole-volume computation at borders and across brick seams), vectors, occupancy.

use neuvolex_bricks::derived::{self, Normaliser};
use neuvolex_bricks::layout::downsample_mode;
use neuvolex_bricks::synth::{Phantom, PhantomChannel, PhantomParams};
use neuvolex_bricks::{BrickStore, VectorEncoding};
use neuvolex_formats::{DType, MemVolume, VolumeSource};
use neuvolex_ingest::downsample_mean;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_tests::{blobs, noise, shared, tmp};

fn build(
    vol: &mut dyn VolumeSource,
    brick: usize,
    shard: Option<usize>,
) -> (tempfile::TempDir, BrickStore) {
    let dir = tmp();
    let p = dir.path().join("s.zarr");
    ingest(
        vol,
        &p,
        &IngestOptions {
            brick,
            shard,
            ..Default::default()
        },
        &mut |_| {},
    )
    .unwrap();
    let s = BrickStore::open(&p).unwrap();
    (dir, s)
}

fn close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (x - y).abs() <= tol * (1.0 + y.abs()),
            "{what}[{i}]: {x} vs {y}"
        );
    }
}

/// Gathers a sub-box of a whole-volume array (x fastest).
fn sub(v: &[f32], dims: [usize; 3], o: [usize; 3], s: [usize; 3]) -> Vec<f32> {
    let mut out = Vec::new();
    for z in o[2]..o[2] + s[2] {
        for y in o[1]..o[1] + s[1] {
            let r = (z * dims[1] + y) * dims[0];
            out.extend_from_slice(&v[r + o[0]..r + o[0] + s[0]]);
        }
    }
    out
}

#[test]
fn boxes_halos_and_derived_match_whole_volume() {
    // Odd dims so the last bricks are partial; brick 8 gives many seams.
    let dims = [21, 19, 17];
    let vals = blobs(dims);
    let mut vol = MemVolume::from_f32(dims, &vals);
    for shard in [None, Some(2)] {
        let (_d, store) = build(&mut vol, 8, shard);
        assert_eq!(store.grid(), [3, 3, 3]);
        assert_eq!(store.read_box(0, [0; 3], dims).unwrap(), vals);
        // An arbitrary box crossing seams.
        assert_eq!(
            store.read_box(0, [5, 3, 6], [9, 12, 7]).unwrap(),
            sub(&vals, dims, [5, 3, 6], [9, 12, 7])
        );
        // Blocks of bricks, one passing the grid's far ends on every axis, read edge-clamped.
        for (o, sz, halo) in [
            ([0, 0, 0], [16, 16, 16], 3),
            ([8, 8, 8], [16, 16, 16], 5),
            ([16, 0, 8], [8, 24, 16], 2),
            ([20, 18, 16], [1, 1, 1], 0),
        ] {
            let h = store.read_padded(o, sz, halo).unwrap();
            let want = derived::halo_from_volume(&vals, dims, o, sz, halo);
            assert_eq!(h.data, want.data, "box {o:?}+{sz:?} halo {halo}");
        }
        assert!(store.read_padded([21, 0, 0], [1, 1, 1], 1).is_err());
        assert!(store.read_padded([0, 0, 0], [0, 1, 1], 1).is_err());
        let norm = store.normaliser();
        let whole = derived::reference(&vals, dims, &norm);
        for b in store.bricks() {
            for halo in [0, 1, 2, 3] {
                let h = store.read_halo(&b, halo).unwrap();
                let want = derived::halo_from_volume(&vals, dims, b.origin, b.size, halo);
                assert_eq!(h.data, want.data, "halo {halo} brick {:?}", b.index);
            }
            let d = store.derived(&b).unwrap();
            close(
                &d.intensity,
                &sub(&whole.intensity, dims, b.origin, b.size),
                1e-6,
                "intensity",
            );
            close(
                &d.mean,
                &sub(&whole.mean, dims, b.origin, b.size),
                1e-5,
                "mean",
            );
            close(
                &d.std,
                &sub(&whole.std, dims, b.origin, b.size),
                1e-4,
                "std",
            );
            for k in 0..3 {
                let g: Vec<f32> = d.gradient.iter().map(|g| g[k]).collect();
                let w: Vec<f32> = whole.gradient.iter().map(|g| g[k]).collect();
                close(&g, &sub(&w, dims, b.origin, b.size), 1e-6, "gradient");
            }
        }
    }
}

#[test]
fn pyramid_is_mean_for_images_and_mode_for_labels() {
    let p = PhantomParams::with_size(96, 1);
    let mut img = Phantom::new(p, PhantomChannel::Image);
    let (_d, mut store) = build(&mut img, 16, None);
    let dims = p.dims;
    let full: Vec<f32> = store.read_box(0, [0; 3], dims).unwrap();
    let l1 = downsample_mean(&full, dims);
    let d1 = store.info().levels[1];
    close(
        &store.read_box(1, [0; 3], d1).unwrap(),
        &l1,
        1e-6,
        "level 1",
    );
    let l2 = downsample_mean(&l1, d1);
    let d2 = store.info().levels[2];
    close(
        &store.read_box(2, [0; 3], d2).unwrap(),
        &l2,
        1e-5,
        "level 2",
    );
    let mut lab = Phantom::new(p, PhantomChannel::Labels);
    store
        .add_labels(
            "gt",
            &mut lab,
            &neuvolex_bricks::synth::phantom_classes(),
            &mut |_| {},
        )
        .unwrap();
    let lv = store.read_labels_box("gt", [0; 3], dims).unwrap();
    let want: Vec<u32> = MemVolume::read_all(&mut Phantom::new(p, PhantomChannel::Labels))
        .unwrap()
        .bytes
        .iter()
        .map(|&b| b as u32)
        .collect();
    assert_eq!(lv, want);
    // Level-1 labels are the mode of each 2x2x2 block.
    let store2 = BrickStore::open(store.root()).unwrap();
    assert_eq!(store2.info().labels, vec!["gt".to_string()]);
    assert_eq!(store2.label_classes("gt").unwrap().len(), 5);
    let reader =
        neuvolex_bricks::omezarr::OmeZarrSource::open(store.root().join("labels/gt")).unwrap();
    drop(reader);
    let l1_dir = store.root().join("labels/gt/v1/1");
    assert!(l1_dir.join("zarr.json").exists());
    let mode = downsample_mode(&want, dims);
    assert_eq!(mode.len(), d1.iter().product::<usize>());
    assert!(mode.contains(&4), "vessels survive mode downsampling");
}

#[test]
fn statistics_match_direct_computation() {
    let dims = [30, 20, 10];
    let raw: Vec<f64> = noise(6000, 5, -1000.0, 2000.0)
        .iter()
        .map(|v| v.round() as f64)
        .collect();
    let mut sorted = raw.clone();
    sorted.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        let pos = q * (sorted.len() - 1) as f64;
        let lo = pos.floor() as usize;
        sorted[lo] + (sorted[(lo + 1).min(sorted.len() - 1)] - sorted[lo]) * (pos - lo as f64)
    };
    let mean = raw.iter().sum::<f64>() / raw.len() as f64;
    let std = (raw.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / raw.len() as f64).sqrt();
    // i16 is exact; i32 goes through the fine histogram, exact for integer data.
    for (dt, tol) in [(DType::I16, 1e-9), (DType::I32, 1e-9)] {
        let mut vol = MemVolume::from_f64(dims, dt, &raw);
        let (_d, store) = build(&mut vol, 8, None);
        let s = &store.info().stats;
        assert_eq!((s.min, s.max), (sorted[0], sorted[5999]));
        assert!(
            (s.mean - mean).abs() < 1e-6 && (s.std - std).abs() < 1e-6,
            "{dt}"
        );
        assert!(
            (s.p0_5 - pct(0.005)).abs() <= tol && (s.p99_5 - pct(0.995)).abs() <= tol,
            "{dt}: {} {} vs {} {}",
            s.p0_5,
            s.p99_5,
            pct(0.005),
            pct(0.995)
        );
        assert_eq!(s.histogram.iter().sum::<u64>(), 6000);
    }
}

#[test]
fn scaled_sources_are_stored_as_f32() {
    let dims = [9, 9, 9];
    let raw: Vec<f64> = (0..729).map(|i| (i % 100) as f64).collect();
    let mut vol = MemVolume::from_f64(dims, DType::U8, &raw);
    vol.meta.scaling = Some((2.0, -50.0));
    let (_d, store) = build(&mut vol, 8, None);
    assert_eq!(store.info().dtype, DType::F32);
    let back = store.read_box(0, [0; 3], dims).unwrap();
    assert_eq!(back[99], 99.0 * 2.0 - 50.0);
    assert_eq!(store.info().stats.min, -50.0);
    assert_eq!(store.info().stats.max, 99.0 * 2.0 - 50.0);
}

#[test]
fn empty_bricks_are_skippable() {
    // Zero background with one bright blob in the first brick.
    let dims = [32, 32, 32];
    let mut v = vec![0.0f32; 32 * 32 * 32];
    for z in 2..10 {
        for y in 2..10 {
            for x in 2..10 {
                v[(z * 32 + y) * 32 + x] = 200.0;
            }
        }
    }
    let (_d, store) = build(&mut MemVolume::from_f32(dims, &v), 16, None);
    let occ = store.occupied_bricks(None);
    assert_eq!(occ.len(), 1);
    assert_eq!(occ[0].index, [0, 0, 0]);
    assert_eq!(store.brick_range(&occ[0]), (0.0, 200.0));
    // An explicit threshold below the background marks everything occupied.
    assert_eq!(store.occupied_bricks(Some(-1.0)).len(), 8);
}

#[test]
fn vectors_roundtrip_f16_and_u8() {
    let dims = [20, 12, 9];
    let (_d, store) = build(&mut MemVolume::from_f32(dims, &blobs(dims)), 8, None);
    let c = 5;
    let mut f16 = store
        .create_vectors("features", c, VectorEncoding::F16)
        .unwrap();
    let mut u8v = store
        .create_vectors(
            "probs",
            c,
            VectorEncoding::U8 {
                lo: vec![0.0; c],
                hi: vec![1.0; c],
            },
        )
        .unwrap();
    let bricks: Vec<_> = store.bricks().collect();
    for b in &bricks {
        let v = noise(
            b.voxels() * c,
            b.index[0] as u64 * 7 + b.index[1] as u64 * 3 + b.index[2] as u64,
            0.0,
            1.0,
        );
        f16.write_brick(b, &v).unwrap();
        u8v.write_brick(b, &v).unwrap();
    }
    f16.finish().unwrap();
    u8v.finish().unwrap();
    let f16 = store.open_vectors("features").unwrap();
    let u8v = store.open_vectors("probs").unwrap();
    assert!(f16.info().complete && u8v.info().complete);
    for b in &bricks {
        let v = noise(
            b.voxels() * c,
            b.index[0] as u64 * 7 + b.index[1] as u64 * 3 + b.index[2] as u64,
            0.0,
            1.0,
        );
        close(&f16.read_brick(b).unwrap(), &v, 1e-3, "f16");
        let q = u8v.read_brick(b).unwrap();
        assert!(
            q.iter()
                .zip(&v)
                .all(|(a, b)| (a - b).abs() <= 0.5 / 255.0 + 1e-6),
            "u8 quantisation error"
        );
    }
    // A brick of the wrong size, and NaN, are rejected.
    assert!(f16.write_brick(&bricks[0], &[0.0; 3]).is_err());
    let mut nan = vec![0.0f32; bricks[0].voxels() * c];
    nan[7] = f32::NAN;
    assert!(f16
        .write_brick(&bricks[0], &nan)
        .unwrap_err()
        .to_string()
        .contains("not finite"));
    // A finite f32 past f16's range would be stored as infinity: rejected, naming it.
    let mut big = vec![0.0f32; bricks[0].voxels() * c];
    big[5] = 1e5;
    let e = f16.write_brick(&bricks[0], &big).unwrap_err().to_string();
    assert!(e.contains("100000") && e.contains("f16"), "{e}");
    // Values already in f16 (the GPU's extraction) store the bytes write_brick stores for
    // their f32 values; the wrong size, infinity and an array of another encoding are errors.
    let v = noise(bricks[1].voxels() * c, 99, -2.0, 2.0);
    let h: Vec<half::f16> = v.iter().map(|&x| half::f16::from_f32(x)).collect();
    f16.write_brick_f16(&bricks[1], &h).unwrap();
    let got = f16.read_brick(&bricks[1]).unwrap();
    assert!(got
        .iter()
        .zip(&h)
        .all(|(a, b)| a.to_bits() == b.to_f32().to_bits()));
    assert!(f16
        .write_brick_f16(&bricks[1], &h[1..])
        .unwrap_err()
        .to_string()
        .contains("needs"));
    let mut hinf = h.clone();
    hinf[3] = half::f16::INFINITY;
    assert!(f16
        .write_brick_f16(&bricks[1], &hinf)
        .unwrap_err()
        .to_string()
        .contains("not finite"));
    assert!(u8v
        .write_brick_f16(&bricks[1], &h)
        .unwrap_err()
        .to_string()
        .contains("f16 values written to an array encoded as"));
    // Nothing of the refused writes landed: the brick still reads what was written.
    assert_eq!(f16.read_brick(&bricks[1]).unwrap(), got);
}

#[test]
fn numeric_extremes_give_finite_derived_quantities() {
    let dims = [10, 9, 8];
    let n = 720;
    let cases: Vec<(&str, Vec<f32>)> = vec![
        ("constant", vec![42.0; n]),
        ("huge", noise(n, 1, 1e29, 1e30)),
        ("huge-negative", noise(n, 2, -1e30, 1e30)),
        ("tiny-range", noise(n, 3, 1.0, 1.0 + 1e-6)),
        ("tiny-values", noise(n, 4, 0.0, 1e-30)),
        (
            "f32-extremes",
            (0..n)
                .map(|i| if i % 2 == 0 { f32::MAX } else { f32::MIN })
                .collect(),
        ),
    ];
    for (name, v) in cases {
        let (_d, store) = build(&mut MemVolume::from_f32(dims, &v), 8, None);
        let s = &store.info().stats;
        assert!(
            s.mean.is_finite() && s.std.is_finite(),
            "{name}: stats {s:?}"
        );
        for b in store.bricks() {
            let d = store.derived(&b).unwrap();
            let all = d
                .intensity
                .iter()
                .chain(&d.mean)
                .chain(&d.std)
                .chain(d.gradient.iter().flatten());
            for x in all {
                assert!(x.is_finite(), "{name}: non-finite derived value");
            }
            if name == "constant" {
                assert!(d.std.iter().all(|&x| x == 0.0) && d.intensity.iter().all(|&x| x == 0.0));
            }
        }
    }
}

#[test]
fn one_voxel_and_thin_volumes() {
    for dims in [[1, 1, 1], [1, 1, 9], [2, 2, 2], [17, 1, 1]] {
        let n: usize = dims.iter().product();
        let v: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let (_d, store) = build(&mut MemVolume::from_f32(dims, &v), 8, None);
        assert_eq!(store.read_box(0, [0; 3], dims).unwrap(), v);
        let norm = store.normaliser();
        let whole = derived::reference(&v, dims, &norm);
        let mut got = vec![0.0f32; n];
        for b in store.bricks() {
            let d = store.derived(&b).unwrap();
            let s = sub(
                &(0..n).map(|i| i as f32).collect::<Vec<_>>(),
                dims,
                b.origin,
                b.size,
            );
            for (k, &i) in s.iter().enumerate() {
                got[i as usize] = d.std[k];
            }
        }
        close(&got, &whole.std, 1e-5, "std");
    }
}

#[test]
fn normaliser_is_robust_to_outliers() {
    // A few extreme voxels (metal) must not squash the normalised range of the rest.
    let mut v = noise(4000, 9, -100.0, 100.0);
    v[17] = 30000.0;
    v[99] = 30000.0;
    let (_d, store) = build(&mut MemVolume::from_f32([20, 20, 10], &v), 8, None);
    let n: Normaliser = store.normaliser();
    // The window is the 0.5th and 99.5th percentiles, computed here by sorting (numpy's linear
    // interpolation between order statistics). f32 stores locate them with a 65 536-bin
    // histogram over [min, max], so they may be off by one bin width.
    let mut sorted: Vec<f64> = v.iter().map(|&x| x as f64).collect();
    sorted.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        let pos = q * (sorted.len() - 1) as f64;
        let (i, f) = (pos.floor() as usize, pos - pos.floor());
        sorted[i] + f * (sorted[i + 1] - sorted[i])
    };
    let (want_lo, want_hi) = (pct(0.005), pct(0.995));
    let bin = (sorted[sorted.len() - 1] - sorted[0]) / 65536.0;
    assert!(
        (n.lo - want_lo).abs() <= bin && (n.hi - want_hi).abs() <= bin,
        "{n:?}: want lo {want_lo}, hi {want_hi} within {bin}"
    );
    // The outliers lie outside the window, the bulk inside it: 99 % of the voxels map to [0, 1].
    assert!(want_hi < 100.0 && want_lo > -100.0);
    let inside = v
        .iter()
        .filter(|&&x| (0.0..=1.0).contains(&n.apply(x)))
        .count();
    assert!((3950..4000).contains(&inside), "{inside} of 4000 in [0, 1]");
    assert!(
        n.apply(30000.0) > 100.0,
        "the outliers stay ordered above 1"
    );
}

#[test]
fn abdomen_ct_store_with_labels_and_derived() {
    let (Some(ct), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let mut src = neuvolex_bricks::open_volume(&ct, None).unwrap();
    let (_d, mut store) = build(src.as_mut(), 32, None);
    let mut l = neuvolex_bricks::open_volume(&lab, None).unwrap();
    store
        .add_labels("ground_truth", l.as_mut(), &[], &mut |_| {})
        .unwrap();
    let s = store.info().stats.clone();
    // Robust window: soft tissue is no longer squeezed into a few percent of the range.
    let n = store.normaliser();
    assert!(
        n.lo <= -900.0 && n.hi > 300.0 && n.hi < s.max,
        "{n:?} {s:?}"
    );
    let occ = store.occupied_bricks(None);
    assert!(
        !occ.is_empty() && occ.len() < store.bricks().count(),
        "air bricks should be skippable, and the body occupied: {} occupied",
        occ.len()
    );
    for b in occ.iter().take(6) {
        let d = store.derived(b).unwrap();
        assert!(d.std.iter().all(|x| x.is_finite()));
    }
    let labels = store
        .read_labels_box("ground_truth", [0; 3], s_dims(&store))
        .unwrap();
    assert!(labels.contains(&4));
}

fn s_dims(s: &BrickStore) -> [usize; 3] {
    s.info().dims
}
