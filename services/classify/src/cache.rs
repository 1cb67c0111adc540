//! The feature cache: an LRU of feature bricks in half precision, shared by every
//! classification and recommendation of a session (and every seed and round of an
//! evaluation), so a new scribble re-trains the forest without recomputing the features.
//! Entries are keyed by feature set, model version and brick, so a newer model snapshot never
//! serves stale features.

use crate::features::{f16_saturating, BrickFeatures};
use crate::ClassifyError;
use neuvolex_bricks::lru::Lru;
use neuvolex_bricks::Brick;
use std::sync::Arc;

type Key = (String, u64, [usize; 3]);

/// Feature bricks (`voxels x channels`, f16) under a byte budget.
pub struct FeatureCache {
    lru: Lru<Key, Arc<Vec<half::f16>>>,
}

impl FeatureCache {
    /// A cache holding at most `bytes` of features.
    pub fn new(bytes: usize) -> Self {
        FeatureCache {
            lru: Lru::new(bytes),
        }
    }

    /// The features of `b` from `fx` (named `set`, computed with model `version`), as f32.
    pub fn get(
        &self,
        set: &str,
        version: u64,
        fx: &BrickFeatures,
        b: &Brick,
    ) -> Result<Vec<f32>, ClassifyError> {
        let v = self
            .lru
            .get_or_try_insert(&(set.to_string(), version, b.index), || {
                let f = fx.brick(b)?;
                let h: Vec<half::f16> = f.iter().map(|&v| f16_saturating(v)).collect();
                let cost = h.len() * 2;
                Ok::<_, ClassifyError>((Arc::new(h), cost))
            })?;
        Ok(v.iter().map(|h| h.to_f32()).collect())
    }

    /// `(hits, misses)` so far.
    pub fn stats(&self) -> (u64, u64) {
        self.lru.hit_stats()
    }

    /// Bytes held.
    pub fn used(&self) -> usize {
        self.lru.used()
    }
}
