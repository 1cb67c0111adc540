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
    remove_stale_siblings(path);
    write_renamed(path, bytes, true)
}

/// Writes `bytes` to `path` through a hidden sibling temporary renamed over it, like
/// [`replace_file`], but neither synced nor preceded by the clean-up of the folder: for
/// many small files of a cache that is made again when lost (content-named label bricks,
/// say), whose owner removes stale temporaries once at start-up. A killed process leaves
/// the previous file or the new one; after a power loss the file may be missing or empty,
/// which its reader must detect.
pub fn put_cached_file(path: &Path, bytes: &[u8]) -> Result<()> {
    write_renamed(path, bytes, false)
}

/// `bytes` to a numbered temporary beside `path`, synced when `sync`, renamed over `path`.
fn write_renamed(path: &Path, bytes: &[u8], sync: bool) -> Result<()> {
    use std::io::Write;
    use std::sync::atomic::{AtomicU64, Ordering};
    static SEQ: AtomicU64 = AtomicU64::new(0);
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| BrickError::io(d, e))?;
    }
    let t = neuvolex_formats::nifti::tmp_name(path);
    let tmp = t.with_file_name(format!(
        "{}-{}",
        t.file_name().unwrap_or_default().to_string_lossy(),
        SEQ.fetch_add(1, Ordering::SeqCst)
    ));
    let r = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        if sync {
            f.sync_all()?;
        }
        std::fs::rename(&tmp, path)
    })();
    if r.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    r.map_err(|e| BrickError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both writers replace what was there, create missing folders and leave no temporary.
    #[test]
    fn files_are_replaced_whole_and_no_temporary_stays() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a/b/brick.zst");
        put_cached_file(&p, b"first").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"first");
        put_cached_file(&p, b"second, longer").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"second, longer");
        replace_file(&p, b"3").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"3");
        let names: Vec<String> = std::fs::read_dir(p.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, vec!["brick.zst".to_string()]);
        // A path whose folder is a file is refused, naming the path.
        let bad = d.path().join("a/b/brick.zst/x");
        let e = put_cached_file(&bad, b"x").unwrap_err().to_string();
        assert!(e.contains("brick.zst"), "{e}");
    }
}
