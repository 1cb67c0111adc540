//! Connected components of a label volume, brick by brick and out of core: the spatial prior
//! that keeps the parts of each class a scribble vouches for.
//!
//! Three pure functions, so any executor (rayon here, actors, cluster workers) runs them:
//!
//! 1. [`label_brick`]: the 6-connected components of one brick's labels, with per-component
//!    statistics (voxels, probability mass, scribbled voxels of its class) and the component id
//!    of every voxel on the brick's six faces: a [`Partial`].
//! 2. [`Partial::merge`]: joins two partials (any two sets of bricks, in any order, like the
//!    k-means partials): components that touch across a shared brick face become one, their
//!    statistics add up. Merging every brick's partial gives the global component table.
//! 3. [`filter_brick`]: relabels one brick against the merged table and clears the voxels of
//!    components the [`PriorConfig`] rejects.
//!
//! The rule: a component of class `c` is kept when it holds a scribble of class `c`, or when its
//! probability mass is at least `relative_mass` times that of the largest scribbled component of
//! `c`. A class made of several separate parts (two ventricles, two kidneys, the vessels of
//! both legs) keeps its unscribbled parts when they are about as credible as the part the user
//! marked, while speckle and small look-alike blobs elsewhere go. The rule has no absolute size:
//! it compares a volume's components with each other.
//!
//! Then the kept labels grow into the voxels the confidence threshold left unlabelled
//! ([`grow_box`], hysteresis as in Canny's edge linking): a doubtful voxel whose most probable
//! class is `c` takes `c` when it touches a voxel of `c`, `grow` times. Boundary voxels mix two
//! tissues, in the image (partial volume) and in the filter responses that describe them, so
//! their probabilities are diluted below the threshold although their best class is right; a
//! confident, kept neighbour of the same class vouches for them. Growth stops after `grow`
//! voxels, because farther from a confident voxel a weak best class is real doubt.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Settings of the spatial prior.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PriorConfig {
    /// An unscribbled component is kept when its probability mass is at least this fraction of
    /// the mass of its class's largest scribbled component.
    pub relative_mass: f64,
    /// Voxels (6-neighbour steps) the kept labels grow into doubtful voxels whose most probable
    /// class is theirs (0: no growth).
    pub grow: u32,
}

/// The most growth steps [`PriorConfig::with_grow`] accepts.
pub const MAX_GROW: u32 = 16;

/// Default growth: the radius (2 sigma, in voxels) of the filter bank's sigma-1 Gaussian, the
/// band beside a boundary where a voxel's features mix both sides and its probabilities are
/// diluted. Beyond it the features are those of one tissue, and a low confidence is real doubt.
pub const DEFAULT_GROW: u32 = 2;

impl PriorConfig {
    /// Settings with `relative_mass` checked: a fraction within 0..=1 (NaN refused); growth
    /// at its default.
    pub fn new(relative_mass: f64) -> Result<Self, String> {
        if (0.0..=1.0).contains(&relative_mass) {
            Ok(PriorConfig {
                relative_mass,
                ..Default::default()
            })
        } else {
            Err("must be within 0..=1".into())
        }
    }

    /// The same settings growing `grow` voxels (at most [`MAX_GROW`]).
    pub fn with_grow(self, grow: u32) -> Result<Self, String> {
        if grow <= MAX_GROW {
            Ok(PriorConfig { grow, ..self })
        } else {
            Err(format!("must be at most {MAX_GROW} voxels"))
        }
    }
}

impl Default for PriorConfig {
    fn default() -> Self {
        PriorConfig {
            relative_mass: 0.5,
            grow: DEFAULT_GROW,
        }
    }
}

/// Statistics of one connected component.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct ComponentStats {
    /// Label of the component.
    pub label: u16,
    /// Voxels.
    pub voxels: u64,
    /// Summed probability of the label over its voxels (equals `voxels` without probabilities).
    pub mass: f64,
    /// Scribbled voxels of the component's label inside it.
    pub seeds: u64,
}

impl ComponentStats {
    fn add(&mut self, o: &ComponentStats) {
        self.voxels += o.voxels;
        self.mass += o.mass;
        self.seeds += o.seeds;
    }
}

/// Faces of a brick, in the order -x, +x, -y, +y, -z, +z.
const FACES: usize = 6;

/// One brick's contribution to a partial: its size, the partial's component of every local
/// component, and the local component of every face voxel (0 = not labelled).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BrickPart {
    /// Brick extent (x, y, z).
    pub size: [usize; 3],
    /// Partial component index of local component `k + 1`.
    pub local: Vec<u32>,
    /// Local component ids of the face voxels (-x, +x, -y, +y, -z, +z; each row-major in the
    /// two other axes, the lower axis fastest).
    pub faces: [Vec<u32>; FACES],
}

/// Components of a set of bricks, mergeable with the partial of any other set.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Partial {
    /// Component statistics.
    pub components: Vec<ComponentStats>,
    /// The bricks, by brick index.
    pub bricks: BTreeMap<[usize; 3], BrickPart>,
}

/// Union-find with path halving.
struct Dsu(Vec<u32>);

impl Dsu {
    fn new(n: usize) -> Self {
        Dsu((0..n as u32).collect())
    }
    fn find(&mut self, mut a: u32) -> u32 {
        while self.0[a as usize] != a {
            let p = self.0[self.0[a as usize] as usize];
            self.0[a as usize] = p;
            a = p;
        }
        a
    }
    fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let (lo, hi) = (ra.min(rb), ra.max(rb));
            self.0[hi as usize] = lo;
        }
    }
}

/// The 6-connected components of one brick's labels (`size`, x fastest; 0 = unlabelled, never
/// a component). Returns the local component id of every voxel (0 for label 0, else 1..=K in
/// order of first voxel) and the brick's partial. `proba` gives each voxel's probability of
/// its label (mass = voxels without it); `seeds` lists scribbled voxels (local index, label).
pub fn label_brick(
    index: [usize; 3],
    size: [usize; 3],
    labels: &[u16],
    proba: Option<&[f32]>,
    seeds: &[(usize, u16)],
) -> (Vec<u32>, Partial) {
    let n: usize = size.iter().product();
    assert_eq!(labels.len(), n, "labels of a {size:?} brick");
    let (sx, sy) = (size[0], size[0] * size[1]);
    let mut dsu = Dsu::new(n);
    for i in 0..n {
        let l = labels[i];
        if l == 0 {
            continue;
        }
        let x = i % sx;
        let y = (i / sx) % size[1];
        let z = i / sy;
        if x > 0 && labels[i - 1] == l {
            dsu.union(i as u32, (i - 1) as u32);
        }
        if y > 0 && labels[i - sx] == l {
            dsu.union(i as u32, (i - sx) as u32);
        }
        if z > 0 && labels[i - sy] == l {
            dsu.union(i as u32, (i - sy) as u32);
        }
    }
    let mut ids = vec![0u32; n];
    let mut root_id: Vec<u32> = vec![0; n];
    let mut comps: Vec<ComponentStats> = Vec::new();
    for i in 0..n {
        if labels[i] == 0 {
            continue;
        }
        let r = dsu.find(i as u32) as usize;
        if root_id[r] == 0 {
            comps.push(ComponentStats {
                label: labels[i],
                ..Default::default()
            });
            root_id[r] = comps.len() as u32;
        }
        let id = root_id[r];
        ids[i] = id;
        let c = &mut comps[id as usize - 1];
        c.voxels += 1;
        c.mass += proba.map_or(1.0, |p| p[i] as f64);
    }
    for &(i, l) in seeds {
        if i < n && ids[i] != 0 && labels[i] == l {
            comps[ids[i] as usize - 1].seeds += 1;
        }
    }
    let faces = faces_of(&ids, size);
    let part = BrickPart {
        size,
        local: (0..comps.len() as u32).collect(),
        faces,
    };
    let mut bricks = BTreeMap::new();
    bricks.insert(index, part);
    (
        ids,
        Partial {
            components: comps,
            bricks,
        },
    )
}

/// The face voxels of a brick's component ids.
fn faces_of(ids: &[u32], size: [usize; 3]) -> [Vec<u32>; FACES] {
    let at = |x: usize, y: usize, z: usize| ids[(z * size[1] + y) * size[0] + x];
    let [nx, ny, nz] = size;
    let yz = |x: usize| -> Vec<u32> {
        (0..nz)
            .flat_map(|z| (0..ny).map(move |y| (y, z)))
            .map(|(y, z)| at(x, y, z))
            .collect()
    };
    let xz = |y: usize| -> Vec<u32> {
        (0..nz)
            .flat_map(|z| (0..nx).map(move |x| (x, z)))
            .map(|(x, z)| at(x, y, z))
            .collect()
    };
    let xy = |z: usize| -> Vec<u32> {
        (0..ny)
            .flat_map(|y| (0..nx).map(move |x| (x, y)))
            .map(|(x, y)| at(x, y, z))
            .collect()
    };
    [yz(0), yz(nx - 1), xz(0), xz(ny - 1), xy(0), xy(nz - 1)]
}

impl Partial {
    /// Joins `other` (a disjoint set of bricks) into `self`: components meeting across a face
    /// shared by a brick of each become one. Associative and commutative up to component
    /// numbering, so partials merge in any grouping.
    pub fn merge(&mut self, other: Partial) {
        let me = std::mem::take(self);
        *self = Partial::merge_all([me, other]);
    }

    /// Merges many partials of disjoint brick sets at once.
    pub fn merge_all(parts: impl IntoIterator<Item = Partial>) -> Partial {
        let mut comps: Vec<ComponentStats> = Vec::new();
        let mut bricks: BTreeMap<[usize; 3], BrickPart> = BTreeMap::new();
        let mut owner: BTreeMap<[usize; 3], usize> = BTreeMap::new();
        for (pi, p) in parts.into_iter().enumerate() {
            let off = comps.len() as u32;
            comps.extend(p.components);
            for (k, mut b) in p.bricks {
                b.local.iter_mut().for_each(|c| *c += off);
                let dup = bricks.insert(k, b);
                assert!(dup.is_none(), "brick {k:?} in two partials");
                owner.insert(k, pi);
            }
        }
        let mut dsu = Dsu::new(comps.len());
        // Every face shared by bricks of different partials, once (from its lower brick).
        for (k, me) in &bricks {
            for axis in 0..3 {
                let mut nb = *k;
                nb[axis] += 1;
                let Some(other) = bricks.get(&nb) else {
                    continue;
                };
                if owner[k] == owner[&nb] {
                    continue;
                }
                let (fa, fb) = (&me.faces[2 * axis + 1], &other.faces[2 * axis]);
                if fa.len() != fb.len() {
                    continue;
                }
                for (&a, &b) in fa.iter().zip(fb) {
                    if a == 0 || b == 0 {
                        continue;
                    }
                    let (ga, gb) = (me.local[a as usize - 1], other.local[b as usize - 1]);
                    if comps[ga as usize].label == comps[gb as usize].label {
                        dsu.union(ga, gb);
                    }
                }
            }
        }
        // Renumber the roots densely (in order of first component) and sum their statistics.
        let mut remap = vec![u32::MAX; comps.len()];
        let mut merged: Vec<ComponentStats> = Vec::new();
        for i in 0..comps.len() {
            let r = dsu.find(i as u32) as usize;
            if remap[r] == u32::MAX {
                remap[r] = merged.len() as u32;
                merged.push(ComponentStats {
                    label: comps[r].label,
                    ..Default::default()
                });
            }
            merged[remap[r] as usize].add(&comps[i]);
        }
        for b in bricks.values_mut() {
            b.local
                .iter_mut()
                .for_each(|c| *c = remap[dsu.find(*c) as usize]);
        }
        Partial {
            components: merged,
            bricks,
        }
    }

    /// Which components the prior keeps (indexed like `components`).
    pub fn keep(&self, cfg: &PriorConfig) -> Vec<bool> {
        let mut best: BTreeMap<u16, f64> = BTreeMap::new();
        for c in self.components.iter().filter(|c| c.seeds > 0) {
            let e = best.entry(c.label).or_insert(0.0);
            *e = e.max(c.mass);
        }
        self.components
            .iter()
            .map(|c| {
                c.seeds > 0
                    || best
                        .get(&c.label)
                        .is_some_and(|&m| c.mass >= cfg.relative_mass * m)
            })
            .collect()
    }
}

/// Clears the voxels of rejected components in one brick: `ids` are the brick's local
/// component ids from [`label_brick`], `merged` the merged partial and `keep` its verdicts.
/// Returns the voxels cleared.
pub fn filter_brick(
    index: [usize; 3],
    labels: &mut [u16],
    ids: &[u32],
    merged: &Partial,
    keep: &[bool],
) -> u64 {
    let Some(part) = merged.bricks.get(&index) else {
        return 0;
    };
    let mut cleared = 0;
    for (l, &id) in labels.iter_mut().zip(ids) {
        if id != 0 && !keep[part.local[id as usize - 1] as usize] {
            *l = 0;
            cleared += 1;
        }
    }
    cleared
}

/// What [`apply_in_memory`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct PriorVerdict {
    /// Connected components of the labels.
    pub components: usize,
    /// Of which kept.
    pub kept: usize,
    /// Voxels set to 0.
    pub cleared: u64,
    /// Doubtful voxels the kept labels grew into.
    pub grown: u64,
}

/// Grows labels into doubtful voxels on a box of `size` voxels (x fastest): `doubtful` holds,
/// per voxel, the class it may take (its most probable class where the threshold left it
/// unlabelled, 0 elsewhere). Each of `steps` rounds gives every unlabelled voxel with
/// `doubtful = c` the label `c` when a 6-neighbour had `c` after the round before. The result is
/// exact on the whole box; on a brick cut from a larger volume it is exact farther than `steps`
/// voxels from the cut faces (a round moves labels one voxel). Returns the voxels labelled.
pub fn grow_box(labels: &mut [u16], doubtful: &[u16], size: [usize; 3], steps: u32) -> u64 {
    let n: usize = size.iter().product();
    assert_eq!(labels.len(), n, "labels of a {size:?} box");
    assert_eq!(doubtful.len(), n, "doubtful classes of a {size:?} box");
    let (sx, sy) = (size[0], size[0] * size[1]);
    let mut grown = 0;
    let mut add: Vec<(usize, u16)> = Vec::new();
    for _ in 0..steps {
        add.clear();
        for i in 0..n {
            let c = doubtful[i];
            if c == 0 || labels[i] != 0 {
                continue;
            }
            let (x, y, z) = (i % sx, (i / sx) % size[1], i / sy);
            let touches = (x > 0 && labels[i - 1] == c)
                || (x + 1 < size[0] && labels[i + 1] == c)
                || (y > 0 && labels[i - sx] == c)
                || (y + 1 < size[1] && labels[i + sx] == c)
                || (z > 0 && labels[i - sy] == c)
                || (z + 1 < size[2] && labels[i + sy] == c);
            if touches {
                add.push((i, c));
            }
        }
        if add.is_empty() {
            break;
        }
        for &(i, c) in &add {
            labels[i] = c;
        }
        grown += add.len() as u64;
    }
    grown
}

/// [`grow_box`] over a whole volume in memory, in parallel slabs of z with a halo of `steps`
/// slices (so the result equals one [`grow_box`] over the volume).
pub fn grow_in_memory(labels: &mut [u16], doubtful: &[u16], dims: [usize; 3], steps: u32) -> u64 {
    use rayon::prelude::*;
    const SLAB: usize = 16;
    let plane = dims[0] * dims[1];
    let h = steps as usize;
    let slabs: Vec<(usize, usize)> = (0..dims[2])
        .step_by(SLAB)
        .map(|z| (z, SLAB.min(dims[2] - z)))
        .collect();
    let src: &[u16] = labels;
    let done: Vec<(usize, Vec<u16>, u64)> = slabs
        .par_iter()
        .map(|&(z0, nz)| {
            let (lo, hi) = (z0.saturating_sub(h), (z0 + nz + h).min(dims[2]));
            let mut l = src[lo * plane..hi * plane].to_vec();
            let d = &doubtful[lo * plane..hi * plane];
            grow_box(&mut l, d, [dims[0], dims[1], hi - lo], steps);
            let inner = l[(z0 - lo) * plane..(z0 - lo + nz) * plane].to_vec();
            let before = &src[z0 * plane..(z0 + nz) * plane];
            let g = inner.iter().zip(before).filter(|(a, b)| a != b).count() as u64;
            (z0, inner, g)
        })
        .collect();
    let mut grown = 0;
    for (z0, inner, g) in done {
        labels[z0 * plane..z0 * plane + inner.len()].copy_from_slice(&inner);
        grown += g;
    }
    grown
}

/// Applies the prior to a whole label volume held in memory (`dims`, x fastest), brick by
/// brick (`brick` edge) with rayon: label, merge, filter, then grow (when `best` is given and
/// `cfg.grow > 0`). `proba` gives each voxel's probability of its label, `best` its most
/// probable output label whatever its probability (0 = background); `seeds` are the scribbles
/// (voxel index, label).
pub fn apply_in_memory(
    labels: &mut [u16],
    dims: [usize; 3],
    brick: usize,
    proba: Option<&[f32]>,
    best: Option<&[u16]>,
    seeds: &[(u64, u16)],
    cfg: &PriorConfig,
) -> PriorVerdict {
    use rayon::prelude::*;
    // Doubtful voxels: left unlabelled by the threshold (not cleared by the filter below).
    let doubtful: Option<Vec<u16>> = best.filter(|_| cfg.grow > 0).map(|b| {
        labels
            .par_iter()
            .zip(b)
            .map(|(&l, &b)| if l == 0 { b } else { 0 })
            .collect()
    });
    let grid = dims.map(|d| d.div_ceil(brick));
    let mut per_brick: BTreeMap<[usize; 3], Vec<(usize, u16)>> = BTreeMap::new();
    for &(i, l) in seeds {
        let i = i as usize;
        let p = [
            i % dims[0],
            (i / dims[0]) % dims[1],
            i / (dims[0] * dims[1]),
        ];
        let b = p.map(|v| v / brick);
        let o = b.map(|v| v * brick);
        let s: [usize; 3] = std::array::from_fn(|a| brick.min(dims[a] - o[a]));
        per_brick
            .entry(b)
            .or_default()
            .push((((p[2] - o[2]) * s[1] + p[1] - o[1]) * s[0] + p[0] - o[0], l));
    }
    let idx: Vec<[usize; 3]> = (0..grid[2])
        .flat_map(|z| (0..grid[1]).flat_map(move |y| (0..grid[0]).map(move |x| [x, y, z])))
        .collect();
    let gather = |b: [usize; 3]| -> ([usize; 3], [usize; 3], Vec<usize>) {
        let o = b.map(|v| v * brick);
        let s: [usize; 3] = std::array::from_fn(|a| brick.min(dims[a] - o[a]));
        let mut at = Vec::with_capacity(s.iter().product());
        for z in 0..s[2] {
            for y in 0..s[1] {
                let row = ((o[2] + z) * dims[1] + o[1] + y) * dims[0] + o[0];
                at.extend(row..row + s[0]);
            }
        }
        (o, s, at)
    };
    let empty = Vec::new();
    let labelled: Vec<([usize; 3], Vec<u32>, Partial)> = idx
        .par_iter()
        .map(|&b| {
            let (_, s, at) = gather(b);
            let l: Vec<u16> = at.iter().map(|&i| labels[i]).collect();
            let p: Option<Vec<f32>> = proba.map(|p| at.iter().map(|&i| p[i]).collect());
            let (ids, part) =
                label_brick(b, s, &l, p.as_deref(), per_brick.get(&b).unwrap_or(&empty));
            (b, ids, part)
        })
        .collect();
    let mut ids_of = Vec::with_capacity(labelled.len());
    let mut parts = Vec::with_capacity(labelled.len());
    for (b, ids, p) in labelled {
        ids_of.push((b, ids));
        parts.push(p);
    }
    let merged = Partial::merge_all(parts);
    let keep = merged.keep(cfg);
    let mut cleared = 0;
    for (b, ids) in ids_of {
        let (_, _, at) = gather(b);
        let mut l: Vec<u16> = at.iter().map(|&i| labels[i]).collect();
        let c = filter_brick(b, &mut l, &ids, &merged, &keep);
        if c > 0 {
            for (&i, &v) in at.iter().zip(&l) {
                labels[i] = v;
            }
            cleared += c;
        }
    }
    let grown = doubtful.map_or(0, |d| grow_in_memory(labels, &d, dims, cfg.grow));
    PriorVerdict {
        components: keep.len(),
        kept: keep.iter().filter(|&&k| k).count(),
        cleared,
        grown,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_bricks::rng::Rng;

    /// Whole-volume 6-connected components by flood fill: component index per voxel (or
    /// `u32::MAX` for label 0).
    fn reference(labels: &[u16], d: [usize; 3]) -> Vec<u32> {
        let n = labels.len();
        let mut comp = vec![u32::MAX; n];
        let mut next = 0;
        for s in 0..n {
            if labels[s] == 0 || comp[s] != u32::MAX {
                continue;
            }
            let mut stack = vec![s];
            comp[s] = next;
            while let Some(i) = stack.pop() {
                let p = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                for a in 0..3 {
                    for dir in [-1isize, 1] {
                        let v = p[a] as isize + dir;
                        if v < 0 || v >= d[a] as isize {
                            continue;
                        }
                        let mut q = p;
                        q[a] = v as usize;
                        let j = (q[2] * d[1] + q[1]) * d[0] + q[0];
                        if labels[j] == labels[i] && comp[j] == u32::MAX {
                            comp[j] = next;
                            stack.push(j);
                        }
                    }
                }
            }
            next += 1;
        }
        comp
    }

    /// Random blobs of 3 labels.
    fn volume(d: [usize; 3], seed: u64, fill: f32) -> Vec<u16> {
        let mut r = Rng(seed);
        (0..d.iter().product::<usize>())
            .map(|_| {
                if r.f32() < fill {
                    1 + r.below(3) as u16
                } else {
                    0
                }
            })
            .collect()
    }

    /// Component ids per brick, with the brick's index.
    type BrickIds = Vec<([usize; 3], Vec<u32>)>;

    /// Labels every brick of `labels`, merging in the order `order` gives.
    fn components_by_brick(
        labels: &[u16],
        d: [usize; 3],
        bs: usize,
        tree: bool,
    ) -> (Partial, BrickIds) {
        let g = d.map(|v| v.div_ceil(bs));
        let mut parts = Vec::new();
        let mut ids = Vec::new();
        for bz in 0..g[2] {
            for by in 0..g[1] {
                for bx in 0..g[0] {
                    let o = [bx * bs, by * bs, bz * bs];
                    let s: [usize; 3] = std::array::from_fn(|a| bs.min(d[a] - o[a]));
                    let mut l = Vec::new();
                    for z in 0..s[2] {
                        for y in 0..s[1] {
                            for x in 0..s[0] {
                                l.push(labels[((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0] + x]);
                            }
                        }
                    }
                    let (i, p) = label_brick([bx, by, bz], s, &l, None, &[]);
                    ids.push(([bx, by, bz], i));
                    parts.push(p);
                }
            }
        }
        let merged = if tree {
            // Pairwise tree reduction, in reverse order, as a cluster would merge.
            parts.reverse();
            while parts.len() > 1 {
                let mut next = Vec::new();
                let mut it = parts.into_iter();
                while let Some(mut a) = it.next() {
                    if let Some(b) = it.next() {
                        a.merge(b);
                    }
                    next.push(a);
                }
                parts = next;
            }
            parts.pop().unwrap()
        } else {
            Partial::merge_all(parts)
        };
        (merged, ids)
    }

    #[test]
    fn bricks_find_the_components_of_the_whole_volume() {
        for (seed, fill, bs) in [(1, 0.6, 4), (2, 0.45, 5), (3, 0.8, 7), (4, 0.3, 16)] {
            let d = [13, 11, 9];
            let labels = volume(d, seed, fill);
            let want = reference(&labels, d);
            for tree in [false, true] {
                let (merged, ids) = components_by_brick(&labels, d, bs, tree);
                let n_ref = want
                    .iter()
                    .filter(|&&c| c != u32::MAX)
                    .max()
                    .map_or(0, |m| m + 1);
                assert_eq!(merged.components.len() as u32, n_ref, "seed {seed} bs {bs}");
                // The same partition: a bijection between reference and merged components.
                let mut map: BTreeMap<u32, u32> = BTreeMap::new();
                let mut voxels = vec![0u64; merged.components.len()];
                for (b, local) in &ids {
                    let part = &merged.bricks[b];
                    let o = b.map(|v| v * bs);
                    let s = part.size;
                    let mut k = 0;
                    for z in 0..s[2] {
                        for y in 0..s[1] {
                            for x in 0..s[0] {
                                let wi = ((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0] + x;
                                if local[k] == 0 {
                                    assert_eq!(want[wi], u32::MAX);
                                } else {
                                    let g = part.local[local[k] as usize - 1];
                                    let e = *map.entry(want[wi]).or_insert(g);
                                    assert_eq!(e, g, "voxel {wi}");
                                    voxels[g as usize] += 1;
                                    assert_eq!(merged.components[g as usize].label, labels[wi]);
                                }
                                k += 1;
                            }
                        }
                    }
                }
                let distinct: std::collections::BTreeSet<u32> = map.values().copied().collect();
                assert_eq!(distinct.len(), map.len());
                for (g, c) in merged.components.iter().enumerate() {
                    assert_eq!(c.voxels, voxels[g]);
                    assert_eq!(c.mass, c.voxels as f64);
                }
            }
        }
    }

    #[test]
    fn the_relative_mass_is_a_fraction() {
        assert_eq!(PriorConfig::new(0.25).unwrap().relative_mass, 0.25);
        for bad in [-0.1, 1.5, f64::NAN, f64::INFINITY] {
            assert_eq!(PriorConfig::new(bad).unwrap_err(), "must be within 0..=1");
        }
        let c = PriorConfig::new(0.25).unwrap();
        assert_eq!(c.grow, DEFAULT_GROW);
        assert_eq!(c.with_grow(0).unwrap().grow, 0);
        assert_eq!(c.with_grow(MAX_GROW).unwrap().grow, MAX_GROW);
        assert_eq!(
            c.with_grow(MAX_GROW + 1).unwrap_err(),
            format!("must be at most {MAX_GROW} voxels")
        );
        // Settings written before growth existed read back with the default.
        let old: PriorConfig = serde_json::from_str(r#"{"relative_mass":0.3}"#).unwrap();
        assert_eq!(old.grow, DEFAULT_GROW);
    }

    #[test]
    fn growth_follows_the_best_class_for_its_steps_and_no_farther() {
        // A row of 10 voxels: a confident class-1 voxel at x = 2; doubtful voxels whose best
        // class is 1 at x = 3..=7, one whose best class is 2 at x = 1, background best at 0.
        let d = [10, 1, 1];
        let mut labels = vec![0u16; 10];
        labels[2] = 1;
        let doubtful = [0u16, 2, 0, 1, 1, 1, 1, 1, 0, 1];
        let mut l = labels.clone();
        assert_eq!(grow_box(&mut l, &doubtful, d, 2), 2);
        assert_eq!(l, [0, 0, 1, 1, 1, 0, 0, 0, 0, 0]);
        let mut l = labels.clone();
        assert_eq!(grow_box(&mut l, &doubtful, d, 16), 5);
        assert_eq!(
            l,
            [0, 0, 1, 1, 1, 1, 1, 1, 0, 0],
            "stops at a background voxel"
        );
        let mut l = labels.clone();
        assert_eq!(grow_box(&mut l, &doubtful, d, 0), 0);
        assert_eq!(l, labels);
    }

    #[test]
    fn growth_in_slabs_equals_growth_on_the_whole_volume() {
        let d = [9, 7, 53];
        let n = d.iter().product::<usize>();
        let mut rng = Rng::new(7);
        let labels: Vec<u16> = (0..n)
            .map(|_| {
                if rng.f32() < 0.05 {
                    1 + rng.below(2) as u16
                } else {
                    0
                }
            })
            .collect();
        let doubtful: Vec<u16> = labels
            .iter()
            .map(|&l| if l == 0 { rng.below(3) as u16 } else { 0 })
            .collect();
        for steps in [0, 1, 3, 20] {
            let mut whole = labels.clone();
            let g1 = grow_box(&mut whole, &doubtful, d, steps);
            let mut slabs = labels.clone();
            let g2 = grow_in_memory(&mut slabs, &doubtful, d, steps);
            assert_eq!(whole, slabs, "{steps} steps");
            assert_eq!(g1, g2);
            assert!(steps == 0 || g1 > 0);
        }
    }

    #[test]
    fn growth_never_revives_what_the_filter_cleared() {
        // A scribbled class-1 bar and a speck of class 1 two voxels past its end: the filter
        // clears the speck; growth then fills the doubtful gap but the speck stays cleared
        // (its own best class is 1, but the threshold had labelled it, so it is not doubtful).
        let d = [12, 1, 1];
        let mut labels = vec![0u16; 12];
        labels[..4].fill(1);
        labels[9] = 1;
        let best = vec![1u16; 12];
        let seeds = [(0u64, 1u16)];
        let cfg = PriorConfig::default().with_grow(8).unwrap();
        let p: Vec<f32> = (0..12).map(|i| if i < 4 { 1.0 } else { 0.1 }).collect();
        let v = apply_in_memory(&mut labels, d, 4, Some(&p), Some(&best), &seeds, &cfg);
        assert_eq!(v.cleared, 1);
        assert_eq!(
            v.grown, 5,
            "x = 4..=8; the cleared speck blocks the way to 10 and 11"
        );
        assert_eq!(labels, [1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0]);
    }

    #[test]
    fn the_prior_keeps_scribbled_and_comparable_parts_and_drops_speckle() {
        // Class 1: two ventricle-like boxes of 4x4x4 and 4x4x3, one scribbled; a 1-voxel
        // speck. Class 2: a scribbled bar and a separate 2-voxel blob.
        let d = [20, 10, 10];
        let mut labels = vec![0u16; 2000];
        let at = |x: usize, y: usize, z: usize| (z * 10 + y) * 20 + x;
        for z in 1..5 {
            for y in 1..5 {
                for x in 1..5 {
                    labels[at(x, y, z)] = 1;
                    if z < 4 {
                        labels[at(x + 10, y, z)] = 1;
                    }
                }
            }
        }
        labels[at(18, 8, 8)] = 1;
        for x in 0..20 {
            labels[at(x, 8, 2)] = 2;
        }
        labels[at(3, 8, 6)] = 2;
        labels[at(3, 8, 7)] = 2;
        let before = labels.clone();
        let seeds = [(at(2, 2, 2) as u64, 1u16), (at(5, 8, 2) as u64, 2)];
        let cleared = apply_in_memory(
            &mut labels,
            d,
            8,
            None,
            None,
            &seeds,
            &PriorConfig::default(),
        )
        .cleared;
        assert_eq!(cleared, 3, "the speck and the 2-voxel blob");
        assert_eq!(labels[at(12, 2, 2)], 1, "the unscribbled twin stays");
        assert_eq!(labels[at(18, 8, 8)], 0);
        assert_eq!(labels[at(3, 8, 6)], 0);
        assert_eq!(labels[at(19, 8, 2)], 2);
        // With probabilities, a large but doubtful twin loses to a confident scribbled part.
        let mut l2 = before.clone();
        let p: Vec<f32> = (0..2000)
            .map(|i| if i % 20 >= 10 { 0.2 } else { 1.0 })
            .collect();
        apply_in_memory(
            &mut l2,
            d,
            8,
            Some(&p),
            None,
            &seeds,
            &PriorConfig::default(),
        );
        assert_eq!(l2[at(12, 2, 2)], 0);
        // Unscribbled classes are left alone only where a scribble vouches: none here for 3.
        let mut l3 = before;
        l3[at(15, 5, 5)] = 3;
        apply_in_memory(&mut l3, d, 8, None, None, &seeds, &PriorConfig::default());
        assert_eq!(l3[at(15, 5, 5)], 0);
    }
}
