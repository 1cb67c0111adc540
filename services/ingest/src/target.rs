//! Where an ingest writes until it publishes: a temporary folder renamed into place, or an S3
//! prefix whose root metadata is written last.

use crate::options::{validate_options, IngestOptions};
use neuvolex_bricks::{Backend, BrickError, Result, StoreLocation, WriterLock};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Where an ingest writes, from its start to its publication: on a file system a temporary
/// sibling folder renamed into place by [`IngestTarget::commit`] (an existing store stays
/// complete until then, and is locked against other writers meanwhile); on S3 the store itself,
/// marked incomplete and emptied first, whose root metadata is written last.
///
/// Every writer of the ingest (this process, or cluster workers given
/// [`IngestTarget::location`]) writes through it; [`SlabWriter`] does the writing.
pub struct IngestTarget {
    out: StoreLocation,
    at: StoreLocation,
    backend: Arc<Backend>,
    pub(crate) tmp: Option<PathBuf>,
    pub(crate) lock: Option<WriterLock>,
    overwrite: bool,
}

impl IngestTarget {
    /// Prepares `out` for a new store: refuses an existing complete store without
    /// `opts.overwrite`, takes the writer lock and makes the folder (or S3 prefix) to write in.
    pub fn begin(out: &StoreLocation, opts: &IngestOptions) -> Result<Self> {
        out.validate()?;
        validate_options(&out.as_path(), opts)?;
        match out {
            StoreLocation::Local(dir) => {
                if dir.exists() && !opts.overwrite {
                    return Err(BrickError::Exists { path: dir.clone() });
                }
                // Replacing a store: no other writer may be working in it meanwhile.
                let lock = if dir.exists() {
                    Some(WriterLock::acquire(
                        &Backend::open(&StoreLocation::Local(dir.clone()))?,
                        "ingest",
                    )?)
                } else {
                    None
                };
                neuvolex_bricks::atomic::remove_stale_siblings(dir);
                let tmp = neuvolex_formats::nifti::tmp_name(dir);
                if tmp.exists() {
                    std::fs::remove_dir_all(&tmp).map_err(|e| BrickError::io(&tmp, e))?;
                }
                std::fs::create_dir_all(&tmp).map_err(|e| BrickError::io(&tmp, e))?;
                let at = StoreLocation::Local(tmp.clone());
                Ok(IngestTarget {
                    out: out.clone(),
                    backend: Backend::open(&at)?,
                    at,
                    tmp: Some(tmp),
                    lock,
                    overwrite: opts.overwrite,
                })
            }
            StoreLocation::S3(_) => {
                let backend = Backend::open(out)?;
                if !opts.overwrite {
                    if let Some(bytes) = backend.get("zarr.json")? {
                        // A complete store is kept; leftovers of an interrupted ingest are
                        // replaced.
                        let complete = serde_json::from_slice::<Value>(&bytes)
                            .ok()
                            .and_then(|v| {
                                v.pointer("/attributes/neuvolex/complete")
                                    .and_then(Value::as_bool)
                            })
                            .unwrap_or(false);
                        if complete {
                            return Err(BrickError::Exists {
                                path: out.as_path(),
                            });
                        }
                    }
                }
                let lock = WriterLock::acquire(&backend, "ingest")?;
                backend.put(
                    "zarr.json",
                    serde_json::to_vec_pretty(&json!({"zarr_format": 3, "node_type": "group",
                        "attributes": {"neuvolex": {"complete": false}}}))
                    .unwrap_or_default(),
                )?;
                for name in backend.list_dir("")? {
                    match name.as_str() {
                        "zarr.json" => {}
                        "neuvolex" => {
                            for n in backend.list_dir("neuvolex")? {
                                if format!("neuvolex/{n}") != neuvolex_bricks::lock::LOCK_KEY {
                                    backend.delete_node(&format!("neuvolex/{n}"))?;
                                }
                            }
                        }
                        n => backend.delete_node(n)?,
                    }
                }
                Ok(IngestTarget {
                    out: out.clone(),
                    at: out.clone(),
                    backend,
                    tmp: None,
                    lock: Some(lock),
                    overwrite: opts.overwrite,
                })
            }
        }
    }

    /// Where the ingest's writers write (the temporary folder on a file system).
    pub fn location(&self) -> &StoreLocation {
        &self.at
    }

    /// The backend of [`Self::location`].
    pub fn backend(&self) -> &Arc<Backend> {
        &self.backend
    }

    /// Publishes the written store at its final location (a rename on a file system; on S3
    /// [`SlabWriter::finish`] already wrote the root metadata last) and releases the lock.
    pub fn commit(self) -> Result<()> {
        if let Some(tmp) = &self.tmp {
            let r = commit_dir(tmp, &self.out.as_path(), self.overwrite);
            if r.is_err() {
                let _ = std::fs::remove_dir_all(tmp);
            }
            r?;
        }
        Ok(())
    }

    /// Gives up: removes the temporary folder (the previous store, if any, is untouched).
    pub fn abort(self) {
        if let Some(tmp) = &self.tmp {
            let _ = std::fs::remove_dir_all(tmp);
        }
    }
}

/// Moves `tmp` to `out` (replacing `out` only when `overwrite`), keeping the old store until
/// the new one is in place. On Linux a replacement is one atomic exchange of the two names
/// (`renameat2(RENAME_EXCHANGE)`), so `out` is at every instant the old store or the new one,
/// even if the process is killed; the old store then sits under `tmp` and is deleted.
fn commit_dir(tmp: &Path, out: &Path, overwrite: bool) -> Result<()> {
    if out.exists() {
        if !overwrite {
            return Err(BrickError::Exists {
                path: out.to_path_buf(),
            });
        }
        match exchange(tmp, out) {
            Ok(()) => {
                let _ = std::fs::remove_dir_all(tmp);
                return Ok(());
            }
            Err(e) => tracing::debug!("atomic exchange unavailable ({e}); two renames"),
        }
        let old = out.with_file_name(format!(
            ".{}.old-{}",
            out.file_name().unwrap_or_default().to_string_lossy(),
            std::process::id()
        ));
        std::fs::rename(out, &old).map_err(|e| BrickError::io(out, e))?;
        std::fs::rename(tmp, out).map_err(|e| BrickError::io(out, e))?;
        let _ = std::fs::remove_dir_all(&old);
    } else {
        std::fs::rename(tmp, out).map_err(|e| BrickError::io(out, e))?;
    }
    Ok(())
}

/// Atomically swaps the names `a` and `b` (both must exist).
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let ca = CString::new(a.as_os_str().as_bytes())?;
    let cb = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: both arguments are valid NUL-terminated paths that outlive the call.
    let r = unsafe {
        libc::renameat2(
            libc::AT_FDCWD,
            ca.as_ptr(),
            libc::AT_FDCWD,
            cb.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// Atomically swaps the names `a` and `b`: not available on this platform.
#[cfg(not(target_os = "linux"))]
fn exchange(_a: &Path, _b: &Path) -> std::io::Result<()> {
    Err(std::io::ErrorKind::Unsupported.into())
}
