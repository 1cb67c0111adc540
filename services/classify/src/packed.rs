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
//! A value's code is found in two steps: a table per feature, indexed by the top bits of the
//! value's order-preserving integer key, gives the first edge of the value's bucket, and a
//! branch-free binary search over a window of a fixed power-of-two width (the fullest bucket,
//! edges padded with `+inf`) counts the bucket's edges below the value: a few steps instead of
//! a search over all of the feature's edges.
//!
//! A block of rows is coded feature by feature (one feature's table stays cached), then every
//! tree walks the block in interleaved lanes (their independent loads overlap) without
//! data-dependent branches while the next tree is prefetched; each row's leaf is recorded, and
//! the leaves' fractions are added row by row in tree order, four classes at a time, so the
//! sums are the bits of the f32 walk.

use half::f16;
use rayon::prelude::*;
use std::hint::select_unpredictable;
use std::sync::OnceLock;

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
    /// Per feature: its coder over the forest's distinct split thresholds on it.
    coders: Vec<Coder>,
    /// Every tree's nodes, one after the other (a tree's `left` indices are global).
    nodes: Vec<Node>,
    /// Per tree: its first node and the offset of its first leaf's fractions in `probs`.
    trees: Vec<(u32, u32)>,
    /// Per node: the offset of its leaf's class fractions in `probs` (split nodes: 0).
    leaf_at: Vec<u32>,
    /// Leaf class fractions, `width` per leaf (`classes` padded with zeros), all trees.
    probs: Vec<f32>,
    /// `classes` rounded up to a multiple of 4, so a leaf's fractions add as whole vectors.
    width: usize,
    /// The code of every f16 bit pattern per feature, made on the first f16 prediction.
    half: HalfCodes,
}

/// A value derived from its owner and made on first use: equality ignores it (two owners
/// that are equal derive the same value).
#[derive(Debug, Clone, Default)]
pub(crate) struct Derived<T>(pub(crate) OnceLock<T>);

impl<T> PartialEq for Derived<T> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// Per feature, the code of each of the 65 536 f16 bit patterns (`feature << 16 | bits`):
/// half-precision features code by one lookup each. Made once per forest.
type HalfCodes = Derived<Vec<u16>>;

/// Rows coded together from half precision: a sub-block's features and codes stay in L2
/// while the per-feature tables take turns.
const HALF_ROWS: usize = 1024;

/// One tree as [`Packed::new`] reads it: per node `(feature, threshold, left)` with
/// self-looping leaves (threshold `+inf`), the leaf index per node (`leaf` for splits) and the
/// leaves' class fractions.
pub(crate) struct TreeView<'a> {
    pub nodes: Vec<(u32, f32, u32)>,
    pub leaf_of: &'a [u32],
    pub probs: &'a [f32],
}

/// The order-preserving integer key of a number that is not NaN (`-0.0` as `+0.0`): `a < b`
/// exactly when `key(a) < key(b)`.
#[inline(always)]
fn key(v: f32) -> u32 {
    // Adding +0 turns -0 into +0 and leaves every other number as it is.
    let b = (v + 0.0).to_bits();
    if b >> 31 == 1 {
        !b
    } else {
        b | 1 << 31
    }
}

/// Most buckets per feature, and buckets per edge: the table (2 bytes a bucket) stays within
/// L2 while a block's rows are coded.
const MAX_BUCKETS: usize = 1 << 14;
const BUCKETS_PER_EDGE: usize = 4;

/// Codes one feature's values: `#{i : e_i < v}` over its ascending distinct edges `e`.
#[derive(Debug, Clone, PartialEq)]
struct Coder {
    /// The edges, then `window` copies of `+inf` (never below any value).
    padded: Vec<f32>,
    /// The key of the first edge; bucket `b` holds keys from `low + (b << shift)`.
    low: u32,
    shift: u32,
    /// Per bucket: the number of edges whose key is below the bucket's first key; one more
    /// entry holding `n`.
    starts: Vec<u16>,
    /// A power of two at least the most edges in one bucket.
    window: usize,
}

impl Coder {
    /// The coder of a feature's split thresholds (none NaN; any order, repeats allowed), or
    /// `None` past `u16::MAX` distinct ones. -0 and +0 split alike (`v > t`), so they are one
    /// edge.
    fn from_thresholds(mut edges: Vec<f32>) -> Option<Self> {
        for t in edges.iter_mut() {
            *t += 0.0;
        }
        edges.sort_unstable_by(|a, b| a.total_cmp(b));
        edges.dedup_by(|a, b| a.to_bits() == b.to_bits());
        (edges.len() <= LEAF_CODE as usize).then(|| Self::new(edges))
    }

    /// The coder of ascending, distinct edges (at most `u16::MAX` of them, none NaN, `-0.0`
    /// and `+0.0` not both).
    fn new(edges: Vec<f32>) -> Self {
        let n = edges.len();
        let (low, high) = match (edges.first(), edges.last()) {
            (Some(&a), Some(&b)) => (key(a), key(b)),
            _ => (0, 0),
        };
        let span = (high - low) as u64;
        let most = (n * BUCKETS_PER_EDGE).clamp(1, MAX_BUCKETS) as u64;
        let mut shift = 0;
        while span >> shift >= most {
            shift += 1;
        }
        let buckets = (span >> shift) as usize + 1;
        let mut starts = Vec::with_capacity(buckets + 1);
        let mut i = 0;
        for b in 0..buckets {
            let first = low as u64 + ((b as u64) << shift);
            while i < n && (key(edges[i]) as u64) < first {
                i += 1;
            }
            starts.push(i as u16);
        }
        starts.push(n as u16);
        let most_in_one = starts.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);
        let window = (most_in_one as usize + 1).next_power_of_two();
        let mut padded = edges;
        padded.resize(n + window, f32::INFINITY);
        Coder {
            padded,
            low,
            shift,
            starts,
            window,
        }
    }

    /// The edges, ascending.
    fn edges(&self) -> &[f32] {
        &self.padded[..self.padded.len() - self.window]
    }

    /// [`Coder::code`] of every f16 bit pattern into `out` (65 536 codes, zeroed by the
    /// caller: NaN patterns keep 0), by one merge of the ascending halves with the edges.
    fn half_codes(&self, out: &mut [u16]) {
        let e = self.edges();
        // +0 to +inf ascend with their bits; -0 to -inf too, so -inf to -0 ascend backwards.
        for run in [
            &mut (0..=0x7c00u16) as &mut dyn Iterator<Item = u16>,
            &mut (0x8000..=0xfc00u16).rev(),
        ] {
            let mut i = 0;
            for b in run {
                let v = f16::from_bits(b).to_f32();
                while i < e.len() && e[i] < v {
                    i += 1;
                }
                out[b as usize] = i as u16;
            }
        }
    }

    /// `#{i : e_i < v}` (0 for NaN), without data-dependent branches.
    #[inline(always)]
    fn code(&self, v: f32) -> u16 {
        // A key below the first edge's is in bucket 0 (whose start is 0); one past the last
        // bucket in the last.
        let last = self.starts.len() - 2;
        let b = ((key(v).saturating_sub(self.low) >> self.shift) as usize).min(last);
        let e = &self.padded[..];
        // Every edge before the bucket is below `v`, every edge past it above, and the window
        // from the bucket's start covers the bucket (its tail is edges of later buckets or
        // the padding, all above `v`).
        // SAFETY: `b <= last`, inside `starts`; a bucket starts at most at the number of edges,
        // and the search reads below its start plus `window`, inside `padded` (the edges and
        // `window` more).
        let (mut base, mut len) = (
            unsafe { *self.starts.get_unchecked(b) } as usize,
            self.window,
        );
        while len > 1 {
            let half = len / 2;
            let below = unsafe { *e.get_unchecked(base + half - 1) } < v;
            base = select_unpredictable(below, base + half, base);
            len -= half;
        }
        let c = base + (unsafe { *e.get_unchecked(base) } < v) as usize;
        select_unpredictable(v.is_nan(), 0, c) as u16
    }
}

impl Packed {
    /// Packs the trees, or `None` where a feature has too many distinct thresholds for u16
    /// codes or there are too many features.
    pub(crate) fn new(d: usize, classes: usize, trees: &[TreeView<'_>], leaf: u32) -> Option<Self> {
        if d > u16::MAX as usize + 1 {
            return None;
        }
        for t in trees {
            // The walk reads without bounds checks, so a forest that is not well formed (one
            // read from a damaged file) is not packed: every split's feature is below `d` and its
            // children inside its tree, its threshold a number, every leaf's fractions inside
            // its tree's.
            let n = t.nodes.len();
            if n == 0 || t.leaf_of.len() != n || !t.probs.len().is_multiple_of(classes) {
                return None;
            }
            let well_formed = t.nodes.iter().zip(t.leaf_of).all(|(&(f, thr, left), &lf)| {
                if lf != leaf {
                    ((lf as usize) + 1) * classes <= t.probs.len()
                } else {
                    (f as usize) < d && (left as usize) + 1 < n && !thr.is_nan()
                }
            });
            if !well_formed {
                return None;
            }
        }
        let mut edges: Vec<Vec<f32>> = vec![Vec::new(); d];
        for t in trees {
            for (&(f, thr, _), &lf) in t.nodes.iter().zip(t.leaf_of) {
                if lf == leaf {
                    edges[f as usize].push(thr);
                }
            }
        }
        let coders: Vec<Coder> = edges
            .into_iter()
            .map(Coder::from_thresholds)
            .collect::<Option<_>>()?;
        let total: usize = trees.iter().map(|t| t.nodes.len()).sum();
        let total_u32 = u32::try_from(total).ok()?;
        let mut nodes = Vec::with_capacity(total);
        let mut leaf_at = Vec::with_capacity(total);
        let width = classes.next_multiple_of(4);
        let mut probs = Vec::new();
        let mut starts = Vec::with_capacity(trees.len());
        for t in trees {
            let start = nodes.len() as u32;
            let leaf0 = probs.len() / width;
            for p in t.probs.chunks_exact(classes) {
                probs.extend_from_slice(p);
                probs.resize(probs.len() + width - classes, 0.0);
            }
            for (i, &(f, thr, left)) in t.nodes.iter().enumerate() {
                if t.leaf_of[i] != leaf {
                    nodes.push(Node {
                        code: LEAF_CODE,
                        feature: 0,
                        left: start + i as u32,
                    });
                    leaf_at.push(((leaf0 + t.leaf_of[i] as usize) * width) as u32);
                } else {
                    let e = coders[f as usize].edges();
                    let j = e
                        .binary_search_by(|a| a.total_cmp(&(thr + 0.0)))
                        .expect("every threshold is an edge");
                    nodes.push(Node {
                        code: j as u16,
                        feature: f as u16,
                        left: start + left,
                    });
                    leaf_at.push(0);
                }
            }
            starts.push((start, (leaf0 * width) as u32));
        }
        debug_assert_eq!(nodes.len() as u32, total_u32);
        u32::try_from(probs.len()).ok()?;
        Some(Packed {
            d,
            classes,
            coders,
            nodes,
            trees: starts,
            leaf_at,
            probs,
            width,
            half: HalfCodes::default(),
        })
    }

    /// Codes rows `x` (`rows x d`) into `out`, feature by feature.
    fn code_rows(&self, x: &[f32], out: &mut [u16]) {
        let d = self.d;
        for (f, c) in self.coders.iter().enumerate() {
            if c.edges().is_empty() {
                for o in out.chunks_exact_mut(d) {
                    o[f] = 0;
                }
                continue;
            }
            for (o, row) in out.chunks_exact_mut(d).zip(x.chunks_exact(d)) {
                o[f] = c.code(row[f]);
            }
        }
    }

    /// The per-feature codes of every f16 bit pattern ([`HalfCodes`]), made on first use.
    fn half_table(&self) -> &[u16] {
        self.half.0.get_or_init(|| {
            let mut t = vec![0u16; self.d << 16];
            t.par_chunks_mut(1 << 16)
                .zip(&self.coders)
                .for_each(|(o, c)| c.half_codes(o));
            t
        })
    }

    /// Codes half-precision rows `x` into `out` by lookup: the same codes as [`Self::code_rows`]
    /// gives their f32 values.
    fn code_rows_f16(&self, table: &[u16], x: &[f16], out: &mut [u16]) {
        let d = self.d;
        for (xs, os) in x.chunks(HALF_ROWS * d).zip(out.chunks_mut(HALF_ROWS * d)) {
            for (f, t) in table.chunks_exact(1 << 16).enumerate() {
                let t: &[u16; 1 << 16] = t.try_into().expect("65 536 codes per feature");
                for (o, row) in os.chunks_exact_mut(d).zip(xs.chunks_exact(d)) {
                    o[f] = t[row[f].to_bits() as usize];
                }
            }
        }
    }

    /// Hints the cache to fetch what walking a tree reads: its nodes, their leaf offsets and
    /// its leaves' class fractions.
    #[inline(always)]
    fn prefetch(&self, tree: usize) {
        let Some(&(start, prob)) = self.trees.get(tree) else {
            return;
        };
        let (end, prob_end) = self
            .trees
            .get(tree + 1)
            .map_or((self.nodes.len(), self.probs.len()), |t| {
                (t.0 as usize, t.1 as usize)
            });
        prefetch_range(&self.nodes[start as usize..end]);
        prefetch_range(&self.leaf_at[start as usize..end]);
        prefetch_range(&self.probs[prob as usize..prob_end]);
    }

    /// Mean class fractions over the trees of every row of `x`, added into `out`
    /// (`rows x classes`, zeroed by the caller), scaled by `inv`.
    pub(crate) fn predict_into(&self, x: &[f32], out: &mut [f32], inv: f32) {
        self.predict_coded(x, out, inv, |xb, codes| self.code_rows(xb, codes));
    }

    /// [`Self::predict_into`] of half-precision rows, coded by lookup: the same bits as
    /// predicting their f32 values.
    pub(crate) fn predict_into_f16(&self, x: &[f16], out: &mut [f32], inv: f32) {
        let table = self.half_table();
        self.predict_coded(x, out, inv, |xb, codes| {
            self.code_rows_f16(table, xb, codes)
        });
    }

    /// The blocked prediction of [`Self::predict_into`], with `code` coding a block's rows.
    fn predict_coded<T: Sync>(
        &self,
        x: &[T],
        out: &mut [f32],
        inv: f32,
        code: impl Fn(&[T], &mut [u16]) + Sync,
    ) {
        let (d, c, w, block) = (self.d, self.classes, self.width, BLOCK);
        out.par_chunks_mut(block * c)
            .zip(x.par_chunks(block * d))
            .for_each_init(
                // Codes of a block of rows and LANES all-zero spare rows that idle lanes walk;
                // each row's leaf in the current tree; the rows' sums, `width` apart.
                || {
                    (
                        vec![0u16; (block + LANES) * d],
                        vec![0u32; block + LANES],
                        vec![0f32; block * w],
                    )
                },
                |(codes, leaves, acc), (o, xb)| {
                    let nr = xb.len() / d;
                    code(xb, &mut codes[..nr * d]);
                    codes[nr * d..(nr + LANES) * d].fill(0);
                    let acc = &mut acc[..nr * w];
                    acc.fill(0.0);
                    for (ti, &(start, _)) in self.trees.iter().enumerate() {
                        self.prefetch(ti + 1);
                        self.walk_tree(start, codes, nr, leaves);
                        // Leaves are added row by row in tree order, as every walk does, so
                        // the sums are the same bits; four classes at a time.
                        for (a, &leaf) in acc.chunks_exact_mut(w).zip(&leaves[..nr]) {
                            let p = self.leaf_at[leaf as usize] as usize;
                            add4(a, &self.probs[p..p + w]);
                        }
                    }
                    for (o, a) in o.chunks_exact_mut(c).zip(acc.chunks_exact(w)) {
                        for (o, a) in o.iter_mut().zip(a) {
                            *o += a * inv;
                        }
                    }
                },
            );
    }

    /// Walks the `nr` coded rows of `codes` through the tree starting at node `start`, and
    /// records each row's leaf in `leaves`. `LANES` rows walk at once (their independent loads
    /// overlap) for `STEPS` unconditional steps (leaves loop to themselves); then every lane on a
    /// leaf takes the next row by selects, without a branch, so no lane idles while another
    /// walks a deeper path. Lanes past the last row walk the all-zero spare rows `nr..nr +
    /// LANES` until every lane is on one.
    #[inline(always)]
    fn walk_tree(&self, start: u32, codes: &[u16], nr: usize, leaves: &mut [u32]) {
        let d = self.d;
        let nodes = &self.nodes[..];
        assert!(codes.len() >= (nr + LANES) * d && leaves.len() >= nr + LANES);
        assert!((start as usize) < nodes.len());
        let mut at = [start; LANES];
        let mut row: [usize; LANES] = std::array::from_fn(|l| if l < nr { l } else { nr + l });
        // Each lane's row offset into `codes`.
        let mut off: [usize; LANES] = std::array::from_fn(|l| row[l] * d);
        let mut next = LANES.min(nr);
        loop {
            for _ in 1..STEPS {
                for l in 0..LANES {
                    // SAFETY: `at[l]` is `start` or a `left`/`left + 1` of a node of this
                    // tree, all inside `nodes` (`Packed::new`); `off[l]` is a row below
                    // `nr + LANES` times `d` and `feature < d`, inside `codes` (asserted above).
                    let nd = unsafe { *nodes.get_unchecked(at[l] as usize) };
                    let v = unsafe { *codes.get_unchecked(off[l] + nd.feature as usize) };
                    at[l] = nd.left + (v > nd.code) as u32;
                }
            }
            // The last step also tells which lanes were on their leaf already (a lane that
            // reaches its leaf in this step is refilled one round later).
            let mut idle = true;
            for l in 0..LANES {
                // SAFETY: as above.
                let nd = unsafe { *nodes.get_unchecked(at[l] as usize) };
                let v = unsafe { *codes.get_unchecked(off[l] + nd.feature as usize) };
                at[l] = nd.left + (v > nd.code) as u32;
                let leaf = nd.code == LEAF_CODE;
                leaves[row[l]] = at[l];
                let more = next < nr;
                let fresh = select_unpredictable(more, next, nr + l);
                row[l] = select_unpredictable(leaf, fresh, row[l]);
                off[l] = row[l] * d;
                at[l] = select_unpredictable(leaf, start, at[l]);
                next += (leaf & more) as usize;
                idle &= row[l] >= nr;
            }
            if idle {
                return;
            }
        }
    }
}

/// `a += b` element-wise, four lanes at a time (`a.len() == b.len()`, a multiple of 4).
#[inline(always)]
fn add4(a: &mut [f32], b: &[f32]) {
    for (a, b) in a.chunks_exact_mut(4).zip(b.chunks_exact(4)) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_add_ps, _mm_loadu_ps, _mm_storeu_ps};
            // SAFETY: SSE is part of x86_64; both chunks hold exactly 4 floats.
            unsafe {
                let s = _mm_add_ps(_mm_loadu_ps(a.as_ptr()), _mm_loadu_ps(b.as_ptr()));
                _mm_storeu_ps(a.as_mut_ptr(), s);
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        for k in 0..4 {
            a[k] += b[k];
        }
    }
}

/// Hints the cache to fetch `s`, a line at a time.
#[inline(always)]
fn prefetch_range<T>(s: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let (p, n) = (s.as_ptr() as *const i8, std::mem::size_of_val(s));
        for b in (0..n).step_by(64) {
            // SAFETY: prefetching is a hint; the address is inside `s`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.add(b)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = s;
}

/// Rows that walk a tree at once.
const LANES: usize = 8;

/// Rows coded and walked together, so each tree's nodes and leaves are fetched once per block.
/// Larger blocks were faster on the bench (1000 trees, 64 features), though past L2: at 300
/// trees on Zen 4, 2048 rows 3.11 s, 4096 2.56-2.80 s, 8192 2.54-2.58 s, 16384 2.41-2.68 s,
/// 32768 2.49 s (interleaved: 4096 2.78-2.80 s against 16384 2.63-2.68 s); the code loads of
/// the lanes overlap, so the codes need not stay in L2.
pub(crate) const BLOCK: usize = 16384;

/// Unconditional steps between refills: a row wastes about half of them after reaching its leaf,
/// and each refill costs about two steps' work. 12 was fastest of 6, 8, 12 and 16 on the
/// bench's deep trees (leaves at depth 20–40).
const STEPS: usize = 12;

#[cfg(test)]
mod tests {
    use super::{key, Coder};
    use neuvolex_bricks::rng::Rng;

    fn coder(e: Vec<f32>) -> Coder {
        Coder::from_thresholds(e).expect("few thresholds")
    }

    fn check(c: &Coder, v: f32) {
        let want = if v.is_nan() {
            0
        } else {
            c.edges().iter().filter(|&&t| t < v).count()
        };
        assert_eq!(c.code(v) as usize, want, "{v:e} ({:#x})", v.to_bits());
    }

    #[test]
    fn codes_count_the_edges_below() {
        let c = coder(vec![-1.0f32, 0.0, 0.5, 2.0, 7.0]);
        for v in [
            -5.0f32, -1.0, -0.5, -0.0, 0.0, 0.25, 0.5, 1.0, 2.0, 3.0, 7.0, 8.0,
        ] {
            check(&c, v);
        }
        assert_eq!(c.code(f32::NAN), 0);
        assert_eq!(c.code(-f32::NAN), 0);
        assert_eq!(c.code(f32::INFINITY), 5);
        assert_eq!(c.code(f32::NEG_INFINITY), 0);
        assert_eq!(coder(vec![]).code(3.0), 0);
        assert_eq!(coder(vec![]).code(f32::INFINITY), 0);
    }

    #[test]
    fn keys_keep_the_order() {
        let v = [
            f32::NEG_INFINITY,
            -f32::MAX,
            -1.0,
            -f32::MIN_POSITIVE,
            -1e-45,
            0.0,
            1e-45,
            f32::MIN_POSITIVE,
            1.0,
            f32::MAX,
            f32::INFINITY,
        ];
        for w in v.windows(2) {
            assert!(key(w[0]) < key(w[1]), "{} {}", w[0], w[1]);
        }
        assert_eq!(key(-0.0), key(0.0));
    }

    /// The lookup codes of half precision equal coding the widened value, for every f16 bit
    /// pattern, on edge sets in and beyond f16's range and between its values.
    #[test]
    fn half_codes_equal_coding_every_widened_pattern() {
        let mut rng = Rng::new(11);
        for case in 0..40 {
            let n = [0usize, 1, 3, 50, 700, 4000][case % 6];
            let e: Vec<f32> = (0..n)
                .map(|_| match case % 4 {
                    0 => rng.uniform(-3.0, 3.0),
                    1 => rng.uniform(-1e5, 1e5),
                    2 => rng.uniform(-1e-6, 1e-6),
                    _ => half::f16::from_f32(rng.uniform(-60.0, 60.0)).to_f32(),
                })
                .chain((case % 3 == 0).then_some(-0.0))
                .collect();
            let c = coder(e);
            let mut t = vec![0u16; 1 << 16];
            c.half_codes(&mut t);
            for b in 0..=u16::MAX {
                let v = half::f16::from_bits(b).to_f32();
                assert_eq!(t[b as usize], c.code(v), "case {case}, {v:e} ({b:#06x})");
            }
        }
    }

    /// Against counting, on edge sets that are spread, clustered (one bucket holding most),
    /// tiny, at the extremes of the number line and with both zeros; values at, next to and
    /// between the edges, and the special numbers.
    #[test]
    fn codes_equal_counting_on_random_edges() {
        let mut rng = Rng::new(7);
        let specials = [
            0.0f32,
            -0.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MAX,
            -f32::MAX,
            f32::MIN_POSITIVE,
            1e-45,
            -1e-45,
        ];
        for case in 0..200 {
            let n = [1usize, 2, 3, 7, 100, 1000, 5000][case % 7];
            let mut e: Vec<f32> = (0..n)
                .map(|_| match case % 5 {
                    0 => rng.uniform(-3.0, 3.0),
                    1 => 1.0 + rng.uniform(0.0, 1e-3),
                    2 => rng.uniform(-1e-38, 1e-38),
                    3 => f32::from_bits(rng.next_u64() as u32 & 0xff7f_ffff),
                    _ => (rng.below(40) as f32 - 20.0) * 0.25,
                })
                .collect();
            if case % 3 == 0 {
                e.push(-0.0);
                e.push(f32::INFINITY);
            }
            let c = coder(e);
            let edges = c.edges().to_vec();
            for &t in &edges {
                for v in [t, t.next_up(), t.next_down(), -t, t * 0.5] {
                    check(&c, v);
                }
            }
            for &v in &specials {
                check(&c, v);
            }
            for _ in 0..200 {
                check(&c, f32::from_bits(rng.next_u64() as u32));
                check(&c, rng.uniform(-4.0, 4.0));
            }
        }
    }
}
