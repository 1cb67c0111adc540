//! The storage under a store: one type for a file-system directory and an S3 object prefix.
//!
//! Every byte a store reads or writes goes through a [`Backend`]: zarrs arrays through
//! [`Backend::zarr`] (a zarrs storage), small objects (metadata, markers, locks, the INR
//! checkpoint) through [`Backend::get`] / [`Backend::put`].
//!
//! - **File system**: zarrs' `FilesystemStore` for reads, wrapped so that every write goes to a
//!   unique temporary file that is synced and renamed over the key ([`AtomicFsStore`]): a
//!   reader never sees a torn chunk or metadata document, and a crash leaves either the old or
//!   the new value.
//! - **S3**: `zarrs_object_store` over `object_store`'s S3 client, with a private Tokio runtime
//!   driving the requests. A PUT is atomic on S3. Timeouts and retries are bounded
//!   ([`crate::S3Options`]), so an unreachable endpoint or wrong credentials fail with an error
//!   naming the URL, never a hang.

use crate::error::{BrickError, Result};
use crate::location::{S3Options, StoreLocation};
use object_store::path::Path as ObjPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use zarrs::storage::{
    Bytes, ListableStorageTraits, ReadableStorageTraits, ReadableWritableListableStorage, StoreKey,
    StorePrefix, WritableStorageTraits,
};
use zarrs_storage::storage_adapter::async_to_sync::{
    AsyncToSyncBlockOn, AsyncToSyncStorageAdapter,
};

pub use crate::fsstore::{AtomicFsStore, TMP_DIR};
use crate::io::{count, Counted, IO_READ, IO_WRITE};
pub use crate::io::{store_io, StoreIo};

/// The storage of one store (or of the folder holding a file).
pub struct Backend {
    location: StoreLocation,
    kind: Kind,
    zarr: ReadableWritableListableStorage,
}

enum Kind {
    Fs(Arc<AtomicFsStore>),
    Object(Arc<dyn ObjectStore>),
}

impl std::fmt::Debug for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Backend({})", self.location)
    }
}

/// A version tag of an object (its ETag on S3), for compare-and-swap writes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Version(pub Option<String>);

impl Backend {
    /// Deletes temporaries left by killed writers (local stores; see [`AtomicFsStore`]).
    pub fn remove_stale_temporaries(&self) {
        if let Kind::Fs(fs) = &self.kind {
            fs.remove_stale_temporaries();
        }
    }

    /// The storage rooted at `location` (nothing is read yet; a missing store is reported by
    /// the first read).
    pub fn open(location: &StoreLocation) -> Result<Arc<Backend>> {
        location.validate()?;
        match location {
            StoreLocation::Local(root) => {
                let fs = Arc::new(AtomicFsStore::new(root)?);
                Ok(Arc::new(Backend {
                    location: location.clone(),
                    zarr: Arc::new(Counted(fs.clone())),
                    kind: Kind::Fs(fs),
                }))
            }
            StoreLocation::S3(u) => {
                let client = s3_client(&u.bucket, &u.options, location)?;
                let store: Arc<dyn ObjectStore> = if u.prefix.is_empty() {
                    client
                } else {
                    Arc::new(object_store::prefix::PrefixStore::new(
                        client,
                        u.prefix.as_str(),
                    ))
                };
                let zarr = Arc::new(Counted(AsyncToSyncStorageAdapter::new(
                    Arc::new(zarrs_object_store::AsyncObjectStore::new(store.clone())),
                    BlockOn,
                )));
                Ok(Arc::new(Backend {
                    location: location.clone(),
                    zarr,
                    kind: Kind::Object(store),
                }))
            }
        }
    }

    /// The storage of the folder holding the file at `location`, and the file's key in it.
    pub fn for_file(location: &StoreLocation) -> Result<(Arc<Backend>, String)> {
        let (dir, name) = location.split_last().ok_or_else(|| {
            BrickError::InvalidArgument(format!("{location}: not a file location"))
        })?;
        Ok((Backend::open(&dir)?, name))
    }

    /// The zarrs storage, for arrays and groups.
    pub fn zarr(&self) -> ReadableWritableListableStorage {
        self.zarr.clone()
    }

    /// The root location.
    pub fn location(&self) -> &StoreLocation {
        &self.location
    }

    /// The root as a path (the URL for S3), for messages.
    pub fn path(&self) -> PathBuf {
        self.location.as_path()
    }

    /// The path (or URL) of `key`, for messages.
    pub fn key_path(&self, key: &str) -> PathBuf {
        self.location.join(key).as_path()
    }

    fn err(&self, key: &str, e: impl std::fmt::Display) -> BrickError {
        storage_error(&self.location, key, e)
    }

    fn zkey(&self, key: &str) -> Result<StoreKey> {
        StoreKey::new(key.trim_start_matches('/')).map_err(|e| {
            BrickError::InvalidArgument(format!("{}: bad key: {e}", self.key_path(key).display()))
        })
    }

    /// Reads the object at `key`; `None` if there is none.
    pub fn get(&self, key: &str) -> Result<Option<Vec<u8>>> {
        let k = self.zkey(key)?;
        self.zarr
            .get(&k)
            .map(|b| b.map(|b| b.to_vec()))
            .map_err(|e| self.err(key, e))
    }

    /// Reads the object at `key` with its version; `None` if there is none.
    pub fn get_versioned(&self, key: &str) -> Result<Option<(Vec<u8>, Version)>> {
        match &self.kind {
            Kind::Fs(_) => Ok(self.get(key)?.map(|b| (b, Version(None)))),
            Kind::Object(s) => {
                let p = ObjPath::from(key.trim_start_matches('/'));
                match block_on(async {
                    let r = s.get(&p).await?;
                    let tag = r.meta.e_tag.clone();
                    let bytes = r.bytes().await?;
                    Ok::<_, object_store::Error>((bytes.to_vec(), Version(tag)))
                }) {
                    Ok(v) => {
                        count(&IO_READ, v.0.len());
                        Ok(Some(v))
                    }
                    Err(object_store::Error::NotFound { .. }) => Ok(None),
                    Err(e) => Err(self.err(key, e)),
                }
            }
        }
    }

    /// Size of the object at `key`, `None` if there is none.
    pub fn size(&self, key: &str) -> Result<Option<u64>> {
        let k = self.zkey(key)?;
        self.zarr.size_key(&k).map_err(|e| self.err(key, e))
    }

    /// True if an object exists at `key`.
    pub fn exists(&self, key: &str) -> Result<bool> {
        Ok(self.size(key)?.is_some())
    }

    /// Writes `bytes` to `key` atomically (rename on a file system, one PUT on S3).
    pub fn put(&self, key: &str, bytes: Vec<u8>) -> Result<()> {
        let k = self.zkey(key)?;
        self.zarr
            .set(&k, Bytes::from(bytes))
            .map_err(|e| self.err(key, e))
    }

    /// Creates `key` with `bytes` only if nothing is there; returns false if something was.
    /// Atomic: of two concurrent creators exactly one succeeds (`O_EXCL` on a file system,
    /// `If-None-Match: *` on S3).
    pub fn create_new(&self, key: &str, bytes: Vec<u8>) -> Result<bool> {
        match &self.kind {
            Kind::Fs(fs) => fs.create_new(key, &bytes).map_err(|e| self.err(key, e)),
            Kind::Object(s) => self.conditional_put(s, key, bytes, PutMode::Create),
        }
    }

    /// A conditional PUT: true if written, false if the condition failed.
    fn conditional_put(
        &self,
        s: &Arc<dyn ObjectStore>,
        key: &str,
        bytes: Vec<u8>,
        mode: PutMode,
    ) -> Result<bool> {
        let p = ObjPath::from(key.trim_start_matches('/'));
        let update = matches!(mode, PutMode::Update(_));
        let opts = PutOptions {
            mode,
            ..Default::default()
        };
        count(&IO_WRITE, bytes.len());
        match block_on(s.put_opts(&p, PutPayload::from(bytes), opts)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::AlreadyExists { .. })
            | Err(object_store::Error::Precondition { .. }) => Ok(false),
            // The object to replace is gone: the condition failed too.
            Err(object_store::Error::NotFound { .. }) if update => Ok(false),
            Err(e) => Err(self.err(key, e)),
        }
    }

    /// Replaces `key` only if it is still at `version` (S3 `If-Match`); returns false if it
    /// changed. On a file system (where callers hold an OS lock instead) it always writes.
    pub fn replace_if(&self, key: &str, bytes: Vec<u8>, version: &Version) -> Result<bool> {
        match &self.kind {
            Kind::Fs(_) => self.put(key, bytes).map(|_| true),
            Kind::Object(s) => self.conditional_put(
                s,
                key,
                bytes,
                PutMode::Update(object_store::UpdateVersion {
                    e_tag: version.0.clone(),
                    version: None,
                }),
            ),
        }
    }

    /// Deletes `key` (no error if absent).
    pub fn delete(&self, key: &str) -> Result<()> {
        let k = self.zkey(key)?;
        self.zarr.erase(&k).map_err(|e| self.err(key, e))
    }

    /// Deletes every object under `prefix` (a folder; no error if absent).
    pub fn delete_prefix(&self, prefix: &str) -> Result<()> {
        let p = prefix_of(prefix).map_err(|e| self.err(prefix, e))?;
        self.zarr.erase_prefix(&p).map_err(|e| self.err(prefix, e))
    }

    /// The keys of every object under `prefix`, relative to the root.
    pub fn list(&self, prefix: &str) -> Result<Vec<String>> {
        let p = prefix_of(prefix).map_err(|e| self.err(prefix, e))?;
        Ok(self
            .zarr
            .list_prefix(&p)
            .map_err(|e| self.err(prefix, e))?
            .into_iter()
            .map(|k| k.as_str().to_string())
            .collect())
    }

    /// The names of the immediate children (objects and folders) of folder `prefix`, without
    /// hidden names (temporary files start with `.`).
    pub fn list_dir(&self, prefix: &str) -> Result<Vec<String>> {
        let (mut keys, folders) = self.list_children(prefix)?;
        keys.extend(folders);
        keys.sort();
        keys.dedup();
        Ok(keys)
    }

    /// The immediate children of folder `prefix`: (object names, folder names), sorted,
    /// without hidden names.
    pub fn list_children(&self, prefix: &str) -> Result<(Vec<String>, Vec<String>)> {
        let p = prefix_of(prefix).map_err(|e| self.err(prefix, e))?;
        let kp = self.zarr.list_dir(&p).map_err(|e| self.err(prefix, e))?;
        let strip = |s: &str| -> String {
            s.strip_prefix(p.as_str())
                .unwrap_or(s)
                .trim_end_matches('/')
                .to_string()
        };
        let keep = |n: &String| !n.is_empty() && !n.starts_with('.');
        let mut keys: Vec<String> = kp
            .keys()
            .iter()
            .map(|k| strip(k.as_str()))
            .filter(keep)
            .collect();
        let mut dirs: Vec<String> = kp
            .prefixes()
            .iter()
            .map(|q| strip(q.as_str()))
            .filter(keep)
            .collect();
        keys.sort();
        dirs.sort();
        Ok((keys, dirs))
    }

    /// Deletes the object or folder `key` (a path of `/`-separated names).
    pub fn delete_node(&self, key: &str) -> Result<()> {
        match key.trim_matches('/').rsplit_once('/') {
            Some((parent, name)) => self.delete_child(parent, name),
            None => self.delete_child("", key.trim_matches('/')),
        }
    }

    /// Deletes child `name` of folder `parent`: the object of that name and everything under
    /// the folder of that name.
    pub fn delete_child(&self, parent: &str, name: &str) -> Result<()> {
        let (keys, dirs) = self.list_children(parent)?;
        let parent = parent.trim_matches('/');
        let key = if parent.is_empty() {
            name.to_string()
        } else {
            format!("{parent}/{name}")
        };
        if dirs.iter().any(|d| d == name) {
            self.delete_prefix(&key)?;
        }
        if keys.iter().any(|k| k == name) {
            self.delete(&key)?;
        }
        Ok(())
    }

    /// True for a store on a file system (where an OS file lock can be taken).
    pub fn local_root(&self) -> Option<&Path> {
        match &self.kind {
            Kind::Fs(fs) => Some(&fs.root),
            Kind::Object(_) => None,
        }
    }
}

fn prefix_of(prefix: &str) -> std::result::Result<StorePrefix, String> {
    let p = prefix.trim_matches('/');
    if p.is_empty() {
        Ok(StorePrefix::root())
    } else {
        StorePrefix::new(format!("{p}/")).map_err(|e| e.to_string())
    }
}

/// A storage error for `key` under `location`, with a hint for the common S3 failures.
pub(crate) fn storage_error(
    location: &StoreLocation,
    key: &str,
    e: impl std::fmt::Display,
) -> BrickError {
    let detail = e.to_string();
    let hint = storage_hint(&detail);
    BrickError::Storage {
        path: location.join(key).as_path(),
        detail: format!("{detail}{hint}"),
    }
}

/// A hint for the usual causes of an object-store error text ("" if none applies).
pub(crate) fn storage_hint(detail: &str) -> &'static str {
    let d = detail.to_ascii_lowercase();
    if has_number(&d, "403")
        || d.contains("forbidden")
        || d.contains("signaturedoesnotmatch")
        || d.contains("invalidaccesskeyid")
        || d.contains("access denied")
        || d.contains("privileges")
        || d.contains("unauthenticated")
        || d.contains("permission")
    {
        " (access denied: check AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)"
    } else if d.contains("connect")
        || d.contains("timed out")
        || d.contains("timeout")
        || d.contains("dns")
        || d.contains("refused")
    {
        " (endpoint unreachable: check AWS_ENDPOINT_URL and that the server runs)"
    } else if d.contains("nosuchbucket") {
        " (no such bucket: create it first)"
    } else {
        ""
    }
}

/// Whether `n` occurs in `text` as a number of its own, not inside a longer one: a status code,
/// not the digits of an elapsed time such as "9.240382585s" or a port. A full stop belongs to
/// the number only where a digit lies beyond it ("403." ending a sentence is 403).
fn has_number(text: &str, n: &str) -> bool {
    let b = text.as_bytes();
    let digit = |j: Option<usize>| j.and_then(|j| b.get(j)).is_some_and(u8::is_ascii_digit);
    let dot = |j: Option<usize>| j.and_then(|j| b.get(j)) == Some(&b'.');
    text.match_indices(n).any(|(i, _)| {
        let (before, after) = (i.checked_sub(1), i + n.len());
        let joined_before = digit(before) || (dot(before) && digit(i.checked_sub(2)));
        let joined_after = digit(Some(after)) || (dot(Some(after)) && digit(Some(after + 1)));
        !joined_before && !joined_after
    })
}

/// The Tokio runtime that drives object-store requests for synchronous callers.
fn runtime() -> &'static tokio::runtime::Runtime {
    static RT: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    RT.get_or_init(|| {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("neuvolex-s3")
            .enable_all()
            .build()
            .unwrap_or_else(|e| panic!("cannot start the object-store runtime: {e}"))
    })
}

/// Runs `f` to completion on the calling thread with the object-store runtime's reactor and
/// timers (driven by its own threads), so it works from plain threads, rayon workers and the
/// blocking threads of another Tokio runtime alike.
fn block_on<F: std::future::Future>(f: F) -> F::Output {
    let _guard = runtime().enter();
    futures::executor::block_on(f)
}

struct BlockOn;

impl AsyncToSyncBlockOn for BlockOn {
    fn block_on<F: core::future::Future>(&self, future: F) -> F::Output {
        block_on(future)
    }
}

/// One S3 client per bucket and settings, shared by every store in the process.
fn s3_client(
    bucket: &str,
    o: &S3Options,
    location: &StoreLocation,
) -> Result<Arc<dyn ObjectStore>> {
    type Clients = Mutex<HashMap<(String, S3Options), Arc<dyn ObjectStore>>>;
    static CLIENTS: OnceLock<Clients> = OnceLock::new();
    let clients = CLIENTS.get_or_init(Default::default);
    let key = (bucket.to_string(), o.clone());
    if let Some(c) = clients.lock().unwrap_or_else(|p| p.into_inner()).get(&key) {
        return Ok(c.clone());
    }
    // TLS for https endpoints; one provider for the process (ignored if one is installed).
    let _ = rustls::crypto::ring::default_provider().install_default();
    let loopback_http = o.endpoint.as_deref().is_some_and(|e| {
        e.starts_with("http://127.")
            || e.starts_with("http://localhost")
            || e.starts_with("http://[::1]")
    });
    let client_opts = object_store::ClientOptions::new()
        .with_allow_http(o.allow_http || loopback_http)
        .with_connect_timeout(o.connect_timeout)
        .with_read_timeout(o.read_timeout)
        .with_timeout(o.request_timeout);
    let retry = object_store::RetryConfig {
        backoff: object_store::BackoffConfig {
            init_backoff: std::time::Duration::from_millis(100),
            max_backoff: std::time::Duration::from_secs(2),
            base: 2.0,
        },
        max_retries: o.retries,
        retry_timeout: o.retry_timeout,
    };
    let mut b = object_store::aws::AmazonS3Builder::new();
    let has_keys = o.access_key_id.is_some() && o.secret_access_key.is_some();
    if !has_keys {
        // Web identity (Kubernetes service accounts) or container credentials: the builder
        // reads them from the environment. Never the instance-metadata service, which would
        // be probed on a non-loopback address.
        let federated = [
            "AWS_WEB_IDENTITY_TOKEN_FILE",
            "AWS_CONTAINER_CREDENTIALS_FULL_URI",
            "AWS_CONTAINER_CREDENTIALS_RELATIVE_URI",
        ]
        .iter()
        .any(|k| std::env::var_os(k).is_some());
        let anonymous = std::env::var("AWS_SKIP_SIGNATURE").is_ok_and(|v| v == "true" || v == "1");
        if federated {
            b = object_store::aws::AmazonS3Builder::from_env();
        } else if anonymous {
            b = b.with_skip_signature(true);
        } else {
            return Err(BrickError::Storage {
                path: location.as_path(),
                detail: "no S3 credentials: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY \
                         (or AWS_SKIP_SIGNATURE=true for a public bucket)"
                    .into(),
            });
        }
    }
    b = b
        .with_bucket_name(bucket)
        .with_region(&o.region)
        .with_client_options(client_opts)
        .with_retry(retry)
        .with_virtual_hosted_style_request(false);
    if let (Some(k), Some(s)) = (&o.access_key_id, &o.secret_access_key) {
        b = b.with_access_key_id(k).with_secret_access_key(s);
        if let Some(t) = &o.session_token {
            b = b.with_token(t);
        }
    }
    if let Some(e) = &o.endpoint {
        b = b.with_endpoint(e);
    }
    let client: Arc<dyn ObjectStore> = Arc::new(
        b.build()
            .map_err(|e| storage_error(location, "", format!("S3 client: {e}")))?,
    );
    clients
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .insert(key, client.clone());
    Ok(client)
}

impl StoreLocation {
    /// True if a file, directory or object exists at this location (false on any error).
    pub fn exists(&self) -> bool {
        match self {
            StoreLocation::Local(p) => p.exists(),
            StoreLocation::S3(_) => Backend::for_file(self)
                .and_then(|(b, key)| b.exists(&key))
                .unwrap_or(false),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hints_read_status_codes_not_digits_of_times() {
        let denied = " (access denied: check AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)";
        let unreachable =
            " (endpoint unreachable: check AWS_ENDPOINT_URL and that the server runs)";
        assert_eq!(
            storage_hint("Server returned non-2xx status code: 403 Forbidden"),
            denied
        );
        assert_eq!(storage_hint("status 403"), denied);
        assert_eq!(storage_hint("the server answered 403."), denied);
        // A black-holed request that happened to take 9.2403... s, on a port with 403 inside.
        let slow = "Error performing HEAD http://127.0.0.1:40312/a in 9.240382585s, after 2 \
                    retries - HTTP error: error sending request: operation timed out";
        assert_eq!(storage_hint(slow), unreachable);
        assert_eq!(storage_hint("HEAD in 1.403s: error sending request"), "");
    }

    #[test]
    fn store_traffic_is_counted() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("c.zarr"))).unwrap();
        let before = store_io();
        b.put("a.json", vec![7; 1000]).unwrap();
        assert_eq!(b.get("a.json").unwrap().map(|v| v.len()), Some(1000));
        assert_eq!(b.get("missing").unwrap(), None);
        // Other tests of this binary may count too: at least this test's traffic is seen.
        let d = store_io().since(&before);
        assert!(d.bytes_written >= 1000 && d.writes >= 1, "{d:?}");
        assert!(d.bytes_read >= 1000 && d.reads >= 1, "{d:?}");
    }

    #[test]
    fn fs_put_is_atomic_and_create_new_is_exclusive() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("s.zarr"))).unwrap();
        assert_eq!(b.get("a/b.json").unwrap(), None);
        b.put("a/b.json", b"one".to_vec()).unwrap();
        b.put("a/b.json", b"two".to_vec()).unwrap();
        assert_eq!(b.get("a/b.json").unwrap().as_deref(), Some(&b"two"[..]));
        assert!(b.create_new("a/lock", b"x".to_vec()).unwrap());
        assert!(!b.create_new("a/lock", b"y".to_vec()).unwrap());
        assert_eq!(b.get("a/lock").unwrap().as_deref(), Some(&b"x"[..]));
        // No temporary files are left behind.
        let names = b.list_dir("a").unwrap();
        assert_eq!(names, vec!["b.json".to_string(), "lock".to_string()]);
        b.delete_prefix("a").unwrap();
        assert!(b.list("").unwrap().is_empty());
    }
}
