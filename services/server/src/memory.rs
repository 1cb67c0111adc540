//! What sessions hold in memory, under server-wide budgets that do not grow with the number of
//! sessions:
//!
//! - feature bricks: one LRU for all sessions ([`FeatureCache`], `--cache-mib`);
//! - render bricks: one LRU for every session's renderer ([`BrickCache`],
//!   `--render-cache-mib`), each session's bricks keyed by its own owner number;
//! - class probabilities: counted per session (one byte per voxel and class, reserved in full
//!   when a classification starts, `--probs-mib`); a classification that would pass the budget
//!   fails with 503 naming it, and a closed session gives its share back.
//!
//! The caches evict; the probabilities are refused. So everything sessions hold together stays
//! under the sum of the three budgets ([`Memory::budget`]), however many are open.
//!
//! A store's trained INR (its `model.nvx`, tens of MiB) is loaded once and shared by every
//! session on that store ([`Memory::store_model`]) instead of once per session; a training's
//! snapshots are its session's own (one training at a time by default, `--max-trainings`).
//!
//! A store's persisted feature bricks ([`neuvolex_classify::persist`]) are opened once and
//! shared by every session on that store too ([`Memory::stored_features`]), so two sessions
//! on one volume never write the same array twice.
//!
//! It also counts the renders in flight: classification yields to them between bricks
//! ([`Memory::yield_to_renders`]), so a user waiting on the 3-D view is served first.

use crate::cache::FeatureCache;
use crate::error::{ApiError, ApiResult};
use neuvolex_bricks::BrickStore;
use neuvolex_classify::features::FeatureSet;
use neuvolex_classify::persist::PersistedFeatures;
use neuvolex_features::InrModel;
use neuvolex_render::BrickCache;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant, SystemTime};

/// A model file's size and modification time: a changed file is loaded again.
type Stamp = (u64, SystemTime);

/// The server's session memory and its budgets.
pub struct Memory {
    /// Feature bricks of every session.
    pub features: Arc<FeatureCache>,
    /// Render bricks of every session's renderer.
    pub render: Arc<BrickCache>,
    render_budget: usize,
    probs_used: Mutex<usize>,
    probs_budget: usize,
    renders: AtomicUsize,
    cancelled: AtomicU64,
    models: Mutex<HashMap<String, (Stamp, Weak<InrModel>)>>,
    stored: Mutex<HashMap<String, Weak<PersistedFeatures>>>,
}

/// Marks a render in flight until dropped ([`Memory::render_started`]).
pub struct RenderTicket(Arc<Memory>);

impl Drop for RenderTicket {
    fn drop(&mut self) {
        self.0.renders.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Longest a classification waits for renders before each brick (so it always progresses).
pub const YIELD_LIMIT: Duration = Duration::from_secs(5);

impl Memory {
    /// Budgets in bytes: feature cache, render cache, probabilities.
    pub fn new(features: usize, render: usize, probs: usize) -> Arc<Memory> {
        Arc::new(Memory {
            features: Arc::new(FeatureCache::new(features)),
            render: Arc::new(BrickCache::new(render)),
            render_budget: render.max(1),
            probs_used: Mutex::new(0),
            probs_budget: probs,
            renders: AtomicUsize::new(0),
            cancelled: AtomicU64::new(0),
            models: Mutex::new(HashMap::new()),
            stored: Mutex::new(HashMap::new()),
        })
    }

    /// The INR saved in `store` (`neuvolex/inr/model.nvx`, by `neuvolex train` or a finished
    /// server training) when it fits the store's grid: loaded once and shared by every session
    /// holding it, loaded again when the file changed (or each time on S3, where the file is
    /// not stamped). `None` without a usable model.
    pub fn store_model(&self, store: &BrickStore) -> Option<Arc<InrModel>> {
        let loc = neuvolex_features::train::model_path(store);
        let stamp = std::fs::metadata(loc.as_path())
            .ok()
            .and_then(|m| Some((m.len(), m.modified().ok()?)));
        let key = loc.to_string();
        let mut models = self.models.lock().unwrap_or_else(|p| p.into_inner());
        models.retain(|_, (_, w)| w.strong_count() > 0);
        if let Some((s, w)) = models.get(&key) {
            if Some(*s) == stamp {
                if let Some(m) = w.upgrade() {
                    return Some(m);
                }
            }
        }
        let model = neuvolex_features::checkpoint::load(loc)
            .ok()
            .filter(|l| l.model.dims == store.info().dims)
            .map(|l| Arc::new(l.model))?;
        if let Some(s) = stamp {
            models.insert(key, (s, Arc::downgrade(&model)));
        }
        Some(model)
    }

    /// The persisted features of `set` in `store` (`channels` per voxel), opened once and
    /// shared while any session holds them; `Ok(None)` for sets with INR parts.
    pub fn stored_features(
        &self,
        store: &BrickStore,
        set: &FeatureSet,
        channels: usize,
    ) -> ApiResult<Option<Arc<PersistedFeatures>>> {
        let key = format!("{}\n{set}", store.root().display());
        let mut open = self.stored.lock().unwrap_or_else(|p| p.into_inner());
        open.retain(|_, w| w.strong_count() > 0);
        if let Some(p) = open.get(&key).and_then(Weak::upgrade) {
            return Ok(Some(p));
        }
        let Some(p) = PersistedFeatures::open(store, set, channels)? else {
            return Ok(None);
        };
        let p = Arc::new(p);
        open.insert(key, Arc::downgrade(&p));
        Ok(Some(p))
    }

    /// Store models held by sessions now: how many, and their parameters' bytes.
    pub fn store_models(&self) -> (usize, usize) {
        let models = self.models.lock().unwrap_or_else(|p| p.into_inner());
        models
            .values()
            .filter_map(|(_, w)| w.upgrade())
            .fold((0, 0), |(n, b), m| {
                (n + 1, b + (m.table.len() + m.dense.len()) * 4)
            })
    }

    /// The three budgets together, bytes.
    pub fn budget(&self) -> usize {
        self.features.budget() + self.render_budget + self.probs_budget
    }

    /// Bytes held now: features, render bricks and reserved probabilities.
    pub fn used(&self) -> usize {
        self.features.used() + self.render.used() + self.probs_used()
    }

    /// Bytes of probabilities reserved by all sessions.
    pub fn probs_used(&self) -> usize {
        *self.probs_used.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Changes a session's probability reservation from `*held` to `want` bytes, or refuses
    /// (503) when the other sessions' reservations leave too little.
    pub fn reserve_probs(&self, held: &mut usize, want: usize, session: &str) -> ApiResult<()> {
        let mut used = self.probs_used.lock().unwrap_or_else(|p| p.into_inner());
        let others = used.saturating_sub(*held);
        if others + want > self.probs_budget {
            return Err(ApiError::Busy(format!(
                "session {session}: its class probabilities need {} MiB, and the server's \
                 probability budget of {} MiB for all sessions (--probs-mib) has {} MiB left; \
                 close a session",
                want.div_ceil(1 << 20),
                self.probs_budget >> 20,
                self.probs_budget.saturating_sub(others) >> 20
            )));
        }
        *used = others + want;
        *held = want;
        Ok(())
    }

    /// Gives back a session's probability reservation (`*held` becomes 0).
    pub fn release_probs(&self, held: &mut usize) {
        let mut used = self.probs_used.lock().unwrap_or_else(|p| p.into_inner());
        *used = used.saturating_sub(std::mem::take(held));
    }

    /// Counts a render in flight until the ticket drops.
    pub fn render_started(self: &Arc<Self>) -> RenderTicket {
        self.renders.fetch_add(1, Ordering::SeqCst);
        RenderTicket(self.clone())
    }

    /// Renders in flight now.
    pub fn renders_in_flight(&self) -> usize {
        self.renders.load(Ordering::SeqCst)
    }

    /// Counts a render cancelled (its requester left, or the server stopped).
    pub fn render_cancelled(&self) {
        self.cancelled.fetch_add(1, Ordering::SeqCst);
    }

    /// Renders cancelled so far.
    pub fn renders_cancelled(&self) -> u64 {
        self.cancelled.load(Ordering::SeqCst)
    }

    /// Waits while renders are in flight, at most [`YIELD_LIMIT`] (classification calls it
    /// before each brick).
    pub fn yield_to_renders(&self) {
        let t = Instant::now();
        while self.renders_in_flight() > 0 && t.elapsed() < YIELD_LIMIT {
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Use and budgets, as `GET /api/server` reports them.
    pub fn report(&self) -> serde_json::Value {
        let (models, model_bytes) = self.store_models();
        serde_json::json!({
            "feature_cache": {"used": self.features.used(), "budget": self.features.budget()},
            "render_cache": {"used": self.render.used(), "budget": self.render_budget},
            "probabilities": {"used": self.probs_used(), "budget": self.probs_budget},
            "used": self.used(),
            "budget": self.budget(),
            "store_models": {"loaded": models, "bytes": model_bytes},
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probability_reservations_stay_within_the_budget() {
        let m = Memory::new(1 << 20, 1 << 20, 100);
        let (mut a, mut b) = (0, 0);
        m.reserve_probs(&mut a, 60, "a").unwrap();
        let e = m.reserve_probs(&mut b, 50, "b").unwrap_err().to_string();
        assert!(e.contains("session b") && e.contains("--probs-mib"), "{e}");
        assert_eq!((m.probs_used(), b), (60, 0));
        // Growing one's own reservation counts only the difference.
        m.reserve_probs(&mut a, 90, "a").unwrap();
        assert_eq!(m.probs_used(), 90);
        m.release_probs(&mut a);
        assert_eq!((m.probs_used(), a), (0, 0));
        m.reserve_probs(&mut b, 50, "b").unwrap();
        assert_eq!(m.probs_used(), 50);
    }
}
