//! Interactive assistance over a session's streamed probabilities: the spatial prior (the
//! component filter of `neuvolex_classify::components`, a toggle) and the next-slice
//! suggestion (`neuvolex_classify::suggest`). Both run the library's per-brick functions over
//! the probability bricks; the raw probabilities stay as they are, the prior's verdict is kept
//! beside them.

use crate::error::{ApiError, ApiResult};
use crate::session::{Probs, Session, BACKGROUND};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::components::{grow_in_memory, label_brick, Partial, PriorConfig};
use neuvolex_classify::suggest::SliceMass;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// Per brick, the sorted local voxel indices the prior relabels, with their new labels.
pub type PriorChanges = HashMap<[usize; 3], Arc<Vec<(u32, u16)>>>;

/// The prior's verdict on one classification.
#[derive(Debug, Clone, Default)]
pub struct PriorState {
    /// The probabilities' generation it was computed from.
    pub generation: u64,
    /// Per brick, the (sorted) local voxel indices whose label the prior changes, with the
    /// label it gives them: 0 where it clears a dropped part, the class where a kept part grew.
    /// Shared, so [`active_prior`]'s copy (taken per brick the label view loads) is cheap.
    pub changed: Arc<PriorChanges>,
    /// What it did.
    pub summary: PriorSummary,
}

/// Components kept and dropped by the prior, and voxels cleared.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct PriorSummary {
    /// Whether labels are filtered.
    pub enabled: bool,
    /// Generation of the verdict (0 before any).
    pub generation: u64,
    /// Connected components of ROI labels.
    pub components: usize,
    /// Of which kept.
    pub kept: usize,
    /// Voxels whose label was cleared.
    pub voxels_cleared: u64,
    /// Doubtful voxels the kept parts grew into.
    pub voxels_grown: u64,
    /// Voxels that kept the label the previous round showed (the stability rule): far from
    /// the new strokes, where the new probabilities did not clearly prefer a change.
    pub voxels_held: u64,
}

/// What the last complete classification showed, per brick, and what it was made from.
#[derive(Debug, Clone)]
pub struct Shown {
    /// The strokes it was classified from.
    pub strokes: Vec<neuvolex_classify::Stroke>,
    /// Its feature set and model version.
    pub features: String,
    /// The labels shown per brick (after the prior, growth and the stability rule).
    pub labels: HashMap<[usize; 3], Vec<u16>>,
}

impl PriorState {
    /// The label the prior gives voxel `p`, where it changes the forest's (`Some(0)`: cleared).
    pub fn label(&self, store: &BrickStore, p: [usize; 3]) -> Option<u16> {
        let b = store.info().brick;
        let br = store.brick(p.map(|v| v / b)).ok()?;
        let c = self.changed.get(&br.index)?;
        let l = [0, 1, 2].map(|k| p[k] - br.origin[k]);
        let i = ((l[2] * br.size[1] + l[1]) * br.size[0] + l[0]) as u32;
        c.binary_search_by_key(&i, |&(v, _)| v).ok().map(|k| c[k].1)
    }
}

/// The most probable class of a voxel's u8 probabilities, whatever its probability (0 when the
/// background is most probable), and that probability.
fn best_of(ids: &[u32], px: &[u8]) -> (u32, u8) {
    let (k, &m) = px
        .iter()
        .enumerate()
        .max_by_key(|(_, &v)| v)
        .unwrap_or((0, &0));
    match ids.get(k) {
        Some(&id) if id != BACKGROUND => (id, m),
        _ => (0, m),
    }
}

/// The label of a voxel's u8 probabilities: the best class when it reaches 0.5 and is not
/// background, else 0 (as the overlays and exports show it).
pub fn label_of(ids: &[u32], px: &[u8]) -> u32 {
    match best_of(ids, px) {
        (id, m) if m >= 128 => id,
        _ => 0,
    }
}

/// The label channels the 3-D label view draws: the classified classes, then the background
/// (which also takes unlabelled voxels) as the last channel, the faint intensity context.
pub fn label_channels(ids: &[u32]) -> Vec<u32> {
    let mut out: Vec<u32> = ids.iter().copied().filter(|&i| i != BACKGROUND).collect();
    out.push(BACKGROUND);
    out
}

/// One brick's current labels as one-hot channels over `channels` ([`label_channels`]): 255 on
/// the channel of each voxel's label ([`label_of`] of its probabilities `px`, `ids.len()` per
/// voxel, then the prior's `changes` where it is on), 0 elsewhere; label 0 goes to the
/// background channel.
pub fn one_hot_labels(
    ids: &[u32],
    px: &[u8],
    changes: Option<&[(u32, u16)]>,
    channels: &[u32],
) -> Vec<u8> {
    let (c, ch) = (ids.len().max(1), channels.len());
    let n = px.len() / c;
    let bg = channels.iter().position(|&i| i == BACKGROUND).unwrap_or(0);
    let slot = |l: u32| {
        if l == 0 {
            bg
        } else {
            channels.iter().position(|&i| i == l).unwrap_or(bg)
        }
    };
    // Probability channel → label channel (the background's goes to the context channel).
    let by_id: Vec<usize> = ids.iter().map(|&i| slot(i)).collect();
    let mut out = vec![0u8; n * ch];
    for (v, p) in px.chunks_exact(c).enumerate() {
        // The most probable channel, picked as `label_of` picks it (ties: the last).
        let (best, &m) = p
            .iter()
            .enumerate()
            .max_by_key(|(_, &q)| q)
            .unwrap_or((0, &0));
        let k = if m >= 128 { by_id[best] } else { bg };
        out[v * ch + k] = 255;
    }
    for &(v, l) in changes.unwrap_or(&[]) {
        let v = v as usize;
        if v < n {
            out[v * ch..(v + 1) * ch].fill(0);
            out[v * ch + slot(l as u32)] = 255;
        }
    }
    out
}

/// Computes the prior over every classified brick of `probs` with the session's scribbles:
/// components per brick, merged, filtered; then growth (`PriorConfig::grow`) over the label
/// volume assembled in memory (2 bytes a voxel, with as much again for the doubtful classes).
pub fn compute_prior(s: &Session, probs: &Probs) -> ApiResult<PriorState> {
    let cfg = PriorConfig::default();
    let scr = s.scribbles()?;
    let dims = s.store.info().dims;
    let bs = s.store.info().brick;
    let mut seeds: BTreeMap<[usize; 3], Vec<(usize, u16)>> = BTreeMap::new();
    for &(i, l) in &scr.voxels {
        if l == BACKGROUND {
            continue;
        }
        let i = i as usize;
        let p = [
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        ];
        let br = s.store.brick(p.map(|v| v / bs))?;
        let li = ((p[2] - br.origin[2]) * br.size[1] + p[1] - br.origin[1]) * br.size[0] + p[0]
            - br.origin[0];
        seeds.entry(br.index).or_default().push((li, l as u16));
    }
    let c = probs.ids.len().max(1);
    let none = Vec::new();
    type Labelled = ([usize; 3], Vec<u16>, Vec<u32>, Partial);
    let done: Vec<Labelled> = probs
        .bricks
        .par_iter()
        .map(|(idx, v)| -> ApiResult<_> {
            let b = s.store.brick(*idx)?;
            let mut labels = Vec::with_capacity(b.voxels());
            let mut conf = Vec::with_capacity(b.voxels());
            for px in v.chunks_exact(c) {
                let l = label_of(&probs.ids, px);
                labels.push(l.min(u16::MAX as u32) as u16);
                conf.push(px.iter().copied().max().unwrap_or(0) as f32 / 255.0);
            }
            let (ids, part) = label_brick(
                *idx,
                b.size,
                &labels,
                Some(&conf),
                seeds.get(idx).unwrap_or(&none),
            );
            Ok((*idx, labels, ids, part))
        })
        .collect::<ApiResult<_>>()?;
    let mut ids_of = Vec::with_capacity(done.len());
    let mut parts = Vec::with_capacity(done.len());
    for (b, labels, ids, p) in done {
        ids_of.push((b, labels, ids));
        parts.push(p);
    }
    let merged = Partial::merge_all(parts);
    let keep = merged.keep(&cfg);
    // The filtered labels per brick (raw labels with dropped parts cleared).
    let mut filtered: HashMap<[usize; 3], (Vec<u16>, Vec<u16>)> = HashMap::new();
    let mut voxels_cleared = 0;
    for (b, raw, ids) in ids_of {
        let part = &merged.bricks[&b];
        let mut l = raw.clone();
        for (v, &id) in l.iter_mut().zip(&ids) {
            if id != 0 && !keep[part.local[id as usize - 1] as usize] {
                *v = 0;
                voxels_cleared += 1;
            }
        }
        filtered.insert(b, (raw, l));
    }
    if cfg.grow > 0 {
        grow_bricks(s, probs, &mut filtered, cfg.grow)?;
    }
    let voxels_held = hold_shown(s, probs, &mut filtered)?;
    let mut changed = HashMap::new();
    let mut voxels_grown = 0;
    for (b, (raw, l)) in filtered {
        let v: Vec<(u32, u16)> = raw
            .iter()
            .zip(&l)
            .enumerate()
            .filter(|(_, (a, b))| a != b)
            .map(|(i, (_, &b))| (i as u32, b))
            .collect();
        voxels_grown += v.iter().filter(|&&(_, l)| l != 0).count() as u64;
        if !v.is_empty() {
            changed.insert(b, Arc::new(v));
        }
    }
    Ok(PriorState {
        generation: probs.generation,
        changed: Arc::new(changed),
        summary: PriorSummary {
            enabled: true,
            generation: probs.generation,
            components: keep.len(),
            kept: keep.iter().filter(|&&k| k).count(),
            voxels_cleared,
            voxels_grown,
            voxels_held,
        },
    })
}

/// The stability rule over the filtered labels (`filtered[brick].1`): where the previous
/// complete classification of this session came from the same features and a prefix of the
/// current strokes, a voxel farther than the margin from the strokes added since keeps the
/// label shown then unless the new probabilities prefer its new label by the rule's `delta`
/// ([`neuvolex_classify::stable`]). Records what is shown now for the next round; returns the voxels held.
fn hold_shown(
    s: &Session,
    probs: &Probs,
    filtered: &mut HashMap<[usize; 3], (Vec<u16>, Vec<u16>)>,
) -> ApiResult<u64> {
    use neuvolex_classify::stable::{delta_u8, near_scribbles, stick, StableConfig};
    let strokes = s.strokes.read().unwrap_or_else(|p| p.into_inner()).clone();
    let (set, model) = s.feature_source()?;
    let features = format!("{set}/{}", model.as_ref().map_or(0, |m| m.0));
    let cfg = StableConfig::default();
    let mut shown = s.shown.lock().unwrap_or_else(|p| p.into_inner());
    let mut held = 0;
    if let Some(prev) = shown
        .as_ref()
        .filter(|p| p.features == features && strokes.starts_with(&p.strokes))
    {
        let d = s.store.info().dims;
        let new = neuvolex_classify::rasterise(&strokes[prev.strokes.len()..], d)
            .map_err(|e| ApiError::BadRequest(e.to_string()))?;
        let close = near_scribbles(&new, cfg.margin);
        let out = neuvolex_classify::output_labels(&probs.ids, BACKGROUND);
        let bg = probs.ids.iter().position(|&i| i == BACKGROUND);
        let delta = delta_u8(cfg.delta);
        for (idx, (_, l)) in filtered.iter_mut() {
            let (Some(before), Some(px)) = (prev.labels.get(idx), probs.bricks.get(idx)) else {
                continue;
            };
            let b = s.store.brick(*idx)?;
            let (w, c) = (b.size[0], out.len().max(1));
            // A row of the brick is a span of the volume's near-the-strokes mask.
            for (k, row) in b.rows(d).enumerate() {
                let r = k * w..(k + 1) * w;
                held += stick(
                    &mut l[r.clone()],
                    &before[r.clone()],
                    &px[r.start * c..r.end * c],
                    &out,
                    bg,
                    &close[row..row + w],
                    delta,
                );
            }
        }
    }
    *shown = Some(Shown {
        strokes,
        features,
        labels: filtered.iter().map(|(k, (_, l))| (*k, l.clone())).collect(),
    });
    Ok(held)
}

/// Grows the filtered labels (`filtered[brick].1`) `steps` voxels into doubtful voxels (raw
/// label 0) whose most probable class is theirs, over the volume assembled in memory.
fn grow_bricks(
    s: &Session,
    probs: &Probs,
    filtered: &mut HashMap<[usize; 3], (Vec<u16>, Vec<u16>)>,
    steps: u32,
) -> ApiResult<()> {
    let d = s.store.info().dims;
    let c = probs.ids.len().max(1);
    let n: usize = d.iter().product();
    // Per brick, in parallel: each doubtful voxel's most probable class (0 elsewhere).
    let local: Vec<([usize; 3], Vec<u16>)> = filtered
        .par_iter()
        .map(|(idx, (raw, _))| {
            let px = &probs.bricks[idx];
            let doubtful = raw
                .iter()
                .zip(px.chunks_exact(c))
                .map(|(&r, p)| {
                    if r == 0 {
                        best_of(&probs.ids, p).0.min(u16::MAX as u32) as u16
                    } else {
                        0
                    }
                })
                .collect();
            (*idx, doubtful)
        })
        .collect();
    // Assembled row by row into the volume, grown, and cut back into the bricks.
    let (mut labels, mut doubtful) = (vec![0u16; n], vec![0u16; n]);
    for (idx, dl) in &local {
        let b = s.store.brick(*idx)?;
        let l = &filtered[idx].1;
        for (k, row) in b.rows(d).enumerate() {
            let r = k * b.size[0]..(k + 1) * b.size[0];
            labels[row..row + b.size[0]].copy_from_slice(&l[r.clone()]);
            doubtful[row..row + b.size[0]].copy_from_slice(&dl[r]);
        }
    }
    grow_in_memory(&mut labels, &doubtful, d, steps);
    filtered
        .par_iter_mut()
        .try_for_each(|(idx, (_, l))| -> ApiResult<()> {
            let b = s.store.brick(*idx)?;
            for (k, row) in b.rows(d).enumerate() {
                l[k * b.size[0]..(k + 1) * b.size[0]]
                    .copy_from_slice(&labels[row..row + b.size[0]]);
            }
            Ok(())
        })
}

/// Recomputes the session's prior verdict once its probabilities are complete (called when a
/// classification finishes, and when the prior is switched on).
pub fn refresh_prior(s: &Session) -> ApiResult<PriorSummary> {
    let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
    let total = s.store.bricks().count();
    let enabled = s.prior_enabled();
    if !enabled || probs.ids.is_empty() || probs.bricks.len() < total {
        return Ok(prior_summary(s));
    }
    let st = compute_prior(s, &probs)?;
    drop(probs);
    let sum = st.summary;
    *s.prior.write().unwrap_or_else(|p| p.into_inner()) = Some(st);
    Ok(sum)
}

/// What the prior does now.
pub fn prior_summary(s: &Session) -> PriorSummary {
    let mut sum = s
        .prior
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .as_ref()
        .map(|p| p.summary)
        .unwrap_or_default();
    sum.enabled = s.prior_enabled();
    sum
}

/// The verdict that applies to the current probabilities, when the prior is on.
pub fn active_prior(s: &Session, probs: &Probs) -> Option<PriorState> {
    if !s.prior_enabled() {
        return None;
    }
    s.prior
        .read()
        .unwrap_or_else(|p| p.into_inner())
        .as_ref()
        .filter(|p| p.generation == probs.generation)
        .cloned()
}

/// Every brick's probabilities, or a conflict while classification has not reached them all.
pub fn complete_probs(s: &Session) -> ApiResult<std::sync::RwLockReadGuard<'_, Probs>> {
    let p = s.probs.read().unwrap_or_else(|p| p.into_inner());
    let total = s.store.bricks().count();
    if p.ids.is_empty() || p.bricks.len() < total {
        return Err(ApiError::Conflict(format!(
            "classification has reached {} of {total} bricks: scribble two classes and wait \
             for it to finish",
            p.bricks.len()
        )));
    }
    Ok(p)
}

/// One u8 per voxel of the volume (x fastest), computed by `f` from each voxel's class
/// probabilities once every brick is classified.
pub fn per_voxel(s: &Session, f: impl Fn(&Probs, &[u8]) -> u8) -> ApiResult<Vec<u8>> {
    let d = s.store.info().dims;
    let p = complete_probs(s)?;
    let c = p.ids.len();
    let mut out = vec![0u8; d.iter().product()];
    for (idx, v) in &p.bricks {
        let b = s.store.brick(*idx)?;
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                let row = ((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0] + b.origin[0];
                for x in 0..b.size[0] {
                    let i = (z * b.size[1] + y) * b.size[0] + x;
                    out[row + x] = f(&p, &v[i * c..(i + 1) * c]);
                }
            }
        }
    }
    Ok(out)
}

/// The arg-max label of every voxel (0 where the background wins or no class reaches 0.5),
/// with the spatial prior's changes when it is on (dropped parts cleared, kept parts grown).
pub fn label_voxels(s: &Session) -> ApiResult<Vec<u8>> {
    let mut out = per_voxel(s, |p, px| label_of(&p.ids, px) as u8)?;
    let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
    if let Some(pr) = active_prior(s, &probs) {
        let d = s.store.info().dims;
        for (idx, changed) in pr.changed.iter() {
            let b = s.store.brick(*idx)?;
            for &(i, l) in changed.iter() {
                let i = i as usize;
                let (x, y, z) = (
                    i % b.size[0],
                    (i / b.size[0]) % b.size[1],
                    i / (b.size[0] * b.size[1]),
                );
                out[((b.origin[2] + z) * d[1] + b.origin[1] + y) * d[0] + b.origin[0] + x] =
                    l as u8;
            }
        }
    }
    Ok(out)
}

/// The slices to scribble next: for each axis, the slice with the best score
/// (`neuvolex_classify::suggest`: the doubtful share of each class's extent, damped near the
/// slices already scribbled) over the bricks classified so far.
pub fn suggest(s: &Session) -> ApiResult<serde_json::Value> {
    let probs = s.probs.read().unwrap_or_else(|p| p.into_inner());
    if probs.ids.is_empty() || probs.bricks.is_empty() {
        return Err(ApiError::Conflict(
            "nothing is classified yet: scribble two classes first".into(),
        ));
    }
    let dims = s.store.info().dims;
    let c = probs.ids.len();
    let mass = probs
        .bricks
        .par_iter()
        .map(|(idx, v)| -> ApiResult<SliceMass> {
            let b = s.store.brick(*idx)?;
            Ok(SliceMass::of_brick(dims, b.origin, b.size, v, c))
        })
        .try_reduce(
            || SliceMass::zeros(dims, c),
            |mut a, b| {
                a.merge(&b);
                Ok(a)
            },
        )?;
    let total = s.store.bricks().count();
    // The slices the user already visited, per axis: their neighbourhoods are damped.
    let mut visited: [Vec<usize>; 3] = Default::default();
    for st in s.strokes.read().unwrap_or_else(|p| p.into_inner()).iter() {
        visited[st.axis as usize].push(st.slice);
    }
    let per_axis: Vec<_> = (0..3)
        .filter_map(|a| mass.suggest(a, &visited[a]))
        .collect();
    Ok(serde_json::json!({
        "generation": probs.generation,
        "bricks": probs.bricks.len(),
        "total_bricks": total,
        "axial": mass.suggest(2, &visited[2]),
        "suggestions": per_axis,
    }))
}

#[cfg(test)]
mod label_tests {
    use super::*;

    #[test]
    fn one_hot_labels_follow_the_half_rule_and_the_prior() {
        let ids = [1, 2, BACKGROUND];
        let channels = label_channels(&ids);
        assert_eq!(channels, vec![1, 2, BACKGROUND]);
        // Voxels: class 1 sure; class 2 at 0.5; background best; nobody above 0.5 (unlabelled).
        let px = [230, 20, 5, 30, 128, 97, 10, 40, 205, 100, 90, 65];
        let h = one_hot_labels(&ids, &px, None, &channels);
        assert_eq!(h, vec![255, 0, 0, 0, 255, 0, 0, 0, 255, 0, 0, 255]);
        // The prior clears voxel 0 and grows class 1 into voxel 3.
        let h = one_hot_labels(&ids, &px, Some(&[(0, 0), (3, 1)]), &channels);
        assert_eq!(h, vec![0, 0, 255, 0, 255, 0, 0, 0, 255, 255, 0, 0]);
        // Without a background class, the context channel is added last.
        let ids = [1, 2];
        let channels = label_channels(&ids);
        assert_eq!(channels, vec![1, 2, BACKGROUND]);
        assert_eq!(
            one_hot_labels(&ids, &[200, 55, 60, 195, 100, 100], None, &channels),
            vec![255, 0, 0, 0, 255, 0, 0, 0, 255]
        );
    }
}
