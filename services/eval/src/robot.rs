//! The interactive protocol: a robot user that corrects the prediction slice by slice, as
//! interactive segmentation is evaluated (interactions to reach a target score).
//!
//! It starts from the S1 scribbles. Each round is one slice visit: on one axial slice it
//! draws, for each true class with wrong voxels there (background included), one stroke of
//! that class inside the largest wrong region of that class on the slice, as a user corrects
//! what the slice shows (the simulator likewise scribbles every class a slice shows, so a round
//! is worth one S-level slice). Then the forest is retrained and the volume predicted again
//! (the features come from the warm cache, as in the service), and the result is scored. Which
//! slice is the [`Placement`]:
//!
//! - [`Placement::Largest`]: the axial slice where the largest 6-connected region of wrong
//!   voxels of one true class (missed or wrongly claimed) has the most voxels;
//! - [`Placement::Suggested`]: the slice the product suggests ([`neuvolex_classify::suggest`]:
//!   the doubtful share of each class's extent, damped near the axial slices already
//!   scribbled);
//! - [`Placement::Random`]: a random slice that shows a class.
//!
//! A stroke is straight, through the deepest pixel of the region's cross-section, along the
//! longest of 8 directions, half the region's diameter long each way at most, with the
//! simulator's brush; it is checked to cover only voxels of its true class.

use crate::data::{Dataset, DatasetSpec, TrainedInr};
use crate::oneshot::{check, feature_sets, models_for};
use crate::predict::{predict, score, seeds, train, Features, Prediction};
use crate::{EvalConfig, EvalError, EvalEvent, Events, Method, Prior, Result};
use neuvolex_bricks::rng::Rng;
use neuvolex_classify::cache::FeatureCache;
use neuvolex_classify::components::{
    apply_in_memory, grow_in_memory, label_brick, Partial, PriorConfig,
};
use neuvolex_classify::scribble::{erode, longest_stroke, stroke_length, Axis};
use neuvolex_classify::stable::{agree, near_scribbles, tested, Evidence, StableConfig, Verdicts};
use neuvolex_classify::{
    rasterise, simulate, thicken, BrickFeatures, FeatureSet, Level, Scribbles, SimConfig,
    SliceMass, Stroke, F1,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Where the robot draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Placement {
    /// In the largest 3-D error region, on its largest axial slice.
    Largest,
    /// On the suggested slice.
    Suggested,
    /// On a random slice showing a class.
    Random,
}

impl std::fmt::Display for Placement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Placement::Largest => "largest",
            Placement::Suggested => "suggested",
            Placement::Random => "random",
        })
    }
}

impl std::str::FromStr for Placement {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "largest" => Ok(Placement::Largest),
            "suggested" => Ok(Placement::Suggested),
            "random" => Ok(Placement::Random),
            _ => Err(format!(
                "unknown placement '{s}' (largest, suggested, random)"
            )),
        }
    }
}

/// Settings of the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotConfig {
    /// Rounds after the S1 start.
    pub rounds: usize,
    /// Placements to run.
    pub placements: Vec<Placement>,
    /// Mean F1 targets whose rounds are reported.
    pub targets: Vec<f64>,
    /// Voxels (Chebyshev distance) around a round's new strokes that count as "near" them;
    /// the F1 change beyond is what the stroke changed far from where it was drawn.
    #[serde(default = "default_margin")]
    pub margin: usize,
    /// The stability rule ([`neuvolex_classify::stable`]): beyond the margin, a voxel keeps
    /// its previous label unless the new probabilities prefer the new one by this much
    /// (`None`: every round shows the new labels as they are).
    #[serde(default)]
    pub stable_delta: Option<f32>,
    /// Steps of the rule's ramp inside the margin ([`neuvolex_classify::stable::needed`]; 0:
    /// new labels stand anywhere within the margin).
    #[serde(default = "default_ramp")]
    pub stable_ramp: u8,
    /// Whether the rule also holds the prior's and growth's decisions beyond the margin
    /// ([`neuvolex_classify::StableConfig::prior`]).
    #[serde(default = "default_true")]
    pub stable_prior: bool,
    /// Whether a far change must be confirmed by the forests of the rounds before
    /// ([`neuvolex_classify::StableConfig::confirm`]).
    #[serde(default = "default_confirm")]
    pub stable_confirm: bool,
    /// How many forests in a row a confirmed far change needs
    /// ([`neuvolex_classify::StableConfig::forests`]).
    #[serde(default = "default_forests")]
    pub stable_forests: u8,
    /// Whether growth follows the labels the rule shows
    /// ([`neuvolex_classify::StableConfig::follow`]).
    #[serde(default = "default_follow")]
    pub stable_follow: bool,
}

fn default_follow() -> bool {
    neuvolex_classify::stable::DEFAULT_FOLLOW
}

fn default_forests() -> u8 {
    neuvolex_classify::stable::DEFAULT_FORESTS
}

fn default_confirm() -> bool {
    neuvolex_classify::stable::DEFAULT_CONFIRM
}

fn default_true() -> bool {
    true
}

fn default_ramp() -> u8 {
    neuvolex_classify::stable::DEFAULT_RAMP
}

/// The default margin around a new stroke: the filter bank's halo, the image a scribbled
/// voxel's features see. Beyond it, a voxel shares no image content with the stroke's rows.
pub fn default_margin() -> usize {
    neuvolex_filters::filter_halo()
}

impl Default for RobotConfig {
    fn default() -> Self {
        RobotConfig {
            rounds: 10,
            placements: vec![Placement::Largest],
            targets: vec![0.7, 0.8],
            margin: default_margin(),
            stable_delta: Some(neuvolex_classify::stable::DEFAULT_DELTA),
            stable_ramp: default_ramp(),
            stable_prior: true,
            stable_confirm: default_confirm(),
            stable_forests: default_forests(),
            stable_follow: default_follow(),
        }
    }
}

/// One scored round.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RoundRow {
    /// Dataset.
    pub dataset: String,
    /// Method (features and prior).
    pub method: String,
    /// INR variant (`-` without one).
    pub inr: String,
    /// Where the robot drew.
    pub placement: Placement,
    /// Seed of the S1 start (and of random slices).
    pub seed: u64,
    /// Round (0 = the S1 start).
    pub round: usize,
    /// The strokes this round added (one slice visit; none at round 0).
    pub strokes: Vec<Stroke>,
    /// F1 per ROI class.
    pub f1: Vec<F1>,
    /// Mean F1 over the ROI classes.
    pub mean_f1: f64,
    /// Change of the mean F1 from the previous round (`None` at round 0).
    #[serde(default)]
    pub delta: Option<f64>,
    /// Change of the mean F1 over the voxels farther than the margin from this round's
    /// strokes: the previous and this round's labels scored on the same voxels.
    #[serde(default)]
    pub delta_outside: Option<f64>,
    /// Voxels whose label changed from the previous round.
    #[serde(default)]
    pub changed: u64,
    /// Of which farther than the margin from this round's strokes.
    #[serde(default)]
    pub changed_outside: u64,
    /// What changed the labels beyond the margin ([`attribute`]; `None` at round 0).
    #[serde(default)]
    pub far: Option<FarChanges>,
    /// Scribbled voxels.
    pub scribbled: usize,
    /// The slice the product suggests next (axial).
    pub suggested_slice: Option<usize>,
    /// Seconds of the round's interactive work: training rows, fit, prediction, prior.
    pub seconds: f64,
    /// Of which fitting the forest.
    pub seconds_fit: f64,
    /// Of which predicting the volume.
    pub seconds_predict: f64,
}

/// A round's labels after each stage of the pipeline, before the stability rule.
#[derive(Debug, Clone)]
pub struct Stages {
    /// The forest's labels (its best class where confident, else 0).
    pub raw: Vec<u16>,
    /// After the component prior cleared the components it rejects.
    pub filtered: Vec<u16>,
    /// After the kept labels grew into doubtful voxels: the labels the rule then holds.
    pub grown: Vec<u16>,
}

impl Stages {
    /// The stages of a prediction: the forest's labels, then (with a prior) the component
    /// filter and growth, the steps of [`apply_in_memory`] kept apart.
    pub fn of(
        p: &Prediction,
        dims: [usize; 3],
        brick: usize,
        scr: &Scribbles,
        background: u32,
        prior: Option<&PriorConfig>,
    ) -> Stages {
        let raw = p.labels.clone();
        let Some(cfg) = prior else {
            return Stages {
                filtered: raw.clone(),
                grown: raw.clone(),
                raw,
            };
        };
        let mut filtered = raw.clone();
        apply_in_memory(
            &mut filtered,
            dims,
            brick,
            Some(&p.confidence),
            None,
            &seeds(scr, background),
            &PriorConfig { grow: 0, ..*cfg },
        );
        let mut grown = filtered.clone();
        if cfg.grow > 0 {
            let doubtful: Vec<u16> = raw
                .par_iter()
                .zip(&p.best)
                .map(|(&l, &b)| if l == 0 { b } else { 0 })
                .collect();
            grow_in_memory(&mut grown, &doubtful, dims, cfg.grow);
        }
        Stages {
            raw,
            filtered,
            grown,
        }
    }
}

/// What changed the shown labels beyond the margin of a round's strokes, voxel by voxel: the
/// first stage whose output moved between the two rounds.
///
/// - `forest`: the forest's own label changed (its probabilities moved past the rule);
/// - `prior`: the forest's label stayed, the component filter's verdict flipped (a component
///   kept or dropped because its connectivity or its rivals' mass changed);
/// - `growth`: both stayed, growth into doubtful voxels changed;
/// - `release`: no stage changed, a label the rule held earlier was let go.
///
/// Each cause's `d_*` is the mean F1 change beyond the margin had only its voxels changed.
/// Apart from the causes, `held` counts the far voxels whose round verdict the rule held back
/// (what the round shows is not what the forest, the prior and growth decided), and `d_held` is
/// what showing them would have changed: the far field's price of the rule (positive: holding
/// cost accuracy) or its gain (negative: holding prevented a loss).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct FarChanges {
    /// Voxels changed by the forest.
    pub forest: u64,
    /// Voxels changed by the component prior's verdict.
    pub prior: u64,
    /// Voxels changed by growth.
    pub growth: u64,
    /// Held labels released.
    pub release: u64,
    /// Mean F1 change beyond the margin from the forest's changes alone.
    pub d_forest: f64,
    /// From the prior's alone.
    pub d_prior: f64,
    /// From growth's alone.
    pub d_growth: f64,
    /// From the releases alone.
    pub d_release: f64,
    /// Far voxels whose round verdict the rule held back (shown label ≠ verdict).
    #[serde(default)]
    pub held: u64,
    /// Mean F1 change beyond the margin had the held verdicts been shown instead.
    #[serde(default)]
    pub d_held: f64,
}

/// Attributes the changes beyond the margin (`!close`) from the shown labels `prev` to `now`
/// to the stage that made them ([`FarChanges`]), from the two rounds' [`Stages`], and measures
/// the verdicts (`after.grown`) the rule held back there.
pub fn attribute(
    before: &Stages,
    after: &Stages,
    prev: &[u16],
    now: &[u16],
    close: &[bool],
    truth: &[u32],
    classes: &[u32],
) -> FarChanges {
    // 0 forest, 1 prior, 2 growth, 3 release; 4 unchanged or near.
    let cause: Vec<u8> = (0..now.len())
        .into_par_iter()
        .map(|v| {
            if close[v] || prev[v] == now[v] {
                4
            } else if before.raw[v] != after.raw[v] {
                0
            } else if before.filtered[v] != after.filtered[v] {
                1
            } else if before.grown[v] != after.grown[v] {
                2
            } else {
                3
            }
        })
        .collect();
    let base = mean_f1_outside(prev, truth, close, classes);
    let mut count = [0u64; 4];
    cause
        .iter()
        .filter(|&&c| c < 4)
        .for_each(|&c| count[c as usize] += 1);
    let d: Vec<f64> = (0..4u8)
        .map(|k| {
            if count[k as usize] == 0 {
                return 0.0;
            }
            let only: Vec<u16> = prev
                .iter()
                .zip(now)
                .zip(&cause)
                .map(|((&p, &n), &c)| if c == k { n } else { p })
                .collect();
            mean_f1_outside(&only, truth, close, classes) - base
        })
        .collect();
    // Beyond the margin the round's verdicts as they were, before the rule held any back.
    let shown: Vec<u16> = now
        .iter()
        .zip(&after.grown)
        .zip(close)
        .map(|((&n, &g), &c)| if c { n } else { g })
        .collect();
    let n_held = now.iter().zip(&shown).filter(|(a, b)| a != b).count() as u64;
    let d_held = if n_held == 0 {
        0.0
    } else {
        mean_f1_outside(&shown, truth, close, classes) - mean_f1_outside(now, truth, close, classes)
    };
    FarChanges {
        forest: count[0],
        prior: count[1],
        growth: count[2],
        release: count[3],
        d_forest: d[0],
        d_prior: d[1],
        d_growth: d[2],
        d_release: d[3],
        held: n_held,
        d_held,
    }
}

/// Error label per voxel: `truth + 1` where the prediction differs from the truth, else 0.
pub fn error_labels(truth: &[u32], pred: &[u16]) -> Vec<u16> {
    truth
        .iter()
        .zip(pred)
        .map(|(&t, &p)| {
            if p as u32 != t {
                (t + 1).min(u16::MAX as u32) as u16
            } else {
                0
            }
        })
        .collect()
}

/// The largest 6-connected component of `labels` (brick by brick, merged), as its label and
/// the axial slice where it has the most voxels, with its mask on that slice.
pub fn largest_region(
    labels: &[u16],
    dims: [usize; 3],
    brick: usize,
) -> Option<(u16, usize, Vec<bool>)> {
    let grid = dims.map(|d| d.div_ceil(brick));
    let idx: Vec<[usize; 3]> = (0..grid[2])
        .flat_map(|z| (0..grid[1]).flat_map(move |y| (0..grid[0]).map(move |x| [x, y, z])))
        .collect();
    let gather = |b: [usize; 3]| -> ([usize; 3], [usize; 3]) {
        let o = b.map(|v| v * brick);
        (o, std::array::from_fn(|a| brick.min(dims[a] - o[a])))
    };
    let done: Vec<([usize; 3], Vec<u32>, Partial)> = idx
        .par_iter()
        .map(|&b| {
            let (o, s) = gather(b);
            let mut l = Vec::with_capacity(s.iter().product());
            for z in 0..s[2] {
                for y in 0..s[1] {
                    let row = ((o[2] + z) * dims[1] + o[1] + y) * dims[0] + o[0];
                    l.extend_from_slice(&labels[row..row + s[0]]);
                }
            }
            let (ids, p) = label_brick(b, s, &l, None, &[]);
            (b, ids, p)
        })
        .collect();
    let mut ids_of = Vec::new();
    let mut parts = Vec::new();
    for (b, ids, p) in done {
        ids_of.push((b, ids));
        parts.push(p);
    }
    let merged = Partial::merge_all(parts);
    let (best, c) = merged
        .components
        .iter()
        .enumerate()
        .max_by_key(|(i, c)| (c.voxels, std::cmp::Reverse(*i)))?;
    let best = best as u32;
    let mut per_z = vec![0u64; dims[2]];
    for (b, ids) in &ids_of {
        let part = &merged.bricks[b];
        let (o, s) = gather(*b);
        for (k, &id) in ids.iter().enumerate() {
            if id != 0 && part.local[id as usize - 1] == best {
                per_z[o[2] + k / (s[0] * s[1])] += 1;
            }
        }
    }
    let z = (0..dims[2]).max_by_key(|&z| (per_z[z], std::cmp::Reverse(z)))?;
    let mut mask = vec![false; dims[0] * dims[1]];
    for (b, ids) in &ids_of {
        let (o, s) = gather(*b);
        if z < o[2] || z >= o[2] + s[2] {
            continue;
        }
        let part = &merged.bricks[b];
        let lz = z - o[2];
        for y in 0..s[1] {
            for x in 0..s[0] {
                let id = ids[(lz * s[1] + y) * s[0] + x];
                if id != 0 && part.local[id as usize - 1] == best {
                    mask[(o[1] + y) * dims[0] + o[0] + x] = true;
                }
            }
        }
    }
    Some((c.label, z, mask))
}

/// The largest 4-connected region of one label on an axial slice of error labels (`w x h`),
/// of any label or of `only` that one.
pub fn largest_on_slice(
    err: &[u16],
    w: usize,
    h: usize,
    only: Option<u16>,
) -> Option<(u16, Vec<bool>)> {
    let mut seen = vec![false; w * h];
    let mut best: Option<(usize, u16, Vec<usize>)> = None;
    for s in 0..w * h {
        if err[s] == 0 || seen[s] || only.is_some_and(|o| err[s] != o) {
            continue;
        }
        let l = err[s];
        let mut region = vec![s];
        seen[s] = true;
        let mut k = 0;
        while k < region.len() {
            let i = region[k];
            k += 1;
            let (x, y) = (i % w, i / w);
            let mut visit = |j: usize| {
                if !seen[j] && err[j] == l {
                    seen[j] = true;
                    region.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        if best.as_ref().is_none_or(|b| region.len() > b.0) {
            best = Some((region.len(), l, region));
        }
    }
    let (_, l, region) = best?;
    let mut mask = vec![false; w * h];
    region.iter().for_each(|&i| mask[i] = true);
    Some((l, mask))
}

/// A stroke of `class` on axial slice `z` inside `mask` (`w x h`), through the region's deepest
/// pixel, with the simulator's brush `radius` where the region is wide enough and a thinner
/// one where not; every pixel it paints lies in `mask`.
pub fn stroke_in(
    mask: &[bool],
    w: usize,
    h: usize,
    z: usize,
    class: u32,
    radius: f32,
) -> Option<Stroke> {
    let area = mask.iter().filter(|&&m| m).count();
    if area == 0 {
        return None;
    }
    // The deepest pixels: the last non-empty square erosion.
    let mut deep = mask.to_vec();
    let mut depth = 0;
    loop {
        let next = erode(&deep, w, h, 1);
        if !next.iter().any(|&m| m) {
            break;
        }
        deep = next;
        depth += 1;
    }
    // Of the deepest pixels, the one nearest their centroid.
    let px: Vec<usize> = (0..w * h).filter(|&i| deep[i]).collect();
    let (cx, cy) = px.iter().fold((0.0, 0.0), |(a, b), &i| {
        (a + (i % w) as f64, b + (i / w) as f64)
    });
    let (cx, cy) = (cx / px.len() as f64, cy / px.len() as f64);
    let start = *px.iter().min_by(|&&a, &&b| {
        let d = |i: usize| ((i % w) as f64 - cx).powi(2) + ((i / w) as f64 - cy).powi(2);
        d(a).total_cmp(&d(b))
    })?;
    let s = [(start % w) as f32, (start / w) as f32];
    let dirs: Vec<[f32; 2]> = (0..8)
        .map(|k| {
            let a = k as f32 * std::f32::consts::PI / 8.0;
            [a.cos(), a.sin()]
        })
        .collect();
    let max_len = stroke_length(area);
    let r = radius.max(0.0);
    let tries: Vec<(f32, usize)> = (r.ceil() as usize..=depth)
        .map(|e| (r, e))
        .chain(std::iter::once((0.0, 0)))
        .collect();
    for (rad, e) in tries {
        let walkable = erode(mask, w, h, e);
        if !walkable[start] {
            continue;
        }
        let [p0, _, p1] = longest_stroke(&walkable, w, h, s, max_len, &dirs);
        let stroke = Stroke {
            class,
            axis: Axis::Z,
            slice: z,
            points: vec![p0, s, p1],
            radius: rad,
        };
        let painted = rasterise(std::slice::from_ref(&stroke), [w, h, z + 1]).ok()?;
        let plane = z * w * h;
        if !painted.voxels.is_empty()
            && painted
                .voxels
                .iter()
                .all(|&(i, _)| mask[i as usize - plane])
        {
            return Some(stroke);
        }
    }
    None
}

/// A slice visit: on axial slice `z` of the error labels, one stroke of the true class in the
/// largest wrong region of each true class there (background included), as a user corrects
/// what they see on the slice, the way the simulator scribbles every class a slice shows.
pub fn slice_strokes(
    err: &[u16],
    dims: [usize; 3],
    z: usize,
    background: u32,
    radius: f32,
) -> Vec<Stroke> {
    let (w, h) = (dims[0], dims[1]);
    let plane = &err[z * w * h..(z + 1) * w * h];
    let mut present: Vec<u16> = plane.iter().copied().filter(|&l| l != 0).collect();
    present.sort_unstable();
    present.dedup();
    present
        .into_iter()
        .filter_map(|l| {
            let (_, mask) = largest_on_slice(plane, w, h, Some(l))?;
            let class = if l == 1 { background } else { l as u32 - 1 };
            stroke_in(&mask, w, h, z, class, radius)
        })
        .collect()
}

/// The robot's next round for a prediction: the strokes of one slice visit
/// ([`slice_strokes`]) on the slice the [`Placement`] picks, or none when nothing is wrong.
#[allow(clippy::too_many_arguments)]
pub fn next_strokes(
    truth: &[u32],
    pred: &[u16],
    dims: [usize; 3],
    brick: usize,
    placement: Placement,
    slices: &SliceMass,
    visited: &[usize],
    fg_slices: &[usize],
    rng: &mut Rng,
    background: u32,
    radius: f32,
) -> Vec<Stroke> {
    let err = error_labels(truth, pred);
    let visit = |z: usize| -> Option<Vec<Stroke>> {
        let s = slice_strokes(&err, dims, z, background, radius);
        (!s.is_empty()).then_some(s)
    };
    let order: Vec<usize> = match placement {
        Placement::Largest => match largest_region(&err, dims, brick) {
            Some((_, z, _)) => vec![z],
            None => Vec::new(),
        },
        Placement::Suggested => slices
            .ranked(2, visited)
            .into_iter()
            .map(|(z, _)| z)
            .collect(),
        Placement::Random => {
            let mut order = fg_slices.to_vec();
            rng.shuffle(&mut order);
            order
        }
    };
    order.into_iter().find_map(visit).unwrap_or_default()
}

/// Mean F1 of `labels` over the voxels `skip` leaves out.
pub fn mean_f1_outside(labels: &[u16], truth: &[u32], skip: &[bool], classes: &[u32]) -> f64 {
    let (l, t): (Vec<u16>, Vec<u32>) = labels
        .iter()
        .zip(truth)
        .zip(skip)
        .filter(|(_, &s)| !s)
        .map(|((&l, &t), _)| (l, t))
        .unzip();
    score(&l, &t, classes).1
}

/// How one round's labels moved from the previous round's: the mean F1 change over the voxels
/// not `close` to the round's new strokes ([`near`] them), the voxels changed, and those
/// changed beyond.
pub fn round_change(
    prev: &[u16],
    labels: &[u16],
    truth: &[u32],
    classes: &[u32],
    close: &[bool],
) -> (f64, u64, u64) {
    let delta = mean_f1_outside(labels, truth, close, classes)
        - mean_f1_outside(prev, truth, close, classes);
    let (mut changed, mut far) = (0u64, 0u64);
    for ((a, b), c) in prev.iter().zip(labels).zip(close) {
        if a != b {
            changed += 1;
            far += u64::from(!c);
        }
    }
    (delta, changed, far)
}

/// Axial slices showing a class in the truth.
pub fn foreground_slices(truth: &[u32], dims: [usize; 3]) -> Vec<usize> {
    let sl = dims[0] * dims[1];
    (0..dims[2])
        .filter(|&z| truth[z * sl..(z + 1) * sl].iter().any(|&t| t > 0))
        .collect()
}

/// Runs the robot for every dataset, method, placement and seed; rounds are also sent as
/// events.
pub fn run(cfg: &EvalConfig, rc: &RobotConfig, events: Events) -> Result<Vec<RoundRow>> {
    check(cfg)?;
    if rc.placements.is_empty() {
        return Err(EvalError::Config("no robot placement".into()));
    }
    let radius = SimConfig::default().radius;
    let mut rows = Vec::new();
    for spec in &cfg.datasets {
        let ds = Dataset::prepare(DatasetSpec::parse(spec, &cfg.data)?, &cfg.work)?;
        events(ds.event());
        let models = models_for(cfg, &ds, events)?;
        let dims = ds.store.info().dims;
        let brick = ds.store.info().brick;
        let fg = foreground_slices(&ds.truth, dims);
        let cache = std::sync::Arc::new(FeatureCache::new(cfg.cache_bytes)).for_session("eval");
        for (fname, priors) in feature_sets(&cfg.methods) {
            let set: FeatureSet = fname.parse().map_err(EvalError::Config)?;
            let variants: Vec<Option<&TrainedInr>> = if set.needs_model() {
                models.iter().map(Some).collect()
            } else {
                vec![None]
            };
            for model in variants {
                let fx = BrickFeatures::new(
                    &ds.store,
                    set.clone(),
                    model.map(|m| m.model.clone()),
                    false,
                )?;
                let (inr, epochs) =
                    model.map_or(("-".into(), 0.0), |m| (m.variant.name(), m.variant.epochs));
                let f = Features::new(fx, Some(&cache), format!("{fname}/{inr}/{epochs}"));
                for &prior in &priors {
                    let method = Method {
                        features: fname.clone(),
                        prior,
                    }
                    .to_string();
                    for &placement in &rc.placements {
                        for seed in 0..cfg.seeds {
                            let mut src = ds.truth_source()?;
                            let (mut strokes, _) = simulate(
                                &mut *src,
                                &SimConfig {
                                    level: Level::S1,
                                    seed,
                                    background: cfg.classify.background,
                                    ..SimConfig::default()
                                },
                            )?;
                            let mut rng = Rng::new(seed ^ 0x0B07_u64);
                            let mut added: Vec<Stroke> = Vec::new();
                            let mut prev: Option<(Vec<u16>, f64)> = None;
                            let mut prev_stages: Option<Stages> = None;
                            // Forests in a row behind each voxel's previous forest label.
                            let mut prev_agree: Vec<u16> = Vec::new();
                            for round in 0..=rc.rounds {
                                let scr = rasterise(&thicken(&strokes, cfg.thicken, dims), dims)?;
                                let t0 = Instant::now();
                                let t = train(&f, &scr, &cfg.classify)?;
                                let p = predict(&f, &t.forest, &t.ts, &cfg.classify, events)?;
                                let st = Stages::of(
                                    &p,
                                    dims,
                                    brick,
                                    &scr,
                                    cfg.classify.background,
                                    (prior == Prior::Components).then_some(&cfg.prior),
                                );
                                let mut labels = st.grown.clone();
                                // Near this round's new strokes (none at round 0).
                                let added_scr = match &prev {
                                    None => None,
                                    Some(_) => {
                                        Some(rasterise(&thicken(&added, cfg.thicken, dims), dims)?)
                                    }
                                };
                                let close =
                                    added_scr.as_ref().map(|a| near_scribbles(a, rc.margin));
                                if let (Some(d), Some((pl, _)), Some(a), Some(ps)) =
                                    (rc.stable_delta, &prev, &added_scr, &prev_stages)
                                {
                                    let rule = StableConfig {
                                        margin: rc.margin,
                                        delta: d,
                                        ramp: rc.stable_ramp,
                                        prior: rc.stable_prior,
                                        confirm: rc.stable_confirm,
                                        forests: rc.stable_forests,
                                        follow: rc.stable_follow,
                                    };
                                    let ev = Evidence {
                                        probs: &p.probs,
                                        out_labels: &p.out_labels,
                                        bg: p.out_labels.iter().position(|&o| o == 0),
                                    };
                                    let v = Verdicts {
                                        forest: &st.raw,
                                        forest_before: &ps.raw,
                                        verdict_before: &ps.grown,
                                        agree_before: &prev_agree,
                                    };
                                    rule.hold(&mut labels, pl, &ev, &rule.levels(a), Some(&v));
                                    rule.follow(
                                        &mut labels,
                                        (&st.raw, &st.grown),
                                        dims,
                                        cfg.prior.grow,
                                    );
                                }
                                let seconds = t0.elapsed().as_secs_f64();
                                let visited: Vec<usize> = strokes
                                    .iter()
                                    .filter(|s| s.axis == Axis::Z)
                                    .map(|s| s.slice)
                                    .collect();
                                let (f1, mean_f1) = score(&labels, &ds.truth, &ds.classes);
                                let (delta, delta_outside, changed, changed_outside) =
                                    match (&prev, &close) {
                                        (Some((pl, pf)), Some(close)) => {
                                            let (d, c, far) = round_change(
                                                pl,
                                                &labels,
                                                &ds.truth,
                                                &ds.classes,
                                                close,
                                            );
                                            (Some(mean_f1 - pf), Some(d), c, far)
                                        }
                                        _ => (None, None, 0, 0),
                                    };
                                let far = match (&prev, &prev_stages, &close) {
                                    (Some((pl, _)), Some(ps), Some(close)) => Some(attribute(
                                        ps,
                                        &st,
                                        pl,
                                        &labels,
                                        close,
                                        &ds.truth,
                                        &ds.classes,
                                    )),
                                    _ => None,
                                };
                                let row = RoundRow {
                                    dataset: ds.spec.name.clone(),
                                    method: method.clone(),
                                    inr: inr.clone(),
                                    placement,
                                    seed,
                                    round,
                                    strokes: std::mem::take(&mut added),
                                    f1,
                                    mean_f1,
                                    delta,
                                    delta_outside,
                                    changed,
                                    changed_outside,
                                    far,
                                    scribbled: scr.voxels.len(),
                                    suggested_slice: p.slices.suggest(2, &visited).map(|s| s.slice),
                                    seconds,
                                    seconds_fit: t.seconds_fit,
                                    seconds_predict: p.seconds,
                                };
                                events(EvalEvent::Round(row.clone()));
                                rows.push(row);
                                prev = Some((labels.clone(), mean_f1));
                                prev_agree = match (&prev_stages, &added_scr) {
                                    (Some(ps), Some(a)) => agree(
                                        &st.raw,
                                        &ps.raw,
                                        &prev_agree,
                                        &tested(a, cfg.classify.background),
                                    ),
                                    _ => Vec::new(),
                                };
                                prev_stages = Some(st);
                                if round == rc.rounds {
                                    break;
                                }
                                added = next_strokes(
                                    &ds.truth,
                                    &labels,
                                    dims,
                                    brick,
                                    placement,
                                    &p.slices,
                                    &visited,
                                    &fg,
                                    &mut rng,
                                    cfg.classify.background,
                                    radius,
                                );
                                if added.is_empty() {
                                    break;
                                }
                                strokes.extend(added.iter().cloned());
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(rows)
}

/// Per (dataset, method, INR, placement): mean F1 per round over seeds, and per seed the first
/// round reaching each target.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Summary {
    /// Dataset.
    pub dataset: String,
    /// Method.
    pub method: String,
    /// INR variant.
    pub inr: String,
    /// Placement.
    pub placement: Placement,
    /// Mean F1 over seeds after each round (round 0 = S1).
    pub f1: Vec<f64>,
    /// Per target, per seed: the first round at or above it (`None`: not within the rounds).
    pub rounds_to: Vec<Vec<Option<usize>>>,
    /// Share of rounds (after round 0, all seeds) that lowered the mean F1.
    pub worse: f64,
    /// Share of rounds that lowered the mean F1 by more than [`BIG_DROP`].
    pub big_drops: f64,
    /// The largest drop of the mean F1 in one round (0 when none dropped).
    pub worst_drop: f64,
    /// Mean change of the mean F1 per round beyond the margin around the round's strokes.
    pub mean_delta_outside: f64,
    /// The largest drop beyond the margin (0 when none dropped).
    pub worst_drop_outside: f64,
    /// Share of the changed voxels that lay beyond the margin, over all rounds.
    pub changed_outside: f64,
    /// The far changes of every round added up ([`FarChanges`]; the `d_*` are sums over
    /// rounds).
    #[serde(default)]
    pub far: FarChanges,
    /// Per cause (forest, prior, growth, release): the rounds that dropped the mean F1 by more
    /// than [`BIG_DROP`] whose largest far loss came from that cause.
    #[serde(default)]
    pub drops_by_cause: [usize; 4],
    /// Runs (seeds) whose last round ended below their first (r10 < r0).
    #[serde(default)]
    pub ended_below: usize,
    /// Mean seconds per round (all rounds, all seeds).
    pub seconds: f64,
    /// Mean seconds per round predicting.
    pub seconds_predict: f64,
}

/// A one-round drop of the mean F1 a user notices (the bound for a round).
pub const BIG_DROP: f64 = 0.02;

/// Summarises round rows against `targets`.
pub fn summarise(rows: &[RoundRow], targets: &[f64]) -> Vec<Summary> {
    let mut keys: Vec<(String, String, String, Placement)> = Vec::new();
    for r in rows {
        let k = (
            r.dataset.clone(),
            r.method.clone(),
            r.inr.clone(),
            r.placement,
        );
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    keys.into_iter()
        .map(|(dataset, method, inr, placement)| {
            let sel: Vec<&RoundRow> = rows
                .iter()
                .filter(|r| {
                    r.dataset == dataset
                        && r.method == method
                        && r.inr == inr
                        && r.placement == placement
                })
                .collect();
            let mut seeds: Vec<u64> = sel.iter().map(|r| r.seed).collect();
            seeds.sort_unstable();
            seeds.dedup();
            let rounds = sel.iter().map(|r| r.round).max().unwrap_or(0);
            // A seed that stopped early (nothing wrong) keeps its last score.
            let at = |seed: u64, round: usize| -> f64 {
                sel.iter()
                    .filter(|r| r.seed == seed && r.round <= round)
                    .max_by_key(|r| r.round)
                    .map_or(0.0, |r| r.mean_f1)
            };
            let f1 = (0..=rounds)
                .map(|k| seeds.iter().map(|&s| at(s, k)).sum::<f64>() / seeds.len() as f64)
                .collect();
            let rounds_to = targets
                .iter()
                .map(|&t| {
                    seeds
                        .iter()
                        .map(|&s| (0..=rounds).find(|&k| at(s, k) >= t))
                        .collect()
                })
                .collect();
            let n = sel.len().max(1) as f64;
            let deltas: Vec<f64> = sel.iter().filter_map(|r| r.delta).collect();
            let outside: Vec<f64> = sel.iter().filter_map(|r| r.delta_outside).collect();
            let share = |k: usize| k as f64 / deltas.len().max(1) as f64;
            let (changed, far) = sel.iter().fold((0u64, 0u64), |(a, b), r| {
                (a + r.changed, b + r.changed_outside)
            });
            let mut sum = FarChanges::default();
            let mut drops_by_cause = [0usize; 4];
            for r in &sel {
                let Some(f) = r.far else { continue };
                sum.forest += f.forest;
                sum.prior += f.prior;
                sum.growth += f.growth;
                sum.release += f.release;
                sum.d_forest += f.d_forest;
                sum.d_prior += f.d_prior;
                sum.d_growth += f.d_growth;
                sum.d_release += f.d_release;
                sum.held += f.held;
                sum.d_held += f.d_held;
                if r.delta.is_some_and(|d| d < -BIG_DROP) {
                    let d = [f.d_forest, f.d_prior, f.d_growth, f.d_release];
                    let k = (0..4).min_by(|&a, &b| d[a].total_cmp(&d[b])).unwrap_or(0);
                    drops_by_cause[k] += 1;
                }
            }
            let ended_below = seeds.iter().filter(|&&s| at(s, rounds) < at(s, 0)).count();
            Summary {
                far: sum,
                drops_by_cause,
                ended_below,
                worse: share(deltas.iter().filter(|&&d| d < 0.0).count()),
                big_drops: share(deltas.iter().filter(|&&d| d < -BIG_DROP).count()),
                worst_drop: -deltas.iter().copied().fold(0.0, f64::min),
                mean_delta_outside: outside.iter().sum::<f64>() / outside.len().max(1) as f64,
                worst_drop_outside: -outside.iter().copied().fold(0.0, f64::min),
                changed_outside: far as f64 / changed.max(1) as f64,
                dataset,
                method,
                inr,
                placement,
                f1,
                rounds_to,
                seconds: sel.iter().map(|r| r.seconds).sum::<f64>() / n,
                seconds_predict: sel.iter().map(|r| r.seconds_predict).sum::<f64>() / n,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_change_scores_beyond_the_margin() {
        let d = [9, 7, 6];
        let n: usize = d.iter().product();
        let at = |x: usize, y: usize, z: usize| (z * d[1] + y) * d[0] + x;
        // Truth: class 1 at x < 4. The previous labels miss it near the stroke (x = 0..2,
        // z = 0) and claim it far away (x = 8, z = 5); the new labels fix the near miss and
        // add a far error (x = 3, z = 5 lost): only the far change counts beyond the margin.
        let truth: Vec<u32> = (0..n).map(|i| u32::from(i % d[0] < 4)).collect();
        let mut prev: Vec<u16> = truth.iter().map(|&t| t as u16).collect();
        for y in 0..d[1] {
            for x in 0..3 {
                prev[at(x, y, 0)] = 0;
            }
            prev[at(8, y, 5)] = 1;
        }
        let mut next = prev.clone();
        for y in 0..d[1] {
            for x in 0..3 {
                next[at(x, y, 0)] = 1;
            }
            next[at(3, y, 5)] = 0;
        }
        let stroke: Vec<u64> = (0..d[1])
            .flat_map(|y| (0..3).map(move |x| (y * d[0] + x) as u64))
            .collect();
        let close = near_scribbles(
            &neuvolex_classify::Scribbles {
                dims: d,
                voxels: stroke.iter().map(|&i| (i, 1)).collect(),
            },
            2,
        );
        let (delta, changed, far) = round_change(&prev, &next, &truth, &[1], &close);
        assert_eq!(changed, 3 * 7 + 7);
        assert_eq!(far, 7, "the x = 3 column of z = 5");
        assert!(
            delta < 0.0,
            "beyond the margin the round only lost: {delta}"
        );
        let (lo, hi) = (
            mean_f1_outside(&prev, &truth, &close, &[1]),
            mean_f1_outside(&next, &truth, &close, &[1]),
        );
        assert!((delta - (hi - lo)).abs() < 1e-12);
        // With nothing beyond the margin changed, the change there is 0.
        let (delta, _, far) = round_change(&prev, &prev, &truth, &[1], &close);
        assert_eq!((delta, far), (0.0, 0));
    }

    #[test]
    fn far_changes_are_attributed_to_the_stage_that_made_them() {
        // Six voxels in a row, all far from the strokes but the last; class 1 truth on 0..3.
        let truth = [1u32, 1, 1, 0, 0, 0];
        let before = Stages {
            raw: vec![1, 0, 1, 0, 0, 0],
            filtered: vec![1, 0, 0, 0, 0, 0],
            grown: vec![1, 0, 0, 1, 0, 0],
        };
        let after = Stages {
            // 0: the forest's label changed (1 -> 0); 2: the prior's verdict flipped (kept
            // now); 3: growth stopped; 4: nothing changed, a held label let go; 5: near.
            raw: vec![0, 0, 1, 0, 0, 1],
            filtered: vec![0, 0, 1, 0, 0, 1],
            grown: vec![0, 0, 1, 0, 0, 1],
        };
        let prev = [1u16, 0, 0, 1, 1, 0];
        let now = [0u16, 0, 1, 0, 0, 1];
        let close = [false, false, false, false, false, true];
        let f = attribute(&before, &after, &prev, &now, &close, &truth, &[1]);
        assert_eq!((f.forest, f.prior, f.growth, f.release), (1, 1, 1, 1));
        // The forest lost a true voxel, the prior found one, growth and the release removed
        // false ones: each cause's F1 change has its sign.
        assert!(f.d_forest < 0.0 && f.d_prior > 0.0, "{f:?}");
        assert!(f.d_growth > 0.0 && f.d_release > 0.0, "{f:?}");
        // The round showed its verdicts: nothing held back.
        assert_eq!((f.held, f.d_held), (0, 0.0));
        // Nothing changed: nothing attributed.
        let none = attribute(&after, &after, &now, &now, &close, &truth, &[1]);
        assert_eq!(none, FarChanges::default());
        // What the round showed, the verdicts held back, and the sign of the far F1 change
        // showing them would make: voxel 0 held at its true 1 against the forest's 0 (holding
        // saved F1), voxel 2 held at 0 against the prior's true 1 (holding cost F1), and a
        // verdict held near the strokes (not counted).
        for (shown, held, sign) in [
            ([1u16, 0, 1, 0, 0, 1], 1, -1.0),
            ([0, 0, 0, 0, 0, 1], 1, 1.0),
            ([0, 0, 1, 0, 0, 0], 0, 0.0),
        ] {
            let f = attribute(&before, &after, &prev, &shown, &close, &truth, &[1]);
            assert_eq!(f.held, held, "{shown:?}");
            assert!(
                if sign == 0.0 {
                    f.d_held == 0.0
                } else {
                    f.d_held * sign > 0.0
                },
                "{shown:?}: {f:?}"
            );
        }
    }

    #[test]
    fn summaries_count_worse_rounds_and_drops() {
        let row = |seed: u64, round: usize, f: f64, d: Option<f64>, o: Option<f64>| RoundRow {
            dataset: "d".into(),
            method: "m".into(),
            inr: "-".into(),
            placement: Placement::Largest,
            seed,
            round,
            strokes: Vec::new(),
            f1: Vec::new(),
            mean_f1: f,
            delta: d,
            delta_outside: o,
            changed: 10,
            changed_outside: 5 * u64::from(round > 0),
            far: None,
            scribbled: 0,
            suggested_slice: None,
            seconds: 1.0,
            seconds_fit: 0.5,
            seconds_predict: 0.5,
        };
        let rows = vec![
            row(0, 0, 0.5, None, None),
            row(0, 1, 0.6, Some(0.1), Some(0.01)),
            row(0, 2, 0.57, Some(-0.03), Some(-0.04)),
            row(1, 0, 0.4, None, None),
            row(1, 1, 0.39, Some(-0.01), Some(0.0)),
            row(1, 2, 0.5, Some(0.11), Some(0.03)),
        ];
        let s = &summarise(&rows, &[0.55])[0];
        assert_eq!(s.worse, 0.5);
        assert_eq!(s.big_drops, 0.25);
        assert!((s.worst_drop - 0.03).abs() < 1e-12);
        assert!((s.worst_drop_outside - 0.04).abs() < 1e-12);
        assert!((s.mean_delta_outside - 0.0).abs() < 1e-12);
        assert!((s.changed_outside - 20.0 / 60.0).abs() < 1e-12);
        assert_eq!(s.rounds_to, vec![vec![Some(1), None]]);
    }

    #[test]
    fn strokes_stay_inside_their_region() {
        // An L-shaped region and a thin line: every painted pixel lies inside.
        let (w, h) = (30, 20);
        let mut mask = vec![false; w * h];
        for y in 2..18 {
            for x in 3..9 {
                mask[y * w + x] = true;
            }
        }
        for y in 12..18 {
            for x in 3..25 {
                mask[y * w + x] = true;
            }
        }
        let s = stroke_in(&mask, w, h, 4, 7, 1.0).unwrap();
        assert_eq!((s.class, s.slice, s.radius), (7, 4, 1.0));
        let painted = rasterise(std::slice::from_ref(&s), [w, h, 5]).unwrap();
        assert!(painted.voxels.len() > 10);
        assert!(painted
            .voxels
            .iter()
            .all(|&(i, _)| mask[i as usize - 4 * w * h]));
        let mut line = vec![false; w * h];
        (5..20).for_each(|x| line[10 * w + x] = true);
        let s = stroke_in(&line, w, h, 0, 2, 1.0).unwrap();
        assert_eq!(s.radius, 0.0);
        let painted = rasterise(std::slice::from_ref(&s), [w, h, 1]).unwrap();
        assert!(!painted.voxels.is_empty());
        assert!(painted.voxels.iter().all(|&(i, _)| line[i as usize]));
        assert!(stroke_in(&vec![false; w * h], w, h, 0, 1, 1.0).is_none());
    }

    #[test]
    fn the_largest_error_region_and_its_slice() {
        // Truth: class 1 in a box; prediction misses part of it and adds a small false blob.
        let d = [20, 16, 12];
        let n: usize = d.iter().product();
        let at = |x: usize, y: usize, z: usize| (z * d[1] + y) * d[0] + x;
        let mut truth = vec![0u32; n];
        let mut pred = vec![0u16; n];
        for z in 2..10 {
            for y in 2..12 {
                for x in 2..12 {
                    truth[at(x, y, z)] = 1;
                    // Predicted except a slab x >= 8 that widens towards z = 7.
                    if x < 8 || (z != 7 && x < 10) {
                        pred[at(x, y, z)] = 1;
                    }
                }
            }
        }
        pred[at(16, 14, 3)] = 1;
        let err = error_labels(&truth, &pred);
        assert_eq!(err[at(16, 14, 3)], 1, "false positive on background");
        assert_eq!(err[at(11, 5, 5)], 2, "missed class 1");
        for bs in [4, 8, 64] {
            let (l, z, mask) = largest_region(&err, d, bs).unwrap();
            assert_eq!((l, z), (2, 7), "brick {bs}");
            assert_eq!(mask.iter().filter(|&&m| m).count(), 4 * 10);
        }
        let slices = SliceMass::zeros(d, 2);
        let mut rng = Rng::new(1);
        let s = next_strokes(
            &truth,
            &pred,
            d,
            8,
            Placement::Largest,
            &slices,
            &[],
            &[],
            &mut rng,
            255,
            1.0,
        );
        assert_eq!(s.len(), 1, "one wrong class on slice 7: {s:?}");
        assert_eq!((s[0].class, s[0].slice), (1, 7));
        // A slice with a missed part and a false blob gets a stroke for each.
        let s3 = slice_strokes(&err, d, 3, 255, 0.0);
        let classes: Vec<u32> = s3.iter().map(|s| s.class).collect();
        assert_eq!(classes, vec![255, 1], "{s3:?}");
        // Nothing wrong: no stroke.
        let t16: Vec<u16> = truth.iter().map(|&t| t as u16).collect();
        assert!(next_strokes(
            &truth,
            &t16,
            d,
            8,
            Placement::Largest,
            &slices,
            &[],
            &[],
            &mut rng,
            255,
            1.0
        )
        .is_empty());
    }
}
