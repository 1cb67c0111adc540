//! The volume-exploration INR as a hand-fused CPU network: hash grid -> (FiLM with the
//! structural encoder) -> main MLP with a residual projection -> multi-task heads.
//!
//! Forward and backward work on chunks of up to [`CHUNK`] samples with `matrixmultiply`
//! GEMMs; all dense parameters live in one flat vector (see [`DenseLayout`]), the hash table in
//! another. Chunks are independent, so callers run them in parallel and merge the per-chunk
//! gradients in chunk order, which keeps training deterministic for any thread count.

use crate::config::InrConfig;
use crate::hashgrid::HashGrid;
use crate::rng::Rng;
use serde::{Deserialize, Serialize};

/// Samples per chunk of forward/backward work.
pub const CHUNK: usize = 256;

/// Outputs of the paper's heads (defined beside the configuration, which counts them).
pub use crate::config::TARGETS;

/// One dense layer inside the flat parameter vector: `w` is `out x in` row-major.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LayerSpec {
    /// Input width.
    pub inp: usize,
    /// Output width.
    pub out: usize,
    /// Offset of the weights.
    pub w: usize,
    /// Offset of the bias, if the layer has one.
    pub b: Option<usize>,
}

/// Positions of every dense layer in the flat parameter vector.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DenseLayout {
    /// Structural encoder layers (patch -> hidden -> hidden), if used.
    pub structural: Vec<LayerSpec>,
    /// FiLM generator (structural hidden -> gamma, beta), if used.
    pub film: Option<LayerSpec>,
    /// Main MLP hidden layers.
    pub main: Vec<LayerSpec>,
    /// Residual projection of the MLP input into layer `residual_at` (no bias).
    pub proj: LayerSpec,
    /// Hidden layer that receives the residual projection.
    pub residual_at: usize,
    /// Output heads.
    pub head: LayerSpec,
    /// Total parameters.
    pub len: usize,
}

impl DenseLayout {
    /// The layout for a configuration whose encoding is `enc` wide.
    pub fn for_config(cfg: &InrConfig, enc: usize) -> Self {
        let mut off = 0;
        let mut layer = |inp: usize, out: usize, bias: bool| {
            let w = off;
            off += inp * out;
            let b = bias.then(|| {
                let b = off;
                off += out;
                b
            });
            LayerSpec { inp, out, w, b }
        };
        let a = cfg.ablation;
        let sh = cfg.structural_hidden;
        let patch = cfg.patch.pow(3);
        let structural = if a.structural() {
            vec![layer(patch, sh, true), layer(sh, sh, true)]
        } else {
            vec![]
        };
        let film = a.film().then(|| layer(sh, 2 * enc, true));
        let mlp_in = if a.structural() && !a.film() {
            enc + sh
        } else {
            enc
        };
        let n = cfg.hidden_layers.max(1);
        let mut main = vec![layer(mlp_in, cfg.hidden, true)];
        for _ in 1..n {
            main.push(layer(cfg.hidden, cfg.hidden, true));
        }
        let proj = layer(mlp_in, cfg.hidden, false);
        let head = layer(cfg.hidden, cfg.head_targets().len(), true);
        DenseLayout {
            structural,
            film,
            main,
            proj,
            residual_at: 2.min(n - 1),
            head,
            len: off,
        }
    }

    /// Width of the main MLP's input.
    pub fn mlp_in(&self) -> usize {
        self.main[0].inp
    }
}

/// Which per-voxel feature to extract.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FeatureKind {
    /// The paper's feature: the last hidden layer (64).
    Hidden,
    /// The hash-grid output F_pos (L x F).
    Pos,
    /// The MLP input: F_mod with FiLM, [F_pos, structural] when concatenated, F_pos in the base model.
    Mod,
    /// Last hidden layer, the MLP input and the normalised position, concatenated.
    Concat,
    /// The coarse half of the hash-grid levels (the first `levels / 2` levels of F_pos): a
    /// smooth learned code of the region a voxel lies in, in place of raw position.
    Region,
}

impl FeatureKind {
    /// Channels of this feature for a model.
    pub fn channels(self, m: &InrModel) -> usize {
        match self {
            FeatureKind::Hidden => m.cfg.hidden,
            FeatureKind::Pos => m.grid.out_dim(),
            FeatureKind::Mod => m.layout.mlp_in(),
            FeatureKind::Concat => m.cfg.hidden + m.layout.mlp_in() + 3,
            FeatureKind::Region => m.region_levels() * m.grid.f,
        }
    }
}

impl std::str::FromStr for FeatureKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "hidden" => Ok(FeatureKind::Hidden),
            "pos" => Ok(FeatureKind::Pos),
            "mod" => Ok(FeatureKind::Mod),
            "concat" => Ok(FeatureKind::Concat),
            "region" => Ok(FeatureKind::Region),
            _ => Err(format!(
                "unknown feature kind '{s}' (hidden, pos, mod, concat, region)"
            )),
        }
    }
}

/// The model: configuration, grid geometry and parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct InrModel {
    /// Architecture.
    pub cfg: InrConfig,
    /// Hash-grid geometry.
    pub grid: HashGrid,
    /// Dense parameter layout.
    pub layout: DenseLayout,
    /// Hash table (level-major).
    pub table: Vec<f32>,
    /// Dense parameters.
    pub dense: Vec<f32>,
    /// The volume grid the model was built for.
    pub dims: [usize; 3],
}

/// One training/inference sample: normalised position, raw patch (normalised), targets.
#[derive(Debug, Clone, Copy)]
pub struct SampleRef<'a> {
    /// Position in [0, 1]^3.
    pub x: [f32; 3],
    /// `patch^3` normalised intensities around the voxel, x fastest.
    pub patch: &'a [f32],
    /// Intensity, gradient xyz, local mean, local std, then the context targets
    /// ([`InrConfig::targets`] values).
    pub target: &'a [f32],
}

/// Per-chunk buffers, reused between steps.
#[derive(Debug, Default, Clone)]
pub struct Work {
    n: usize,
    /// Targets per sample.
    tw: usize,
    patch: Vec<f32>,
    target: Vec<f32>,
    coords: Vec<[f32; 3]>,
    idx: Vec<u32>,
    wts: Vec<f32>,
    pos: Vec<f32>,
    s: Vec<Vec<f32>>,
    gb: Vec<f32>,
    inp: Vec<f32>,
    h: Vec<Vec<f32>>,
    y: Vec<f32>,
    // Gradients.
    dy: Vec<f32>,
    dh: Vec<f32>,
    dh2: Vec<f32>,
    dinp: Vec<f32>,
    dpos: Vec<f32>,
    dgb: Vec<f32>,
    ds: Vec<f32>,
    ds2: Vec<f32>,
    /// Dense-parameter gradient of this chunk.
    pub grad: Vec<f32>,
    /// Corner indices of every sample of the lane (`n x levels x 8`), kept for the table scatter.
    lane_idx: Vec<u32>,
    /// Corner weights, same layout.
    lane_wts: Vec<f32>,
    /// Gradient of the encoding per sample (`n x levels*F`).
    lane_dpos: Vec<f32>,
    /// Samples accumulated in the lane.
    lane_n: usize,
    /// Sum of squared intensity errors of the chunk.
    pub sse_int: f64,
    /// Loss contribution of the chunk (already divided by the batch size).
    pub loss: f64,
}

impl Work {
    /// The lane's table-gradient terms: samples, corner indices and weights
    /// (`n x levels x 8`), and the encoding gradient (`n x levels*F`). Entry `idx` of level `l`
    /// receives `weight * dpos[l*F..(l+1)*F]`.
    pub fn table_terms(&self) -> (usize, &[u32], &[f32], &[f32]) {
        (self.lane_n, &self.lane_idx, &self.lane_wts, &self.lane_dpos)
    }
}

/// How many samples ahead the table gather prefetches.
pub(crate) const PREFETCH: usize = 4;

/// Hints the CPU to fetch `v[i]` into the cache (no effect where unsupported).
#[inline(always)]
pub(crate) fn prefetch<T>(v: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if i < v.len() {
        // SAFETY: prefetching an in-bounds address has no side effects.
        unsafe {
            std::arch::x86_64::_mm_prefetch(
                v.as_ptr().add(i) as *const i8,
                std::arch::x86_64::_MM_HINT_T0,
            )
        };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (v, i);
}

/// `c[n x out] = beta c + a[n x inp] * W^T`.
fn gemm_xwt(a: &[f32], n: usize, l: &LayerSpec, p: &[f32], c: &mut [f32], beta: f32) {
    assert!(a.len() >= n * l.inp && c.len() >= n * l.out && p.len() >= l.w + l.out * l.inp);
    // SAFETY: the slices were checked to hold n x inp, n x out and out x inp elements.
    unsafe {
        matrixmultiply::sgemm(
            n,
            l.inp,
            l.out,
            1.0,
            a.as_ptr(),
            l.inp as isize,
            1,
            p[l.w..].as_ptr(),
            1,
            l.inp as isize,
            beta,
            c.as_mut_ptr(),
            l.out as isize,
            1,
        );
    }
}

/// `c[n x out] = a[n x inp] * W^T (+ b)`.
fn linear(a: &[f32], n: usize, l: &LayerSpec, p: &[f32], c: &mut [f32]) {
    let beta = match l.b {
        Some(b) => {
            for r in 0..n {
                c[r * l.out..(r + 1) * l.out].copy_from_slice(&p[b..b + l.out]);
            }
            1.0
        }
        None => 0.0,
    };
    gemm_xwt(a, n, l, p, c, beta);
}

/// `c[n x out] += a[n x inp] * W^T` (accumulating, no bias).
fn linear_acc(a: &[f32], n: usize, l: &LayerSpec, p: &[f32], c: &mut [f32]) {
    gemm_xwt(a, n, l, p, c, 1.0);
}

/// Backward of a linear layer: `dw += dc^T a`, `db += sum dc`, and `da (+)= dc W` if asked.
fn linear_back(
    a: &[f32],
    dc: &[f32],
    n: usize,
    l: &LayerSpec,
    p: &[f32],
    g: &mut [f32],
    da: Option<(&mut [f32], bool)>,
) {
    assert!(a.len() >= n * l.inp && dc.len() >= n * l.out && g.len() >= l.w + l.out * l.inp);
    // SAFETY: sizes checked above; dw is out x inp row-major.
    unsafe {
        matrixmultiply::sgemm(
            l.out,
            n,
            l.inp,
            1.0,
            dc.as_ptr(),
            1,
            l.out as isize,
            a.as_ptr(),
            l.inp as isize,
            1,
            1.0,
            g[l.w..].as_mut_ptr(),
            l.inp as isize,
            1,
        );
    }
    if let Some(b) = l.b {
        for r in 0..n {
            for o in 0..l.out {
                g[b + o] += dc[r * l.out + o];
            }
        }
    }
    if let Some((da, acc)) = da {
        assert!(da.len() >= n * l.inp);
        // SAFETY: sizes checked.
        unsafe {
            matrixmultiply::sgemm(
                n,
                l.out,
                l.inp,
                1.0,
                dc.as_ptr(),
                l.out as isize,
                1,
                p[l.w..].as_ptr(),
                l.inp as isize,
                1,
                if acc { 1.0 } else { 0.0 },
                da.as_mut_ptr(),
                l.inp as isize,
                1,
            );
        }
    }
}

fn relu(v: &mut [f32]) {
    v.iter_mut().for_each(|x| *x = x.max(0.0));
}

fn relu_back(h: &[f32], d: &mut [f32]) {
    d.iter_mut().zip(h).for_each(|(d, &h)| {
        if h <= 0.0 {
            *d = 0.0
        }
    });
}

impl InrModel {
    /// A freshly initialised model for a volume of `dims` (PyTorch's default layer init, table
    /// uniform in ±1e-4 as in Instant-NGP).
    pub fn new(cfg: &InrConfig, dims: [usize; 3], seed: u64) -> Self {
        let grid = HashGrid::new(cfg, *dims.iter().max().unwrap_or(&1));
        let layout = DenseLayout::for_config(cfg, grid.out_dim());
        let mut rng = Rng::new(seed);
        let table = (0..grid.table_len())
            .map(|_| rng.uniform(-1e-4, 1e-4))
            .collect();
        let mut dense = vec![0.0f32; layout.len];
        let mut all: Vec<LayerSpec> = layout.structural.clone();
        all.extend(layout.film);
        all.extend(layout.main.iter().copied());
        all.push(layout.proj);
        all.push(layout.head);
        for l in all {
            let k = 1.0 / (l.inp as f32).sqrt();
            for v in &mut dense[l.w..l.w + l.inp * l.out] {
                *v = rng.uniform(-k, k);
            }
            if let Some(b) = l.b {
                for v in &mut dense[b..b + l.out] {
                    *v = rng.uniform(-k, k);
                }
            }
        }
        InrModel {
            cfg: cfg.clone(),
            grid,
            layout,
            table,
            dense,
            dims,
        }
    }

    /// Fresh per-chunk buffers.
    pub fn work(&self) -> Work {
        let n = CHUNK;
        let e = self.grid.out_dim();
        let l = &self.layout;
        let sh = self.cfg.structural_hidden;
        let hid = self.cfg.hidden;
        Work {
            n: 0,
            tw: self.cfg.targets(),
            patch: vec![0.0; n * self.cfg.patch.pow(3)],
            target: vec![0.0; n * self.cfg.targets()],
            coords: vec![[0.0; 3]; n],
            idx: vec![0; n * self.grid.levels.len() * 8],
            wts: vec![0.0; n * self.grid.levels.len() * 8],
            pos: vec![0.0; n * e],
            s: vec![vec![0.0; n * sh]; 2],
            gb: vec![0.0; n * 2 * e],
            inp: vec![0.0; n * l.mlp_in()],
            h: vec![vec![0.0; n * hid]; l.main.len()],
            y: vec![0.0; n * l.head.out],
            dy: vec![0.0; n * l.head.out],
            dh: vec![0.0; n * hid],
            dh2: vec![0.0; n * hid],
            dinp: vec![0.0; n * l.mlp_in()],
            dpos: vec![0.0; n * e],
            dgb: vec![0.0; n * 2 * e],
            ds: vec![0.0; n * sh],
            ds2: vec![0.0; n * sh],
            grad: vec![0.0; l.len],
            lane_idx: Vec::new(),
            lane_wts: Vec::new(),
            lane_dpos: Vec::new(),
            lane_n: 0,
            sse_int: 0.0,
            loss: 0.0,
        }
    }

    /// Loads samples into a work buffer (at most [`CHUNK`]).
    pub fn load(&self, w: &mut Work, samples: &[SampleRef<'_>]) {
        self.load_with(w, samples.len(), |i, x, p, t| {
            *x = samples[i].x;
            p.copy_from_slice(&samples[i].patch[..p.len()]);
            t.copy_from_slice(&samples[i].target[..t.len()]);
        });
    }

    /// Forward pass over the loaded chunk.
    pub fn forward(&self, w: &mut Work) {
        let n = w.n;
        let e = self.grid.out_dim();
        let f = self.grid.f;
        let nl = self.grid.levels.len();
        let t = self.grid.t;
        // Hash grid: corner indices and weights first, then the gather with the corners of a
        // later sample prefetched (the table is too large for the caches; latency dominates).
        for i in 0..n {
            for l in 0..nl {
                let (idx, wt) = self.grid.corners(l, w.coords[i]);
                let o = (i * nl + l) * 8;
                w.idx[o..o + 8].copy_from_slice(&idx);
                w.wts[o..o + 8].copy_from_slice(&wt);
            }
        }
        for i in 0..n {
            if i + PREFETCH < n {
                let j = i + PREFETCH;
                for l in 0..nl {
                    let o = (j * nl + l) * 8;
                    for c in 0..8 {
                        prefetch(&self.table, (l * t + w.idx[o + c] as usize) * f);
                    }
                }
            }
            for l in 0..nl {
                let o = (i * nl + l) * 8;
                let out = &mut w.pos[i * e + l * f..i * e + (l + 1) * f];
                out.iter_mut().for_each(|v| *v = 0.0);
                for c in 0..8 {
                    let base = (l * t + w.idx[o + c] as usize) * f;
                    let wt = w.wts[o + c];
                    for (k, v) in out.iter_mut().enumerate() {
                        *v += wt * self.table[base + k];
                    }
                }
            }
        }
        let lay = &self.layout;
        let p = &self.dense;
        let a = self.cfg.ablation;
        let mi = lay.mlp_in();
        if a.structural() {
            let (s0, s1) = w.s.split_at_mut(1);
            linear(&w.patch, n, &lay.structural[0], p, &mut s0[0]);
            relu(&mut s0[0][..n * lay.structural[0].out]);
            linear(&s0[0], n, &lay.structural[1], p, &mut s1[0]);
            relu(&mut s1[0][..n * lay.structural[1].out]);
        }
        if let Some(fl) = &lay.film {
            linear(&w.s[1], n, fl, p, &mut w.gb);
            for i in 0..n {
                for j in 0..e {
                    let g = w.gb[i * 2 * e + j];
                    let b = w.gb[i * 2 * e + e + j];
                    w.inp[i * mi + j] = w.pos[i * e + j] * (g + 1.0) + b;
                }
            }
        } else if a.structural() {
            let sh = self.cfg.structural_hidden;
            for i in 0..n {
                w.inp[i * mi..i * mi + e].copy_from_slice(&w.pos[i * e..(i + 1) * e]);
                w.inp[i * mi + e..(i + 1) * mi].copy_from_slice(&w.s[1][i * sh..(i + 1) * sh]);
            }
        } else {
            w.inp[..n * e].copy_from_slice(&w.pos[..n * e]);
        }
        for k in 0..lay.main.len() {
            let (prev, rest) = w.h.split_at_mut(k);
            let src: &[f32] = if k == 0 { &w.inp } else { &prev[k - 1] };
            let dst = &mut rest[0];
            linear(src, n, &lay.main[k], p, dst);
            if k == lay.residual_at {
                linear_acc(&w.inp, n, &lay.proj, p, dst);
            }
            relu(&mut dst[..n * lay.main[k].out]);
        }
        linear(&w.h[lay.main.len() - 1], n, &lay.head, p, &mut w.y);
    }

    /// Loss and output gradient for the loaded chunk; `batch` is the full batch size. The loss
    /// is the weighted sum of each output's mean squared error ([`InrConfig::head_weights`]).
    fn loss(&self, w: &mut Work, batch: usize) {
        let n = w.n;
        let outs = self.layout.head.out;
        let tw = w.tw;
        let inv = 1.0 / batch as f32;
        let weights = self.cfg.head_weights();
        let tix = self.cfg.head_targets();
        let mut loss = 0.0f64;
        let mut sse = 0.0f64;
        for i in 0..n {
            let y = &w.y[i * outs..(i + 1) * outs];
            let t = &w.target[i * tw..(i + 1) * tw];
            let dy = &mut w.dy[i * outs..(i + 1) * outs];
            let e0 = y[0] - t[0];
            sse += (e0 * e0) as f64;
            for k in 0..outs {
                let e = y[k] - t[tix[k]];
                loss += (weights[k] * e * e * inv) as f64;
                dy[k] = weights[k] * 2.0 * e * inv;
            }
        }
        w.loss = loss;
        w.sse_int = sse;
    }

    /// Clears the accumulated gradients, loss and error of a work buffer.
    pub fn reset(&self, w: &mut Work) {
        w.grad.iter_mut().for_each(|g| *g = 0.0);
        w.lane_idx.clear();
        w.lane_wts.clear();
        w.lane_dpos.clear();
        w.lane_n = 0;
        w.loss = 0.0;
        w.sse_int = 0.0;
    }

    /// Loads `n` samples through `fill(i, position, patch, targets)` (at most [`CHUNK`];
    /// `targets` holds [`InrConfig::targets`] values).
    pub fn load_with(
        &self,
        w: &mut Work,
        n: usize,
        mut fill: impl FnMut(usize, &mut [f32; 3], &mut [f32], &mut [f32]),
    ) {
        assert!(n <= CHUNK);
        let p3 = self.cfg.patch.pow(3);
        let tw = w.tw;
        w.n = n;
        for i in 0..n {
            fill(
                i,
                &mut w.coords[i],
                &mut w.patch[i * p3..(i + 1) * p3],
                &mut w.target[i * tw..(i + 1) * tw],
            );
        }
    }

    /// Forward, loss and backward over the loaded chunk, adding this chunk's share of the batch
    /// gradient to `w.grad` (dense) and `w.table_grad` (sparse), and its loss to `w.loss`.
    /// Call [`Self::reset`] before the first chunk of a batch.
    pub fn forward_backward(&self, w: &mut Work, batch: usize) {
        self.forward(w);
        let (loss0, sse0) = (w.loss, w.sse_int);
        self.loss(w, batch);
        w.loss += loss0;
        w.sse_int += sse0;
        let n = w.n;
        let lay = &self.layout;
        let p = &self.dense;
        let e = self.grid.out_dim();
        let nl = self.grid.levels.len();
        let hid = self.cfg.hidden;
        let mi = lay.mlp_in();
        let last = lay.main.len() - 1;
        // Heads.
        linear_back(
            &w.h[last],
            &w.dy,
            n,
            &lay.head,
            p,
            &mut w.grad,
            Some((&mut w.dh, false)),
        );
        w.dinp[..n * mi].iter_mut().for_each(|v| *v = 0.0);
        for k in (0..=last).rev() {
            relu_back(&w.h[k][..n * hid], &mut w.dh[..n * hid]);
            if k == lay.residual_at {
                linear_back(
                    &w.inp,
                    &w.dh,
                    n,
                    &lay.proj,
                    p,
                    &mut w.grad,
                    Some((&mut w.dinp, true)),
                );
            }
            if k == 0 {
                linear_back(
                    &w.inp,
                    &w.dh,
                    n,
                    &lay.main[0],
                    p,
                    &mut w.grad,
                    Some((&mut w.dinp, true)),
                );
            } else {
                linear_back(
                    &w.h[k - 1],
                    &w.dh,
                    n,
                    &lay.main[k],
                    p,
                    &mut w.grad,
                    Some((&mut w.dh2, false)),
                );
                std::mem::swap(&mut w.dh, &mut w.dh2);
            }
        }
        // Fusion.
        let a = self.cfg.ablation;
        if let Some(fl) = &lay.film {
            for i in 0..n {
                for j in 0..e {
                    let d = w.dinp[i * mi + j];
                    let g = w.gb[i * 2 * e + j];
                    w.dpos[i * e + j] = d * (g + 1.0);
                    w.dgb[i * 2 * e + j] = d * w.pos[i * e + j];
                    w.dgb[i * 2 * e + e + j] = d;
                }
            }
            linear_back(
                &w.s[1],
                &w.dgb,
                n,
                fl,
                p,
                &mut w.grad,
                Some((&mut w.ds, false)),
            );
        } else {
            let sh = self.cfg.structural_hidden;
            for i in 0..n {
                w.dpos[i * e..(i + 1) * e].copy_from_slice(&w.dinp[i * mi..i * mi + e]);
                if a.structural() {
                    w.ds[i * sh..(i + 1) * sh].copy_from_slice(&w.dinp[i * mi + e..(i + 1) * mi]);
                }
            }
        }
        if a.structural() {
            let sh = self.cfg.structural_hidden;
            relu_back(&w.s[1][..n * sh], &mut w.ds[..n * sh]);
            linear_back(
                &w.s[0],
                &w.ds,
                n,
                &lay.structural[1],
                p,
                &mut w.grad,
                Some((&mut w.ds2, false)),
            );
            relu_back(&w.s[0][..n * sh], &mut w.ds2[..n * sh]);
            linear_back(
                &w.patch,
                &w.ds2,
                n,
                &lay.structural[0],
                p,
                &mut w.grad,
                None,
            );
        }
        // Hash table: keep what the scatter needs (see `Work::table_terms`).
        let k = n * nl * 8;
        w.lane_idx.extend_from_slice(&w.idx[..k]);
        w.lane_wts.extend_from_slice(&w.wts[..k]);
        w.lane_dpos.extend_from_slice(&w.dpos[..n * e]);
        w.lane_n += n;
    }

    /// Per-sample outputs of the last forward pass (`n x heads`).
    pub fn outputs<'a>(&self, w: &'a Work) -> &'a [f32] {
        &w.y[..w.n * self.layout.head.out]
    }

    /// Writes the feature of every loaded sample (`n x channels`) after [`Self::forward`].
    pub fn features(&self, w: &Work, kind: FeatureKind, out: &mut [f32]) {
        let n = w.n;
        let c = kind.channels(self);
        let hid = self.cfg.hidden;
        let mi = self.layout.mlp_in();
        let e = self.grid.out_dim();
        let last = &w.h[self.layout.main.len() - 1];
        for i in 0..n {
            let o = &mut out[i * c..(i + 1) * c];
            match kind {
                FeatureKind::Hidden => o.copy_from_slice(&last[i * hid..(i + 1) * hid]),
                FeatureKind::Pos => o.copy_from_slice(&w.pos[i * e..(i + 1) * e]),
                FeatureKind::Mod => o.copy_from_slice(&w.inp[i * mi..(i + 1) * mi]),
                FeatureKind::Concat => {
                    o[..hid].copy_from_slice(&last[i * hid..(i + 1) * hid]);
                    o[hid..hid + mi].copy_from_slice(&w.inp[i * mi..(i + 1) * mi]);
                    o[hid + mi..].copy_from_slice(&w.coords[i]);
                }
                FeatureKind::Region => o.copy_from_slice(&w.pos[i * e..i * e + c]),
            }
        }
    }

    /// Hash-grid levels of the [`FeatureKind::Region`] code: the coarse half.
    pub fn region_levels(&self) -> usize {
        (self.grid.levels.len() / 2).max(1)
    }

    /// Number of samples loaded in `w`.
    pub fn loaded(w: &Work) -> usize {
        w.n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Ablation;

    fn small(ablation: Ablation, context_sigmas: &[f32]) -> InrModel {
        let cfg = InrConfig {
            context_sigmas: context_sigmas.to_vec(),
            levels: 3,
            log2_table: 8,
            base_resolution: 2,
            finest_resolution: Some(9),
            patch: 3,
            structural_hidden: 5,
            hidden: 7,
            hidden_layers: 4,
            ablation,
            ..Default::default()
        };
        let mut m = InrModel::new(&cfg, [9, 9, 9], 1);
        // Larger table values so the encoding matters in the check.
        let mut r = Rng::new(5);
        m.table.iter_mut().for_each(|v| *v = r.uniform(-0.5, 0.5));
        m
    }

    type Batch = (Vec<[f32; 3]>, Vec<Vec<f32>>, Vec<Vec<f32>>);

    fn batch(m: &InrModel, n: usize) -> Batch {
        let mut r = Rng::new(9);
        let p3 = m.cfg.patch.pow(3);
        let xs = (0..n).map(|_| [r.f32(), r.f32(), r.f32()]).collect();
        let ps = (0..n)
            .map(|_| (0..p3).map(|_| r.uniform(-1.0, 1.0)).collect())
            .collect();
        let ts = (0..n)
            .map(|_| {
                let mut t = vec![
                    r.f32(),
                    r.uniform(-0.2, 0.2),
                    r.uniform(-0.2, 0.2),
                    r.uniform(-0.2, 0.2),
                    r.f32(),
                    r.f32() * 0.3,
                ];
                t.extend((TARGETS..m.cfg.targets()).map(|_| r.f32()));
                t
            })
            .collect();
        (xs, ps, ts)
    }

    fn loss_of(m: &InrModel, xs: &[[f32; 3]], ps: &[Vec<f32>], ts: &[Vec<f32>]) -> f64 {
        let mut w = m.work();
        let s: Vec<SampleRef> = (0..xs.len())
            .map(|i| SampleRef {
                x: xs[i],
                patch: &ps[i],
                target: &ts[i],
            })
            .collect();
        m.load(&mut w, &s);
        m.reset(&mut w);
        m.forward_backward(&mut w, xs.len());
        w.loss
    }

    /// Analytic gradients against central finite differences (in f64 loss, f32 model), for
    /// every ablation, with and without context outputs.
    #[test]
    fn gradient_check_every_ablation() {
        for (ab, ctx) in [
            (Ablation::Base, &[][..]),
            (Ablation::Structural, &[]),
            (Ablation::Film, &[]),
            (Ablation::Full, &[]),
            (Ablation::Full, &[1.0, 4.0]),
            (Ablation::Base, &[2.0]),
        ] {
            let m = small(ab, ctx);
            let (xs, ps, ts) = batch(&m, 6);
            let mut w = m.work();
            let s: Vec<SampleRef> = (0..xs.len())
                .map(|i| SampleRef {
                    x: xs[i],
                    patch: &ps[i],
                    target: &ts[i],
                })
                .collect();
            m.load(&mut w, &s);
            m.reset(&mut w);
            m.forward_backward(&mut w, xs.len());
            let grad = w.grad.clone();
            let mut tg = crate::adam::TableGrad::new(m.grid.levels.len(), m.grid.t, m.grid.f);
            tg.scatter(&[&w]);
            let tgrad = tg.g.clone();
            // Central differences at two step sizes; where they disagree, a ReLU kink lies within
            // the step and the parameter is skipped (counted). f32 forward passes make the quotient
            // noisy at ~3e-5 absolute, hence the absolute part of the tolerance.
            let fd_at = |which: &dyn Fn(&mut InrModel, f32), h: f32| {
                let mut a = m.clone();
                which(&mut a, h);
                let mut b = m.clone();
                which(&mut b, -h);
                (loss_of(&a, &xs, &ps, &ts) - loss_of(&b, &xs, &ps, &ts)) / (2.0 * h as f64)
            };
            let tol = |a: f64, b: f64| 5e-5 + 2e-2 * a.abs().max(b.abs());
            let (mut checked, mut kinks, mut worst) = (0, 0, 0.0f64);
            let mut check = |which: &dyn Fn(&mut InrModel, f32), an: f64| {
                let f1 = fd_at(which, 1e-3);
                let f2 = fd_at(which, 3e-4);
                if (f1 - f2).abs() > 4.0 * tol(f1, f2) {
                    kinks += 1;
                    return;
                }
                worst = worst.max((f1 - an).abs() / tol(f1, an));
                checked += 1;
            };
            let mut r = Rng::new(3);
            for _ in 0..60 {
                let i = r.below(m.dense.len());
                check(&|mm: &mut InrModel, h| mm.dense[i] += h, grad[i] as f64);
            }
            let touched: Vec<usize> = tgrad
                .iter()
                .enumerate()
                .filter(|(_, g)| g.abs() > 1e-6)
                .map(|(i, _)| i)
                .collect();
            for &i in touched.iter().step_by((touched.len() / 20).max(1)) {
                check(&|mm: &mut InrModel, h| mm.table[i] += h, tgrad[i] as f64);
            }
            assert!(
                kinks * 5 < checked,
                "{ab:?} {ctx:?}: {kinks} kinks of {checked}"
            );
            assert!(
                checked > 50 && worst <= 1.0,
                "{ab:?} {ctx:?}: worst error {worst} x tolerance ({checked} checked, {kinks} kinks)"
            );
        }
    }

    /// Without context sigmas the model is the paper's: the same layout, heads and loss
    /// weights; context sigmas only widen the heads layer.
    #[test]
    fn context_outputs_only_widen_the_heads() {
        let paper = small(Ablation::Full, &[]);
        assert_eq!(paper.layout.head.out, TARGETS);
        assert_eq!(
            paper.cfg.head_weights(),
            vec![1.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 0.5, 0.5]
        );
        let ctx = small(Ablation::Full, &[1.0, 2.0, 4.0]);
        assert_eq!(ctx.layout.head.out, TARGETS + 6);
        assert_eq!(ctx.cfg.targets(), TARGETS + 6);
        let w = ctx.cfg.head_weights();
        assert!((w[TARGETS..].iter().sum::<f32>() - ctx.cfg.lambda_context).abs() < 1e-6);
        let (p, c) = (&paper.layout, &ctx.layout);
        assert_eq!(p.main, c.main);
        assert_eq!(p.structural, c.structural);
        assert_eq!(p.head.inp, c.head.inp);
        let base = small(Ablation::Base, &[2.0]);
        assert_eq!(base.layout.head.out, 3);
        assert_eq!(base.cfg.head_targets(), vec![0, TARGETS, TARGETS + 1]);
        assert!(InrConfig {
            context_sigmas: vec![0.1],
            ..Default::default()
        }
        .check()
        .is_err());
    }
}
