//! K-means and view scoring on real volumes, against scikit-learn's KMeans on the same rows
//! (`cargo bench -p neuvolex-benches --bench kmeans -- [--k 50]`).
//!
//! Abdomen CT: the INR's 64-D last hidden layer (1 epoch), as in the paper. CT-Bonsai: the 11-D
//! local features (an INR epoch on its 16.7 M voxels is not a benchmark's job). Rows are those of
//! the occupied bricks, held in memory so both sides time clustering only. Reported: k-means
//! time and inertia for Lloyd and mini-batch, scikit-learn's time and inertia (where
//! `NEUVOLEX_SKLEARN_PYTHON` or `python3` imports it), and the time to aggregate cluster normals,
//! score 1800 views and select.

use neuvolex_benches::{machine, shared};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::features::BrickFeatures;
use neuvolex_features::extract::extract_brick;
use neuvolex_features::FeatureKind;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_viewpoints::kmeans::Algorithm;
use neuvolex_viewpoints::scores::{score_views, select, Aggregator, SelectConfig};
use neuvolex_viewpoints::{fibonacci_sphere, ClusterPartial, KMeans, KMeansConfig};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let k: usize = args
        .iter()
        .position(|a| a == "--k")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(50);
    println!("machine: {}, k = {k}", machine());
    println!("| volume | features | rows x dim | neuvolex Lloyd s (iters) | inertia | mini-batch s | inertia | scikit-learn s (iters) | inertia | speed ratio | inertia ratio | normals + 1800 views + select s |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, rel, inr) in [
        ("abdomen_ct", "abdomen_ct/ct.nii.gz", true),
        ("bonsai", "scivis/bonsai.nii.gz", false),
    ] {
        let Some(src) = shared(rel) else { continue };
        let dir = tempfile::tempdir().expect("tmp");
        let sp = dir.path().join("s.zarr");
        let mut v = open_volume(&src, None).expect("open");
        ingest(v.as_mut(), &sp, &IngestOptions::default(), &mut |_| {}).expect("ingest");
        let store = BrickStore::open(&sp).expect("store");
        let bricks = store.occupied_bricks(None);
        let (chunks, dim, what): (Vec<Vec<f32>>, usize, &str) = if inr {
            let model = neuvolex_benches::train_one_epoch(&store);
            let ch = bricks
                .iter()
                .map(|b| extract_brick(&model, &store, b, FeatureKind::Hidden).expect("features"))
                .collect();
            (ch, 64, "INR hidden")
        } else {
            let fx = BrickFeatures::new(&store, "local".parse().unwrap(), None, false)
                .expect("features");
            let ch = bricks
                .iter()
                .map(|b| fx.brick(b).expect("features"))
                .collect();
            (ch, 11, "local")
        };
        let rows: usize = chunks.iter().map(|c| c.len() / dim).sum();
        let fit = |algorithm| {
            let t = Instant::now();
            let km = KMeans::fit(
                chunks.len(),
                dim,
                |i| Ok(chunks[i].as_slice()),
                &KMeansConfig {
                    k,
                    algorithm,
                    ..Default::default()
                },
            )
            .expect("kmeans");
            (t.elapsed().as_secs_f64(), km)
        };
        let (t_lloyd, km) = fit(Algorithm::Lloyd);
        let (t_mb, mb) = fit(Algorithm::MiniBatch { epochs: 3 });
        // View scoring: cluster normals from every occupied brick, 1800 views, selection.
        let t = Instant::now();
        let mut agg = Aggregator::new(k);
        for (b, c) in bricks.iter().zip(&chunks) {
            let labels = km.assign(c);
            let g = store.derived(b).expect("derived").gradient;
            agg.add(
                &ClusterPartial::from_brick(k, &labels, &g, store.info().spacing).expect("partial"),
            );
        }
        let summ = agg.partial().summary();
        let views = fibonacci_sphere(1800);
        let scores = score_views(&summ, &views).expect("scores");
        let sel = select(&summ, &scores, &SelectConfig::default()).expect("select");
        let t_views = t.elapsed().as_secs_f64();
        // scikit-learn on the same rows.
        let path = dir.path().join("rows.f32");
        let bytes: Vec<u8> = chunks
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(&path, bytes).expect("rows");
        let py = std::env::var("NEUVOLEX_SKLEARN_PYTHON").unwrap_or_else(|_| "python3".into());
        let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("kmeans_sklearn.py");
        let sk = std::process::Command::new(&py)
            .arg(&script)
            .arg(&path)
            .arg(dim.to_string())
            .arg(k.to_string())
            .output()
            .ok()
            .filter(|o| o.status.success())
            .and_then(|o| serde_json::from_slice::<serde_json::Value>(&o.stdout).ok());
        let (sk_s, sk_in, sk_it) = match &sk {
            Some(v) => (
                format!("{:.1}", v["fit_s"].as_f64().unwrap_or(f64::NAN)),
                format!("{:.4e}", v["inertia"].as_f64().unwrap_or(f64::NAN)),
                v["iterations"].as_i64().unwrap_or(0),
            ),
            None => {
                eprintln!("SKIP scikit-learn ({py}): not importable");
                ("-".into(), "-".into(), 0)
            }
        };
        let ratio = sk
            .as_ref()
            .map(|v| {
                (
                    format!("{:.2}x", v["fit_s"].as_f64().unwrap_or(f64::NAN) / t_lloyd),
                    format!(
                        "{:.4}",
                        km.inertia / v["inertia"].as_f64().unwrap_or(f64::NAN)
                    ),
                )
            })
            .unwrap_or(("-".into(), "-".into()));
        println!(
            "| {name} | {what} | {rows} x {dim} | {t_lloyd:.1} ({}) | {:.4e} | {t_mb:.1} | {:.4e} | {sk_s} ({sk_it}) | {sk_in} | {} | {} | {t_views:.2} ({} views) |",
            km.iterations, km.inertia, mb.inertia, ratio.0, ratio.1, sel.views.len()
        );
    }
}
