//! Warm CPU frames of one volume, for profiling the ray marcher (`perf record`, callgrind)
//! without the benchmark's VTK run:
//! `cargo run --release -p neuvolex-render --example frames -- VOLUME.nii.gz PRESET SIZE FRAMES
//! [STORE]` ingests the volume into STORE (default: a temporary folder; an existing store is
//! reused), renders one cold frame and FRAMES warm ones with the benchmark's view, and prints
//! the milliseconds of each and a checksum of the last image.

use neuvolex_bricks::{open_volume, BrickStore};

use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_render::{BrickSource, RenderParams, Renderer, StoreSource, TfFile};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 5 {
        eprintln!("usage: frames VOLUME PRESET SIZE FRAMES [STORE]");
        std::process::exit(2);
    }
    let (size, frames): (usize, usize) =
        (a[3].parse().expect("SIZE"), a[4].parse().expect("FRAMES"));
    let tmp = std::env::temp_dir().join(format!("neuvolex-frames-{}", std::process::id()));
    let store = a.get(5).map_or(tmp.clone(), PathBuf::from);
    if !store.exists() {
        let mut v = open_volume(std::path::Path::new(&a[1]), None).expect("open volume");
        let o = IngestOptions {
            brick: 32,
            ..Default::default()
        };
        ingest(v.as_mut(), &store, &o, &mut |_| {}).expect("ingest");
    }
    let st = Arc::new(BrickStore::open(&store).expect("open store"));
    let source = StoreSource::new(st);
    let tf = TfFile::preset(&a[2]).expect("preset");
    let luts = tf.compile(&source.normaliser(), &source.classes());
    let p = RenderParams::bench_view(size);
    let mut r = Renderer::new(source, 2 << 30);
    let t = Instant::now();
    r.render(&p, &luts).expect("render");
    println!("cold {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    let mut img = None;
    for _ in 0..frames {
        let t = Instant::now();
        img = Some(r.render(&p, &luts).expect("render"));
        println!("warm {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    }
    if let Some(i) = img {
        let s: f64 = i.rgb.iter().flatten().map(|&v| v as f64).sum();
        println!("checksum {s:.4}; {:?}", r.stats());
    }
    if a.get(5).is_none() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
}
