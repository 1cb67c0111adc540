//! `neuvolex classify` and `neuvolex eval`.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_bricks::meta::MemVolume;
use neuvolex_bricks::store::BrickStore;
use neuvolex_classify::pipeline::ClassifyRequest;
use neuvolex_classify::{
    classify_volume, f1_scores, fit, simulate, training_set, BrickFeatures, ClassWeight,
    ClassifyConfig, FeatureSet, Level, Quantise, SimConfig,
};
use neuvolex_features::InrModel;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// Forest and output options shared by `classify` and `eval`.
#[derive(clap::Args, Clone, Debug)]
pub struct ForestArgs {
    /// Trees in the forest.
    #[arg(long, default_value_t = 1000)]
    pub trees: usize,
    /// A node with fewer samples becomes a leaf.
    #[arg(long, default_value_t = 8)]
    pub min_split: usize,
    /// Class weighting: balanced (each scribbled class weighs the same) or none (the paper).
    #[arg(long, default_value = "balanced")]
    pub class_weight: String,
    /// Minimum probability for a voxel to take its most probable class.
    #[arg(long, default_value_t = 0.5)]
    pub tau: f32,
    /// The scribble label meaning background/other.
    #[arg(long, default_value_t = 255)]
    pub background: u32,
    /// Predict empty bricks too (by default they are background when background is scribbled).
    #[arg(long)]
    pub all_bricks: bool,
    /// Forest seed.
    #[arg(long, default_value_t = 0)]
    pub forest_seed: u64,
}

impl ForestArgs {
    fn config(&self) -> Result<ClassifyConfig> {
        let mut c = ClassifyConfig::default();
        if self.trees == 0 || self.trees > 100_000 {
            bail!("--trees {} must be 1..=100000", self.trees);
        }
        if self.min_split < 2 {
            bail!("--min-split {} must be at least 2", self.min_split);
        }
        if !(0.0..=1.0).contains(&self.tau) {
            bail!("--tau {} must be in [0, 1]", self.tau);
        }
        if self.background == 0 {
            bail!("--background 0: label 0 means unlabelled");
        }
        c.forest.trees = self.trees;
        c.forest.min_samples_split = self.min_split;
        c.forest.seed = self.forest_seed;
        c.forest.class_weight = match self.class_weight.as_str() {
            "balanced" => ClassWeight::Balanced,
            "none" => ClassWeight::None,
            o => bail!("--class-weight '{o}' must be balanced or none"),
        };
        c.tau = self.tau;
        c.background = self.background;
        c.skip_empty = !self.all_bricks;
        Ok(c)
    }
}

/// A progress bar with `template` (hidden when quiet).
pub(crate) fn styled_bar(quiet: bool, len: u64, template: &str) -> ProgressBar {
    let b = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(len)
    };
    b.set_style(
        ProgressStyle::with_template(template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    b
}

/// A progress bar over bricks.
pub(crate) fn bar(quiet: bool, len: u64, what: &str) -> ProgressBar {
    styled_bar(
        quiet,
        len,
        &format!("{what:>10} [{{bar:40}}] {{pos}}/{{len}} bricks {{elapsed}} eta {{eta}}"),
    )
}

pub(crate) fn load_model(store: &BrickStore) -> Result<Option<Arc<InrModel>>> {
    let mp = neuvolex_features::train::model_path(store);
    if !mp.exists() {
        return Ok(None);
    }
    Ok(Some(Arc::new(
        neuvolex_features::checkpoint::load(&mp)?.model,
    )))
}

/// Arguments of `neuvolex classify`.
#[derive(clap::Args, Clone, Debug)]
pub struct ClassifyArgs {
    /// The brick store.
    pub store: PathBuf,
    /// Scribbles: a sparse label volume (NIfTI, NRRD, Zarr; 0 = unlabelled) or strokes (.json).
    #[arg(long)]
    pub scribbles: PathBuf,
    /// Feature set: inr (default: learned + local), paper (the last hidden layer), intensity,
    /// local, filters, or a '+' list of intensity, local, filters, xyz, hidden, pos, mod, concat.
    #[arg(long, default_value = "inr")]
    pub features: String,
    /// Class table JSON ({"classes": [{"id", "name", "color"}], "background": 255}).
    #[arg(long)]
    pub classes: Option<PathBuf>,
    /// Write the label volume as NIfTI (3D Slicer, ITK-SNAP, napari).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace an existing --out file.
    #[arg(long)]
    pub force: bool,
    /// Use stored INR feature arrays (from `neuvolex features`) instead of recomputing them.
    #[arg(long)]
    pub stored_features: bool,
    /// Write a JSON report here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    #[command(flatten)]
    pub forest: ForestArgs,
    #[command(flatten)]
    pub cluster: crate::cluster::ClusterArgs,
}

/// `neuvolex classify`: parses, chooses the executor, shows progress, prints.
pub fn run_classify(a: &ClassifyArgs, quiet: bool) -> Result<()> {
    let req = ClassifyRequest {
        store: a.store.clone(),
        scribbles: a.scribbles.clone(),
        features: a.features.parse().map_err(anyhow::Error::msg)?,
        classes: a.classes.clone(),
        out: a.out.clone(),
        force: a.force,
        stored_features: a.stored_features,
        config: a.forest.config()?,
        bricks_per_task: a.cluster.bricks_per_task,
    };
    let exec = a.cluster.executor()?;
    let mut bar = crate::cluster::StageBar::new(quiet);
    let o = neuvolex_classify::pipeline::classify(&req, &exec, &mut |e| bar.on(e))?;
    bar.finish();
    let r = &o.report;
    if let Some(p) = &a.report {
        std::fs::write(p, serde_json::to_string_pretty(r)?)
            .with_context(|| format!("{}: cannot write the report", p.display()))?;
    }
    if !o.dead.is_empty() {
        for d in &o.dead {
            eprintln!(
                "  dead: task {} bricks {:?} after {} deliveries: {}",
                d.task, d.bricks, d.deliveries, d.error
            );
        }
        bail!(
            "classify: {} task(s) failed on every delivery (bricks listed above); the other {} \
             completed and stay marked done, so a re-run after fixing the cause finishes only \
             the rest",
            o.dead.len(),
            r.run.completed
        );
    }
    println!(
        "classify: {} features ({} channels), {} scribbled voxels in {} classes; forest {} trees \
         in {:.2} s; {} bricks predicted, {} empty skipped, {} resumed, {:.2} s ({:.0} k voxels/s) on {}",
        r.features,
        r.channels,
        o.scribbled_voxels,
        r.labels.len(),
        r.trees,
        r.seconds_fit,
        r.bricks_predicted,
        r.bricks_skipped,
        r.bricks_resumed,
        r.seconds_classify,
        r.voxels_per_second / 1e3,
        r.run.executor
    );
    if r.run.per_worker.len() > 1 || a.cluster.cluster.is_some() {
        let w: Vec<String> = r
            .run
            .per_worker
            .iter()
            .map(|(w, n)| format!("{w} {n}"))
            .collect();
        println!("  tasks per worker: {}", w.join(", "));
    }
    for (l, n) in &r.counts {
        let name = o
            .classes
            .iter()
            .find(|c| c.id == *l as u32)
            .map_or(if *l == 0 { "background" } else { "?" }, |c| &c.name);
        println!("  label {l:>3} {name:<16} {n:>12} voxels");
    }
    println!(
        "  probabilities: {}/neuvolex/vectors/classes_proba (u8); labels: {}/labels/classified",
        a.store.display(),
        a.store.display()
    );
    if let Some(o) = &a.out {
        println!("  label volume: {}", o.display());
    }
    Ok(())
}

/// Arguments of `neuvolex eval`.
#[derive(clap::Args, Clone, Debug)]
pub struct EvalArgs {
    /// Datasets: names under --data (abdomen_ct, brain_mri) or NAME=IMAGE,LABELS.
    #[arg(long, value_delimiter = ';', default_value = "abdomen_ct;brain_mri")]
    pub datasets: Vec<String>,
    /// Where the named datasets live.
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Scribble levels.
    #[arg(long, value_delimiter = ',', default_value = "S1,S2,S3,S4")]
    pub levels: Vec<String>,
    /// Scribble seeds per level (0..N).
    #[arg(long, default_value_t = 3)]
    pub seeds: u64,
    /// Feature sets (see `classify --features`).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "intensity,local,filters,paper,inr"
    )]
    pub methods: Vec<String>,
    /// Forest sizes to score (sub-forests of the largest).
    #[arg(long, value_delimiter = ',')]
    pub tree_counts: Vec<usize>,
    /// INR training budgets in epochs.
    #[arg(long, value_delimiter = ',', default_value = "3")]
    pub epochs: Vec<f64>,
    /// INR ablations: base, structural, film, full.
    #[arg(long, value_delimiter = ',', default_value = "full")]
    pub ablations: Vec<String>,
    /// Feature precision: f32, f16, u8.
    #[arg(long, value_delimiter = ',', default_value = "f32")]
    pub quantise: Vec<String>,
    /// Working directory for stores and models (reused between runs).
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// JSON output.
    #[arg(long)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub forest: ForestArgs,
}

/// One scored run.
#[derive(Serialize, Clone)]
struct Row {
    dataset: String,
    method: String,
    level: String,
    seed: u64,
    ablation: String,
    epochs: f64,
    trees: usize,
    quantise: String,
    scribbled_fraction: f64,
    f1: Vec<neuvolex_classify::F1>,
    mean_f1: f64,
    seconds_features: f64,
    seconds_fit: f64,
    seconds_classify: f64,
    voxels_predicted: u64,
}

#[derive(Serialize)]
struct ModelRow {
    dataset: String,
    ablation: String,
    epochs: f64,
    psnr: f64,
    seconds: f64,
    dead_units: usize,
}

fn dataset_paths(a: &EvalArgs, spec: &str) -> Result<(String, PathBuf, PathBuf)> {
    if let Some((name, rest)) = spec.split_once('=') {
        let (img, lab) = rest
            .split_once(',')
            .with_context(|| format!("--datasets '{spec}': expected NAME=IMAGE,LABELS"))?;
        return Ok((name.into(), img.into(), lab.into()));
    }
    let files = match spec {
        "abdomen_ct" => ("abdomen_ct/ct.nii.gz", "abdomen_ct/labels.nii.gz"),
        "brain_mri" => ("brain_mri/t1_norm.nii.gz", "brain_mri/labels.nii.gz"),
        o => {
            bail!("--datasets: unknown dataset '{o}' (abdomen_ct, brain_mri, or NAME=IMAGE,LABELS)")
        }
    };
    let (i, l) = (a.data.join(files.0), a.data.join(files.1));
    if !i.exists() || !l.exists() {
        bail!(
            "{}: dataset '{spec}' not found under {} (see ../shared/data/README.md)",
            i.display(),
            a.data.display()
        );
    }
    Ok((spec.into(), i, l))
}

/// Trains (or loads) the INR of `store` for an ablation and budget.
fn eval_model(
    store: &BrickStore,
    dir: &Path,
    ablation: &str,
    epochs: f64,
    quiet: bool,
) -> Result<(Arc<InrModel>, f64, f64)> {
    use neuvolex_features::{checkpoint, train, InrConfig, Preset, TrainConfig};
    let path = dir.join(format!("inr-{ablation}-{epochs}ep.nvx"));
    let meta = dir.join(format!("inr-{ablation}-{epochs}ep.json"));
    if path.exists() && meta.exists() {
        let m = checkpoint::load(&path)?.model;
        let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&meta)?)?;
        return Ok((
            Arc::new(m),
            v["psnr"].as_f64().unwrap_or(f64::NAN),
            v["seconds"].as_f64().unwrap_or(f64::NAN),
        ));
    }
    let inr = InrConfig {
        ablation: ablation.parse().map_err(anyhow::Error::msg)?,
        ..InrConfig::default()
    };
    let mut cfg = TrainConfig::preset(Preset::Fast);
    cfg.budget = neuvolex_features::Budget {
        epochs: Some(epochs),
        samples: None,
        seconds: None,
    };
    let cancel = std::sync::atomic::AtomicBool::new(false);
    let pb = styled_bar(
        quiet,
        0,
        "     train [{bar:40}] {pos}/{len} samples {msg} eta {eta}",
    );
    let t = Instant::now();
    let tr = train(store, &inr, &cfg, None, None, &cancel, &mut |e| match e {
        neuvolex_features::TrainEvent::Started { budget_samples, .. } => {
            pb.set_length(budget_samples.unwrap_or(0))
        }
        neuvolex_features::TrainEvent::Step { samples, psnr, .. } => {
            pb.set_position(samples);
            pb.set_message(format!("PSNR {psnr:.1} dB"));
        }
        _ => {}
    })?;
    pb.finish_and_clear();
    let secs = t.elapsed().as_secs_f64();
    std::fs::create_dir_all(dir)?;
    checkpoint::save(&path, &tr.model, None)?;
    std::fs::write(
        &meta,
        serde_json::json!({"psnr": tr.psnr, "seconds": secs}).to_string(),
    )?;
    Ok((Arc::new(tr.model), tr.psnr as f64, secs))
}

/// Units of the last hidden layer never active on a sample of bricks.
fn dead_units(store: &BrickStore, model: &InrModel) -> Result<usize> {
    let h = model.cfg.hidden;
    let mut alive = vec![false; h];
    for b in store.occupied_bricks(None).iter().step_by(3).take(8) {
        let f = neuvolex_features::extract::extract_brick(
            model,
            store,
            b,
            neuvolex_features::FeatureKind::Hidden,
        )?;
        for r in f.chunks(h) {
            for (k, &v) in r.iter().enumerate() {
                alive[k] |= v > 0.0;
            }
        }
    }
    Ok(alive.iter().filter(|a| !**a).count())
}

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len().max(1) as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

/// `neuvolex eval`.
pub fn run_eval(a: &EvalArgs, quiet: bool) -> Result<()> {
    let base_cfg = a.forest.config()?;
    let levels: Vec<Level> = a
        .levels
        .iter()
        .map(|l| l.parse().map_err(anyhow::Error::msg))
        .collect::<Result<_>>()?;
    let methods: Vec<(String, FeatureSet)> = a
        .methods
        .iter()
        .map(|m| Ok((m.clone(), m.parse().map_err(anyhow::Error::msg)?)))
        .collect::<Result<_>>()?;
    let mut tree_counts = a.tree_counts.clone();
    if tree_counts.is_empty() {
        tree_counts.push(base_cfg.forest.trees);
    }
    tree_counts.sort_unstable();
    tree_counts.dedup();
    if tree_counts[0] == 0 {
        bail!("--tree-counts: 0 trees");
    }
    let max_trees = *tree_counts.last().unwrap_or(&1);
    for e in &a.epochs {
        if !(*e > 0.0 && e.is_finite()) {
            bail!("--epochs {e} must be positive");
        }
    }
    for q in &a.quantise {
        if !matches!(q.as_str(), "f32" | "f16" | "u8") {
            bail!("--quantise '{q}' must be f32, f16 or u8");
        }
    }
    if a.seeds == 0 {
        bail!("--seeds 0: need at least one");
    }
    let work = a
        .work
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("neuvolex-eval"));
    std::fs::create_dir_all(&work)
        .with_context(|| format!("{}: cannot create the work directory", work.display()))?;
    let mut rows: Vec<Row> = Vec::new();
    let mut models_out = Vec::new();
    for spec in &a.datasets {
        let (name, img, lab) = dataset_paths(a, spec)?;
        let store_path = work.join(format!("{name}.zarr"));
        if !store_path.exists() {
            let opts = neuvolex_bricks::store::IngestOptions::default();
            let mut src = neuvolex_bricks::open::open_volume(&img, None)?;
            neuvolex_bricks::store::ingest(&mut *src, &store_path, &opts, &mut |_| {})
                .with_context(|| format!("{}: cannot ingest", img.display()))?;
        }
        let store = BrickStore::open(&store_path).with_context(|| {
            format!(
                "{}: cannot open the cached store (delete it to re-ingest)",
                store_path.display()
            )
        })?;
        let mut lsrc = neuvolex_bricks::open::open_volume(&lab, None)?;
        store.meta().check_same_grid(lsrc.meta(), &lab)?;
        let truth: Vec<u32> = MemVolume::read_all(&mut *lsrc)?
            .to_f32()
            .iter()
            .map(|&v| v as u32)
            .collect();
        let mut classes: Vec<u32> = truth.iter().copied().filter(|&c| c > 0).collect();
        classes.sort_unstable();
        classes.dedup();
        tracing::info!(dataset = %name, ?classes, "evaluating");
        // Models per (ablation, epochs), only when a method needs one.
        let mut models: Vec<(String, f64, Arc<InrModel>)> = Vec::new();
        if methods.iter().any(|(_, s)| s.needs_model()) {
            for ab in &a.ablations {
                for &ep in &a.epochs {
                    let (m, psnr, secs) =
                        eval_model(&store, &work.join(format!("{name}-models")), ab, ep, quiet)?;
                    let dead = dead_units(&store, &m)?;
                    eprintln!(
                        "{name}: INR {ab} {ep} epochs: PSNR {psnr:.2} dB, {secs:.1} s, {dead}/{} dead hidden units",
                        m.cfg.hidden
                    );
                    models_out.push(ModelRow {
                        dataset: name.clone(),
                        ablation: ab.clone(),
                        epochs: ep,
                        psnr,
                        seconds: secs,
                        dead_units: dead,
                    });
                    models.push((ab.clone(), ep, m));
                }
            }
        }
        for &level in &levels {
            for seed in 0..a.seeds {
                let mut lsrc = neuvolex_bricks::open::open_volume(&lab, None)?;
                let (_, scr) = simulate(
                    &mut *lsrc,
                    &SimConfig {
                        level,
                        seed,
                        background: base_cfg.background,
                        ..SimConfig::default()
                    },
                )?;
                for (mname, set) in &methods {
                    let variants: Vec<(String, f64, Option<Arc<InrModel>>)> = if set.needs_model() {
                        models
                            .iter()
                            .map(|(ab, ep, m)| (ab.clone(), *ep, Some(m.clone())))
                            .collect()
                    } else {
                        vec![("-".into(), 0.0, None)]
                    };
                    for (ab, ep, model) in variants {
                        for q in &a.quantise {
                            let mut fx =
                                BrickFeatures::new(&store, set.clone(), model.clone(), false)?;
                            let t = Instant::now();
                            let mut ts = training_set(&fx, &scr, base_cfg.background)?;
                            let quant = match q.as_str() {
                                "f16" => Quantise::F16,
                                "u8" => Quantise::u8_from_rows(&ts.x, ts.d),
                                _ => Quantise::F32,
                            };
                            quant.apply(&mut ts.x, ts.d);
                            fx.set_quantise(quant);
                            let t_feat = t.elapsed().as_secs_f64();
                            let t = Instant::now();
                            let mut fcfg = base_cfg.forest.clone();
                            fcfg.trees = max_trees;
                            let full = fit(&ts, &fcfg)?;
                            let t_fit = t.elapsed().as_secs_f64();
                            for &k in &tree_counts {
                                let forest = full.truncated(k);
                                let pb = bar(
                                    quiet,
                                    store.info().grid().iter().product::<usize>() as u64,
                                    mname,
                                );
                                let c =
                                    classify_volume(&fx, &forest, &ts, &base_cfg, None, &|d| {
                                        pb.set_position(d)
                                    })?;
                                pb.finish_and_clear();
                                let f1 = f1_scores(&c.labels, &truth, &classes);
                                let mean_f1 =
                                    f1.iter().map(|f| f.f1).sum::<f64>() / f1.len().max(1) as f64;
                                eprintln!(
                                    "{name} {} seed {seed} {mname:<10} {ab:<10} {ep:>5} ep {k:>4} trees {q}: mean F1 {mean_f1:.3} [{}] fit {t_fit:.1} s classify {:.1} s",
                                    level_name(level),
                                    f1.iter().map(|f| format!("{}:{:.3}", f.label, f.f1)).collect::<Vec<_>>().join(" "),
                                    c.seconds
                                );
                                rows.push(Row {
                                    dataset: name.clone(),
                                    method: mname.clone(),
                                    level: level_name(level),
                                    seed,
                                    ablation: ab.clone(),
                                    epochs: ep,
                                    trees: k,
                                    quantise: q.clone(),
                                    scribbled_fraction: scr.fraction(),
                                    f1,
                                    mean_f1,
                                    seconds_features: t_feat,
                                    seconds_fit: t_fit * k as f64 / max_trees as f64,
                                    seconds_classify: c.seconds,
                                    voxels_predicted: c.voxels_predicted,
                                });
                            }
                        }
                    }
                }
            }
        }
    }
    print_tables(&rows, &levels);
    if let Some(p) = &a.json {
        std::fs::write(
            p,
            serde_json::to_string_pretty(&serde_json::json!({
                "config": {
                    "levels": a.levels, "seeds": a.seeds, "methods": a.methods,
                    "tree_counts": tree_counts, "epochs": a.epochs, "ablations": a.ablations,
                    "quantise": a.quantise, "forest": base_cfg,
                },
                "models": models_out,
                "runs": rows,
            }))?,
        )
        .with_context(|| format!("{}: cannot write", p.display()))?;
        println!("eval: {} runs written to {}", rows.len(), p.display());
    }
    Ok(())
}

fn level_name(l: Level) -> String {
    format!("S{}", l as usize + 1)
}

/// A configuration: dataset, method, ablation, epochs, trees, precision.
type ConfigKey = (String, String, String, String, usize, String);

fn key_of(r: &Row) -> ConfigKey {
    (
        r.dataset.clone(),
        r.method.clone(),
        r.ablation.clone(),
        format!("{}", r.epochs),
        r.trees,
        r.quantise.clone(),
    )
}

/// Prints mean F1 (over classes; mean ± std over seeds) per configuration and level, then the
/// per-class F1 of each configuration.
fn print_tables(rows: &[Row], levels: &[Level]) {
    let mut keys: Vec<ConfigKey> = Vec::new();
    for r in rows {
        let k = key_of(r);
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    let of = |k: &ConfigKey, l: &str| -> Vec<&Row> {
        rows.iter()
            .filter(|r| &key_of(r) == k && r.level == l)
            .collect()
    };
    let lv: Vec<String> = levels.iter().map(|&l| level_name(l)).collect();
    println!(
        "\n| dataset | features | INR | epochs | trees | precision | {} | classify s |",
        lv.join(" | ")
    );
    println!("|---|---|---|---|---|---|{}---|", "---|".repeat(lv.len()));
    for k in &keys {
        let sel = |l: &str| of(k, l);
        let cells: Vec<String> = lv
            .iter()
            .map(|l| {
                let v: Vec<f64> = sel(l).iter().map(|r| r.mean_f1).collect();
                if v.is_empty() {
                    "".into()
                } else {
                    let (m, s) = mean_std(&v);
                    format!("{m:.3} ± {s:.3}")
                }
            })
            .collect();
        let secs: Vec<f64> = lv
            .iter()
            .flat_map(|l| sel(l).into_iter().map(|r| r.seconds_classify))
            .collect();
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {:.1} |",
            k.0,
            k.1,
            k.2,
            k.3,
            k.4,
            k.5,
            cells.join(" | "),
            mean_std(&secs).0
        );
    }
    println!("\nper-class F1 (mean over seeds):");
    for k in &keys {
        let mut line = format!("  {} {} {} {}ep {}t {}:", k.0, k.1, k.2, k.3, k.4, k.5);
        for l in &lv {
            let rs = of(k, l);
            if rs.is_empty() {
                continue;
            }
            let nc = rs[0].f1.len();
            let per: Vec<String> = (0..nc)
                .map(|c| {
                    let v: Vec<f64> = rs.iter().map(|r| r.f1[c].f1).collect();
                    format!("{}={:.2}", rs[0].f1[c].label, mean_std(&v).0)
                })
                .collect();
            line.push_str(&format!(" {l}[{}]", per.join(" ")));
        }
        println!("{line}");
    }
}
