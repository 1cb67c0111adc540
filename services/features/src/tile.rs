//! Training tiles: a brick's normalised halo and its derived targets, loaded from the store.
//!
//! A tile is the unit of residency: training samples voxels of the few tiles in memory, and
//! extraction runs tile by tile. Everything here is a pure function of a brick and its halo.

use crate::config::InrConfig;
use crate::model::TARGETS;
use neuvolex_bricks::derived::{compute, Normaliser, DERIVED_HALO};
use neuvolex_bricks::{Brick, BrickStore, HaloBrick, Result};
use neuvolex_filters::scale::ScaleField;

/// One brick ready for sampling.
#[derive(Debug, Clone)]
pub struct Tile {
    /// The brick.
    pub brick: Brick,
    /// Volume grid (for normalised coordinates).
    pub dims: [usize; 3],
    /// Halo width of `norm`.
    pub halo: usize,
    /// Normalised intensities of the brick plus halo, x fastest.
    pub norm: Vec<f32>,
    /// Targets per core voxel: intensity, gradient xyz, local mean, local std.
    pub targets: Vec<[f32; TARGETS]>,
    /// Context targets per core voxel (`voxels x 2 sigmas`: smoothed intensity and
    /// scale-normalised gradient magnitude per sigma); empty for the paper's model.
    pub context: Vec<f32>,
}

impl Tile {
    /// Builds a tile from a halo brick (halo >= max(2, patch / 2)).
    pub fn from_halo(h: &HaloBrick, dims: [usize; 3], norm: &Normaliser) -> Self {
        let d = compute(h, norm);
        let targets = (0..d.intensity.len())
            .map(|i| {
                [
                    d.intensity[i],
                    d.gradient[i][0],
                    d.gradient[i][1],
                    d.gradient[i][2],
                    d.mean[i],
                    d.std[i],
                ]
            })
            .collect();
        let n: Vec<f32> = h.data.iter().map(|&v| norm.apply(v)).collect();
        Tile {
            brick: Brick {
                index: [0; 3],
                origin: h.origin,
                size: h.size,
            },
            dims,
            halo: h.halo,
            norm: n,
            targets,
            context: Vec::new(),
        }
    }

    /// Loads brick `b` of `store` for a model whose patch edge is `patch`.
    pub fn load(store: &BrickStore, b: &Brick, patch: usize) -> Result<Self> {
        let halo = DERIVED_HALO.max(patch / 2);
        let h = store.read_halo(b, halo)?;
        let mut t = Tile::from_halo(&h, store.info().dims, &store.normaliser());
        t.brick = *b;
        Ok(t)
    }

    /// Loads brick `b` with every target a model of `cfg` trains on (the context targets
    /// from the store's pyramid, see [`neuvolex_filters::scale`]).
    pub fn load_for(store: &BrickStore, b: &Brick, cfg: &InrConfig) -> Result<Self> {
        let mut t = Tile::load(store, b, cfg.patch)?;
        if cfg.context_sigmas.is_empty() {
            return Ok(t);
        }
        let levels = &store.info().levels;
        let norm = store.normaliser();
        let lo = b.origin.map(|o| o as isize);
        let hi: [isize; 3] = std::array::from_fn(|a| (b.origin[a] + b.size[a]) as isize - 1);
        let fields = cfg
            .context_sigmas
            .iter()
            .map(|&s| {
                ScaleField::compute(s, levels, &norm, lo, hi, |k, o, sz| {
                    store.read_box(k, o, sz)
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let nc = 2 * fields.len();
        t.context = Vec::with_capacity(b.voxels() * nc);
        for z in 0..b.size[2] {
            for y in 0..b.size[1] {
                for x in 0..b.size[0] {
                    let p = [lo[0] + x as isize, lo[1] + y as isize, lo[2] + z as isize];
                    for f in &fields {
                        let (v, g) = f.sample(p);
                        t.context.push(v);
                        t.context.push(g);
                    }
                }
            }
        }
        Ok(t)
    }

    /// Core voxels.
    pub fn voxels(&self) -> usize {
        self.targets.len()
    }

    /// Writes the position, patch and targets of core voxel `v` (x fastest within the brick;
    /// `t` holds the paper's targets, then as many context targets as the tile was loaded with).
    #[inline]
    pub fn sample(&self, v: usize, patch: usize, x: &mut [f32; 3], p: &mut [f32], t: &mut [f32]) {
        let s = self.brick.size;
        let (vx, vy, vz) = (v % s[0], (v / s[0]) % s[1], v / (s[0] * s[1]));
        let o = self.brick.origin;
        *x = [
            (o[0] + vx) as f32 / self.dims[0] as f32 + 0.5 / self.dims[0] as f32,
            (o[1] + vy) as f32 / self.dims[1] as f32 + 0.5 / self.dims[1] as f32,
            (o[2] + vz) as f32 / self.dims[2] as f32 + 0.5 / self.dims[2] as f32,
        ];
        let pd = [s[0] + 2 * self.halo, s[1] + 2 * self.halo];
        let r = patch / 2;
        let (cx, cy, cz) = (vx + self.halo - r, vy + self.halo - r, vz + self.halo - r);
        let mut k = 0;
        for dz in 0..patch {
            for dy in 0..patch {
                let row = ((cz + dz) * pd[1] + cy + dy) * pd[0] + cx;
                p[k..k + patch].copy_from_slice(&self.norm[row..row + patch]);
                k += patch;
            }
        }
        t[..TARGETS].copy_from_slice(&self.targets[v]);
        let nc = t.len() - TARGETS;
        if nc > 0 {
            if self.context.is_empty() {
                // Loaded for extraction only: no context targets.
                t[TARGETS..].fill(0.0);
            } else {
                t[TARGETS..].copy_from_slice(&self.context[v * nc..(v + 1) * nc]);
            }
        }
    }
}
