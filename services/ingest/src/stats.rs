//! Streaming volume statistics: min, max, mean, std, 0.5/99.5 percentiles, 256-bin histogram
//! ([`VolumeStats`], as the store keeps them).
//!
//! Integer types of at most 16 bits are counted exactly in one pass. Wider and float types
//! need a second pass once min and max are known: a 65 536-bin histogram over `[min, max]`
//! locates the percentiles to within `(max-min)/65536`, refined by linear interpolation.

use neuvolex_bricks::stats::{VolumeStats, HIST_BINS};
use neuvolex_formats::dtype::DType;
use serde::{Deserialize, Serialize};

const FINE_BINS: usize = 65536;

/// One-pass accumulator of count, min, max, mean and variance (shifted sums in f64),
/// plus exact counts for small integer types. Serialisable, so a cluster task can return it as
/// a partial.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StatsAccumulator {
    n: u64,
    min: f64,
    max: f64,
    shift: Option<f64>,
    sum: f64,
    sumsq: f64,
    exact: Option<(f64, Vec<u64>)>,
    scaling: Option<(f64, f64)>,
    /// Non-finite values replaced upstream.
    pub non_finite_replaced: u64,
}

impl StatsAccumulator {
    /// A new accumulator. With `raw_dtype` a small integer type, raw values are counted exactly.
    pub fn new(raw_dtype: DType, scaling: Option<(f64, f64)>) -> Self {
        let exact = raw_dtype.is_small_int().then(|| {
            (
                raw_dtype.range().0,
                vec![0u64; (raw_dtype.range().1 - raw_dtype.range().0) as usize + 1],
            )
        });
        StatsAccumulator {
            n: 0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            shift: None,
            sum: 0.0,
            sumsq: 0.0,
            exact,
            scaling,
            non_finite_replaced: 0,
        }
    }

    /// Adds raw (unscaled) values. Small integer types only count (everything else is derived
    /// from the exact histogram at the end); other types keep shifted f64 sums.
    pub fn add_raw(&mut self, raw: &[f64]) {
        if let Some((lo, counts)) = &mut self.exact {
            let lo = *lo;
            for &v in raw {
                counts[(v - lo) as usize] += 1;
            }
            self.n += raw.len() as u64;
            return;
        }
        let (s, i) = self.scaling.unwrap_or((1.0, 0.0));
        let shift = *self
            .shift
            .get_or_insert_with(|| raw.first().map(|&v| v * s + i).unwrap_or(0.0));
        let (mut sum, mut sumsq) = (0.0f64, 0.0f64);
        let (mut mn, mut mx) = (self.min, self.max);
        for &r in raw {
            let v = r * s + i;
            mn = mn.min(v);
            mx = mx.max(v);
            let d = v - shift;
            sum += d;
            sumsq += d * d;
        }
        self.min = mn;
        self.max = mx;
        self.sum += sum;
        self.sumsq += sumsq;
        self.n += raw.len() as u64;
    }

    /// Counts small-integer raw values exactly (only valid when [`Self::needs_second_pass`] is false).
    pub fn add_ints(&mut self, raw: &[i32]) {
        if let Some((lo, counts)) = &mut self.exact {
            let lo = *lo as i32;
            for &v in raw {
                counts[(v - lo) as usize] += 1;
            }
            self.n += raw.len() as u64;
        }
    }

    /// Rebuilds min, max and the shifted sums from the exact counts.
    fn derive_from_counts(&mut self) {
        let Some((lo, counts)) = &self.exact else {
            return;
        };
        let (s, i) = self.scaling.unwrap_or((1.0, 0.0));
        let shift = self.shift.unwrap_or(0.0);
        let (mut mn, mut mx, mut sum, mut sumsq) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0.0);
        for (k, &c) in counts.iter().enumerate() {
            if c > 0 {
                let v = (k as f64 + lo) * s + i;
                mn = mn.min(v);
                mx = mx.max(v);
                let d = v - shift;
                sum += d * c as f64;
                sumsq += d * d * c as f64;
            }
        }
        (self.min, self.max, self.sum, self.sumsq) = (mn, mx, sum, sumsq);
    }

    /// Takes the shifted sums accumulated so far (leaving zero), so a caller can keep them per
    /// slice and add them back in a fixed order with [`Self::add_sums`].
    pub fn take_sums(&mut self) -> (f64, f64) {
        (
            std::mem::take(&mut self.sum),
            std::mem::take(&mut self.sumsq),
        )
    }

    /// Adds shifted sums that [`Self::take_sums`] took.
    pub fn add_sums(&mut self, sum: f64, sumsq: f64) {
        self.sum += sum;
        self.sumsq += sumsq;
    }

    /// Fixes the shift used for the shifted sums (done once, before forking).
    pub fn set_shift_if_unset(&mut self, raw_first: f64) {
        let (s, i) = self.scaling.unwrap_or((1.0, 0.0));
        self.shift.get_or_insert(raw_first * s + i);
    }

    /// An empty accumulator with the same type, scaling and shift, for parallel partial sums.
    pub fn fork(&self) -> Self {
        StatsAccumulator {
            n: 0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            shift: self.shift,
            sum: 0.0,
            sumsq: 0.0,
            exact: self.exact.as_ref().map(|(lo, c)| (*lo, vec![0; c.len()])),
            scaling: self.scaling,
            non_finite_replaced: 0,
        }
    }

    /// Adds a forked accumulator's counts into this one (both must share the shift).
    pub fn merge(&mut self, o: StatsAccumulator) {
        debug_assert_eq!(self.shift, o.shift);
        self.n += o.n;
        self.min = self.min.min(o.min);
        self.max = self.max.max(o.max);
        self.sum += o.sum;
        self.sumsq += o.sumsq;
        self.non_finite_replaced += o.non_finite_replaced;
        if let (Some((_, a)), Some((_, b))) = (&mut self.exact, o.exact) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
    }

    /// True when percentiles need a second pass (see [`FineHistogram`]).
    pub fn needs_second_pass(&self) -> bool {
        self.exact.is_none()
    }

    /// Current min and max.
    pub fn range(&self) -> (f64, f64) {
        if self.exact.is_some() {
            let mut c = self.clone();
            c.derive_from_counts();
            return (c.min, c.max);
        }
        (self.min, self.max)
    }

    /// Finishes; `fine` must be given when [`Self::needs_second_pass`].
    pub fn finish(mut self, fine: Option<FineHistogram>) -> VolumeStats {
        self.derive_from_counts();
        let n = self.n.max(1) as f64;
        let shift = self.shift.unwrap_or(0.0);
        let mean_d = self.sum / n;
        let var = (self.sumsq / n - mean_d * mean_d).max(0.0);
        let (min, max) = if self.n == 0 {
            (0.0, 0.0)
        } else {
            (self.min, self.max)
        };
        let (s, i) = self.scaling.unwrap_or((1.0, 0.0));
        let mut histogram = vec![0u64; HIST_BINS];
        let (p0_5, p99_5) = match (&self.exact, fine) {
            (Some((lo, counts)), _) => {
                let value = |k: usize| (k as f64 + lo) * s + i;
                for (k, &c) in counts.iter().enumerate() {
                    if c > 0 {
                        histogram[bin_of(value(k), min, max, HIST_BINS)] += c;
                    }
                }
                let ordered: Box<dyn Fn(u64) -> f64> = if s >= 0.0 {
                    Box::new(|r| value(rank_index(counts, r)))
                } else {
                    Box::new(|r| value(rank_index(counts, self.n - 1 - r)))
                };
                (
                    percentile(self.n, 0.005, &ordered),
                    percentile(self.n, 0.995, &ordered),
                )
            }
            (None, Some(f)) => {
                for (k, &c) in f.counts.iter().enumerate() {
                    histogram[k * HIST_BINS / FINE_BINS] += c;
                }
                (f.quantile(0.005), f.quantile(0.995))
            }
            (None, None) => (min, max),
        };
        VolumeStats {
            voxels: self.n,
            min,
            max,
            mean: shift + mean_d,
            std: var.sqrt(),
            p0_5,
            p99_5,
            histogram,
            non_finite_replaced: self.non_finite_replaced,
        }
    }
}

fn rank_index(counts: &[u64], r: u64) -> usize {
    let mut acc = 0u64;
    for (k, &c) in counts.iter().enumerate() {
        acc += c;
        if acc > r {
            return k;
        }
    }
    counts.len() - 1
}

/// Linear-interpolated percentile (numpy's default) from an order-statistic function.
fn percentile(n: u64, q: f64, at: &dyn Fn(u64) -> f64) -> f64 {
    if n == 0 {
        return 0.0;
    }
    let pos = q * (n - 1) as f64;
    let lo = pos.floor() as u64;
    let hi = (lo + 1).min(n - 1);
    let f = pos - lo as f64;
    let a = at(lo);
    if f == 0.0 {
        a
    } else {
        a + (at(hi) - a) * f
    }
}

/// Index of the equal-width bin of `[min, max]` holding `v`.
pub fn bin_of(v: f64, min: f64, max: f64, bins: usize) -> usize {
    if max <= min {
        return 0;
    }
    let t = (v - min) / (max - min);
    ((t * bins as f64) as usize).min(bins - 1)
}

/// A 65 536-bin histogram over a known `[min, max]`, for percentiles of wide types. Each bin
/// also keeps the smallest and largest value it saw, so order statistics are exact whenever a
/// bin holds one distinct value (integer data) and interpolated inside the bin otherwise.
/// Histograms of parts of a volume merge exactly ([`Self::merge`]), in any order.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FineHistogram {
    min: f64,
    max: f64,
    counts: Vec<u64>,
    lo: Vec<f32>,
    hi: Vec<f32>,
    n: u64,
}

impl FineHistogram {
    /// An empty histogram over `[min, max]`.
    pub fn new(min: f64, max: f64) -> Self {
        FineHistogram {
            min,
            max,
            counts: vec![0; FINE_BINS],
            lo: vec![f32::INFINITY; FINE_BINS],
            hi: vec![f32::NEG_INFINITY; FINE_BINS],
            n: 0,
        }
    }

    /// Adds values.
    pub fn add(&mut self, values: &[f32]) {
        for &v in values {
            let k = bin_of(v as f64, self.min, self.max, FINE_BINS);
            self.counts[k] += 1;
            self.lo[k] = self.lo[k].min(v);
            self.hi[k] = self.hi[k].max(v);
        }
        self.n += values.len() as u64;
    }

    /// Adds the counts of a histogram over the same range (a part of the volume). Counts add and
    /// per-bin extremes combine, so the result does not depend on how the volume was split.
    pub fn merge(&mut self, o: &FineHistogram) {
        debug_assert!(
            self.min.to_bits() == o.min.to_bits() && self.max.to_bits() == o.max.to_bits()
        );
        for k in 0..self.counts.len().min(o.counts.len()) {
            self.counts[k] += o.counts[k];
            self.lo[k] = self.lo[k].min(o.lo[k]);
            self.hi[k] = self.hi[k].max(o.hi[k]);
        }
        self.n += o.n;
    }

    /// The `r`-th smallest value (0-based), exact when its bin holds a single distinct value.
    fn order_stat(&self, r: u64) -> f64 {
        let mut acc = 0u64;
        for (k, &c) in self.counts.iter().enumerate() {
            if c > 0 && acc + c > r {
                let (lo, hi) = (self.lo[k] as f64, self.hi[k] as f64);
                return if c == 1 || lo == hi {
                    lo
                } else {
                    lo + (hi - lo) * (r - acc) as f64 / (c - 1) as f64
                };
            }
            acc += c;
        }
        self.max
    }

    /// Quantile `q` in [0, 1] with numpy's linear interpolation between order statistics.
    pub fn quantile(&self, q: f64) -> f64 {
        if self.n == 0 || self.max <= self.min {
            return self.min;
        }
        percentile(self.n, q, &|r| self.order_stat(r))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_percentiles_match_sorting() {
        let vals: Vec<f64> = (0..1000).map(|i| ((i * 37) % 256) as f64).collect();
        let mut acc = StatsAccumulator::new(DType::U8, None);
        acc.add_raw(&vals);
        let s = acc.finish(None);
        let mut sorted = vals.clone();
        sorted.sort_by(f64::total_cmp);
        let pos: f64 = 0.995 * 999.0;
        let want = sorted[pos as usize]
            + (sorted[pos as usize + 1] - sorted[pos as usize]) * (pos - pos.floor());
        assert!((s.p99_5 - want).abs() < 1e-9, "{} vs {want}", s.p99_5);
        assert_eq!(s.histogram.iter().sum::<u64>(), 1000);
        let mean = vals.iter().sum::<f64>() / 1000.0;
        assert!((s.mean - mean).abs() < 1e-9);
    }

    #[test]
    fn huge_values_are_stable() {
        let vals = vec![1e30, 1e30, 1e30 + 1e24, 1e30];
        let mut acc = StatsAccumulator::new(DType::F64, None);
        acc.add_raw(&vals);
        let (lo, hi) = acc.range();
        let mut fine = FineHistogram::new(lo, hi);
        fine.add(&vals.iter().map(|&v| v as f32).collect::<Vec<_>>());
        let s = acc.finish(Some(fine));
        assert!(s.std.is_finite() && s.std > 0.0);
        assert!((s.mean - 1.00000025e30).abs() / 1e30 < 1e-9);
    }

    #[test]
    fn constant_volume() {
        let mut acc = StatsAccumulator::new(DType::F32, None);
        acc.add_raw(&[5.0; 64]);
        let fine = FineHistogram::new(5.0, 5.0);
        let s = acc.finish(Some(fine));
        assert_eq!(
            (s.min, s.max, s.std, s.p0_5, s.p99_5),
            (5.0, 5.0, 0.0, 5.0, 5.0)
        );
    }
}
