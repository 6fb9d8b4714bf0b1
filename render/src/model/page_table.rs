//! The layout ("page") table: one entry per level-0 brick position, pointing at the cache slot
//! of whichever resident octree node covers it. This is Eq. 1-5 of the mixed-resolution paper
//! generalised from two levels to an octree: instead of storing the translation t and scale
//! t_w per entry, an entry stores (slot, level); the shader derives
//! t_w = 2^-L, node = page >> L and the translation from the slot origin, which is the same
//! affine map x' = x · bscale · t_w + t with fewer bits.

use std::collections::HashMap;

use crate::error::RenderError;
use crate::model::transfer_function::TransferFunctionTable;
use strata_types::ValueMapping;

use crate::model::layout::{neighbour_bit, neighbour_offsets};

/// An octree node: (level, node coordinates within the level).
type NodeKey = (u8, [u32; 3]);

use crate::model::layout::{
    FLAG_EMPTY, FLAG_NOT_RESIDENT, FLAG_TRANSITION, FLAG_WHOLE_NODE, LEVEL_MASK, LEVEL_SHIFT,
    SLOT_AXIS_BITS, SLOT_AXIS_MASK,
};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PageEntry {
    /// Cache slot holding the covering node's 36³ payload.
    pub slot_in_cache: u32,
    /// Octree level of that node; it covers 2^level page positions per axis.
    pub level: u8,
    /// Transparent under the current transfer function: rays jump over this position.
    pub empty: bool,
    /// Nothing resident: rays treat the position as empty. The loader normally points at a
    /// coarser resident ancestor instead (the root always is).
    pub resident: bool,
}

impl PageEntry {
    pub fn resident(slot_in_cache: u32, level: u8) -> Self {
        PageEntry {
            slot_in_cache,
            level,
            empty: false,
            resident: true,
        }
    }

    pub const NOT_RESIDENT: PageEntry = PageEntry {
        slot_in_cache: 0,
        level: 0,
        empty: false,
        resident: false,
    };

    /// GPU word for a cache whose slot grid is `slots_per_axis` (each ≤ 255).
    pub fn encode(&self, slots_per_axis: [u32; 3]) -> u32 {
        let [sx, sy, _] = slots_per_axis.map(|v| v.max(1));
        let s = self.slot_in_cache;
        let xyz = (s % sx)
            | (((s / sx) % sy) << SLOT_AXIS_BITS)
            | ((s / (sx * sy)).min(SLOT_AXIS_MASK) << (2 * SLOT_AXIS_BITS));
        let mut word = xyz | ((self.level as u32 & LEVEL_MASK) << LEVEL_SHIFT);
        if self.empty {
            word |= FLAG_EMPTY;
        }
        if !self.resident {
            word |= FLAG_NOT_RESIDENT;
        }
        word
    }

    pub fn decode(word: u32, slots_per_axis: [u32; 3]) -> Self {
        let [sx, sy, _] = slots_per_axis.map(|v| v.max(1));
        let axis = |a: u32| (word >> (a * SLOT_AXIS_BITS)) & SLOT_AXIS_MASK;
        let (x, y, z) = (axis(0), axis(1), axis(2));
        PageEntry {
            slot_in_cache: x + sx * (y + sy * z),
            level: ((word >> LEVEL_SHIFT) & LEVEL_MASK) as u8,
            empty: word & FLAG_EMPTY != 0,
            resident: word & FLAG_NOT_RESIDENT == 0,
        }
    }

    /// Rays skip it: nothing to sample, or nothing visible.
    pub fn skipped(&self) -> bool {
        self.empty || !self.resident
    }
}

/// CPU page table: x fastest, then y, then z over `page_dims` = ceil(dims / 32).
#[derive(Clone, Debug, PartialEq)]
pub struct PageTable {
    pub page_dims: [u32; 3],
    pub entries: Vec<PageEntry>,
}

impl PageTable {
    pub fn new(page_dims: [u32; 3]) -> Self {
        let n = page_dims.iter().map(|&d| d as usize).product();
        PageTable {
            page_dims,
            entries: vec![PageEntry::NOT_RESIDENT; n],
        }
    }

    pub fn linear(&self, page: [u32; 3]) -> usize {
        let [nx, ny, _] = self.page_dims;
        page[0] as usize + nx as usize * (page[1] as usize + ny as usize * page[2] as usize)
    }

    pub fn get(&self, page: [u32; 3]) -> PageEntry {
        self.entries[self.linear(page)]
    }

    pub fn set(&mut self, page: [u32; 3], entry: PageEntry) {
        let i = self.linear(page);
        self.entries[i] = entry;
    }

    pub fn page_of_linear(&self, linear: usize) -> [u32; 3] {
        let [nx, ny, _] = self.page_dims;
        let l = linear as u32;
        [l % nx, (l / nx) % ny, l / (nx * ny)]
    }

    /// Octree node covering `page` at `level`.
    pub fn node_of(page: [u32; 3], level: u8) -> [u32; 3] {
        page.map(|p| p >> level)
    }

    pub fn encoded(&self, slots_per_axis: [u32; 3]) -> Vec<u32> {
        self.entries
            .iter()
            .map(|e| e.encode(slots_per_axis))
            .collect()
    }

    /// The words the raycaster reads (binding 3): [`PageEntry::encode`] plus what only the
    /// whole table knows, for the node-extent exit (raycast.wgsl): [`FLAG_WHOLE_NODE`] on
    /// entries whose node is covered by that one word, [`FLAG_TRANSITION`] where
    /// `transition_masks` (one per entry, smooth_transitions.rs) is non-zero, and in a
    /// not-resident word's level field its skip level ([`PageTable::not_resident_skip_levels`]).
    pub fn encoded_for_gpu(&self, slots_per_axis: [u32; 3], transition_masks: &[u32]) -> Vec<u32> {
        let whole = self.whole_node_flags();
        let skip = self.not_resident_skip_levels();
        self.entries
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let mut word = if e.resident {
                    e.encode(slots_per_axis)
                } else {
                    let mut blank = *e;
                    blank.level = skip[i];
                    blank.slot_in_cache = 0;
                    blank.encode(slots_per_axis)
                };
                if whole[i] {
                    word |= FLAG_WHOLE_NODE;
                }
                if transition_masks.get(i).is_some_and(|&m| m != 0) {
                    word |= FLAG_TRANSITION;
                }
                word
            })
            .collect()
    }

    /// Per entry: is it resident and does every page cell of its node (within the grid) hold
    /// the same entry? False for a parent that stands in for some of its children only (the
    /// loader shows a pending child's parent there), whose node box holds other entries too.
    pub fn whole_node_flags(&self) -> Vec<bool> {
        let mut cells_with: HashMap<(NodeKey, u32, bool), u64> = HashMap::new();
        let key = |i: usize, e: &PageEntry| {
            let node = Self::node_of(self.page_of_linear(i), e.level);
            ((e.level, node), e.slot_in_cache, e.empty)
        };
        for (i, e) in self.entries.iter().enumerate() {
            if e.resident {
                *cells_with.entry(key(i, e)).or_insert(0) += 1;
            }
        }
        self.entries
            .iter()
            .enumerate()
            .map(|(i, e)| {
                if !e.resident {
                    return false;
                }
                let k = key(i, e);
                let (level, node) = k.0;
                let span: u64 = (0..3)
                    .map(|a| {
                        let lo = (node[a] as u64) << level;
                        let hi = ((node[a] as u64 + 1) << level).min(self.page_dims[a] as u64);
                        hi.saturating_sub(lo)
                    })
                    .product();
                cells_with.get(&k) == Some(&span)
            })
            .collect()
    }

    /// Per not-resident entry, the largest s (≤ [`LEVEL_MASK`]) such that the aligned block of
    /// 2^s page cells per axis around it holds only not-resident entries (cells beyond the grid
    /// count as not resident: no ray samples there); 0 for resident entries. Rays skip such a
    /// block at once, as they skip a whole empty node.
    pub fn not_resident_skip_levels(&self) -> Vec<u8> {
        let mut levels = vec![0u8; self.entries.len()];
        // all_skipped[s] over the block grid of level s: is every cell of that block skipped.
        let mut dims = self.page_dims;
        let mut all: Vec<bool> = self.entries.iter().map(|e| !e.resident).collect();
        for s in 1..=LEVEL_MASK as u8 {
            if dims.iter().all(|&d| d <= 1) {
                break;
            }
            let next_dims = dims.map(|d| d.div_ceil(2));
            let lin = |p: [u32; 3], d: [u32; 3]| {
                p[0] as usize + d[0] as usize * (p[1] as usize + d[1] as usize * p[2] as usize)
            };
            let mut next = vec![true; next_dims.iter().map(|&d| d as usize).product()];
            for z in 0..dims[2] {
                for y in 0..dims[1] {
                    for x in 0..dims[0] {
                        if !all[lin([x, y, z], dims)] {
                            next[lin([x / 2, y / 2, z / 2], next_dims)] = false;
                        }
                    }
                }
            }
            let mut any = false;
            for (i, level) in levels.iter_mut().enumerate() {
                let p = self.page_of_linear(i).map(|c| c >> s);
                if *level == s - 1 && next[lin(p, next_dims)] && !self.entries[i].resident {
                    *level = s;
                    any = true;
                }
            }
            if !any {
                break;
            }
            dims = next_dims;
            all = next;
        }
        levels
    }

    pub fn check_against(&self, page_dims: [u32; 3]) -> Result<(), RenderError> {
        let n: usize = page_dims.iter().map(|&d| d as usize).product();
        if self.page_dims != page_dims || self.entries.len() != n {
            return Err(RenderError::PageTableMismatch(format!(
                "table is {:?} with {} entries, volume needs {:?}",
                self.page_dims,
                self.entries.len(),
                page_dims
            )));
        }
        Ok(())
    }

    /// Per entry, the stored [min, max] of every value a sample there can take: the covering
    /// node's range (core and apron), widened by the ranges of its coarser neighbours, whose
    /// field smooth transitions blend in within half a voxel of the shared face
    /// (smooth_transitions.rs). None where any of them is unknown.
    pub fn sampled_ranges(
        &self,
        mut range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    ) -> Vec<Option<(u16, u16)>> {
        let mut cache: HashMap<NodeKey, Option<(u16, u16)>> = HashMap::new();
        let mut range = |level: u8, node: [u32; 3]| {
            *cache
                .entry((level, node))
                .or_insert_with(|| range_of(level, node))
        };
        let mut hulls: HashMap<NodeKey, Option<(u16, u16)>> = HashMap::new();
        (0..self.entries.len())
            .map(|i| {
                let e = self.entries[i];
                if !e.resident {
                    return None;
                }
                let node = Self::node_of(self.page_of_linear(i), e.level);
                *hulls.entry((e.level, node)).or_insert_with(|| {
                    let (_, coarser) = coarser_neighbours(self, self.page_dims, e.level, node);
                    let mut hull = range(e.level, node)?;
                    for (level, n) in coarser {
                        let (lo, hi) = range(level, n)?;
                        hull = (hull.0.min(lo), hull.1.max(hi));
                    }
                    Some(hull)
                })
            })
            .collect()
    }

    /// Sets each entry's empty flag from the covering node's stored [min, max] (which must
    /// include the apron: trilinear samples near a page face read it). `range_of` returns None
    /// when the range is unknown, which leaves the entry visible.
    pub fn classify_empty(
        &mut self,
        table: &TransferFunctionTable,
        mapping: ValueMapping,
        range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    ) {
        let ranges = self.sampled_ranges(range_of);
        for (i, range) in ranges.iter().enumerate() {
            let e = self.entries[i];
            if !e.resident {
                continue;
            }
            let empty = match *range {
                Some((lo, hi)) => {
                    let (a, b) = (mapping.physical(lo as f64), mapping.physical(hi as f64));
                    table.is_transparent(a.min(b), a.max(b))
                }
                None => false,
            };
            self.entries[i].empty = empty;
        }
    }

    /// Per entry, the largest physical value any sample there can take: the covering node's
    /// stored max (core and apron, so trilinear samples near a face are bounded too) mapped to
    /// physical units. MIP rays skip an entry whose bound cannot beat their running maximum.
    /// Unknown ranges and non-resident entries give +inf, which never skips.
    pub fn value_max_physical(
        &self,
        mapping: ValueMapping,
        range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    ) -> Vec<f32> {
        let ranges = self.sampled_ranges(range_of);
        (0..self.entries.len())
            .map(|i| {
                let e = self.entries[i];
                if !e.resident {
                    return f32::INFINITY;
                }
                ranges[i].map_or(f32::INFINITY, |r| physical_max_bound(r, mapping))
            })
            .collect()
    }

    /// Isosurface variant: a node is empty when the iso value lies outside its [min, max]
    /// (no crossing can start inside it from below... nor be entered from it).
    pub fn classify_empty_for_iso(
        &mut self,
        iso_value: f64,
        mapping: ValueMapping,
        range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    ) {
        let ranges = self.sampled_ranges(range_of);
        for (i, range) in ranges.iter().enumerate() {
            let e = self.entries[i];
            if !e.resident {
                continue;
            }
            self.entries[i].empty = match *range {
                Some((lo, hi)) => {
                    let (a, b) = (mapping.physical(lo as f64), mapping.physical(hi as f64));
                    a.max(b) < iso_value
                }
                None => false,
            };
        }
    }
}

/// The largest physical value of the stored range `(lo, hi)` as f32, rounded up so f32 never
/// makes the bound smaller than a real sample (a MIP bound).
pub fn physical_max_bound((lo, hi): (u16, u16), mapping: ValueMapping) -> f32 {
    let (a, b) = (mapping.physical(lo as f64), mapping.physical(hi as f64));
    let bound = a.max(b) as f32;
    if (bound as f64) < a.max(b) {
        bound.next_up()
    } else {
        bound
    }
}

/// The 26-neighbour mask of the level-`level` node `node` and the distinct coarser nodes
/// (level, node) it touches by a face, an edge or a corner: the nodes whose field its
/// transition bands blend in.
pub fn coarser_neighbours(
    table: &PageTable,
    dims: [u32; 3],
    level: u8,
    node: [u32; 3],
) -> (u32, Vec<(u8, [u32; 3])>) {
    let side = 1i64 << level;
    let mut mask = 0;
    let mut nodes = Vec::new();
    for o in neighbour_offsets() {
        // Page range of the adjacent region along each axis, clipped to the grid.
        let mut lo = [0i64; 3];
        let mut hi = [0i64; 3];
        let mut outside = false;
        for a in 0..3 {
            let first = node[a] as i64 * side;
            let (l, h) = match o[a] {
                -1 => (first - 1, first - 1),
                1 => (first + side, first + side),
                _ => (first, first + side - 1),
            };
            lo[a] = l.max(0);
            hi[a] = h.min(dims[a] as i64 - 1);
            outside |= lo[a] > hi[a];
        }
        if outside {
            continue;
        }
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let page = [x as u32, y as u32, z as u32];
                    let e = table.get(page);
                    if e.resident && e.level > level {
                        mask |= 1 << neighbour_bit(o);
                        let key = (e.level, PageTable::node_of(page, e.level));
                        if !nodes.contains(&key) {
                            nodes.push(key);
                        }
                    }
                }
            }
        }
    }
    (mask, nodes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampled_ranges_widen_by_the_coarser_neighbours_only() {
        // Pages x = 0, 1: level-0 nodes; x = 2, 3: one level-1 node. The x = 1 nodes blend the
        // level-1 field into their +x band; the x = 0 nodes and the coarse node do not.
        let mut t = PageTable::new([4, 1, 1]);
        t.set([0, 0, 0], PageEntry::resident(0, 0));
        t.set([1, 0, 0], PageEntry::resident(1, 0));
        t.set([2, 0, 0], PageEntry::resident(2, 1));
        t.set([3, 0, 0], PageEntry::resident(2, 1));
        let range = |level: u8, node: [u32; 3]| match (level, node[0]) {
            (0, 0) => Some((0, 10)),
            (0, 1) => Some((5, 20)),
            (1, 1) => Some((100, 200)),
            _ => None,
        };
        let r = t.sampled_ranges(range);
        assert_eq!(
            r,
            vec![
                Some((0, 10)),
                Some((5, 200)),
                Some((100, 200)),
                Some((100, 200))
            ]
        );
        // Unknown neighbour range: unknown, so never classified empty.
        let r = t.sampled_ranges(|level, node| (level == 0).then_some((0, node[0] as u16)));
        assert_eq!(r[0], Some((0, 0)));
        assert_eq!(r[1], None);
    }

    #[test]
    fn whole_node_flags_tell_a_leaf_from_a_parent_standing_in_for_some_children() {
        // 4×2×2 grid: a level-1 node at x = 2..4 covers all its cells (a leaf of the cut);
        // the level-1 node at x = 0..2 shows in two of its eight cells only (a pending child's
        // parent), level-0 leaves in the rest; one cell is not resident.
        let mut t = PageTable::new([4, 2, 2]);
        for i in 0..t.entries.len() {
            let p = t.page_of_linear(i);
            let e = if p[0] >= 2 {
                PageEntry::resident(0, 1)
            } else if p[1] == 0 && p[2] == 0 {
                PageEntry::resident(1, 1)
            } else if p == [1, 1, 1] {
                PageEntry::NOT_RESIDENT
            } else {
                PageEntry::resident(2 + i as u32, 0)
            };
            t.entries[i] = e;
        }
        let whole = t.whole_node_flags();
        for (i, e) in t.entries.iter().enumerate() {
            let p = t.page_of_linear(i);
            let expected = e.resident && (p[0] >= 2 || e.level == 0);
            assert_eq!(whole[i], expected, "page {p:?}");
        }
        // An odd grid: the last node reaches past the grid, its cells inside all agree.
        let mut t = PageTable::new([3, 1, 1]);
        t.entries = vec![
            PageEntry::resident(0, 0),
            PageEntry::resident(1, 1),
            PageEntry::resident(1, 1),
        ];
        assert_eq!(t.whole_node_flags(), vec![true, false, true]);
    }

    #[test]
    fn skip_levels_are_the_largest_all_not_resident_aligned_blocks() {
        // 8×4×4: everything not resident but the cells (1, 0, 0) and (1, 3, 3).
        let mut t = PageTable::new([8, 4, 4]);
        t.set([1, 0, 0], PageEntry::resident(0, 0));
        t.set([1, 3, 3], PageEntry::resident(1, 0));
        let levels = t.not_resident_skip_levels();
        // Brute force: the largest s whose aligned block (clipped to the grid) is all not
        // resident.
        for (i, &got) in levels.iter().enumerate() {
            let p = t.page_of_linear(i);
            if t.entries[i].resident {
                assert_eq!(got, 0);
                continue;
            }
            let all_skipped = |s: u32| {
                let lo = p.map(|c| (c >> s) << s);
                (0..t.entries.len()).all(|j| {
                    let q = t.page_of_linear(j);
                    let inside = (0..3).all(|a| q[a] >= lo[a] && q[a] < lo[a] + (1 << s));
                    !inside || !t.entries[j].resident
                })
            };
            let want = (0..=4).rev().find(|&s| all_skipped(s)).unwrap() as u8;
            assert_eq!(got, want, "page {p:?}");
        }
        // x 4..8 is one all-not-resident level-2 block; the level-3 block (the grid) is not.
        assert_eq!(levels[t.linear([5, 0, 0])], 2);
        assert_eq!(levels[t.linear([0, 0, 0])], 0);
        assert_eq!(levels[t.linear([2, 2, 2])], 1);
        // The GPU words: skip levels in the not-resident words' level field, no slot bits.
        let words = t.encoded_for_gpu([4, 4, 4], &[]);
        for (i, w) in words.iter().enumerate() {
            if !t.entries[i].resident {
                assert_eq!(w & FLAG_NOT_RESIDENT, FLAG_NOT_RESIDENT);
                assert_eq!((w >> LEVEL_SHIFT) & LEVEL_MASK, levels[i] as u32);
                assert_eq!(w & 0x00ff_ffff, 0);
            } else {
                assert_eq!(
                    w & FLAG_WHOLE_NODE,
                    FLAG_WHOLE_NODE,
                    "level-0 leaves are whole"
                );
            }
        }
    }

    #[test]
    fn entry_round_trips() {
        let grid = [56, 40, 255];
        for e in [
            PageEntry::resident(0, 0),
            PageEntry::resident(56 * 40 * 255 - 1, LEVEL_MASK as u8),
            PageEntry {
                slot_in_cache: 77,
                level: 3,
                empty: true,
                resident: true,
            },
            PageEntry::NOT_RESIDENT,
        ] {
            assert_eq!(PageEntry::decode(e.encode(grid), grid), e);
        }
    }
}
