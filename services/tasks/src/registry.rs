//! How a worker rebuilds a stage from its name and parameters.

use crate::{DynStage, Result, TaskError};
use std::collections::BTreeMap;
use std::sync::Arc;

/// A large read-only object a stage's workers fetch once per run.
#[derive(Clone)]
pub struct Blob {
    /// Content key (stable for the same bytes, e.g. `forest-<fingerprint>`).
    pub key: String,
    /// The bytes.
    pub bytes: Arc<Vec<u8>>,
}

/// Where a worker fetches blobs (the NATS object store on a cluster).
pub trait Blobs: Sync {
    /// The bytes stored under `key`.
    fn get(&self, key: &str) -> Result<Arc<Vec<u8>>>;
}

/// No blobs: every lookup fails.
pub struct NoBlobs;

impl Blobs for NoBlobs {
    fn get(&self, key: &str) -> Result<Arc<Vec<u8>>> {
        Err(TaskError::Engine(format!(
            "blob '{key}' is not available here"
        )))
    }
}

/// Rebuilds a stage from its parameters.
pub type Build = fn(&serde_json::Value, &dyn Blobs) -> Result<Arc<dyn DynStage>>;

/// The stages a worker can run, by name.
#[derive(Default, Clone)]
pub struct Registry {
    builders: BTreeMap<&'static str, Build>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a stage.
    pub fn with(mut self, name: &'static str, build: Build) -> Self {
        self.builders.insert(name, build);
        self
    }

    /// Stage names known.
    pub fn names(&self) -> Vec<&'static str> {
        self.builders.keys().copied().collect()
    }

    /// Builds stage `name` from `params`.
    pub fn build(
        &self,
        name: &str,
        params: &serde_json::Value,
        blobs: &dyn Blobs,
    ) -> Result<Arc<dyn DynStage>> {
        let b = self
            .builders
            .get(name)
            .ok_or_else(|| TaskError::UnknownStage(name.to_string(), self.names().join(", ")))?;
        b(params, blobs)
    }
}
