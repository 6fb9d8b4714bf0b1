//! Value ranges of every octree node, read once from the store's skeleton, and the O(1)
//! emptiness tests the cut selection makes with them (octree paper §4: a node is empty when the
//! transfer function's opacity summed over its [min, max] is zero, via the prefix sum).
//!
//! Two ranges per node: its own payload's (apron included; what the page table's empty flag
//! must use, exactly like `PageTable::classify_empty`) and its whole subtree's. Averaging
//! narrows ranges, so a coarse node can look transparent while a one-voxel wire inside it is
//! not; only the subtree range may end refinement, or that wire would never load.

use strata_render::{TransferFunctionTable, ValueMapping};
use strata_source::VolumeSource;
use strata_storage::BrickId;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoredRange {
    pub min: u16,
    pub max: u16,
}

impl StoredRange {
    fn union(self, other: StoredRange) -> StoredRange {
        StoredRange {
            min: self.min.min(other.min),
            max: self.max.max(other.max),
        }
    }
}

struct LevelRanges {
    bricks: [u32; 3],
    own: Vec<StoredRange>,
    subtree: Vec<StoredRange>,
}

/// Own and subtree ranges of every node, per level (level 0 = finest).
pub struct OctreeRanges {
    levels: Vec<LevelRanges>,
    page_dims: [u32; 3],
}

impl OctreeRanges {
    /// `own_range(level, coords)` for every node of a layout with `bricks_per_level[l]` bricks.
    pub fn from_fn(
        bricks_per_level: &[[u32; 3]],
        mut own_range: impl FnMut(u8, [u32; 3]) -> StoredRange,
    ) -> Self {
        let mut levels: Vec<LevelRanges> = bricks_per_level
            .iter()
            .enumerate()
            .map(|(level, &bricks)| {
                let n = bricks.iter().map(|&b| b as usize).product();
                let mut own = Vec::with_capacity(n);
                for z in 0..bricks[2] {
                    for y in 0..bricks[1] {
                        for x in 0..bricks[0] {
                            own.push(own_range(level as u8, [x, y, z]));
                        }
                    }
                }
                LevelRanges {
                    bricks,
                    subtree: own.clone(),
                    own,
                }
            })
            .collect();
        for level in 1..levels.len() {
            let (finer, coarser) = levels.split_at_mut(level);
            let child = &finer[level - 1];
            let parent = &mut coarser[0];
            for z in 0..child.bricks[2] {
                for y in 0..child.bricks[1] {
                    for x in 0..child.bricks[0] {
                        let c = (x + child.bricks[0] * (y + child.bricks[1] * z)) as usize;
                        let [px, py, pz] = [x / 2, y / 2, z / 2];
                        let p = (px + parent.bricks[0] * (py + parent.bricks[1] * pz)) as usize;
                        parent.subtree[p] = parent.subtree[p].union(child.subtree[c]);
                    }
                }
            }
        }
        let page_dims = bricks_per_level.first().copied().unwrap_or([1, 1, 1]);
        OctreeRanges { levels, page_dims }
    }

    /// From a source's skeleton (a local store, or one opened over the network).
    pub fn from_source(store: &dyn VolumeSource) -> Self {
        let layout = store.layout();
        let bricks: Vec<[u32; 3]> = (0..layout.level_count())
            .map(|l| layout.bricks_in_level(l).map(|b| b))
            .collect();
        Self::from_fn(&bricks, |level, coords| {
            // A node missing from the skeleton cannot happen in an opened store; treating it as
            // full-range keeps it visible rather than silently culled.
            store.node(BrickId::new(level, coords)).map_or(
                StoredRange {
                    min: 0,
                    max: u16::MAX,
                },
                |n| StoredRange {
                    min: n.min,
                    max: n.max,
                },
            )
        })
    }

    pub fn level_count(&self) -> u8 {
        self.levels.len() as u8
    }

    pub fn root_level(&self) -> u8 {
        self.level_count().saturating_sub(1)
    }

    pub fn page_dims(&self) -> [u32; 3] {
        self.page_dims
    }

    pub fn bricks_in_level(&self, level: u8) -> [u32; 3] {
        self.levels.get(level as usize).map_or([0; 3], |l| l.bricks)
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.index(id).is_some()
    }

    fn index(&self, id: BrickId) -> Option<usize> {
        let l = self.levels.get(id.level as usize)?;
        let [bx, by, bz] = l.bricks;
        let [x, y, z] = id.coords;
        (x < bx && y < by && z < bz).then(|| (x + bx * (y + by * z)) as usize)
    }

    pub fn own_range(&self, id: BrickId) -> Option<StoredRange> {
        Some(self.levels[id.level as usize].own[self.index(id)?])
    }

    pub fn subtree_range(&self, id: BrickId) -> Option<StoredRange> {
        Some(self.levels[id.level as usize].subtree[self.index(id)?])
    }

    /// The existing children of a node (up to 8; fewer at odd-sized borders).
    pub fn children(&self, id: BrickId) -> impl Iterator<Item = BrickId> + '_ {
        let level = id.level.checked_sub(1);
        (0..8u32).filter_map(move |i| {
            let level = level?;
            let c = [0, 1, 2].map(|a| id.coords[a] * 2 + ((i >> a) & 1));
            let child = BrickId::new(level, c);
            self.contains(child).then_some(child)
        })
    }

    /// Level-0 page range `[lo, hi)` a node covers.
    pub fn page_span(&self, id: BrickId) -> ([u32; 3], [u32; 3]) {
        let lo = id.coords.map(|c| c << id.level);
        let hi = [0, 1, 2].map(|a| ((id.coords[a] + 1) << id.level).min(self.page_dims[a]));
        (lo, hi)
    }
}

/// What "contributes nothing" means for the current render mode.
#[derive(Clone, Copy)]
pub enum Emptiness<'a> {
    /// DVR and MIP: zero opacity over the whole range.
    TransferFunction {
        table: &'a TransferFunctionTable,
        mapping: ValueMapping,
    },
    /// Isosurface: the range stays below the iso value.
    Iso { value: f64, mapping: ValueMapping },
}

impl Emptiness<'_> {
    pub fn is_empty(&self, range: StoredRange) -> bool {
        match *self {
            Emptiness::TransferFunction { table, mapping } => {
                let (a, b) = (
                    mapping.physical(range.min as f64),
                    mapping.physical(range.max as f64),
                );
                table.is_transparent(a.min(b), a.max(b))
            }
            Emptiness::Iso { value, mapping } => {
                let (a, b) = (
                    mapping.physical(range.min as f64),
                    mapping.physical(range.max as f64),
                );
                a.max(b) < value
            }
        }
    }
}

impl Emptiness<'_> {
    /// The subtree reaches clearly more opacity than the node's own (averaged) values: a thin
    /// bright structure is blurred away at this level, so the node's pages may show nothing in
    /// the visibility feedback although its children would.
    pub fn hides_detail(&self, own: StoredRange, subtree: StoredRange) -> bool {
        match *self {
            Emptiness::TransferFunction { table, mapping } => {
                let opacity = |r: StoredRange| {
                    let (a, b) = (
                        mapping.physical(r.min as f64),
                        mapping.physical(r.max as f64),
                    );
                    table.source.max_opacity_in(a.min(b), a.max(b))
                };
                opacity(subtree) > opacity(own) + 0.05
            }
            Emptiness::Iso { .. } => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subtree_range_keeps_a_peak_that_averaging_hid() {
        // Two levels: 2x1x1 bricks at level 0, one root. The root's own range is narrow, but
        // brick [1,0,0] holds a bright voxel.
        let ranges =
            OctreeRanges::from_fn(&[[2, 1, 1], [1, 1, 1]], |level, c| match (level, c[0]) {
                (1, _) => StoredRange { min: 10, max: 20 },
                (0, 1) => StoredRange { min: 5, max: 900 },
                _ => StoredRange { min: 10, max: 12 },
            });
        let root = BrickId::new(1, [0, 0, 0]);
        assert_eq!(
            ranges.own_range(root),
            Some(StoredRange { min: 10, max: 20 })
        );
        assert_eq!(
            ranges.subtree_range(root),
            Some(StoredRange { min: 5, max: 900 })
        );
        assert_eq!(ranges.children(root).count(), 2);
        assert_eq!(ranges.page_span(root), ([0, 0, 0], [2, 1, 1]));
    }
}
