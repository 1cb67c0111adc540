//! Prediction on an accelerator (the GPU of `neuvolex-classify-gpu`) behind two small traits,
//! so that this crate never depends on a GPU API: the command line passes an [`Accelerator`]
//! into [`crate::pipeline::classify_with`], the pipeline binds it to the trained forest once
//! ([`Accelerator::prepare`]) and streams a task's occupied bricks through it
//! ([`BrickPredictor::predict_stream`]), and [`brick_result`], the pure per-brick step, turns
//! what the predictor gives into the same [`BrickResult`] as [`crate::shard::classify_brick`],
//! so everything after prediction (the stored probabilities and labels, the prior, the
//! published label image) is unchanged.

use crate::features::FeatureSet;
use crate::forest::Forest;
use crate::shard::BrickResult;
use crate::ClassifyError;
use neuvolex_bricks::{Brick, BrickStore};
use std::sync::Arc;

/// The class index of a voxel whose top probability is below `tau` (in
/// [`AcceleratedBrick::classes`]).
pub const BELOW_TAU: u8 = u8::MAX;

/// What an accelerator gives for one brick.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AcceleratedBrick {
    /// Class probabilities, `voxels x classes`, as u8 ([`crate::stable::to_u8`] of the CPU
    /// forest's f32 probabilities).
    pub probs: Vec<u8>,
    /// Per voxel, the first most probable class index, or [`BELOW_TAU`] where its probability
    /// is below `tau` (compared in f32, as [`crate::shard::predict_brick`] does).
    pub classes: Vec<u8>,
}

/// Bricks a task of the pipeline gives an accelerator at once (at least), so that its stream
/// ([`BrickPredictor::predict_stream`]) can overlap and group them.
pub const STREAM_BRICKS: usize = 64;

/// How a forest is bound to an accelerator ([`Accelerator::prepare`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccelOptions {
    /// Voxels whose top probability is below it get [`BELOW_TAU`] (the CLI's `--tau`; 0 where
    /// only the probabilities are used, as in the service).
    pub tau: f32,
    /// Round every feature through f16 before the forest reads it, as the service's feature
    /// cache holds them ([`crate::Forest::predict_proba_f16`]): a forest trained on the cache's
    /// features then sees the values it was trained on.
    pub f16_features: bool,
}

impl AccelOptions {
    /// `tau`, features in f32 (the CLI's `--gpu`).
    pub fn tau(tau: f32) -> Self {
        AccelOptions {
            tau,
            f16_features: false,
        }
    }
}

/// Something that predicts bricks with a trained forest (a GPU).
pub trait Accelerator: Send + Sync {
    /// The device, for the log ("NVIDIA H200 (Vulkan, DiscreteGpu)").
    fn describe(&self) -> String;

    /// `forest` bound to this device, over the features `set` gives for `store`'s bricks;
    /// an error naming the set where the device cannot compute it.
    fn prepare(
        &self,
        store: Arc<BrickStore>,
        set: &FeatureSet,
        forest: &Forest,
        opts: &AccelOptions,
    ) -> Result<Box<dyn BrickPredictor>, ClassifyError>;
}

/// A forest bound to an accelerator.
pub trait BrickPredictor: Send + Sync {
    /// Computes brick `b`'s features and predicts them.
    fn predict(&self, b: &Brick) -> Result<AcceleratedBrick, ClassifyError>;

    /// Predicts `bricks` and gives each brick's result to `on` as it comes back, until `on`
    /// returns false (the bricks not given yet are then not predicted). Results come in the
    /// order of `bricks`, except that an accelerator may predict neighbouring bricks together
    /// and give them together, at the place of the first of them. The default predicts one
    /// brick at a time; the GPU's overlaps reading the next bricks with the device's work.
    fn predict_stream(
        &self,
        bricks: &[Brick],
        on: &mut dyn FnMut(&Brick, AcceleratedBrick) -> bool,
    ) -> Result<(), ClassifyError> {
        for b in bricks {
            if !on(b, self.predict(b)?) {
                break;
            }
        }
        Ok(())
    }
}

/// The [`BrickResult`] of what an accelerator gave for brick `b` (`seconds` of prediction):
/// the probabilities as `q / 255` and the classes as the output labels of `out_labels`.
pub fn brick_result(
    p: AcceleratedBrick,
    labels: &[u32],
    out_labels: &[u16],
    b: &Brick,
    seconds: f64,
) -> Result<BrickResult, ClassifyError> {
    let n = b.voxels();
    if p.probs.len() != n * labels.len() || p.classes.len() != n {
        return Err(ClassifyError::Input(format!(
            "the accelerator gave {} probabilities and {} labels for a brick of {n} voxels and {} \
             classes",
            p.probs.len(),
            p.classes.len(),
            labels.len()
        )));
    }
    let lab = p
        .classes
        .iter()
        .map(|&k| match k {
            BELOW_TAU => 0,
            k => out_labels.get(k as usize).copied().unwrap_or(0),
        })
        .collect();
    Ok(BrickResult {
        proba: p.probs.iter().map(|&q| q as f32 / 255.0).collect(),
        labels: lab,
        skipped: false,
        feature_seconds: 0.0,
        predict_seconds: seconds,
    })
}
