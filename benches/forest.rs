//! Random-forest benchmark against scikit-learn on identical inputs
//! (`cargo bench -p neuvolex-benches --bench forest -- [--trees 1000] [--rounds 3]`).
//!
//! The task is the product's, on real data: the abdomen CT with the default feature set
//! (`filters+xyz`, the filter bank plus position, no model) and the simulated S2 scribbles
//! (`scribble-sim --level S2 --seed 0`, background 255) as the training rows; every voxel of the
//! volume is predicted and scored against the ground truth. Same settings on both sides as the
//! product's classifier (trees, min_samples_split 8, max_features sqrt, no bootstrap, Gini,
//! balanced class weights) and the same threads (rayon's pool; `n_jobs`).
//!
//! Rounds interleave: each round fits a new forest on each side (seed / random_state = the
//! round) and then predicts with it on each side, scikit-learn in a persistent Python process
//! (`forest_sklearn.py`, where `NEUVOLEX_SKLEARN_PYTHON` or `python3` imports it) that loaded
//! the arrays once. Timed regions: the *fit* is `Forest::fit` plus the coding of the forest
//! for prediction (`Forest::prepare`, shown apart) against scikit-learn's `fit` (which builds
//! its tree arrays inside); the *predict* is `Forest::predict` (probabilities and argmax)
//! against `predict_proba` plus the argmax. Rounds are paired by index: a round where either
//! side failed is dropped from both. Reported: median (the mean of the two middle rounds for
//! an even count) [min-max] of each, the per-round ratio, and the mean F1 over the foreground
//! classes on both sides, with whether they agree to 0.01.

use neuvolex_benches::{
    arg, load_average, machine, median_min_max, ratio_spread, shared, spread, JsonChild,
};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::features::DEFAULT_FEATURES;
use neuvolex_classify::{
    simulate, training_set, BrickFeatures, ClassifyConfig, Dataset, Forest, ForestConfig, Level,
    SimConfig,
};
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

/// Training and test rows: `(d, classes, x_train, y_train, x_test, y_test)`, class 0 the
/// background.
type Inputs = (usize, usize, Vec<f32>, Vec<u16>, Vec<f32>, Vec<u16>);

/// The bench's inputs from the abdomen CT: ingest into `work`, the default features, the S2
/// scribbles (seed 0) as training rows and every voxel as test rows. Classes are the
/// scribbles' labels in order with the background (255 in the scribbles, 0 in the ground truth)
/// first, so class 0 is the background on both sides.
fn make_inputs(ct: &std::path::Path, lab: &std::path::Path, work: &std::path::Path) -> Inputs {
    const BACKGROUND: u32 = 255;
    let sp = work.join("ct.zarr");
    let mut src = open_volume(ct, None).expect("ct");
    ingest(src.as_mut(), &sp, &IngestOptions::default(), &mut |_| {}).expect("ingest");
    let mut store = BrickStore::open(&sp).expect("store");
    let mut l = open_volume(lab, None).expect("labels");
    store
        .add_labels("gt", l.as_mut(), &[], &mut |_| {})
        .expect("labels");
    let (_, scr) = simulate(
        open_volume(lab, None).expect("labels").as_mut(),
        &SimConfig {
            level: Level::S2,
            seed: 0,
            background: BACKGROUND,
            ..SimConfig::default()
        },
    )
    .expect("S2 scribbles");
    let set = DEFAULT_FEATURES.parse().expect("feature set");
    let fx = BrickFeatures::new(&store, set, None, false).expect("features");
    let ts = training_set(&fx, &scr, BACKGROUND).expect("training set");
    assert!(
        ts.labels.contains(&BACKGROUND),
        "the background is scribbled"
    );
    // The class of a label: the background 0, the others from 1 in the scribbles' order.
    let fg: Vec<u32> = ts
        .labels
        .iter()
        .copied()
        .filter(|&c| c != BACKGROUND)
        .collect();
    let class = |label: u32| -> u16 {
        match label {
            0 | BACKGROUND => 0,
            l => fg
                .iter()
                .position(|&c| c == l)
                .map_or(u16::MAX, |k| k as u16 + 1),
        }
    };
    let ytr: Vec<u16> = ts.y.iter().map(|&k| class(ts.labels[k as usize])).collect();
    let (d, classes) = (ts.d, ts.labels.len());
    // Every voxel, brick by brick; a ground-truth class the scribbles never name is left out.
    let (mut xte, mut yte) = (Vec::new(), Vec::new());
    for b in store.bricks() {
        let f = fx.brick(&b).expect("features");
        let truth = store
            .read_labels_box("gt", b.origin, b.size)
            .expect("labels");
        for (row, &t) in f.chunks_exact(d).zip(&truth) {
            let c = class(t);
            if c != u16::MAX {
                xte.extend_from_slice(row);
                yte.push(c);
            }
        }
    }
    println!(
        "inputs: {DEFAULT_FEATURES} ({d} features), S2 scribbles: {} training rows over {classes} classes {:?}, {} test rows (every voxel)",
        ytr.len(),
        ts.labels,
        yte.len()
    );
    (d, classes, ts.x, ytr, xte, yte)
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
        format!("{{\"d\": {d}, \"classes\": {classes}, \"class_weight\": \"balanced\"}}")
            .into_bytes(),
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
    let mut dropped = Vec::new();
    let mut last = None;
    for round in 0..rounds {
        let cfg = ForestConfig {
            trees,
            seed: round as u64,
            ..ClassifyConfig::default().forest
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
        let sk_fit_s = sk
            .as_mut()
            .and_then(|s| s.send("fit"))
            .and_then(|r| r["fit_s"].as_f64());
        let t = Instant::now();
        let pred = f.predict(&xte).expect("predict");
        let predict_s = t.elapsed().as_secs_f64();
        let round_f1 = f1_mean(&pred, &yte, classes).0;
        let sk_pred = sk
            .as_mut()
            .and_then(|s| s.send("predict"))
            .and_then(|r| Some((r["predict_s"].as_f64()?, r["f1_mean"].as_f64()?)));
        if !coded {
            eprintln!(
                "note: round {round}'s forest could not be coded; it predicts with the f32 walk"
            );
        }
        last = Some(f);
        // Rounds are paired by index: a round that failed on either side counts on neither.
        let (Some(sk_fit_s), Some((sk_predict_s, sk_round_f1))) = (sk_fit_s, sk_pred) else {
            eprintln!("note: round {round} failed on the scikit-learn side; dropped from both");
            dropped.push(round);
            continue;
        };
        fit.push(total);
        pack.push(total - t_fit);
        predict.push(predict_s);
        f1.push(round_f1);
        sk_fit.push(sk_fit_s);
        sk_predict.push(sk_predict_s);
        sk_f1.push(sk_round_f1);
    }
    println!(
        "rounds: {} paired, {} dropped {dropped:?}",
        fit.len(),
        dropped.len()
    );
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
        median_min_max(t).map_or("-".into(), |(m, _, _)| {
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
    let cond = format!("the abdomen CT's S2 scribbles ({} rows) and every voxel ({nte} rows), {DEFAULT_FEATURES} ({d} features), the classifier's settings (balanced class weights); {threads} threads each; {} paired rounds of {rounds}", ytr.len(), fit.len());
    // F1 equal on both sides: the medians within 0.01.
    let equal = match (median_min_max(&f1), median_min_max(&sk_f1)) {
        (Some((a, _, _)), Some((b, _, _))) if (a - b).abs() <= 0.01 => "equal to 0.01",
        (Some(_), Some(_)) => "NOT equal to 0.01",
        _ => "not compared",
    };
    let f1s = format!(
        "mean F1 {} against {} ({equal})",
        spread(&f1, 3),
        spread(&sk_f1, 3)
    );
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
