//! The filter bank per brick and per slice (`cargo bench -p neuvolex-benches --bench filters`):
//! `neuvolex_filters::compute` (each intermediate step restricted to what the core reads)
//! against `filter_bank_reference` (every step over the whole halo read, the algorithm before),
//! on the same halo reads, threads and timed region, the outputs checked equal bit for bit.
//! Boxes: a 64^3 brick (the service's brick) and one whole axial slice, of the abdomen CT
//! (a generated volume of the same size where `../shared/data` is absent).
//!
//! Then what the enclosure rays (`neuvolex_filters::enclosure`, the `encl` features) add to a
//! box: their time from the store's pyramid against the filter bank's on the same box.

use neuvolex_benches::{machine, shared};
use neuvolex_bricks::derived::{halo_from_volume, Normaliser};
use neuvolex_bricks::open_volume;
use neuvolex_filters::{compute, enclosure, filter_bank_reference, Classic};
use neuvolex_ingest::downsample_mean;
use std::time::Instant;

fn main() {
    println!(
        "machine: {}, {} threads",
        machine(),
        rayon::current_num_threads()
    );
    let (name, dims, vals) = match shared("abdomen_ct/ct.nii.gz") {
        Some(p) => {
            let mut v = open_volume(&p, None).expect("open");
            let d = v.meta().dims;
            let slab = v.read_slab(0, d[2]).expect("read");
            let vals: Vec<f32> = slab.to_f32_scaled(v.meta());
            ("abdomen_ct", d, vals)
        }
        None => {
            let d = [122, 101, 112];
            let vals = (0..d.iter().product::<usize>())
                .map(|i| ((i % 122) as f32 * 0.3).sin() * 400.0 + (i / 12322) as f32)
                .collect();
            ("generated 122x101x112", d, vals)
        }
    };
    let lo = vals.iter().cloned().fold(f32::MAX, f32::min) as f64;
    let hi = vals.iter().cloned().fold(f32::MIN, f32::max) as f64;
    let norm = Normaliser { lo, hi };
    let h = Classic::Filters.halo();
    println!("volume: {name} {dims:?}, halo {h}");
    println!("| box | voxels | restricted s (median, range of 5) | whole-halo s (median, range of 5) | speed-up | equal |");
    println!("|---|---|---|---|---|---|");
    let time = |f: &dyn Fn() -> Vec<f32>| {
        let mut t: Vec<f64> = (0..5)
            .map(|_| {
                let s = Instant::now();
                std::hint::black_box(f());
                s.elapsed().as_secs_f64()
            })
            .collect();
        t.sort_by(f64::total_cmp);
        (t[2], t[0], t[4])
    };
    let z = dims[2] / 2;
    for (label, o, s) in [
        ("64^3 brick", [0, 0, 0], [64, 64, 64]),
        ("axial slice", [0, 0, z], [dims[0], dims[1], 1]),
    ] {
        let b = halo_from_volume(&vals, dims, o, s, h);
        let fast = compute(Classic::Filters, &b, &norm, dims);
        let full = filter_bank_reference(&b, &norm);
        let equal = fast.len() == full.len()
            && fast
                .iter()
                .zip(&full)
                .all(|(a, b)| a.to_bits() == b.to_bits());
        let (a, a0, a1) = time(&|| compute(Classic::Filters, &b, &norm, dims));
        let (r, r0, r1) = time(&|| filter_bank_reference(&b, &norm));
        println!(
            "| {label} | {} | {a:.3} ({a0:.3}–{a1:.3}) | {r:.3} ({r0:.3}–{r1:.3}) | {:.2}x | {equal} |",
            s.iter().product::<usize>(),
            r / a
        );
        assert!(equal, "{label}: the restricted filter bank changed a value");
    }
    // The pyramid the store keeps (2x means), from which the rays read.
    let mut data = vec![vals.clone()];
    let mut levels = vec![dims];
    for _ in 1..3 {
        let pd = *levels.last().expect("level 0");
        data.push(downsample_mean(data.last().expect("level"), pd));
        levels.push(pd.map(|d| d.div_ceil(2)));
    }
    let read = |k: usize, o: [usize; 3], s: [usize; 3]| -> Result<Vec<f32>, ()> {
        let d = levels[k];
        let mut out = Vec::with_capacity(s.iter().product());
        for z in o[2]..o[2] + s[2] {
            for y in o[1]..o[1] + s[1] {
                let row = (z * d[1] + y) * d[0];
                out.extend_from_slice(&data[k][row + o[0]..row + o[0] + s[0]]);
            }
        }
        Ok(out)
    };
    println!();
    println!("| box | enclosure s (median, range of 5) | filter bank s (median) | enclosure / filter bank |");
    println!("|---|---|---|---|");
    for (label, o, s) in [
        ("64^3 brick", [0, 0, 0], [64, 64, 64]),
        ("axial slice", [0, 0, z], [dims[0], dims[1], 1]),
    ] {
        let b = halo_from_volume(&vals, dims, o, s, h);
        let (e, e0, e1) = time(&|| enclosure::compute(&levels, &norm, o, s, read).expect("read"));
        let (f, _, _) = time(&|| compute(Classic::Filters, &b, &norm, dims));
        println!(
            "| {label} | {e:.3} ({e0:.3}–{e1:.3}) | {f:.3} | {:.2} |",
            e / f
        );
    }
}
