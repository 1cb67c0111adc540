//! Interactive assistance over a session's streamed probabilities: the spatial prior (the
//! component filter of `neuvolex_classify::components`, a toggle) and the next-slice
//! suggestion (`neuvolex_classify::suggest`). Both run the library's per-brick functions over
//! the probability bricks; the raw probabilities stay as they are, the prior's verdict is kept
//! beside them.

use crate::error::{ApiError, ApiResult};
use crate::session::{Probs, Session, BACKGROUND};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::components::{label_brick, Partial, PriorConfig};
use neuvolex_classify::suggest::SliceMass;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

/// The prior's verdict on one classification.
#[derive(Debug, Clone, Default)]
pub struct PriorState {
    /// The probabilities' generation it was computed from.
    pub generation: u64,
    /// Per brick, the (sorted) local voxel indices whose label the prior clears.
    pub cleared: HashMap<[usize; 3], Arc<Vec<u32>>>,
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
}

impl PriorState {
    /// Whether the prior clears voxel `p`.
    pub fn clears(&self, store: &BrickStore, p: [usize; 3]) -> bool {
        let b = store.info().brick;
        let Ok(br) = store.brick(p.map(|v| v / b)) else {
            return false;
        };
        let Some(c) = self.cleared.get(&br.index) else {
            return false;
        };
        let l = [0, 1, 2].map(|k| p[k] - br.origin[k]);
        let i = ((l[2] * br.size[1] + l[1]) * br.size[0] + l[0]) as u32;
        c.binary_search(&i).is_ok()
    }
}

/// The label of a voxel's u8 probabilities: the best class when it reaches 0.5 and is not
/// background, else 0 (as the overlays and exports show it).
pub fn label_of(ids: &[u32], px: &[u8]) -> u32 {
    let (k, &m) = px
        .iter()
        .enumerate()
        .max_by_key(|(_, &v)| v)
        .unwrap_or((0, &0));
    match ids.get(k) {
        Some(&id) if m >= 128 && id != BACKGROUND => id,
        _ => 0,
    }
}

/// Computes the prior over every classified brick of `probs` with the session's scribbles.
pub fn compute_prior(s: &Session, probs: &Probs) -> ApiResult<PriorState> {
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
    let done: Vec<([usize; 3], Vec<u32>, Partial)> = probs
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
            Ok((*idx, ids, part))
        })
        .collect::<ApiResult<_>>()?;
    let mut ids_of = Vec::with_capacity(done.len());
    let mut parts = Vec::with_capacity(done.len());
    for (b, ids, p) in done {
        ids_of.push((b, ids));
        parts.push(p);
    }
    let merged = Partial::merge_all(parts);
    let keep = merged.keep(&PriorConfig::default());
    let mut cleared = HashMap::new();
    let mut voxels = 0;
    for (b, ids) in ids_of {
        let part = &merged.bricks[&b];
        let v: Vec<u32> = ids
            .iter()
            .enumerate()
            .filter(|(_, &id)| id != 0 && !keep[part.local[id as usize - 1] as usize])
            .map(|(i, _)| i as u32)
            .collect();
        if !v.is_empty() {
            voxels += v.len() as u64;
            cleared.insert(b, Arc::new(v));
        }
    }
    Ok(PriorState {
        generation: probs.generation,
        cleared,
        summary: PriorSummary {
            enabled: true,
            generation: probs.generation,
            components: keep.len(),
            kept: keep.iter().filter(|&&k| k).count(),
            voxels_cleared: voxels,
        },
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
