//! The layout ("page") table: one entry per level-0 brick position, pointing at the cache slot
//! of whichever resident octree node covers it. This is Eq. 1-5 of the mixed-resolution paper
//! generalised from two levels to an octree: instead of storing the translation t and scale
//! t_w per entry, an entry stores (slot, level); the shader derives
//! t_w = 2^-L, node = page >> L and the translation from the slot origin, which is the same
//! affine map x' = x · bscale · t_w + t with fewer bits.

use std::collections::HashMap;

use crate::error::RenderError;
use crate::transfer_function::TransferFunctionTable;
use strata_types::ValueMapping;

use crate::layout::{neighbour_bit, neighbour_offsets};

/// An octree node: (level, node coordinates within the level).
type NodeKey = (u8, [u32; 3]);

/// The page word's bits and the slot limits (moved to layout.rs; kept here so existing paths
/// resolve).
pub use crate::layout::{
    FLAG_EMPTY, FLAG_NOT_RESIDENT, FLAG_TRANSITION, LEVEL_MASK, LEVEL_SHIFT, MAX_SLOTS,
    MAX_SLOTS_PER_AXIS, SLOT_AXIS_BITS, SLOT_AXIS_MASK,
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
                match ranges[i] {
                    Some((lo, hi)) => {
                        let (a, b) = (mapping.physical(lo as f64), mapping.physical(hi as f64));
                        // Rounded up so f32 never makes the bound smaller than a real sample.
                        let bound = a.max(b) as f32;
                        if (bound as f64) < a.max(b) {
                            bound.next_up()
                        } else {
                            bound
                        }
                    }
                    None => f32::INFINITY,
                }
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
    fn entry_round_trips() {
        let grid = [56, 40, 255];
        for e in [
            PageEntry::resident(0, 0),
            PageEntry::resident(56 * 40 * 255 - 1, 31),
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
