//! Model and training configuration: one serde struct per stage, the paper's values as defaults.

use serde::{Deserialize, Serialize};

/// Architecture of the volume-exploration INR. Every size is a field; defaults are the paper's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InrConfig {
    /// Hash-grid levels L.
    pub levels: usize,
    /// Features per level F.
    pub features_per_level: usize,
    /// log2 of the hash-table size per level (T).
    pub log2_table: u32,
    /// Coarsest grid resolution.
    pub base_resolution: usize,
    /// Finest grid resolution; `None` = the volume's largest dimension.
    pub finest_resolution: Option<usize>,
    /// Edge of the raw patch fed to the structural encoder (5 -> 5x5x5).
    pub patch: usize,
    /// Hidden width of the structural encoder (2 layers).
    pub structural_hidden: usize,
    /// Hidden width of the main MLP.
    pub hidden: usize,
    /// Hidden layers of the main MLP (the last one is the feature).
    pub hidden_layers: usize,
    /// Ablation switches (paper Fig. 8).
    pub ablation: Ablation,
    /// Loss weight of the gradient head.
    pub lambda_grad: f32,
    /// Loss weight of the local mean and std heads.
    pub lambda_stat: f32,
    /// Multi-scale context targets (empty = the paper's model): for each sigma (level-0
    /// voxels), two extra outputs of the heads layer predict the Gaussian-smoothed normalised
    /// intensity and its scale-normalised gradient magnitude at that scale, read from the
    /// store's pyramid, so the last hidden layer has to describe the voxel's surroundings.
    pub context_sigmas: Vec<f32>,
    /// Loss weight of the context outputs together (each of the `2 x sigmas` outputs weighs
    /// `lambda_context / (2 x sigmas)`).
    pub lambda_context: f32,
}

impl Default for InrConfig {
    fn default() -> Self {
        InrConfig {
            levels: 16,
            features_per_level: 2,
            log2_table: 19,
            base_resolution: 16,
            finest_resolution: None,
            patch: 5,
            structural_hidden: 32,
            hidden: 64,
            hidden_layers: 4,
            ablation: Ablation::Full,
            lambda_grad: 1.0,
            lambda_stat: 0.5,
            context_sigmas: Vec::new(),
            lambda_context: 1.0,
        }
    }
}

/// Outputs of the paper's heads: intensity, gradient (3), local mean, local std. Context
/// outputs ([`InrConfig::context_sigmas`]) follow them. Defined here rather than in `model`
/// so that the configuration depends on nothing else in the crate (`hashgrid` and `model`
/// build on it, never the other way round); `model::TARGETS` re-exports it.
pub const TARGETS: usize = 6;

impl InrConfig {
    /// Target values per training sample: intensity, gradient (3), local mean, local std, then
    /// smoothed intensity and gradient magnitude per context sigma.
    pub fn targets(&self) -> usize {
        TARGETS + 2 * self.context_sigmas.len()
    }

    /// Loss weight of every output of the heads layer, in output order: the paper's heads
    /// (intensity 1, gradient `lambda_grad / 3` each, mean and std `lambda_stat`; intensity
    /// alone without multi-task heads), then the context outputs.
    pub fn head_weights(&self) -> Vec<f32> {
        let mut w = if self.ablation.multitask() {
            let g = self.lambda_grad / 3.0;
            vec![1.0, g, g, g, self.lambda_stat, self.lambda_stat]
        } else {
            vec![1.0]
        };
        let nc = 2 * self.context_sigmas.len();
        w.extend(std::iter::repeat_n(
            self.lambda_context / nc.max(1) as f32,
            nc,
        ));
        w
    }

    /// The target index of each output of the heads layer.
    pub fn head_targets(&self) -> Vec<usize> {
        let base = if self.ablation.multitask() {
            TARGETS
        } else {
            1
        };
        (0..base)
            .chain((0..2 * self.context_sigmas.len()).map(|k| TARGETS + k))
            .collect()
    }

    /// Checks the context settings.
    pub fn check(&self) -> Result<(), String> {
        if let Some(s) = self
            .context_sigmas
            .iter()
            .find(|s| !(s.is_finite() && **s >= 0.5 && **s <= 64.0))
        {
            return Err(format!("context sigma {s} must be in 0.5..=64 voxels"));
        }
        if !(self.lambda_context.is_finite() && self.lambda_context >= 0.0) {
            return Err(format!(
                "lambda_context {} must be finite and non-negative",
                self.lambda_context
            ));
        }
        Ok(())
    }

    /// Checks every size against limits far above any useful model (16 levels of 2^19 entries
    /// is the paper's), so a damaged or hostile model file is refused before anything is
    /// allocated for it.
    pub fn validate(&self) -> Result<(), String> {
        let within = |name: &str, v: usize, lo: usize, hi: usize| {
            if (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(format!("{name} {v} is outside {lo}..={hi}"))
            }
        };
        within("levels", self.levels, 1, 32)?;
        within("features_per_level", self.features_per_level, 1, 16)?;
        within("log2_table", self.log2_table as usize, 1, 26)?;
        within("base_resolution", self.base_resolution, 1, 1 << 20)?;
        if let Some(f) = self.finest_resolution {
            within("finest_resolution", f, 1, 1 << 20)?;
        }
        within("patch", self.patch, 1, 15)?;
        within("structural_hidden", self.structural_hidden, 1, 1024)?;
        within("hidden", self.hidden, 1, 1024)?;
        within("hidden_layers", self.hidden_layers, 1, 64)?;
        if !(self.lambda_grad.is_finite() && self.lambda_stat.is_finite()) {
            return Err("loss weights must be finite".into());
        }
        if self.context_sigmas.len() > 8 {
            return Err(format!(
                "{} context sigmas: at most 8",
                self.context_sigmas.len()
            ));
        }
        self.check()
    }
}

/// The paper's ablation ladder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Ablation {
    /// Hash grid + MLP + intensity head.
    Base,
    /// + structural encoder, concatenated with the positional features.
    Structural,
    /// + FiLM fusion instead of concatenation (intensity head only).
    Film,
    /// + multi-task heads (intensity, gradient, local mean, local std): the full model.
    Full,
}

impl Ablation {
    /// Whether the structural encoder is used.
    pub fn structural(self) -> bool {
        !matches!(self, Ablation::Base)
    }
    /// Whether FiLM fuses the pathways.
    pub fn film(self) -> bool {
        matches!(self, Ablation::Film | Ablation::Full)
    }
    /// Whether the gradient/mean/std heads are trained.
    pub fn multitask(self) -> bool {
        matches!(self, Ablation::Full)
    }
}

impl std::str::FromStr for Ablation {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "base" => Ok(Ablation::Base),
            "structural" => Ok(Ablation::Structural),
            "film" => Ok(Ablation::Film),
            "full" | "multitask" => Ok(Ablation::Full),
            _ => Err(format!(
                "unknown ablation '{s}' (base, structural, film, full)"
            )),
        }
    }
}

/// How Adam treats the hash table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TableAdam {
    /// Update only the rows touched in a step (moments of untouched rows are left as they are).
    Lazy,
    /// Update every row every step, as PyTorch's Adam does.
    Dense,
}

/// What stops training. Whichever limit is reached first ends it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Budget {
    /// Passes over the occupied voxels.
    pub epochs: Option<f64>,
    /// Total training samples.
    pub samples: Option<u64>,
    /// Wall-clock seconds.
    pub seconds: Option<f64>,
}

/// The user's speed/accuracy presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// A quick preview: 1 epoch.
    Fast,
    /// 5 epochs.
    Balanced,
    /// The paper: 100 epochs at lr 1e-4.
    Paper,
}

impl std::str::FromStr for Preset {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "fast" => Ok(Preset::Fast),
            "balanced" => Ok(Preset::Balanced),
            "paper" => Ok(Preset::Paper),
            _ => Err(format!("unknown preset '{s}' (fast, balanced, paper)")),
        }
    }
}

/// Training settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Learning rate of the MLPs.
    pub lr: f32,
    /// Learning rate of the hash table (Instant-NGP trains tables faster than MLPs).
    pub lr_table: f32,
    /// Samples per optimiser step.
    pub batch: usize,
    /// Seed of initialisation and sampling.
    pub seed: u64,
    /// Stopping rule.
    pub budget: Budget,
    /// Bricks resident at once (the tile); samples of a step come from these.
    pub tile_bricks: usize,
    /// Train on empty bricks too.
    pub include_empty: bool,
    /// Adam mode of the hash table.
    pub table_adam: TableAdam,
    /// Steps between checkpoints (0 = only at the end).
    pub checkpoint_every: u64,
    /// Steps between progress events.
    pub report_every: u64,
    /// Steps between preview slices (0 = none).
    pub preview_every: u64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig::preset(Preset::Fast)
    }
}

impl TrainConfig {
    /// The settings of a preset.
    pub fn preset(p: Preset) -> Self {
        let (epochs, lr, lr_table) = match p {
            Preset::Fast => (1.0, 1e-3, 1e-2),
            Preset::Balanced => (5.0, 1e-3, 1e-2),
            Preset::Paper => (100.0, 1e-4, 1e-4),
        };
        TrainConfig {
            lr,
            lr_table,
            batch: 16384,
            seed: 0,
            budget: Budget {
                epochs: Some(epochs),
                samples: None,
                seconds: None,
            },
            tile_bricks: 8,
            include_empty: false,
            table_adam: TableAdam::Lazy,
            checkpoint_every: 500,
            report_every: 10,
            preview_every: 100,
        }
    }
}

/// Where training and feature extraction run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// The fused CPU engine.
    Cpu,
    /// The GPU engine on any adapter, software ones (Mesa lavapipe, llvmpipe) included.
    Gpu,
    /// The GPU engine when a hardware GPU adapter exists, else the CPU engine.
    #[default]
    Auto,
}

impl Backend {
    /// The name `FromStr` accepts.
    pub fn as_str(self) -> &'static str {
        match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
            Backend::Auto => "auto",
        }
    }
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Backend::Cpu),
            "gpu" => Ok(Backend::Gpu),
            "auto" => Ok(Backend::Auto),
            _ => Err(format!("unknown backend '{s}' (cpu, gpu, auto)")),
        }
    }
}
