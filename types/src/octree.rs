//! The brick octree's shape: how many levels, and how many voxels and bricks each has.
//!
//! Level 0 is full resolution. Level L+1 has `ceil(dims_L / 2)` voxels per axis (which equals
//! `ceil(dims_0 / 2^(L+1))`); its voxel `i` is centred at level-0 index `(i + 0.5)·2^L − 0.5`.
//! Levels are added until one brick core covers the whole volume. How a coarser level's values
//! are made (2×2×2 averages at cell centres) lives with the importer in storage.

use serde::{Deserialize, Serialize};

use crate::BRICK_CORE;

/// Dimensions of octree level `level`: ceil(dims / 2^level).
pub fn level_dims(dims: [u32; 3], level: u8) -> [u32; 3] {
    dims.map(|d| d.div_ceil(1 << level))
}

/// Number of levels: halve until one brick covers the volume.
pub fn level_count(dims: [u32; 3]) -> u8 {
    let mut level = 0u8;
    while level_dims(dims, level).iter().any(|&d| d > BRICK_CORE) {
        level += 1;
    }
    level + 1
}

/// One node of the octree: a brick at a level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct BrickId {
    pub level: u8,
    /// Brick coordinates within the level (x, y, z).
    pub coords: [u32; 3],
}

impl BrickId {
    pub fn new(level: u8, coords: [u32; 3]) -> Self {
        BrickId { level, coords }
    }
    /// The parent node one level up.
    pub fn parent(self) -> BrickId {
        BrickId {
            level: self.level + 1,
            coords: [self.coords[0] / 2, self.coords[1] / 2, self.coords[2] / 2],
        }
    }
}

/// Dimensions of every level, in voxels and bricks.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct OctreeLayout {
    pub level_dims: Vec<[u32; 3]>,
}

impl OctreeLayout {
    pub fn new(dims: [u32; 3]) -> Self {
        OctreeLayout {
            level_dims: (0..level_count(dims))
                .map(|l| level_dims(dims, l))
                .collect(),
        }
    }

    pub fn level_count(&self) -> usize {
        self.level_dims.len()
    }

    pub fn bricks_in_level(&self, level: usize) -> [u32; 3] {
        self.level_dims[level].map(|d| d.div_ceil(BRICK_CORE))
    }

    pub fn brick_count_in_level(&self, level: usize) -> u64 {
        self.bricks_in_level(level)
            .iter()
            .map(|&n| u64::from(n))
            .product()
    }

    pub fn total_bricks(&self) -> u64 {
        (0..self.level_count())
            .map(|l| self.brick_count_in_level(l))
            .sum()
    }

    /// Position of `id` in the level's row-major (x fastest) brick order.
    pub fn index_in_level(&self, id: BrickId) -> Option<usize> {
        let level = id.level as usize;
        if level >= self.level_count() {
            return None;
        }
        let n = self.bricks_in_level(level).map(u64::from);
        let c = id.coords.map(u64::from);
        if c[0] >= n[0] || c[1] >= n[1] || c[2] >= n[2] {
            return None;
        }
        usize::try_from(c[0] + n[0] * (c[1] + n[1] * c[2])).ok()
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.index_in_level(id).is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_stop_when_one_brick_covers() {
        let l = OctreeLayout::new([512, 512, 512]);
        assert_eq!(l.level_count(), 5);
        assert_eq!(l.level_dims[4], [32, 32, 32]);
        let l = OctreeLayout::new([188, 256, 190]);
        assert_eq!(l.level_dims.last(), Some(&[24, 32, 24]));
        let l = OctreeLayout::new([33, 1, 1]);
        assert_eq!(l.level_dims, vec![[33, 1, 1], [17, 1, 1]]);
        let l = OctreeLayout::new([1, 1, 1]);
        assert_eq!(l.level_count(), 1);
    }

    #[test]
    fn repeated_halving_equals_one_division() {
        // The importer halves level by level; the renderer divides by 2^L once.
        for n in [1u32, 2, 3, 31, 32, 33, 63, 65, 187, 1000, 4097] {
            let mut d = n;
            for level in 0..12u8 {
                assert_eq!(level_dims([d, 1, 1], 0)[0], d);
                assert_eq!(level_dims([n, 1, 1], level)[0], d, "n={n} level={level}");
                d = d.div_ceil(2);
            }
        }
    }
}
