//! The feature cache: one LRU of feature bricks in half precision for a whole process (the
//! server's sessions, or every seed and round of an evaluation), under one memory budget
//! (`--cache-mib`), so opening more sessions never multiplies the memory it may hold. Each session reads it through a [`SessionFeatures`]
//! handle, shared by every classification and recommendation of that session, so a new scribble
//! re-trains the forest without recomputing the features. Entries are keyed by session, feature
//! set, model version and brick, so a newer model snapshot never serves stale features, and a
//! closed session's entries are dropped.

use crate::features::{f16_saturating, BrickFeatures};
use crate::persist::PersistedFeatures;
use crate::ClassifyError;
use neuvolex_bricks::lru::Lru;
use neuvolex_bricks::Brick;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

type Key = (String, String, u64, [usize; 3]);

/// Feature bricks (`voxels x channels`, f16) of every session under one byte budget.
pub struct FeatureCache {
    lru: Lru<Key, Arc<Vec<half::f16>>>,
    budget: usize,
}

impl FeatureCache {
    /// A cache holding at most `bytes` of features (at least one brick is always kept).
    pub fn new(bytes: usize) -> Self {
        FeatureCache {
            lru: Lru::new(bytes),
            budget: bytes,
        }
    }

    /// The handle a session reads through.
    pub fn for_session(self: &Arc<Self>, session: &str) -> SessionFeatures {
        SessionFeatures {
            cache: self.clone(),
            session: session.to_string(),
            closed: AtomicBool::new(false),
        }
    }

    /// Drops every entry of `session` (it was closed).
    pub fn drop_session(&self, session: &str) {
        self.lru.retain(|k| k.0 != session);
    }

    /// `(hits, misses)` so far, all sessions.
    pub fn stats(&self) -> (u64, u64) {
        self.lru.hit_stats()
    }

    /// Bytes held, all sessions.
    pub fn used(&self) -> usize {
        self.lru.used()
    }

    /// The budget, bytes.
    pub fn budget(&self) -> usize {
        self.budget
    }
}

/// One session's view of the shared [`FeatureCache`].
pub struct SessionFeatures {
    cache: Arc<FeatureCache>,
    session: String,
    /// Set by [`SessionFeatures::close`]: nothing computed after it stays in the cache.
    closed: AtomicBool,
}

impl SessionFeatures {
    /// Drops the session's entries and keeps none computed later: work still running when
    /// the session closes (a classification, the background feature pass) gets its features
    /// but leaves nothing behind in the shared budget.
    pub fn close(&self) {
        // Marked before the entries go: an insert racing with the close is either removed
        // here or sees the mark and removes itself.
        self.closed.store(true, Ordering::SeqCst);
        self.cache.drop_session(&self.session);
    }

    /// The features of `b` from `fx` (named `set`, computed with model `version`), as f32.
    pub fn get(
        &self,
        set: &str,
        version: u64,
        fx: &BrickFeatures,
        b: &Brick,
    ) -> Result<Vec<f32>, ClassifyError> {
        self.get_with(set, version, fx, b, None)
    }

    /// [`Self::get`], reading a brick missing from the cache from `stored` when it holds it
    /// (the same f16 values) before computing it.
    pub fn get_with(
        &self,
        set: &str,
        version: u64,
        fx: &BrickFeatures,
        b: &Brick,
        stored: Option<&PersistedFeatures>,
    ) -> Result<Vec<f32>, ClassifyError> {
        Ok(widen(&self.get_f16_with(set, version, fx, b, stored)?))
    }

    /// [`Self::get_with`] as the cache holds it, in half precision and shared, without a copy
    /// (what [`neuvolex_classify::Forest::predict_proba_f16`](crate::Forest::predict_proba_f16)
    /// reads).
    pub fn get_f16_with(
        &self,
        set: &str,
        version: u64,
        fx: &BrickFeatures,
        b: &Brick,
        stored: Option<&PersistedFeatures>,
    ) -> Result<Arc<Vec<half::f16>>, ClassifyError> {
        let key = (self.session.clone(), set.to_string(), version, b.index);
        let v = self.cache.lru.get_or_try_insert(&key, || {
            let h: Vec<half::f16> = match stored.and_then(|p| p.read(b)) {
                Some(f) => f.iter().map(|&v| half::f16::from_f32(v)).collect(),
                None => fx.brick(b)?.iter().map(|&v| f16_saturating(v)).collect(),
            };
            let cost = h.len() * 2;
            Ok::<_, ClassifyError>((Arc::new(h), cost))
        })?;
        if self.closed.load(Ordering::SeqCst) {
            self.cache.lru.remove(&key);
        }
        Ok(v)
    }

    /// The cached features of `b`, if any (f32 of the f16 values).
    pub fn cached(&self, set: &str, version: u64, b: &Brick) -> Option<Vec<f32>> {
        let key = (self.session.clone(), set.to_string(), version, b.index);
        self.cache.lru.get(&key).map(|v| widen(&v))
    }

    /// The features of `part`, a box inside brick `whole`, rounded through f16 as [`Self::get`]
    /// rounds them: the whole brick's when it is cached or in `stored` (with `whole` as the
    /// box they cover), else just `part`'s, computed and not cached (a stroke's few slices of
    /// a brick cost a fraction of the brick, and the values are the same as the brick's).
    pub fn get_part(
        &self,
        set: &str,
        version: u64,
        fx: &BrickFeatures,
        whole: &Brick,
        part: &Brick,
        stored: Option<&PersistedFeatures>,
    ) -> Result<(Vec<f32>, Brick), ClassifyError> {
        if let Some(v) = self.cached(set, version, whole) {
            return Ok((v, *whole));
        }
        if stored.is_some_and(|p| p.has(whole)) {
            return Ok((self.get_with(set, version, fx, whole, stored)?, *whole));
        }
        let f = fx.brick(part)?;
        Ok((
            f.iter().map(|&v| f16_saturating(v).to_f32()).collect(),
            *part,
        ))
    }

    /// `(hits, misses)` so far, all sessions.
    pub fn stats(&self) -> (u64, u64) {
        self.cache.stats()
    }

    /// Bytes held, all sessions.
    pub fn used(&self) -> usize {
        self.cache.used()
    }
}

/// Half-precision features widened to f32 in bulk (the slice conversion uses the CPU's
/// vector instructions; element by element it dispatches per value).
pub(crate) fn widen(h: &[half::f16]) -> Vec<f32> {
    use half::slice::HalfFloatSliceExt;
    let mut out = vec![0.0f32; h.len()];
    h.convert_to_f32_slice(&mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::FeatureSet;
    use neuvolex_bricks::synth::PhantomParams;

    #[test]
    fn a_closed_session_keeps_nothing_in_the_cache() {
        let d = tempfile::tempdir().unwrap();
        let store = neuvolex_ingest::phantom_store(
            &d.path().join("ph.zarr"),
            PhantomParams::with_size(16, 0),
            &neuvolex_ingest::IngestOptions {
                brick: 8,
                ..Default::default()
            },
            &mut |_| {},
        )
        .unwrap();
        let set: FeatureSet = "local".parse().unwrap();
        let fx = BrickFeatures::new(&store, set.clone(), None, false).unwrap();
        let b = store.bricks().next().unwrap();
        let cache = Arc::new(FeatureCache::new(1 << 24));
        let (a, other) = (cache.for_session("a"), cache.for_session("b"));
        let want = a.get("local", 0, &fx, &b).unwrap();
        other.get("local", 0, &fx, &b).unwrap();
        let one = cache.used() / 2;
        a.close();
        assert_eq!(cache.used(), one, "the other session's entry stays");
        // Work that outlives the close still gets its features, and leaves none behind.
        assert_eq!(a.get("local", 0, &fx, &b).unwrap(), want);
        assert_eq!(cache.used(), one);
        assert!(a.cached("local", 0, &b).is_none());
    }
}
