//! Value ranges of every octree node, read once from the store's skeleton (kept for its stored
//! nodes only: memory and build time grow with the non-constant part), and the O(1)
//! emptiness tests the cut selection makes with them (octree paper §4: a node is empty when the
//! transfer function's opacity summed over its [min, max] is zero, via the prefix sum).
//!
//! Two ranges per node: its own payload's (apron included; what the page table's empty flag
//! must use, exactly like `PageTable::classify_empty`) and its whole subtree's. Averaging
//! narrows ranges, so a coarse node can look transparent while a one-voxel wire inside it is
//! not; only the subtree range may end refinement, or that wire would never load.

use strata_render::{TransferFunctionTable, ValueMapping};
use strata_source::VolumeSource;
use strata_storage::store::Skeleton;
use strata_types::{BrickId, OctreeLayout};

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
    /// Indices in level (brick order, increasing) of the nodes kept; `None` when every node
    /// of the level is kept (then a node's index is its position).
    indices: Option<Vec<u64>>,
    own: Vec<StoredRange>,
    subtree: Vec<StoredRange>,
}

impl LevelRanges {
    fn position(&self, index: u64) -> Option<usize> {
        match &self.indices {
            None => usize::try_from(index).ok().filter(|&i| i < self.own.len()),
            Some(indices) => indices.binary_search(&index).ok(),
        }
    }
}

/// Own and subtree ranges per level (level 0 = finest). Built from a sparse skeleton it keeps
/// only the skeleton's stored nodes: a node of a collapsed constant subtree answers its
/// collapsed root's range (its own and its subtree's: the root's constant value).
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
                    indices: None,
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

    /// From a skeleton's stored nodes, in O(stored nodes · log): a stored node's subtree range
    /// folds in its stored children's (a stored node has all of its children stored or none).
    pub fn from_skeleton(layout: &OctreeLayout, skeleton: &Skeleton) -> Self {
        let mut levels: Vec<LevelRanges> = (0..skeleton.level_count().min(layout.level_count()))
            .map(|level| {
                let bricks = layout.bricks_in_level(level);
                let stored = skeleton.stored_in_level(level);
                let dense = stored as u64 == skeleton.nodes_in_level(level);
                let mut indices = Vec::with_capacity(if dense { 0 } else { stored });
                let mut own = Vec::with_capacity(stored);
                for (id, n) in skeleton.stored_in_level_iter(level) {
                    if !dense {
                        indices.push(index_in(bricks, id.coords));
                    }
                    own.push(StoredRange {
                        min: n.min,
                        max: n.max,
                    });
                }
                LevelRanges {
                    bricks,
                    indices: (!dense).then_some(indices),
                    subtree: own.clone(),
                    own,
                }
            })
            .collect();
        for level in 1..levels.len() {
            let (finer, coarser) = levels.split_at_mut(level);
            let child = &finer[level - 1];
            let parent = &mut coarser[0];
            for c in 0..child.own.len() {
                let index = child.indices.as_ref().map_or(c as u64, |i| i[c]);
                let coords = coords_in(child.bricks, index);
                // Every stored node's parent is stored (the skeleton's invariant).
                if let Some(p) = parent.position(index_in(parent.bricks, coords.map(|v| v / 2))) {
                    parent.subtree[p] = parent.subtree[p].union(child.subtree[c]);
                }
            }
        }
        let page_dims = if layout.level_count() == 0 {
            [1, 1, 1]
        } else {
            layout.bricks_in_level(0)
        };
        OctreeRanges { levels, page_dims }
    }

    /// From a source's skeleton (a local store, or one opened over the network).
    pub fn from_source(store: &dyn VolumeSource) -> Self {
        Self::from_skeleton(store.layout(), store.skeleton())
    }

    /// Level and position of `id`'s record, or of the collapsed ancestor standing in for it.
    fn locate(&self, id: BrickId) -> Option<(usize, usize)> {
        if !self.contains(id) {
            return None;
        }
        let mut level = id.level as usize;
        let mut coords = id.coords;
        loop {
            let l = self.levels.get(level)?;
            if let Some(p) = l.position(index_in(l.bricks, coords)) {
                return Some((level, p));
            }
            level += 1;
            coords = coords.map(|c| c / 2);
        }
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
        self.levels
            .get(id.level as usize)
            .is_some_and(|l| (0..3).all(|a| id.coords[a] < l.bricks[a]))
    }

    pub fn own_range(&self, id: BrickId) -> Option<StoredRange> {
        let (level, p) = self.locate(id)?;
        Some(self.levels[level].own[p])
    }

    pub fn subtree_range(&self, id: BrickId) -> Option<StoredRange> {
        let (level, p) = self.locate(id)?;
        Some(self.levels[level].subtree[p])
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

fn index_in(bricks: [u32; 3], c: [u32; 3]) -> u64 {
    let n = bricks.map(u64::from);
    u64::from(c[0]) + n[0] * (u64::from(c[1]) + n[1] * u64::from(c[2]))
}

fn coords_in(bricks: [u32; 3], index: u64) -> [u32; 3] {
    let n = bricks.map(u64::from);
    [
        (index % n[0]) as u32,
        ((index / n[0]) % n[1]) as u32,
        (index / (n[0] * n[1])) as u32,
    ]
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

    /// Random small layouts with mostly constant nodes (constant coarse nodes over varying
    /// children included): the ranges built from the sparse skeleton answer every node as the
    /// dense construction does.
    #[test]
    fn ranges_from_a_sparse_skeleton_equal_the_dense_construction() {
        use strata_storage::store::NodeInfo;
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            rng >> 33
        };
        for _ in 0..30 {
            let dims = [0, 1, 2].map(|_| 1 + (next() % 300) as u32);
            let layout = OctreeLayout::new(dims);
            let dense: Vec<Vec<NodeInfo>> = (0..layout.level_count())
                .map(|l| {
                    (0..layout.brick_count_in_level(l))
                        .map(|_| match next() % 12 {
                            0 => NodeInfo {
                                min: (next() % 50) as u16,
                                max: 50 + (next() % 900) as u16,
                                flags: 0,
                            },
                            1 => NodeInfo::constant(3),
                            _ => NodeInfo::constant(0),
                        })
                        .collect()
                })
                .collect();
            let skeleton = Skeleton::from_dense(&layout, &dense);
            let sparse = OctreeRanges::from_skeleton(&layout, &skeleton);
            let bricks: Vec<[u32; 3]> = (0..layout.level_count())
                .map(|l| layout.bricks_in_level(l))
                .collect();
            let reference = OctreeRanges::from_fn(&bricks, |level, c| {
                let i = layout.index_in_level(BrickId::new(level, c)).unwrap();
                let n = dense[level as usize][i];
                StoredRange {
                    min: n.min,
                    max: n.max,
                }
            });
            assert_eq!(sparse.level_count(), reference.level_count());
            assert_eq!(sparse.page_dims(), reference.page_dims());
            for (l, &n) in bricks.iter().enumerate() {
                assert_eq!(sparse.bricks_in_level(l as u8), n);
                for z in 0..n[2] {
                    for y in 0..n[1] {
                        for x in 0..n[0] {
                            let id = BrickId::new(l as u8, [x, y, z]);
                            let at = format!("{dims:?} {id:?}");
                            assert_eq!(sparse.own_range(id), reference.own_range(id), "{at}");
                            assert_eq!(
                                sparse.subtree_range(id),
                                reference.subtree_range(id),
                                "{at}"
                            );
                        }
                    }
                }
                let past = BrickId::new(l as u8, [n[0], 0, 0]);
                assert_eq!(sparse.own_range(past), None);
            }
        }
    }
}
