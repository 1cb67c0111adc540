//! The store's writer lock: one writing process per store, readers never block.
//!
//! - **File system**: an OS lock (`flock`, through `File::try_lock`) on `neuvolex/writer.lock`
//!   inside the store. The OS releases it when the holder exits, however it exits. The file
//!   keeps the last holder's description, so a refused writer can name the holder.
//! - **S3**: the object `neuvolex/writer.lock`, created with a conditional PUT
//!   (`If-None-Match: *`): of two writers exactly one creates it. It records the owner and a
//!   lease (`NEUVOLEX_LOCK_LEASE_S`, default 60 s) that a background thread renews every third
//!   of the lease. A lock whose lease has expired (its holder died) is taken over with a
//!   compare-and-swap PUT (`If-Match` on its ETag), so two writers cannot both take it over.
//!   `neuvolex unlock STORE` ([`break_lock`]) deletes a lock by hand.
//!
//! Taking the lock finishes a store-level commit that a killed writer left after its commit
//! point (`commit::recover`, which `WriterLock::acquire` runs).
//!
//! Within one process the lock is shared: acquiring a store's lock while this process already
//! holds it returns another handle to the same lock, released when the last handle drops. The
//! recorded purpose lists what every live acquisition is doing, and is rewritten as they come
//! and go, so a refused writer names what the holder is doing now (not only what it did first).
//!
//! Writers take it for: ingest (over an existing store), adding a label image, and a vector
//! array from creation to [`crate::VectorArray::finish`]. Cluster workers that only write bricks
//! into a pending vector array of a stage whose coordinator holds the lock do not take it.

use crate::backend::Backend;
use crate::error::{BrickError, Result};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex, OnceLock, Weak};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Key of the lock inside a store.
pub const LOCK_KEY: &str = "neuvolex/writer.lock";

/// Who holds a lock, as recorded in the lock file or object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LockHolder {
    /// Host name.
    pub host: String,
    /// Process id.
    pub pid: u32,
    /// What the holder is doing ("ingest", "vectors inr_hidden", ...).
    pub purpose: String,
    /// Unique token of this acquisition.
    pub token: String,
    /// When it was taken (seconds since the Unix epoch).
    pub acquired_unix: u64,
    /// When the lease ends unless renewed (S3 only; 0 on a file system).
    #[serde(default)]
    pub expires_unix: u64,
}

impl std::fmt::Display for LockHolder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "pid {} on {} ({}), since {}",
            self.pid,
            self.host,
            self.purpose,
            fmt_time(self.acquired_unix)
        )
    }
}

fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

fn fmt_time(unix: u64) -> String {
    // UTC, without a date library: days since the epoch to a civil date (Howard Hinnant).
    let (days, secs) = ((unix / 86400) as i64, unix % 86400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC",
        secs / 3600,
        (secs / 60) % 60,
        secs % 60
    )
}

fn new_token() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0),
    );
    h.write_u32(std::process::id());
    format!("{:016x}", h.finish())
}

fn lease() -> Duration {
    let s = std::env::var("NEUVOLEX_LOCK_LEASE_S")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v >= 1.0)
        .unwrap_or(60.0);
    Duration::from_secs_f64(s)
}

/// A held writer lock; released when the last clone is dropped.
#[derive(Clone)]
pub struct WriterLock {
    share: Arc<Share>,
}

impl std::fmt::Debug for WriterLock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "WriterLock({})", self.share.held.backend.location())
    }
}

/// One acquisition of a lock this process holds: its purpose is listed while it lives.
struct Share {
    held: Arc<Held>,
    key: u64,
}

impl Drop for Share {
    fn drop(&mut self) {
        self.held.purposes.remove(self.key);
        // The last acquisition releases the lock itself: nothing to record.
        if Arc::strong_count(&self.held) > 1 {
            self.held.record();
        }
    }
}

/// The purposes of a held lock's live acquisitions, in the order they were taken.
#[derive(Default)]
struct Purposes {
    list: Mutex<(u64, Vec<(u64, String)>)>,
}

impl Purposes {
    fn add(&self, purpose: &str) -> u64 {
        let mut l = self.list.lock().unwrap_or_else(|p| p.into_inner());
        l.0 += 1;
        let key = l.0;
        l.1.push((key, purpose.to_string()));
        key
    }

    fn remove(&self, key: u64) {
        let mut l = self.list.lock().unwrap_or_else(|p| p.into_inner());
        l.1.retain(|(k, _)| *k != key);
    }

    /// The live purposes, comma-separated; `fallback` when none is left (the last handle is
    /// dropping).
    fn joined(&self, fallback: &str) -> String {
        let l = self.list.lock().unwrap_or_else(|p| p.into_inner());
        if l.1.is_empty() {
            return fallback.to_string();
        }
        l.1.iter()
            .map(|(_, p)| p.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

struct Held {
    backend: Arc<Backend>,
    holder: LockHolder,
    kind: HeldKind,
    lost: Arc<AtomicBool>,
    id: String,
    purposes: Arc<Purposes>,
}

impl Held {
    /// The holder with the live acquisitions' purposes.
    fn current(&self) -> LockHolder {
        LockHolder {
            purpose: self.purposes.joined(&self.holder.purpose),
            ..self.holder.clone()
        }
    }

    /// Records the live purposes where other processes read the holder: the lock file, or
    /// (through the renewing thread) the lock object.
    fn record(&self) {
        match &self.kind {
            HeldKind::Fs(f) => {
                // One rewrite at a time, so the last one written holds the newest purposes.
                let f = f.lock().unwrap_or_else(|p| p.into_inner());
                if let Err(e) = write_holder(&f, &self.current()) {
                    tracing::warn!(
                        "{}: recording the writer lock's purposes: {e}",
                        self.backend.path().display()
                    );
                }
            }
            HeldKind::Object { stop } => {
                if let Some(tx) = stop.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
                    let _ = tx.send(Renew::Now);
                }
            }
        }
    }
}

/// What the renewing thread of an object lock is told.
enum Renew {
    /// Rewrite the lock now (its purposes changed).
    Now,
    /// Stop renewing: the lock is being released.
    Stop,
}

enum HeldKind {
    /// The locked file; its mutex serialises the rewrites of the holder.
    Fs(Mutex<std::fs::File>),
    Object {
        stop: Mutex<Option<mpsc::Sender<Renew>>>,
    },
}

/// Writes `holder` into the lock file `f` as one positioned write, then cuts the file to it.
fn write_holder(f: &std::fs::File, holder: &LockHolder) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt;
    let text = serde_json::to_vec(holder).unwrap_or_default();
    f.write_all_at(&text, 0)?;
    f.set_len(text.len() as u64)
}

/// Reads a lock file or object with `read`, again (up to three tries, 5 ms apart) while the
/// read fails or its bytes (from `bytes`) do not parse as a holder: a reader can catch the
/// holder rewriting it (`Held::record`). The last read is returned as it is.
fn read_settled<T>(
    read: &dyn Fn() -> Result<Option<T>>,
    bytes: fn(&T) -> &[u8],
) -> Result<Option<T>> {
    let mut tries = 0;
    loop {
        let r = read();
        tries += 1;
        let settled = match &r {
            Ok(None) => true,
            Ok(Some(t)) => serde_json::from_slice::<LockHolder>(bytes(t)).is_ok(),
            Err(_) => false,
        };
        if settled || tries == 3 {
            return r;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The holder recorded in a lock file, read as [`read_settled`] does (`None` if unreadable).
fn read_file_holder(path: &std::path::Path) -> Option<LockHolder> {
    read_settled(&|| Ok(std::fs::read(path).ok()), |b: &Vec<u8>| b)
        .ok()
        .flatten()
        .and_then(|b| serde_json::from_slice(&b).ok())
}

/// The lock object and its version, read as [`read_settled`] does.
fn read_object(backend: &Backend) -> Result<Option<(Vec<u8>, crate::backend::Version)>> {
    read_settled(&|| backend.get_versioned(LOCK_KEY), |(b, _)| b)
}

fn registry() -> &'static Mutex<HashMap<String, Weak<Held>>> {
    static R: OnceLock<Mutex<HashMap<String, Weak<Held>>>> = OnceLock::new();
    R.get_or_init(Default::default)
}

impl WriterLock {
    /// Takes the writer lock of the store at `backend` for `purpose`, or fails at once with
    /// [`BrickError::Locked`] naming the holder; `on_acquired` runs once the lock is held and
    /// before it is shared in this process (if it fails, the lock is released with its error).
    /// Writers call `WriterLock::acquire` (module `commit`), which finishes an outstanding
    /// commit there.
    pub(crate) fn acquire_then(
        backend: &Arc<Backend>,
        purpose: &str,
        on_acquired: &dyn Fn(&Backend) -> Result<()>,
    ) -> Result<WriterLock> {
        let id = match backend.local_root() {
            Some(r) => std::fs::canonicalize(r)
                .unwrap_or_else(|_| r.to_path_buf())
                .display()
                .to_string(),
            None => backend.location().to_string(),
        };
        let mut reg = registry().lock().unwrap_or_else(|p| p.into_inner());
        if let Some(held) = reg.get(&id).and_then(Weak::upgrade) {
            drop(reg);
            let key = held.purposes.add(purpose);
            held.record();
            return Ok(WriterLock {
                share: Arc::new(Share { held, key }),
            });
        }
        let holder = LockHolder {
            host: crate::fsstore::host_name(),
            pid: std::process::id(),
            purpose: purpose.to_string(),
            token: new_token(),
            acquired_unix: now_unix(),
            expires_unix: 0,
        };
        let held = Arc::new(match backend.local_root() {
            Some(_) => {
                let h = acquire_fs(backend, holder, id.clone())?;
                // Temporaries of killed writers (their process is gone) are debris now.
                backend.remove_stale_temporaries();
                h
            }
            None => acquire_object(backend, holder, id.clone())?,
        });
        on_acquired(backend)?;
        reg.insert(id, Arc::downgrade(&held));
        let key = held.purposes.add(purpose);
        Ok(WriterLock {
            share: Arc::new(Share { held, key }),
        })
    }

    /// Who holds it (this process), with the purposes of its live acquisitions.
    pub fn holder(&self) -> LockHolder {
        self.share.held.current()
    }

    /// Errors if the lock was lost (an S3 lease that someone broke or took over): a writer
    /// checks this before it publishes anything.
    pub fn check(&self) -> Result<()> {
        if self.share.held.lost.load(Ordering::SeqCst) {
            return Err(BrickError::Locked {
                path: self.share.held.backend.path(),
                holder: "another writer (this process's lease was broken or expired)".into(),
                hint: "; nothing was published, run the stage again".into(),
            });
        }
        Ok(())
    }
}

fn acquire_fs(backend: &Arc<Backend>, holder: LockHolder, id: String) -> Result<Held> {
    let root = backend.local_root().unwrap_or(std::path::Path::new("."));
    let path = root.join(LOCK_KEY);
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d).map_err(|e| BrickError::io(d, e))?;
    }
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| BrickError::io(&path, e))?;
    match f.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            let who = read_file_holder(&path)
                .map(|h| h.to_string())
                .unwrap_or_else(|| "another process".into());
            return Err(BrickError::Locked {
                path: backend.path(),
                holder: who,
                hint: "; wait for it to finish (the lock is released when that process exits)"
                    .into(),
            });
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(BrickError::io(&path, e)),
    }
    write_holder(&f, &holder).map_err(|e| BrickError::io(&path, e))?;
    Ok(Held {
        backend: backend.clone(),
        holder,
        kind: HeldKind::Fs(Mutex::new(f)),
        lost: Arc::new(AtomicBool::new(false)),
        id,
        purposes: Default::default(),
    })
}

fn acquire_object(backend: &Arc<Backend>, mut holder: LockHolder, id: String) -> Result<Held> {
    let lease = lease();
    holder.expires_unix = now_unix() + lease.as_secs().max(1);
    let body = |h: &LockHolder| serde_json::to_vec_pretty(h).unwrap_or_default();
    let mut taken = backend.create_new(LOCK_KEY, body(&holder))?;
    if !taken {
        let Some((bytes, version)) = read_object(backend)? else {
            // Released between our create and read: try once more.
            return if backend.create_new(LOCK_KEY, body(&holder))? {
                start_object(backend, holder, lease, id)
            } else {
                Err(locked_object(backend, None))
            };
        };
        let current = serde_json::from_slice::<LockHolder>(&bytes).ok();
        let expired = current.as_ref().is_none_or(|c| c.expires_unix < now_unix());
        if expired {
            taken = backend.replace_if(LOCK_KEY, body(&holder), &version)?;
            if taken {
                tracing::warn!(
                    "{}: took over an expired writer lock ({})",
                    backend.path().display(),
                    current
                        .as_ref()
                        .map(|c| c.to_string())
                        .unwrap_or_else(|| "unreadable".into())
                );
            }
        }
        if !taken {
            return Err(locked_object(backend, current));
        }
    }
    start_object(backend, holder, lease, id)
}

fn locked_object(backend: &Backend, current: Option<LockHolder>) -> BrickError {
    let hint = match &current {
        Some(c) => format!(
            "; its lease runs until {} and is taken over after that if the holder stopped; \
             to break it now: neuvolex unlock {}",
            fmt_time(c.expires_unix),
            backend.location()
        ),
        None => format!("; to break it: neuvolex unlock {}", backend.location()),
    };
    BrickError::Locked {
        path: backend.path(),
        holder: current
            .map(|c| c.to_string())
            .unwrap_or_else(|| "another process".into()),
        hint,
    }
}

fn start_object(
    backend: &Arc<Backend>,
    holder: LockHolder,
    lease: Duration,
    id: String,
) -> Result<Held> {
    let (tx, rx) = mpsc::channel::<Renew>();
    let lost = Arc::new(AtomicBool::new(false));
    let purposes = Arc::new(Purposes::default());
    let (b, mut h, l, ps) = (
        backend.clone(),
        holder.clone(),
        lost.clone(),
        purposes.clone(),
    );
    let first = holder.purpose.clone();
    std::thread::Builder::new()
        .name("neuvolex-lock".into())
        .spawn(move || loop {
            match rx.recv_timeout(lease / 3) {
                Err(mpsc::RecvTimeoutError::Timeout) | Ok(Renew::Now) => {}
                Ok(Renew::Stop) | Err(mpsc::RecvTimeoutError::Disconnected) => return,
            }
            h.purpose = ps.joined(&first);
            let ours = match b.get_versioned(LOCK_KEY) {
                Ok(Some((bytes, v))) => serde_json::from_slice::<LockHolder>(&bytes)
                    .ok()
                    .filter(|c| c.token == h.token)
                    .map(|_| v),
                Ok(None) => None,
                Err(e) => {
                    tracing::warn!("{}: renewing the writer lock: {e}", b.path().display());
                    continue;
                }
            };
            let Some(v) = ours else {
                tracing::error!(
                    "{}: the writer lock was broken by another process",
                    b.path().display()
                );
                l.store(true, Ordering::SeqCst);
                return;
            };
            h.expires_unix = now_unix() + lease.as_secs().max(1);
            let bytes = serde_json::to_vec_pretty(&h).unwrap_or_default();
            if let Ok(false) = b.replace_if(LOCK_KEY, bytes, &v) {
                l.store(true, Ordering::SeqCst);
                return;
            }
        })
        .map_err(|e| BrickError::io(backend.path(), e))?;
    Ok(Held {
        backend: backend.clone(),
        holder,
        kind: HeldKind::Object {
            stop: Mutex::new(Some(tx)),
        },
        lost,
        id,
        purposes,
    })
}

impl Drop for Held {
    fn drop(&mut self) {
        let mut reg = registry().lock().unwrap_or_else(|p| p.into_inner());
        if reg.get(&self.id).is_some_and(|w| w.strong_count() == 0) {
            reg.remove(&self.id);
        }
        drop(reg);
        if let HeldKind::Object { stop } = &self.kind {
            if let Some(tx) = stop.lock().unwrap_or_else(|p| p.into_inner()).take() {
                let _ = tx.send(Renew::Stop);
            }
            if self.lost.load(Ordering::SeqCst) {
                return;
            }
            // Delete it only if it is still ours.
            if let Ok(Some((bytes, _))) = self.backend.get_versioned(LOCK_KEY) {
                if serde_json::from_slice::<LockHolder>(&bytes)
                    .is_ok_and(|c| c.token == self.holder.token)
                {
                    if let Err(e) = self.backend.delete(LOCK_KEY) {
                        tracing::warn!("releasing the writer lock: {e}");
                    }
                }
            }
        }
        // A file lock is released when the file closes.
    }
}

/// Who holds the writer lock of the store at `backend`, if anyone.
pub fn lock_holder(backend: &Arc<Backend>) -> Result<Option<LockHolder>> {
    match backend.local_root() {
        Some(root) => {
            let path = root.join(LOCK_KEY);
            let f = match std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(&path)
            {
                Ok(f) => f,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
                Err(e) => return Err(BrickError::io(&path, e)),
            };
            match f.try_lock() {
                Ok(()) => Ok(None),
                Err(std::fs::TryLockError::WouldBlock) => {
                    Ok(Some(read_file_holder(&path).unwrap_or(LockHolder {
                        host: "?".into(),
                        pid: 0,
                        purpose: "?".into(),
                        token: String::new(),
                        acquired_unix: 0,
                        expires_unix: 0,
                    })))
                }
                Err(std::fs::TryLockError::Error(e)) => Err(BrickError::io(&path, e)),
            }
        }
        None => Ok(read_object(backend)?.and_then(|(b, _)| serde_json::from_slice(&b).ok())),
    }
}

/// Breaks the writer lock of an object store by deleting it, returning the holder it had.
/// On a file system there is nothing to break: the OS releases the lock when the holder exits,
/// so this reports the live holder as an error.
pub fn break_lock(backend: &Arc<Backend>) -> Result<Option<LockHolder>> {
    let holder = lock_holder(backend)?;
    if backend.local_root().is_some() {
        return match holder {
            None => Ok(None),
            Some(h) => Err(BrickError::Locked {
                path: backend.path(),
                holder: h.to_string(),
                hint: "; a file-system lock is held by a live process and ends when it exits \
                       (stop that process)"
                    .into(),
            }),
        };
    }
    backend.delete(LOCK_KEY)?;
    Ok(holder)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::location::StoreLocation;

    #[test]
    fn formats_utc() {
        assert_eq!(fmt_time(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(fmt_time(1_795_000_000), "2026-11-18 11:06:40 UTC");
    }

    #[test]
    fn shared_in_process_and_released_on_drop() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("s.zarr"))).unwrap();
        let l1 = WriterLock::acquire(&b, "test").unwrap();
        let l2 = WriterLock::acquire(&b, "test again").unwrap();
        assert_eq!(l1.holder().token, l2.holder().token);
        let seen = || lock_holder(&b).unwrap().unwrap().purpose;
        // Another process reads every live acquisition's purpose, in order.
        assert_eq!(seen(), "test, test again");
        assert_eq!(l2.holder().purpose, "test, test again");
        assert!(break_lock(&b).is_err());
        // The first acquisition ends: the holder names what is still going on, and a
        // clone of a handle is the same acquisition.
        let l2b = l2.clone();
        drop(l1);
        assert_eq!(seen(), "test again");
        drop(l2);
        assert_eq!(seen(), "test again");
        let l4 = WriterLock::acquire(&b, "fourth").unwrap();
        assert_eq!(seen(), "test again, fourth");
        drop(l2b);
        assert_eq!(seen(), "fourth");
        drop(l4);
        assert!(lock_holder(&b).unwrap().is_none());
        let l3 = WriterLock::acquire(&b, "third").unwrap();
        assert_ne!(l3.holder().purpose, "test");
    }
}
