//! Datasets: an image and its ground-truth labels, ingested once into a brick store in the
//! work directory, and the INR variants trained on it (cached beside it).

use crate::{EvalError, EvalEvent, Events, InrVariant, Result};
use neuvolex_bricks::BrickStore;
use neuvolex_features::{FeatureKind, InrModel};
use neuvolex_formats::meta::MemVolume;
use neuvolex_ingest::IngestOptions;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// A dataset to evaluate on.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSpec {
    /// Name.
    pub name: String,
    /// The image.
    pub image: PathBuf,
    /// Ground truth on the image's grid (0 = background, 1..N = classes).
    pub labels: PathBuf,
}

impl DatasetSpec {
    /// `abdomen_ct` and `brain_mri` under `data` (../shared/data), or `NAME=IMAGE,LABELS`.
    pub fn parse(spec: &str, data: &Path) -> Result<Self> {
        if let Some((name, rest)) = spec.split_once('=') {
            let (img, lab) = rest.split_once(',').ok_or_else(|| {
                EvalError::Config(format!("--datasets '{spec}': expected NAME=IMAGE,LABELS"))
            })?;
            return Ok(DatasetSpec {
                name: name.into(),
                image: img.into(),
                labels: lab.into(),
            });
        }
        let files = match spec {
            "abdomen_ct" => ("abdomen_ct/ct.nii.gz", "abdomen_ct/labels.nii.gz"),
            "brain_mri" => ("brain_mri/t1_norm.nii.gz", "brain_mri/labels.nii.gz"),
            o => {
                return Err(EvalError::Config(format!(
                    "--datasets: unknown dataset '{o}' (abdomen_ct, brain_mri, or \
                     NAME=IMAGE,LABELS)"
                )))
            }
        };
        let (i, l) = (data.join(files.0), data.join(files.1));
        if !i.exists() || !l.exists() {
            return Err(EvalError::File {
                path: i,
                detail: format!(
                    "dataset '{spec}' not found under {} (see ../shared/data/README.md)",
                    data.display()
                ),
            });
        }
        Ok(DatasetSpec {
            name: spec.into(),
            image: i,
            labels: l,
        })
    }
}

/// A dataset ready to score against: its store, the ground truth in memory, its classes.
pub struct Dataset {
    /// The spec.
    pub spec: DatasetSpec,
    /// The brick store (in the work directory).
    pub store: BrickStore,
    /// Ground truth per voxel (x fastest).
    pub truth: Vec<u32>,
    /// ROI classes present in the truth (ascending).
    pub classes: Vec<u32>,
    /// Directory for this dataset's models.
    pub models: PathBuf,
}

impl Dataset {
    /// Ingests the image into `work/NAME.zarr` (once) and reads the truth.
    pub fn prepare(spec: DatasetSpec, work: &Path) -> Result<Self> {
        std::fs::create_dir_all(work).map_err(|e| EvalError::File {
            path: work.to_path_buf(),
            detail: format!("cannot create the work directory: {e}"),
        })?;
        let store_path = work.join(format!("{}.zarr", spec.name));
        if !store_path.exists() {
            let mut src = neuvolex_bricks::open_volume(&spec.image, None)?;
            neuvolex_ingest::ingest(
                &mut *src,
                &store_path,
                &IngestOptions::default(),
                &mut |_| {},
            )?;
        }
        let store = BrickStore::open(&store_path).map_err(|e| EvalError::File {
            path: store_path.clone(),
            detail: format!("cannot open the cached store ({e}); delete it to re-ingest"),
        })?;
        let mut lsrc = neuvolex_bricks::open_volume(&spec.labels, None)?;
        store.meta().check_same_grid(lsrc.meta(), &spec.labels)?;
        let truth: Vec<u32> = MemVolume::read_all(&mut *lsrc)?
            .to_f32()
            .iter()
            .map(|&v| v as u32)
            .collect();
        let mut classes: Vec<u32> = truth.iter().copied().filter(|&c| c > 0).collect();
        classes.sort_unstable();
        classes.dedup();
        if classes.is_empty() {
            return Err(EvalError::File {
                path: spec.labels.clone(),
                detail: "no foreground label".into(),
            });
        }
        let models = work.join(format!("{}-models", spec.name));
        Ok(Dataset {
            spec,
            store,
            truth,
            classes,
            models,
        })
    }

    /// The dataset's event.
    pub fn event(&self) -> EvalEvent {
        EvalEvent::Dataset {
            name: self.spec.name.clone(),
            dims: self.store.info().dims,
            classes: self.classes.clone(),
        }
    }

    /// A fresh source over the ground truth (for the scribble simulator).
    pub fn truth_source(&self) -> Result<Box<dyn neuvolex_formats::VolumeSource>> {
        Ok(neuvolex_bricks::open_volume(&self.spec.labels, None)?)
    }
}

/// A trained INR and what it cost.
#[derive(Debug, Clone)]
pub struct TrainedInr {
    /// The variant.
    pub variant: InrVariant,
    /// The model.
    pub model: Arc<InrModel>,
    /// Reconstruction PSNR at the end of training.
    pub psnr: f64,
    /// Training seconds.
    pub seconds: f64,
    /// Units of the last hidden layer never active on a sample of bricks.
    pub dead_units: usize,
}

/// Trains (or loads from the dataset's model directory) an INR variant.
pub fn train_inr(ds: &Dataset, v: &InrVariant, events: Events) -> Result<TrainedInr> {
    use neuvolex_features::{checkpoint, train, InrConfig, Preset, TrainConfig};
    let tag = format!("inr-{}-{}ep", v.name(), v.epochs);
    let path = ds.models.join(format!("{tag}.nvx"));
    let meta = ds.models.join(format!("{tag}.json"));
    let (model, psnr, seconds) = if path.exists() && meta.exists() {
        let m = checkpoint::load(&path)?.model;
        let text = std::fs::read_to_string(&meta).map_err(|e| EvalError::File {
            path: meta.clone(),
            detail: e.to_string(),
        })?;
        let j: serde_json::Value = serde_json::from_str(&text).map_err(|e| EvalError::File {
            path: meta.clone(),
            detail: e.to_string(),
        })?;
        (
            m,
            j["psnr"].as_f64().unwrap_or(f64::NAN),
            j["seconds"].as_f64().unwrap_or(f64::NAN),
        )
    } else {
        let inr = InrConfig {
            ablation: v.ablation.parse().map_err(EvalError::Config)?,
            context_sigmas: v.context_sigmas.clone(),
            ..InrConfig::default()
        };
        let mut cfg = TrainConfig::preset(Preset::Fast);
        cfg.budget = neuvolex_features::Budget {
            epochs: Some(v.epochs),
            samples: None,
            seconds: None,
        };
        let cancel = std::sync::atomic::AtomicBool::new(false);
        let t = Instant::now();
        let tr = train(
            &ds.store,
            &inr,
            &cfg,
            None,
            None,
            &cancel,
            &mut |e| match e {
                neuvolex_features::TrainEvent::Started { budget_samples, .. } => {
                    events(EvalEvent::Training {
                        what: format!("{} INR {tag}", ds.spec.name),
                        done: 0,
                        total: budget_samples.unwrap_or(0),
                        psnr: 0.0,
                    })
                }
                neuvolex_features::TrainEvent::Step { samples, psnr, .. } => {
                    events(EvalEvent::Training {
                        what: String::new(),
                        done: samples,
                        total: 0,
                        psnr,
                    })
                }
                _ => {}
            },
        )?;
        let secs = t.elapsed().as_secs_f64();
        std::fs::create_dir_all(&ds.models).map_err(|e| EvalError::File {
            path: ds.models.clone(),
            detail: e.to_string(),
        })?;
        checkpoint::save(&path, &tr.model, None)?;
        std::fs::write(
            &meta,
            serde_json::json!({"psnr": tr.psnr, "seconds": secs}).to_string(),
        )
        .map_err(|e| EvalError::File {
            path: meta.clone(),
            detail: e.to_string(),
        })?;
        (tr.model, tr.psnr as f64, secs)
    };
    let dead_units = dead_units(&ds.store, &model)?;
    Ok(TrainedInr {
        variant: v.clone(),
        model: Arc::new(model),
        psnr,
        seconds,
        dead_units,
    })
}

/// Units of the last hidden layer never active on a sample of bricks.
fn dead_units(store: &BrickStore, model: &InrModel) -> Result<usize> {
    let h = model.cfg.hidden;
    let mut alive = vec![false; h];
    for b in store.occupied_bricks(None).iter().step_by(3).take(8) {
        let f = neuvolex_features::extract::extract_brick(model, store, b, FeatureKind::Hidden)?;
        for r in f.chunks(h) {
            for (k, &v) in r.iter().enumerate() {
                alive[k] |= v > 0.0;
            }
        }
    }
    Ok(alive.iter().filter(|a| !**a).count())
}
