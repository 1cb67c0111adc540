//! Multiresolution hash-grid encoding (Instant-NGP), forward and backward on the CPU.
//!
//! Level `l` has resolution `N_l = floor(N_min * b^l)` with `b = (N_max / N_min)^(1/(L-1))`; a
//! coordinate `x` in [0, 1]^3 falls in the cell `floor(x * N_l)` of a grid with `N_l + 1`
//! vertices per axis. Levels whose vertices fit the table are indexed densely
//! (`i + j R + k R^2`), finer ones through the spatial hash `(i * 1) ^ (j * 2654435761) ^
//! (k * 805459861) mod T`. The level's feature is the trilinear blend of its 8 corners.
//! The table is level-major: entry `e` of level `l`, feature `f` is at `(l * T + e) * F + f`.

use crate::config::InrConfig;

/// The spatial-hash primes.
pub const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// One level of the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Level {
    /// Cells per axis.
    pub res: u32,
    /// True when indexed densely (no collisions).
    pub dense: bool,
}

/// Geometry of the encoding (the table itself lives in the model's parameters).
#[derive(Debug, Clone, PartialEq)]
pub struct HashGrid {
    /// Levels, coarse to fine.
    pub levels: Vec<Level>,
    /// Features per level.
    pub f: usize,
    /// Entries per level (a power of two).
    pub t: usize,
}

impl HashGrid {
    /// The grid for a volume whose largest dimension is `max_dim`.
    pub fn new(cfg: &InrConfig, max_dim: usize) -> Self {
        let t = 1usize << cfg.log2_table;
        let n_min = cfg.base_resolution.max(1) as f64;
        let n_max = (cfg.finest_resolution.unwrap_or(max_dim) as f64).max(n_min);
        let l = cfg.levels.max(1);
        let b = if l > 1 {
            ((n_max.ln() - n_min.ln()) / (l - 1) as f64).exp()
        } else {
            1.0
        };
        let levels = (0..l)
            .map(|i| {
                let res = (n_min * b.powi(i as i32) + 1e-9).floor().max(1.0) as u32;
                let verts = (res as u64 + 1).pow(3);
                Level {
                    res,
                    dense: verts <= t as u64,
                }
            })
            .collect();
        HashGrid {
            levels,
            f: cfg.features_per_level,
            t,
        }
    }

    /// Output width: levels x features.
    pub fn out_dim(&self) -> usize {
        self.levels.len() * self.f
    }

    /// Number of table parameters.
    pub fn table_len(&self) -> usize {
        self.levels.len() * self.t * self.f
    }

    /// Table entry indices (within the level, before the level offset) and trilinear weights of
    /// the 8 corners around `x` at `level`. Corner `c` has offsets `(c & 1, c >> 1 & 1, c >> 2)`.
    #[inline]
    pub fn corners(&self, level: usize, x: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let lv = self.levels[level];
        let res = lv.res;
        // Per axis: the two vertex coordinates' index terms and the two weights.
        let mut term = [[0u32; 2]; 3];
        let mut wa = [[0f32; 2]; 3];
        let r = res + 1;
        let mul = if lv.dense { [1, r, r * r] } else { PRIMES };
        for a in 0..3 {
            let p = x[a].clamp(0.0, 1.0) * res as f32;
            let c = (p as u32).min(res - 1);
            let f = p - c as f32;
            wa[a] = [1.0 - f, f];
            term[a] = [c.wrapping_mul(mul[a]), (c + 1).wrapping_mul(mul[a])];
        }
        let mut idx = [0u32; 8];
        let mut w = [0f32; 8];
        let mask = (self.t - 1) as u32;
        for c in 0..8 {
            let (ox, oy, oz) = (c & 1, (c >> 1) & 1, c >> 2);
            idx[c] = if lv.dense {
                term[0][ox] + term[1][oy] + term[2][oz]
            } else {
                (term[0][ox] ^ term[1][oy] ^ term[2][oz]) & mask
            };
            w[c] = wa[0][ox] * wa[1][oy] * wa[2][oz];
        }
        (idx, w)
    }

    /// Encodes `x` into `out` (`out_dim` values).
    pub fn encode(&self, table: &[f32], x: [f32; 3], out: &mut [f32]) {
        let f = self.f;
        for l in 0..self.levels.len() {
            let (idx, w) = self.corners(l, x);
            let base = l * self.t;
            let o = &mut out[l * f..(l + 1) * f];
            o.iter_mut().for_each(|v| *v = 0.0);
            for c in 0..8 {
                let e = (base + idx[c] as usize) * f;
                for k in 0..f {
                    o[k] += w[c] * table[e + k];
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(levels: usize, log2: u32, base: usize, fin: usize) -> InrConfig {
        InrConfig {
            levels,
            log2_table: log2,
            base_resolution: base,
            finest_resolution: Some(fin),
            ..Default::default()
        }
    }

    #[test]
    fn resolutions_follow_the_geometric_series() {
        let g = HashGrid::new(&InrConfig::default(), 161);
        assert_eq!(g.levels.len(), 16);
        assert_eq!(g.levels[0].res, 16);
        assert_eq!(g.levels[15].res, 161);
        // 2^19 entries hold a dense grid of (R+1)^3 <= 524288, i.e. R <= 79.
        assert!(g
            .levels
            .iter()
            .all(|l| l.dense == ((l.res as u64 + 1).pow(3) <= 1 << 19)));
        assert!(g.levels[0].dense && !g.levels[15].dense);
    }

    #[test]
    fn hand_computed_dense_corner_and_weights() {
        // One level of 4 cells: x = (0.3, 0.55, 0.9) -> p = (1.2, 2.2, 3.6), cell (1, 2, 3).
        let g = HashGrid::new(&cfg(1, 10, 4, 4), 4);
        let (idx, w) = g.corners(0, [0.3, 0.55, 0.9]);
        // R = 5 vertices per axis: corner 0 = 1 + 2*5 + 3*25 = 86; corner 7 = 2 + 15 + 100 = 117.
        assert_eq!(idx[0], 86);
        assert_eq!(idx[7], 117);
        assert_eq!(idx[1], 87);
        assert_eq!(idx[2], 91);
        assert_eq!(idx[4], 111);
        let (fx, fy, fz) = (0.2f32, 0.2f32, 0.6f32);
        let want0 = (1.0 - fx) * (1.0 - fy) * (1.0 - fz);
        let want7 = fx * fy * fz;
        assert!(
            (w[0] - want0).abs() < 1e-5 && (w[7] - want7).abs() < 1e-5,
            "{w:?}"
        );
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn hand_computed_hash() {
        // A level too fine for the table (R = 64 -> 65^3 > 2^10): hashed.
        let g = HashGrid::new(&cfg(1, 10, 64, 64), 64);
        assert!(!g.levels[0].dense);
        let (idx, _) = g.corners(0, [3.5 / 64.0, 7.5 / 64.0, 11.5 / 64.0]);
        let h = |x: u32, y: u32, z: u32| {
            (x ^ y.wrapping_mul(2654435761) ^ z.wrapping_mul(805459861)) & 1023
        };
        assert_eq!(idx[0], h(3, 7, 11));
        assert_eq!(idx[7], h(4, 8, 12));
        assert_eq!(idx[6], h(3, 8, 12));
    }

    #[test]
    fn encoding_is_trilinear_and_exact_at_vertices() {
        let g = HashGrid::new(&cfg(1, 12, 8, 8), 8);
        let table: Vec<f32> = (0..g.table_len()).map(|i| (i % 97) as f32 * 0.01).collect();
        let mut out = [0.0f32; 2];
        // At a vertex only one corner has weight.
        g.encode(&table, [2.0 / 8.0, 3.0 / 8.0, 4.0 / 8.0], &mut out);
        let e = (2 + 3 * 9 + 4 * 81) * 2;
        assert!((out[0] - table[e]).abs() < 1e-6 && (out[1] - table[e + 1]).abs() < 1e-6);
        // Halfway along x: the mean of the two vertices.
        g.encode(&table, [2.5 / 8.0, 3.0 / 8.0, 4.0 / 8.0], &mut out);
        assert!((out[0] - 0.5 * (table[e] + table[e + 2])).abs() < 1e-6);
    }
}
