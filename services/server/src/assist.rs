//! Interactive assistance over a session's streamed probabilities: the spatial prior (the
//! component filter of `neuvolex_classify::components`, a toggle) and the next-slice
//! suggestion (`neuvolex_classify::suggest`). Both run the library's per-brick functions over
//! the probability bricks; the raw probabilities stay as they are, the prior's verdict is kept
//! beside them.

use crate::error::{ApiError, ApiResult};
use crate::session::Session;
use neuvolex_classify::suggest::SliceMass;
use rayon::prelude::*;

use crate::labels::{label_of, Probs};

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
    if let Some(pr) = s.active_prior(&probs) {
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
