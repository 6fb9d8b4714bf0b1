//! **Smooth mixed-resolution transitions** (mixed-resolution paper §4): where a node of the cut
//! meets a coarser one, the sampled field stays C0-continuous instead of jumping at the face.
//!
//! # What carries over from the paper and what cannot
//! The paper keeps coarse samples *on* brick faces (its coarse grid is vertex-aligned with the
//! brick, `(16+1)³` bricks), so the field on a high/low boundary is a bilinear function of coarse
//! *samples*, and Eq. 6-9 warp texture coordinates in the fine brick's half-voxel band so that one
//! hardware trilinear fetch, with the fine apron overwritten by those samples (§4.3 fix-up),
//! yields trapezoid/triangle interpolation. Strata's octree is cell-centred at every level
//! (level-L voxel `i` at level-0 index `(i + 0.5)·2^L − 0.5`), so the coarse samples nearest a
//! face sit one fine voxel *inside* the coarse node. The coarse field on the face is then the
//! average of two coarse sample layers, and at an edge or corner junction it is the average of
//! four or eight coarse samples, which is no texel of any brick. A single warped fetch can hit
//! such a value only through extrapolated apron values (outside the unorm range of the cache
//! texture), so the paper's warp does not carry over at junctions.
//!
//! # The construction used instead (same band, same mask, exact at every junction)
//! All level-(L+1) nodes sample one global trilinear field `G_{L+1}` (their aprons hold real
//! level data), and so do all level-L nodes (`G_L`). In a level-L node with coarser neighbours,
//!
//! ```text
//! F(p) = (1 − w(p))·G_L(p) + w(p)·G_{L+1}(p),   w(p) = clamp(1 − 2·d(p), 0, 1)
//! ```
//!
//! where `d(p)` is the L∞ distance, in level-L voxels, from `p` to the nearest coarser
//! neighbour (face, edge or corner; the 26-neighbour mask says which exist). `w` is a function
//! of position alone, so two level-L nodes sharing a face compute the same `F` there; on a face
//! shared with a coarser node `w = 1` and `F = G_{L+1}`, which is what the coarser node samples;
//! at half a voxel from every coarser neighbour `w = 0`. Hence `F` is continuous everywhere for
//! any cut whose neighbours differ by at most one level (the loader's 2:1 balance over 26
//! neighbours); deeper jumps (transient fallbacks to a resident ancestor) are blended towards
//! the nearest coarser node but not guaranteed continuous. `G_{L+1}(p)` is read from the coarser
//! neighbour's own payload: `p` lies within a quarter of its voxel from its face and its apron
//! is two voxels deep. The brick cache is never modified (no fix-up pass is needed), so core
//! and apron voxels are always the stored ones.
//!
//! Shading uses the same blend of the two fields' central-difference gradients, so normals are
//! continuous across level boundaries too. The blend is part of the field's one definition
//! ([`sample_field`] in field.rs; its WGSL twin is `transition_blend`).
//!
//! # What this module holds
//! The masks: per page entry the 26-neighbour mask of coarser neighbours
//! ([`transition_masks`], bit layout [`neighbour_bit`] from layout.rs), its near-side closure
//! ([`near_side_closure`], which lets the shader test one bit per sample), and the share of
//! transition nodes ([`transition_node_fraction`]). `GpuPageTable::update` writes the first
//! two to binding 11.

use crate::model::page_table::PageTable;

use crate::model::layout::{neighbour_bit, neighbour_offsets};
use crate::model::page_table::coarser_neighbours;

/// Per page entry, the 26-neighbour mask of the node covering it: bit set where the region
/// adjacent to the node across that face, edge or corner contains a resident page of a coarser
/// level. Zero for non-resident entries and for nodes with no coarser neighbour. Rebuilt with
/// the page table (O(nodes · face pages)).
pub fn transition_masks(table: &PageTable) -> Vec<u32> {
    let dims = table.page_dims;
    let mut masks = vec![0u32; table.entries.len()];
    let mut node_mask: std::collections::HashMap<(u8, [u32; 3]), u32> = Default::default();
    for (i, entry) in table.entries.iter().enumerate() {
        if !entry.resident {
            continue;
        }
        let page = table.page_of_linear(i);
        let level = entry.level;
        let node = PageTable::node_of(page, level);
        masks[i] = *node_mask
            .entry((level, node))
            .or_insert_with(|| coarser_neighbours(table, dims, level, node).0);
    }
    masks
}

/// For each side code `s` ∈ {−1, 0, 1}³ (per axis: within half a voxel of the low face, of
/// neither, of the high face), bit [`neighbour_bit`]`(s)` is set when a coarser neighbour lies
/// across one of those sides, i.e. across a non-empty subset `o` of them (a face, edge or
/// corner region). A sample can be in a transition band only where this bit is set, so the
/// shader tests one bit per sample instead of searching the mask.
pub fn near_side_closure(mask: u32) -> u32 {
    // Called once per page entry on every page-table write: most masks are zero, and the
    // loop below allocates nothing (it was the frame thread's largest cost at 1024³).
    if mask == 0 {
        return 0;
    }
    let mut closure = 0;
    for s in neighbour_offsets() {
        // Non-empty subsets of the axes where `s` is non-zero, as axis bit sets.
        let axes = (0..3).fold(0u32, |bits, a| bits | (u32::from(s[a] != 0) << a));
        let hit = (1u32..8)
            .filter(|subset| subset & !axes == 0)
            .any(|subset| {
                let o = [0, 1, 2].map(|a| if subset & (1 << a) != 0 { s[a] } else { 0 });
                mask & (1 << neighbour_bit(o)) != 0
            });
        if hit {
            closure |= 1 << neighbour_bit(s);
        }
    }
    closure
}

/// Share of resident nodes that have at least one coarser neighbour (the paper's "transition
/// bricks" column of Table 1).
pub fn transition_node_fraction(table: &PageTable, masks: &[u32]) -> f64 {
    let mut nodes = std::collections::HashSet::new();
    let mut transition = std::collections::HashSet::new();
    for (i, e) in table.entries.iter().enumerate() {
        if !e.resident {
            continue;
        }
        let key = (
            e.level,
            PageTable::node_of(table.page_of_linear(i), e.level),
        );
        nodes.insert(key);
        if masks[i] != 0 {
            transition.insert(key);
        }
    }
    if nodes.is_empty() {
        0.0
    } else {
        transition.len() as f64 / nodes.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::layout::neighbour_offset;
    use crate::model::page_table::PageEntry;

    #[test]
    fn bits_and_offsets_round_trip() {
        let offsets: Vec<_> = neighbour_offsets().collect();
        assert_eq!(offsets.len(), 26);
        for o in offsets {
            assert_eq!(neighbour_offset(neighbour_bit(o)), o);
            assert_ne!(neighbour_bit(o), 13);
        }
    }

    /// A 4×2×2 page grid: pages x = 0, 1 are level-0 nodes, x = 2, 3 one level-1 node.
    fn half_coarse_table() -> PageTable {
        let mut t = PageTable::new([4, 2, 2]);
        for z in 0..2 {
            for y in 0..2 {
                for x in 0..4 {
                    let level = if x >= 2 { 1 } else { 0 };
                    t.set([x, y, z], PageEntry::resident(x + 4 * (y + 2 * z), level));
                }
            }
        }
        t
    }

    #[test]
    fn masks_mark_exactly_the_coarser_sides() {
        let t = half_coarse_table();
        let m = transition_masks(&t);
        // x = 0 nodes touch no coarser node; x = 1 nodes touch it across +x (face, and the
        // edges/corners that stay inside the grid); the coarse node itself has none.
        assert_eq!(m[t.linear([0, 0, 0])], 0);
        assert_eq!(m[t.linear([2, 1, 1])], 0);
        let m1 = m[t.linear([1, 0, 0])];
        for o in neighbour_offsets() {
            let inside = (0..3).all(|a| {
                let n = [1i32, 0, 0][a] + o[a];
                n >= 0 && n < [4, 2, 2][a]
            });
            let expected = o[0] == 1 && inside;
            assert_eq!(m1 & (1 << neighbour_bit(o)) != 0, expected, "offset {o:?}");
        }
        assert!((transition_node_fraction(&t, &m) - 4.0 / 9.0).abs() < 1e-12);
    }

    #[test]
    fn near_side_closure_sets_exactly_the_side_codes_that_reach_a_coarser_neighbour() {
        // Coarser across the +x face only: every side code with x = +1 reaches it.
        let face = 1 << neighbour_bit([1, 0, 0]);
        let c = near_side_closure(face);
        for s in neighbour_offsets() {
            assert_eq!(c & (1 << neighbour_bit(s)) != 0, s[0] == 1, "{s:?}");
        }
        // Coarser across the (−x, +y) edge only: only codes near both of those faces.
        let edge = 1 << neighbour_bit([-1, 1, 0]);
        let c = near_side_closure(edge);
        for s in neighbour_offsets() {
            assert_eq!(
                c & (1 << neighbour_bit(s)) != 0,
                s[0] == -1 && s[1] == 1,
                "{s:?}"
            );
        }
        assert_eq!(near_side_closure(0), 0);
    }

    #[test]
    fn near_side_closure_matches_its_definition_for_many_masks() {
        // The definition, written out plainly: bit s is set when some non-empty sub-offset o
        // of s (s with some non-zero axes zeroed) has its mask bit set.
        let by_definition = |mask: u32| {
            let mut closure = 0;
            for s in neighbour_offsets() {
                let reaches = neighbour_offsets().any(|o| {
                    (0..3).all(|a| o[a] == 0 || o[a] == s[a]) && mask & (1 << neighbour_bit(o)) != 0
                });
                if reaches {
                    closure |= 1 << neighbour_bit(s);
                }
            }
            closure
        };
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut masks: Vec<u32> = neighbour_offsets().map(|o| 1 << neighbour_bit(o)).collect();
        for _ in 0..3000 {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            // Sparse and dense masks alike; bit 13 (the node itself) is never set.
            let bits = (state >> 32) as u32 & ((1 << 27) - 1) & !(1 << 13);
            masks.push(if state & 1 == 0 {
                bits
            } else {
                bits & (bits >> 3) & (bits >> 7)
            });
        }
        for mask in masks {
            assert_eq!(
                near_side_closure(mask),
                by_definition(mask),
                "mask {mask:#x}"
            );
        }
    }
}
