//! The brick octree's shape: levels, bricks with aprons, and how a coarser level is made.
//!
//! Level 0 is full resolution. Level L+1 has `ceil(dims_L / 2)` voxels per axis; its voxel `i`
//! is the rounded average of level-L voxels `2i` and `2i+1` on each axis (2×2×2 = 8 values), so it
//! sits at the centre of their cell (mixed-resolution paper §3.1). On an odd-sized axis the last
//! coarse voxel has only one fine neighbour; the missing one is the edge voxel replicated (index
//! clamped), so the average there equals that edge voxel's value. Geometrically, level-L voxel `i`
//! is centred at level-0 index `(i + 0.5)·2^L − 0.5`, so an odd axis reaches half a fine voxel past
//! the volume at the coarser level — the same convention the renderer uses.
//!
//! A brick holds 32³ core voxels plus a 2-voxel apron on every side (36³ stored), so trilinear
//! filtering and central differences never need a neighbouring brick. Apron voxels outside the
//! level replicate the edge voxel. Levels are added until one brick covers the whole volume.

use serde::{Deserialize, Serialize};

pub const BRICK_CORE: u64 = 32;
pub const BRICK_APRON: u64 = 2;
pub const BRICK_EDGE: u64 = BRICK_CORE + 2 * BRICK_APRON;
pub const BRICK_VOXELS: usize = (BRICK_EDGE * BRICK_EDGE * BRICK_EDGE) as usize;

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
    pub level_dims: Vec<[u64; 3]>,
}

impl OctreeLayout {
    pub fn new(dims: [u64; 3]) -> Self {
        let mut level_dims = vec![dims];
        let mut d = dims;
        while d.iter().any(|&n| n > BRICK_CORE) {
            d = [d[0].div_ceil(2), d[1].div_ceil(2), d[2].div_ceil(2)];
            level_dims.push(d);
        }
        OctreeLayout { level_dims }
    }

    pub fn level_count(&self) -> usize {
        self.level_dims.len()
    }

    pub fn bricks_in_level(&self, level: usize) -> [u64; 3] {
        let d = self.level_dims[level];
        [
            d[0].div_ceil(BRICK_CORE),
            d[1].div_ceil(BRICK_CORE),
            d[2].div_ceil(BRICK_CORE),
        ]
    }

    pub fn brick_count_in_level(&self, level: usize) -> u64 {
        self.bricks_in_level(level).iter().product()
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
        let n = self.bricks_in_level(level);
        let c = id.coords.map(u64::from);
        if c[0] >= n[0] || c[1] >= n[1] || c[2] >= n[2] {
            return None;
        }
        Some((c[0] + n[0] * (c[1] + n[1] * c[2])) as usize)
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.index_in_level(id).is_some()
    }
}

/// Rounded mean of 8 values, halves rounded up: what every coarser voxel is.
#[inline]
pub fn average8(sum: u32) -> u16 {
    ((sum + 4) / 8) as u16
}

/// Downsamples two consecutive slices of a level into one slice of the next level.
/// `next` (the slice 2k+1) is `None` at the end of an odd axis, where the edge slice is replicated.
pub fn downsample_slice_pair(
    first: &[u16],
    next: Option<&[u16]>,
    nx: usize,
    ny: usize,
    out: &mut [u16],
) {
    use rayon::prelude::*;
    let second = next.unwrap_or(first);
    let ox = nx.div_ceil(2);
    out.par_chunks_mut(ox).enumerate().for_each(|(oy, row)| {
        let y0 = 2 * oy;
        let y1 = (y0 + 1).min(ny - 1);
        for (ox_i, v) in row.iter_mut().enumerate() {
            let x0 = 2 * ox_i;
            let x1 = (x0 + 1).min(nx - 1);
            let mut sum = 0u32;
            for s in [first, second] {
                sum += s[y0 * nx + x0] as u32
                    + s[y0 * nx + x1] as u32
                    + s[y1 * nx + x0] as u32
                    + s[y1 * nx + x1] as u32;
            }
            *v = average8(sum);
        }
    });
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
    fn odd_axis_replicates_edge_voxel() {
        // 3×1 slice: last coarse voxel averages the edge voxel with itself.
        let a = [10u16, 20, 31];
        let mut out = [0u16; 2];
        downsample_slice_pair(&a, None, 3, 1, &mut out);
        assert_eq!(out, [15, 31]);
    }
}
