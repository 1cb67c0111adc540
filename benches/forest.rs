//! Random-forest benchmark against scikit-learn on identical inputs
//! (`cargo bench -p neuvolex-benches --bench forest -- [--trees 1000] [--rounds 3]`).
//!
//! Inputs are real: the 64-D INR features of the abdomen CT (trained 1 epoch) with its
//! ground-truth labels. 20 000 voxels drawn at random (seeded) train both forests; 1 000 000
//! other voxels are predicted. Same settings on both sides (trees, min_samples_split 8,
//! max_features sqrt, no bootstrap, Gini) and the same threads (rayon's pool; `n_jobs`).
//!
//! Rounds interleave: each round fits a new forest on each side (seed / random_state = the
//! round) and then predicts with it on each side, scikit-learn in a persistent Python process
//! (`forest_sklearn.py`, where `NEUVOLEX_SKLEARN_PYTHON` or `python3` imports it) that loaded
//! the arrays once. Timed regions: the *fit* is `Forest::fit` plus the coding of the forest
//! for prediction (`Forest::prepare`, shown apart) against scikit-learn's `fit` (which builds
//! its tree arrays inside); the *predict* is `Forest::predict` (probabilities and argmax)
//! against `predict_proba` plus the argmax. Reported: median [min-max] of each and the
//! per-round ratio, and the mean F1 over the four foreground classes on both sides.

use neuvolex_benches::{arg, load_average, machine, ratio_spread, shared, spread, JsonChild};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::{Dataset, Forest, ForestConfig};
use neuvolex_features::extract::extract_brick;
use neuvolex_features::rng::Rng;
use neuvolex_features::FeatureKind;
use neuvolex_ingest::{ingest, IngestOptions};
use std::time::Instant;

fn f1_mean(pred: &[u16], truth: &[u16], classes: usize) -> (f64, Vec<f64>) {
    let mut f1s = Vec::new();
    for c in 1..classes as u16 {
        let tp = pred
            .iter()
            .zip(truth)
            .filter(|(p, t)| **p == c && **t == c)
            .count() as f64;
        let fp = pred
            .iter()
            .zip(truth)
            .filter(|(p, t)| **p == c && **t != c)
            .count() as f64;
        let fnn = pred
            .iter()
            .zip(truth)
            .filter(|(p, t)| **p != c && **t == c)
            .count() as f64;
        if tp + fnn > 0.0 {
            f1s.push(2.0 * tp / (2.0 * tp + fp + fnn));
        }
    }
    (f1s.iter().sum::<f64>() / f1s.len().max(1) as f64, f1s)
}

/// Training and test rows: `(d, classes, x_train, y_train, x_test, y_test)`.
type Inputs = (usize, usize, Vec<f32>, Vec<u16>, Vec<f32>, Vec<u16>);

/// The bench's inputs from the abdomen CT: ingest into `work`, one INR epoch, 64-D hidden
/// features of every voxel, 20 000 seeded training rows and 1 000 000 test rows.
fn make_inputs(ct: &std::path::Path, lab: &std::path::Path, work: &std::path::Path) -> Inputs {
    let sp = work.join("ct.zarr");
    let mut src = open_volume(ct, None).expect("ct");
    ingest(src.as_mut(), &sp, &IngestOptions::default(), &mut |_| {}).expect("ingest");
    let mut store = BrickStore::open(&sp).expect("store");
    let mut l = open_volume(lab, None).expect("labels");
    store
        .add_labels("gt", l.as_mut(), &[], &mut |_| {})
        .expect("labels");
    let model = neuvolex_benches::train_one_epoch(&store);
    // Features and labels of every voxel, brick by brick.
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for b in store.bricks() {
        x.extend(extract_brick(&model, &store, &b, FeatureKind::Hidden).expect("features"));
        y.extend(
            store
                .read_labels_box("gt", b.origin, b.size)
                .expect("labels")
                .iter()
                .map(|&v| v as u16),
        );
    }
    let d = 64;
    let n = y.len();
    let classes = *y.iter().max().unwrap_or(&0) as usize + 1;
    let mut order: Vec<usize> = (0..n).collect();
    Rng::new(0).shuffle(&mut order);
    let ntr = 20_000.min(n / 2);
    let nte = 1_000_000.min(n - ntr);
    let gather = |ids: &[usize]| -> (Vec<f32>, Vec<u16>) {
        (
            ids.iter()
                .flat_map(|&i| x[i * d..(i + 1) * d].iter().copied())
                .collect(),
            ids.iter().map(|&i| y[i]).collect(),
        )
    };
    let (xtr, ytr) = gather(&order[..ntr]);
    let (xte, yte) = gather(&order[ntr..ntr + nte]);
    (d, classes, xtr, ytr, xte, yte)
}

/// Writes the inputs as raw little-endian arrays and `meta.json` (what `forest_sklearn.py`
/// reads).
fn save_inputs(dir: &std::path::Path, (d, classes, xtr, ytr, xte, yte): &Inputs) {
    std::fs::create_dir_all(dir).expect("inputs folder");
    let w = |name: &str, bytes: Vec<u8>| std::fs::write(dir.join(name), bytes).expect("write");
    w(
        "xtr.f32",
        xtr.iter().flat_map(|v| v.to_le_bytes()).collect(),
    );
    w(
        "ytr.u16",
        ytr.iter().flat_map(|v| v.to_le_bytes()).collect(),
    );
    w(
        "xte.f32",
        xte.iter().flat_map(|v| v.to_le_bytes()).collect(),
    );
    w(
        "yte.u16",
        yte.iter().flat_map(|v| v.to_le_bytes()).collect(),
    );
    w(
        "meta.json",
        format!("{{\"d\": {d}, \"classes\": {classes}}}").into_bytes(),
    );
}

/// The inputs saved by [`save_inputs`] in `dir`, or `None` where any file is missing or
/// malformed.
fn load_inputs(dir: &std::path::Path) -> Option<Inputs> {
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("meta.json")).ok()?).ok()?;
    let (d, classes) = (
        meta["d"].as_u64()? as usize,
        meta["classes"].as_u64()? as usize,
    );
    let f32s = |name: &str| -> Option<Vec<f32>> {
        let b = std::fs::read(dir.join(name)).ok()?;
        (b.len() % (4 * d) == 0).then(|| {
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        })
    };
    let u16s = |name: &str| -> Option<Vec<u16>> {
        let b = std::fs::read(dir.join(name)).ok()?;
        Some(
            b.chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect(),
        )
    };
    let (xtr, ytr, xte, yte) = (
        f32s("xtr.f32")?,
        u16s("ytr.u16")?,
        f32s("xte.f32")?,
        u16s("yte.u16")?,
    );
    (xtr.len() == ytr.len() * d && xte.len() == yte.len() * d)
        .then_some((d, classes, xtr, ytr, xte, yte))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let trees: usize = arg(&args, "--trees", 1000);
    let rounds = arg(&args, "--rounds", 3usize).max(1);
    let threads = rayon::current_num_threads();
    println!(
        "machine: {}, {trees} trees, {rounds} interleaved rounds, {threads} threads on both sides, {}",
        machine(),
        load_average()
    );
    let (Some(ct), Some(lab)) = (
        shared("abdomen_ct/ct.nii.gz"),
        shared("abdomen_ct/labels.nii.gz"),
    ) else {
        return;
    };
    let dir = tempfile::tempdir().expect("tmp");
    // `NEUVOLEX_FOREST_INPUTS=DIR`: reuse the inputs saved there by an earlier run (so walks
    // built from different commits are compared on identical rows), or save them there.
    let saved = std::env::var_os("NEUVOLEX_FOREST_INPUTS").map(std::path::PathBuf::from);
    let inputs = match saved.as_deref().and_then(load_inputs) {
        Some(inputs) => inputs,
        None => {
            let inputs = make_inputs(&ct, &lab, dir.path());
            save_inputs(saved.as_deref().unwrap_or(dir.path()), &inputs);
            inputs
        }
    };
    // scikit-learn reads the saved inputs where they are.
    let inputs_dir = saved.as_deref().unwrap_or(dir.path());
    let (d, classes, xtr, ytr, xte, yte) = inputs;
    let nte = yte.len();
    let py = std::env::var("NEUVOLEX_SKLEARN_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("forest_sklearn.py");
    let mut sk = JsonChild::start(
        "scikit-learn",
        &py,
        &script,
        &[
            inputs_dir.display().to_string(),
            trees.to_string(),
            threads.to_string(),
        ],
        &[],
    );
    let (mut fit, mut pack, mut predict) = (Vec::new(), Vec::new(), Vec::new());
    let (mut sk_fit, mut sk_predict) = (Vec::new(), Vec::new());
    let (mut f1, mut sk_f1) = (Vec::new(), Vec::new());
    let mut last = None;
    for round in 0..rounds {
        let cfg = ForestConfig {
            trees,
            seed: round as u64,
            ..ForestConfig::default()
        };
        let t = Instant::now();
        let f = Forest::fit(
            Dataset {
                x: &xtr,
                y: &ytr,
                d,
                classes,
            },
            &cfg,
        )
        .expect("fit");
        let t_fit = t.elapsed().as_secs_f64();
        let coded = f.prepare();
        let total = t.elapsed().as_secs_f64();
        fit.push(total);
        pack.push(total - t_fit);
        if let Some(r) = sk.as_mut().and_then(|s| s.send("fit")) {
            sk_fit.push(r["fit_s"].as_f64().unwrap_or(f64::NAN));
        }
        let t = Instant::now();
        let pred = f.predict(&xte).expect("predict");
        predict.push(t.elapsed().as_secs_f64());
        f1.push(f1_mean(&pred, &yte, classes).0);
        if let Some(r) = sk.as_mut().and_then(|s| s.send("predict")) {
            sk_predict.push(r["predict_s"].as_f64().unwrap_or(f64::NAN));
            sk_f1.push(r["f1_mean"].as_f64().unwrap_or(f64::NAN));
        }
        if !coded {
            eprintln!(
                "note: round {round}'s forest could not be coded; it predicts with the f32 walk"
            );
        }
        last = Some(f);
    }
    let f = last.expect("one round");
    let mut depths = f.depths();
    depths.sort_unstable();
    println!(
        "forest shape (last round): {} nodes ({:.0} per tree, {:.1} MB as 8-byte nodes), deepest leaf per tree: median {}, range {}–{}",
        f.nodes(),
        f.nodes() as f64 / trees as f64,
        f.nodes() as f64 * 8.0 / 1e6,
        depths[depths.len() / 2],
        depths[0],
        depths[depths.len() - 1]
    );
    // A digest of the whole forest (FNV-1a of its JSON), so runs of different commits can show
    // that they grew the same trees.
    let json = serde_json::to_vec(&f).expect("forest as JSON");
    let digest = json.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    });
    println!("forest digest (last round): {digest:016x}");
    let rate = |t: &[f64]| {
        let mut s: Vec<f64> = t.iter().copied().filter(|x| x.is_finite()).collect();
        s.sort_by(f64::total_cmp);
        s.get(s.len() / 2).map_or("-".into(), |m| {
            format!("{:.0} k rows/s", nte as f64 / m / 1e3)
        })
    };
    let version = sk.as_ref().map_or("-".to_string(), |s| {
        s.ready["ready"].as_str().unwrap_or("?").to_string()
    });
    println!("| side | fit s (coding included) | of which coding s | predict {nte} rows s | rate | mean F1 per round |");
    println!("|---|---|---|---|---|---|");
    println!(
        "| neuvolex | {} | {} | {} | {} | {} |",
        spread(&fit, 2),
        spread(&pack, 2),
        spread(&predict, 2),
        rate(&predict),
        spread(&f1, 3)
    );
    println!(
        "| scikit-learn {version} | {} | - | {} | {} | {} |",
        spread(&sk_fit, 2),
        spread(&sk_predict, 2),
        rate(&sk_predict),
        spread(&sk_f1, 3)
    );
    let cond = format!("the same 20 000 training and {nte} test rows of the abdomen CT's 64-D INR features, same settings; {threads} threads each; {rounds} rounds");
    let f1s = format!("mean F1 {} against {}", spread(&f1, 3), spread(&sk_f1, 3));
    println!(
        "summary: | random forest fit, {trees} trees, against scikit-learn {version} | {cond}; timed: Forest::fit + coding against fit | {} s | {} s | {} | {f1s} |",
        spread(&fit, 2),
        spread(&sk_fit, 2),
        ratio_spread(&sk_fit, &fit)
    );
    println!(
        "summary: | random forest predict, {trees} trees, against scikit-learn {version} | {cond}; timed: predict (probabilities + argmax) on both | {} s | {} s | {} | {f1s} |",
        spread(&predict, 2),
        spread(&sk_predict, 2),
        ratio_spread(&sk_predict, &predict)
    );
    println!(
        "| ratio scikit-learn / neuvolex, per round | {} | | {} | | F1 difference {} |",
        ratio_spread(&sk_fit, &fit),
        ratio_spread(&sk_predict, &predict),
        spread(
            &f1.iter()
                .zip(&sk_f1)
                .map(|(a, b)| a - b)
                .collect::<Vec<_>>(),
            3
        )
    );
}
