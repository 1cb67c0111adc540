//! What the session's label history costs (`cargo bench -p neuvolex-benches --bench history`).
//!
//! Every complete round of a session records the labels it showed (issue 45: undo, redo and a
//! restore show them again), one zstd frame a brick, and the autosave writes the bricks not
//! written yet. This times, on real label volumes as the service bricks them (64^3), the parts
//! a round and a save add: packing every brick (the round), unpacking them (the base of the
//! next round, an undo), writing a round's bricks (first all, then a round that changed one
//! slab of 8 slices, sharing the rest), and reading two rounds back (a restart); with the bytes
//! they take. Volumes: the abdomen CT's and the brain MRI's ground truth (`../shared/data`,
//! skipped where absent), and the 512x512x452 phantom's (generated). Five repetitions each,
//! median and range.

use neuvolex_benches::{machine, shared, spread};
use neuvolex_bricks::synth::PhantomParams;
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_formats::MemVolume;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_server::labels::{load_rounds, save_bricks, LabelBrick, Round};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

const REPS: usize = 5;

/// A label volume bricked as the service bricks it (64^3).
fn bricked(dir: &std::path::Path, dims: [usize; 3], labels: &[f32]) -> BrickStore {
    let sp = dir.join("labels.zarr");
    let mut mem = MemVolume::from_f32(dims, labels);
    ingest(
        &mut mem,
        &sp,
        &IngestOptions {
            brick: 64,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    BrickStore::open(&sp).expect("store")
}

/// The labels of every brick of `store` from the whole label volume (x fastest).
fn per_brick<T: Copy + Into<u32>>(
    store: &BrickStore,
    labels: &[T],
) -> HashMap<[usize; 3], Vec<u16>> {
    let dims = store.info().dims;
    store
        .bricks()
        .map(|b| {
            let mut v = Vec::with_capacity(b.voxels());
            for row in b.rows(dims) {
                v.extend(
                    labels[row..row + b.size[0]]
                        .iter()
                        .map(|&x| x.into() as u16),
                );
            }
            (b.index, v)
        })
        .collect()
}

fn secs<F: FnMut()>(mut f: F) -> Vec<f64> {
    (0..REPS)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect()
}

fn run(name: &str, store: &BrickStore, per: HashMap<[usize; 3], Vec<u16>>) {
    let dims = store.info().dims;
    let voxels: usize = dims.iter().product();
    let pack = |per: &HashMap<[usize; 3], Vec<u16>>| -> HashMap<[usize; 3], Arc<LabelBrick>> {
        use rayon::prelude::*;
        per.par_iter()
            .map(|(k, l)| (*k, Arc::new(LabelBrick::pack(l).expect("pack"))))
            .collect()
    };
    let t_pack = secs(|| {
        std::hint::black_box(pack(&per));
    });
    let r1 = pack(&per);
    let t_unpack = secs(|| {
        use rayon::prelude::*;
        let n: usize = r1
            .par_iter()
            .map(|(_, b)| b.unpack().expect("unpack").len())
            .sum();
        assert_eq!(n, voxels);
    });
    // Round 2: one slab of 8 axial slices relabelled (a correction), the other bricks shared.
    let z0 = dims[2] / 2;
    let mut per2 = per.clone();
    let mut changed = 0;
    for b in store.bricks() {
        if b.origin[2] + b.size[2] <= z0 || b.origin[2] >= z0 + 8 {
            continue;
        }
        let l = per2.get_mut(&b.index).expect("brick");
        for z in 0..b.size[2] {
            if (z0..z0 + 8).contains(&(b.origin[2] + z)) {
                let s = z * b.size[0] * b.size[1];
                for v in &mut l[s..s + b.size[0] * b.size[1]] {
                    *v = if *v == 0 { 1 } else { 0 };
                }
            }
        }
        changed += 1;
    }
    let r2: HashMap<[usize; 3], Arc<LabelBrick>> = {
        let fresh = pack(&per2);
        fresh
            .into_iter()
            .map(|(k, b)| match r1.get(&k) {
                Some(old) if old.name == b.name => (k, old.clone()),
                _ => (k, b),
            })
            .collect()
    };
    let stroke: neuvolex_classify::Stroke = serde_json::from_value(serde_json::json!({
        "class": 1, "axis": "z", "slice": z0, "points": [[1, 1]], "radius": 1
    }))
    .expect("stroke");
    let line = vec![stroke.clone(), stroke];
    let rounds = vec![
        Arc::new(Round {
            strokes: Arc::new(line[..1].to_vec()),
            features: "filters+xyz/0".into(),
            labels: r1.clone(),
            verdicts: Default::default(),
        }),
        Arc::new(Round {
            strokes: Arc::new(line.clone()),
            features: "filters+xyz/0".into(),
            labels: r2,
            verdicts: Default::default(),
        }),
    ];
    let (mut t_save1, mut t_save2, mut t_load) = (Vec::new(), Vec::new(), Vec::new());
    let mut refs = Vec::new();
    for _ in 0..REPS {
        let w = tempfile::tempdir().expect("tempdir");
        let t = Instant::now();
        save_bricks(w.path(), &rounds[..1], &line).expect("save");
        t_save1.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        refs = save_bricks(w.path(), &rounds, &line).expect("save");
        t_save2.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let back = load_rounds(w.path(), store, &refs, &line).expect("load");
        t_load.push(t.elapsed().as_secs_f64() * 1e3);
        assert_eq!(back.len(), 2);
    }
    let bytes1: usize = r1.values().map(|b| b.zst.len()).sum();
    let unique: std::collections::HashSet<&String> = refs
        .iter()
        .flat_map(|r| r.bricks.iter().map(|b| &b.1))
        .collect();
    println!(
        "| {name} | {voxels} | {} | {} | {} | {} | {} ({changed} bricks) | {} | {:.0} KiB, {} unique bricks for 2 rounds |",
        store.bricks().count(),
        spread(&t_pack, 1),
        spread(&t_unpack, 1),
        spread(&t_save1, 1),
        spread(&t_save2, 1),
        spread(&t_load, 1),
        bytes1 as f64 / 1024.0,
        unique.len(),
    );
}

fn read_labels(rel: &str) -> Option<([usize; 3], Vec<f32>)> {
    let p = shared(rel)?;
    let mut v = open_volume(&p, None).expect("labels");
    let d = v.meta().dims;
    Some((d, MemVolume::read_all(v.as_mut()).expect("labels").to_f32()))
}

fn main() {
    println!(
        "label history, {} ({} reps, ms median [min-max])",
        machine(),
        REPS
    );
    println!("| labels | voxels | bricks | pack all | unpack all | write round 1 | write round 2 | read 2 rounds | round 1 on disk |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, rel) in [
        ("abdomen CT truth", "abdomen_ct/labels.nii.gz"),
        ("brain MRI truth", "brain_mri/labels.nii.gz"),
    ] {
        if let Some((d, l)) = read_labels(rel) {
            let dir = tempfile::tempdir().expect("tempdir");
            let store = bricked(dir.path(), d, &l);
            let per = per_brick(&store, &l.iter().map(|&x| x as u8).collect::<Vec<u8>>());
            run(name, &store, per);
        }
    }
    if std::env::var_os("NEUVOLEX_BENCH_NO_PHANTOM").is_none() {
        let dir = tempfile::tempdir().expect("tempdir");
        let sp = dir.path().join("phantom.zarr");
        let opts = IngestOptions {
            brick: 64,
            ..Default::default()
        };
        let store = neuvolex_ingest::phantom_store(
            &sp,
            PhantomParams::with_size(512, 0),
            &opts,
            &mut |_| {},
        )
        .expect("phantom");
        let dims = store.info().dims;
        let truth = store
            .read_labels_box("ground_truth", [0; 3], dims)
            .expect("truth");
        let per = per_brick(&store, &truth);
        drop(truth);
        run("512x512x452 phantom truth", &store, per);
    }
}
