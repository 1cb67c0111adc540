//! The harness shared by the fuzz targets: a scratch folder per process (on tmpfs where there
//! is one), the multi-file input format of the targets whose inputs are several files (NRRD
//! with detached data, raw with a sidecar, Zarr stores), and bounded reads of an opened volume.
//!
//! A target returns normally on any `Err`: only a panic, an abort, a leak past
//! `-rss_limit_mb`, an allocation past `-malloc_limit_mb` or a timeout is a finding.

pub mod alloc_limit;
pub mod mutate;
pub mod targets;

use neuvolex_formats::VolumeSource;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// This process's scratch folder (`/dev/shm/nvx-fuzz-PID`, or under the temp folder).
pub fn scratch() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let base = if Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        };
        let d = base.join(format!("nvx-fuzz-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("scratch folder");
        d
    })
}

/// Removes this process's scratch folder (the replay test calls it when done).
pub fn remove_scratch() {
    let _ = std::fs::remove_dir_all(scratch());
}

/// An empty folder `name` inside the scratch folder (its previous content removed).
pub fn fresh(name: &str) -> PathBuf {
    let d = scratch().join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch folder");
    d
}

/// Most files in one multi-file input.
pub const MAX_ENTRIES: usize = 64;

/// Packs files into one fuzz input: for each, a name length byte, the name, a little-endian
/// u32 length and the bytes.
pub fn pack(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    for (name, bytes) in entries {
        let n = name.as_bytes();
        out.push(n.len().min(255) as u8);
        out.extend_from_slice(&n[..n.len().min(255)]);
        out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        out.extend_from_slice(bytes);
    }
    out
}

/// Unpacks a multi-file input. Any byte string unpacks: a short length takes what is left, and
/// names are made safe relative paths (no `..`, no absolute paths, at most 8 levels).
pub fn unpack(mut data: &[u8]) -> Vec<(PathBuf, &[u8])> {
    let mut out = Vec::new();
    while !data.is_empty() && out.len() < MAX_ENTRIES {
        let nl = data[0] as usize;
        data = &data[1..];
        let name = &data[..nl.min(data.len())];
        data = &data[name.len()..];
        let mut len = [0u8; 4];
        let k = data.len().min(4);
        len[..k].copy_from_slice(&data[..k]);
        data = &data[k..];
        let len = (u32::from_le_bytes(len) as usize).min(data.len());
        let (bytes, rest) = data.split_at(len);
        data = rest;
        if let Some(p) = safe_name(name) {
            out.push((p, bytes));
        }
    }
    out
}

fn safe_name(name: &[u8]) -> Option<PathBuf> {
    let s = std::str::from_utf8(name).ok()?;
    let parts: Vec<&str> = s.split('/').filter(|c| !c.is_empty()).collect();
    if parts.is_empty() || parts.len() > 8 {
        return None;
    }
    let ok = |c: &str| {
        c != "."
            && c != ".."
            && c.len() <= 64
            && c.bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
    };
    parts.iter().all(|c| ok(c)).then(|| parts.iter().collect())
}

/// Writes unpacked files under `dir` (a file where a folder is needed, or the reverse, is
/// skipped: the fuzzer may name both `a` and `a/b`).
pub fn write_all(dir: &Path, entries: &[(PathBuf, &[u8])]) {
    for (name, bytes) in entries {
        let p = dir.join(name);
        if let Some(parent) = p.parent() {
            if std::fs::create_dir_all(parent).is_err() {
                continue;
            }
        }
        let _ = std::fs::write(&p, bytes);
    }
}

/// Most voxel bytes read at once by [`exercise`] beyond the first and last slice.
pub const READ_ALL_BYTES: u64 = 1 << 20;

/// Reads an opened volume as the ingest does, within bounds: the first and last slice, the
/// whole volume when it is small, and the conversions to floats.
pub fn exercise(src: &mut dyn VolumeSource) {
    let meta = src.meta().clone();
    let nz = meta.dims[2];
    let total = meta.voxels() * meta.dtype.size() as u64;
    let _ = meta.scale(1.0);
    for z in [0, nz - 1] {
        if let Ok(slab) = src.read_slab(z, 1) {
            let _ = slab.to_f32_scaled(&meta);
            src.release(z, 1);
        }
    }
    if total <= READ_ALL_BYTES {
        if let Ok(slab) = src.read_slab(0, nz) {
            assert_eq!(slab.len() as u64, meta.voxels(), "slab of the wrong size");
            let v = slab.to_f32_scaled(&meta);
            let _ = v.iter().fold(0f32, |a, &b| a.max(b));
        }
    }
    // Out-of-range requests must be errors.
    assert!(src.read_slab(nz, 1).is_err());
    assert!(src.read_slab(0, 0).is_err());
}

/// Opens `path` with the format detection of `neuvolex ingest` and reads it.
pub fn open_and_read(path: &Path) {
    if let Ok(mut src) = neuvolex_bricks::open_volume(path, None) {
        exercise(src.as_mut());
    }
}

/// Writes every target's seeds into `out/TARGET/` with the `seeds` binary (`seeds_bin`), from
/// the real volumes beside the project (`fuzz/../../shared/data`): their crops are skipped,
/// visibly, where that folder is missing, and that is an error under `CI=true`. Panics when
/// the seed writer fails (test helper).
pub fn write_seeds(seeds_bin: &Path, out: &Path) {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if !data.is_dir() {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "{} is missing: CI=true requires the real volumes for the fuzz seeds",
            data.display()
        );
        eprintln!(
            "fuzz: {} missing, real-volume seeds SKIPPED (project-written seeds only)",
            data.display()
        );
    }
    let st = std::process::Command::new(seeds_bin)
        .arg(&data)
        .arg(out)
        .status()
        .expect("running the seed writer");
    assert!(st.success(), "the seed writer failed");
}

/// Every input of `target` under `dirs` (each `DIR/TARGET/*`), sorted: the seeds and the saved
/// findings (`fuzz/regressions/TARGET/`).
pub fn inputs(target: &str, dirs: &[&Path]) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = dirs
        .iter()
        .filter_map(|d| std::fs::read_dir(d.join(target)).ok())
        .flat_map(|rd| rd.flatten().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    v.sort();
    v
}

/// The message of a caught panic.
pub fn panic_message(e: &(dyn std::any::Any + Send)) -> String {
    e.downcast_ref::<String>()
        .cloned()
        .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_default()
}
