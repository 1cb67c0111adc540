//! K-means on real volumes against scikit-learn's KMeans, like for like, and view scoring
//! (`cargo bench -p neuvolex-benches --bench kmeans -- [--k 50] [--rounds 3] [--max-iter 20]
//! [--threads 2]`).
//!
//! Volumes: abdomen CT, the INR's 64-D last hidden layer after 1 epoch (as in the paper), and
//! CT-Bonsai, the 11-D local features (an INR epoch on its 16.7 M voxels is not a benchmark's
//! job). Rows are those of the occupied bricks, held in memory by both sides.
//!
//! Conditions, the same on both sides:
//! - **Start**: the same `k x dim` initial centroids, computed once before any timing by
//!   neuvolex's greedy k-means++ (seed 0, on its 20 000-row seeded sample,
//!   [`KMeans::init_centroids`]); neuvolex fits from them with [`KMeans::fit_from`],
//!   scikit-learn with `init=array, n_init=1`. Neither side's timing includes an
//!   initialisation.
//! - **Iterations**: `tol = 0` and `max_iter` (20 by default) on both sides, so each stops only
//!   at `max_iter` or on strict convergence (neuvolex: a zero centroid shift; scikit-learn:
//!   labels unchanged, which gives a zero shift). Both then run one more assignment pass for
//!   the final labels and inertia. (With a non-zero `tol` the two would not stop alike:
//!   scikit-learn scales `tol` by the mean per-feature variance of all rows, neuvolex by that of
//!   its 20 000-row sample.) The table gives each side's iterations and, where they differ, the
//!   per-iteration ratio too.
//! - **Algorithms**, two pairs: plain Lloyd (neuvolex `bounds_mib: 0`: every distance every
//!   pass) against scikit-learn `algorithm="lloyd"`, and bounded: neuvolex Hamerly (a bounds
//!   budget that holds every row's 10 bytes, `bounds: Always`) against scikit-learn
//!   `algorithm="elkan"`. (neuvolex's default, `bounds: Auto`, measures both on the first
//!   passes and keeps the faster.)
//! - **Threads**: `--threads` (2 by default) on both sides: neuvolex's rayon global pool (its
//!   only parallelism; the matrix product is single-threaded), scikit-learn's OpenMP and BLAS
//!   pools limited by threadpoolctl (`threadpool_limits`) and `OMP_NUM_THREADS`. Both counts
//!   are printed as the libraries report them.
//! - **Data and timed region**: float32 rows on both sides. neuvolex times `KMeans::fit_from`
//!   over the in-memory chunks (which includes drawing its 20 000-row sample for the
//!   tolerance and empty-cluster re-seeding: milliseconds). scikit-learn's rows are a float32
//!   C-contiguous array loaded once, before any timing, in one persistent Python process
//!   (`kmeans_sklearn.py`, JSON lines on stdin/stdout; `NEUVOLEX_SKLEARN_PYTHON`, else
//!   `python3`); it times `km.fit(x)` only, with the default `copy_x=True` (fit copies and
//!   centres x: part of its time).
//! - **Rounds**: `--rounds` (3 by default) interleaved rounds, each neuvolex plain,
//!   scikit-learn lloyd, neuvolex Hamerly, scikit-learn elkan, so a load change on the machine
//!   hits both sides alike. Times are median [min-max] over the rounds; the ratio is the
//!   per-round scikit-learn / neuvolex time, median [min-max].
//! - **Equivalence**: from the same start with the same iterations the inertias should agree
//!   to about 1e-4 (float rounding can move a near-tie row); both are float32 squared distances
//!   summed in float64 (scikit-learn's recomputed from its centres and labels after the timing;
//!   its own `inertia_`, a float32 sum, is printed below the table). A ratio off 1 by more than
//!   1e-3 is flagged.
//!
//! - **Best against best**: per volume, each side's fastest algorithm (the lower median time of
//!   its two) against the other's, as one more row and `summary:` line (the per-round ratio of
//!   those two fits); and neuvolex's default configuration (`bounds: Auto`, run once a round
//!   after the pairs) against scikit-learn's fastest.
//!
//! Also: mini-batch k-means (3 epochs, from the same start) and the time to aggregate cluster
//! normals over every occupied brick, score 1800 views and select, from the Hamerly fit.
//! Without Python or scikit-learn a SKIP line says so and neuvolex's side still runs.

use neuvolex_benches::{
    arg, load_average, machine, median_min_max, ratio_spread, shared, spread, JsonChild,
};
use neuvolex_bricks::{open_volume, BrickStore};
use neuvolex_classify::features::BrickFeatures;
use neuvolex_features::extract::extract_brick;
use neuvolex_features::FeatureKind;
use neuvolex_ingest::{ingest, IngestOptions};
use neuvolex_viewpoints::kmeans::{Algorithm, BoundsUse};
use neuvolex_viewpoints::scores::{score_views, select, Aggregator, SelectConfig};
use neuvolex_viewpoints::{fibonacci_sphere, ClusterPartial, KMeans, KMeansConfig};
use std::io::{BufWriter, Write};
use std::path::Path;
use std::time::Instant;

/// scikit-learn's KMeans in one persistent Python process (`kmeans_sklearn.py`).
struct Sk(JsonChild);

impl Sk {
    /// Starts the script with `threads` threads; `None` (with a SKIP line naming what is
    /// missing) where Python or scikit-learn is not there.
    fn start(threads: usize) -> Option<Sk> {
        let py = std::env::var("NEUVOLEX_SKLEARN_PYTHON").unwrap_or_else(|_| "python3".into());
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("kmeans_sklearn.py");
        let t = threads.to_string();
        let c = JsonChild::start(
            "scikit-learn",
            &py,
            &script,
            std::slice::from_ref(&t),
            &[("OMP_NUM_THREADS", &t)],
        )?;
        if c.ready["ready"] == true {
            return Some(Sk(c));
        }
        println!(
            "SKIP scikit-learn: `{py}` cannot run kmeans_sklearn.py: {}",
            c.ready["error"].as_str().unwrap_or("no ready line")
        );
        None
    }

    /// Sends one command; the reply, or `Err` with the script's error (or its exit).
    fn send(&mut self, cmd: &str) -> Result<serde_json::Value, String> {
        match self.0.send(cmd) {
            None => Err("the Python process ended (its error is above)".into()),
            Some(r) => match r["error"].as_str() {
                Some(e) => Err(e.to_string()),
                None => Ok(r),
            },
        }
    }
}

/// One side's fits over the rounds (NaN where a fit failed).
#[derive(Default)]
struct Runs {
    secs: Vec<f64>,
    iters: Vec<usize>,
    inertia: Vec<f64>,
}

/// The median of the finite values, or NaN.
fn median(v: &[f64]) -> f64 {
    median_min_max(v).map_or(f64::NAN, |s| s.0)
}

/// Per-round `a[i] / b[i]`.
fn ratios(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x / y).collect()
}

/// The distinct values of a side's iteration counts, as `20` or `19-20`.
fn iters(v: &[usize]) -> String {
    match (v.iter().min(), v.iter().max()) {
        (Some(a), Some(b)) if a == b => a.to_string(),
        (Some(a), Some(b)) => format!("{a}-{b}"),
        _ => "-".into(),
    }
}

/// Writes `values` as little-endian float32.
fn write_f32<'a>(path: &Path, values: impl Iterator<Item = &'a f32>) {
    let mut w = BufWriter::new(std::fs::File::create(path).expect("create"));
    for v in values {
        w.write_all(&v.to_le_bytes()).expect("write");
    }
    w.flush().expect("write");
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let k = arg(&args, "--k", 50);
    let rounds = arg(&args, "--rounds", 3).max(1);
    let max_iter = arg(&args, "--max-iter", 20).max(1);
    let threads = arg(&args, "--threads", 2).max(1);
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global()
        .expect("rayon pool");
    println!("machine: {}; {} at start", machine(), load_average());
    println!(
        "k = {k}, tol = 0, max_iter = {max_iter}, {rounds} interleaved rounds, the same \
         k-means++ start (neuvolex, seed 0) on both sides, float32 rows"
    );
    let mut sk = Sk::start(threads);
    let sk_threads = match &sk {
        Some(s) => {
            println!(
                "threads: neuvolex rayon {}; scikit-learn {} (numpy {}) OpenMP {} (OMP_NUM_THREADS={threads}, threadpoolctl pools: {})",
                rayon::current_num_threads(),
                s.0.ready["sklearn"].as_str().unwrap_or("?"),
                s.0.ready["numpy"].as_str().unwrap_or("?"),
                s.0.ready["openmp_threads"],
                s.0.ready["pools"]
                    .as_array()
                    .map(|a| a
                        .iter()
                        .filter_map(|p| p.as_str())
                        .collect::<Vec<_>>()
                        .join(", "))
                    .unwrap_or_default()
            );
            s.0.ready["openmp_threads"].to_string()
        }
        None => {
            println!("threads: neuvolex rayon {}", rayon::current_num_threads());
            "-".into()
        }
    };
    let mut table = Vec::new();
    let mut summaries: Vec<String> = Vec::new();
    let mut notes = Vec::new();
    let mut views_table = Vec::new();
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
            (ch, 64, "INR hidden (1 epoch)")
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
        let load = |i: usize| Ok(chunks[i].as_slice());
        let base = KMeansConfig {
            k,
            max_iter,
            tol: 0.0,
            ..Default::default()
        };
        // The one start of every fit, outside any timing.
        let init = KMeans::init_centroids(chunks.len(), dim, load, &base).expect("init");
        // Hamerly's budget holds every row's bounds (10 bytes a row).
        let hamerly = KMeansConfig {
            bounds_mib: (rows * 10).div_ceil(1 << 20).max(base.bounds_mib),
            bounds: BoundsUse::Always,
            ..base
        };
        let plain = KMeansConfig {
            bounds_mib: 0,
            ..base
        };
        // scikit-learn's copy of the rows and the start, loaded once.
        let mut sk_here = false;
        if let Some(s) = sk.as_mut() {
            let rows_path = dir.path().join("rows.f32");
            let init_path = dir.path().join("init.f32");
            write_f32(&rows_path, chunks.iter().flatten());
            write_f32(&init_path, init.iter());
            match s.send(&format!(
                "load {} {} {dim} {k} {max_iter}",
                rows_path.display(),
                init_path.display()
            )) {
                Ok(r) if r["rows"].as_u64() == Some(rows as u64) => sk_here = true,
                Ok(r) => println!("SKIP scikit-learn on {name}: it read {} rows", r["rows"]),
                Err(e) => println!("SKIP scikit-learn on {name}: {e}"),
            }
            std::fs::remove_file(&rows_path).ok();
        }
        let pairs = [
            ("plain Lloyd vs lloyd", plain, "lloyd"),
            ("Hamerly vs elkan", hamerly, "elkan"),
        ];
        // runs[pair][side]: side 0 neuvolex, 1 scikit-learn.
        let mut runs: [[Runs; 2]; 2] = Default::default();
        // neuvolex's default (`bounds: Auto`), once a round after the pairs.
        let mut auto = Runs::default();
        let mut sk_own_inertia: [Vec<f64>; 2] = Default::default();
        let mut fitted = None;
        for round in 0..rounds {
            for (p, (label, cfg, algo)) in pairs.iter().enumerate() {
                let t = Instant::now();
                let km = KMeans::fit_from(chunks.len(), dim, load, cfg, &init).expect("kmeans");
                let secs = t.elapsed().as_secs_f64();
                eprintln!(
                    "{name} round {}: neuvolex {label}: {secs:.2} s, {} iterations",
                    round + 1,
                    km.iterations
                );
                let n = &mut runs[p][0];
                n.secs.push(secs);
                n.iters.push(km.iterations);
                n.inertia.push(km.inertia);
                fitted = Some(km);
                if !sk_here {
                    continue;
                }
                let s = sk.as_mut().expect("scikit-learn");
                let r = s.send(&format!("fit {algo}"));
                let o = &mut runs[p][1];
                match r {
                    Ok(r) => {
                        let f = |key: &str| r[key].as_f64().unwrap_or(f64::NAN);
                        eprintln!(
                            "{name} round {}: scikit-learn {algo}: {:.2} s, {} iterations",
                            round + 1,
                            f("fit_s"),
                            r["iterations"]
                        );
                        o.secs.push(f("fit_s"));
                        o.iters.push(r["iterations"].as_u64().unwrap_or(0) as usize);
                        o.inertia.push(f("inertia"));
                        sk_own_inertia[p].push(f("inertia_sklearn"));
                    }
                    Err(e) => {
                        println!(
                            "SKIP scikit-learn {algo} on {name}, round {}: {e}",
                            round + 1
                        );
                        o.secs.push(f64::NAN);
                        o.iters.push(0);
                        o.inertia.push(f64::NAN);
                    }
                }
            }
            let t = Instant::now();
            let km = KMeans::fit_from(chunks.len(), dim, load, &base, &init).expect("kmeans");
            let secs = t.elapsed().as_secs_f64();
            eprintln!(
                "{name} round {}: neuvolex default (auto): {secs:.2} s, {} iterations",
                round + 1,
                km.iterations
            );
            auto.secs.push(secs);
            auto.iters.push(km.iterations);
            auto.inertia.push(km.inertia);
        }
        for (p, (label, _, algo)) in pairs.iter().enumerate() {
            let [n, o] = &runs[p];
            let have_sk = o.secs.iter().any(|s| s.is_finite());
            let mut ratio = ratio_spread(&o.secs, &n.secs);
            if have_sk && n.iters != o.iters {
                let per = |r: &Runs| -> Vec<f64> {
                    r.secs
                        .iter()
                        .zip(&r.iters)
                        .map(|(s, &i)| s / i as f64)
                        .collect()
                };
                let (per_n, per_o) = (per(n), per(o));
                ratio = format!("{ratio}; per iteration {}", ratio_spread(&per_o, &per_n));
            }
            let in_n = median(&n.inertia);
            let in_ratios = ratios(&n.inertia, &o.inertia);
            let worst = in_ratios
                .iter()
                .filter(|r| r.is_finite())
                .map(|r| (r - 1.0).abs())
                .fold(0.0f64, f64::max);
            let inertia = if have_sk {
                let in_o = median(&o.inertia);
                let flag = if worst > 1e-3 {
                    println!(
                        "WARNING: {name} {label}: inertia ratio off 1 by {worst:.2e} (> 1e-3): \
                         the two sides did not compute the same clustering"
                    );
                    " **MISMATCH > 1e-3**"
                } else {
                    ""
                };
                format!("{in_n:.6e} / {in_o:.6e} ({:.6}){flag}", median(&in_ratios))
            } else {
                format!("{in_n:.6e} / -")
            };
            table.push(format!(
                "| {name} | {what} | {rows} x {dim} | {} / {sk_threads} | {label} | {} / {} | {} | {} | {ratio} | {inertia} |",
                rayon::current_num_threads(),
                iters(&n.iters),
                if have_sk { iters(&o.iters) } else { "-".into() },
                spread(&n.secs, 2),
                if have_sk { spread(&o.secs, 2) } else { "-".into() },
            ));
            if have_sk {
                summaries.push(format!(
                    "| k-means {label}, {name} | k = {k}, {rows} x {dim} float32 rows ({what}), the same k-means++ start, tol 0 and {max_iter} iterations on both ({} / {}); timed: fit alone; {} threads each; {rounds} rounds | {} s | {} s (scikit-learn {}) | {ratio} | inertia ratio {} |",
                    iters(&n.iters),
                    iters(&o.iters),
                    rayon::current_num_threads(),
                    spread(&n.secs, 2),
                    spread(&o.secs, 2),
                    sk.as_ref().map_or("?", |s| s.0.ready["sklearn"].as_str().unwrap_or("?")),
                    format_args!("{:.6}", median(&in_ratios)),
                ));
                notes.push(format!(
                    "{name} {algo}: scikit-learn's own inertia_ (float32 sum) {:.6e}",
                    median(&sk_own_inertia[p])
                ));
            }
        }
        // Best against best: each side's fastest algorithm on this volume (lowest median
        // time), per-round times of those two.
        let have_sk = runs.iter().all(|r| r[1].secs.iter().any(|s| s.is_finite()));
        if have_sk {
            let fastest = |side: usize| -> usize {
                let m = |p: usize| median(&runs[p][side].secs);
                if m(1) < m(0) {
                    1
                } else {
                    0
                }
            };
            let (bn, bo) = (fastest(0), fastest(1));
            let (n, o) = (&runs[bn][0], &runs[bo][1]);
            let n_name = ["plain Lloyd", "Hamerly"][bn];
            let o_name = pairs[bo].2;
            let label = format!("best against best (neuvolex {n_name} vs {o_name})");
            let ratio = ratio_spread(&o.secs, &n.secs);
            let in_ratio = median(&ratios(&n.inertia, &o.inertia));
            table.push(format!(
                "| {name} | {what} | {rows} x {dim} | {} / {sk_threads} | {label} | {} / {} | {} | {} | {ratio} | {:.6e} / {:.6e} ({in_ratio:.6}) |",
                rayon::current_num_threads(),
                iters(&n.iters),
                iters(&o.iters),
                spread(&n.secs, 2),
                spread(&o.secs, 2),
                median(&n.inertia),
                median(&o.inertia),
            ));
            summaries.push(format!(
                "| k-means {label}, {name} | k = {k}, {rows} x {dim} float32 rows ({what}), each side's fastest of its two algorithms by median time, the same k-means++ start, tol 0 and {max_iter} iterations on both ({} / {}); timed: fit alone; {} threads each; {rounds} rounds | {} s | {} s (scikit-learn {}) | {ratio} | inertia ratio {in_ratio:.6} |",
                iters(&n.iters),
                iters(&o.iters),
                rayon::current_num_threads(),
                spread(&n.secs, 2),
                spread(&o.secs, 2),
                sk.as_ref().map_or("?", |s| s.0.ready["sklearn"].as_str().unwrap_or("?")),
            ));
            // neuvolex's default (bounds: Auto, which measures both ways on its first passes)
            // against scikit-learn's fastest.
            let label = format!("default (auto) against scikit-learn's best ({o_name})");
            let ratio = ratio_spread(&o.secs, &auto.secs);
            let in_ratio = median(&ratios(&auto.inertia, &o.inertia));
            table.push(format!(
                "| {name} | {what} | {rows} x {dim} | {} / {sk_threads} | {label} | {} / {} | {} | {} | {ratio} | {:.6e} / {:.6e} ({in_ratio:.6}) |",
                rayon::current_num_threads(),
                iters(&auto.iters),
                iters(&o.iters),
                spread(&auto.secs, 2),
                spread(&o.secs, 2),
                median(&auto.inertia),
                median(&o.inertia),
            ));
            summaries.push(format!(
                "| k-means {label}, {name} | k = {k}, {rows} x {dim} float32 rows ({what}), neuvolex's default configuration (bounds: Auto) against scikit-learn's fastest of its two algorithms by median time, the same k-means++ start, tol 0 and {max_iter} iterations on both ({} / {}); timed: fit alone; {} threads each; {rounds} rounds | {} s | {} s (scikit-learn {}) | {ratio} | inertia ratio {in_ratio:.6} |",
                iters(&auto.iters),
                iters(&o.iters),
                rayon::current_num_threads(),
                spread(&auto.secs, 2),
                spread(&o.secs, 2),
                sk.as_ref().map_or("?", |s| s.0.ready["sklearn"].as_str().unwrap_or("?")),
            ));
        }
        let km = fitted.expect("a fit");
        // Mini-batch from the same start, one run.
        let t = Instant::now();
        let mb = KMeans::fit_from(
            chunks.len(),
            dim,
            load,
            &KMeansConfig {
                algorithm: Algorithm::MiniBatch { epochs: 3 },
                ..base
            },
            &init,
        )
        .expect("mini-batch");
        let t_mb = t.elapsed().as_secs_f64();
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
        views_table.push(format!(
            "| {name} | {t_mb:.2} | {:.4e} ({:.4} of Lloyd's) | {t_views:.2} ({} views) |",
            mb.inertia,
            mb.inertia / km.inertia,
            sel.views.len()
        ));
    }
    println!();
    println!("| volume | features | rows x dim | threads (neuvolex / scikit-learn) | pair (neuvolex vs scikit-learn) | iterations (n / sk) | neuvolex s, median [range] | scikit-learn s, median [range] | scikit-learn / neuvolex time, median [range] | inertia n / sk (ratio) |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in &table {
        println!("{r}");
    }
    for n in &notes {
        println!("- {n}");
    }
    println!();
    println!("| volume | mini-batch (3 epochs, same start) s | mini-batch inertia | normals + 1800 views + select s |");
    println!("|---|---|---|---|");
    for r in &views_table {
        println!("{r}");
    }
    println!();
    println!("{} at end", load_average());
    for r in &summaries {
        println!("summary: {r}");
    }
}
