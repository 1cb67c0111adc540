//! `neuvolex classify` and `neuvolex eval`.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_bricks::meta::MemVolume;
use neuvolex_bricks::store::BrickStore;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::DType;
use neuvolex_classify::shard::create_proba_array;
use neuvolex_classify::{
    classify_volume, f1_scores, fit, load_scribbles, simulate, training_set, BrickFeatures,
    ClassTable, ClassWeight, Classified, ClassifyConfig, FeatureSet, Level, Quantise, SimConfig,
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

/// The label volume as a u8 (or u16) volume on the store's grid.
fn label_volume(store: &BrickStore, c: &Classified) -> MemVolume {
    let max = c.labels.iter().copied().max().unwrap_or(0);
    let v: Vec<f64> = c.labels.iter().map(|&l| l as f64).collect();
    let dtype = if max <= 255 { DType::U8 } else { DType::U16 };
    let mut m = MemVolume::from_f64(c.dims, dtype, &v);
    let meta = store.meta();
    m.meta.spacing = meta.spacing;
    m.meta.affine = meta.affine;
    m.name = PathBuf::from("<classified>");
    m
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
}

/// What `classify` did.
#[derive(Serialize)]
struct Report {
    features: String,
    channels: usize,
    labels: Vec<u32>,
    scribbled: Vec<(u32, u64)>,
    training_bricks: usize,
    trees: usize,
    nodes: usize,
    seconds_training_features: f64,
    seconds_fit: f64,
    bricks_predicted: usize,
    bricks_skipped: usize,
    voxels_predicted: u64,
    seconds_classify: f64,
    voxels_per_second: f64,
    counts: Vec<(u16, u64)>,
}

/// `neuvolex classify`.
pub fn run_classify(a: &ClassifyArgs, quiet: bool) -> Result<()> {
    let cfg = a.forest.config()?;
    if let Some(o) = &a.out {
        if o.exists() && !a.force {
            bail!("{}: exists (use --force to replace it)", o.display());
        }
    }
    let set: FeatureSet = a.features.parse().map_err(anyhow::Error::msg)?;
    let mut store = BrickStore::open(&a.store)?;
    let scr = load_scribbles(&a.scribbles, &store.meta())
        .with_context(|| format!("{}: cannot use these scribbles", a.scribbles.display()))?;
    let table = match &a.classes {
        Some(p) => {
            let t = ClassTable::load(p)?;
            if t.background != cfg.background {
                bail!(
                    "{}: background {} differs from --background {}",
                    p.display(),
                    t.background,
                    cfg.background
                );
            }
            let labels: Vec<u32> = scr.counts().keys().copied().collect();
            t.check(&labels)
                .with_context(|| format!("{}", a.scribbles.display()))?;
            Some(t)
        }
        None => None,
    };
    let model = if set.needs_model() {
        load_model(&store)?
    } else {
        None
    };
    let fx = BrickFeatures::new(&store, set.clone(), model, a.stored_features)?;
    let t = Instant::now();
    let ts = training_set(&fx, &scr, cfg.background)
        .with_context(|| format!("{}", a.scribbles.display()))?;
    let t_feat = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let forest = fit(&ts, &cfg.forest)?;
    let t_fit = t.elapsed().as_secs_f64();
    tracing::info!(
        rows = ts.y.len(),
        d = ts.d,
        classes = ts.labels.len(),
        t_feat,
        t_fit,
        "forest trained"
    );
    let total = store.info().grid().iter().product::<usize>() as u64;
    let pb = bar(quiet, total, "classify");
    let mut proba = create_proba_array(&fx, "classes_proba", &ts.labels, cfg.background)?;
    let c = classify_volume(&fx, &forest, &ts, &cfg, Some(&mut proba), &|d| {
        pb.set_position(d)
    })?;
    pb.finish_and_clear();
    drop(fx);
    let mut counts = std::collections::BTreeMap::<u16, u64>::new();
    c.labels
        .iter()
        .for_each(|&l| *counts.entry(l).or_default() += 1);
    let classes: Vec<ClassInfo> = match &table {
        Some(t) => t.classes.clone(),
        None => ts
            .labels
            .iter()
            .filter(|&&l| l != cfg.background)
            .map(|&l| ClassInfo {
                id: l,
                name: format!("class_{l}"),
                color: neuvolex_bricks::synth::palette(l),
            })
            .collect(),
    };
    let mut lv = label_volume(&store, &c);
    store.add_labels("classified", &mut lv, &classes, &mut |_| {})?;
    if let Some(o) = &a.out {
        neuvolex_bricks::nifti::write_nifti(o, &mut lv, 64)?;
    }
    let r = Report {
        features: set.to_string(),
        channels: ts.d,
        labels: ts.labels.clone(),
        scribbled: scr.counts().into_iter().collect(),
        training_bricks: ts.bricks,
        trees: forest.trees(),
        nodes: forest.nodes(),
        seconds_training_features: t_feat,
        seconds_fit: t_fit,
        bricks_predicted: c.bricks_predicted,
        bricks_skipped: c.bricks_skipped,
        voxels_predicted: c.voxels_predicted,
        seconds_classify: c.seconds,
        voxels_per_second: c.voxels_predicted as f64 / c.seconds.max(1e-9),
        counts: counts.into_iter().collect(),
    };
    println!(
        "classify: {} features ({} channels), {} scribbled voxels in {} classes; forest {} trees \
         in {:.2} s; {} bricks predicted, {} empty skipped, {:.2} s ({:.0} k voxels/s)",
        r.features,
        r.channels,
        ts.y.len(),
        r.labels.len(),
        r.trees,
        t_fit,
        r.bricks_predicted,
        r.bricks_skipped,
        c.seconds,
        r.voxels_per_second / 1e3
    );
    for (l, n) in &r.counts {
        let name = classes
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
    if let Some(p) = &a.report {
        std::fs::write(p, serde_json::to_string_pretty(&r)?)
            .with_context(|| format!("{}: cannot write the report", p.display()))?;
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
