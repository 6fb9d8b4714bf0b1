//! The page table of a cut kept per leaf, not per page cell (issue 18): what the octree
//! traversal is prepared from, so the CPU side of its index grows with the cut like its GPU
//! side. A 16384³ volume has 512³ page cells; a dense [`PageTable`] of them is 1 GiB per
//! copy, while its cut is a few thousand leaves.
//!
//! A [`SparsePageTable`] is the leaves the loader painted the dense table from (aligned
//! blocks of 2^size page cells, each with the entry its cells hold) plus a hash index by
//! (size, block), so a point query costs one lookup per level. Because the blocks tile the
//! grid as an octree does, a neighbour query needs one cell per neighbouring block
//! ([`SparsePageTable::coarser_neighbours`]), where the dense table reads every cell of the
//! shared face. [`IndexTable`] is either table: what the loader and the GPU index keep as
//! "the table last written".

use std::collections::HashMap;

use crate::model::layout::{neighbour_bit, neighbour_offsets};
use crate::model::octree_cut::CutLeaf;
use crate::model::page_table::{coarser_neighbours, PageEntry, PageTable};

/// Read access to a page table, dense or per leaf: what the per-leaf transition masks, MIP
/// bounds and empty refinement ask of it.
pub trait PageLookup {
    fn page_dims(&self) -> [u32; 3];

    /// The entry page cell `page` holds (not resident outside the grid).
    fn entry_at(&self, page: [u32; 3]) -> PageEntry;

    /// The 26-neighbour mask of coarser resident neighbours of the level-`level` node `node`
    /// and those neighbours (level, node): see `page_table::coarser_neighbours`.
    fn coarser_neighbours(&self, level: u8, node: [u32; 3]) -> (u32, Vec<(u8, [u32; 3])>);

    /// The stored [min, max] of every value a sample in the level-`level` node `node` can
    /// take: its own range widened by its coarser neighbours', whose field smooth transitions
    /// blend in (`PageTable::sampled_ranges` per page cell); None where any is unknown.
    fn sampled_range(
        &self,
        level: u8,
        node: [u32; 3],
        mut range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    ) -> Option<(u16, u16)> {
        let (_, coarser) = self.coarser_neighbours(level, node);
        let mut hull = range_of(level, node)?;
        for (l, n) in coarser {
            let (lo, hi) = range_of(l, n)?;
            hull = (hull.0.min(lo), hull.1.max(hi));
        }
        Some(hull)
    }
}

impl PageLookup for PageTable {
    fn page_dims(&self) -> [u32; 3] {
        self.page_dims
    }

    fn entry_at(&self, page: [u32; 3]) -> PageEntry {
        if (0..3).any(|a| page[a] >= self.page_dims[a]) {
            return PageEntry::NOT_RESIDENT;
        }
        self.get(page)
    }

    fn coarser_neighbours(&self, level: u8, node: [u32; 3]) -> (u32, Vec<(u8, [u32; 3])>) {
        coarser_neighbours(self, self.page_dims, level, node)
    }
}

/// A cut's page table as its leaves (see the module doc).
#[derive(Clone, Debug)]
pub struct SparsePageTable {
    page_dims: [u32; 3],
    /// Aligned blocks tiling the grid (cells no block covers are not resident), in the
    /// order given.
    leaves: Vec<CutLeaf>,
    /// (size, origin >> size) → index in `leaves`.
    index: HashMap<(u8, [u32; 3]), u32>,
    /// The largest block size present: a point query tries sizes 0..=this.
    max_size: u8,
}

impl PartialEq for SparsePageTable {
    /// Equal when every page cell holds the same entry given the same leaf list (the loader
    /// builds both sides from cuts in one order, so equal cuts give equal lists).
    fn eq(&self, other: &Self) -> bool {
        self.page_dims == other.page_dims && self.leaves == other.leaves
    }
}

impl SparsePageTable {
    /// The table `leaves` paint: each an aligned block of 2^size page cells from `origin`
    /// (origin a multiple of 2^size), holding `entry`. Blocks outside the grid are dropped;
    /// where blocks overlap, the later one is what a point query finds at its own size
    /// (the loader's blocks never overlap).
    pub fn from_leaves(page_dims: [u32; 3], leaves: Vec<CutLeaf>) -> Self {
        let leaves: Vec<CutLeaf> = leaves
            .into_iter()
            .filter(|l| (0..3).all(|a| l.origin[a] < page_dims[a]))
            .collect();
        let mut index = HashMap::with_capacity(leaves.len());
        let mut max_size = 0;
        for (i, l) in leaves.iter().enumerate() {
            index.insert((l.size, l.origin.map(|c| c >> l.size)), i as u32);
            max_size = max_size.max(l.size);
        }
        SparsePageTable {
            page_dims,
            leaves,
            index,
            max_size,
        }
    }

    /// One block covering the grid, holding `entry` (the loader's root-only first table).
    pub fn uniform(page_dims: [u32; 3], entry: PageEntry) -> Self {
        let max = page_dims.iter().copied().max().unwrap_or(1).max(1);
        let size = (32 - (max - 1).leading_zeros()) as u8;
        Self::from_leaves(
            page_dims,
            vec![CutLeaf {
                origin: [0; 3],
                size,
                entry,
            }],
        )
    }

    pub fn leaves(&self) -> &[CutLeaf] {
        &self.leaves
    }

    /// The leaf block holding `page`, if any.
    pub fn leaf_at(&self, page: [u32; 3]) -> Option<&CutLeaf> {
        if (0..3).any(|a| page[a] >= self.page_dims[a]) {
            return None;
        }
        (0..=self.max_size).find_map(|s| {
            self.index
                .get(&(s, page.map(|c| c >> s)))
                .map(|&i| &self.leaves[i as usize])
        })
    }

    /// Every page cell's entry, one per cell (tests, the f64 reference and the CPU passes
    /// over small grids; O(cells), so never on a large volume's frame path).
    pub fn to_dense(&self) -> PageTable {
        let mut table = PageTable::new(self.page_dims);
        for l in &self.leaves {
            let hi = |a: usize| {
                ((l.origin[a] as u64 + (1u64 << l.size)).min(self.page_dims[a] as u64)) as u32
            };
            for z in l.origin[2]..hi(2) {
                for y in l.origin[1]..hi(1) {
                    for x in l.origin[0]..hi(0) {
                        table.set([x, y, z], l.entry);
                    }
                }
            }
        }
        table
    }

    /// CPU bytes of the leaves and their index.
    pub fn cpu_bytes(&self) -> usize {
        self.leaves.capacity() * size_of::<CutLeaf>()
            + self.index.capacity() * (size_of::<((u8, [u32; 3]), u32)>() + 1)
    }
}

impl PageLookup for SparsePageTable {
    fn page_dims(&self) -> [u32; 3] {
        self.page_dims
    }

    fn entry_at(&self, page: [u32; 3]) -> PageEntry {
        self.leaf_at(page)
            .map_or(PageEntry::NOT_RESIDENT, |l| l.entry)
    }

    /// The dense table's answer from one cell per neighbouring block. The blocks are aligned
    /// and tile the grid, so the region beside the node in direction `o` (inside the
    /// level-`level` node next to it) is either inside one block of size ≥ `level`, whose
    /// cells all hold its entry, or split into smaller blocks, whose entries name levels
    /// ≤ `level` (a block's entry is its own node or, pending, its parent): either way its
    /// first cell tells whether a coarser node borders there and which.
    fn coarser_neighbours(&self, level: u8, node: [u32; 3]) -> (u32, Vec<(u8, [u32; 3])>) {
        let side = 1i64 << level;
        let mut mask = 0;
        let mut nodes = Vec::new();
        for o in neighbour_offsets() {
            let mut cell = [0u32; 3];
            let mut outside = false;
            for a in 0..3 {
                let c = node[a] as i64 * side + if o[a] == 1 { side } else { o[a] as i64 };
                outside |= c < 0 || c >= self.page_dims[a] as i64;
                cell[a] = c.max(0) as u32;
            }
            if outside {
                continue;
            }
            let e = self.entry_at(cell);
            if e.resident && e.level > level {
                mask |= 1 << neighbour_bit(o);
                let key = (e.level, PageTable::node_of(cell, e.level));
                if !nodes.contains(&key) {
                    nodes.push(key);
                }
            }
        }
        (mask, nodes)
    }
}

/// The CPU table a GPU index was prepared from: dense for the flat traversal (one entry per
/// page cell, which the flat buffers hold anyway), per leaf for the octree.
#[derive(Clone, Debug, PartialEq)]
pub enum IndexTable {
    Dense(PageTable),
    Sparse(SparsePageTable),
}

impl IndexTable {
    /// Every page cell's entry (a copy for the sparse table: see
    /// [`SparsePageTable::to_dense`]).
    pub fn to_page_table(&self) -> PageTable {
        match self {
            IndexTable::Dense(t) => t.clone(),
            IndexTable::Sparse(t) => t.to_dense(),
        }
    }

    /// The dense table, if this is one.
    pub fn dense(&self) -> Option<&PageTable> {
        match self {
            IndexTable::Dense(t) => Some(t),
            IndexTable::Sparse(_) => None,
        }
    }

    /// Each node a resident entry names, once: (level, node, slot in the cache).
    pub fn resident_nodes(&self) -> Vec<(u8, [u32; 3], u32)> {
        let mut seen = std::collections::HashSet::new();
        let mut out = Vec::new();
        let mut visit = |page: [u32; 3], e: &PageEntry| {
            if e.resident {
                let node = PageTable::node_of(page, e.level);
                if seen.insert((e.level, node)) {
                    out.push((e.level, node, e.slot_in_cache));
                }
            }
        };
        match self {
            IndexTable::Dense(t) => {
                for (i, e) in t.entries.iter().enumerate() {
                    visit(t.page_of_linear(i), e);
                }
            }
            IndexTable::Sparse(t) => {
                for l in &t.leaves {
                    visit(l.origin, &l.entry);
                }
            }
        }
        out
    }

    /// CPU bytes of the table.
    pub fn cpu_bytes(&self) -> usize {
        match self {
            IndexTable::Dense(t) => t.entries.capacity() * size_of::<PageEntry>(),
            IndexTable::Sparse(t) => t.cpu_bytes(),
        }
    }
}

impl PageLookup for IndexTable {
    fn page_dims(&self) -> [u32; 3] {
        match self {
            IndexTable::Dense(t) => t.page_dims,
            IndexTable::Sparse(t) => t.page_dims,
        }
    }

    fn entry_at(&self, page: [u32; 3]) -> PageEntry {
        match self {
            IndexTable::Dense(t) => t.entry_at(page),
            IndexTable::Sparse(t) => t.entry_at(page),
        }
    }

    fn coarser_neighbours(&self, level: u8, node: [u32; 3]) -> (u32, Vec<(u8, [u32; 3])>) {
        match self {
            IndexTable::Dense(t) => PageLookup::coarser_neighbours(t, level, node),
            IndexTable::Sparse(t) => t.coarser_neighbours(level, node),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::octree_cut::test_cuts::cuts;

    /// The cut's leaves of a dense table painted from aligned blocks: each cell's entry with
    /// the largest aligned block around it that holds that one entry and is no bigger than
    /// the node it names (what the loader paints: a leaf's block, its parent's entry).
    fn blocks_of(table: &PageTable) -> Vec<CutLeaf> {
        let mut covered = vec![false; table.entries.len()];
        let mut out = Vec::new();
        for i in 0..table.entries.len() {
            if covered[i] {
                continue;
            }
            let p = table.page_of_linear(i);
            let e = table.entries[i];
            let uniform = |s: u8| {
                let lo = p.map(|c| (c >> s) << s);
                (0..table.entries.len()).all(|j| {
                    let q = table.page_of_linear(j);
                    let inside = (0..3).all(|a| q[a] >= lo[a] && q[a] < lo[a] + (1 << s));
                    !inside || table.entries[j] == e
                })
            };
            let mut s = 0;
            while s < 15 && uniform(s + 1) && (s < e.level || !e.resident) {
                s += 1;
            }
            let lo = p.map(|c| (c >> s) << s);
            for (j, c) in covered.iter_mut().enumerate() {
                let q = table.page_of_linear(j);
                if (0..3).all(|a| q[a] >= lo[a] && q[a] < lo[a] + (1 << s)) {
                    *c = true;
                }
            }
            out.push(CutLeaf {
                origin: lo,
                size: s,
                entry: e,
            });
        }
        out
    }

    #[test]
    fn the_sparse_table_answers_every_query_as_the_dense_one() {
        for (name, dense) in cuts() {
            let sparse = SparsePageTable::from_leaves(dense.page_dims, blocks_of(&dense));
            assert_eq!(sparse.to_dense(), dense, "{name}: painted back");
            for i in 0..dense.entries.len() {
                let p = dense.page_of_linear(i);
                assert_eq!(sparse.entry_at(p), dense.entries[i], "{name}: page {p:?}");
            }
            // Every node any cell names, at every level: the neighbour answers agree.
            let max = dense.page_dims.iter().copied().max().unwrap();
            let levels = 32 - (max - 1).leading_zeros();
            for level in 0..=levels as u8 {
                let n = dense.page_dims.map(|d| d.div_ceil(1 << level));
                for z in 0..n[2] {
                    for y in 0..n[1] {
                        for x in 0..n[0] {
                            let node = [x, y, z];
                            let mut want = PageLookup::coarser_neighbours(&dense, level, node);
                            let mut got = sparse.coarser_neighbours(level, node);
                            want.1.sort_unstable();
                            got.1.sort_unstable();
                            assert_eq!(got, want, "{name}: node {node:?} at level {level}");
                        }
                    }
                }
            }
            let index = IndexTable::Sparse(sparse.clone());
            let mut a = index.resident_nodes();
            let mut b = IndexTable::Dense(dense.clone()).resident_nodes();
            a.sort_unstable();
            b.sort_unstable();
            assert_eq!(a, b, "{name}: resident nodes");
        }
    }

    #[test]
    fn a_uniform_table_covers_an_odd_grid_and_nothing_outside() {
        let t = SparsePageTable::uniform([5, 3, 9], PageEntry::resident(0, 4));
        assert_eq!(t.entry_at([4, 2, 8]), PageEntry::resident(0, 4));
        assert_eq!(t.entry_at([5, 0, 0]), PageEntry::NOT_RESIDENT);
        assert!(t.to_dense().entries.iter().all(|e| e.resident));
        assert!(t.cpu_bytes() < 1024, "{}", t.cpu_bytes());
    }
}
