//! Adam for the dense parameters and the hash table, with lazy (touched-rows-only) or dense
//! updates of the table.
//!
//! Lazy updates follow TensorFlow's LazyAdam: rows that got no gradient in a step keep their
//! moments and value. With 16.8 M table parameters and a few hundred thousand touched per step,
//! this turns the per-step cost of the table from O(table) into O(touched).

use crate::config::TableAdam;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Adam hyper-parameters and state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// First-moment decay.
    pub b1: f32,
    /// Second-moment decay.
    pub b2: f32,
    /// Denominator epsilon.
    pub eps: f32,
    /// Steps taken.
    pub t: u64,
    /// Dense first moments.
    #[serde(skip)]
    pub m_dense: Vec<f32>,
    /// Dense second moments.
    #[serde(skip)]
    pub v_dense: Vec<f32>,
    /// Table first moments.
    #[serde(skip)]
    pub m_table: Vec<f32>,
    /// Table second moments.
    #[serde(skip)]
    pub v_table: Vec<f32>,
}

/// Accumulated table gradient of one step: a dense buffer plus, per level, a bitset of the
/// touched entries (walked in index order, so updates and clearing stream through memory).
#[derive(Debug, Clone)]
pub struct TableGrad {
    /// Gradient per table parameter (zero where untouched).
    pub g: Vec<f32>,
    mark: Vec<Vec<u64>>,
    /// Entries per level.
    pub t: usize,
    /// Features per entry.
    pub f: usize,
}

/// Calls `f(entry)` for every set bit of `mark`, in increasing order.
#[inline]
fn for_each_marked(mark: &[u64], mut f: impl FnMut(usize)) {
    for (w, &word) in mark.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            f(w * 64 + b);
            bits &= bits - 1;
        }
    }
}

impl TableGrad {
    /// An empty accumulator for `levels` levels of `t` entries of `f` features.
    pub fn new(levels: usize, t: usize, f: usize) -> Self {
        TableGrad {
            g: vec![0.0; levels * t * f],
            mark: vec![vec![0; t.div_ceil(64)]; levels],
            t,
            f,
        }
    }

    /// Scatters the lanes' table-gradient terms into the buffer, level by level in parallel,
    /// lanes and samples in order (so the sums are the same for any thread count).
    pub fn scatter(&mut self, lanes: &[&crate::model::Work]) {
        let (t, f) = (self.t, self.f);
        let nl = self.mark.len();
        self.g
            .par_chunks_mut(t * f)
            .zip(self.mark.par_iter_mut())
            .enumerate()
            .for_each(|(l, (g, mark))| {
                for lane in lanes {
                    let (n, idx, wts, dpos) = lane.table_terms();
                    for i in 0..n {
                        if i + crate::model::PREFETCH < n {
                            let o = ((i + crate::model::PREFETCH) * nl + l) * 8;
                            for c in 0..8 {
                                crate::model::prefetch(g, idx[o + c] as usize * f);
                            }
                        }
                        let o = (i * nl + l) * 8;
                        let d = &dpos[i * nl * f + l * f..i * nl * f + (l + 1) * f];
                        for c in 0..8 {
                            let e = idx[o + c] as usize;
                            let wt = wts[o + c];
                            mark[e / 64] |= 1u64 << (e % 64);
                            for k in 0..f {
                                g[e * f + k] += wt * d[k];
                            }
                        }
                    }
                }
            });
    }

    /// ORs the entries touched so far into `acc` (one bitset of `t` bits per level, as
    /// [`TableGrad::empty_marks`] makes).
    pub fn mark_into(&self, acc: &mut [Vec<u64>]) {
        for (a, m) in acc.iter_mut().zip(&self.mark) {
            a.iter_mut().zip(m).for_each(|(a, m)| *a |= m);
        }
    }

    /// Empty touched-entry bitsets shaped like this accumulator's.
    pub fn empty_marks(&self) -> Vec<Vec<u64>> {
        self.mark.iter().map(|m| vec![0; m.len()]).collect()
    }

    /// Number of touched table parameters.
    pub fn touched_params(&self) -> usize {
        self.mark
            .iter()
            .flatten()
            .map(|w| w.count_ones() as usize)
            .sum::<usize>()
            * self.f
    }
}

/// Learning rates and table mode of one Adam step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rates {
    /// Dense (MLP) learning rate.
    pub lr: f32,
    /// Hash-table learning rate.
    pub lr_table: f32,
    /// Lazy or dense table update.
    pub mode: TableAdam,
}

impl Adam {
    /// Fresh state for `dense` dense and `table` table parameters.
    pub fn new(dense: usize, table: usize) -> Self {
        Adam {
            b1: 0.9,
            b2: 0.999,
            eps: 1e-8,
            t: 0,
            m_dense: vec![0.0; dense],
            v_dense: vec![0.0; dense],
            m_table: vec![0.0; table],
            v_table: vec![0.0; table],
        }
    }

    /// One step: updates `dense` with `g_dense`, the table with `tg`, and clears `tg`.
    pub fn step(
        &mut self,
        dense: &mut [f32],
        g_dense: &[f32],
        table: &mut [f32],
        tg: &mut TableGrad,
        rates: Rates,
    ) {
        let Rates { lr, lr_table, mode } = rates;
        self.t += 1;
        let (b1, b2, eps) = (self.b1, self.b2, self.eps);
        let c1 = 1.0 - b1.powi(self.t.min(i32::MAX as u64) as i32);
        let c2 = 1.0 - b2.powi(self.t.min(i32::MAX as u64) as i32);
        let upd = move |p: &mut f32, m: &mut f32, v: &mut f32, g: f32, lr: f32| {
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            *p -= lr * (*m / c1) / ((*v / c2).sqrt() + eps);
        };
        for i in 0..dense.len() {
            upd(
                &mut dense[i],
                &mut self.m_dense[i],
                &mut self.v_dense[i],
                g_dense[i],
                lr,
            );
        }
        let (t, f) = (tg.t, tg.f);
        match mode {
            TableAdam::Dense => {
                table
                    .par_chunks_mut(1 << 16)
                    .zip(self.m_table.par_chunks_mut(1 << 16))
                    .zip(self.v_table.par_chunks_mut(1 << 16))
                    .zip(tg.g.par_chunks(1 << 16))
                    .for_each(|(((p, m), v), g)| {
                        for i in 0..p.len() {
                            upd(&mut p[i], &mut m[i], &mut v[i], g[i], lr_table);
                        }
                    });
            }
            TableAdam::Lazy => {
                table
                    .par_chunks_mut(t * f)
                    .zip(self.m_table.par_chunks_mut(t * f))
                    .zip(self.v_table.par_chunks_mut(t * f))
                    .zip(tg.g.par_chunks(t * f))
                    .zip(tg.mark.par_iter())
                    .for_each(|((((p, m), v), g), mark)| {
                        for_each_marked(mark, |e| {
                            for k in 0..f {
                                let i = e * f + k;
                                upd(&mut p[i], &mut m[i], &mut v[i], g[i], lr_table);
                            }
                        });
                    });
            }
        }
        // Clear the touched gradient entries and marks.
        tg.g.par_chunks_mut(t * f)
            .zip(tg.mark.par_iter_mut())
            .for_each(|(g, mark)| {
                for_each_marked(mark, |e| {
                    for k in 0..f {
                        g[e * f + k] = 0.0;
                    }
                });
                mark.iter_mut().for_each(|w| *w = 0);
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lazy_and_dense_agree_on_touched_rows_and_lazy_leaves_the_rest() {
        let mut table_a = vec![1.0f32; 2 * 8 * 2];
        let mut table_b = table_a.clone();
        let (mut da, mut db) = (vec![0.5f32; 3], vec![0.5f32; 3]);
        let mut adam_a = Adam::new(3, table_a.len());
        let mut adam_b = Adam::new(3, table_a.len());
        let mut tg_a = TableGrad::new(2, 8, 2);
        let mut tg_b = TableGrad::new(2, 8, 2);
        for tg in [&mut tg_a, &mut tg_b] {
            // Level 0 entry 3 gets (0.2, -0.2); level 1 entry 7 gets (1, 1).
            tg.g[3 * 2] = 0.2;
            tg.g[3 * 2 + 1] = -0.2;
            tg.mark[0][0] |= 1 << 3;
            tg.g[(8 + 7) * 2] = 1.0;
            tg.g[(8 + 7) * 2 + 1] = 1.0;
            tg.mark[1][0] |= 1 << 7;
        }
        assert_eq!(tg_a.touched_params(), 4);
        adam_a.step(
            &mut da,
            &[0.1, 0.0, -0.1],
            &mut table_a,
            &mut tg_a,
            Rates {
                lr: 0.01,
                lr_table: 0.1,
                mode: TableAdam::Lazy,
            },
        );
        adam_b.step(
            &mut db,
            &[0.1, 0.0, -0.1],
            &mut table_b,
            &mut tg_b,
            Rates {
                lr: 0.01,
                lr_table: 0.1,
                mode: TableAdam::Dense,
            },
        );
        assert_eq!(da, db);
        // Touched rows move by lr (first Adam step), identically in both modes.
        assert!((table_a[6] - 0.9).abs() < 1e-6 && table_a[6] == table_b[6]);
        assert!((table_a[(8 + 7) * 2] - 0.9).abs() < 1e-6);
        // Untouched rows: unchanged (zero gradient gives a zero first step in both modes).
        assert_eq!(table_a[0], 1.0);
        assert!(tg_a.g.iter().all(|&g| g == 0.0) && tg_a.touched_params() == 0);
    }
}
