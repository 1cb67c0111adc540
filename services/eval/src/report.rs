//! Markdown tables of the results, as BENCHMARKS.md shows them.

use crate::oneshot::Row;
use crate::robot::{summarise, RoundRow, BIG_DROP};
use std::fmt::Write;

/// Mean and sample standard deviation.
pub fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len().max(1) as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

/// A configuration of the one-shot table: dataset, method, INR, epochs, trees, precision.
type Key = (String, String, String, String, usize, String);

fn key_of(r: &Row) -> Key {
    (
        r.dataset.clone(),
        r.method.clone(),
        r.inr.clone(),
        format!("{}", r.epochs),
        r.trees,
        r.quantise.clone(),
    )
}

/// Mean F1 (over classes; mean ± std over seeds) per configuration and level, then the
/// per-class F1 of each configuration.
pub fn oneshot_tables(rows: &[Row]) -> String {
    let mut keys: Vec<Key> = Vec::new();
    let mut levels: Vec<String> = Vec::new();
    for r in rows {
        let k = key_of(r);
        if !keys.contains(&k) {
            keys.push(k);
        }
        if !levels.contains(&r.level) {
            levels.push(r.level.clone());
        }
    }
    levels.sort();
    let of = |k: &Key, l: &str| -> Vec<&Row> {
        rows.iter()
            .filter(|r| &key_of(r) == k && r.level == l)
            .collect()
    };
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| dataset | method | INR | epochs | trees | precision | {} | classify s |",
        levels.join(" | ")
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|{}---|",
        "---|".repeat(levels.len())
    );
    for k in &keys {
        let cells: Vec<String> = levels
            .iter()
            .map(|l| {
                let v: Vec<f64> = of(k, l).iter().map(|r| r.mean_f1).collect();
                if v.is_empty() {
                    String::new()
                } else {
                    let (m, sd) = mean_std(&v);
                    format!("{m:.3} ± {sd:.3}")
                }
            })
            .collect();
        let secs: Vec<f64> = levels
            .iter()
            .flat_map(|l| of(k, l).into_iter().map(|r| r.seconds_classify))
            .collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {:.1} |",
            k.0,
            k.1,
            k.2,
            k.3,
            k.4,
            k.5,
            cells.join(" | "),
            mean_std(&secs).0
        );
    }
    let _ = writeln!(s, "\nper-class F1 (mean over seeds):");
    for k in &keys {
        let mut line = format!("  {} {} {} {}ep {}t {}:", k.0, k.1, k.2, k.3, k.4, k.5);
        for l in &levels {
            let rs = of(k, l);
            if rs.is_empty() {
                continue;
            }
            let per: Vec<String> = (0..rs[0].f1.len())
                .map(|c| {
                    let v: Vec<f64> = rs.iter().map(|r| r.f1[c].f1).collect();
                    format!("{}={:.2}", rs[0].f1[c].label, mean_std(&v).0)
                })
                .collect();
            let _ = write!(line, " {l}[{}]", per.join(" "));
        }
        let _ = writeln!(s, "{line}");
    }
    s
}

/// The robot's table: per method and placement, mean F1 after rounds 0 (S1), 1, 2, 5 and the
/// last, rounds to each target (median over seeds; `>N` where a seed did not get there), and
/// seconds per round.
pub fn robot_table(rows: &[RoundRow], targets: &[f64]) -> String {
    let sums = summarise(rows, targets);
    let rounds = sums.iter().map(|s| s.f1.len()).max().unwrap_or(1) - 1;
    let mut show: Vec<usize> = vec![0, 1, 2, 5, rounds];
    show.retain(|&r| r <= rounds);
    show.dedup();
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| dataset | method | INR | robot | {} | {} | worse rounds | drops > {BIG_DROP} | worst drop | mean change outside | worst drop outside | changed outside | s / round (predict) |",
        show.iter()
            .map(|r| format!("F1 r{r}"))
            .collect::<Vec<_>>()
            .join(" | "),
        targets
            .iter()
            .map(|t| format!("rounds to {t}"))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|{}{}---|---|---|---|---|---|---|",
        "---|".repeat(show.len()),
        "---|".repeat(targets.len())
    );
    for m in &sums {
        let f1: Vec<String> = show
            .iter()
            .map(|&r| format!("{:.3}", m.f1[r.min(m.f1.len() - 1)]))
            .collect();
        let to: Vec<String> = m
            .rounds_to
            .iter()
            .map(|per_seed| {
                let cells: Vec<String> = per_seed
                    .iter()
                    .map(|r| r.map_or(format!(">{rounds}"), |r| r.to_string()))
                    .collect();
                let mut v: Vec<usize> = per_seed.iter().map(|r| r.unwrap_or(usize::MAX)).collect();
                v.sort_unstable();
                let med = v[v.len() / 2];
                let med = if med == usize::MAX {
                    format!(">{rounds}")
                } else {
                    med.to_string()
                };
                format!("{med} ({})", cells.join(" "))
            })
            .collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {:.0} % | {:.0} % | {:.3} | {:+.4} | {:.3} | {:.0} % | {:.2} ({:.2}) |",
            m.dataset,
            m.method,
            m.inr,
            m.placement,
            f1.join(" | "),
            to.join(" | "),
            100.0 * m.worse,
            100.0 * m.big_drops,
            m.worst_drop,
            m.mean_delta_outside,
            m.worst_drop_outside,
            100.0 * m.changed_outside,
            m.seconds,
            m.seconds_predict
        );
    }
    s
}

/// What changed the labels beyond the margin of each round's strokes
/// ([`crate::robot::attribute`]), per dataset, method and placement: each cause's share of the
/// far changed voxels, the mean F1 change it made beyond the margin per round, and the rounds
/// dropping more than [`BIG_DROP`] whose largest far loss it made; then the far verdicts the
/// rule held back and the mean F1 change per round showing them would have made; then the runs
/// whose last round ended below their first.
pub fn far_table(rows: &[RoundRow], targets: &[f64]) -> String {
    let sums = summarise(rows, targets);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| dataset | method | robot | far voxels changed | forest | prior | growth | release | mean far F1 change per round: forest / prior / growth / release | drops > {BIG_DROP} by cause (forest prior growth release) | far verdicts held back | mean far F1 change per round had they been shown | runs ending below r0 |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for m in &sums {
        let f = &m.far;
        let total = f.forest + f.prior + f.growth + f.release;
        let share = |k: u64| format!("{:.0} %", 100.0 * k as f64 / total.max(1) as f64);
        let n = rows
            .iter()
            .filter(|r| {
                r.far.is_some()
                    && r.dataset == m.dataset
                    && r.method == m.method
                    && r.inr == m.inr
                    && r.placement == m.placement
            })
            .count()
            .max(1) as f64;
        let seeds = {
            let mut v: Vec<u64> = rows
                .iter()
                .filter(|r| r.dataset == m.dataset && r.method == m.method)
                .map(|r| r.seed)
                .collect();
            v.sort_unstable();
            v.dedup();
            v.len()
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {:+.4} / {:+.4} / {:+.4} / {:+.4} | {} {} {} {} | {} | {:+.4} | {} of {} |",
            m.dataset,
            m.method,
            m.placement,
            total,
            share(f.forest),
            share(f.prior),
            share(f.growth),
            share(f.release),
            f.d_forest / n,
            f.d_prior / n,
            f.d_growth / n,
            f.d_release / n,
            m.drops_by_cause[0],
            m.drops_by_cause[1],
            m.drops_by_cause[2],
            m.drops_by_cause[3],
            f.held,
            f.d_held / n,
            m.ended_below,
            seeds,
        );
    }
    s
}
