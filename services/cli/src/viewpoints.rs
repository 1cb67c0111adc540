//! `neuvolex viewpoints`: k-means on per-voxel features, view entropy over a Fibonacci sphere,
//! greedy selection, and a rendering of each selected view.

use anyhow::{bail, Context, Result};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::features::{BrickFeatures, FeatureSet};
use neuvolex_classify::pipeline::{FeatureSpec, OpenedFeatures};
use neuvolex_render::{BrickSource, Camera, Image, RenderParams, Renderer, StoreSource, TfFile};
use neuvolex_viewpoints::kmeans::Algorithm;
use neuvolex_viewpoints::scores::{entropy_map, SelectConfig};
use neuvolex_viewpoints::{
    direction_to_view, fibonacci_sphere, recommend, KMeansConfig, RecommendConfig,
};
use std::borrow::Cow;
use std::path::PathBuf;
use std::sync::Arc;

/// Arguments of `neuvolex viewpoints`.
#[derive(clap::Args)]
pub struct ViewpointArgs {
    /// Brick store (.zarr).
    store: PathBuf,
    /// Features to cluster: paper (the INR's 64-D last hidden layer; needs `neuvolex train`),
    /// inr, local, filters, intensity, or a `+` list.
    #[arg(long, default_value = "paper")]
    features: String,
    /// Read INR features stored by `neuvolex features` instead of recomputing them.
    #[arg(long)]
    stored_features: bool,
    /// Clusters.
    #[arg(long, default_value_t = 50)]
    k: usize,
    /// Candidate views on the sphere.
    #[arg(long, default_value_t = 1800)]
    views: usize,
    /// Seed of the k-means initialisation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// k-means update: lloyd or minibatch.
    #[arg(long, default_value = "lloyd")]
    algorithm: String,
    /// Most selected views.
    #[arg(long, default_value_t = 12)]
    max_views: usize,
    /// Coverage at which a cluster counts as seen.
    #[arg(long, default_value_t = 0.5)]
    cover: f32,
    /// Size of each view's rendering (0: none).
    #[arg(long, default_value_t = 256)]
    size: usize,
    /// Transfer function of the renderings (file or preset:NAME; default as `render`).
    #[arg(long)]
    tf: Option<String>,
    /// Memory for holding features between k-means passes (MiB); beyond it they stream.
    #[arg(long, default_value_t = 2048)]
    memory_mib: usize,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    cluster: crate::cluster::ClusterArgs,
}

/// A blue-to-yellow colour ramp (viridis control points).
fn ramp(t: f32) -> [f32; 3] {
    const C: [[f32; 3]; 5] = [
        [0.267, 0.005, 0.329],
        [0.230, 0.322, 0.546],
        [0.128, 0.567, 0.551],
        [0.370, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ];
    let x = t.clamp(0.0, 1.0) * 4.0;
    let i = (x as usize).min(3);
    let f = x - i as f32;
    [0, 1, 2].map(|k| C[i][k] + (C[i + 1][k] - C[i][k]) * f)
}

/// Runs `neuvolex viewpoints`.
pub fn run_viewpoints(a: &ViewpointArgs, quiet: bool) -> Result<()> {
    if a.views == 0 || a.views > 1_000_000 {
        bail!("--views {} must be 1..=1000000", a.views);
    }
    if a.k == 0 || a.k > u16::MAX as usize {
        bail!("--k {} must be 1..=65535", a.k);
    }
    if a.size > neuvolex_render::march::MAX_SIZE {
        bail!(
            "--size {} exceeds {}",
            a.size,
            neuvolex_render::march::MAX_SIZE
        );
    }
    let algorithm = match a.algorithm.as_str() {
        "lloyd" => Algorithm::Lloyd,
        "minibatch" => Algorithm::MiniBatch { epochs: 3 },
        o => bail!("--algorithm '{o}' must be lloyd or minibatch"),
    };
    let set: FeatureSet = a.features.parse().map_err(anyhow::Error::msg)?;
    let store = Arc::new(BrickStore::open(&a.store)?);
    let cfg = RecommendConfig {
        kmeans: KMeansConfig {
            k: a.k,
            seed: a.seed,
            algorithm,
            ..Default::default()
        },
        views: a.views,
        select: SelectConfig {
            cover: a.cover,
            max_views: a.max_views,
            ..Default::default()
        },
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}", a.out.display()))?;
    let views = fibonacci_sphere(a.views);
    let mut refined = |n: usize, agg: &neuvolex_viewpoints::scores::Aggregator| {
        if n.is_multiple_of(16) {
            if let Ok(s) = agg.snapshot(&views) {
                let best = s.entropy.iter().cloned().fold(0.0f32, f32::max);
                tracing::debug!(bricks = n, best_entropy = best, "entropy map refined");
            }
        }
    };
    let rec = if algorithm == Algorithm::Lloyd {
        // Every per-brick step as tasks: in this process, or on the cluster's workers.
        neuvolex_viewpoints::distributed::set_feature_cache_mib(a.memory_mib);
        let model = if set.needs_model() {
            crate::classify::load_model(&store)?
        } else {
            None
        };
        let spec = FeatureSpec::new(&a.store, &set, a.stored_features, model.as_deref());
        let src = OpenedFeatures {
            store: store.clone(),
            model,
            set: set.clone(),
            spec,
            model_bytes: None,
        };
        let exec = a.cluster.executor()?;
        let mut bar = crate::cluster::StageBar::new(quiet);
        let (rec, run) = neuvolex_viewpoints::distributed::recommend_on(
            &exec,
            src,
            &cfg,
            a.cluster.bricks_per_task,
            &mut |e| bar.on(e),
            &mut refined,
        )?;
        bar.finish();
        tracing::info!(executor = %run.executor, tasks = run.tasks, work_seconds = run.work_seconds, "viewpoint stages done");
        rec
    } else {
        anyhow::ensure!(
            a.cluster.cluster.is_none(),
            "--algorithm minibatch runs in one process (its updates are sequential); use lloyd with --cluster"
        );
        let model = if set.needs_model() {
            crate::classify::load_model(&store)?
        } else {
            None
        };
        let fx = BrickFeatures::new(&store, set.clone(), model, a.stored_features)?;
        let bricks = store.occupied_bricks(None);
        let dim = fx.channels();
        // Every k-means pass reads each brick's features; hold them in memory where they fit
        // the budget (otherwise they stream from the store or the model on every pass).
        let bytes: usize = bricks.iter().map(|b| b.voxels() * dim * 4).sum();
        let cached: Option<Vec<Vec<f32>>> = if bytes <= a.memory_mib << 20 {
            Some(
                bricks
                    .iter()
                    .map(|b| fx.brick(b))
                    .collect::<Result<_, _>>()?,
            )
        } else {
            tracing::info!(
                mib = bytes >> 20,
                "features exceed --memory-mib: streaming them per pass"
            );
            None
        };
        let pb = crate::classify::bar(quiet, bricks.len() as u64, "normals");
        let err = |e: String| neuvolex_viewpoints::ViewpointError::Input(e);
        // k-means over the occupied bricks (empty ones are excluded), then cluster normals
        // merged brick by brick: the entropy map refines as bricks arrive.
        let rec = recommend(
            bricks.len(),
            dim,
            |i| match &cached {
                Some(c) => Ok(Cow::Borrowed(&c[i][..])),
                None => fx
                    .brick(&bricks[i])
                    .map(Cow::Owned)
                    .map_err(|e| err(e.to_string())),
            },
            |i| {
                Ok(store
                    .derived(&bricks[i])
                    .map_err(|e| err(e.to_string()))?
                    .gradient)
            },
            store.info().spacing,
            &cfg,
            &mut |n, agg| {
                pb.set_position(n as u64);
                refined(n, agg);
            },
        )?;
        pb.finish_and_clear();
        rec
    };
    let (summ, scores, sel, km) = (&rec.summary, &rec.scores, &rec.selection, &rec.kmeans);
    let (t_kmeans, t_views) = (rec.kmeans_seconds, rec.scoring_seconds);
    let used = km.counts.iter().filter(|&&c| c > 0).count();
    // 3. Outputs: entropy map, JSON, renderings.
    let (w, h) = (360, 180);
    let map = entropy_map(summ, w, h);
    let hi = map.iter().cloned().fold(0.0f32, f32::max).max(1e-6);
    let img = Image {
        width: w,
        height: h,
        rgb: map.iter().map(|&v| ramp(v / hi)).collect(),
        alpha: vec![1.0; w * h],
    };
    img.save_png(&a.out.join("entropy_map.png"))?;
    let selected: Vec<serde_json::Value> = sel
        .views
        .iter()
        .zip(&sel.gains)
        .map(|(&i, &g)| {
            let d = scores.views[i];
            let (az, el) = direction_to_view(d);
            serde_json::json!({"index": i, "azimuth": az, "elevation": el, "direction": d,
                "entropy": scores.entropy[i], "gain": g})
        })
        .collect();
    let clusters: Vec<serde_json::Value> = summ
        .iter()
        .zip(&sel.coverage)
        .map(|(s, c)| {
            serde_json::json!({"voxels": s.count, "normal": s.normal,
            "coherence": s.coherence, "weight": s.weight, "coverage": c})
        })
        .collect();
    let report = serde_json::json!({
        "store": a.store, "features": set.to_string(), "k": a.k, "clusters_used": used,
        "kmeans": {"inertia": km.inertia, "iterations": km.iterations, "seconds": t_kmeans},
        "candidate_views": a.views, "scoring_seconds": t_views,
        "selected": selected, "uncovered_clusters": sel.uncovered, "clusters": clusters,
    });
    let jp = a.out.join("views.json");
    std::fs::write(&jp, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("{}", jp.display()))?;
    if a.size > 0 {
        let src = StoreSource::new(store.clone());
        let tf = match &a.tf {
            Some(t) => TfFile::from_arg(t)?,
            None => TfFile::preset(TfFile::default_preset(store.info().stats.min))?,
        };
        let luts = tf.compile(&src.normaliser(), &[]);
        let mut r = Renderer::new(src, 1 << 30);
        for (n, &i) in sel.views.iter().enumerate() {
            let (az, el) = direction_to_view(scores.views[i]);
            let p = RenderParams {
                width: a.size,
                height: a.size,
                camera: Camera {
                    azimuth: az,
                    elevation: el.clamp(-90.0, 90.0),
                    ..Camera::default()
                },
                ..RenderParams::default()
            };
            r.render(&p, &luts)?
                .save_png(&a.out.join(format!("view_{n:02}.png")))?;
        }
    }
    println!(
        "{}: {} views selected of {} ({} of {} clusters used, {} uncovered); k-means {:.2} s, scoring {:.2} s",
        a.out.display(),
        sel.views.len(),
        a.views,
        used,
        a.k,
        sel.uncovered.len(),
        t_kmeans,
        t_views
    );
    for v in &selected {
        println!(
            "  azimuth {:7.1}  elevation {:6.1}  entropy {:.3}",
            v["azimuth"].as_f64().unwrap_or(0.0),
            v["elevation"].as_f64().unwrap_or(0.0),
            v["entropy"].as_f64().unwrap_or(0.0)
        );
    }
    Ok(())
}
