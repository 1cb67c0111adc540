//! Helpers shared by the workspace integration tests.
//!
//! Real volumes are read from `../shared/data` (beside the repository). Where that folder is
//! absent (a user's fresh clone) the tests that need it print `SKIP` and return; where
//! `CI=true` its absence is a failure.

use std::path::PathBuf;

/// The workspace root.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `../shared/data/<rel>` if present. Skips (returns `None`) where absent, panics under CI.
pub fn shared(rel: &str) -> Option<PathBuf> {
    let p = workspace().join("..").join("shared").join("data").join(rel);
    if p.exists() {
        return Some(p);
    }
    if std::env::var("CI").map(|v| v == "true").unwrap_or(false) {
        panic!("{} is required under CI=true but missing", p.display());
    }
    eprintln!(
        "SKIP: {} is absent (real-data test skipped on this machine)",
        p.display()
    );
    None
}

/// A fresh temporary directory.
pub fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// Deterministic pseudo-random f32 values in [lo, hi).
pub fn noise(n: usize, seed: u64, lo: f32, hi: f32) -> Vec<f32> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((s >> 40) as f32 / (1u64 << 24) as f32)
        })
        .collect()
}

/// A smooth test volume with structure at several scales (x fastest).
pub fn blobs(dims: [usize; 3]) -> Vec<f32> {
    let mut v = Vec::with_capacity(dims.iter().product());
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let (fx, fy, fz) = (x as f32, y as f32, z as f32);
                v.push(
                    100.0 * (fx * 0.3).sin() * (fy * 0.2).cos()
                        + 50.0 * (fz * 0.45).sin()
                        + 0.5 * fx * fy
                        - fz,
                );
            }
        }
    }
    v
}

/// Writes a little-endian NIfTI-1 file of `dtype` from f64 values (for reader tests).
pub fn write_nifti_values(
    path: &std::path::Path,
    dims: [usize; 3],
    dtype: neuvolex_bricks::DType,
    values: &[f64],
    scaling: Option<(f64, f64)>,
) {
    let mut vol = neuvolex_bricks::MemVolume::from_f64(dims, dtype, values);
    vol.meta.scaling = scaling;
    neuvolex_bricks::nifti::write_nifti(path, &mut vol, 7).expect("write nifti");
}

/// Ingests `vol` into a fresh temporary store with `brick`-sized bricks.
pub fn store_of(
    vol: &mut dyn neuvolex_bricks::VolumeSource,
    brick: usize,
) -> (tempfile::TempDir, neuvolex_bricks::BrickStore) {
    let d = tmp();
    let p = d.path().join("s.zarr");
    neuvolex_bricks::ingest(
        vol,
        &p,
        &neuvolex_bricks::IngestOptions {
            brick,
            ..Default::default()
        },
        &mut |_| {},
    )
    .expect("ingest");
    let s = neuvolex_bricks::BrickStore::open(&p).expect("open store");
    (d, s)
}
