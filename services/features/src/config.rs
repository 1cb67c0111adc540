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
        }
    }
}

impl InrConfig {
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
        Ok(())
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
