//! Brick-store benchmarks (`cargo bench -p neuvolex-benches --bench bricks`):
//! 1. ingest throughput of bonsai (256^3 u8) against reading the same bytes plainly;
//! 2. halo-brick read throughput (cold and cached) and derived-quantity throughput;
//! 3. peak RSS while ingesting a 512x512x452 u16 raw volume written by the bench itself.

use neuvolex_benches::{machine, median, peak_rss_mib, shared};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_formats::{DType, Endian, RawSpec, VolumeSource};
use neuvolex_ingest::{ingest, IngestOptions};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

const CTA: [usize; 3] = [512, 512, 452];

fn read_plain(src: &mut dyn VolumeSource) -> usize {
    let nz = src.meta().dims[2];
    let mut n = 0;
    let mut z = 0;
    while z < nz {
        let d = 64.min(nz - z);
        n += src.read_slab(z, d).expect("read").bytes.len();
        z += d;
    }
    n
}

fn bench_ingest(name: &str, path: &Path, raw: Option<&RawSpec>, dir: &Path) {
    let bytes = {
        let mut s = open_volume(path, raw).expect("open");
        read_plain(s.as_mut())
    };
    let mb = bytes as f64 / 1e6;
    let t_read = median(3, || {
        let mut s = open_volume(path, raw).expect("open");
        read_plain(s.as_mut());
    });
    let out = dir.join(format!("{name}.zarr"));
    let t_ingest = median(3, || {
        let mut s = open_volume(path, raw).expect("open");
        let opts = IngestOptions {
            overwrite: true,
            ..Default::default()
        };
        ingest(s.as_mut(), &out, &opts, &mut |_| {}).expect("ingest");
    });
    println!(
        "| ingest {name} | {mb:.1} MB | plain read {:.0} MB/s ({:.3} s) | ingest {:.0} MB/s ({:.3} s) | ingest/read time {:.2}x |",
        mb / t_read.as_secs_f64(),
        t_read.as_secs_f64(),
        mb / t_ingest.as_secs_f64(),
        t_ingest.as_secs_f64(),
        t_ingest.as_secs_f64() / t_read.as_secs_f64()
    );
}

fn bench_halo(store_path: &Path) {
    let voxels_per = |store: &BrickStore| store.bricks().map(|b| b.voxels()).sum::<usize>() as f64;
    let cold = {
        let store = BrickStore::open(store_path).expect("open store");
        let n = voxels_per(&store);
        let t = Instant::now();
        for b in store.bricks().collect::<Vec<_>>() {
            std::hint::black_box(store.read_halo(&b, 2).expect("halo"));
        }
        n / t.elapsed().as_secs_f64()
    };
    let store = BrickStore::open(store_path).expect("open store");
    store.set_cache_capacity(4096);
    let bricks: Vec<_> = store.bricks().collect();
    for b in &bricks {
        store.read_halo(b, 2).expect("halo");
    }
    let n = voxels_per(&store);
    let warm = median(3, || {
        for b in &bricks {
            std::hint::black_box(store.read_halo(b, 2).expect("halo"));
        }
    });
    let derived = median(3, || {
        for b in &bricks {
            std::hint::black_box(store.derived(b).expect("derived"));
        }
    });
    println!(
        "| halo-2 brick reads (bonsai store, 64^3 bricks) | cold {:.1} Mvox/s | cached {:.1} Mvox/s | derived quantities {:.1} Mvox/s |",
        cold / 1e6,
        n / warm.as_secs_f64() / 1e6,
        n / derived.as_secs_f64() / 1e6
    );
}

/// Writes a CTA-scale u16 raw volume slice by slice (bounded memory).
fn write_cta_raw(path: &Path) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).expect("create raw"));
    let mut slice = vec![0u8; CTA[0] * CTA[1] * 2];
    for z in 0..CTA[2] {
        for y in 0..CTA[1] {
            for x in 0..CTA[0] {
                let (fx, fy) = (x as f32 / 256.0 - 1.0, y as f32 / 256.0 - 1.0);
                let body = fx * fx / 0.8 + fy * fy / 0.5 < 1.0;
                let v: u16 = if body {
                    1000 + ((x * 7 + y * 13 + z * 3) % 200) as u16
                        + if (fx * fx + fy * fy) < 0.01 { 1500 } else { 0 }
                } else {
                    24
                };
                slice[(y * CTA[0] + x) * 2..(y * CTA[0] + x) * 2 + 2]
                    .copy_from_slice(&v.to_le_bytes());
            }
        }
        f.write_all(&slice).expect("write");
    }
    f.flush().expect("flush");
}

fn child_ingest(raw: &str, out: &str) {
    let spec = RawSpec {
        dims: CTA,
        dtype: DType::U16,
        endian: Endian::Little,
        spacing: [0.4, 0.4, 0.5],
        offset: 0,
    };
    let t = Instant::now();
    let mut s = open_volume(Path::new(raw), Some(&spec)).expect("open raw");
    let info = ingest(
        s.as_mut(),
        Path::new(out),
        &IngestOptions {
            overwrite: true,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    println!(
        "{} {} {}",
        t.elapsed().as_secs_f64(),
        peak_rss_mib().unwrap_or(f64::NAN),
        info.grid().iter().product::<usize>()
    );
}

fn bench_rss(dir: &Path) {
    let raw = dir.join("cta_512x512x452_uint16.raw");
    write_cta_raw(&raw);
    let out = dir.join("cta.zarr");
    let exe = std::env::current_exe().expect("exe");
    let o = std::process::Command::new(exe)
        .args([
            "--child-ingest",
            &raw.to_string_lossy(),
            &out.to_string_lossy(),
        ])
        .output()
        .expect("child");
    let text = String::from_utf8_lossy(&o.stdout);
    let v: Vec<f64> = text
        .split_whitespace()
        .filter_map(|s| s.parse().ok())
        .collect();
    if v.len() < 3 {
        eprintln!("child failed: {}", String::from_utf8_lossy(&o.stderr));
        return;
    }
    let mb = (CTA.iter().product::<usize>() * 2) as f64 / 1e6;
    println!("| ingest 512x512x452 u16 raw (mmap) | {mb:.0} MB | {:.2} s, {:.0} MB/s | peak RSS {:.1} MiB ({:.0}% of the volume) | {} bricks |", v[0], mb / v[0], v[1], 100.0 * v[1] * 1.048576 / mb, v[2]);
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child-ingest") {
        child_ingest(&args[i + 1], &args[i + 2]);
        return;
    }
    println!("machine: {}", machine());
    let dir = tempfile::tempdir().expect("tmp");
    if let Some(bonsai) = shared("scivis/bonsai.nii.gz") {
        bench_ingest("bonsai.nii.gz (gzip)", &bonsai, None, dir.path());
        // The same voxels as an uncompressed raw file, to separate gzip from ingest cost.
        let raw = dir.path().join("bonsai_256x256x256_uint8.raw");
        let mut s = open_volume(&bonsai, None).expect("open");
        std::fs::write(&raw, s.read_slab(0, 256).expect("read").bytes).expect("write raw");
        bench_ingest("bonsai raw (mmap)", &raw, None, dir.path());
        bench_halo(&dir.path().join("bonsai raw (mmap).zarr"));
    }
    bench_rss(dir.path());
}
