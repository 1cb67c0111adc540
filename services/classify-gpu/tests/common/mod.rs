//! Shared by the GPU tests: one device per test binary, and a small CT-like phantom.

#![allow(dead_code)]

use neuvolex_bricks::derived::{halo_from_volume, HaloBrick, Normaliser};
use neuvolex_bricks::rng::Rng;
use neuvolex_bricks::synth::phantom_at;
use neuvolex_classify::stable::to_u8;
use neuvolex_classify::{Dataset, Forest, ForestConfig};
use neuvolex_classify_gpu::{AdapterKind, GpuDevice, GpuFilterBank, GpuForest};
use neuvolex_filters::{compute, pos, Classic, PER_SIGMA, SIGMAS};
use std::sync::{Arc, OnceLock};

/// The device (any adapter: lavapipe in CI), or `None` with a visible SKIP; under `CI=true` a
/// missing adapter fails.
pub fn gpu() -> Option<Arc<GpuDevice>> {
    static DEV: OnceLock<Result<Arc<GpuDevice>, String>> = OnceLock::new();
    match DEV.get_or_init(|| GpuDevice::new(AdapterKind::Any).map_err(|e| e.to_string())) {
        Ok(d) => {
            eprintln!("gpu adapter: {}", d.describe());
            Some(d.clone())
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

/// The CT-like phantom on a `dims` grid with uniform noise of `noise` HU: intensities and
/// labels, x fastest.
pub fn phantom(dims: [usize; 3], noise: f32, seed: u64) -> (Vec<f32>, Vec<u8>) {
    let mut rng = Rng::new(seed);
    let mut v = Vec::with_capacity(dims.iter().product());
    let mut l = Vec::with_capacity(v.capacity());
    let c = |i: usize, n: usize| 2.0 * (i as f64 + 0.5) / n as f64 - 1.0;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (hu, lab) = phantom_at([c(x, dims[0]), c(y, dims[1]), c(z, dims[2])]);
                v.push(hu as f32 + rng.uniform(-noise, noise));
                l.push(lab);
            }
        }
    }
    (v, l)
}

/// Labels as class indices in order of first appearance, and the number of classes.
pub fn class_indices(lab: &[u8]) -> (Vec<u16>, usize) {
    let mut seen: Vec<u8> = Vec::new();
    let y = lab
        .iter()
        .map(|l| match seen.iter().position(|s| s == l) {
            Some(k) => k as u16,
            None => {
                seen.push(*l);
                seen.len() as u16 - 1
            }
        })
        .collect();
    (y, seen.len())
}

/// Relative tolerance of the smoothed channels (Gaussian, LoG, gradient magnitude, DoG).
pub const REL: f32 = 2e-5;
/// Relative tolerance of the eigenvalue channels (f32 closed form against f64), of the largest
/// eigenvalue magnitude of the same matrix in the brick.
pub const REL_EIGEN: f32 = 5e-4;

/// The CPU's `filters` of `hb`, then `xyz` where asked (voxel-major).
pub fn cpu_filters(hb: &HaloBrick, norm: &Normaliser, dims: [usize; 3], xyz: bool) -> Vec<f32> {
    let bank = compute(Classic::Filters, hb, norm, dims);
    let ch = Classic::Filters.channels();
    let mut out = Vec::with_capacity(bank.len() / ch * (ch + 3));
    let mut i = 0;
    for z in 0..hb.size[2] {
        for y in 0..hb.size[1] {
            for x in 0..hb.size[0] {
                out.extend_from_slice(&bank[i * ch..(i + 1) * ch]);
                if xyz {
                    out.extend([
                        pos(hb.origin[0] + x, dims[0]),
                        pos(hb.origin[1] + y, dims[1]),
                        pos(hb.origin[2] + z, dims[2]),
                    ]);
                }
                i += 1;
            }
        }
    }
    out
}

/// Compares the GPU's features of `hb` with the CPU's within the stated tolerances, and prints
/// the largest error per channel kind relative to its scale.
pub fn check_filters(
    what: &str,
    bank: &GpuFilterBank,
    hb: &HaloBrick,
    norm: &Normaliser,
    dims: [usize; 3],
) {
    let ch = bank.channels();
    let bank_ch = SIGMAS.len() * PER_SIGMA;
    let want = cpu_filters(hb, norm, dims, ch > bank_ch);
    let got = bank.compute(hb, norm, dims).expect("gpu filter bank");
    assert_eq!(got.len(), want.len(), "{what}");
    assert!(
        got.iter().all(|v| !v.is_nan()),
        "{what}: NaN in the GPU's features"
    );
    // Scales: per scale, the Gaussian's largest magnitude; per channel, its own.
    let mut own = vec![0.0f32; ch];
    for row in want.chunks_exact(ch) {
        for (o, v) in own.iter_mut().zip(row) {
            *o = o.max(v.abs());
        }
    }
    let mut worst = [0.0f32; 4];
    for (v, (g, w)) in got.chunks_exact(ch).zip(want.chunks_exact(ch)).enumerate() {
        for c in 0..ch {
            let (a, b) = (g[c], w[c]);
            if c >= bank_ch {
                assert_eq!(a, b, "{what}: position channel {c} of voxel {v}");
                continue;
            }
            let (s, k) = (c / PER_SIGMA, c % PER_SIGMA);
            let (scale, tol, kind) = match k {
                0 | 3 => (own[s * PER_SIGMA], REL, 0),
                1 | 2 => (own[c], REL, 1),
                4..=6 => (own[s * PER_SIGMA + 4], REL_EIGEN, 2),
                _ => (
                    own[s * PER_SIGMA + 7]
                        .max(own[s * PER_SIGMA + 9])
                        .max(own[s * PER_SIGMA + 8]),
                    REL_EIGEN,
                    3,
                ),
            };
            let err = (a - b).abs();
            let bound = tol * (b.abs() + scale);
            if scale > 0.0 {
                worst[kind] = worst[kind].max(err / scale);
            }
            assert!(
                err <= bound || (a == b),
                "{what}: channel {c} (scale {s}, kind {k}) of voxel {v}: gpu {a:e}, cpu {b:e}, \
                 error {err:e} > {bound:e}"
            );
        }
    }
    eprintln!(
        "{what}: largest error over the channel's scale: gaussian/dog {:.1e}, log/gradient \
         {:.1e}, structure tensor {:.1e}, hessian {:.1e}",
        worst[0], worst[1], worst[2], worst[3]
    );
}

/// `filters+xyz` of the whole volume, as the CPU computes it (voxel-major).
pub fn filters_xyz(v: &[f32], dims: [usize; 3], norm: &Normaliser) -> Vec<f32> {
    let hb = halo_from_volume(v, dims, [0; 3], dims, Classic::Filters.halo());
    let bank = compute(Classic::Filters, &hb, norm, dims);
    let ch = Classic::Filters.channels();
    let mut out = Vec::with_capacity(bank.len() / ch * (ch + 3));
    let mut i = 0;
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                out.extend_from_slice(&bank[i * ch..(i + 1) * ch]);
                out.extend([pos(x, dims[0]), pos(y, dims[1]), pos(z, dims[2])]);
                i += 1;
            }
        }
    }
    out
}

/// A forest of `trees` trained on `rows` random rows of `x` with labels `y`.
pub fn train_forest(
    x: &[f32],
    y: &[u16],
    d: usize,
    classes: usize,
    rows: usize,
    trees: usize,
) -> Forest {
    let mut rng = Rng::new(5);
    let n = y.len();
    let pick: Vec<usize> = (0..rows).map(|_| rng.below(n)).collect();
    let xs: Vec<f32> = pick
        .iter()
        .flat_map(|&r| x[r * d..(r + 1) * d].iter().copied())
        .collect();
    let ys: Vec<u16> = pick.iter().map(|&r| y[r]).collect();
    let cfg = ForestConfig {
        trees,
        min_samples_split: 2,
        ..Default::default()
    };
    Forest::fit(
        Dataset {
            x: &xs,
            y: &ys,
            d,
            classes,
        },
        &cfg,
    )
    .expect("forest")
}

/// What the CPU gives: u8 probabilities, labels (first most probable), and the rows whose top
/// two probabilities are equal (ties).
pub fn cpu_forest(forest: &Forest, x: &[f32]) -> (Vec<u8>, Vec<u8>, usize) {
    let c = forest.classes();
    let p = forest.predict_proba(x).expect("cpu");
    let labels = forest.predict(x).expect("cpu");
    let ties = p
        .chunks(c)
        .filter(|r| {
            let mut s = r.to_vec();
            s.sort_by(|a, b| b.total_cmp(a));
            s.len() > 1 && s[0] == s[1]
        })
        .count();
    (
        p.iter().map(|&v| to_u8(v)).collect(),
        labels.iter().map(|&l| l as u8).collect(),
        ties,
    )
}

/// Asserts the GPU's prediction equals the CPU's, and reports ties.
pub fn check_forest(what: &str, gpu_forest: &GpuForest, forest: &Forest, x: &[f32]) {
    let (want_p, want_l, ties) = cpu_forest(forest, x);
    let got = gpu_forest.predict(x).expect("gpu prediction");
    let c = forest.classes();
    let n = want_l.len();
    assert_eq!(got.probs.len(), n * c, "{what}");
    assert_eq!(got.labels.len(), n, "{what}");
    let prob_diff = got
        .probs
        .iter()
        .zip(&want_p)
        .filter(|(a, b)| a != b)
        .count();
    let label_diff = got
        .labels
        .iter()
        .zip(&want_l)
        .filter(|(a, b)| a != b)
        .count();
    eprintln!(
        "{what}: {n} voxels, {c} classes, {} trees: {prob_diff} u8 probabilities and \
         {label_diff} labels differ; {ties} voxels have tied top probabilities on the CPU",
        forest.trees()
    );
    assert_eq!(prob_diff, 0, "{what}: u8 probabilities differ");
    assert_eq!(label_diff, 0, "{what}: labels differ");
}
