//! The GPU forest against the CPU forest on the same features: u8 probabilities (the session's
//! quantisation) and labels, on the filter bank of a generated phantom and on extremes
//! (constant features, huge and tiny values, infinities, NaN), in both feature layouts.
//! Without an adapter the tests skip visibly; under CI=true they fail.

mod common;

use common::{
    check_forest as check, class_indices, filters_xyz, gpu, phantom, train_forest as train,
};
use neuvolex_bricks::derived::Normaliser;
use neuvolex_bricks::rng::Rng;
use neuvolex_classify_gpu::{FeatureLayout, GpuError, GpuForest, BELOW_TAU, MAX_CLASSES};
use neuvolex_filters::Classic;

#[test]
fn gpu_forest_equals_the_cpu_forest_on_the_filter_bank_of_a_phantom() {
    let Some(dev) = gpu() else { return };
    let dims = [40, 36, 30];
    let (v, lab) = phantom(dims, 18.0, 3);
    let norm = Normaliser {
        lo: -200.0,
        hi: 400.0,
    };
    let x = filters_xyz(&v, dims, &norm);
    let d = Classic::Filters.channels() + 3;
    // Classes in order of first appearance.
    let (y, classes) = class_indices(&lab);
    assert!(classes >= 3, "the phantom has several classes");
    let forest = train(&x, &y, d, classes, 4000, 24);
    let g = GpuForest::new(dev.clone(), &forest).expect("upload");
    check("phantom filters+xyz", &g, &forest, &x);
    // The feature-major layout the GPU filter bank writes, through `encode`.
    let n = y.len();
    let mut planes = vec![0.0f32; n * d];
    for r in 0..n {
        for f in 0..d {
            planes[f * n + r] = x[r * d + f];
        }
    }
    let fb = dev
        .upload(
            "planes",
            bytemuck::cast_slice(&planes),
            wgpu::BufferUsages::STORAGE,
        )
        .expect("upload");
    let ob = dev
        .buffer(
            "out",
            g.output_bytes(n),
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        )
        .expect("out");
    let mut enc = dev.device.create_command_encoder(&Default::default());
    g.encode(&mut enc, &fb, FeatureLayout::planes(n), n, &ob)
        .expect("encode");
    dev.queue.submit([enc.finish()]);
    let bytes = dev.read(&ob, g.output_bytes(n)).expect("read");
    let rows = g.predict(&x).expect("rows");
    let lo = g.labels_offset(n) as usize;
    assert_eq!(&bytes[..n * classes], &rows.probs[..]);
    assert_eq!(&bytes[lo..lo + n], &rows.labels[..]);
    // A layout past the end of its buffer is refused, not read out of bounds.
    let mut enc = dev.device.create_command_encoder(&Default::default());
    let e = g
        .encode(&mut enc, &fb, FeatureLayout::planes(n + 1), n + 1, &ob)
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    // With a threshold, a voxel whose top f32 probability is below it is labelled BELOW_TAU,
    // as `neuvolex_classify::shard::predict_brick` thresholds it (`neuvolex classify --gpu`).
    let p = forest.predict_proba(&x).expect("cpu");
    for tau in [0.3f32, 0.5, 0.7] {
        let g = GpuForest::new(dev.clone(), &forest)
            .expect("upload")
            .with_tau(tau);
        let want: Vec<u8> = p
            .chunks_exact(classes)
            .map(|r| match neuvolex_classify::shard::argmax(r) {
                (k, v) if v >= tau => k as u8,
                _ => BELOW_TAU,
            })
            .collect();
        let got = g.predict(&x).expect("rows").labels;
        let below = want.iter().filter(|&&k| k == BELOW_TAU).count();
        let differ = want.iter().zip(&got).filter(|(a, b)| a != b).count();
        eprintln!("tau {tau}: {below} of {n} voxels below it, {differ} labels differ");
        assert_eq!(differ, 0, "tau {tau}");
    }
    dev.check().expect("no device error");
}

#[test]
fn gpu_forest_equals_the_cpu_forest_on_extremes() {
    let Some(dev) = gpu() else { return };
    let mut rng = Rng::new(9);
    let (d, classes) = (6, 5);
    // Training values spanning the whole f32 range, tiny ones and exact repeats.
    let n = 3000;
    let x: Vec<f32> = (0..n * d)
        .map(|i| match i % d {
            0 => rng.uniform(-1.0, 1.0) * 1e30,
            1 => rng.uniform(-1.0, 1.0) * 1e-30,
            2 => (rng.below(7) as f32 - 3.0) * 0.5,
            3 => 42.0,
            4 => rng.uniform(-3.0, 3.0),
            _ => f32::from_bits(rng.next_u64() as u32 & 0xff7f_ffff),
        })
        .collect();
    let y: Vec<u16> = (0..n)
        .map(|r| {
            let row = &x[r * d..(r + 1) * d];
            ((row[0] > 0.0) as u16 + 2 * (row[1] > 0.0) as u16 + (row[2] > 0.5) as u16)
                % classes as u16
        })
        .collect();
    let forest = train(&x, &y, d, classes, n, 16);
    let g = GpuForest::new(dev, &forest).expect("upload");
    check("random extremes", &g, &forest, &x);
    // Constant features; every value on a threshold and next to it; huge, tiny, infinite, NaN.
    let mut probe: Vec<f32> = std::iter::repeat_n(0.0f32, 100 * d).collect();
    probe.extend(std::iter::repeat_n(1e30f32, 70 * d));
    probe.extend(std::iter::repeat_n(-1e-30f32, 70 * d));
    for v in [
        f32::MAX,
        -f32::MAX,
        f32::MIN_POSITIVE,
        -f32::MIN_POSITIVE,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        -0.0,
        42.0,
    ] {
        for k in 0..d {
            let mut row: Vec<f32> = x[k * d..(k + 1) * d].to_vec();
            row[k] = v;
            probe.extend(&row);
        }
    }
    for r in 0..200 {
        let mut row: Vec<f32> = x[r * d..(r + 1) * d].to_vec();
        let k = r % d;
        row[k] = x[((r * 7) % n) * d + k].next_up();
        probe.extend(&row);
    }
    check(
        "constant, huge, tiny, infinite and NaN rows",
        &g,
        &forest,
        &probe,
    );
    // Fewer voxels than a workgroup, and one more than a whole group.
    check("3 voxels", &g, &forest, &probe[..3 * d]);
    check("65 voxels", &g, &forest, &probe[..65 * d]);
    assert!(
        g.predict(&probe[..d + 1]).is_err(),
        "ragged rows are refused"
    );
}

#[test]
fn class_count_limit_is_an_error_not_a_panic() {
    let Some(dev) = gpu() else { return };
    let c = MAX_CLASSES + 1;
    let x: Vec<f32> = (0..c * 4).map(|i| i as f32).collect();
    let y: Vec<u16> = (0..c * 4).map(|i| (i / 4) as u16).collect();
    let forest = train(&x, &y, 1, c, c * 4, 2);
    let e = GpuForest::new(dev.clone(), &forest).unwrap_err();
    assert!(e.to_string().contains("classes"), "{e}");
    // Exactly the limit works, and equals the CPU.
    let c = MAX_CLASSES;
    let x: Vec<f32> = (0..c * 8).map(|i| i as f32 * 0.25).collect();
    let y: Vec<u16> = (0..c * 8).map(|i| (i / 8) as u16).collect();
    let forest = train(&x, &y, 1, c, c * 8, 3);
    let g = GpuForest::new(dev, &forest).expect("16 classes");
    check("16 classes", &g, &forest, &x);
}
