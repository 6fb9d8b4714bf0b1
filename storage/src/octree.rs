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

pub use strata_types::{
    BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS,
};

/// The brick constants at the width storage's index arithmetic uses (u64: slice indices and
/// byte offsets of many-GB volumes). Derived from strata-types' definitions, not new ones.
pub(crate) const CORE: u64 = BRICK_CORE as u64;
pub(crate) const APRON: u64 = BRICK_APRON as u64;
#[cfg(feature = "local")]
pub(crate) const PAYLOAD: u64 = BRICK_PAYLOAD as u64;

/// Rounded mean of 8 values, halves rounded up: what every coarser voxel is.
#[inline]
pub fn average8(sum: u32) -> u16 {
    ((sum + 4) / 8) as u16
}

/// Downsamples two consecutive slices of a level into one slice of the next level.
/// `next` (the slice 2k+1) is `None` at the end of an odd axis, where the edge slice is replicated.
/// Import's (rows in parallel on rayon), so local-only.
#[cfg(feature = "local")]
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
    fn odd_axis_replicates_edge_voxel() {
        // 3×1 slice: last coarse voxel averages the edge voxel with itself.
        let a = [10u16, 20, 31];
        let mut out = [0u16; 2];
        downsample_slice_pair(&a, None, 3, 1, &mut out);
        assert_eq!(out, [15, 31]);
    }
}
