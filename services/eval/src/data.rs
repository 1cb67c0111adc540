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
    /// A regrouping of the ground truth: class `k + 1` is the union of the labels of
    /// `groups[k]`, every other label background (`None`: the labels as they are).
    pub groups: Option<Vec<Vec<u32>>>,
}

/// The named regroupings of the development volumes ([`DatasetSpec::parse`]): shapes the
/// interactive evaluation must hold on that the volumes' own classes do not show.
///
/// - `brain_mri:brain`: the whole brain (labels 1–7) against everything else, two classes of
///   one huge component each, as a head MRI's brain-versus-rest task;
/// - `abdomen_ct:aorta`: the aorta (label 4) alone, one thin vessel in a large background, as a
///   CTA's single-vessel task.
pub const GROUPINGS: &[(&str, &str)] = &[
    ("brain_mri:brain", "1+2+3+4+5+6+7"),
    ("abdomen_ct:aorta", "4"),
];

/// The datasets `neuvolex eval --interactive` scores by default: the development volumes and
/// their [`GROUPINGS`].
pub const INTERACTIVE_DATASETS: &[&str] = &[
    "abdomen_ct",
    "brain_mri",
    "abdomen_ct:aorta",
    "brain_mri:brain",
];

/// Parses a regrouping `A+B,C`: class 1 is labels A and B, class 2 label C.
pub fn parse_groups(s: &str) -> std::result::Result<Vec<Vec<u32>>, String> {
    let groups: Vec<Vec<u32>> = s
        .split(',')
        .map(|g| {
            g.split('+')
                .map(|l| {
                    l.trim()
                        .parse::<u32>()
                        .ok()
                        .filter(|&l| l > 0)
                        .ok_or_else(|| format!("'{l}' is not a label above 0"))
                })
                .collect()
        })
        .collect::<std::result::Result<_, _>>()?;
    let mut all: Vec<u32> = groups.iter().flatten().copied().collect();
    all.sort_unstable();
    if all.windows(2).any(|w| w[0] == w[1]) {
        return Err("a label is in two groups".into());
    }
    Ok(groups)
}

/// `truth` regrouped: class `k + 1` where the label is in `groups[k]`, else 0.
pub fn regroup(truth: &[u32], groups: &[Vec<u32>]) -> Vec<u32> {
    let max = groups.iter().flatten().copied().max().unwrap_or(0) as usize;
    let mut map = vec![0u32; max + 1];
    for (k, g) in groups.iter().enumerate() {
        g.iter().for_each(|&l| map[l as usize] = k as u32 + 1);
    }
    truth
        .iter()
        .map(|&t| map.get(t as usize).copied().unwrap_or(0))
        .collect()
}

impl DatasetSpec {
    /// `abdomen_ct` and `brain_mri` under `data` (../shared/data), `NAME=IMAGE,LABELS`, or
    /// either followed by `:GROUPS` (a regrouping of its labels, `1+2,4`: [`parse_groups`]) or
    /// by the name of one of the [`GROUPINGS`] (`brain_mri:brain`).
    pub fn parse(spec: &str, data: &Path) -> Result<Self> {
        if let Some((base, g)) = spec.rsplit_once(':').filter(|(b, _)| !b.contains('=')) {
            let named = GROUPINGS.iter().find(|(n, _)| *n == spec).map(|(_, g)| *g);
            let groups = parse_groups(named.unwrap_or(g)).map_err(|e| {
                EvalError::Config(format!(
                    "--datasets '{spec}': {e} (a regrouping such as 1+2,4, or one of {})",
                    GROUPINGS
                        .iter()
                        .map(|(n, _)| *n)
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?;
            let mut d = DatasetSpec::parse(base, data)?;
            d.name = spec.into();
            d.groups = Some(groups);
            return Ok(d);
        }
        if let Some((name, rest)) = spec.split_once('=') {
            let (img, lab) = rest.split_once(',').ok_or_else(|| {
                EvalError::Config(format!("--datasets '{spec}': expected NAME=IMAGE,LABELS"))
            })?;
            return Ok(DatasetSpec {
                name: name.into(),
                image: img.into(),
                labels: lab.into(),
                groups: None,
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
            groups: None,
        })
    }

    /// The name of the image's store and models: the dataset's name without its regrouping
    /// (every grouping of one image shares them).
    pub fn image_name(&self) -> &str {
        match &self.groups {
            Some(_) => self.name.rsplit_once(':').map_or(&self.name, |(b, _)| b),
            None => &self.name,
        }
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
        let store_path = work.join(format!("{}.zarr", spec.image_name()));
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
        let truth = match &spec.groups {
            Some(g) => regroup(&truth, g),
            None => truth,
        };
        let mut classes: Vec<u32> = truth.iter().copied().filter(|&c| c > 0).collect();
        classes.sort_unstable();
        classes.dedup();
        if classes.is_empty() {
            return Err(EvalError::File {
                path: spec.labels.clone(),
                detail: "no foreground label".into(),
            });
        }
        let models = work.join(format!("{}-models", spec.image_name()));
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

    /// A fresh source over the ground truth (for the scribble simulator), regrouped as the
    /// spec says.
    pub fn truth_source(&self) -> Result<Box<dyn neuvolex_formats::VolumeSource>> {
        let src = neuvolex_bricks::open_volume(&self.spec.labels, None)?;
        if self.spec.groups.is_none() {
            return Ok(src);
        }
        let values: Vec<f32> = self.truth.iter().map(|&t| t as f32).collect();
        let mut mem = MemVolume::from_f32(src.meta().dims, &values);
        let dtype = mem.meta.dtype;
        mem.meta = src.meta().clone();
        mem.meta.dtype = dtype;
        mem.meta.scaling = None;
        mem.name = self.spec.labels.clone();
        Ok(Box::new(mem))
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regroupings_parse_and_map_labels() {
        assert_eq!(
            parse_groups("1+2+3,4").unwrap(),
            vec![vec![1, 2, 3], vec![4]]
        );
        assert_eq!(parse_groups(" 4 ").unwrap(), vec![vec![4]]);
        for bad in ["", "0", "1+x", "1,1", "2+3,3", "-1"] {
            assert!(parse_groups(bad).is_err(), "'{bad}' accepted");
        }
        let truth = [0, 1, 2, 3, 4, 5, 7, 300];
        assert_eq!(
            regroup(&truth, &[vec![1, 2, 3], vec![4]]),
            vec![0, 1, 1, 1, 2, 0, 0, 0]
        );
    }

    #[test]
    fn named_groupings_and_explicit_ones_share_the_image() {
        let d = tempfile::tempdir().unwrap();
        for f in ["abdomen_ct/ct.nii.gz", "abdomen_ct/labels.nii.gz"] {
            let p = d.path().join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, b"").unwrap();
        }
        let named = DatasetSpec::parse("abdomen_ct:aorta", d.path()).unwrap();
        assert_eq!(named.name, "abdomen_ct:aorta");
        assert_eq!(named.groups, Some(vec![vec![4]]));
        assert_eq!(named.image_name(), "abdomen_ct");
        let plain = DatasetSpec::parse("abdomen_ct", d.path()).unwrap();
        assert_eq!(
            (plain.image.clone(), plain.groups.clone()),
            (named.image.clone(), None)
        );
        assert_eq!(plain.image_name(), "abdomen_ct");
        let explicit = DatasetSpec::parse("abdomen_ct:2+3", d.path()).unwrap();
        assert_eq!(explicit.groups, Some(vec![vec![2, 3]]));
        // Bad groupings and unknown bases are refused with the spec in the message.
        let e = DatasetSpec::parse("abdomen_ct:kidneys", d.path()).unwrap_err();
        assert!(e.to_string().contains("abdomen_ct:kidneys"), "{e}");
        assert!(DatasetSpec::parse("nowhere:1", d.path()).is_err());
        // Every named grouping and interactive dataset parses.
        for (n, g) in GROUPINGS {
            assert!(parse_groups(g).is_ok(), "{n}");
        }
        assert!(INTERACTIVE_DATASETS
            .iter()
            .all(|s| s.starts_with("abdomen_ct") || s.starts_with("brain_mri")));
    }
}
