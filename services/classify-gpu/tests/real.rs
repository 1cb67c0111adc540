//! The GPU filter bank and forest on real bricks: the abdomen CT of `../shared/data` (skipped
//! where absent, required under CI=true), against the CPU paths with the tolerances of
//! `tests/filters.rs` (filter bank) and exactly (forest: u8 probabilities and labels), and the
//! two chained on the GPU (at least 99.9 % of the labels equal the CPU's).

mod common;

use common::{check_filters, check_forest, gpu, train_forest};
use neuvolex_bricks::derived::{halo_from_volume, Normaliser};
use neuvolex_bricks::open_volume;
use neuvolex_classify_gpu::{wgpu, FeatureLayout, GpuFilterBank, GpuForest};
use neuvolex_filters::{compute, filter_halo, pos, Classic};
use std::path::PathBuf;

/// `../shared/data/<rel>` if present; `None` with a SKIP line where absent, a panic under CI.
fn shared(rel: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(rel);
    if p.exists() {
        return Some(p);
    }
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("{} is required under CI=true but missing", p.display());
    }
    eprintln!("SKIP: {} is absent", p.display());
    None
}

/// A whole volume as f32 (scaling applied) and its grid.
fn read(path: &std::path::Path) -> (Vec<f32>, [usize; 3]) {
    let mut s = open_volume(path, None).unwrap_or_else(|e| panic!("{e}"));
    let meta = s.meta().clone();
    let slab = s
        .read_slab(0, meta.dims[2])
        .unwrap_or_else(|e| panic!("{e}"));
    (slab.to_f32_scaled(&meta), meta.dims)
}

#[test]
fn abdomen_ct_bricks_on_the_gpu_equal_the_cpu() {
    let (Some(ct), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let Some(dev) = gpu() else { return };
    let (v, dims) = read(&ct);
    let (l, ldims) = read(&lab);
    assert_eq!(dims, ldims);
    let norm = Normaliser {
        lo: -1000.0,
        hi: 1500.0,
    };
    let h = filter_halo();
    // The filter bank on bricks inside and at both corners of the volume.
    let bank = GpuFilterBank::new(dev.clone(), true).expect("compile");
    let s = [24, 20, 16];
    for o in [
        [0, 0, 0],
        [dims[0] / 2, dims[1] / 2, dims[2] / 2],
        [dims[0] - s[0], dims[1] - s[1], dims[2] - s[2]],
    ] {
        let hb = halo_from_volume(&v, dims, o, s, h);
        check_filters(
            &format!("abdomen CT brick at {o:?}"),
            &bank,
            &hb,
            &norm,
            dims,
        );
    }
    // The forest on the CPU's filters+xyz of a central box, trained on its labels.
    let (o, s) = ([30, 25, 30], [48, 40, 40]);
    let hb = halo_from_volume(&v, dims, o, s, h);
    let f = compute(Classic::Filters, &hb, &norm, dims);
    let ch = Classic::Filters.channels();
    let d = ch + 3;
    let mut x = Vec::with_capacity(f.len() / ch * d);
    let mut y = Vec::with_capacity(f.len() / ch);
    let mut i = 0;
    for z in 0..s[2] {
        for yy in 0..s[1] {
            for xx in 0..s[0] {
                x.extend_from_slice(&f[i * ch..(i + 1) * ch]);
                x.extend([
                    pos(o[0] + xx, dims[0]),
                    pos(o[1] + yy, dims[1]),
                    pos(o[2] + z, dims[2]),
                ]);
                y.push(l[((o[2] + z) * dims[1] + o[1] + yy) * dims[0] + o[0] + xx] as u16);
                i += 1;
            }
        }
    }
    let classes = *y.iter().max().expect("voxels") as usize + 1;
    assert!(classes >= 3, "the box holds several labels");
    let forest = train_forest(&x, &y, d, classes, 6000, 20);
    let g = GpuForest::new(dev.clone(), &forest).expect("upload");
    check_forest("abdomen CT box, filters+xyz", &g, &forest, &x);
    // End to end on the GPU: the filter bank's planes straight into the forest, against the
    // CPU's features and forest (labels may differ only where an eigenvalue's f32 rounding
    // crosses a split threshold).
    let n = y.len();
    let slot = bank.slot(s, h).expect("slot");
    let out = dev
        .buffer(
            "out",
            g.output_bytes(n),
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        )
        .expect("out");
    let mut enc = dev.device.create_command_encoder(&Default::default());
    bank.encode(&slot, &mut enc, &hb, &norm, dims)
        .expect("filters");
    g.encode(&mut enc, slot.features(), FeatureLayout::planes(n), n, &out)
        .expect("forest");
    dev.queue.submit([enc.finish()]);
    let bytes = dev.read(&out, g.output_bytes(n)).expect("read");
    let lo = g.labels_offset(n) as usize;
    let want = forest.predict(&x).expect("cpu");
    let agree = want
        .iter()
        .zip(&bytes[lo..lo + n])
        .filter(|(a, b)| **a as u8 == **b)
        .count();
    eprintln!(
        "abdomen CT box end to end (GPU filter bank -> GPU forest): {agree} of {n} labels equal \
         the CPU's"
    );
    assert!(agree as f64 >= 0.999 * n as f64, "{agree} of {n}");
    dev.check().expect("no device error");
}
