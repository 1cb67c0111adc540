//! A first look at one slice: the forest's labels on a plane, before the rest of the volume
//! and before the spatial prior. Interactive front ends (the napari widget) show it while the
//! whole-volume classification runs. The forest is the one the pipeline trains for the same
//! scribbles and settings, and each voxel gets the label its brick's classification gives it
//! ([`classify_brick`]), so with the prior off the plane equals that slice of the full result.

use crate::features::BrickFeatures;
use crate::scribble::Scribbles;
use crate::shard::{fit, output_labels, predict_brick, training_set, ClassifyConfig};
use crate::ClassifyError;
use neuvolex_bricks::Brick;
use rayon::prelude::*;

/// The labels of one plane (0 = background).
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneLabels {
    /// The plane's axis (0 = x, 1 = y, 2 = z) and index along it.
    pub axis: usize,
    /// Index along the axis.
    pub index: usize,
    /// Size of the plane: the other two axes in x, y, z order, the first fastest.
    pub size: [usize; 2],
    /// Labels, the first of the other axes fastest.
    pub labels: Vec<u16>,
    /// The scribble label of each forest class.
    pub classes: Vec<u32>,
}

/// The other two axes of `axis`, in x, y, z order.
fn others(axis: usize) -> [usize; 2] {
    match axis {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

/// Trains the forest on `scr` (as the pipeline does) and labels plane `index` of `axis`:
/// only the bricks crossing it are read, and only its voxels predicted. `cancelled` is polled
/// between bricks.
pub fn preview_plane(
    fx: &BrickFeatures<'_>,
    scr: &Scribbles,
    cfg: &ClassifyConfig,
    axis: usize,
    index: usize,
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<PlaneLabels, ClassifyError> {
    let store = fx.store();
    let dims = store.info().dims;
    if axis > 2 || index >= dims[axis.min(2)] {
        return Err(ClassifyError::Input(format!(
            "plane {index} of axis {axis} lies outside the grid {dims:?}"
        )));
    }
    let ts = training_set(fx, scr, cfg.background)?;
    let forest = fit(&ts, &cfg.forest)?;
    let out = output_labels(&ts.labels, cfg.background);
    let bg = ts.labels.iter().position(|&l| l == cfg.background);
    let [u, v] = others(axis);
    let size = [dims[u], dims[v]];
    let crossing: Vec<Brick> = store
        .bricks()
        .filter(|b| b.origin[axis] <= index && index < b.origin[axis] + b.size[axis])
        .collect();
    let parts: Vec<(Brick, Vec<u16>)> = crossing
        .into_par_iter()
        .map(|b| {
            if cancelled() {
                return Err(ClassifyError::Input("cancelled".into()));
            }
            let n = b.size[u] * b.size[v];
            let skip = cfg.skip_empty
                && bg.is_some()
                && !store.is_occupied(&b, None)
                && !ts.roi_bricks.contains(&b.index);
            if skip {
                return Ok((b, vec![0; n]));
            }
            let f = fx.brick(&b)?;
            let d = ts.d;
            // The plane's voxels of the brick, the first other axis fastest.
            let mut g = Vec::with_capacity(n * d);
            let k = index - b.origin[axis];
            for j in 0..b.size[v] {
                for i in 0..b.size[u] {
                    let mut p = [0usize; 3];
                    p[axis] = k;
                    p[u] = i;
                    p[v] = j;
                    let at = (p[2] * b.size[1] + p[1]) * b.size[0] + p[0];
                    g.extend_from_slice(&f[at * d..(at + 1) * d]);
                }
            }
            let (_, lab) = predict_brick(&forest, &g, &out, cfg.tau)?;
            Ok((b, lab))
        })
        .collect::<Result<_, _>>()?;
    let mut labels = vec![0u16; size[0] * size[1]];
    for (b, lab) in parts {
        for j in 0..b.size[v] {
            let row = (b.origin[v] + j) * size[0] + b.origin[u];
            labels[row..row + b.size[u]].copy_from_slice(&lab[j * b.size[u]..(j + 1) * b.size[u]]);
        }
    }
    Ok(PlaneLabels {
        axis,
        index,
        size,
        labels,
        classes: ts.labels.clone(),
    })
}
