//! `neuvolex eval`: parses, draws progress, prints; the evaluation is `neuvolex-eval`.

use crate::classify::{bar, styled_bar, ForestArgs};
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use neuvolex_eval::oneshot::OneShotConfig;
use neuvolex_eval::report::{far_table, oneshot_tables, robot_table};
use neuvolex_eval::robot::{summarise, Placement, RobotConfig};
use neuvolex_eval::{EvalConfig, EvalEvent, InrVariant, Method};
use std::path::PathBuf;
use std::sync::Mutex;

/// Arguments of `neuvolex eval`.
#[derive(clap::Args, Clone, Debug)]
pub struct EvalArgs {
    /// Datasets: names under --data (abdomen_ct, brain_mri) or NAME=IMAGE,LABELS, each
    /// optionally regrouped (`brain_mri:brain`, `abdomen_ct:aorta`, or `:1+2,4`). Default:
    /// abdomen_ct;brain_mri, and with --interactive also abdomen_ct:aorta;brain_mri:brain.
    #[arg(long, value_delimiter = ';')]
    pub datasets: Option<Vec<String>>,
    /// Where the named datasets live.
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Scribble levels (one-shot protocol).
    #[arg(long, value_delimiter = ',', default_value = "S1,S2,S3,S4")]
    pub levels: Vec<String>,
    /// Scribble seeds (0..N).
    #[arg(long, default_value_t = 3)]
    pub seeds: u64,
    /// Methods: feature sets (see `classify --features`), each optionally with `@cc` for the
    /// component prior.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "local,filters,filters+xyz,filters+xyz@cc,paper,inr"
    )]
    pub methods: Vec<String>,
    /// Forest sizes to score (sub-forests of the largest; one-shot protocol).
    #[arg(long, value_delimiter = ',')]
    pub tree_counts: Vec<usize>,
    /// INR training budgets in epochs.
    #[arg(long, value_delimiter = ',', default_value = "3")]
    pub epochs: Vec<f64>,
    /// INR ablations: base, structural, film, full.
    #[arg(long, value_delimiter = ',', default_value = "full")]
    pub ablations: Vec<String>,
    /// INR heads: paper (the paper's targets), or context sigmas such as 1-2-4-8 (extra
    /// outputs predicting the smoothed intensity and gradient magnitude at those scales).
    #[arg(long, value_delimiter = ',', default_value = "paper")]
    pub inr_heads: Vec<String>,
    /// Feature precision: f32 (recomputed), f16 (cached, default), u8.
    #[arg(long, value_delimiter = ',', default_value = "f16")]
    pub quantise: Vec<String>,
    /// The interactive protocol: a robot user corrects the S1 result slice by slice.
    #[arg(long)]
    pub interactive: bool,
    /// Robot rounds after the S1 start.
    #[arg(long, default_value_t = 10)]
    pub rounds: usize,
    /// Where the robot draws: largest (the largest error region), suggested (the suggested
    /// slice), random (a random slice).
    #[arg(long, value_delimiter = ',', default_value = "largest")]
    pub robot: Vec<String>,
    /// Mean F1 targets of the robot.
    #[arg(long, value_delimiter = ',', default_value = "0.7,0.8")]
    pub targets: Vec<f64>,
    /// Voxels around a robot round's new strokes that count as near them (default: the filter
    /// bank's halo); the F1 change beyond them is reported apart.
    #[arg(long, default_value_t = neuvolex_eval::robot::default_margin())]
    pub margin: usize,
    /// Robot rounds: beyond the margin, a voxel keeps its previous label unless the new
    /// probabilities prefer the new one by this much (the service's rule); `off` shows every
    /// round's labels as they are.
    #[arg(long, default_value_t = neuvolex_classify::StableConfig::default().delta.to_string())]
    pub stable: String,
    /// Robot rounds: steps of the rule's ramp inside the margin (the preference a change needs
    /// rises from 0 at the new strokes to the rule's delta at the margin; 0: new labels stand
    /// anywhere within the margin).
    #[arg(long, default_value_t = neuvolex_classify::StableConfig::default().ramp)]
    pub stable_ramp: u8,
    /// Robot rounds: whether the rule also holds the spatial prior's and growth's decisions
    /// beyond the margin (a voxel whose forest label did not change keeps its label).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub stable_prior: bool,
    /// Robot rounds: whether a change beyond the margin must be confirmed by the forests of
    /// the rounds before (they already gave the new label; how many: `--stable-forests`).
    #[arg(long, default_value_t = neuvolex_classify::stable::DEFAULT_CONFIRM, action = clap::ArgAction::Set)]
    pub stable_confirm: bool,
    /// Robot rounds: how many forests in a row a confirmed far change needs (2: the previous
    /// round's and this one; 2 to 8); a forest before this round's counts only when its
    /// round's strokes name another class than the change's.
    #[arg(long, default_value_t = neuvolex_classify::stable::DEFAULT_FORESTS, value_parser = clap::value_parser!(u8).range(2..=neuvolex_classify::stable::MAX_FORESTS as i64))]
    pub stable_forests: u8,
    /// Robot rounds: whether growth follows the labels the rule shows (a doubtful voxel that
    /// growth gave a class takes it when it touches a shown voxel of that class).
    #[arg(long, default_value_t = neuvolex_classify::stable::DEFAULT_FOLLOW, action = clap::ArgAction::Set)]
    pub stable_follow: bool,
    /// The prior keeps an unscribbled component whose probability mass is at least this
    /// fraction of its class's largest scribbled component.
    #[arg(long, default_value_t = neuvolex_classify::PriorConfig::default().relative_mass)]
    pub prior_mass: f64,
    /// The prior's kept parts grow this many voxels into doubtful voxels of their class.
    #[arg(long, default_value_t = neuvolex_classify::PriorConfig::default().grow)]
    pub prior_grow: u32,
    /// Each scribble stroke also covers this many slices on either side of its own.
    #[arg(long, default_value_t = 0)]
    pub thicken: usize,
    /// Feature-cache budget in MiB.
    #[arg(long, default_value_t = 4096)]
    pub cache_mib: usize,
    /// Working directory for stores and models (reused between runs).
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// JSON output.
    #[arg(long)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub forest: ForestArgs,
}

impl EvalArgs {
    fn config(&self) -> Result<EvalConfig> {
        let methods: Vec<Method> = self
            .methods
            .iter()
            .map(|m| m.parse().map_err(anyhow::Error::msg))
            .collect::<Result<_>>()?;
        let mut inr = Vec::new();
        for ab in &self.ablations {
            ab.parse::<neuvolex_features::Ablation>()
                .map_err(anyhow::Error::msg)?;
            for &epochs in &self.epochs {
                for h in &self.inr_heads {
                    let context_sigmas = if h == "paper" {
                        Vec::new()
                    } else {
                        h.split('-')
                            .map(|s| s.parse::<f32>())
                            .collect::<std::result::Result<Vec<_>, _>>()
                            .map_err(|_| {
                                anyhow::anyhow!(
                                    "--inr-heads '{h}': paper, or sigmas joined by '-' (1-2-4-8)"
                                )
                            })?
                    };
                    let v = InrVariant {
                        ablation: ab.clone(),
                        epochs,
                        context_sigmas,
                    };
                    neuvolex_features::InrConfig {
                        context_sigmas: v.context_sigmas.clone(),
                        ..Default::default()
                    }
                    .check()
                    .map_err(|e| anyhow::anyhow!("--inr-heads '{h}': {e}"))?;
                    inr.push(v);
                }
            }
        }
        let prior = crate::classify::prior_config(self.prior_mass, self.prior_grow)?;
        Ok(EvalConfig {
            datasets: match &self.datasets {
                Some(d) => d.clone(),
                None if self.interactive => neuvolex_eval::data::INTERACTIVE_DATASETS
                    .iter()
                    .map(|d| d.to_string())
                    .collect(),
                None => vec!["abdomen_ct".into(), "brain_mri".into()],
            },
            data: self.data.clone(),
            work: self
                .work
                .clone()
                .unwrap_or_else(|| std::env::temp_dir().join("neuvolex-eval")),
            methods,
            seeds: self.seeds,
            classify: self.forest.config()?,
            prior,
            inr,
            cache_bytes: self.cache_mib << 20,
            thicken: self.thicken,
        })
    }
}

/// Draws evaluation events: a bar per prediction and per INR, a line per scored run.
struct Progress {
    quiet: bool,
    bar: Mutex<Option<ProgressBar>>,
    models: Mutex<Vec<neuvolex_eval::oneshot::ModelRow>>,
}

impl Progress {
    fn event(&self, e: EvalEvent) {
        let mut b = self.bar.lock().unwrap_or_else(|p| p.into_inner());
        match e {
            EvalEvent::Dataset {
                name,
                dims,
                classes,
            } => {
                eprintln!("{name}: {dims:?}, classes {classes:?}")
            }
            EvalEvent::Training {
                what,
                done,
                total,
                psnr,
            } => {
                if total > 0 {
                    if let Some(o) = b.take() {
                        o.finish_and_clear();
                    }
                    let nb = styled_bar(
                        self.quiet,
                        total,
                        "     train [{bar:40}] {pos}/{len} samples {msg} eta {eta}",
                    );
                    nb.set_message(what);
                    *b = Some(nb);
                } else if let Some(pb) = b.as_ref() {
                    pb.set_position(done);
                    pb.set_message(format!("PSNR {psnr:.1} dB"));
                }
            }
            EvalEvent::Model(m) => {
                if let Some(o) = b.take() {
                    o.finish_and_clear();
                }
                self.models
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push(m.clone());
                eprintln!(
                    "{}: INR {} {} epochs: PSNR {:.2} dB, {:.1} s, {} dead hidden units",
                    m.dataset, m.inr, m.epochs, m.psnr, m.seconds, m.dead_units
                )
            }
            EvalEvent::Predicting { what, total } => {
                if let Some(o) = b.take() {
                    o.finish_and_clear();
                }
                *b = Some(bar(
                    self.quiet,
                    total,
                    &what.chars().take(10).collect::<String>(),
                ));
            }
            EvalEvent::Bricks { done } => {
                if let Some(pb) = b.as_ref() {
                    pb.set_position(done);
                }
            }
            EvalEvent::Row(r) => {
                if let Some(o) = b.take() {
                    o.finish_and_clear();
                }
                eprintln!(
                    "{} {} seed {} {} {} {}t {}: mean F1 {:.3} [{}] fit {:.1} s classify {:.1} s",
                    r.dataset,
                    r.level,
                    r.seed,
                    r.method,
                    r.inr,
                    r.trees,
                    r.quantise,
                    r.mean_f1,
                    r.f1.iter()
                        .map(|f| format!("{}:{:.3}", f.label, f.f1))
                        .collect::<Vec<_>>()
                        .join(" "),
                    r.seconds_fit,
                    r.seconds_classify
                );
            }
            EvalEvent::Round(r) => {
                if let Some(o) = b.take() {
                    o.finish_and_clear();
                }
                eprintln!(
                    "{} {} {} {} seed {} round {:>2}: mean F1 {:.3} [{}] {} voxels scribbled, {:.2} s{}",
                    r.dataset,
                    r.method,
                    r.inr,
                    r.placement,
                    r.seed,
                    r.round,
                    r.mean_f1,
                    r.f1.iter()
                        .map(|f| format!("{}:{:.2}", f.label, f.f1))
                        .collect::<Vec<_>>()
                        .join(" "),
                    r.scribbled,
                    r.seconds,
                    r.strokes
                        .first()
                        .map(|s| format!(
                            ", {} stroke(s) on z {} (classes {})",
                            r.strokes.len(),
                            s.slice,
                            r.strokes
                                .iter()
                                .map(|s| s.class.to_string())
                                .collect::<Vec<_>>()
                                .join(",")
                        ))
                        .unwrap_or_default()
                );
            }
        }
    }
}

/// `neuvolex eval`.
pub fn run_eval(a: &EvalArgs, quiet: bool) -> Result<()> {
    let cfg = a.config()?;
    let p = Progress {
        quiet,
        bar: Mutex::new(None),
        models: Mutex::new(Vec::new()),
    };
    let events = |e: EvalEvent| p.event(e);
    let mut json = if a.interactive {
        let rc = RobotConfig {
            rounds: a.rounds,
            placements: a
                .robot
                .iter()
                .map(|s| s.parse::<Placement>().map_err(anyhow::Error::msg))
                .collect::<Result<_>>()?,
            targets: a.targets.clone(),
            margin: a.margin,
            stable_delta: match a.stable.as_str() {
                "off" => None,
                v => Some(
                    v.parse::<f32>()
                        .ok()
                        .filter(|d| (0.0..=1.0).contains(d))
                        .ok_or_else(|| {
                            anyhow::anyhow!("--stable {v}: off or a probability in 0..=1")
                        })?,
                ),
            },
            stable_ramp: a.stable_ramp,
            stable_prior: a.stable_prior,
            stable_confirm: a.stable_confirm,
            stable_forests: a.stable_forests,
            stable_follow: a.stable_follow,
        };
        let rows = neuvolex_eval::robot::run(&cfg, &rc, &events)?;
        println!("\n{}", robot_table(&rows, &rc.targets));
        println!("{}", far_table(&rows, &rc.targets));
        serde_json::json!({
            "config": {"eval": cfg, "robot": rc},
            "summary": summarise(&rows, &rc.targets),
            "rounds": rows,
        })
    } else {
        let os = OneShotConfig {
            levels: a
                .levels
                .iter()
                .map(|l| l.parse().map_err(anyhow::Error::msg))
                .collect::<Result<_>>()?,
            tree_counts: a.tree_counts.clone(),
            quantise: a.quantise.clone(),
        };
        let rows = neuvolex_eval::oneshot::run(&cfg, &os, &events)?;
        println!("\n{}", oneshot_tables(&rows));
        serde_json::json!({
            "config": {"eval": cfg, "oneshot": os},
            "runs": rows,
        })
    };
    if let Some(b) = p.bar.lock().unwrap_or_else(|p| p.into_inner()).take() {
        b.finish_and_clear();
    }
    json["models"] = serde_json::to_value(&*p.models.lock().unwrap_or_else(|p| p.into_inner()))?;
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("{}: cannot write", path.display()))?;
        println!("eval: results written to {}", path.display());
    }
    Ok(())
}
