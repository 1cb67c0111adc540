//! Store-level commits: every output of one step published together, or none of them.
//!
//! A stage output (a label image, a vector array) is written as a new generation `vN` beside
//! the current one; its *pointer node* (`labels/NAME/zarr.json`, `neuvolex/vectors/NAME/
//! zarr.json`, and for a new label image `labels/zarr.json` and the root `zarr.json`) names the
//! current generation. A [`Commit`] collects the new documents of every pointer node a step
//! changes (classify: probabilities, label vectors and the OME label image) and publishes
//! them with one atomic write of the commit record [`COMMIT_KEY`]. That write is the commit
//! point. The record is then applied (each pointer written, itself an atomic write), the
//! replaced generations are deleted, and the record is removed.
//!
//! A writer killed before the commit point leaves unpublished generations (resumed by their
//! done markers, or deleted by the node's next publication) and readers see every previous
//! output. Killed after it, the record stays: readers of the store resolve pointer nodes
//! through it ([`read_committed_node`]), so they see every new output, and the next process
//! to take the writer lock applies it ([`recover`], called by [`crate::WriterLock::acquire`]).
//! Either way a reader sees the old set or the new set, never a mix.

use crate::backend::Backend;
use crate::error::{BrickError, Result};
use crate::lock::WriterLock;
use crate::omezarr::read_node;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::sync::Arc;

/// Key of the commit record inside a store.
pub const COMMIT_KEY: &str = "neuvolex/commit.json";

/// One pointer node's new metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct NodeWrite {
    /// The node (`labels/classified`, `neuvolex/vectors/NAME`, "" for the root).
    node: String,
    /// Its new `zarr.json`.
    doc: Value,
}

/// A node whose generations other than `generation` are deleted once the writes are applied.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Keep {
    node: String,
    generation: String,
}

/// The outputs of one step, published together by [`Commit::publish`].
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct Commit {
    writes: Vec<NodeWrite>,
    keep: Vec<Keep>,
    #[serde(skip)]
    lock: Option<WriterLock>,
}

/// The `zarr.json` key of `node`.
fn node_key(node: &str) -> String {
    let node = node.trim_matches('/');
    if node.is_empty() {
        "zarr.json".into()
    } else {
        format!("{node}/zarr.json")
    }
}

/// A Zarr v3 group document with `attributes`.
pub fn group_doc(attributes: serde_json::Map<String, Value>) -> Value {
    json!({"zarr_format": 3, "node_type": "group", "attributes": attributes})
}

impl Commit {
    /// An empty commit.
    pub fn new() -> Self {
        Self::default()
    }

    /// Sets the new `zarr.json` of pointer node `node` (a later call for the same node wins).
    pub fn write(&mut self, node: &str, doc: Value) {
        let node = node.trim_matches('/').to_string();
        self.writes.retain(|w| w.node != node);
        self.writes.push(NodeWrite { node, doc });
    }

    /// After the writes, deletes every generation of `node` other than `generation` (older
    /// ones, abandoned pending ones and their done markers).
    pub fn keep_only(&mut self, node: &str, generation: &str) {
        let node = node.trim_matches('/').to_string();
        self.keep.retain(|k| k.node != node);
        self.keep.push(Keep {
            node,
            generation: generation.to_string(),
        });
    }

    /// Holds the store's writer lock until the commit is published or dropped. Every part
    /// adds the lock it wrote under (within a process they are one lock).
    pub fn hold(&mut self, lock: WriterLock) {
        self.lock.get_or_insert(lock);
    }

    /// The new document of `node` if this commit writes it.
    pub fn doc(&self, node: &str) -> Option<&Value> {
        let node = node.trim_matches('/');
        self.writes.iter().find(|w| w.node == node).map(|w| &w.doc)
    }

    /// True if nothing was added.
    pub fn is_empty(&self) -> bool {
        self.writes.is_empty() && self.keep.is_empty()
    }

    /// Publishes every part at once: the commit record is written (the commit point), then
    /// applied, then removed. Needs the writer lock ([`Self::hold`]); releases it.
    pub fn publish(mut self, backend: &Backend) -> Result<()> {
        let lock = self.lock.take().ok_or_else(|| {
            BrickError::InvalidArgument(format!(
                "{}: a commit is published under the store's writer lock",
                backend.path().display()
            ))
        })?;
        if self.is_empty() {
            return Ok(());
        }
        lock.check()?;
        let record = serde_json::to_vec(&self)
            .map_err(|e| BrickError::corrupt(backend.key_path(COMMIT_KEY), e.to_string()))?;
        backend.put(COMMIT_KEY, record)?;
        self.apply(backend)?;
        backend.delete(COMMIT_KEY)?;
        drop(lock);
        Ok(())
    }

    /// Writes every pointer node, then deletes the replaced generations. Idempotent, so an
    /// interrupted application is finished by running it again.
    fn apply(&self, backend: &Backend) -> Result<()> {
        for w in &self.writes {
            let bytes = serde_json::to_vec_pretty(&w.doc)
                .map_err(|e| BrickError::corrupt(backend.key_path(&w.node), e.to_string()))?;
            backend.put(&node_key(&w.node), bytes)?;
        }
        for k in &self.keep {
            drop_other_generations(backend, &k.node, &k.generation)?;
        }
        Ok(())
    }
}

/// The commit record a killed writer left after its commit point, if any.
pub fn outstanding(backend: &Backend) -> Result<Option<Commit>> {
    let Some(bytes) = backend.get(COMMIT_KEY)? else {
        return Ok(None);
    };
    serde_json::from_slice(&bytes).map(Some).map_err(|e| {
        BrickError::corrupt(
            backend.key_path(COMMIT_KEY),
            format!("unreadable commit record: {e}"),
        )
    })
}

/// Finishes the commit a killed writer left (roll forward); true if there was one. Call it
/// holding the writer lock: [`crate::WriterLock::acquire`] does.
pub fn recover(backend: &Backend) -> Result<bool> {
    let Some(c) = outstanding(backend)? else {
        return Ok(false);
    };
    tracing::info!(
        store = %backend.path().display(),
        nodes = c.writes.len(),
        "finishing the commit of an interrupted writer"
    );
    c.apply(backend)?;
    backend.delete(COMMIT_KEY)?;
    Ok(true)
}

/// The committed `zarr.json` of `node` as a reader must see it: from an outstanding commit
/// record when it names the node, else the node's own document.
pub fn read_committed_node(backend: &Backend, node: &str) -> Result<Value> {
    match committed_doc(backend, node)? {
        Some(v) => Ok(v),
        None => read_node(backend, node),
    }
}

/// The document an outstanding commit record holds for `node`, if any.
pub fn committed_doc(backend: &Backend, node: &str) -> Result<Option<Value>> {
    Ok(outstanding(backend)?.and_then(|c| c.doc(node).cloned()))
}

/// The generation number of a child name `vN`.
pub(crate) fn generation_number(name: &str) -> Option<u64> {
    name.strip_prefix('v')
        .filter(|d| !d.is_empty() && d.bytes().all(|c| c.is_ascii_digit()))
        .and_then(|d| d.parse().ok())
}

/// The next free generation name (`v1`, `v2`, ...) under node `node`.
pub(crate) fn next_generation(backend: &Backend, node: &str) -> Result<String> {
    let n = backend
        .list_dir(node)?
        .iter()
        .filter_map(|c| generation_number(c.strip_suffix(".done").unwrap_or(c)))
        .max()
        .unwrap_or(0);
    Ok(format!("v{}", n + 1))
}

/// Deletes every child of `node` except its `zarr.json` and generation `keep`: older
/// generations, abandoned pending ones, their markers, and the arrays of the layout before
/// generations.
pub(crate) fn drop_other_generations(backend: &Backend, node: &str, keep: &str) -> Result<()> {
    for child in backend.list_dir(node)? {
        if child == "zarr.json" || (!keep.is_empty() && child == keep) || child.starts_with('.') {
            continue;
        }
        let key = format!("{node}/{child}");
        if !child.ends_with(".done") {
            backend.delete_node(&key)?;
            continue;
        }
        // Done markers of a finished generation: a cluster worker running a late duplicate of a
        // task (redelivered after its first worker went quiet) may still add one while they are
        // deleted. They are no longer read, so a folder that will not go is left, with a warning.
        let mut tries = 0;
        while let Err(e) = backend.delete_node(&key) {
            tries += 1;
            if tries == 5 {
                tracing::warn!("{}: left in place: {e}", backend.key_path(&key).display());
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }
    Ok(())
}

impl WriterLock {
    /// Takes the writer lock of the store at `backend` for `purpose`, or fails at once with
    /// [`BrickError::Locked`] naming the holder. A commit a killed writer left after its
    /// commit point is finished ([`recover`]) before anything else is written; if that fails,
    /// the lock is released with the error.
    pub fn acquire(backend: &Arc<Backend>, purpose: &str) -> Result<WriterLock> {
        WriterLock::acquire_then(backend, purpose, &|b| recover(b).map(|_| ()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::location::StoreLocation;

    fn doc(gen: &str) -> Value {
        let mut a = serde_json::Map::new();
        a.insert("neuvolex".into(), json!({"current": gen}));
        group_doc(a)
    }

    #[test]
    fn an_outstanding_record_is_what_readers_see_and_the_next_writer_applies() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("s.zarr"))).unwrap();
        for n in ["a", "b"] {
            b.put(&node_key(n), serde_json::to_vec(&doc("v1")).unwrap())
                .unwrap();
            b.put(&format!("{n}/v1/zarr.json"), b"{}".to_vec()).unwrap();
            b.put(&format!("{n}/v2/zarr.json"), b"{}".to_vec()).unwrap();
        }
        let mut c = Commit::new();
        for n in ["a", "b"] {
            c.write(n, doc("v2"));
            c.keep_only(n, "v2");
        }
        // Killed right after the commit point: the record is there, nothing applied.
        b.put(COMMIT_KEY, serde_json::to_vec(&c).unwrap()).unwrap();
        for n in ["a", "b"] {
            assert_eq!(read_committed_node(&b, n).unwrap(), doc("v2"));
            assert_eq!(read_node(&b, n).unwrap(), doc("v1"));
        }
        // Killed half-way through applying: still the new pair.
        b.put(&node_key("a"), serde_json::to_vec(&doc("v2")).unwrap())
            .unwrap();
        assert_eq!(read_committed_node(&b, "b").unwrap(), doc("v2"));
        // The next writer finishes it.
        let lock = WriterLock::acquire(&b, "test").unwrap();
        assert!(!b.exists(COMMIT_KEY).unwrap());
        for n in ["a", "b"] {
            assert_eq!(read_node(&b, n).unwrap(), doc("v2"));
            assert!(!b.exists(&format!("{n}/v1/zarr.json")).unwrap());
            assert!(b.exists(&format!("{n}/v2/zarr.json")).unwrap());
        }
        assert!(!recover(&b).unwrap());
        // A publish without the lock is refused; with it, it leaves no record.
        let mut c = Commit::new();
        c.write("a", doc("v3"));
        assert!(Commit {
            writes: c.writes.clone(),
            ..Commit::default()
        }
        .publish(&b)
        .is_err());
        c.hold(lock);
        c.publish(&b).unwrap();
        assert_eq!(read_node(&b, "a").unwrap(), doc("v3"));
        assert!(!b.exists(COMMIT_KEY).unwrap());
    }

    #[test]
    fn a_damaged_record_is_an_error_naming_it() {
        let d = tempfile::tempdir().unwrap();
        let b = Backend::open(&StoreLocation::Local(d.path().join("s.zarr"))).unwrap();
        b.put(COMMIT_KEY, b"{not json".to_vec()).unwrap();
        let e = read_committed_node(&b, "a").unwrap_err().to_string();
        assert!(
            e.contains("commit.json") && e.contains("commit record"),
            "{e}"
        );
    }
}
