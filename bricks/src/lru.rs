//! A small thread-safe least-recently-used cache with a cost budget, shared by every stage that
//! keeps decoded bricks in memory (store chunks, feature bricks, render bricks).

use std::collections::HashMap;
use std::hash::Hash;
use std::sync::Mutex;

struct Entry<V> {
    value: V,
    cost: usize,
    tick: u64,
}

struct State<K, V> {
    map: HashMap<K, Entry<V>>,
    budget: usize,
    used: usize,
    tick: u64,
    hits: u64,
    misses: u64,
}

/// An LRU map from `K` to cheaply cloned values (usually `Arc`s), evicting the least recently
/// used entries once the summed cost of its entries exceeds the budget. One entry is always
/// kept, however costly.
pub struct Lru<K, V> {
    state: Mutex<State<K, V>>,
}

impl<K: Eq + Hash + Clone, V: Clone> Lru<K, V> {
    /// An empty cache holding entries whose costs sum to at most `budget`.
    pub fn new(budget: usize) -> Self {
        Lru {
            state: Mutex::new(State {
                map: HashMap::new(),
                budget: budget.max(1),
                used: 0,
                tick: 0,
                hits: 0,
                misses: 0,
            }),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<K, V>> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The cached value of `key`, marking it recently used.
    pub fn get(&self, key: &K) -> Option<V> {
        let mut s = self.lock();
        s.tick += 1;
        let t = s.tick;
        match s.map.get_mut(key) {
            Some(e) => {
                e.tick = t;
                let v = e.value.clone();
                s.hits += 1;
                Some(v)
            }
            None => {
                s.misses += 1;
                None
            }
        }
    }

    /// Inserts (or replaces) `key`, evicting least recently used entries over the budget.
    pub fn insert(&self, key: K, value: V, cost: usize) {
        let mut s = self.lock();
        s.tick += 1;
        let tick = s.tick;
        if let Some(old) = s.map.insert(key, Entry { value, cost, tick }) {
            s.used -= old.cost;
        }
        s.used += cost;
        while s.used > s.budget && s.map.len() > 1 {
            let Some(k) = s
                .map
                .iter()
                .filter(|(_, e)| e.tick != tick)
                .min_by_key(|(_, e)| e.tick)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            if let Some(e) = s.map.remove(&k) {
                s.used -= e.cost;
            }
        }
    }

    /// The value of `key`, computing and caching it with `load` (which returns it and its cost)
    /// on a miss. Errors are returned and not cached.
    pub fn get_or_try_insert<E>(
        &self,
        key: &K,
        load: impl FnOnce() -> Result<(V, usize), E>,
    ) -> Result<V, E> {
        if let Some(v) = self.get(key) {
            return Ok(v);
        }
        let (v, cost) = load()?;
        self.insert(key.clone(), v.clone(), cost);
        Ok(v)
    }

    /// Changes the budget and drops every entry.
    pub fn set_budget(&self, budget: usize) {
        let mut s = self.lock();
        s.budget = budget.max(1);
        s.map.clear();
        s.used = 0;
    }

    /// Drops `key` if cached.
    pub fn remove(&self, key: &K) {
        let mut s = self.lock();
        if let Some(e) = s.map.remove(key) {
            s.used -= e.cost;
        }
    }

    /// Keeps only the entries whose key passes `keep` (e.g. drops a closed session's).
    pub fn retain(&self, keep: impl Fn(&K) -> bool) {
        let mut s = self.lock();
        let mut freed = 0;
        s.map.retain(|k, e| {
            let k2 = keep(k);
            if !k2 {
                freed += e.cost;
            }
            k2
        });
        s.used -= freed;
    }

    /// Drops every entry.
    pub fn clear(&self) {
        let mut s = self.lock();
        s.map.clear();
        s.used = 0;
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.lock().map.len()
    }

    /// True when nothing is cached.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Summed cost of the entries held.
    pub fn used(&self) -> usize {
        self.lock().used
    }

    /// `(hits, misses)` of [`Self::get`] so far.
    pub fn hit_stats(&self) -> (u64, u64) {
        let s = self.lock();
        (s.hits, s.misses)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_least_recently_used_over_budget() {
        let c: Lru<u32, u32> = Lru::new(10);
        c.insert(1, 10, 4);
        c.insert(2, 20, 4);
        assert_eq!(c.get(&1), Some(10));
        c.insert(3, 30, 4);
        assert_eq!(c.get(&2), None, "2 was least recently used");
        assert_eq!(c.get(&1), Some(10));
        assert_eq!(c.get(&3), Some(30));
        assert_eq!(c.used(), 8);
        c.insert(4, 40, 100);
        assert_eq!(c.len(), 1, "an entry over budget is kept alone");
        assert_eq!(c.get(&4), Some(40));
        c.remove(&4);
        assert!(c.is_empty());
        let r: Result<u32, ()> = c.get_or_try_insert(&5, || Ok((50, 1)));
        assert_eq!(r, Ok(50));
        let e: Result<u32, &str> = c.get_or_try_insert(&6, || Err("no"));
        assert_eq!(e, Err("no"));
        assert_eq!(c.get(&6), None);
    }
}
