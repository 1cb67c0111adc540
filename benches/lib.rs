//! Shared helpers for the benchmark binaries.

use std::path::PathBuf;

pub mod vs_torch;
use std::time::{Duration, Instant};

/// `../shared/data/<rel>` if present (benchmarks that need it say so and skip otherwise).
/// `NEUVOLEX_DATA` names another data folder (a bench binary carried to another machine).
pub fn shared(rel: &str) -> Option<PathBuf> {
    let root = std::env::var_os("NEUVOLEX_DATA").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
        PathBuf::from,
    );
    let p = root.join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("SKIP: {} absent", p.display());
        None
    }
}

/// Runs `f` `reps` times and returns the median duration.
pub fn median<F: FnMut()>(reps: usize, mut f: F) -> Duration {
    let mut t: Vec<Duration> = (0..reps.max(1))
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed()
        })
        .collect();
    t.sort();
    t[t.len() / 2]
}

/// Peak resident set size of this process (VmHWM) in MiB, from /proc.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// A one-line description of this machine for BENCHMARKS.md.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    format!(
        "{cpu}, {} threads",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    )
}

/// The INR trained on `store` for one epoch with the default configuration (no previews, no
/// checkpoints): the feature extractor the classification and viewpoint benchmarks share.
pub fn train_one_epoch(store: &neuvolex_bricks::BrickStore) -> neuvolex_features::InrModel {
    use neuvolex_features::{train, Budget, InrConfig, TrainConfig};
    let c = TrainConfig {
        budget: Budget {
            epochs: Some(1.0),
            ..Default::default()
        },
        preview_every: 0,
        checkpoint_every: 0,
        ..TrainConfig::default()
    };
    train(
        store,
        &InrConfig::default(),
        &c,
        None,
        None,
        &std::sync::atomic::AtomicBool::new(false),
        &mut |_| {},
    )
    .expect("train")
    .model
}

/// Writes the CT-like phantom at CTA-Cardiac scale (512x512x452, int16 raw, seed 1) to `path`,
/// slab by slab, for the benchmarks' large-volume runs.
pub fn write_cta(path: &std::path::Path) {
    use std::io::Write;
    let d = [512usize, 512, 452];
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).expect("raw"));
    let p = neuvolex_bricks::synth::PhantomParams {
        dims: d,
        seed: 1,
        noise: 18.0,
    };
    let mut src =
        neuvolex_bricks::synth::Phantom::new(p, neuvolex_bricks::synth::PhantomChannel::Image);
    for z in (0..d[2]).step_by(4) {
        let s =
            neuvolex_formats::VolumeSource::read_slab(&mut src, z, 4.min(d[2] - z)).expect("slab");
        f.write_all(&s.bytes).expect("write");
    }
    f.flush().expect("flush");
}

/// A reference implementation in a child process that answers one JSON line per command line
/// (`render_vtk.py`, `forest_sklearn.py`, `kmeans_sklearn.py`): it loads its inputs once, then
/// the bench interleaves its rounds with our own, so a load change on a shared machine hits
/// both sides alike. Sends `quit` and waits for the child when dropped.
pub struct JsonChild {
    child: std::process::Child,
    stdin: std::process::ChildStdin,
    out: std::io::BufReader<std::process::ChildStdout>,
    /// The first line the child printed (its `ready` message).
    pub ready: serde_json::Value,
}

impl JsonChild {
    /// Starts `python script args` with `envs` and waits for its first JSON line; `None`, with
    /// the reason on stderr (`what` names the reference), where the interpreter or a module
    /// is missing or the script fails before it is ready.
    pub fn start(
        what: &str,
        python: &str,
        script: &std::path::Path,
        args: &[String],
        envs: &[(&str, &str)],
    ) -> Option<JsonChild> {
        JsonChild::spawn(python, script, args, envs, std::process::Stdio::inherit())
            .map_err(|e| eprintln!("SKIP {what} ({python}): {e}"))
            .ok()
    }

    /// [`JsonChild::start`] with the child's stderr going to `stderr`; `Err` says why it did
    /// not become ready.
    pub fn spawn(
        python: &str,
        script: &std::path::Path,
        args: &[String],
        envs: &[(&str, &str)],
        stderr: std::process::Stdio,
    ) -> Result<JsonChild, String> {
        use std::process::{Command, Stdio};
        let mut child = Command::new(python)
            .arg(script)
            .args(args)
            .envs(envs.iter().copied())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(stderr)
            .spawn()
            .map_err(|e| e.to_string())?;
        let stdin = child.stdin.take().expect("piped stdin");
        let out = std::io::BufReader::new(child.stdout.take().expect("piped stdout"));
        let mut c = JsonChild {
            child,
            stdin,
            out,
            ready: serde_json::Value::Null,
        };
        match c.reply() {
            Some(r) => {
                c.ready = r;
                Ok(c)
            }
            None => Err("the script did not start (its error is on its stderr)".into()),
        }
    }

    /// The next JSON line the child prints (other lines are skipped); `None` once it exits.
    pub fn reply(&mut self) -> Option<serde_json::Value> {
        use std::io::BufRead;
        let mut line = String::new();
        loop {
            line.clear();
            if self.out.read_line(&mut line).ok()? == 0 {
                return None;
            }
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line) {
                return Some(v);
            }
        }
    }

    /// Sends one command line and returns the reply.
    pub fn send(&mut self, cmd: &str) -> Option<serde_json::Value> {
        use std::io::Write;
        writeln!(self.stdin, "{cmd}").ok()?;
        self.stdin.flush().ok()?;
        self.reply()
    }
}

impl Drop for JsonChild {
    fn drop(&mut self) {
        use std::io::Write;
        let _ = writeln!(self.stdin, "quit");
        let _ = self.stdin.flush();
        let _ = self.child.wait();
    }
}

/// The median (the mean of the two middle values of an even count), smallest and largest of
/// the finite values of `v`, or `None` where there are none.
pub fn median_min_max(v: &[f64]) -> Option<(f64, f64, f64)> {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    // The true median: the middle value, or the mean of the two middle values for an even
    // count (so two rounds report their mean, not their maximum).
    let m = match n {
        0 => return None,
        _ if n % 2 == 1 => s[n / 2],
        _ => 0.5 * (s[n / 2 - 1] + s[n / 2]),
    };
    Some((m, s[0], s[n - 1]))
}

/// `median [min-max]` of `v` (non-finite values left out) with `digits` decimals, or `-`.
pub fn spread(v: &[f64], digits: usize) -> String {
    median_min_max(v).map_or("-".into(), |(m, lo, hi)| {
        format!("{m:.digits$} [{lo:.digits$}-{hi:.digits$}]")
    })
}

/// The per-round ratios `a[i] / b[i]` as `median x [min-max]`, or `-`.
pub fn ratio_spread(a: &[f64], b: &[f64]) -> String {
    let r: Vec<f64> = a.iter().zip(b).map(|(x, y)| x / y).collect();
    median_min_max(&r).map_or("-".into(), |(m, lo, hi)| {
        format!("{m:.2}x [{lo:.2}-{hi:.2}]")
    })
}

/// The machine's load average as `load average A B C` (the one, five and fifteen minutes).
pub fn load_average() -> String {
    let l = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    format!(
        "load average {}",
        l.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    )
}

/// The value after `--name` in `args`, parsed, or `default` where it is absent or does not parse.
pub fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A class stroke and a background stroke on axial slice `z`, along the longest runs of each
/// in the ground truth `labels` (x fastest).
pub fn strokes_on(
    labels: &[u32],
    dims: [usize; 3],
    z: usize,
    class: u32,
    dx: usize,
) -> Vec<neuvolex_classify::scribble::Stroke> {
    let run = |want: &dyn Fn(u32) -> bool| {
        let mut best = (0usize, 0usize, 0usize);
        for y in 0..dims[1] {
            let mut len = 0;
            for x in 0..dims[0] {
                if want(labels[(z * dims[1] + y) * dims[0] + x]) {
                    len += 1;
                    if len > best.2 {
                        best = (x + 1 - len, y, len);
                    }
                } else {
                    len = 0;
                }
            }
        }
        let (x0, y, len) = best;
        assert!(len >= 3, "no run of the class on slice {z}");
        let a = (x0 + len / 4 + dx.min(len / 4)) as f32;
        let b = (x0 + 3 * len / 4) as f32;
        vec![[a, y as f32], [b, y as f32]]
    };
    vec![
        neuvolex_classify::scribble::Stroke {
            class: 1,
            axis: neuvolex_classify::scribble::Axis::Z,
            slice: z,
            points: run(&|l| l == class),
            radius: 1.0,
        },
        neuvolex_classify::scribble::Stroke {
            class: neuvolex_server::session::BACKGROUND,
            axis: neuvolex_classify::scribble::Axis::Z,
            slice: z,
            points: run(&|l| l == 0),
            radius: 1.0,
        },
    ]
}

/// The most frequent non-zero label on slice `z`.
pub fn main_class(labels: &[u32], dims: [usize; 3], z: usize) -> u32 {
    let mut counts = std::collections::HashMap::new();
    let n = dims[0] * dims[1];
    for &l in &labels[z * n..(z + 1) * n] {
        if l != 0 {
            *counts.entry(l).or_insert(0usize) += 1;
        }
    }
    counts
        .into_iter()
        .max_by_key(|e| e.1)
        .map(|e| e.0)
        .expect("a labelled voxel")
}

/// A session of `neuvolex serve` named `name` over `store` (2 GiB of features), with a class
/// for each label of `truth` (0 is none); returns it and the class ids.
pub fn session_with_classes(
    name: &str,
    store: std::sync::Arc<neuvolex_bricks::BrickStore>,
    truth: &[u32],
) -> (std::sync::Arc<neuvolex_server::session::Session>, Vec<u32>) {
    let mut ids: Vec<u32> = truth.iter().copied().filter(|&x| x > 0).collect();
    ids.sort_unstable();
    ids.dedup();
    let s = neuvolex_server::session::Session::new("bench".into(), name.into(), store, 2 << 30);
    *s.classes.write().unwrap() = ids
        .iter()
        .map(|&id| neuvolex_bricks::synth::ClassInfo {
            id,
            name: format!("class {id}"),
            color: neuvolex_bricks::synth::palette(id),
        })
        .collect();
    (s, ids)
}

#[cfg(test)]
mod tests {
    use super::median_min_max;

    #[test]
    fn median_is_the_middle_or_the_mean_of_the_two_middle_values() {
        assert_eq!(median_min_max(&[3.0, 1.0, 2.0]), Some((2.0, 1.0, 3.0)));
        assert_eq!(median_min_max(&[4.0, 1.0]), Some((2.5, 1.0, 4.0)));
        assert_eq!(
            median_min_max(&[f64::NAN, 5.0, 1.0, 2.0, 9.0]),
            Some((3.5, 1.0, 9.0))
        );
        assert_eq!(median_min_max(&[f64::NAN]), None);
    }
}
