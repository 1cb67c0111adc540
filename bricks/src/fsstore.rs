//! zarrs' file-system store with atomic writes (unique synced temporaries renamed over
//! their keys).

use crate::error::{BrickError, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use zarrs::storage::{
    byte_range::ByteRangeIterator, Bytes, ListableStorageTraits, MaybeBytesIterator,
    OffsetBytesIterator, ReadableStorageTraits, StorageError, StoreKey, StoreKeys,
    StoreKeysPrefixes, StorePrefix, WritableStorageTraits,
};

/// This host's name (for lock holders and temporary names).
pub(crate) fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown-host".into())
}

/// Folder of a local store holding the temporaries of atomic writes.
pub const TMP_DIR: &str = ".neuvolex-tmp";

/// This host's name as used in temporary names (letters, digits, '.', '_').
fn tmp_host() -> String {
    host_name()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// zarrs' file-system store with atomic writes: each value is written to a unique temporary
/// file (`.neuvolex-tmp/HOST-PID-N` in the store), synced, and renamed over its key; the
/// temporaries of killed writers are removed when the writer lock is next taken.
///
/// Reads, listing and erasing are zarrs' own. zarrs' handle cache stays off, so replacing a
/// file by rename never leaves a stale open handle.
pub struct AtomicFsStore {
    pub(crate) root: PathBuf,
    inner: zarrs::filesystem::FilesystemStore,
}

impl AtomicFsStore {
    /// The store rooted at directory `root` (created on the first write).
    pub fn new(root: &Path) -> Result<Self> {
        let inner =
            zarrs::filesystem::FilesystemStore::new(root).map_err(|e| BrickError::zarr(root, e))?;
        Ok(AtomicFsStore {
            root: root.to_path_buf(),
            inner,
        })
    }

    fn path(&self, key: &str) -> PathBuf {
        self.root.join(key.trim_start_matches('/'))
    }

    /// Where temporaries go: one folder per store, so those of killed writers are found
    /// without walking the store.
    fn tmp_dir(&self) -> PathBuf {
        self.root.join(TMP_DIR)
    }

    fn tmp_path(&self) -> PathBuf {
        static N: AtomicU64 = AtomicU64::new(0);
        self.tmp_dir().join(format!(
            "{}-{}-{}",
            tmp_host(),
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ))
    }

    /// Deletes the temporaries that writers on this host left when they were killed (their
    /// process is gone). Called when the writer lock is taken. Linux only; elsewhere a no-op.
    pub fn remove_stale_temporaries(&self) {
        let Ok(rd) = std::fs::read_dir(self.tmp_dir()) else {
            return;
        };
        let prefix = format!("{}-", tmp_host());
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let pid = name
                .strip_prefix(&prefix)
                .and_then(|r| r.split('-').next())
                .and_then(|p| p.parse::<u32>().ok());
            if let Some(pid) = pid {
                if cfg!(target_os = "linux")
                    && pid != std::process::id()
                    && !Path::new(&format!("/proc/{pid}")).exists()
                {
                    tracing::debug!(path = %e.path().display(), "removing a killed writer's temporary");
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
    }

    fn write_tmp(&self, dst: &Path, value: &[u8], create_new: bool) -> std::io::Result<PathBuf> {
        use std::io::Write;
        if let Some(dir) = dst.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::create_dir_all(self.tmp_dir())?;
        let tmp = self.tmp_path();
        let res = (|| {
            let mut f = std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&tmp)?;
            f.write_all(value)?;
            f.sync_all()?;
            if create_new {
                // link(2) fails if the destination exists: an atomic create-if-absent.
                std::fs::hard_link(&tmp, dst)?;
                std::fs::remove_file(&tmp)?;
            } else {
                std::fs::rename(&tmp, dst)?;
            }
            Ok(())
        })();
        if res.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        res.map(|_| tmp)
    }

    pub(crate) fn create_new(&self, key: &str, value: &[u8]) -> std::io::Result<bool> {
        match self.write_tmp(&self.path(key), value, true) {
            Ok(_) => Ok(true),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
            Err(e) => Err(e),
        }
    }
}

impl ReadableStorageTraits for AtomicFsStore {
    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> std::result::Result<MaybeBytesIterator<'a>, StorageError> {
        self.inner.get_partial_many(key, byte_ranges)
    }

    fn size_key(&self, key: &StoreKey) -> std::result::Result<Option<u64>, StorageError> {
        self.inner.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.inner.supports_get_partial()
    }
}

impl WritableStorageTraits for AtomicFsStore {
    fn set(&self, key: &StoreKey, value: Bytes) -> std::result::Result<(), StorageError> {
        self.write_tmp(&self.path(key.as_str()), &value, false)?;
        Ok(())
    }

    fn set_partial_many(
        &self,
        key: &StoreKey,
        offset_values: OffsetBytesIterator,
    ) -> std::result::Result<(), StorageError> {
        // Read, patch and replace the whole value, so the update stays atomic.
        zarrs::storage::store_set_partial_many(self, key, offset_values)
    }

    fn erase(&self, key: &StoreKey) -> std::result::Result<(), StorageError> {
        self.inner.erase(key)
    }

    fn erase_prefix(&self, prefix: &StorePrefix) -> std::result::Result<(), StorageError> {
        self.inner.erase_prefix(prefix)
    }

    fn supports_set_partial(&self) -> bool {
        false
    }
}

impl ListableStorageTraits for AtomicFsStore {
    fn list(&self) -> std::result::Result<StoreKeys, StorageError> {
        self.inner.list()
    }

    fn list_prefix(&self, prefix: &StorePrefix) -> std::result::Result<StoreKeys, StorageError> {
        self.inner.list_prefix(prefix)
    }

    fn list_dir(
        &self,
        prefix: &StorePrefix,
    ) -> std::result::Result<StoreKeysPrefixes, StorageError> {
        self.inner.list_dir(prefix)
    }

    fn size_prefix(&self, prefix: &StorePrefix) -> std::result::Result<u64, StorageError> {
        self.inner.size_prefix(prefix)
    }
}
