//! Resolving user-given volume paths inside the data root, and nowhere else.

use crate::error::{ApiError, ApiResult};
use std::path::{Component, Path, PathBuf};

/// `rel` inside `root`: relative, no `..`, and (after following links) still under the root.
pub fn resolve(root: &Path, rel: &str) -> ApiResult<PathBuf> {
    let p = Path::new(rel);
    if rel.is_empty() || rel.len() > 4096 || rel.contains('\0') {
        return Err(ApiError::BadRequest(format!(
            "volume path '{}' is empty, too long or has a NUL",
            rel.escape_debug()
        )));
    }
    if p.is_absolute()
        || p.components()
            .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(ApiError::Forbidden(format!(
            "volume path '{rel}' must be relative to the data root, without '..'"
        )));
    }
    let root_c = root
        .canonicalize()
        .map_err(|e| ApiError::Internal(format!("{}: {e}", root.display())))?;
    let full = root_c.join(p);
    let c = full
        .canonicalize()
        .map_err(|_| ApiError::NotFound(format!("no volume '{rel}' in the data root")))?;
    if !c.starts_with(&root_c) {
        return Err(ApiError::Forbidden(format!(
            "volume path '{rel}' leaves the data root"
        )));
    }
    Ok(c)
}

/// Volumes under `root` (NIfTI, NRRD, raw with sidecar, Zarr stores), relative paths, sorted;
/// at most `depth` folders deep.
pub fn list(root: &Path, depth: usize) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, depth: usize, out: &mut Vec<String>) {
        let Ok(rd) = std::fs::read_dir(dir) else {
            return;
        };
        for e in rd.flatten() {
            let p = e.path();
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            let rel = || {
                p.strip_prefix(root)
                    .ok()
                    .map(|r| r.to_string_lossy().into_owned())
            };
            if name.ends_with(".zarr") {
                if let Some(r) = rel() {
                    out.push(r);
                }
                continue;
            }
            if p.is_dir() {
                if depth > 0 {
                    walk(root, &p, depth - 1, out);
                }
                continue;
            }
            let volume = [".nii", ".nii.gz", ".nrrd", ".nhdr"]
                .iter()
                .any(|s| name.ends_with(s))
                && !name.contains("label")
                && !name.contains("scribble");
            if volume {
                if let Some(r) = rel() {
                    out.push(r);
                }
            }
        }
    }
    let mut out = Vec::new();
    walk(root, root, depth, &mut out);
    out.sort();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_paths_inside_the_root_resolve() {
        let d = std::env::temp_dir().join(format!("nvx-paths-{}", std::process::id()));
        std::fs::create_dir_all(d.join("a")).unwrap();
        std::fs::write(d.join("a/v.nii.gz"), b"x").unwrap();
        assert!(resolve(&d, "a/v.nii.gz").is_ok());
        for bad in ["../etc/passwd", "/etc/passwd", "a/../../x", ""] {
            assert!(resolve(&d, bad).is_err(), "{bad}");
        }
        assert!(matches!(
            resolve(&d, "nope.nii"),
            Err(ApiError::NotFound(_))
        ));
        #[cfg(unix)]
        {
            let _ = std::os::unix::fs::symlink("/etc", d.join("out"));
            assert!(matches!(
                resolve(&d, "out/passwd"),
                Err(ApiError::Forbidden(_))
            ));
        }
        assert_eq!(list(&d, 2), vec!["a/v.nii.gz".to_string()]);
        let _ = std::fs::remove_dir_all(&d);
    }
}
