//! A random forest for dense per-voxel features, with scikit-learn's semantics for the settings
//! the paper uses: exact CART splits on Gini impurity, `sqrt(d)` candidate features per split
//! counting only features that vary in the node (as scikit-learn), no bootstrap, `min_samples_split`,
//! and `predict_proba` as the mean of the trees' leaf class fractions.
//!
//! Trees are trained in parallel from per-tree seeds, so a forest is deterministic for any
//! number of threads. Prediction walks flat node arrays tree by tree over blocks of rows, so
//! one tree stays in cache while a block of rows passes through it.

use crate::packed::{Packed, TreeView};
use neuvolex_bricks::rng::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Features considered per split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum MaxFeatures {
    /// `max(1, floor(sqrt(d)))`, the paper's setting.
    Sqrt,
    /// All features (bagging-free CART ensembles).
    All,
    /// A fixed number.
    Count(usize),
}

/// How samples are weighted by class.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ClassWeight {
    /// Every sample weighs 1 (the paper).
    None,
    /// Each class weighs `n / (classes * n_class)` in total, as scikit-learn's "balanced".
    Balanced,
}

/// Forest settings; defaults are the paper's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ForestConfig {
    /// Number of trees.
    pub trees: usize,
    /// A node with fewer samples becomes a leaf.
    pub min_samples_split: usize,
    /// Candidate features per split.
    pub max_features: MaxFeatures,
    /// Maximum depth (`None`: grow until pure or too small).
    pub max_depth: Option<usize>,
    /// Class weighting.
    pub class_weight: ClassWeight,
    /// Seed of the per-tree feature draws.
    pub seed: u64,
}

impl Default for ForestConfig {
    fn default() -> Self {
        ForestConfig {
            trees: 1000,
            min_samples_split: 8,
            max_features: MaxFeatures::Sqrt,
            max_depth: None,
            class_weight: ClassWeight::None,
            seed: 0,
        }
    }
}

/// Errors of training or prediction.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ForestError {
    /// The training set cannot train a classifier.
    #[error("training data: {0}")]
    Data(String),
    /// Prediction input does not match the forest.
    #[error("prediction input: {0}")]
    Input(String),
}

/// Training samples: `n` rows of `d` features (row-major) and a class index per row.
#[derive(Debug, Clone, Copy)]
pub struct Dataset<'a> {
    /// Features, `n x d`.
    pub x: &'a [f32],
    /// Class index of every row, `0..classes`.
    pub y: &'a [u16],
    /// Features per row.
    pub d: usize,
    /// Number of classes.
    pub classes: usize,
}

const LEAF: u32 = u32::MAX;

/// One node: a split on `feature <= threshold`, or a leaf (`feature == LEAF`, `left` = leaf index).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Node {
    feature: u32,
    threshold: f32,
    left: u32,
    right: u32,
}

/// A node as prediction walks it: go to `left` when `x[feature] <= threshold`, else to
/// `left + 1` (children are adjacent). Leaves loop to themselves with an infinite threshold.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Flat {
    threshold: f32,
    feature: u32,
    left: u32,
}

/// One tree in flat arrays. For prediction, leaves are made self-loops (`feature 0 <= +inf`
/// leads back to themselves), so rows can walk a fixed `depth` steps without branching.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Tree {
    nodes: Vec<Flat>,
    /// `leaves x classes` class fractions.
    probs: Vec<f32>,
    /// Leaf index of every node (`LEAF` for split nodes).
    leaf_of: Vec<u32>,
    /// Depth of the deepest leaf.
    depth: u32,
}

/// A trained forest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Forest {
    d: usize,
    classes: usize,
    trees: Vec<Tree>,
    /// The coded form prediction walks, made on first use.
    #[serde(skip)]
    packed: PackedCell,
}

/// The coded forest, made on first use (`None`: the forest cannot be coded and predicts with
/// the f32 walk); equality and serialisation ignore it.
type PackedCell = crate::packed::Derived<Option<Packed>>;

/// [`FlatForest::feature`] of a leaf.
pub const LEAF_FEATURE: u32 = u32::MAX;

/// A forest in flat arrays, one entry per node of every tree one after the other
/// ([`Forest::flat`]). A row walks each tree from its root: at a split, it goes to `next` when
/// its value of `feature` is at most `threshold` (NaN included), else to `next + 1`; at a leaf
/// (`feature == LEAF_FEATURE`), `next` is the offset of the leaf's `classes` fractions in
/// `probs`. [`Forest::predict_proba`] is the sum of the leaves' fractions in tree order, times
/// `1 / trees` (computed in f32).
#[derive(Debug, Clone, PartialEq)]
pub struct FlatForest {
    /// Features per row.
    pub features: usize,
    /// Classes.
    pub classes: usize,
    /// Per node: the split's feature, or [`LEAF_FEATURE`].
    pub feature: Vec<u32>,
    /// Per node: the split's threshold (`+inf` at a leaf).
    pub threshold: Vec<f32>,
    /// Per node: the global index of the split's left child (the right child follows it), or
    /// the offset of the leaf's class fractions in `probs`.
    pub next: Vec<u32>,
    /// Per tree: the global index of its root.
    pub roots: Vec<u32>,
    /// Leaf class fractions, `classes` per leaf, all trees.
    pub probs: Vec<f32>,
    /// The most splits on any root-to-leaf path (a walk ends within `depth` steps).
    pub depth: u32,
}

/// Sorts `v` by the upper 32 bits of each item, keeping the input order of equal keys: a
/// least-significant-digit radix sort in bytes (digits shared by every key are skipped), or an
/// stable comparison sort for short slices. `tmp` is scratch.
fn sort_by_key(v: &mut Vec<u64>, tmp: &mut Vec<u64>) {
    if v.len() < 128 {
        v.sort_by_key(|x| x >> 32);
        return;
    }
    let mut hist = [[0usize; 256]; 4];
    for &x in v.iter() {
        for (b, h) in hist.iter_mut().enumerate() {
            h[(x >> (32 + 8 * b)) as usize & 255] += 1;
        }
    }
    tmp.clear();
    tmp.resize(v.len(), 0);
    for (b, h) in hist.iter().enumerate() {
        if h.contains(&v.len()) {
            continue; // every key has this byte
        }
        let mut at = [0usize; 256];
        let mut sum = 0;
        for (a, &c) in at.iter_mut().zip(h) {
            *a = sum;
            sum += c;
        }
        for &x in v.iter() {
            let k = (x >> (32 + 8 * b)) as usize & 255;
            tmp[at[k]] = x;
            at[k] += 1;
        }
        std::mem::swap(v, tmp);
    }
}

/// `v`'s bits as an unsigned integer in the order of [`f32::total_cmp`].
#[inline(always)]
fn order_key(v: f32) -> u32 {
    let b = v.to_bits();
    if b >> 31 == 1 {
        !b
    } else {
        b | 1 << 31
    }
}

/// The value whose [`order_key`] is `k`.
#[inline(always)]
fn from_order_key(k: u32) -> f32 {
    f32::from_bits(if k >> 31 == 1 { k & !(1 << 31) } else { !k })
}

/// Values closer than this count as equal when looking for split points (as scikit-learn).
const FEATURE_EPS: f32 = 1e-7;

/// The Gini proxy of a cut with class weights `left` on the left of `total`, `wl` and `wr`
/// in all: maximising `sum_k l_k^2 / w_l + sum_k r_k^2 / w_r` minimises the weighted Gini.
#[inline(always)]
fn gini_proxy(left: &[f64], total: &[f64], wl: f64, wr: f64) -> f64 {
    let mut sl = 0.0;
    let mut sr = 0.0;
    for k in 0..left.len() {
        sl += left[k] * left[k];
        let r = total[k] - left[k];
        sr += r * r;
    }
    sl / wl + sr / wr
}

/// The threshold of a cut between `v` and the next larger value: their midpoint, or `v` where
/// the midpoint rounds to `next` or overflows.
#[inline(always)]
fn cut_threshold(v: f32, next: f32) -> f32 {
    let thr = 0.5 * (v + next);
    if thr >= next || !thr.is_finite() {
        v
    } else {
        thr
    }
}

/// A feature that does not vary in a node (nor, then, in any node below it).
struct Constant;

struct Builder<'a> {
    data: Dataset<'a>,
    /// The features column by column (`d x n`): a node's values of one feature are read from
    /// one column that stays cached, not from `n` rows far apart.
    cols: Vec<f32>,
    /// Per class: the weight of each of its samples (class weights are per class).
    w: Vec<f64>,
    cfg: &'a ForestConfig,
    mtry: usize,
}

impl Builder<'_> {
    fn counts(&self, idx: &[u32], out: &mut [f64]) {
        out.iter_mut().for_each(|c| *c = 0.0);
        for &i in idx {
            let y = self.data.y[i as usize] as usize;
            out[y] += self.w[y];
        }
    }

    /// Best split of `idx` on feature `f`: (proxy improvement, threshold), if any; or
    /// [`Constant`] where `f` does not vary in `idx`.
    fn best_on(
        &self,
        idx: &[u32],
        f: usize,
        total: &[f64],
        buf: &mut Vec<u64>,
        tmp: &mut Vec<u64>,
        left: &mut [f64],
    ) -> Result<Option<(f64, f32)>, Constant> {
        let col = &self.cols[f * self.data.y.len()..][..self.data.y.len()];
        // Each sample as one integer, its value's order key above its class, so the sort
        // compares plain integers (the order of `f32::total_cmp`) and the scan reads no other
        // array. The sort is stable and a node's samples are in ascending order, so ties, which
        // no split point separates, fall in index order.
        // The extremes come first, so a feature constant here (a dead unit) costs no sort.
        buf.clear();
        let (mut lo, mut hi) = (u32::MAX, 0u32);
        let y = self.data.y;
        buf.extend(idx.iter().map(|&i| {
            let k = order_key(col[i as usize]);
            (lo, hi) = (lo.min(k), hi.max(k));
            ((k as u64) << 32) | y[i as usize] as u64
        }));
        if from_order_key(hi) <= from_order_key(lo) + FEATURE_EPS {
            return Err(Constant);
        }
        sort_by_key(buf, tmp);
        let at = |p: usize| (from_order_key((buf[p] >> 32) as u32), buf[p] as u32);
        left.iter_mut().for_each(|c| *c = 0.0);
        let wt: f64 = total.iter().sum();
        let mut wl = 0.0f64;
        let mut best: Option<(f64, f32)> = None;
        // The class of every sample in the current group (samples that no cut separates), or
        // `MIXED`.
        const MIXED: u32 = u32::MAX;
        let (mut group, mut first) = (MIXED, true);
        let n = buf.len();
        for p in 0..n - 1 {
            let (v, y) = at(p);
            group = if first || group == y { y } else { MIXED };
            first = false;
            let y = y as usize;
            let wi = self.w[y];
            left[y] += wi;
            wl += wi;
            let (next, next_y) = at(p + 1);
            if next <= v + FEATURE_EPS {
                continue;
            }
            first = true;
            // A cut between two groups of one class is skipped: along consecutive groups of
            // one class the proxy is strictly convex in the samples moved left (a sum of
            // quadratic-over-linear terms), so its maximum is at the run's ends, cuts next to
            // another class (Fayyad and Irani's boundary points), which are evaluated. The
            // next group is checked only where it is one sample.
            if group == next_y && (p + 2 == n || at(p + 2).0 > next + FEATURE_EPS) {
                continue;
            }
            let wr = wt - wl;
            if wl <= 0.0 || wr <= 0.0 {
                continue;
            }
            let proxy = gini_proxy(left, total, wl, wr);
            if best.is_none_or(|b| proxy > b.0) {
                best = Some((proxy, cut_threshold(v, next)));
            }
        }
        Ok(best)
    }

    fn grow(&self, seed: u64) -> Tree {
        let n = self.data.y.len();
        let c = self.data.classes;
        let d = self.data.d;
        let mut rng = Rng(seed);
        let mut idx: Vec<u32> = (0..n as u32).collect();
        let mut nodes: Vec<Node> = Vec::new();
        let mut probs: Vec<f32> = Vec::new();
        let mut buf = Vec::with_capacity(n);
        let mut tmp = Vec::with_capacity(n);
        let mut right: Vec<u32> = Vec::with_capacity(n);
        let mut total = vec![0.0f64; c];
        let mut left = vec![0.0f64; c];
        let mut feats: Vec<usize> = (0..d).collect();
        // (node id, lo, hi, depth)
        nodes.push(Node {
            feature: LEAF,
            threshold: 0.0,
            left: 0,
            right: 0,
        });
        // Per node on the stack: the features found constant in an ancestor, as bits (a feature
        // constant in a node is constant in its subsets, so it is not read again).
        let words = d.div_ceil(64);
        let mut stack = vec![(0usize, 0usize, n, 0usize, vec![0u64; words])];
        let mut max_depth = 0usize;
        while let Some((id, lo, hi, depth, mut constant)) = stack.pop() {
            max_depth = max_depth.max(depth);
            let part = &idx[lo..hi];
            self.counts(part, &mut total);
            let wsum: f64 = total.iter().sum();
            let pure = total.iter().filter(|&&v| v > 0.0).count() <= 1;
            let can_split = hi - lo >= self.cfg.min_samples_split.max(2)
                && !pure
                && self.cfg.max_depth.is_none_or(|m| depth < m);
            let mut split: Option<(f64, usize, f32)> = None;
            if can_split {
                // Draw features without replacement until `mtry` of them vary in this node (as
                // scikit-learn: features constant here, such as dead units, do not use up the
                // draw), or the features run out.
                let mut tried = 0;
                let mut k = 0;
                while k < d && tried < self.mtry {
                    let j = k + rng.below(d - k);
                    feats.swap(k, j);
                    let f = feats[k];
                    k += 1;
                    if constant[f / 64] >> (f % 64) & 1 == 1 {
                        continue;
                    }
                    match self.best_on(part, f, &total, &mut buf, &mut tmp, &mut left) {
                        Ok(Some((proxy, thr))) => {
                            tried += 1;
                            if split.is_none_or(|s| proxy > s.0) {
                                split = Some((proxy, f, thr));
                            }
                        }
                        Ok(None) => {}
                        Err(Constant) => constant[f / 64] |= 1 << (f % 64),
                    }
                }
            }
            match split {
                Some((_, f, thr)) => {
                    // Partition idx[lo..hi] into <= thr | > thr, stably: every node's samples
                    // stay in ascending order, so reading a column for them walks it forwards.
                    let part = &mut idx[lo..hi];
                    let col = &self.cols[f * n..][..n];
                    right.clear();
                    let mut m = 0;
                    for q in 0..part.len() {
                        let i = part[q];
                        if col[i as usize] <= thr {
                            part[m] = i;
                            m += 1;
                        } else {
                            right.push(i);
                        }
                    }
                    part[m..].copy_from_slice(&right);
                    let l = nodes.len();
                    nodes.push(Node {
                        feature: LEAF,
                        threshold: 0.0,
                        left: 0,
                        right: 0,
                    });
                    nodes.push(Node {
                        feature: LEAF,
                        threshold: 0.0,
                        left: 0,
                        right: 0,
                    });
                    nodes[id] = Node {
                        feature: f as u32,
                        threshold: thr,
                        left: l as u32,
                        right: l as u32 + 1,
                    };
                    stack.push((l + 1, lo + m, hi, depth + 1, constant.clone()));
                    stack.push((l, lo, lo + m, depth + 1, constant));
                }
                None => {
                    let leaf = probs.len() / c;
                    probs.extend(total.iter().map(|&v| {
                        if wsum > 0.0 {
                            (v / wsum) as f32
                        } else {
                            1.0 / c as f32
                        }
                    }));
                    nodes[id] = Node {
                        feature: LEAF,
                        threshold: 0.0,
                        left: leaf as u32,
                        right: 0,
                    };
                }
            }
        }
        // Self-looping leaves for branch-free prediction.
        let mut leaf_of = vec![LEAF; nodes.len()];
        for (i, nd) in nodes.iter_mut().enumerate() {
            if nd.feature == LEAF {
                leaf_of[i] = nd.left;
                *nd = Node {
                    feature: 0,
                    threshold: f32::INFINITY,
                    left: i as u32,
                    right: i as u32,
                };
            }
        }
        let nodes = nodes
            .iter()
            .map(|n| {
                debug_assert!(n.right == n.left + 1 || n.threshold == f32::INFINITY);
                Flat {
                    threshold: n.threshold,
                    feature: n.feature,
                    left: n.left,
                }
            })
            .collect();
        Tree {
            nodes,
            probs,
            leaf_of,
            depth: max_depth as u32,
        }
    }
}

impl Forest {
    /// Trains a forest.
    pub fn fit(data: Dataset<'_>, cfg: &ForestConfig) -> Result<Forest, ForestError> {
        let n = data.y.len();
        if data.d == 0 || data.x.len() != n * data.d {
            return Err(ForestError::Data(format!(
                "{} values for {n} rows of {} features",
                data.x.len(),
                data.d
            )));
        }
        if n == 0 {
            return Err(ForestError::Data("no labelled samples".into()));
        }
        if data.classes < 2 || data.classes > u16::MAX as usize {
            return Err(ForestError::Data(format!(
                "{} classes: need at least 2",
                data.classes
            )));
        }
        if let Some(&bad) = data.y.iter().find(|&&c| c as usize >= data.classes) {
            return Err(ForestError::Data(format!(
                "class index {bad} is outside 0..{}",
                data.classes
            )));
        }
        let mut per = vec![0usize; data.classes];
        data.y.iter().for_each(|&c| per[c as usize] += 1);
        if per.iter().filter(|&&k| k > 0).count() < 2 {
            return Err(ForestError::Data(
                "only one class has samples; scribble at least two classes".into(),
            ));
        }
        if let Some(i) = data.x.iter().position(|v| !v.is_finite()) {
            return Err(ForestError::Data(format!(
                "feature {} of row {} is not finite",
                i % data.d,
                i / data.d
            )));
        }
        if cfg.trees == 0 {
            return Err(ForestError::Data("0 trees".into()));
        }
        let present = per.iter().filter(|&&k| k > 0).count() as f32;
        let w: Vec<f64> = per
            .iter()
            .map(|&k| match cfg.class_weight {
                ClassWeight::None => 1.0,
                // Computed in f32 as before, so the trees keep their bits.
                ClassWeight::Balanced => (n as f32 / (present * k as f32)) as f64,
            })
            .collect();
        let mtry = match cfg.max_features {
            MaxFeatures::Sqrt => ((data.d as f64).sqrt().floor() as usize).max(1),
            MaxFeatures::All => data.d,
            MaxFeatures::Count(k) => k.clamp(1, data.d),
        };
        let n = data.y.len();
        let mut cols = vec![0.0f32; data.x.len()];
        for (i, row) in data.x.chunks_exact(data.d).enumerate() {
            for (f, &v) in row.iter().enumerate() {
                cols[f * n + i] = v;
            }
        }
        let b = Builder {
            data,
            cols,
            w,
            cfg,
            mtry,
        };
        let trees = (0..cfg.trees)
            .into_par_iter()
            .map(|t| b.grow(cfg.seed ^ (t as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03)))
            .collect();
        Ok(Forest {
            d: data.d,
            classes: data.classes,
            trees,
            packed: PackedCell::default(),
        })
    }

    /// Features per row.
    pub fn features(&self) -> usize {
        self.d
    }

    /// Number of classes.
    pub fn classes(&self) -> usize {
        self.classes
    }

    /// Number of trees.
    pub fn trees(&self) -> usize {
        self.trees.len()
    }

    /// The forest of the first `k` trees. Trees are grown from per-tree seeds, so this equals a
    /// forest trained with `k` trees.
    pub fn truncated(&self, k: usize) -> Forest {
        Forest {
            d: self.d,
            classes: self.classes,
            trees: self.trees[..k.clamp(1, self.trees.len())].to_vec(),
            packed: PackedCell::default(),
        }
    }

    /// The coded form of the forest ([`crate::packed`]), packed on first use.
    fn packed(&self) -> Option<&Packed> {
        self.packed
            .0
            .get_or_init(|| {
                let views: Vec<TreeView<'_>> = self
                    .trees
                    .iter()
                    .map(|t| TreeView {
                        nodes: t
                            .nodes
                            .iter()
                            .map(|n| (n.feature, n.threshold, n.left))
                            .collect(),
                        leaf_of: &t.leaf_of,
                        probs: &t.probs,
                    })
                    .collect();
                Packed::new(self.d, self.classes, &views, LEAF)
            })
            .as_ref()
    }

    /// Codes the forest for prediction now ([`crate::packed`]) instead of on the first
    /// prediction; a no-op once done. Returns whether the coded form exists (a forest that
    /// cannot be coded predicts with the plain f32 walk).
    pub fn prepare(&self) -> bool {
        self.packed().is_some()
    }

    /// The forest in flat arrays for another walker (the GPU kernels of
    /// `neuvolex-classify-gpu`), checked to be well formed: every split's feature is below
    /// [`Forest::features`], its threshold a number and its children after it inside its tree,
    /// every leaf's fractions inside its tree's. Walking it as [`FlatForest`] says gives
    /// [`Forest::predict_proba`]'s leaves for every input; prediction here is unchanged.
    ///
    /// ```
    /// # use neuvolex_classify::{Dataset, Forest, ForestConfig};
    /// let x = [0.0f32, 1.0, 2.0, 3.0];
    /// let data = Dataset { x: &x, y: &[0, 0, 1, 1], d: 1, classes: 2 };
    /// let cfg = ForestConfig { trees: 2, min_samples_split: 2, ..Default::default() };
    /// let flat = Forest::fit(data, &cfg).unwrap().flat().unwrap();
    /// assert_eq!(flat.roots.len(), 2);
    /// ```
    pub fn flat(&self) -> Result<FlatForest, ForestError> {
        let bad = |t: usize, what: String| ForestError::Input(format!("tree {t}: {what}"));
        let c = self.classes;
        let total: usize = self.trees.iter().map(|t| t.nodes.len()).sum();
        if u32::try_from(total).is_err() || c == 0 {
            return Err(ForestError::Input(format!(
                "{total} nodes of {c} classes cannot be flattened"
            )));
        }
        let mut out = FlatForest {
            features: self.d,
            classes: c,
            feature: Vec::with_capacity(total),
            threshold: Vec::with_capacity(total),
            next: Vec::with_capacity(total),
            roots: Vec::with_capacity(self.trees.len()),
            probs: Vec::new(),
            depth: 0,
        };
        for (ti, t) in self.trees.iter().enumerate() {
            let n = t.nodes.len();
            if n == 0 || t.leaf_of.len() != n || !t.probs.len().is_multiple_of(c) {
                return Err(bad(ti, "its arrays do not fit together".into()));
            }
            let start = out.feature.len() as u32;
            let leaf0 = out.probs.len();
            let mut depth = vec![0u32; n];
            for (i, (nd, &lf)) in t.nodes.iter().zip(&t.leaf_of).enumerate() {
                if lf != LEAF {
                    if (lf as usize + 1) * c > t.probs.len() {
                        return Err(bad(ti, format!("leaf {lf} has no class fractions")));
                    }
                    out.feature.push(LEAF_FEATURE);
                    out.threshold.push(f32::INFINITY);
                    let at = leaf0 + lf as usize * c;
                    out.next.push(u32::try_from(at).map_err(|_| {
                        ForestError::Input(format!("{at} leaf fractions cannot be flattened"))
                    })?);
                } else {
                    let (f, thr, left) = (nd.feature, nd.threshold, nd.left as usize);
                    if f as usize >= self.d || thr.is_nan() || left <= i || left + 1 >= n {
                        return Err(bad(ti, format!("node {i} is not a well-formed split")));
                    }
                    out.feature.push(f);
                    out.threshold.push(thr);
                    out.next.push(start + left as u32);
                    depth[left] = depth[left].max(depth[i] + 1);
                    depth[left + 1] = depth[left + 1].max(depth[i] + 1);
                }
            }
            out.depth = out.depth.max(depth.iter().copied().max().unwrap_or(0));
            out.probs.extend_from_slice(&t.probs);
            out.roots.push(start);
        }
        Ok(out)
    }

    /// Depth of each tree's deepest leaf, in tree order.
    pub fn depths(&self) -> Vec<u32> {
        self.trees.iter().map(|t| t.depth).collect()
    }

    /// Total nodes in the forest.
    pub fn nodes(&self) -> usize {
        self.trees.iter().map(|t| t.nodes.len()).sum()
    }

    /// A zeroed `rows x classes` output for the rows of `x`, or the error naming ragged input.
    fn output_for(&self, values: usize) -> Result<Vec<f32>, ForestError> {
        if !values.is_multiple_of(self.d) {
            return Err(ForestError::Input(format!(
                "{values} values are not whole rows of {} features",
                self.d
            )));
        }
        Ok(vec![0.0f32; values / self.d * self.classes])
    }

    /// Class probabilities of `x` (`rows x d`), returned as `rows x classes`.
    pub fn predict_proba(&self, x: &[f32]) -> Result<Vec<f32>, ForestError> {
        let mut out = self.output_for(x.len())?;
        let inv = 1.0 / self.trees.len() as f32;
        if let Some(p) = self.packed() {
            p.predict_into(x, &mut out, inv);
            return Ok(out);
        }
        self.predict_f32(x, &mut out, inv);
        Ok(out)
    }

    /// [`Forest::predict_proba`] of half-precision features (what the feature cache holds),
    /// the same bits as predicting their f32 values: the coded forest codes each value by one
    /// lookup in a per-feature table of the 65 536 f16 patterns (made on first use), without
    /// widening the features.
    pub fn predict_proba_f16(&self, x: &[half::f16]) -> Result<Vec<f32>, ForestError> {
        let mut out = self.output_for(x.len())?;
        let inv = 1.0 / self.trees.len() as f32;
        if let Some(p) = self.packed() {
            p.predict_into_f16(x, &mut out, inv);
            return Ok(out);
        }
        self.predict_f32(&crate::cache::widen(x), &mut out, inv);
        Ok(out)
    }

    /// [`Forest::predict_proba`] by the f32 walk, without coding the features: the path for
    /// forests that cannot be coded, kept public to measure against.
    pub fn predict_proba_f32(&self, x: &[f32]) -> Result<Vec<f32>, ForestError> {
        let mut out = self.output_for(x.len())?;
        self.predict_f32(x, &mut out, 1.0 / self.trees.len() as f32);
        Ok(out)
    }

    /// The f32 walk of [`Forest::predict_proba`] into `out`.
    fn predict_f32(&self, x: &[f32], out: &mut [f32], inv: f32) {
        let c = self.classes;
        const BLOCK: usize = 1024;
        const LANES: usize = 16;
        let d = self.d;
        out.par_chunks_mut(BLOCK * c)
            .zip(x.par_chunks(BLOCK * d))
            .for_each(|(o, xb)| {
                let nr = xb.len() / d;
                for t in &self.trees {
                    let mut r0 = 0;
                    while r0 < nr {
                        let lanes = LANES.min(nr - r0);
                        let mut at = [0u32; LANES];
                        // Walk all lanes in lockstep (independent loads overlap, no branches), and
                        // stop early once every lane sits on a (self-looping) leaf.
                        let rows = &xb[r0 * d..(r0 + lanes) * d];
                        let mut step = 0;
                        while step < t.depth {
                            let mut live = false;
                            for _ in 0..4 {
                                live = false;
                                for (a, row) in at.iter_mut().zip(rows.chunks_exact(d)) {
                                    let nd = t.nodes[*a as usize];
                                    let v = row[nd.feature as usize];
                                    *a = nd.left + (v > nd.threshold) as u32;
                                    live |= nd.threshold != f32::INFINITY;
                                }
                            }
                            step += 4;
                            if !live {
                                break;
                            }
                        }
                        for (l, a) in at.iter().enumerate().take(lanes) {
                            let leaf = t.leaf_of[*a as usize] as usize;
                            let p = &t.probs[leaf * c..(leaf + 1) * c];
                            o[(r0 + l) * c..(r0 + l + 1) * c]
                                .iter_mut()
                                .zip(p)
                                .for_each(|(a, b)| *a += b);
                        }
                        r0 += lanes;
                    }
                }
                o.iter_mut().for_each(|v| *v *= inv);
            });
    }

    /// The most probable class of every row.
    pub fn predict(&self, x: &[f32]) -> Result<Vec<u16>, ForestError> {
        let p = self.predict_proba(x)?;
        Ok(p.chunks(self.classes)
            .map(|r| {
                r.iter()
                    .enumerate()
                    .fold(
                        (0usize, f32::MIN),
                        |b, (k, &v)| if v > b.1 { (k, v) } else { b },
                    )
                    .0 as u16
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_sort_equals_a_stable_sort_by_key() {
        let mut rng = Rng(7);
        let mut tmp = Vec::new();
        for (n, spread) in [
            (0, 1),
            (5, 3),
            (127, 1000),
            (128, 2),
            (3000, 1 << 30),
            (5000, 300),
        ] {
            // Keys in a narrow range (shared high bytes) and wide ones; many ties.
            let v: Vec<u64> = (0..n as u64)
                .map(|i| {
                    ((order_key(rng.below(spread) as f32 - 7.5) as u64) << 32) | (i * 7919 % 65_536)
                })
                .collect();
            let mut want = v.clone();
            want.sort_by_key(|x| x >> 32);
            let mut got = v;
            sort_by_key(&mut got, &mut tmp);
            assert_eq!(got, want, "{n} items");
        }
    }

    #[test]
    fn order_keys_sort_as_total_cmp_and_invert() {
        let mut v = vec![
            f32::NEG_INFINITY,
            -3.5,
            -1e-40,
            -0.0,
            0.0,
            1e-40,
            1e-7,
            2.0,
            f32::MAX,
            f32::INFINITY,
            f32::NAN,
            -f32::NAN,
        ];
        for &x in &v {
            assert_eq!(from_order_key(order_key(x)).to_bits(), x.to_bits());
        }
        let mut by_key = v.clone();
        by_key.sort_by_key(|&x| order_key(x));
        v.sort_by(f32::total_cmp);
        let bits = |s: &[f32]| s.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&by_key), bits(&v));
    }

    fn cfg(trees: usize) -> ForestConfig {
        ForestConfig {
            trees,
            ..Default::default()
        }
    }

    /// The best cut by evaluating every cut between distinct values (the scan before cuts
    /// inside one-class runs were skipped), in the same order and arithmetic.
    fn every_cut(b: &Builder<'_>, idx: &[u32], f: usize, total: &[f64]) -> Option<(f64, f32)> {
        let n = b.data.y.len();
        let col = &b.cols[f * n..][..n];
        let mut s: Vec<(f32, u32)> = idx.iter().map(|&i| (col[i as usize], i)).collect();
        s.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut left = vec![0.0f64; total.len()];
        let wt: f64 = total.iter().sum();
        let (mut wl, mut best) = (0.0f64, None::<(f64, f32)>);
        for p in 0..s.len() - 1 {
            let (v, i) = s[p];
            let y = b.data.y[i as usize] as usize;
            left[y] += b.w[y];
            wl += b.w[y];
            let next = s[p + 1].0;
            let wr = wt - wl;
            if next <= v + FEATURE_EPS || wl <= 0.0 || wr <= 0.0 {
                continue;
            }
            let proxy = gini_proxy(&left, total, wl, wr);
            if best.is_none_or(|b| proxy > b.0) {
                best = Some((proxy, cut_threshold(v, next)));
            }
        }
        best
    }

    #[test]
    fn skipping_cuts_inside_one_class_runs_finds_the_best_cut() {
        // Values on a coarse grid (ties) whose class follows the value with noise (runs of
        // one class), balanced and unit weights, random subsets as nodes.
        let mut r = Rng(11);
        for trial in 0..200 {
            let (n, d, classes) = (40 + r.below(260), 3, 2 + r.below(4));
            let levels = 2 + r.below(60);
            let mut x = vec![0.0f32; n * d];
            let mut y = vec![0u16; n];
            for i in 0..n {
                for f in 0..d {
                    x[i * d + f] = r.below(levels) as f32 * 0.25 - 3.0;
                }
                y[i] = if r.below(5) == 0 {
                    r.below(classes) as u16
                } else {
                    ((x[i * d] + 3.0) * 4.0) as u16 * classes as u16 / levels as u16
                };
            }
            let mut per = vec![0usize; classes];
            y.iter().for_each(|&c| per[c as usize] += 1);
            let balanced = trial % 2 == 0;
            let w: Vec<f64> = per
                .iter()
                .map(|&k| {
                    if balanced {
                        (n as f32 / (classes as f32 * k.max(1) as f32)) as f64
                    } else {
                        1.0
                    }
                })
                .collect();
            let mut cols = vec![0.0f32; n * d];
            for i in 0..n {
                for f in 0..d {
                    cols[f * n + i] = x[i * d + f];
                }
            }
            let config = cfg(1);
            let b = Builder {
                data: Dataset {
                    x: &x,
                    y: &y,
                    d,
                    classes,
                },
                cols,
                w,
                cfg: &config,
                mtry: d,
            };
            let idx: Vec<u32> = (0..n as u32).filter(|_| r.below(4) != 0).collect();
            if idx.len() < 2 {
                continue;
            }
            let mut total = vec![0.0f64; classes];
            b.counts(&idx, &mut total);
            let (mut buf, mut tmp, mut left) = (Vec::new(), Vec::new(), vec![0.0f64; classes]);
            for f in 0..d {
                // `Constant` only for a feature that does not vary in the node.
                let got = match b.best_on(&idx, f, &total, &mut buf, &mut tmp, &mut left) {
                    Ok(cut) => cut,
                    Err(Constant) => {
                        let v = idx.iter().map(|&i| b.cols[f * n + i as usize]);
                        let lo = v.clone().fold(f32::INFINITY, f32::min);
                        let hi = v.fold(f32::NEG_INFINITY, f32::max);
                        assert!(
                            hi <= lo + FEATURE_EPS,
                            "trial {trial} feature {f}: Constant over {lo}..{hi}"
                        );
                        None
                    }
                };
                let want = every_cut(&b, &idx, f, &total);
                assert_eq!(
                    got.map(|(p, t)| (p.to_bits(), t.to_bits())),
                    want.map(|(p, t)| (p.to_bits(), t.to_bits())),
                    "trial {trial} feature {f}"
                );
            }
        }
    }

    #[test]
    fn constant_features_do_not_use_up_the_draw() {
        // 100 dead (constant) features, one perfect and one weak feature: sqrt(102) = 10 draws of
        // features that vary always see both, so every root splits on the perfect one.
        let (d, n) = (102, 400);
        let mut x = vec![0.5f32; n * d];
        let mut y = vec![0u16; n];
        for i in 0..n {
            y[i] = (i % 2) as u16;
            x[i * d + 37] = y[i] as f32 * 2.0 - 1.0 + (i % 7) as f32 * 0.01;
            x[i * d + 80] = y[i] as f32 * 0.2 + (i % 5) as f32 * 0.1;
        }
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d,
                classes: 2,
            },
            &cfg(30),
        )
        .unwrap();
        for t in &f.trees {
            assert_eq!(
                t.nodes[0].feature, 37,
                "the root splits on the perfect feature"
            );
        }
    }

    #[test]
    fn one_stump_splits_at_the_midpoint() {
        let x = [0.0f32, 1.0, 2.0, 10.0, 11.0, 12.0, 13.0, 14.0];
        let y = [0u16, 0, 0, 1, 1, 1, 1, 1];
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 1,
                classes: 2,
            },
            &ForestConfig {
                trees: 1,
                min_samples_split: 2,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(f.trees[0].nodes[0].threshold, 6.0);
        assert_eq!(f.trees[0].depth, 1);
        assert_eq!(f.predict(&[5.9, 6.1]).unwrap(), vec![0, 1]);
        assert_eq!(f.predict_proba(&[-5.0]).unwrap(), vec![1.0, 0.0]);
    }

    #[test]
    fn min_samples_split_stops_growth() {
        // 7 samples < 8: the root is a leaf with the class fractions.
        let x = [0.0f32, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let y = [0u16, 0, 0, 1, 1, 1, 1];
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 1,
                classes: 2,
            },
            &cfg(3),
        )
        .unwrap();
        assert_eq!(f.nodes(), 3);
        let p = f.predict_proba(&[0.0]).unwrap();
        assert!((p[0] - 3.0 / 7.0).abs() < 1e-6 && (p[1] - 4.0 / 7.0).abs() < 1e-6);
    }

    fn xor(n: usize) -> (Vec<f32>, Vec<u16>) {
        let mut r = Rng(3);
        let mut x = Vec::new();
        let mut y = Vec::new();
        for _ in 0..n {
            let (a, b) = (
                (r.next_u64() % 1000) as f32 / 1000.0,
                (r.next_u64() % 1000) as f32 / 1000.0,
            );
            x.extend([
                a,
                b,
                (r.next_u64() % 1000) as f32 / 1000.0,
                (r.next_u64() % 1000) as f32 / 1000.0,
            ]);
            y.push(((a > 0.5) ^ (b > 0.5)) as u16);
        }
        (x, y)
    }

    #[test]
    fn learns_xor_with_noise_features_and_probabilities_sum_to_one() {
        let (x, y) = xor(2000);
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 4,
                classes: 2,
            },
            &cfg(50),
        )
        .unwrap();
        let (xt, yt) = xor(500);
        let pred = f.predict(&xt[..]).unwrap();
        let acc = pred.iter().zip(&yt).filter(|(a, b)| a == b).count() as f64 / 500.0;
        assert!(acc > 0.9, "accuracy {acc}");
        for row in f.predict_proba(&xt).unwrap().chunks(2) {
            assert!((row[0] + row[1] - 1.0).abs() < 1e-5);
        }
    }

    /// Walks one row through one tree node by node.
    fn naive(t: &Tree, row: &[f32]) -> usize {
        let mut a = 0usize;
        while t.leaf_of[a] == LEAF {
            let n = t.nodes[a];
            a = if row[n.feature as usize] <= n.threshold {
                n.left as usize
            } else {
                n.left as usize + 1
            };
        }
        t.leaf_of[a] as usize
    }

    #[test]
    fn lockstep_prediction_equals_a_naive_walk_and_sub_forests_equal_small_ones() {
        let (n, d, c) = (700, 6, 3);
        let x: Vec<f32> = (0..n * d)
            .map(|i| ((i * 2654435761usize) % 1000) as f32 / 100.0)
            .collect();
        let y: Vec<u16> = (0..n)
            .map(|r| (x[r * d] + x[r * d + 1] * 0.5) as u16 % c as u16)
            .collect();
        let data = Dataset {
            x: &x,
            y: &y,
            d,
            classes: c,
        };
        let f = Forest::fit(data, &cfg(12)).unwrap();
        let p = f.predict_proba(&x).unwrap();
        for r in 0..n {
            let row = &x[r * d..(r + 1) * d];
            let mut want = vec![0.0f32; c];
            for t in &f.trees {
                let l = naive(t, row);
                for (w, p) in want.iter_mut().zip(&t.probs[l * c..(l + 1) * c]) {
                    *w += p / 12.0;
                }
            }
            for k in 0..c {
                assert!((p[r * c + k] - want[k]).abs() < 1e-5, "row {r}");
            }
        }
        // The first k trees of a forest are the forest trained with k trees.
        assert_eq!(f.truncated(5), Forest::fit(data, &cfg(5)).unwrap());
    }

    /// Walking the flat arrays as their docs say gives `predict_proba` bit for bit (on
    /// thresholds, next to them, infinite and NaN inputs), and damaged forests are refused.
    #[test]
    fn flat_walk_equals_predict_proba_bit_for_bit() {
        let (n, d, c) = (2000, 4, 3);
        let x: Vec<f32> = (0..n * d)
            .map(|i| ((i * 2654435761usize) % 991) as f32 / 41.0 - 11.0)
            .collect();
        let y: Vec<u16> = (0..n)
            .map(|r| ((x[r * d] * x[r * d + 3]).abs() as u16 + (x[r * d + 1] > 0.0) as u16) % 3)
            .collect();
        let data = Dataset {
            x: &x,
            y: &y,
            d,
            classes: c,
        };
        let f = Forest::fit(data, &cfg(9)).unwrap();
        let flat = f.flat().unwrap();
        assert_eq!((flat.features, flat.classes, flat.roots.len()), (d, c, 9));
        assert_eq!(flat.depth, *f.depths().iter().max().unwrap());
        let mut probe = x.clone();
        for (&fe, &t) in flat.feature.iter().zip(&flat.threshold).take(300) {
            if fe != LEAF_FEATURE {
                let mut row = x[..d].to_vec();
                row[fe as usize] = t;
                probe.extend(&row);
                row[fe as usize] = t.next_up();
                probe.extend(&row);
            }
        }
        probe.extend([f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -0.0]);
        let want = f.predict_proba(&probe).unwrap();
        let inv = 1.0 / 9.0f32;
        for (r, row) in probe.chunks_exact(d).enumerate() {
            let mut acc = vec![0.0f32; c];
            for &root in &flat.roots {
                let mut at = root as usize;
                let mut steps = 0;
                while flat.feature[at] != LEAF_FEATURE {
                    let right = row[flat.feature[at] as usize] > flat.threshold[at];
                    at = flat.next[at] as usize + right as usize;
                    steps += 1;
                }
                assert!(steps <= flat.depth);
                let p = flat.next[at] as usize;
                acc.iter_mut()
                    .zip(&flat.probs[p..p + c])
                    .for_each(|(a, b)| *a += b);
            }
            for k in 0..c {
                assert_eq!(
                    (acc[k] * inv).to_bits(),
                    want[r * c + k].to_bits(),
                    "row {r} class {k}"
                );
            }
        }
        let mut bad = f.truncated(2);
        bad.trees[1].nodes[0].feature = d as u32;
        assert!(bad.flat().is_err());
        let mut bad = f.truncated(2);
        bad.trees[0].nodes[0].left = 0;
        assert!(bad.flat().is_err());
        let mut bad = f.truncated(2);
        bad.trees[0].probs.pop();
        assert!(bad.flat().is_err());
    }

    #[test]
    fn coded_prediction_equals_the_f32_walk_bit_for_bit() {
        let (n, d, c) = (3000, 5, 4);
        let x: Vec<f32> = (0..n * d)
            .map(|i| ((i * 2654435761usize) % 997) as f32 / 37.0 - 9.0)
            .collect();
        let y: Vec<u16> = (0..n)
            .map(|r| ((x[r * d] * x[r * d + 2]).abs() as u16 + (x[r * d + 1] > 0.0) as u16) % 4)
            .collect();
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d,
                classes: c,
            },
            &cfg(25),
        )
        .unwrap();
        assert!(f.prepare(), "small forests are coded");
        // Inputs exactly on thresholds, next to them, outside the range, infinite and NaN.
        let mut probe = x[..200 * d].to_vec();
        for t in &f.trees {
            for nd in t
                .nodes
                .iter()
                .filter(|nd| nd.threshold.is_finite())
                .take(40)
            {
                let mut row = vec![0.0f32; d];
                for (k, v) in row.iter_mut().enumerate() {
                    *v = if k == nd.feature as usize {
                        nd.threshold
                    } else {
                        x[k]
                    };
                }
                probe.extend(&row);
                row[nd.feature as usize] = f32::from_bits(nd.threshold.to_bits() + 1);
                probe.extend(&row);
            }
        }
        probe.extend([f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1e30, 1e30]);
        let want = {
            let mut o = vec![0.0f32; probe.len() / d * c];
            f.predict_f32(&probe, &mut o, 1.0 / 25.0);
            o
        };
        let got = f.predict_proba(&probe).unwrap();
        let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&want));
        // Several blocks of rows with a partial last one, and fewer rows than lanes.
        let block = crate::packed::BLOCK;
        let many: Vec<f32> = x
            .iter()
            .cycle()
            .take((2 * block + 5) * d)
            .copied()
            .collect();
        for rows in [1, 3, 7, 9, block - 1, block, block + 1, 2 * block + 5] {
            let part = &many[..rows * d];
            let mut want = vec![0.0f32; rows * c];
            f.predict_f32(part, &mut want, 1.0 / 25.0);
            assert_eq!(
                bits(&f.predict_proba(part).unwrap()),
                bits(&want),
                "{rows} rows"
            );
        }
        // A forest that is not well formed (as from a damaged file) is never walked unchecked.
        let mut bad = f.truncated(3);
        bad.trees[1].nodes[0].feature = d as u32;
        assert!(bad.packed().is_none());
        let mut bad = f.truncated(3);
        let last = bad.trees[2].nodes.len() as u32 - 1;
        bad.trees[2].nodes[0].left = last;
        assert!(bad.packed().is_none());
    }

    #[test]
    fn half_precision_prediction_equals_predicting_the_widened_values_bit_for_bit() {
        use half::f16;
        let (n, d, c) = (3000, 6, 3);
        // Trained on f16-rounded values, as the service's cache holds them, so thresholds sit
        // between neighbouring f16 values.
        let x: Vec<f32> = (0..n * d)
            .map(|i| f16::from_f32(((i * 2654435761usize) % 1999) as f32 / 91.0 - 11.0).to_f32())
            .collect();
        let y: Vec<u16> = (0..n)
            .map(|r| ((x[r * d] - x[r * d + 3]).abs() as u16 + (x[r * d + 1] > 0.5) as u16) % 3)
            .collect();
        let f = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d,
                classes: c,
            },
            &cfg(20),
        )
        .unwrap();
        assert!(f.prepare());
        let mut probe: Vec<f16> = x.iter().map(|&v| f16::from_f32(v)).collect();
        // Every threshold's neighbours in f16, and the special values in every feature.
        for t in &f.trees {
            for nd in t.nodes.iter().filter(|nd| nd.threshold.is_finite()) {
                let h = f16::from_f32(nd.threshold);
                for v in [
                    h,
                    f16::from_bits(h.to_bits().wrapping_add(1)),
                    f16::from_bits(h.to_bits().wrapping_sub(1)),
                ] {
                    let mut row: Vec<f16> = probe[..d].to_vec();
                    row[nd.feature as usize] = v;
                    probe.extend(row);
                }
            }
        }
        let specials = [
            f16::NAN,
            -f16::NAN,
            f16::INFINITY,
            f16::NEG_INFINITY,
            f16::ZERO,
            f16::NEG_ZERO,
            f16::MAX,
            f16::MIN,
            f16::MIN_POSITIVE_SUBNORMAL,
            -f16::MIN_POSITIVE_SUBNORMAL,
        ];
        for (k, &v) in specials.iter().enumerate() {
            probe.extend((0..d).map(|j| {
                if j == k % d {
                    v
                } else {
                    specials[(k + j) % specials.len()]
                }
            }));
        }
        // Every bit pattern once, in whole rows.
        probe.extend((0..=u16::MAX).map(f16::from_bits));
        probe.truncate(probe.len() / d * d);
        let wide: Vec<f32> = probe.iter().map(|v| v.to_f32()).collect();
        let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let want = f.predict_proba(&wide).unwrap();
        assert_eq!(bits(&f.predict_proba_f16(&probe).unwrap()), bits(&want));
        let mut walk = vec![0.0f32; want.len()];
        f.predict_f32(&wide, &mut walk, 1.0 / 20.0);
        assert_eq!(bits(&want), bits(&walk));
        // Partial blocks of rows and of the coding's sub-blocks.
        for rows in [1, 5, 1023, 1025, crate::packed::BLOCK + 3] {
            let part: Vec<f16> = probe.iter().cycle().take(rows * d).copied().collect();
            let wide: Vec<f32> = part.iter().map(|v| v.to_f32()).collect();
            assert_eq!(
                bits(&f.predict_proba_f16(&part).unwrap()),
                bits(&f.predict_proba(&wide).unwrap()),
                "{rows} rows"
            );
        }
        assert!(f.predict_proba_f16(&probe[..d + 1]).is_err(), "ragged rows");
    }

    #[test]
    fn deterministic_for_any_thread_count() {
        let (x, y) = xor(800);
        let a = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 4,
                classes: 2,
            },
            &cfg(20),
        )
        .unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let b = pool.install(|| {
            Forest::fit(
                Dataset {
                    x: &x,
                    y: &y,
                    d: 4,
                    classes: 2,
                },
                &cfg(20),
            )
            .unwrap()
        });
        assert_eq!(a, b);
        let c = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 4,
                classes: 2,
            },
            &ForestConfig { seed: 9, ..cfg(20) },
        )
        .unwrap();
        assert_ne!(a, c);
    }

    #[test]
    fn balanced_weights_favour_the_rare_class() {
        // 95 of class 0 at x<1, 5 of class 1 at x in [0.9, 1.0]: overlapping region.
        let mut x = Vec::new();
        let mut y = Vec::new();
        for i in 0..95 {
            x.push(i as f32 / 95.0);
            y.push(0u16);
        }
        for i in 0..5 {
            x.push(0.9 + i as f32 * 0.02);
            y.push(1u16);
        }
        let plain = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 1,
                classes: 2,
            },
            &ForestConfig {
                trees: 5,
                min_samples_split: 40,
                ..Default::default()
            },
        )
        .unwrap();
        let bal = Forest::fit(
            Dataset {
                x: &x,
                y: &y,
                d: 1,
                classes: 2,
            },
            &ForestConfig {
                trees: 5,
                min_samples_split: 40,
                class_weight: ClassWeight::Balanced,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(bal.predict_proba(&[0.95]).unwrap()[1] > plain.predict_proba(&[0.95]).unwrap()[1]);
    }

    #[test]
    fn bad_training_data_and_inputs() {
        let x = [0.0f32, 1.0];
        let e = |x: &[f32], y: &[u16], d, c| {
            Forest::fit(
                Dataset {
                    x,
                    y,
                    d,
                    classes: c,
                },
                &cfg(2),
            )
            .unwrap_err()
            .to_string()
        };
        assert!(e(&[], &[], 1, 2).contains("no labelled samples"));
        assert!(e(&x, &[0, 0], 1, 2).contains("only one class"));
        assert!(e(&x, &[0, 5], 1, 2).contains("outside"));
        assert!(e(&x, &[0, 1], 1, 1).contains("at least 2"));
        assert!(e(&[0.0, f32::NAN], &[0, 1], 1, 2).contains("not finite"));
        assert!(e(&x, &[0, 1, 1], 1, 2).contains("rows"));
        let f = Forest::fit(
            Dataset {
                x: &[0.0, 0.0, 1.0, 1.0],
                y: &[0, 1],
                d: 2,
                classes: 2,
            },
            &cfg(2),
        )
        .unwrap();
        assert!(f.predict_proba(&[1.0, 2.0, 3.0]).is_err());
    }
}
