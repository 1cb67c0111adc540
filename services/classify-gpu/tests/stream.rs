//! Bricks streamed through the GPU's ring of blocks (`predict_stream`) against the same bricks
//! predicted one at a time on the GPU (bit for bit) and against the CPU forest on the CPU's
//! features (labels), on a store with partial bricks at every far end; the f16 rounding of the
//! service's cached features; the order results come in; stopping early; and the GPU memory
//! budget (a ring that must shrink, and one brick over budget refused with the budget named).
//! Without an adapter the tests skip visibly; under CI=true they fail.

mod common;

use common::{class_indices, filters_xyz, gpu, phantom, train_forest};
use neuvolex_bricks::{Brick, BrickStore};
use neuvolex_classify::accel::{AccelOptions, AcceleratedBrick, Accelerator, BrickPredictor};
use neuvolex_classify::features::FeatureSet;
use neuvolex_classify::Forest;
use neuvolex_classify_gpu::{AdapterKind, GpuAccelerator, GpuDevice, StreamConfig};
use neuvolex_filters::Classic;
use std::collections::HashMap;
use std::sync::Arc;

/// A store of the phantom on an odd grid in bricks of 8, its CPU features (`filters+xyz`,
/// voxel-major) and a forest trained on them.
struct Case {
    _dir: tempfile::TempDir,
    store: Arc<BrickStore>,
    x: Vec<f32>,
    forest: Forest,
    classes: usize,
}

fn case() -> Case {
    let dims = [45, 38, 29];
    let (v, lab) = phantom(dims, 18.0, 7);
    let dir = tempfile::tempdir().expect("tmp");
    let p = dir.path().join("s.zarr");
    let mut vol = neuvolex_formats::MemVolume::from_f32(dims, &v);
    neuvolex_ingest::ingest(
        &mut vol,
        &p,
        &neuvolex_ingest::IngestOptions {
            brick: 8,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    let store = Arc::new(BrickStore::open(&p).expect("store"));
    let x = filters_xyz(&v, dims, &store.normaliser());
    let (y, classes) = class_indices(&lab);
    let d = Classic::Filters.channels() + 3;
    let forest = train_forest(&x, &y, d, classes, 3000, 16);
    Case {
        _dir: dir,
        store,
        x,
        forest,
        classes,
    }
}

fn predictor(
    dev: &Arc<GpuDevice>,
    c: &Case,
    stream: StreamConfig,
    f16: bool,
) -> Box<dyn BrickPredictor> {
    GpuAccelerator::new(dev.clone())
        .with_stream(stream)
        .prepare(
            c.store.clone(),
            &"filters+xyz".parse::<FeatureSet>().expect("set"),
            &c.forest,
            &AccelOptions {
                tau: 0.0,
                f16_features: f16,
            },
        )
        .expect("prepare")
}

/// Every brick streamed, in the order given: (brick, result) in the order they came.
fn stream(p: &dyn BrickPredictor, order: &[Brick]) -> Vec<(Brick, AcceleratedBrick)> {
    let mut got = Vec::new();
    p.predict_stream(order, &mut |b, a| {
        got.push((*b, a));
        true
    })
    .expect("stream");
    got
}

/// The stroked-slice-first order of a session: the bricks of brick layer 1 (z), then the
/// rest from the far corner back.
fn session_order(store: &BrickStore) -> Vec<Brick> {
    let mut all: Vec<Brick> = store.bricks().collect();
    all.reverse();
    let (mut first, rest): (Vec<Brick>, Vec<Brick>) =
        all.into_iter().partition(|b| b.index[2] == 1);
    first.extend(rest);
    first
}

#[test]
fn streamed_blocks_equal_bricks_predicted_alone_and_the_cpu() {
    let Some(dev) = gpu() else { return };
    let c = case();
    let order = session_order(&c.store);
    let alone = predictor(&dev, &c, StreamConfig::default(), false);
    // Blocks of 2^3 bricks of 8, a ring of 2.
    let cfg = StreamConfig {
        in_flight: 2,
        block: 16,
        ..StreamConfig::default()
    };
    let p = predictor(&dev, &c, cfg, false);
    let got = stream(p.as_ref(), &order);
    assert_eq!(got.len(), order.len(), "every brick once");
    let mut seen = std::collections::BTreeSet::new();
    for (b, _) in &got {
        assert!(seen.insert(b.index), "brick {:?} twice", b.index);
    }
    // Blocks come whole, in the order of their first brick in `order`.
    let key = |b: &Brick| b.index.map(|i| i / 2);
    let mut first_at: HashMap<[usize; 3], usize> = HashMap::new();
    for (i, b) in order.iter().enumerate() {
        first_at.entry(key(b)).or_insert(i);
    }
    let ranks: Vec<usize> = got.iter().map(|(b, _)| first_at[&key(b)]).collect();
    assert!(
        ranks.windows(2).all(|w| w[0] <= w[1]),
        "block order {ranks:?}"
    );
    // The first results are the stroked layer's.
    assert_eq!(got[0].0.index[2], 1);
    // Bit for bit the bricks computed alone; labels as the CPU forest on the CPU's features.
    let dims = c.store.info().dims;
    let d = Classic::Filters.channels() + 3;
    let (mut differ_cpu, mut voxels) = (0usize, 0usize);
    for (b, a) in &got {
        let one = alone.predict(b).expect("alone");
        assert_eq!(a.probs, one.probs, "probabilities of brick {:?}", b.index);
        assert_eq!(a.classes, one.classes, "classes of brick {:?}", b.index);
        let mut rows = Vec::with_capacity(b.voxels() * d);
        for r in b.rows(dims) {
            rows.extend_from_slice(&c.x[r * d..(r + b.size[0]) * d]);
        }
        let want = c.forest.predict(&rows).expect("cpu");
        differ_cpu += want
            .iter()
            .zip(&a.classes)
            .filter(|(w, g)| **w as u8 != **g)
            .count();
        voxels += b.voxels();
        assert_eq!(a.probs.len(), b.voxels() * c.classes);
    }
    eprintln!("streamed: {differ_cpu} of {voxels} labels differ from the CPU's");
    assert!(differ_cpu * 1000 <= voxels, "{differ_cpu} of {voxels}");
    dev.check().expect("no device error");
}

#[test]
fn f16_features_are_predicted_as_the_cpu_predicts_the_cache() {
    let Some(dev) = gpu() else { return };
    let c = case();
    let order: Vec<Brick> = c.store.bricks().collect();
    let p = predictor(&dev, &c, StreamConfig::default(), true);
    let dims = c.store.info().dims;
    let d = Classic::Filters.channels() + 3;
    let (mut differ, mut probs_differ, mut voxels) = (0usize, 0usize, 0usize);
    for (b, a) in stream(p.as_ref(), &order) {
        let mut rows = Vec::with_capacity(b.voxels() * d);
        for r in b.rows(dims) {
            rows.extend(
                c.x[r * d..(r + b.size[0]) * d]
                    .iter()
                    .map(|&v| neuvolex_classify::features::f16_saturating(v)),
            );
        }
        let want = c.forest.predict_proba_f16(&rows).expect("cpu");
        let q: Vec<u8> = want
            .iter()
            .map(|&v| neuvolex_classify::stable::to_u8(v))
            .collect();
        probs_differ += q.iter().zip(&a.probs).filter(|(x, y)| x != y).count();
        for (row, &g) in want.chunks_exact(c.classes).zip(&a.classes) {
            differ += (neuvolex_classify::shard::argmax(row).0 as u8 != g) as usize;
        }
        voxels += b.voxels();
    }
    eprintln!(
        "f16 features: {differ} of {voxels} labels and {probs_differ} of {} probabilities differ \
         from the CPU forest on the cache's f16 features",
        voxels * c.classes
    );
    assert!(differ * 1000 <= voxels, "{differ} of {voxels}");
    assert!(probs_differ * 500 <= voxels * c.classes);
}

#[test]
fn a_stream_stops_when_asked_and_the_ring_serves_the_next() {
    let Some(dev) = gpu() else { return };
    let c = case();
    let order: Vec<Brick> = c.store.bricks().collect();
    let cfg = StreamConfig {
        in_flight: 3,
        block: 16,
        ..StreamConfig::default()
    };
    let p = predictor(&dev, &c, cfg, false);
    let mut calls = 0;
    p.predict_stream(&order, &mut |_, _| {
        calls += 1;
        calls < 5
    })
    .expect("stopped stream");
    assert_eq!(calls, 5, "no brick after the one that said stop");
    let again = stream(p.as_ref(), &order[..10]);
    assert_eq!(again.len(), 10);
    let alone = predictor(&dev, &c, StreamConfig::default(), false);
    for (b, a) in &again {
        assert_eq!(a.classes, alone.predict(b).expect("alone").classes);
    }
}

#[test]
fn the_ring_stays_within_its_gpu_memory_budget() {
    let Some(shared) = gpu() else { return };
    let c = case();
    let order: Vec<Brick> = c.store.bricks().collect();
    let want: Vec<Vec<u8>> = {
        let p = predictor(&shared, &c, StreamConfig::default(), false);
        stream(p.as_ref(), &order)
            .into_iter()
            .map(|(_, a)| a.classes)
            .collect()
    };
    // A device of its own, so that its memory account holds this test's buffers alone.
    let dev = GpuDevice::new(AdapterKind::Any).expect("device");
    // Room for one block of one brick: blocks of 16 shrink to 8, and the ring to one block.
    for budget in [12 << 20, 40 << 20] {
        let cfg = StreamConfig {
            in_flight: 4,
            block: 32,
            budget,
        };
        let p = predictor(&dev, &c, cfg, false);
        dev.reset_peak();
        let got: Vec<Vec<u8>> = stream(p.as_ref(), &order)
            .into_iter()
            .map(|(_, a)| a.classes)
            .collect();
        let peak = dev.peak_bytes();
        eprintln!("budget {budget} bytes: peak GPU buffers {peak} bytes");
        assert!(peak <= budget, "peak {peak} over the budget {budget}");
        // In order here (one block a brick in the first case), and the same labels either way.
        let mut got_sorted = got.clone();
        got_sorted.sort();
        let mut want_sorted = want.clone();
        want_sorted.sort();
        assert_eq!(got_sorted, want_sorted, "budget {budget}");
    }
    // Past the budget with one brick: refused, the budget named.
    let p = predictor(
        &dev,
        &c,
        StreamConfig {
            budget: 1 << 20,
            ..StreamConfig::default()
        },
        false,
    );
    let e = p
        .predict_stream(&order, &mut |_, _| true)
        .expect_err("over budget");
    assert!(e.to_string().contains("budget of 1 MiB"), "{e}");
}
