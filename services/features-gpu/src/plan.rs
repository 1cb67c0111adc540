//! Where everything lives in the arena: the dense parameters and their optimiser state, the
//! per-micro-batch activations and gradients as `[feature][sample]` matrices, and the few
//! full-batch matrices the table scatter reads after the last micro-batch.

use neuvolex_features::model::{DenseLayout, InrModel};

/// Samples per weight-gradient split on the layered path (one workgroup's share of the sum
/// over samples).
pub const SPLIT: usize = 256;
/// Samples per workgroup of the default fused path (`shaders/inr_fused.wgsl` `FB`): its
/// block of samples is also its weight-gradient split and its loss partial. The fused path
/// also runs with blocks of 32 and 16 ([`crate::context::FUSED_BLOCKS`]).
pub const FUSED_BLOCK: usize = crate::context::DEFAULT_FUSED_BLOCK;
/// Steps whose (loss, sse) the arena keeps before the slots are reused.
pub const STATS_RING: usize = 256;
/// Invocations per workgroup of the element-wise kernels.
pub const WG: usize = 256;

/// A matrix in the arena: element `[row][col]` at `off + row * stride + col`. Full-batch
/// matrices hold every sample of a step; the others one micro-batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mat {
    /// Offset of element [0][0] (in f32 units).
    pub off: u32,
    /// Distance between rows.
    pub stride: u32,
    /// Columns span the whole batch (else one micro-batch).
    pub full: bool,
}

impl Mat {
    /// Row `r` onwards.
    pub fn row(self, r: usize) -> Mat {
        Mat {
            off: self.off + (r as u32) * self.stride,
            ..self
        }
    }
    /// This matrix as seen by micro-batch `j` (full-batch matrices shift to its columns).
    pub fn at(self, j: usize, mb: usize) -> Mat {
        if self.full {
            Mat {
                off: self.off + (j * mb) as u32,
                ..self
            }
        } else {
            self
        }
    }
}

/// The arena's layout for one model, micro-batch and batch.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Samples per micro-batch.
    pub mb: usize,
    /// Samples per weight-gradient partial ([`SPLIT`] layered, the block fused).
    pub split: usize,
    /// Samples per loss partial ([`WG`] layered, the block fused).
    pub group: usize,
    /// Samples per step (columns of the full-batch matrices).
    pub batch: usize,
    /// With the backward pass and optimiser regions.
    pub train: bool,
    /// Dense parameters.
    pub params: u32,
    /// Adam first moments of the dense parameters.
    pub m: u32,
    /// Adam second moments.
    pub v: u32,
    /// The step's dense gradient.
    pub g: u32,
    /// Per-output loss weights.
    pub weights: u32,
    /// Level table: (resolution, dense) per level.
    pub levels: u32,
    /// Exact normalised coordinates per axis: dims x, then y, then z.
    pub axes: u32,
    /// (loss, sse) per step, `STATS_RING` slots.
    pub stats: u32,
    /// Normalised patches.
    pub patch: Mat,
    /// Targets.
    pub target: Mat,
    /// Positions (full batch).
    pub coords: Mat,
    /// Hash-grid output.
    pub pos: Mat,
    /// Structural layers' outputs.
    pub s: [Mat; 2],
    /// FiLM's gamma and beta.
    pub gb: Mat,
    /// The MLP input.
    pub inp: Mat,
    /// Hidden layers' outputs.
    pub h: Vec<Mat>,
    /// Head outputs.
    pub y: Mat,
    /// Output gradient.
    pub dy: Mat,
    /// Hidden-layer gradients (two, used in turn).
    pub dh: [Mat; 2],
    /// MLP-input gradient.
    pub dinp: Mat,
    /// Hash-grid-output gradient (full batch).
    pub dpos: Mat,
    /// FiLM gradient.
    pub dgb: Mat,
    /// Structural gradients (two).
    pub ds: [Mat; 2],
    /// Per-workgroup (loss, sse) partials of a step.
    pub loss_parts: u32,
    /// Dense-gradient partials, one per split.
    pub parts: u32,
    /// Per-voxel features, voxel-major.
    pub out: u32,
    /// Widest feature.
    pub out_channels: usize,
    /// Total f32 elements.
    pub len: usize,
}

/// Hands out arena regions in order (16-byte aligned).
struct Alloc {
    off: usize,
    mb: usize,
    batch: usize,
}

impl Alloc {
    fn take(&mut self, n: usize) -> u32 {
        let o = self.off;
        self.off += n.div_ceil(4) * 4;
        o as u32
    }
    fn mat(&mut self, rows: usize, full: bool) -> Mat {
        let stride = if full { self.batch } else { self.mb };
        Mat {
            off: self.take(rows * stride),
            stride: stride as u32,
            full,
        }
    }
}

impl Plan {
    /// Weight-gradient partials of a micro-batch of `n` samples.
    pub fn splits(&self, n: usize) -> usize {
        n.div_ceil(self.split)
    }

    /// Loss partials of a micro-batch of `n` samples.
    pub fn loss_groups(&self, n: usize) -> usize {
        n.div_ceil(self.group)
    }

    /// The layout for `model` with micro-batches of `mb` samples and steps of `batch`, for
    /// the fused path's partials (`fused`, blocks of [`FUSED_BLOCK`]) or the layered path's.
    pub fn new(model: &InrModel, mb: usize, batch: usize, train: bool, fused: bool) -> Plan {
        Plan::with_block(model, mb, batch, train, fused.then_some(FUSED_BLOCK))
    }

    /// [`Plan::new`] with the fused path's block of samples per workgroup (`Some(block)`) or
    /// the layered path's partials (`None`).
    pub fn with_block(
        model: &InrModel,
        mb: usize,
        batch: usize,
        train: bool,
        block: Option<usize>,
    ) -> Plan {
        let (split, group) = match block {
            Some(b) => (b.max(1), b.max(1)),
            None => (SPLIT, WG),
        };
        let lay: &DenseLayout = &model.layout;
        let cfg = &model.cfg;
        let a = cfg.ablation;
        let enc = model.grid.out_dim();
        let mi = lay.mlp_in();
        let sh = cfg.structural_hidden;
        let hid = cfg.hidden;
        let outs = lay.head.out;
        let batch = if train { batch.max(mb) } else { mb };
        let mut al = Alloc { off: 0, mb, batch };
        let dl = lay.len;
        let params = al.take(dl);
        let (m, v, g) = if train {
            (al.take(dl), al.take(dl), al.take(dl))
        } else {
            (0, 0, 0)
        };
        let weights = al.take(outs);
        let levels = al.take(2 * model.grid.levels.len());
        let axes = al.take(model.dims.iter().sum());
        let stats = al.take(2 * STATS_RING);
        let patch = al.mat(cfg.patch.pow(3), false);
        let target = al.mat(neuvolex_features::model::TARGETS, false);
        let coords = al.mat(3, true);
        let none = Mat {
            off: 0,
            stride: mb as u32,
            full: false,
        };
        // The MLP input: F_mod (FiLM), [F_pos; s] (concatenation) or F_pos itself.
        let inp = al.mat(mi, false);
        let (pos, s1) = if a.film() {
            (al.mat(enc, false), al.mat(sh, false))
        } else if a.structural() {
            (inp, inp.row(enc))
        } else {
            (inp, none)
        };
        let s0 = if a.structural() {
            al.mat(sh, false)
        } else {
            none
        };
        let gb = if a.film() {
            al.mat(2 * enc, false)
        } else {
            none
        };
        let h = (0..lay.main.len()).map(|_| al.mat(hid, false)).collect();
        let y = al.mat(outs, false);
        let out_channels = hid + mi + 3;
        let out = al.take(mb * out_channels);
        let (mut dy, mut dh, mut dinp, mut dpos, mut dgb, mut ds) =
            (none, [none; 2], none, none, none, [none; 2]);
        let (mut loss_parts, mut parts) = (0, 0);
        if train {
            dy = al.mat(outs, false);
            dh = [al.mat(hid, false), al.mat(hid, false)];
            if a.film() {
                dinp = al.mat(mi, false);
                dpos = al.mat(enc, true);
                dgb = al.mat(2 * enc, false);
                ds = [al.mat(sh, false), al.mat(sh, false)];
            } else {
                // dF_pos is the first rows of dL/dinp; the structural gradient the rest.
                dinp = al.mat(mi, true);
                dpos = dinp;
                if a.structural() {
                    ds = [dinp.row(enc), al.mat(sh, false)];
                }
            }
            loss_parts = al.take(2 * batch.div_ceil(mb) * mb.div_ceil(group));
            parts = al.take(mb.div_ceil(split) * dl);
        }
        Plan {
            mb,
            split,
            group,
            batch,
            train,
            params,
            m,
            v,
            g,
            weights,
            levels,
            axes,
            stats,
            patch,
            target,
            coords,
            pos,
            s: [s0, s1],
            gb,
            inp,
            h,
            y,
            dy,
            dh,
            dinp,
            dpos,
            dgb,
            ds,
            loss_parts,
            parts,
            out,
            out_channels,
            len: al.off,
        }
    }

    /// The arena's size in bytes.
    pub fn bytes(&self) -> u64 {
        self.len as u64 * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use neuvolex_features::{Ablation, InrConfig};

    #[test]
    fn regions_do_not_overlap() {
        for ab in [
            Ablation::Base,
            Ablation::Structural,
            Ablation::Film,
            Ablation::Full,
        ] {
            let cfg = InrConfig {
                ablation: ab,
                log2_table: 10,
                ..Default::default()
            };
            let m = InrModel::new(&cfg, [20, 30, 40], 0);
            for block in [None, Some(64), Some(32), Some(16)] {
                let p = Plan::with_block(&m, 512, 1300, true, block);
                assert_eq!(p.split, block.unwrap_or(SPLIT));
                assert_eq!(p.splits(512), 512 / p.split);
                let mut spans: Vec<(u32, u32, &str)> = vec![
                    (p.params, m.layout.len as u32, "params"),
                    (p.patch.off, 125 * 512, "patch"),
                    (p.coords.off, 3 * 1300, "coords"),
                    (p.h[0].off, 64 * 512, "h0"),
                    (p.dh[1].off, 64 * 512, "dh1"),
                    (p.parts, (p.splits(512) * m.layout.len) as u32, "parts"),
                    (p.out, (512 * p.out_channels) as u32, "out"),
                ];
                spans.sort();
                for w in spans.windows(2) {
                    assert!(
                        w[0].0 + w[0].1 <= w[1].0,
                        "{ab:?}: {} overlaps {}",
                        w[0].2,
                        w[1].2
                    );
                }
                assert!(p.len as u32 >= p.parts);
                // Concatenation: F_pos and the structural output are the MLP input's two halves.
                if ab == Ablation::Structural {
                    assert_eq!(p.pos.off, p.inp.off);
                    assert_eq!(p.s[1].off, p.inp.off + 32 * 512);
                    assert!(p.dinp.full && p.dpos == p.dinp);
                }
            }
        }
    }
}
