//! Shared helpers for the benchmark binaries.

use std::path::PathBuf;
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
