//! The forest as prediction walks it: features coded exactly as u16 bin indices between the
//! forest's own split thresholds, and 8-byte nodes comparing codes.
//!
//! For each feature, the forest's distinct thresholds `e_0 < e_1 < ...` are the bin edges. A
//! value `v` codes to `#{i : e_i < v}`, and a node splitting at `e_j` sends `v` right exactly
//! when its code exceeds `j`. So coded prediction equals the f32 walk for every input (NaN
//! codes to 0 and goes left, as `v > t` is false for NaN), as long as a feature has at most
//! 65 535 distinct thresholds; forests past that (or with more than 65 536 features) keep the
//! f32 walk.
//!
//! A block of rows is coded feature by feature (one feature's edges stay cached), then every
//! tree walks the block in 16 interleaved lanes (their independent loads overlap) while the
//! next tree's nodes are prefetched; a lane that reaches its leaf takes the next row at once.

use rayon::prelude::*;

/// Code of a leaf: larger than every feature code, so a leaf's test always goes "left", to
/// itself.
const LEAF_CODE: u16 = u16::MAX;

/// One node: go to `left` when the row's code of `feature` is at most `code`, else to
/// `left + 1`. Leaves loop to themselves.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(8))]
struct Node {
    code: u16,
    feature: u16,
    left: u32,
}

/// A forest packed for coded prediction.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Packed {
    d: usize,
    classes: usize,
    /// Per feature: its distinct split thresholds, ascending.
    edges: Vec<Vec<f32>>,
    /// Every tree's nodes, one after the other (a tree's `left` indices are global).
    nodes: Vec<Node>,
    /// Per tree: first node and depth of its deepest leaf.
    trees: Vec<(u32, u32)>,
    /// Per node: the offset of its leaf's class fractions in `probs` (split nodes: 0).
    leaf_at: Vec<u32>,
    /// Leaf class fractions, `classes` per leaf, all trees.
    probs: Vec<f32>,
}

/// One tree as [`Packed::new`] reads it: per node `(feature, threshold, left)` with
/// self-looping leaves (threshold `+inf`), the leaf index per node (`None` for splits), the
/// leaves' class fractions and the depth.
pub(crate) struct TreeView<'a> {
    pub nodes: Vec<(u32, f32, u32)>,
    pub leaf_of: &'a [u32],
    pub probs: &'a [f32],
    pub depth: u32,
}

/// `#{i : e_i < v}` for ascending `e`, without data-dependent branches.
#[inline(always)]
fn code(e: &[f32], v: f32) -> u16 {
    if e.is_empty() {
        return 0;
    }
    let (mut base, mut len) = (0usize, e.len());
    while len > 1 {
        let half = len / 2;
        base += (e[base + half - 1] < v) as usize * half;
        len -= half;
    }
    (base + (e[base] < v) as usize) as u16
}

impl Packed {
    /// Packs the trees, or `None` where a feature has too many distinct thresholds for u16
    /// codes or there are too many features.
    pub(crate) fn new(d: usize, classes: usize, trees: &[TreeView<'_>], leaf: u32) -> Option<Self> {
        if d > u16::MAX as usize + 1 {
            return None;
        }
        let mut edges: Vec<Vec<f32>> = vec![Vec::new(); d];
        for t in trees {
            for &(f, thr, _) in &t.nodes {
                if thr != f32::INFINITY {
                    edges[f as usize].push(thr);
                }
            }
        }
        for e in &mut edges {
            e.sort_unstable_by(|a, b| a.total_cmp(b));
            e.dedup_by(|a, b| a.to_bits() == b.to_bits());
            if e.len() > LEAF_CODE as usize {
                return None;
            }
        }
        let total: usize = trees.iter().map(|t| t.nodes.len()).sum();
        let total_u32 = u32::try_from(total).ok()?;
        let mut nodes = Vec::with_capacity(total);
        let mut leaf_at = Vec::with_capacity(total);
        let mut probs = Vec::new();
        let mut starts = Vec::with_capacity(trees.len());
        for t in trees {
            let start = nodes.len() as u32;
            let leaf0 = probs.len() / classes;
            probs.extend_from_slice(t.probs);
            for (i, &(f, thr, left)) in t.nodes.iter().enumerate() {
                if t.leaf_of[i] != leaf {
                    nodes.push(Node {
                        code: LEAF_CODE,
                        feature: 0,
                        left: start + i as u32,
                    });
                    leaf_at.push(((leaf0 + t.leaf_of[i] as usize) * classes) as u32);
                } else {
                    let e = &edges[f as usize];
                    let j = e
                        .binary_search_by(|a| a.total_cmp(&thr))
                        .expect("every threshold is an edge");
                    nodes.push(Node {
                        code: j as u16,
                        feature: f as u16,
                        left: start + left,
                    });
                    leaf_at.push(0);
                }
            }
            starts.push((start, t.depth));
        }
        debug_assert_eq!(nodes.len() as u32, total_u32);
        u32::try_from(probs.len()).ok()?;
        Some(Packed {
            d,
            classes,
            edges,
            nodes,
            trees: starts,
            leaf_at,
            probs,
        })
    }

    /// Codes rows `x` (`rows x d`) into `out`, feature by feature.
    fn code_rows(&self, x: &[f32], out: &mut [u16]) {
        let d = self.d;
        for (f, e) in self.edges.iter().enumerate() {
            for (o, row) in out.chunks_exact_mut(d).zip(x.chunks_exact(d)) {
                o[f] = code(e, row[f]);
            }
        }
    }

    /// Hints the cache to fetch a tree's nodes.
    #[inline(always)]
    fn prefetch(&self, tree: usize) {
        let Some(&(start, _)) = self.trees.get(tree) else {
            return;
        };
        let end = self
            .trees
            .get(tree + 1)
            .map_or(self.nodes.len(), |t| t.0 as usize);
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            // 8 nodes per 64-byte line.
            for i in (start as usize..end).step_by(8) {
                // SAFETY: prefetching is a hint; the address is inside `nodes`.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(self.nodes.as_ptr().add(i) as *const i8) };
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (start, end);
    }

    /// Mean class fractions over the trees of every row of `x`, added into `out`
    /// (`rows x classes`, zeroed by the caller), scaled by `inv`.
    pub(crate) fn predict_into(&self, x: &[f32], out: &mut [f32], inv: f32) {
        const BLOCK: usize = 1024;
        let (d, c) = (self.d, self.classes);
        out.par_chunks_mut(BLOCK * c)
            .zip(x.par_chunks(BLOCK * d))
            .for_each_init(
                || vec![0u16; BLOCK * d],
                |codes, (o, xb)| {
                    let nr = xb.len() / d;
                    let codes = &mut codes[..nr * d];
                    self.code_rows(xb, codes);
                    for (ti, &(start, _)) in self.trees.iter().enumerate() {
                        self.prefetch(ti + 1);
                        self.walk_tree(start, codes, nr, o);
                    }
                    o.iter_mut().for_each(|v| *v *= inv);
                },
            );
    }

    /// Walks the `nr` coded rows of `codes` through the tree starting at node `start`, adding
    /// each row's leaf fractions into `o`. `LANES` rows walk at once (their independent loads
    /// overlap); a lane that reaches its leaf takes the next row at once, so no lane idles
    /// while another walks a deeper path.
    #[inline(always)]
    fn walk_tree(&self, start: u32, codes: &[u16], nr: usize, o: &mut [f32]) {
        const LANES: usize = 16;
        let (d, c) = (self.d, self.classes);
        let nodes = &self.nodes[..];
        let mut at = [start; LANES];
        // Each lane's row offset into `codes`.
        let mut row = [0usize; LANES];
        let mut live = LANES.min(nr);
        for (l, r) in row.iter_mut().enumerate().take(live) {
            *r = l * d;
        }
        let mut next = live;
        let add = |o: &mut [f32], r: usize, node: u32| {
            let p = self.leaf_at[node as usize] as usize;
            let r = r / d;
            o[r * c..(r + 1) * c]
                .iter_mut()
                .zip(&self.probs[p..p + c])
                .for_each(|(a, b)| *a += b);
        };
        while live == LANES {
            for l in 0..LANES {
                let nd = nodes[at[l] as usize];
                if nd.code == LEAF_CODE {
                    add(o, row[l], at[l]);
                    if next < nr {
                        row[l] = next * d;
                        at[l] = start;
                        next += 1;
                    } else {
                        // Park the lane on its leaf; the tail loop below finishes the rest.
                        live -= 1;
                        at[l] = u32::MAX;
                    }
                    continue;
                }
                at[l] = nd.left + (codes[row[l] + nd.feature as usize] > nd.code) as u32;
            }
        }
        // The last lanes (fewer than LANES rows left): compacted, walked to their leaves.
        let mut m = 0;
        for l in 0..LANES.min(nr) {
            if at[l] != u32::MAX {
                (at[m], row[m]) = (at[l], row[l]);
                m += 1;
            }
        }
        while m > 0 {
            let mut l = 0;
            while l < m {
                let nd = nodes[at[l] as usize];
                if nd.code == LEAF_CODE {
                    add(o, row[l], at[l]);
                    m -= 1;
                    (at[l], row[l]) = (at[m], row[m]);
                    continue;
                }
                at[l] = nd.left + (codes[row[l] + nd.feature as usize] > nd.code) as u32;
                l += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::code;

    #[test]
    fn codes_count_the_edges_below() {
        let e = [-1.0f32, 0.0, 0.5, 2.0, 7.0];
        for v in [-5.0f32, -1.0, -0.5, 0.0, 0.25, 0.5, 1.0, 2.0, 3.0, 7.0, 8.0] {
            let want = e.iter().filter(|&&t| t < v).count() as u16;
            assert_eq!(code(&e, v), want, "{v}");
        }
        assert_eq!(code(&e, f32::NAN), 0);
        assert_eq!(code(&[], 3.0), 0);
        assert_eq!(code(&e, f32::INFINITY), 5);
    }
}
