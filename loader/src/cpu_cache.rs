//! The level-2 cache of decompressed bricks in system memory (octree paper §4): LRU within a
//! byte budget, so recently used bricks come back without touching the store. Owned by the
//! frame loop; fetch workers hand bricks over through a channel.
//!
//! The budget counts sled's own cache for format 1-2 stores, and prefetch guesses never evict
//! demanded bricks. Its GPU counterpart is `gpu_slots.rs` (slot LRU, the root pinned).

use std::collections::BTreeMap;

// Keys are brick ids, not attacker-chosen: a fast hash (the frame thread looks bricks up
// thousands of times a frame).
use rustc_hash::FxHashMap as HashMap;
use std::sync::Arc;

use strata_types::BrickId;

pub type Brick = Arc<Vec<u16>>;

struct Entry {
    brick: Brick,
    bytes: u64,
    tick: u64,
    /// Loaded speculatively and not used yet (for the prefetch hit rate).
    unused_prefetch: bool,
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CpuCacheCounters {
    pub lookups: u64,
    pub hits: u64,
    pub evictions: u64,
    pub prefetch_loaded: u64,
    pub prefetch_used: u64,
}

pub struct CpuBrickCache {
    budget_bytes: u64,
    bytes: u64,
    tick: u64,
    entries: HashMap<BrickId, Entry>,
    by_age: BTreeMap<u64, BrickId>,
    counters: CpuCacheCounters,
}

impl CpuBrickCache {
    pub fn new(budget_bytes: u64) -> Self {
        CpuBrickCache {
            budget_bytes,
            bytes: 0,
            tick: 0,
            entries: HashMap::default(),
            by_age: BTreeMap::new(),
            counters: CpuCacheCounters::default(),
        }
    }

    pub fn budget_bytes(&self) -> u64 {
        self.budget_bytes
    }

    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn counters(&self) -> CpuCacheCounters {
        self.counters
    }

    /// The bricks held (the selection thread's snapshot of what is in CPU memory).
    pub fn ids(&self) -> impl Iterator<Item = BrickId> + '_ {
        self.entries.keys().copied()
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.entries.contains_key(&id)
    }

    /// Inserts (or refreshes) a brick, evicting least recently used ones to stay in budget.
    /// A brick larger than the whole budget is not kept.
    pub fn insert(&mut self, id: BrickId, brick: Brick, prefetched: bool) {
        let bytes = (brick.len() * size_of::<u16>()) as u64;
        if let Some(old) = self.entries.remove(&id) {
            self.by_age.remove(&old.tick);
            self.bytes -= old.bytes;
        }
        if bytes > self.budget_bytes {
            return;
        }
        if prefetched {
            // A guess must never push out what the view asked for: it may only replace older
            // unused guesses, or it is not kept.
            let mut freeable = self.budget_bytes - self.bytes;
            let mut victims = Vec::new();
            for (&tick, id) in &self.by_age {
                if freeable >= bytes {
                    break;
                }
                if let Some(e) = self.entries.get(id).filter(|e| e.unused_prefetch) {
                    freeable += e.bytes;
                    victims.push(tick);
                }
            }
            if freeable < bytes {
                return;
            }
            for tick in victims {
                self.evict(tick);
            }
        }
        while self.bytes + bytes > self.budget_bytes {
            let Some((&tick, _)) = self.by_age.first_key_value() else {
                break;
            };
            self.evict(tick);
        }
        self.tick += 1;
        self.by_age.insert(self.tick, id);
        self.entries.insert(
            id,
            Entry {
                brick,
                bytes,
                tick: self.tick,
                unused_prefetch: prefetched,
            },
        );
        self.bytes += bytes;
        if prefetched {
            self.counters.prefetch_loaded += 1;
        }
    }

    fn evict(&mut self, tick: u64) {
        if let Some(victim) = self.by_age.remove(&tick) {
            if let Some(e) = self.entries.remove(&victim) {
                self.bytes -= e.bytes;
                self.counters.evictions += 1;
            }
        }
    }

    /// Takes a brick for use (upload): counts the lookup, refreshes its age.
    pub fn get_for_use(&mut self, id: BrickId) -> Option<Brick> {
        self.counters.lookups += 1;
        let tick = self.tick + 1;
        let e = self.entries.get_mut(&id)?;
        self.tick = tick;
        self.by_age.remove(&e.tick);
        e.tick = tick;
        self.by_age.insert(tick, id);
        self.counters.hits += 1;
        if std::mem::take(&mut e.unused_prefetch) {
            self.counters.prefetch_used += 1;
        }
        Some(e.brick.clone())
    }

    /// The brick if held, without counting a lookup or refreshing its age (a snapshot for
    /// another pass, cut_payloads.rs, must not change what the loader keeps).
    pub fn peek(&self, id: BrickId) -> Option<Brick> {
        self.entries.get(&id).map(|e| e.brick.clone())
    }

    /// Counts a wanted brick that was not here (the miss side of the hit rate).
    pub fn note_miss(&mut self) {
        self.counters.lookups += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_least_recently_used_within_budget() {
        let brick = |v: u16| Arc::new(vec![v; 10]);
        let mut cache = CpuBrickCache::new(50); // room for two 20-byte bricks
        let ids: Vec<BrickId> = (0..3).map(|i| BrickId::new(0, [i, 0, 0])).collect();
        cache.insert(ids[0], brick(0), false);
        cache.insert(ids[1], brick(1), true);
        assert!(cache.get_for_use(ids[0]).is_some());
        cache.insert(ids[2], brick(2), false);
        assert!(cache.contains(ids[0]) && !cache.contains(ids[1]) && cache.contains(ids[2]));
        assert!(cache.bytes() <= 50);
        assert_eq!(cache.counters().prefetch_loaded, 1);
        assert_eq!(cache.counters().prefetch_used, 0);
    }

    #[test]
    fn a_prefetched_brick_never_evicts_a_demanded_one() {
        let brick = |v: u16| Arc::new(vec![v; 10]);
        let mut cache = CpuBrickCache::new(50);
        let ids: Vec<BrickId> = (0..4).map(|i| BrickId::new(0, [i, 0, 0])).collect();
        cache.insert(ids[0], brick(0), false);
        cache.insert(ids[1], brick(1), false);
        cache.insert(ids[2], brick(2), true);
        assert!(!cache.contains(ids[2]) && cache.contains(ids[0]) && cache.contains(ids[1]));
        cache.insert(ids[0], brick(0), true);
        cache.insert(ids[3], brick(3), true);
        assert!(
            cache.contains(ids[3]) && !cache.contains(ids[0]),
            "an unused guess makes room for a newer one"
        );
    }
}
