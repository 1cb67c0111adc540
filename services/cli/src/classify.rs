//! `neuvolex classify`, and the forest options and progress bars `neuvolex eval` shares.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::pipeline::ClassifyRequest;
use neuvolex_classify::{ClassWeight, ClassifyConfig};
use neuvolex_features::InrModel;
use std::path::PathBuf;
use std::sync::Arc;

/// Forest and output options shared by `classify` and `eval`.
#[derive(clap::Args, Clone, Debug)]
pub struct ForestArgs {
    /// Trees in the forest.
    #[arg(long, default_value_t = ClassifyConfig::default().forest.trees)]
    pub trees: usize,
    /// A node with fewer samples becomes a leaf.
    #[arg(long, default_value_t = ClassifyConfig::default().forest.min_samples_split)]
    pub min_split: usize,
    /// Class weighting: balanced (each scribbled class weighs the same) or none (the paper).
    #[arg(long, default_value = "balanced")]
    pub class_weight: String,
    /// Minimum probability for a voxel to take its most probable class.
    #[arg(long, default_value_t = ClassifyConfig::default().tau)]
    pub tau: f32,
    /// The scribble label meaning background/other.
    #[arg(long, default_value_t = ClassifyConfig::default().background)]
    pub background: u32,
    /// Predict empty bricks too (by default they are background when background is scribbled).
    #[arg(long)]
    pub all_bricks: bool,
    /// Forest seed.
    #[arg(long, default_value_t = ClassifyConfig::default().forest.seed)]
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

/// Arguments of `neuvolex classify`.
#[derive(clap::Args, Clone, Debug)]
pub struct ClassifyArgs {
    /// The brick store.
    pub store: PathBuf,
    /// Scribbles: a sparse label volume (NIfTI, NRRD, Zarr; 0 = unlabelled) or strokes (.json).
    #[arg(long)]
    pub scribbles: PathBuf,
    /// Feature set: filters+xyz (default: the filter bank and position), inr (learned + local),
    /// paper (the last hidden layer), intensity, local, filters, or a '+' list of intensity,
    /// local, filters, tubes, xyz, ctx, ctxp, encl, hidden, pos, mod, concat, region.
    #[arg(long, default_value = neuvolex_classify::DEFAULT_FEATURES)]
    pub features: String,
    /// Turn the spatial prior off: the label image is the forest's labels as they are. By
    /// default each class keeps only the connected parts a scribble of it touches, and
    /// unscribbled parts whose probability mass is comparable (see --prior-mass); the
    /// probabilities and the per-brick label vectors stay raw either way.
    #[arg(long)]
    pub no_prior: bool,
    /// The prior keeps an unscribbled part whose probability mass is at least this fraction
    /// of its class's largest scribbled part.
    #[arg(long, default_value_t = neuvolex_classify::PriorConfig::default().relative_mass)]
    pub prior_mass: f64,
    /// The kept parts grow this many voxels into voxels below the confidence threshold whose
    /// most probable class is theirs (the diluted boundary band; 0 = no growth).
    #[arg(long, default_value_t = neuvolex_classify::PriorConfig::default().grow)]
    pub prior_grow: u32,
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
    /// Predict on the GPU: the filter bank and the forest in this process, bricks streamed in
    /// blocks through a ring within a 2 GiB GPU memory budget (feature sets filters+xyz and
    /// filters; not with --cluster), writing the same probabilities and
    /// labels as the CPU, the default and the reference. An error where no GPU adapter (or
    /// Mesa's software lavapipe) exists, or in a build without the `gpu` feature.
    #[arg(long)]
    pub gpu: bool,
    #[command(flatten)]
    pub forest: ForestArgs,
    #[command(flatten)]
    pub cluster: crate::cluster::ClusterArgs,
}

/// The prior's settings from `--prior-mass` and `--prior-grow`, checked.
pub(crate) fn prior_config(mass: f64, grow: u32) -> Result<neuvolex_classify::PriorConfig> {
    neuvolex_classify::PriorConfig::new(mass)
        .map_err(|e| anyhow::anyhow!("--prior-mass {mass}: {e}"))?
        .with_grow(grow)
        .map_err(|e| anyhow::anyhow!("--prior-grow {grow}: {e}"))
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
        prior: Some(prior_config(a.prior_mass, a.prior_grow)?).filter(|_| !a.no_prior),
        hold: None,
        gpu: a.gpu,
    };
    let accel = if a.gpu {
        Some(gpu_accelerator(a, &req)?)
    } else {
        None
    };
    let exec = a.cluster.executor()?;
    let mut bar = crate::cluster::StageBar::new(quiet);
    let o = neuvolex_classify::pipeline::classify_with(&req, accel.as_deref(), &exec, &mut |e| {
        bar.on(e)
    })?;
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
         in {:.2} s; {} bricks predicted, {} empty skipped, {} resumed, {:.2} s ({:.0} k voxels/s) on {}; \
         labels assembled in {:.2} s, published in {:.2} s",
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
        r.run.executor,
        r.seconds_assemble,
        r.seconds_publish
    );
    if let Some(g) = &r.gpu {
        println!("  predicted on the GPU: {g}");
    }
    if r.run.per_worker.len() > 1 || a.cluster.cluster.is_some() {
        let w: Vec<String> = r
            .run
            .per_worker
            .iter()
            .map(|(w, n)| format!("{w} {n}"))
            .collect();
        println!("  tasks per worker: {}", w.join(", "));
    }
    match &r.prior {
        Some(p) => println!(
            "  spatial prior: kept {} of {} connected parts, {} voxels set to background \
             ({:.2} s; --no-prior turns it off)",
            p.kept, p.components, p.voxels_cleared, p.seconds
        ),
        None => println!("  spatial prior: off"),
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
        "  probabilities (raw): {}/neuvolex/vectors/classes_proba (u8); labels: \
         {}/labels/classified",
        a.store.display(),
        a.store.display()
    );
    if let Some(o) = &a.out {
        println!("  label volume: {}", o.display());
    }
    Ok(())
}

/// The GPU `--gpu` predicts on, after the checks that need no device: no `--cluster`, a
/// feature set the GPU computes.
#[cfg(feature = "gpu")]
fn gpu_accelerator(
    a: &ClassifyArgs,
    req: &ClassifyRequest,
) -> Result<Box<dyn neuvolex_classify::accel::Accelerator>> {
    use neuvolex_classify_gpu::{stage, AdapterKind, GpuAccelerator, GpuDevice};
    if a.cluster.cluster.is_some() {
        bail!(
            "--gpu predicts in this process and cannot be combined with --cluster; drop one of \
             them"
        );
    }
    if stage::gpu_features(&req.features).is_none() {
        bail!("{}", stage::unsupported_features(&req.features));
    }
    let dev = GpuDevice::new(AdapterKind::Any)
        .map_err(|e| anyhow::anyhow!("--gpu: {e}; classify without --gpu to use the CPU"))?;
    if dev.is_software() {
        tracing::warn!(
            adapter = %dev.describe(),
            "--gpu: only a software adapter was found; the CPU path is usually faster"
        );
    }
    Ok(Box::new(GpuAccelerator::new(dev)))
}

/// Without the `gpu` feature, `--gpu` is an error.
#[cfg(not(feature = "gpu"))]
fn gpu_accelerator(
    a: &ClassifyArgs,
    _req: &ClassifyRequest,
) -> Result<Box<dyn neuvolex_classify::accel::Accelerator>> {
    if a.cluster.cluster.is_some() {
        bail!(
            "--gpu predicts in this process and cannot be combined with --cluster; drop one of \
             them"
        );
    }
    bail!("--gpu: this neuvolex was built without the `gpu` feature (cargo build --features gpu)")
}
