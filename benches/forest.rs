//! Random-forest benchmark against scikit-learn on identical inputs
//! (`cargo bench -p neuvolex-benches --bench forest -- [--trees 1000] [--repeat 3]`).
//!
//! Inputs are real: the 64-D INR features of the abdomen CT (trained 1 epoch) with its
//! ground-truth labels. 20 000 voxels drawn at random (seeded) train both forests; 1 000 000
//! other voxels are predicted. Fit time, predict time and the mean F1 over the four foreground
//! classes are reported for both, from one run; prediction runs `--repeat` times for both
//! (alternating is not possible across processes, so each side repeats back to back) and is
//! reported as the range and the ratio of the medians. scikit-learn runs where `NEUVOLEX_SKLEARN_PYTHON`
//! (or `python3`) imports it.

use neuvolex_benches::{machine, shared};
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

/// Median and `min–max` of timings.
fn median_range(t: &mut [f64]) -> (f64, String) {
    if t.is_empty() {
        return (f64::NAN, String::new());
    }
    t.sort_by(f64::total_cmp);
    (
        t[t.len() / 2],
        format!("{:.2}–{:.2} s", t[0], t[t.len() - 1]),
    )
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
    let trees: usize = args
        .iter()
        .position(|a| a == "--trees")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(1000);
    let repeat: usize = args
        .iter()
        .position(|a| a == "--repeat")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(1)
        .max(1);
    println!("machine: {}, {trees} trees", machine());
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
    let (d, classes, xtr, ytr, xte, yte) = match saved.as_deref().and_then(load_inputs) {
        Some(inputs) => inputs,
        None => {
            let inputs = make_inputs(&ct, &lab, dir.path());
            if let Some(s) = &saved {
                save_inputs(s, &inputs);
            }
            inputs
        }
    };
    let nte = yte.len();
    let cfg = ForestConfig {
        trees,
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
    let fit = t.elapsed().as_secs_f64();
    let mut depths = f.depths();
    depths.sort_unstable();
    println!(
        "forest shape: {} nodes ({:.0} per tree, {:.1} MB as 8-byte nodes), deepest leaf per tree: median {}, range {}–{}",
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
    println!("forest digest: {digest:016x}");
    let mut times = Vec::new();
    let mut pred = Vec::new();
    for _ in 0..repeat {
        let t = Instant::now();
        pred = f.predict(&xte).expect("predict");
        times.push(t.elapsed().as_secs_f64());
    }
    let (predict, range) = median_range(&mut times);
    // The uncoded f32 walk (the previous prediction), once, for the step's gain.
    let t = Instant::now();
    let p32 = f.predict_proba_f32(&xte).expect("predict");
    let walk = t.elapsed().as_secs_f64();
    let coded = f.predict_proba(&xte).expect("predict");
    let same = p32 == coded;
    println!("| neuvolex f32 walk (before coding) | predict {walk:.2} s | coded / f32 walk {:.2}x | identical probabilities: {same} |", walk / predict);
    let (f1, per) = f1_mean(&pred, &yte, classes);
    println!("| neuvolex forest | fit {fit:.1} s | predict {nte} rows {predict:.2} s [{range}] ({:.0} k rows/s) | mean F1 {f1:.3} {per:.3?} | {} nodes |", nte as f64 / predict / 1e3, f.nodes());
    // scikit-learn on the same arrays.
    save_inputs(dir.path(), &(d, classes, xtr, ytr, xte, yte));
    let py = std::env::var("NEUVOLEX_SKLEARN_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("forest_sklearn.py");
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(2);
    match std::process::Command::new(py)
        .arg(script)
        .arg(dir.path())
        .arg(trees.to_string())
        .arg(threads.to_string())
        .arg(repeat.to_string())
        .output()
    {
        Ok(o) if o.status.success() => {
            let text = String::from_utf8_lossy(&o.stdout);
            let v: serde_json::Value =
                serde_json::from_str(text.lines().last().unwrap_or("{}")).unwrap_or_default();
            let sf = v["fit_s"].as_f64().unwrap_or(f64::NAN);
            let mut st: Vec<f64> = v["predict_s"]
                .as_array()
                .map(|a| a.iter().filter_map(|t| t.as_f64()).collect())
                .unwrap_or_default();
            let (sp, srange) = median_range(&mut st);
            println!("| scikit-learn {} | fit {sf:.1} s | predict {predict_rows} rows {sp:.2} s [{srange}] ({:.0} k rows/s) | mean F1 {:.3} {:?} |", v["sklearn"], nte as f64 / sp / 1e3, v["f1_mean"].as_f64().unwrap_or(f64::NAN), v["f1"], predict_rows = nte);
            println!("| ratio scikit-learn / neuvolex | fit {:.2}x | predict {:.2}x | F1 difference {:+.3} |", sf / fit, sp / predict, f1 - v["f1_mean"].as_f64().unwrap_or(f64::NAN));
        }
        Ok(o) => eprintln!(
            "SKIP scikit-learn: {}",
            String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
        Err(e) => eprintln!("SKIP scikit-learn: {e}"),
    }
}
