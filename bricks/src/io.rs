//! The store traffic of this process: every byte and request through any [`crate::Backend`]
//! is counted, so executors report what their tasks read and wrote.

use std::sync::atomic::{AtomicU64, Ordering};
use zarrs::storage::{
    byte_range::ByteRangeIterator, Bytes, ListableStorageTraits, MaybeBytesIterator,
    OffsetBytesIterator, ReadableStorageTraits, StorageError, StoreKey, StoreKeys,
    StoreKeysPrefixes, StorePrefix, WritableStorageTraits,
};

/// Bytes and requests that went through the stores of this process so far (every
/// [`Backend`], file system and S3 alike): what a task or a stage moved is the difference of
/// two readings ([`StoreIo::since`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct StoreIo {
    /// Bytes read (whole and partial gets).
    pub bytes_read: u64,
    /// Bytes written.
    pub bytes_written: u64,
    /// Read requests.
    pub reads: u64,
    /// Write requests.
    pub writes: u64,
}

impl StoreIo {
    /// What moved between `earlier` and this reading.
    pub fn since(&self, earlier: &StoreIo) -> StoreIo {
        StoreIo {
            bytes_read: self.bytes_read.saturating_sub(earlier.bytes_read),
            bytes_written: self.bytes_written.saturating_sub(earlier.bytes_written),
            reads: self.reads.saturating_sub(earlier.reads),
            writes: self.writes.saturating_sub(earlier.writes),
        }
    }
}

/// (bytes, requests) read and written through every store of the process.
pub(crate) static IO_READ: [AtomicU64; 2] = [AtomicU64::new(0), AtomicU64::new(0)];
pub(crate) static IO_WRITE: [AtomicU64; 2] = [AtomicU64::new(0), AtomicU64::new(0)];

pub(crate) fn count(c: &[AtomicU64; 2], bytes: usize) {
    c[0].fetch_add(bytes as u64, Ordering::Relaxed);
    c[1].fetch_add(1, Ordering::Relaxed);
}

/// The store traffic of this process so far.
pub fn store_io() -> StoreIo {
    StoreIo {
        bytes_read: IO_READ[0].load(Ordering::Relaxed),
        bytes_written: IO_WRITE[0].load(Ordering::Relaxed),
        reads: IO_READ[1].load(Ordering::Relaxed),
        writes: IO_WRITE[1].load(Ordering::Relaxed),
    }
}

/// A zarrs storage that counts the bytes passing through it into [`store_io`].
pub(crate) struct Counted<T>(pub(crate) T);

impl<T: ReadableStorageTraits> ReadableStorageTraits for Counted<T> {
    fn get(&self, key: &StoreKey) -> std::result::Result<Option<Bytes>, StorageError> {
        let v = self.0.get(key)?;
        if let Some(b) = &v {
            count(&IO_READ, b.len());
        }
        Ok(v)
    }

    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> std::result::Result<MaybeBytesIterator<'a>, StorageError> {
        let Some(parts) = self.0.get_partial_many(key, byte_ranges)? else {
            return Ok(None);
        };
        let parts: Vec<_> = parts.collect();
        count(
            &IO_READ,
            parts.iter().map(|b| b.as_ref().map_or(0, Bytes::len)).sum(),
        );
        Ok(Some(Box::new(parts.into_iter())))
    }

    fn size_key(&self, key: &StoreKey) -> std::result::Result<Option<u64>, StorageError> {
        self.0.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.0.supports_get_partial()
    }
}

impl<T: WritableStorageTraits> WritableStorageTraits for Counted<T> {
    fn set(&self, key: &StoreKey, value: Bytes) -> std::result::Result<(), StorageError> {
        count(&IO_WRITE, value.len());
        self.0.set(key, value)
    }

    fn set_partial_many(
        &self,
        key: &StoreKey,
        offset_values: OffsetBytesIterator,
    ) -> std::result::Result<(), StorageError> {
        let parts: Vec<_> = offset_values.collect();
        count(&IO_WRITE, parts.iter().map(|(_, b)| b.len()).sum());
        self.0.set_partial_many(key, Box::new(parts.into_iter()))
    }

    fn erase(&self, key: &StoreKey) -> std::result::Result<(), StorageError> {
        self.0.erase(key)
    }

    fn erase_many(&self, keys: &[StoreKey]) -> std::result::Result<(), StorageError> {
        self.0.erase_many(keys)
    }

    fn erase_prefix(&self, prefix: &StorePrefix) -> std::result::Result<(), StorageError> {
        self.0.erase_prefix(prefix)
    }

    fn supports_set_partial(&self) -> bool {
        self.0.supports_set_partial()
    }
}

impl<T: ListableStorageTraits> ListableStorageTraits for Counted<T> {
    fn list(&self) -> std::result::Result<StoreKeys, StorageError> {
        self.0.list()
    }

    fn list_prefix(&self, prefix: &StorePrefix) -> std::result::Result<StoreKeys, StorageError> {
        self.0.list_prefix(prefix)
    }

    fn list_dir(
        &self,
        prefix: &StorePrefix,
    ) -> std::result::Result<StoreKeysPrefixes, StorageError> {
        self.0.list_dir(prefix)
    }

    fn size_prefix(&self, prefix: &StorePrefix) -> std::result::Result<u64, StorageError> {
        self.0.size_prefix(prefix)
    }

    fn size(&self) -> std::result::Result<u64, StorageError> {
        self.0.size()
    }
}
