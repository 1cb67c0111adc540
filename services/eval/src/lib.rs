//! # neuvolex-eval
//!
//! Accuracy against ground truth, in the two protocols users of interactive segmentation
//! know:
//!
//! - **one-shot** ([`oneshot`]): scribbles simulated at the paper's levels S1–S4 (1, 3, 9, 27
//!   axial slices), every feature set, mean F1 over the ROI classes, seeds, forest sizes, INR
//!   ablations and budgets, feature precision, with and without the spatial prior;
//! - **interactive** ([`robot`]): a robot user starts from S1 and, each round, visits one
//!   axial slice (where the largest connected error region is largest; or the suggested slice;
//!   or a random one) and draws one stroke of the true class in the largest wrong region of
//!   each class there, retrains and predicts with warm caches; F1 after every round, rounds to
//!   reach 0.7 and 0.8, and the time per round.
//!
//! Both run the product's pipeline (brick store, [`neuvolex_classify`] feature sets, forest,
//! per-brick prediction, the [`neuvolex_classify::components`] prior) with features cached per
//! (volume, method) in half precision across seeds, levels and rounds. Progress and results
//! are a stream of [`EvalEvent`]s; the command line only draws and prints them.

#![warn(missing_docs)]

pub mod data;
pub mod oneshot;
pub mod predict;
pub mod report;
pub mod robot;

use neuvolex_classify::{ClassifyConfig, PriorConfig};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Errors of an evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A volume or store error.
    #[error(transparent)]
    Volume(#[from] neuvolex_bricks::BrickError),
    /// A classification error.
    #[error(transparent)]
    Classify(#[from] neuvolex_classify::ClassifyError),
    /// An INR error.
    #[error(transparent)]
    Features(#[from] neuvolex_features::FeatureError),
    /// A scribble error.
    #[error(transparent)]
    Scribble(#[from] neuvolex_classify::ScribbleError),
    /// Settings that cannot be used.
    #[error("{0}")]
    Config(String),
    /// A file that cannot be used.
    #[error("{path}: {detail}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
}

impl From<neuvolex_formats::FormatError> for EvalError {
    /// A volume file error, as the store reports it ([`neuvolex_bricks::BrickError::Format`]).
    fn from(e: neuvolex_formats::FormatError) -> Self {
        EvalError::Volume(e.into())
    }
}

/// Result of an evaluation step.
pub type Result<T> = std::result::Result<T, EvalError>;

/// Whether the spatial prior filters the labels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Prior {
    /// The forest's labels as they are.
    None,
    /// The component prior ([`neuvolex_classify::components`]).
    Components,
}

impl std::fmt::Display for Prior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Prior::None => "none",
            Prior::Components => "cc",
        })
    }
}

impl std::str::FromStr for Prior {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "none" => Ok(Prior::None),
            "cc" | "components" => Ok(Prior::Components),
            _ => Err(format!("unknown prior '{s}' (none, cc)")),
        }
    }
}

/// A method: a feature set (as `classify --features` names it) and a prior, written
/// `FEATURES` or `FEATURES@cc`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Method {
    /// The feature set's name.
    pub features: String,
    /// The prior.
    pub prior: Prior,
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.prior {
            Prior::None => write!(f, "{}", self.features),
            p => write!(f, "{}@{p}", self.features),
        }
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (f, p) = match s.split_once('@') {
            Some((f, p)) => (f, p.parse()?),
            None => (s, Prior::None),
        };
        f.parse::<neuvolex_classify::FeatureSet>()?;
        Ok(Method {
            features: f.to_string(),
            prior: p,
        })
    }
}

/// INR variants to train for methods that need one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InrVariant {
    /// Ablation (base, structural, film, full).
    pub ablation: String,
    /// Training budget in epochs.
    pub epochs: f64,
    /// Context sigmas of the heads (empty = the paper's heads).
    pub context_sigmas: Vec<f32>,
}

impl InrVariant {
    /// A short name: `full`, `full+ctx1-2-4-8`.
    pub fn name(&self) -> String {
        if self.context_sigmas.is_empty() {
            self.ablation.clone()
        } else {
            let s: Vec<String> = self.context_sigmas.iter().map(|s| format!("{s}")).collect();
            format!("{}+ctx{}", self.ablation, s.join("-"))
        }
    }
}

/// What an evaluation runs, shared by both protocols.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Datasets: names under `data` (abdomen_ct, brain_mri) or `NAME=IMAGE,LABELS`.
    pub datasets: Vec<String>,
    /// Where the named datasets live.
    pub data: PathBuf,
    /// Working directory for stores and models (reused between runs).
    pub work: PathBuf,
    /// Methods.
    pub methods: Vec<Method>,
    /// Scribble seeds (0..seeds).
    pub seeds: u64,
    /// Forest, tau, background label, empty-brick skipping.
    pub classify: ClassifyConfig,
    /// The prior's settings.
    pub prior: PriorConfig,
    /// INR variants for methods with learned parts.
    pub inr: Vec<InrVariant>,
    /// Feature-cache budget in bytes.
    pub cache_bytes: usize,
    /// Slices on either side of its own that each scribble stroke also covers
    /// ([`neuvolex_classify::thicken`]).
    #[serde(default)]
    pub thicken: usize,
}

/// Progress and results, in order.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum EvalEvent {
    /// A dataset is ready.
    Dataset {
        /// Its name.
        name: String,
        /// Grid.
        dims: [usize; 3],
        /// ROI classes.
        classes: Vec<u32>,
    },
    /// INR training progress (`total` and `what` set on the first event of a model).
    Training {
        /// The model.
        what: String,
        /// Samples so far.
        done: u64,
        /// Sample budget.
        total: u64,
        /// Reconstruction PSNR so far.
        psnr: f64,
    },
    /// An INR is trained (or loaded).
    Model(oneshot::ModelRow),
    /// Work on a volume started: `total` bricks to predict.
    Predicting {
        /// What is being predicted.
        what: String,
        /// Bricks.
        total: u64,
    },
    /// Bricks predicted so far.
    Bricks {
        /// Done.
        done: u64,
    },
    /// A one-shot run is scored.
    Row(oneshot::Row),
    /// A robot round is scored.
    Round(robot::RoundRow),
}

/// Where events go (called from worker threads).
pub type Events<'a> = &'a (dyn Fn(EvalEvent) + Sync);
