//! Which node lives in which slot of the brick cache texture: an LRU over slots (octree paper
//! §4) with the root pinned, so every frame can draw the whole volume. Any level fits any slot
//! (mixed-resolution paper §3.2: one cache, levels mixed freely through the page table).

// Keys are brick ids, not attacker-chosen: a fast hash (looked up for every node of every cut).
use rustc_hash::FxHashMap as HashMap;

use strata_types::BrickId;

/// Cloned into each job of the selection thread (cut_worker.rs), which returns the copy
/// with the cut's slots assigned.
#[derive(Clone)]
pub struct GpuSlots {
    node_in_slot: Vec<Option<BrickId>>,
    slot_of: HashMap<BrickId, u32>,
    last_used_frame: Vec<u64>,
    pinned: Vec<bool>,
    free: Vec<u32>,
}

impl GpuSlots {
    pub fn new(capacity: u32) -> Self {
        GpuSlots {
            node_in_slot: vec![None; capacity as usize],
            slot_of: HashMap::default(),
            last_used_frame: vec![0; capacity as usize],
            pinned: vec![false; capacity as usize],
            // Popped from the back: hand out slot 0 first.
            free: (0..capacity).rev().collect(),
        }
    }

    pub fn capacity(&self) -> usize {
        self.node_in_slot.len()
    }

    pub fn occupied(&self) -> usize {
        self.slot_of.len()
    }

    pub fn slot_of(&self, id: BrickId) -> Option<u32> {
        self.slot_of.get(&id).copied()
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.slot_of.contains_key(&id)
    }

    pub fn resident(&self) -> impl Iterator<Item = (BrickId, u32)> + '_ {
        self.slot_of.iter().map(|(&id, &s)| (id, s))
    }

    /// Marks a resident node as used by `frame`, protecting it from eviction this frame.
    pub fn touch(&mut self, id: BrickId, frame: u64) {
        if let Some(&s) = self.slot_of.get(&id) {
            self.last_used_frame[s as usize] = frame;
        }
    }

    /// A slot for `id`: a free one, else the least recently used unpinned slot not used by
    /// `frame`. None when every slot is in use this frame.
    pub fn allocate(&mut self, id: BrickId, frame: u64, pin: bool) -> Option<u32> {
        if let Some(&s) = self.slot_of.get(&id) {
            self.last_used_frame[s as usize] = frame;
            return Some(s);
        }
        let slot = match self.free.pop() {
            Some(s) => s,
            None => {
                let victim = (0..self.capacity())
                    .filter(|&s| !self.pinned[s] && self.last_used_frame[s] < frame)
                    .min_by_key(|&s| self.last_used_frame[s])? as u32;
                if let Some(old) = self.node_in_slot[victim as usize].take() {
                    self.slot_of.remove(&old);
                }
                victim
            }
        };
        self.node_in_slot[slot as usize] = Some(id);
        self.slot_of.insert(id, slot);
        self.last_used_frame[slot as usize] = frame;
        self.pinned[slot as usize] = pin;
        Some(slot)
    }

    /// Resident nodes per level (index = level).
    pub fn per_level(&self, levels: usize) -> Vec<usize> {
        let mut counts = vec![0; levels];
        for id in self.slot_of.keys() {
            if let Some(c) = counts.get_mut(id.level as usize) {
                *c += 1;
            }
        }
        counts
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_oldest_unpinned_and_never_this_frames() {
        let mut slots = GpuSlots::new(3);
        let id = |i: u32| BrickId::new(0, [i, 0, 0]);
        let root = BrickId::new(2, [0, 0, 0]);
        assert_eq!(slots.allocate(root, 1, true), Some(0));
        assert_eq!(slots.allocate(id(1), 1, false), Some(1));
        assert_eq!(slots.allocate(id(2), 2, false), Some(2));
        // Frame 3 uses id(2): the only candidate is id(1)'s slot.
        slots.touch(id(2), 3);
        assert_eq!(slots.allocate(id(3), 3, false), Some(1));
        assert!(!slots.contains(id(1)) && slots.contains(root));
        assert_eq!(
            slots.allocate(id(4), 3, false),
            None,
            "all slots in use this frame"
        );
        assert_eq!(slots.per_level(3), vec![2, 0, 1]);
    }
}
