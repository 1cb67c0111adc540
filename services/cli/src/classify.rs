//! `neuvolex classify`, and the forest options and progress bars `neuvolex eval` shares.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_bricks::meta::MemVolume;
use neuvolex_bricks::store::BrickStore;
use neuvolex_bricks::synth::ClassInfo;
use neuvolex_bricks::DType;
use neuvolex_classify::shard::create_proba_array;
use neuvolex_classify::{
    classify_volume, fit, load_scribbles, training_set, BrickFeatures, ClassTable, ClassWeight,
    Classified, ClassifyConfig, FeatureSet,
};
use neuvolex_features::InrModel;
use serde::Serialize;
use std::path::PathBuf;
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
    pub(crate) fn config(&self) -> Result<ClassifyConfig> {
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
