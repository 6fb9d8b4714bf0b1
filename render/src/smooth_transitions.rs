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
//! continuous across level boundaries too. The shader (`transition_blend` in raycast.wgsl) and
//! the reference ([`sample_field`]) implement the same definition.

use glam::DVec3;

use crate::layout::{BrickSource, BRICK_CORE};
use crate::page_table::PageTable;
use crate::reference::{gradient_index, locate, locate_in_page, trilinear, FieldLocation};

/// The mask's bit layout (layout.rs: the shader reads the same bits).
pub use crate::layout::{neighbour_bit, neighbour_offset, neighbour_offsets};
/// The coarser-neighbour query is topology (page_table.rs); kept here so existing paths resolve.
pub use crate::page_table::coarser_neighbours;

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
    let mut closure = 0;
    for s in neighbour_offsets() {
        let axes: Vec<usize> = (0..3).filter(|&a| s[a] != 0).collect();
        let hit = (1u32..(1 << axes.len())).any(|subset| {
            let mut o = [0i32; 3];
            for (k, &a) in axes.iter().enumerate() {
                if subset & (1 << k) != 0 {
                    o[a] = s[a];
                }
            }
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

/// Blend weight from the L∞ distance to the nearest coarser neighbour, in the node's voxels:
/// 1 on the shared face, 0 from half a voxel inward.
pub fn band_weight(distance_voxels: f64) -> f64 {
    (1.0 - 2.0 * distance_voxels).clamp(0.0, 1.0)
}

/// Distance (node voxels) from `p` (level-0 index) to the region across neighbour offset `o`
/// of the level-`level` node `node`: the largest of the distances to the faces `o` points at.
pub fn distance_to_neighbour(p: DVec3, level: u8, node: [u32; 3], o: [i32; 3]) -> f64 {
    let scale = (1u64 << level) as f64;
    let core = BRICK_CORE as f64;
    let mut d = f64::NEG_INFINITY;
    for a in 0..3 {
        let q = (p[a] + 0.5) / scale - 0.5;
        let lo = node[a] as f64 * core - 0.5;
        match o[a] {
            -1 => d = d.max(q - lo),
            1 => d = d.max(lo + core - q),
            _ => {}
        }
    }
    d
}

/// One sample of the (optionally smoothed) field.
pub struct FieldSample<'b> {
    /// Stored units (not physical).
    pub value: f64,
    pub location: FieldLocation<'b>,
    /// The coarser neighbour blended in and its weight, when inside a transition band.
    pub coarse: Option<(FieldLocation<'b>, f64)>,
}

impl FieldSample<'_> {
    /// Gradient in stored units per level-0 index step, blended like the value.
    pub fn gradient_index(&self) -> DVec3 {
        let fine = gradient_index(&self.location);
        match &self.coarse {
            Some((c, w)) => fine * (1.0 - w) + gradient_index(c) * *w,
            None => fine,
        }
    }
}

/// The field at level-0 index `p`: the covering node's trilinear value, blended with its nearest
/// coarser neighbour inside the half-voxel band when `masks` (from [`transition_masks`]) is given.
/// None where nothing is resident.
pub fn sample_field<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    masks: Option<&[u32]>,
    dims: [u32; 3],
    p: DVec3,
) -> Option<FieldSample<'b>> {
    let location = locate(source, table, dims, p)?;
    let fine = trilinear(location.brick, location.local);
    let mask = masks.map_or(0, |m| m[location.page_linear]);
    let coarse = if mask != 0 {
        nearest_coarser(source, table, dims, p, &location, mask)
    } else {
        None
    };
    let value = match &coarse {
        Some((c, w)) => fine * (1.0 - w) + trilinear(c.brick, c.local) * w,
        None => fine,
    };
    Some(FieldSample {
        value,
        location,
        coarse,
    })
}

fn nearest_coarser<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    dims: [u32; 3],
    p: DVec3,
    location: &FieldLocation<'b>,
    mask: u32,
) -> Option<(FieldLocation<'b>, f64)> {
    let pc = DVec3::new(
        p.x.clamp(-0.5, dims[0] as f64 - 0.5),
        p.y.clamp(-0.5, dims[1] as f64 - 0.5),
        p.z.clamp(-0.5, dims[2] as f64 - 0.5),
    );
    let page = table.page_of_linear(location.page_linear);
    let node = PageTable::node_of(page, location.level);
    let mut best: Option<(f64, [u32; 3])> = None;
    for bit in (0..27).filter(|b| mask & (1 << b) != 0) {
        let o = neighbour_offset(bit);
        let d = distance_to_neighbour(pc, location.level, node, o);
        if d >= 0.5 || best.is_some_and(|(bd, _)| d >= bd) {
            continue;
        }
        let mut neighbour = [0u32; 3];
        let mut inside = true;
        for a in 0..3 {
            let n = page[a] as i64 + o[a] as i64;
            inside &= n >= 0 && n < table.page_dims[a] as i64;
            neighbour[a] = n.max(0) as u32;
        }
        if !inside {
            continue;
        }
        let e = table.get(neighbour);
        if e.resident && e.level > location.level {
            best = Some((d, neighbour));
        }
    }
    let (d, neighbour) = best?;
    let w = band_weight(d);
    if w <= 0.0 {
        return None;
    }
    let coarse = locate_in_page(source, table, neighbour, pc)?;
    Some((coarse, w))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::page_table::PageEntry;

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
    fn band_weight_is_one_on_the_face_and_zero_half_a_voxel_in() {
        assert_eq!(band_weight(0.0), 1.0);
        assert_eq!(band_weight(0.25), 0.5);
        assert_eq!(band_weight(0.5), 0.0);
        assert_eq!(band_weight(3.0), 0.0);
        assert_eq!(band_weight(-0.1), 1.0);
        // Node 1 at level 0 spans level-0 indices [31.5, 63.5); its +x face is at 63.5.
        let d = distance_to_neighbour(DVec3::new(63.25, 40.0, 40.0), 0, [1, 1, 1], [1, 0, 0]);
        assert!((d - 0.25).abs() < 1e-12);
        // An edge neighbour is as far as the farther of its two faces.
        let d = distance_to_neighbour(DVec3::new(63.25, 63.0, 40.0), 0, [1, 1, 1], [1, 1, 0]);
        assert!((d - 0.5).abs() < 1e-12);
        // Level 1: voxels are two level-0 indices wide.
        let d = distance_to_neighbour(DVec3::new(-0.5 + 0.5, 10.0, 10.0), 1, [0, 0, 0], [-1, 0, 0]);
        assert!((d - 0.25).abs() < 1e-12);
    }
}
