//! Feature bricks kept in the store, so a volume opened again is warm: the f16 values the
//! [`crate::cache`] holds, written brick by brick into the resumable vector array
//! `neuvolex/vectors/features_SET` and published once every brick is in.
//!
//! Only sets without INR parts are kept (learned features change with every model snapshot;
//! `neuvolex features` stores those). The array's identity names the set, the store's
//! intensity normalisation and [`PERSIST_VERSION`], so features computed by another filter
//! bank or on other intensities are never read back: they are written again.
//!
//! The store's writer lock is held only to start the pending generation and to publish it;
//! bricks are written between, as a cluster worker writes a stage's, so a `neuvolex train`
//! beside the server is not kept waiting. A session closed half-way leaves the bricks done so
//! far, and the next open resumes from them.

use crate::features::FeatureSet;
use crate::ClassifyError;
use neuvolex_bricks::{Brick, BrickStore, VectorArray, VectorEncoding};
use std::sync::{Mutex, RwLock};

/// Bumped whenever the classic features' values change, so stored ones are recomputed.
pub const PERSIST_VERSION: u32 = 1;

/// The vector array holding `set`'s features (`None` for sets with INR parts).
pub fn array_name(set: &FeatureSet) -> Option<String> {
    if set.needs_model() {
        return None;
    }
    let s: String = set
        .to_string()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    Some(format!("features_{s}"))
}

/// What the stored values depend on: the set, the store's normalisation and the code version.
pub fn identity(store: &BrickStore, set: &FeatureSet) -> String {
    let n = store.normaliser();
    format!(
        "{set} v{PERSIST_VERSION} norm {:e} {:e} brick {}",
        n.lo,
        n.hi,
        store.info().brick
    )
}

/// Bytes the features of `set` take in the store (f16, before compression).
pub fn stored_bytes(store: &BrickStore, channels: usize) -> u64 {
    store.info().dims.iter().map(|&d| d as u64).product::<u64>() * channels as u64 * 2
}

enum State {
    /// Every brick is in (a published array, read-only).
    Complete(VectorArray),
    /// Some bricks are in (the pending generation, with its done markers).
    Pending(VectorArray),
}

/// The stored features of one feature set of one store: read a brick when it is in, add the
/// ones computed.
pub struct PersistedFeatures {
    name: String,
    identity: String,
    channels: usize,
    state: RwLock<State>,
    /// Serialises writes and the publication.
    writing: Mutex<()>,
}

impl std::fmt::Debug for PersistedFeatures {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PersistedFeatures")
            .field("name", &self.name)
            .field("channels", &self.channels)
            .field("complete", &self.complete())
            .finish()
    }
}

impl PersistedFeatures {
    /// Opens `set`'s stored features in `store` (`channels` per voxel): the published array
    /// when it was written for this identity, else the pending one resumed (or started).
    /// `Ok(None)` for sets with INR parts. Errors when the store cannot be written (read-only,
    /// or locked by another process).
    pub fn open(
        store: &BrickStore,
        set: &FeatureSet,
        channels: usize,
    ) -> Result<Option<Self>, ClassifyError> {
        let Some(name) = array_name(set) else {
            return Ok(None);
        };
        let id = identity(store, set);
        if let Ok(a) = store.open_vectors(&name) {
            let i = a.info();
            if i.complete && i.channels == channels && i.identity.as_deref() == Some(&id) {
                return Ok(Some(PersistedFeatures {
                    name,
                    identity: id,
                    channels,
                    state: RwLock::new(State::Complete(a)),
                    writing: Mutex::new(()),
                }));
            }
        }
        // The pending generation is started (or found) under the store's writer lock, then
        // written as a cluster worker writes a stage's bricks: without holding the lock, so
        // other writers (a `neuvolex train` beside the server) are not kept waiting.
        let started = match store.resume_vectors(&name, channels, VectorEncoding::F16, &id) {
            Err(neuvolex_bricks::BrickError::StageMismatch { .. }) => {
                // Written for other intensities or an older filter bank: start over.
                store.discard_pending_vectors(&name)?;
                store.resume_vectors(&name, channels, VectorEncoding::F16, &id)?
            }
            r => r?,
        };
        drop(started);
        let pending = store.open_pending_vectors(&name, &id)?;
        Ok(Some(PersistedFeatures {
            name,
            identity: id,
            channels,
            state: RwLock::new(State::Pending(pending)),
            writing: Mutex::new(()),
        }))
    }

    /// The vector array's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Channels per voxel.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// True once every brick is stored and published.
    pub fn complete(&self) -> bool {
        matches!(
            *self.state.read().unwrap_or_else(|p| p.into_inner()),
            State::Complete(_)
        )
    }

    /// True when brick `b` is stored.
    pub fn has(&self, b: &Brick) -> bool {
        match &*self.state.read().unwrap_or_else(|p| p.into_inner()) {
            State::Complete(_) => true,
            State::Pending(a) => a.is_done(b).unwrap_or(false),
        }
    }

    /// Brick `b`'s stored features (`voxels x channels`), or `None` when it is not stored
    /// (or cannot be read: it is computed again).
    pub fn read(&self, b: &Brick) -> Option<Vec<f32>> {
        let st = self.state.read().unwrap_or_else(|p| p.into_inner());
        let a = match &*st {
            State::Complete(a) => a,
            State::Pending(a) if a.is_done(b).unwrap_or(false) => a,
            State::Pending(_) => return None,
        };
        match a.read_brick(b) {
            Ok(v) if v.len() == b.voxels() * self.channels => Some(v),
            Ok(_) => None,
            Err(e) => {
                tracing::warn!("stored features {} brick {:?}: {e}", self.name, b.index);
                None
            }
        }
    }

    /// Stores brick `b`'s features (`voxels x channels`, already rounded to f16 so they read
    /// back exactly); a brick already stored is left alone.
    pub fn write(&self, b: &Brick, values: &[f32]) -> Result<(), ClassifyError> {
        let _w = self.writing.lock().unwrap_or_else(|p| p.into_inner());
        let st = self.state.read().unwrap_or_else(|p| p.into_inner());
        if let State::Pending(a) = &*st {
            if !a.is_done(b)? {
                a.write_brick(b, values)?;
                a.mark_done(b)?;
            }
        }
        Ok(())
    }

    /// Of `bricks`, those not stored yet, in their order.
    pub fn missing(&self, bricks: &[Brick]) -> Vec<Brick> {
        match &*self.state.read().unwrap_or_else(|p| p.into_inner()) {
            State::Complete(_) => Vec::new(),
            State::Pending(a) => a.pending(bricks.iter().copied()).unwrap_or_default(),
        }
    }

    /// Publishes the array once every brick of `store` is in, under the store's writer lock
    /// (later opens then read it whole); true when it is complete. When another process holds
    /// the lock, it stays pending (its bricks are read all the same) and a later call
    /// publishes it.
    pub fn finish_if_complete(&self, store: &BrickStore) -> Result<bool, ClassifyError> {
        let all: Vec<Brick> = store.bricks().collect();
        if !self.missing(&all).is_empty() {
            return Ok(false);
        }
        let _w = self.writing.lock().unwrap_or_else(|p| p.into_inner());
        let mut st = self.state.write().unwrap_or_else(|p| p.into_inner());
        if let State::Pending(_) = &*st {
            let mut w = match store.resume_vectors(
                &self.name,
                self.channels,
                VectorEncoding::F16,
                &self.identity,
            ) {
                Ok(w) => w,
                Err(e @ neuvolex_bricks::BrickError::Locked { .. }) => {
                    tracing::info!("stored features {} stay pending: {e}", self.name);
                    return Ok(false);
                }
                Err(e) => return Err(e.into()),
            };
            w.set_extra(serde_json::json!({"kind": "session_features", "set": self.name}));
            w.finish()?;
            *st = State::Complete(store.open_vectors(&self.name)?);
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::BrickFeatures;
    use neuvolex_bricks::synth::PhantomParams;

    fn store(dir: &std::path::Path) -> BrickStore {
        neuvolex_ingest::phantom_store(
            &dir.join("ph.zarr"),
            PhantomParams::with_size(24, 0),
            &neuvolex_ingest::IngestOptions {
                brick: 8,
                ..Default::default()
            },
            &mut |_| {},
        )
        .unwrap()
    }

    #[test]
    fn stored_bricks_read_back_exactly_and_a_reopen_resumes_then_reads_whole() {
        let d = tempfile::tempdir().unwrap();
        let s = store(d.path());
        let set: FeatureSet = "filters+xyz".parse().unwrap();
        let fx = BrickFeatures::new(&s, set.clone(), None, false).unwrap();
        let bricks: Vec<Brick> = s.bricks().collect();
        let f16 = |b: &Brick| -> Vec<f32> {
            fx.brick(b)
                .unwrap()
                .iter()
                .map(|&v| crate::features::f16_saturating(v).to_f32())
                .collect()
        };
        {
            let p = PersistedFeatures::open(&s, &set, fx.channels())
                .unwrap()
                .unwrap();
            assert!(!p.complete());
            assert_eq!(p.missing(&bricks).len(), bricks.len());
            let v = f16(&bricks[0]);
            p.write(&bricks[0], &v).unwrap();
            assert!(p.has(&bricks[0]) && !p.has(&bricks[1]));
            assert_eq!(p.read(&bricks[0]).unwrap(), v, "bit for bit");
            assert!(p.read(&bricks[1]).is_none());
            assert!(!p.finish_if_complete(&s).unwrap());
        }
        // Dropped half-way (a closed session): the next open resumes where it stopped.
        let p = PersistedFeatures::open(&s, &set, fx.channels())
            .unwrap()
            .unwrap();
        assert_eq!(p.missing(&bricks).len(), bricks.len() - 1);
        for b in &bricks[1..] {
            p.write(b, &f16(b)).unwrap();
        }
        assert!(p.finish_if_complete(&s).unwrap());
        assert!(p.complete());
        drop(p);
        // Published: read whole, and the writer lock is free for others.
        let p = PersistedFeatures::open(&s, &set, fx.channels())
            .unwrap()
            .unwrap();
        assert!(p.complete());
        for b in &bricks {
            assert_eq!(p.read(b).unwrap(), f16(b));
        }
        drop(s.writer_lock("test").unwrap());
    }

    #[test]
    fn features_written_for_another_identity_are_not_read_back_and_inr_sets_are_not_kept() {
        let d = tempfile::tempdir().unwrap();
        let s = store(d.path());
        let set: FeatureSet = "filters+xyz".parse().unwrap();
        assert_eq!(array_name(&"paper".parse().unwrap()), None);
        assert!(PersistedFeatures::open(&s, &"paper".parse().unwrap(), 64)
            .unwrap()
            .is_none());
        let name = array_name(&set).unwrap();
        assert_eq!(name, "features_filters-xyz");
        assert!(identity(&s, &set).starts_with("filters+xyz v1 norm "));
        let bricks: Vec<Brick> = s.bricks().collect();
        let ch = 53;
        // Bricks written by an older filter bank (or for other intensities).
        {
            let a = s
                .resume_vectors(&name, ch, VectorEncoding::F16, "filters+xyz v0")
                .unwrap();
            a.write_brick(&bricks[0], &vec![0.5; bricks[0].voxels() * ch])
                .unwrap();
            a.mark_done(&bricks[0]).unwrap();
        }
        let p = PersistedFeatures::open(&s, &set, ch).unwrap().unwrap();
        assert!(!p.has(&bricks[0]), "another identity's brick is not ours");
        assert!(p.read(&bricks[0]).is_none());
        assert_eq!(p.missing(&bricks).len(), bricks.len());
    }
}
