//! The GPU filter bank against the CPU filter bank (`neuvolex_filters::compute`,
//! `Classic::Filters`, then the position): bricks of a generated phantom inside and at the edge
//! of its volume, constant bricks, huge and tiny values, and NaN-free output for finite input.
//! Without an adapter the tests skip visibly; under CI=true they fail.
//!
//! Tolerance (per channel `c` of a brick, against the CPU value `w`):
//! `|gpu - w| <= REL * (|w| + scale_c)`, where `scale_c` is the largest `|w|` of the channel's
//! kind in the brick (the Gaussians' for the Gaussian and DoG, the channel's own otherwise): the
//! GPU sums the same taps in the same order but may fuse multiply-adds, and its eigenvalues are
//! the CPU's closed form in f32 instead of f64. Positions are exact.

mod common;

use common::{check_filters as check, cpu_filters as cpu, gpu, phantom};
use neuvolex_bricks::derived::{halo_from_volume, Normaliser};
use neuvolex_bricks::rng::Rng;
use neuvolex_classify_gpu::GpuFilterBank;
use neuvolex_filters::{filter_halo, PER_SIGMA};

#[test]
fn gpu_filter_bank_equals_the_cpu_on_phantom_bricks() {
    let Some(dev) = gpu() else { return };
    let bank = GpuFilterBank::new(dev.clone(), true).expect("compile");
    let dims = [40, 34, 30];
    let (v, _) = phantom(dims, 18.0, 1);
    let norm = Normaliser {
        lo: -200.0,
        hi: 400.0,
    };
    let h = filter_halo();
    // Inside, at the low corner and at the high corner of the volume (partial bricks).
    for (o, s) in [
        ([12, 10, 9], [16, 12, 10]),
        ([0, 0, 0], [9, 7, 5]),
        ([31, 26, 24], [9, 8, 6]),
    ] {
        let hb = halo_from_volume(&v, dims, o, s, h);
        check(&format!("phantom brick at {o:?}"), &bank, &hb, &norm, dims);
    }
    // A larger halo than needed is fine; a smaller one is an error.
    let hb = halo_from_volume(&v, dims, [5, 5, 5], [4, 4, 4], h + 2);
    check("halo + 2", &bank, &hb, &norm, dims);
    let hb = halo_from_volume(&v, dims, [5, 5, 5], [4, 4, 4], h - 1);
    assert!(bank.compute(&hb, &norm, dims).is_err());
    dev.check().expect("no device error");
}

#[test]
fn gpu_filter_bank_on_extremes() {
    let Some(dev) = gpu() else { return };
    let bank = GpuFilterBank::new(dev.clone(), false).expect("compile");
    let dims = [20, 18, 16];
    let h = filter_halo();
    let unit = Normaliser { lo: 0.0, hi: 1.0 };
    let (v, _) = phantom(dims, 30.0, 2);
    let (o, s) = ([4, 3, 2], [8, 7, 6]);
    // Constant bricks: the Gaussians are the value, the DoG a rounding, everything else zero.
    for c in [0.0f32, 1.0, -3.5e6, 1e-20] {
        let hb = halo_from_volume(&vec![c; v.len()], dims, o, s, h);
        let got = bank.compute(&hb, &unit, dims).expect("constant");
        let want = cpu(&hb, &unit, dims, false);
        let ch = bank.channels();
        for (g, w) in got.chunks_exact(ch).zip(want.chunks_exact(ch)) {
            for k in 0..ch {
                // The Gaussian and the DoG (two kernels' sums of the value, a rounding apart).
                if k % PER_SIGMA == 0 || k % PER_SIGMA == 3 {
                    assert!(
                        (g[k] - w[k]).abs() <= 1e-6 * c.abs(),
                        "{c}: {} {}",
                        g[k],
                        w[k]
                    );
                } else {
                    assert_eq!(g[k], 0.0, "constant {c}, channel {k}");
                }
            }
        }
    }
    // Huge and tiny intensities (normalised as they are).
    for scale in [1e15f32, 1e-25] {
        let w: Vec<f32> = v.iter().map(|x| x * scale).collect();
        let hb = halo_from_volume(&w, dims, o, s, h);
        check(&format!("phantom x {scale:e}"), &bank, &hb, &unit, dims);
    }
    // Any finite input up to 1e18 (whose structure-tensor products stay finite in f32): no NaN.
    let mut rng = Rng::new(4);
    for mag in [1e18f32, 1.0, 1e-30] {
        let w: Vec<f32> = (0..v.len())
            .map(|_| match rng.below(4) {
                0 => 0.0,
                1 => mag,
                2 => -mag,
                _ => rng.uniform(-mag, mag),
            })
            .collect();
        let hb = halo_from_volume(&w, dims, o, s, h);
        let got = bank.compute(&hb, &unit, dims).expect("random");
        assert!(
            got.iter().all(|x| x.is_finite()),
            "non-finite features for finite input of magnitude {mag:e}"
        );
    }
    dev.check().expect("no device error");
}
