//! Atomic replacement of files and folders on a file system, and the clean-up of what killed
//! writers left beside them.

use crate::error::{BrickError, Result};
use std::path::Path;

/// Deletes what killed writers left beside `out`: `.NAME.partial-PID` and `.NAME.old-PID`
/// folders whose process is gone (Linux; elsewhere they are left).
pub fn remove_stale_siblings(out: &Path) {
    let (Some(dir), Some(name)) = (out.parent(), out.file_name()) else {
        return;
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let name = name.to_string_lossy();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let f = e.file_name().to_string_lossy().into_owned();
        // `.NAME.partial-PID`, `.NAME.old-PID`, or with a sequence number `-PID-N`.
        let pid = [".partial-", ".old-"].iter().find_map(|tag| {
            f.strip_prefix(&format!(".{name}{tag}"))
                .and_then(|p| p.split('-').next())
                .and_then(|p| p.parse::<u32>().ok())
        });
        if let Some(pid) = pid {
            let gone = cfg!(target_os = "linux") && !Path::new(&format!("/proc/{pid}")).exists();
            if gone && pid != std::process::id() {
                tracing::info!(path = %e.path().display(), "removing what an interrupted writer left");
                let p = e.path();
                let _ = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
            }
        }
    }
}

/// Replaces the file at `path` with `bytes` atomically: written to a hidden sibling
/// temporary (`.NAME.partial-PID-N`), synced, then renamed over it, so a crash leaves the
/// previous file or the new one, never a part. Temporaries that killed writers left beside
/// it are removed first.
pub fn replace_file(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    use std::sync::atomic::{AtomicU64, Ordering};
    static SEQ: AtomicU64 = AtomicU64::new(0);
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| BrickError::io(d, e))?;
    }
    remove_stale_siblings(path);
    let t = neuvolex_formats::nifti::tmp_name(path);
    let tmp = t.with_file_name(format!(
        "{}-{}",
        t.file_name().unwrap_or_default().to_string_lossy(),
        SEQ.fetch_add(1, Ordering::SeqCst)
    ));
    let r = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if r.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    r.map_err(|e| BrickError::io(path, e))
}
