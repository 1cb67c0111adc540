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
        self.predict_with(x, out, inv, avx2());
    }

    /// [`Packed::predict_into`], by the vector walk where `avx2` (the CPU must have AVX2).
    pub(crate) fn predict_with(&self, x: &[f32], out: &mut [f32], inv: f32, avx2: bool) {
        let (d, c) = (self.d, self.classes);
        out.par_chunks_mut(BLOCK * c)
            .zip(x.par_chunks(BLOCK * d))
            .for_each_init(
                // One spare row of codes and of leaves: the rows that lanes walk once every
                // real row of the block is handed out.
                // (and one more code: the vector walk reads codes as 4-byte words).
                || (vec![0u16; (BLOCK + 1) * d + 1], vec![0u32; BLOCK + 1]),
                |(codes, hit), (o, xb)| {
                    let nr = xb.len() / d;
                    self.code_rows(xb, &mut codes[..nr * d]);
                    for (ti, &(start, _)) in self.trees.iter().enumerate() {
                        self.prefetch(ti + 1);
                        self.walk(avx2, start, codes, nr, hit);
                        // Add the tree's leaves in row order: every row sums its trees in
                        // tree order, as the f32 walk does, so the sums are bit-identical.
                        for (r, &leaf) in hit[..nr].iter().enumerate() {
                            let p = self.leaf_at[leaf as usize] as usize;
                            o[r * c..(r + 1) * c]
                                .iter_mut()
                                .zip(&self.probs[p..p + c])
                                .for_each(|(a, b)| *a += b);
                        }
                    }
                    o.iter_mut().for_each(|v| *v *= inv);
                },
            );
    }

    /// [`Packed::walk_tree`], by AVX2 gathers where `avx2` (both record the same leaves).
    #[inline(always)]
    fn walk(&self, avx2: bool, start: u32, codes: &[u16], nr: usize, hit: &mut [u32]) {
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            // SAFETY: `avx2` is true only where the CPU has AVX2.
            unsafe { self.walk_tree_avx2(start, codes, nr, hit) };
            return;
        }
        let _ = avx2;
        self.walk_tree(start, codes, nr, hit);
    }

    /// [`Packed::walk_tree`] with 32 lanes in four AVX2 vectors: each step gathers the lanes'
    /// nodes and codes (8 lanes per gather) and selects the child without a branch; every
    /// `STEPS` steps the lanes on a leaf record it and take the next row, as in the scalar walk.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn walk_tree_avx2(&self, start: u32, codes: &[u16], nr: usize, hit: &mut [u32]) {
        use std::arch::x86_64::*;
        const V: usize = 4;
        const LANES: usize = 8 * V;
        const STEPS: usize = 4;
        let d = self.d;
        // Every gather below stays inside these: node indices are valid (children and
        // self-looping leaves lie in `nodes`), rows are at most `nr` and features below `d`,
        // and a code is read as the 4-byte word at its offset (one spare code at the end).
        assert!(codes.len() > (nr + 1) * d && hit.len() > nr);
        assert!(self.nodes.len() < (i32::MAX / 8) as usize);
        let np = self.nodes.as_ptr() as *const i32;
        let cp = codes.as_ptr() as *const i32;
        let mut at = [start; LANES];
        let mut row = [nr; LANES];
        for (l, r) in row.iter_mut().enumerate().take(nr) {
            *r = l;
        }
        let mut off = [0i32; LANES];
        let mut next = LANES.min(nr);
        let mut done = 0;
        let low = _mm256_set1_epi32(0xFFFF);
        while done < nr {
            for (o, &r) in off.iter_mut().zip(&row) {
                *o = (r * d) as i32;
            }
            let mut a = [_mm256_setzero_si256(); V];
            let mut ro = [_mm256_setzero_si256(); V];
            for v in 0..V {
                a[v] = _mm256_loadu_si256(at.as_ptr().add(8 * v) as *const __m256i);
                ro[v] = _mm256_loadu_si256(off.as_ptr().add(8 * v) as *const __m256i);
            }
            for _ in 0..STEPS {
                for v in 0..V {
                    // Node word 0: code | feature << 16; word 1: left.
                    let w = _mm256_i32gather_epi32::<8>(np, a[v]);
                    let left = _mm256_i32gather_epi32::<8>(np.add(1), a[v]);
                    let code = _mm256_and_si256(w, low);
                    let f = _mm256_add_epi32(ro[v], _mm256_srli_epi32::<16>(w));
                    let x = _mm256_and_si256(_mm256_i32gather_epi32::<2>(cp, f), low);
                    a[v] = _mm256_sub_epi32(left, _mm256_cmpgt_epi32(x, code));
                }
            }
            for v in 0..V {
                _mm256_storeu_si256(at.as_mut_ptr().add(8 * v) as *mut __m256i, a[v]);
            }
            for l in 0..LANES {
                let leaf = self.nodes[at[l] as usize].code == LEAF_CODE;
                hit[row[l]] = at[l];
                done += (leaf & (row[l] < nr)) as usize;
                row[l] = if leaf { next.min(nr) } else { row[l] };
                at[l] = if leaf { start } else { at[l] };
                next += leaf as usize;
            }
        }
    }

    /// Walks the `nr` coded rows of `codes` through the tree starting at node `start`, writing
    /// each row's leaf node into `hit[row]`. `LANES` rows walk at once (their independent
    /// loads overlap) without a data-dependent branch: every lane takes `STEPS` steps (a lane
    /// on a leaf stays there), then each lane on a leaf records it and takes the next row, by
    /// selects, so no mispredicted branch flushes the lanes' loads in flight. Once every row
    /// is handed out, finished lanes walk the spare row `nr` until the last real row is done.
    #[inline(always)]
    fn walk_tree(&self, start: u32, codes: &[u16], nr: usize, hit: &mut [u32]) {
        const LANES: usize = 16;
        const STEPS: usize = 2;
        let d = self.d;
        let nodes = &self.nodes[..];
        let codes = &codes[..(nr + 1) * d];
        let hit = &mut hit[..nr + 1];
        let mut at = [start; LANES];
        // Each lane's row.
        let mut row = [nr; LANES];
        for (l, r) in row.iter_mut().enumerate().take(nr) {
            *r = l;
        }
        let mut next = LANES.min(nr);
        let mut done = 0;
        while done < nr {
            for _ in 0..STEPS {
                for l in 0..LANES {
                    let nd = nodes[at[l] as usize];
                    at[l] = nd.left + (codes[row[l] * d + nd.feature as usize] > nd.code) as u32;
                }
            }
            for l in 0..LANES {
                let leaf = nodes[at[l] as usize].code == LEAF_CODE;
                hit[row[l]] = at[l];
                done += (leaf & (row[l] < nr)) as usize;
                row[l] = if leaf { next.min(nr) } else { row[l] };
                at[l] = if leaf { start } else { at[l] };
                next += leaf as usize;
            }
        }
    }
}

/// Whether the vector walk runs here: the CPU has AVX2 and `NEUVOLEX_FOREST_WALK` is not
/// `scalar` (which benchmarks set to time the scalar walk).
pub(crate) fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
            && std::env::var("NEUVOLEX_FOREST_WALK").as_deref() != Ok("scalar")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Rows coded and walked together: their codes stay in L2 while every tree walks them.
const BLOCK: usize = 1024;

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
