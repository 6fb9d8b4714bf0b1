//! The cut as an octree with neighbour pointers ("ropes", octree paper §5.1-5.2), built from the
//! page table the loader gives render: the CPU half of the octree traversal. gpu_octree.rs
//! encodes it into the GPU node buffer that shaders/octree.wgsl traverses; this module fixes
//! the node layout, the ropes and the traversal order the GPU reproduces, with the brute-force
//! checks that define them (render/tests/octree_traversal.rs runs the GPU walk against them).
//!
//! - **Nodes**: an aligned block of 2^size page cells per axis. A block whose cells (those inside
//!   the page grid) all hold one entry is a leaf carrying that entry: a whole node of the cut,
//!   an all-not-resident block, or a piece of a parent standing in for some of its children.
//!   Any other block is an inner node with 8 children (x fastest; children wholly outside the
//!   grid are [`NULL`]).
//! - **Ropes**: per leaf and face (−x, +x, −y, +y, −z, +z), the node adjacent across that face
//!   with the same size, or, where the tree is coarser there, the leaf covering that whole
//!   neighbourhood; [`NULL`] on the volume's faces. A ray leaving a leaf follows the rope of its
//!   exit face and descends from there to the leaf holding the exit point: no stack, no restart
//!   from the root.
//! - **Point query** ([`OctreeCut::leaf_at`]): descend from the root; what smooth transitions
//!   need for edge and corner neighbours, which face ropes do not reach.
//! - **Tie-breaking**: a point on a face between two nodes belongs to the one the ray moves
//!   into (half-open in the ray's direction per axis), so a ray through an edge or a corner goes
//!   straight to the diagonal leaf and never visits a leaf for zero length, as the DDA over the
//!   page grid does.

use crate::model::page_table::{PageEntry, PageTable};

/// No node: outside the volume (ropes) or a child wholly outside the page grid.
pub const NULL: u32 = u32::MAX;

#[derive(Clone, Debug, PartialEq)]
pub enum NodeKind {
    /// Children in x-fastest order (bit 0: +x half, bit 1: +y, bit 2: +z).
    Inner { children: [u32; 8] },
    /// The entry every cell of the block holds, and the ropes (−x, +x, −y, +y, −z, +z).
    Leaf { entry: PageEntry, ropes: [u32; 6] },
}

#[derive(Clone, Debug, PartialEq)]
pub struct OctreeNode {
    /// First page cell of the block.
    pub origin: [u32; 3],
    /// The block spans 2^size cells per axis.
    pub size: u8,
    pub kind: NodeKind,
}

impl OctreeNode {
    pub fn is_leaf(&self) -> bool {
        matches!(self.kind, NodeKind::Leaf { .. })
    }

    fn side(&self) -> u64 {
        1u64 << self.size
    }

    fn contains_cell(&self, cell: [u32; 3]) -> bool {
        (0..3).all(|a| {
            let lo = self.origin[a] as u64;
            (cell[a] as u64) >= lo && (cell[a] as u64) < lo + self.side()
        })
    }
}

/// A leaf the ray crosses for a positive length: node index and ray interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeafVisit {
    pub node: u32,
    pub t_enter: f64,
    pub t_exit: f64,
}

/// The cut's octree over the page grid (see the module doc). Node 0 is the root.
#[derive(Clone, Debug, PartialEq)]
pub struct OctreeCut {
    pub page_dims: [u32; 3],
    pub nodes: Vec<OctreeNode>,
}

/// One leaf of a cut as the loader hands it over: an aligned block of 2^size page cells
/// from `origin` holding `entry` (see [`OctreeCut::from_leaves`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CutLeaf {
    pub origin: [u32; 3],
    pub size: u8,
    pub entry: PageEntry,
}

/// Morton code of a page cell (x in the lowest bit of each triple, as the child order); page
/// grids have at most 2^15 cells per axis (layout.rs `LEVEL_MASK`), 21 bits are room enough.
fn morton(cell: [u32; 3]) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut x = (v as u64) & 0x1f_ffff;
        x = (x | x << 32) & 0x1f_0000_0000_ffff;
        x = (x | x << 16) & 0x1f_0000_ff00_00ff;
        x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
        x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
        x = (x | x << 2) & 0x1249_2492_4924_9249;
        x
    }
    spread(cell[0]) | spread(cell[1]) << 1 | spread(cell[2]) << 2
}

impl OctreeCut {
    /// Builds the tree and its ropes from `table`, O(cells · depth): every page cell as a
    /// one-cell leaf handed to [`OctreeCut::from_leaves`], which merges uniform blocks.
    pub fn from_page_table(table: &PageTable) -> Self {
        let cells: Vec<CutLeaf> = (0..table.entries.len())
            .map(|i| CutLeaf {
                origin: table.page_of_linear(i),
                size: 0,
                entry: table.entries[i],
            })
            .collect();
        Self::from_leaves(table.page_dims, cells)
    }

    /// Builds the tree and its ropes from the cut's leaves, O(leaves · depth) time and memory,
    /// whatever the page grid's size: each leaf an aligned block of 2^size page cells
    /// (a level-L node of the cut covers 2^L cells per axis from `coords << L`) with the entry
    /// its cells hold. Leaves must not overlap (the first in Morton order wins where they do);
    /// cells no leaf covers are not resident. A block whose cells all hold one entry becomes
    /// one leaf, so the tree equals the one of the dense page table the leaves paint.
    pub fn from_leaves(page_dims: [u32; 3], mut leaves: Vec<CutLeaf>) -> Self {
        let max = page_dims.iter().copied().max().unwrap_or(1).max(1);
        let root_size = (32 - (max - 1).leading_zeros()) as u8;
        let mut cut = OctreeCut {
            page_dims,
            nodes: Vec::with_capacity(leaves.len() * 8 / 7 + 1),
        };
        // Morton order (x fastest, as the children): a block's leaves are one run of it.
        leaves.retain(|l| (0..3).all(|a| l.origin[a] < page_dims[a]));
        leaves.sort_unstable_by_key(|l| morton(l.origin));
        cut.build(&leaves, [0; 3], root_size);
        let ropes: Vec<(usize, [u32; 6])> = (0..cut.nodes.len())
            .filter(|&i| cut.nodes[i].is_leaf())
            .map(|i| (i, std::array::from_fn(|face| cut.face_neighbour(i, face))))
            .collect();
        for (i, r) in ropes {
            if let NodeKind::Leaf { ropes, .. } = &mut cut.nodes[i].kind {
                *ropes = r;
            }
        }
        cut
    }

    /// The subtree of the block at `origin` of 2^size cells over `leaves` (the run of the
    /// Morton-sorted leaves inside the block), in pre-order; children that end up uniform
    /// leaves of one entry merge into their parent.
    fn build(&mut self, leaves: &[CutLeaf], origin: [u32; 3], size: u8) -> u32 {
        let index = self.nodes.len() as u32;
        let covering = leaves.first().filter(|l| l.size >= size || size == 0);
        if leaves.is_empty() || covering.is_some() {
            let entry = covering.map_or(PageEntry::NOT_RESIDENT, |l| l.entry);
            self.nodes.push(OctreeNode {
                origin,
                size,
                kind: NodeKind::Leaf {
                    entry,
                    ropes: [NULL; 6],
                },
            });
            return index;
        }
        self.nodes.push(OctreeNode {
            origin,
            size,
            kind: NodeKind::Inner {
                children: [NULL; 8],
            },
        });
        let dims = self.page_dims;
        let half = 1u32 << (size - 1);
        let child_span = 1u64 << (3 * (size as u32 - 1));
        let mut children = [NULL; 8];
        let mut rest = leaves;
        for (c, child) in children.iter_mut().enumerate() {
            let o: [u32; 3] =
                std::array::from_fn(|a| origin[a] + if c >> a & 1 == 1 { half } else { 0 });
            let end = morton(o) + child_span;
            let split = rest.partition_point(|l| morton(l.origin) < end);
            let (inside, after) = rest.split_at(split);
            rest = after;
            if (0..3).all(|a| o[a] < dims[a]) {
                *child = self.build(inside, o, size - 1);
            }
        }
        // Uniform children (all leaves, one entry) are one leaf: the dense table's rule.
        let mut entries =
            children
                .iter()
                .filter(|&&c| c != NULL)
                .map(|&c| match &self.nodes[c as usize].kind {
                    NodeKind::Leaf { entry, .. } => Some(*entry),
                    NodeKind::Inner { .. } => None,
                });
        let first = entries.next().flatten();
        let uniform = first.is_some() && entries.all(|e| e == first);
        if let (true, Some(entry)) = (uniform, first) {
            self.nodes.truncate(index as usize + 1);
            self.nodes[index as usize].kind = NodeKind::Leaf {
                entry,
                ropes: [NULL; 6],
            };
        } else {
            self.nodes[index as usize].kind = NodeKind::Inner { children };
        }
        index
    }

    /// CPU bytes of this tree (nodes; what the octree path holds per cut instead of a dense
    /// table's entry per page cell).
    pub fn cpu_bytes(&self) -> usize {
        self.nodes.len() * size_of::<OctreeNode>()
    }

    /// The rope of leaf `leaf` across `face` (see the module doc).
    fn face_neighbour(&self, leaf: usize, face: usize) -> u32 {
        let n = &self.nodes[leaf];
        let axis = face / 2;
        let side = n.side() as i64;
        let target = n.origin[axis] as i64 + if face % 2 == 1 { side } else { -1 };
        if target < 0 || target >= self.page_dims[axis] as i64 {
            return NULL;
        }
        let mut cell = n.origin;
        cell[axis] = target as u32;
        // Descend towards the cell across the face, no deeper than the leaf's own size.
        let mut at = 0u32;
        loop {
            let node = &self.nodes[at as usize];
            match &node.kind {
                NodeKind::Leaf { .. } => return at,
                NodeKind::Inner { .. } if node.size <= n.size => return at,
                NodeKind::Inner { children } => {
                    at = children[child_of(node, cell)];
                    if at == NULL {
                        return NULL;
                    }
                }
            }
        }
    }

    /// The leaf holding page cell `cell` (a point query from the root); None outside the grid.
    pub fn leaf_at(&self, cell: [u32; 3]) -> Option<u32> {
        if (0..3).any(|a| cell[a] >= self.page_dims[a]) {
            return None;
        }
        self.descend(0, cell)
    }

    fn descend(&self, mut at: u32, cell: [u32; 3]) -> Option<u32> {
        loop {
            let node = self.nodes.get(at as usize)?;
            match &node.kind {
                NodeKind::Leaf { .. } => return node.contains_cell(cell).then_some(at),
                NodeKind::Inner { children } => {
                    if !node.contains_cell(cell) {
                        return None;
                    }
                    at = children[child_of(node, cell)];
                    if at == NULL {
                        return None;
                    }
                }
            }
        }
    }

    /// Leaves, in the order a ray `o + t·d` (page-cell units: cell c spans [c, c+1) per axis)
    /// crosses them within [t0, t1] and the grid: stackless, the entry leaf by a point query,
    /// then ropes and descents from the rope's node. Visits of zero length are not reported.
    pub fn traverse(&self, o: [f64; 3], d: [f64; 3], t0: f64, t1: f64) -> Vec<LeafVisit> {
        let mut out = Vec::new();
        let grid = self.page_dims.map(|v| v as f64);
        let Some((mut t, t_end)) = slab(o, d, [0.0; 3], grid, t0, t1) else {
            return out;
        };
        let Some(mut at) = self.leaf_at(self.cell_on_ray(o, d, t)) else {
            return out;
        };
        // One visit per leaf at most; the bound also stops a malformed tree.
        for _ in 0..self.nodes.len() + 1 {
            let node = &self.nodes[at as usize];
            let lo = node.origin.map(|v| v as f64);
            let hi: [f64; 3] = std::array::from_fn(|a| (lo[a] + node.side() as f64).min(grid[a]));
            let (exit_t, exit_face) = exit_of(o, d, lo, hi);
            let t_exit = exit_t.min(t_end);
            if t_exit > t {
                out.push(LeafVisit {
                    node: at,
                    t_enter: t,
                    t_exit,
                });
            }
            if exit_t >= t_end {
                break;
            }
            let NodeKind::Leaf { ropes, .. } = &node.kind else {
                break;
            };
            let next = ropes[exit_face];
            if next == NULL {
                break;
            }
            t = exit_t;
            // The exit axis's cell is the one across the face, whatever f32/f64 rounding makes
            // of the exit point there; the other axes follow the point.
            let mut cell = self.cell_on_ray(o, d, t);
            let axis = exit_face / 2;
            cell[axis] = if exit_face % 2 == 1 {
                (node.origin[axis] as u64 + node.side()) as u32
            } else {
                node.origin[axis].wrapping_sub(1)
            };
            // Through an edge or a corner the ray moves into a diagonal neighbour, outside the
            // rope's node: only then does it query from the root.
            match self.descend(next, cell).or_else(|| self.leaf_at(cell)) {
                Some(n) => at = n,
                None => break,
            }
        }
        out
    }

    /// The cell a ray at `t` is in, moving forward: on a face it belongs to the cell the ray
    /// moves into (the tie-breaking of the module doc), clamped to the grid.
    fn cell_on_ray(&self, o: [f64; 3], d: [f64; 3], t: f64) -> [u32; 3] {
        std::array::from_fn(|a| {
            let p = o[a] + d[a] * t;
            let mut c = p.floor();
            if d[a] < 0.0 && p == c {
                c -= 1.0;
            }
            c.clamp(0.0, self.page_dims[a] as f64 - 1.0) as u32
        })
    }

    /// All leaves the ray crosses for a positive length, by testing every leaf: the ground
    /// truth [`OctreeCut::traverse`] is checked against.
    pub fn leaves_on_ray_brute_force(
        &self,
        o: [f64; 3],
        d: [f64; 3],
        t0: f64,
        t1: f64,
    ) -> Vec<LeafVisit> {
        let grid = self.page_dims.map(|v| v as f64);
        let mut out: Vec<LeafVisit> = (0..self.nodes.len())
            .filter(|&i| self.nodes[i].is_leaf())
            .filter_map(|i| {
                let n = &self.nodes[i];
                let lo = n.origin.map(|v| v as f64);
                let hi: [f64; 3] = std::array::from_fn(|a| (lo[a] + n.side() as f64).min(grid[a]));
                let (a, b) = slab(o, d, lo, hi, t0, t1)?;
                (b > a).then_some(LeafVisit {
                    node: i as u32,
                    t_enter: a,
                    t_exit: b,
                })
            })
            .collect();
        out.sort_by(|x, y| x.t_enter.total_cmp(&y.t_enter));
        out
    }
}

/// Child of inner `node` holding `cell` (x fastest).
fn child_of(node: &OctreeNode, cell: [u32; 3]) -> usize {
    let half = 1u32 << (node.size - 1);
    (0..3)
        .map(|a| (((cell[a] - node.origin[a]) >= half) as usize) << a)
        .sum()
}

/// The ray's interval inside the box [lo, hi] within [t0, t1]; None if it misses.
fn slab(
    o: [f64; 3],
    d: [f64; 3],
    lo: [f64; 3],
    hi: [f64; 3],
    t0: f64,
    t1: f64,
) -> Option<(f64, f64)> {
    let (mut a, mut b) = (t0, t1);
    for k in 0..3 {
        if d[k] == 0.0 {
            if o[k] < lo[k] || o[k] >= hi[k] {
                return None;
            }
        } else {
            let ta = (lo[k] - o[k]) / d[k];
            let tb = (hi[k] - o[k]) / d[k];
            a = a.max(ta.min(tb));
            b = b.min(ta.max(tb));
        }
    }
    (b >= a).then_some((a, b))
}

/// Where the ray leaves the box and through which face (−x, +x, −y, +y, −z, +z); ties go to the
/// lowest axis (the descent from the rope then lands in the diagonal leaf, see the module doc).
fn exit_of(o: [f64; 3], d: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> (f64, usize) {
    let mut best = (f64::INFINITY, 0);
    for k in 0..3 {
        if d[k] == 0.0 {
            continue;
        }
        let (bound, face) = if d[k] > 0.0 {
            (hi[k], 2 * k + 1)
        } else {
            (lo[k], 2 * k)
        };
        let t = (bound - o[k]) / d[k];
        if t < best.0 {
            best = (t, face);
        }
    }
    best
}

/// The random cuts and rays the traversal is tested on, shared by the CPU tests here and the
/// GPU walk's tests (render/tests/octree_traversal.rs).
#[cfg(any(test, feature = "test-probe"))]
// The loops' indices are page positions (page_of_linear) and face numbers, not just indices.
#[allow(clippy::needless_range_loop)]
pub mod test_cuts {
    use crate::model::page_table::{PageEntry, PageTable};

    pub struct Rng(pub u64);
    impl Rng {
        /// Uniform in [0, 1).
        pub fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// A random cut of a `dims` page grid as a page table: blocks split at random down to
    /// level 0, leaves resident with distinct slots, some not resident; with `balanced`, split
    /// further until face/edge/corner neighbours differ by at most one level (2:1).
    pub fn random_cut(rng: &mut Rng, dims: [u32; 3], balanced: bool) -> PageTable {
        let mut level = vec![0u8; dims.iter().map(|&d| d as usize).product()];
        let mut table = PageTable::new(dims);
        let max = dims.iter().copied().max().unwrap();
        let root = (32 - (max - 1).leading_zeros()) as u8;
        fn split(rng: &mut Rng, t: &PageTable, level: &mut [u8], origin: [u32; 3], size: u8) {
            if size == 0 || rng.uniform() < 0.35 {
                for i in 0..level.len() {
                    let p = t.page_of_linear(i);
                    if (0..3).all(|a| p[a] >= origin[a] && p[a] < origin[a] + (1 << size)) {
                        level[i] = size;
                    }
                }
                return;
            }
            let half = 1u32 << (size - 1);
            for c in 0..8usize {
                let o = std::array::from_fn(|a| origin[a] + if c >> a & 1 == 1 { half } else { 0 });
                if (0..3).all(|a| o[a] < t.page_dims[a]) {
                    split(rng, t, level, o, size - 1);
                }
            }
        }
        split(rng, &table, &mut level, [0; 3], root);
        if balanced {
            loop {
                let mut changed = false;
                for i in 0..level.len() {
                    let p = table.page_of_linear(i);
                    for o in crate::model::layout::neighbour_offsets() {
                        let q: [i64; 3] = std::array::from_fn(|a| p[a] as i64 + o[a] as i64);
                        if (0..3).any(|a| q[a] < 0 || q[a] >= dims[a] as i64) {
                            continue;
                        }
                        let j = table.linear(q.map(|v| v as u32));
                        if level[i] > level[j] + 1 {
                            // Split this coarse leaf one level: every cell of it drops a level.
                            let l = level[i];
                            let origin = p.map(|c| c >> l << l);
                            for k in 0..level.len() {
                                let r = table.page_of_linear(k);
                                if (0..3).all(|a| r[a] >= origin[a] && r[a] < origin[a] + (1 << l))
                                {
                                    level[k] = l - 1;
                                }
                            }
                            changed = true;
                        }
                    }
                }
                if !changed {
                    break;
                }
            }
        }
        let mut slots = std::collections::HashMap::new();
        let mut not_resident = std::collections::HashMap::new();
        for i in 0..level.len() {
            let p = table.page_of_linear(i);
            let l = level[i];
            let key = (l, p.map(|c| c >> l));
            let next = slots.len() as u32;
            let slot = *slots.entry(key).or_insert(next);
            let skip = *not_resident
                .entry(key)
                .or_insert_with(|| rng.uniform() < 0.2);
            table.entries[i] = if skip {
                PageEntry::NOT_RESIDENT
            } else {
                PageEntry::resident(slot, l)
            };
        }
        table
    }

    pub fn cuts() -> Vec<(String, PageTable)> {
        let mut rng = Rng(0x2545_f491_4f6c_dd1d);
        let mut out = Vec::new();
        for (k, dims) in [[8, 8, 8], [5, 7, 3], [16, 4, 9], [1, 1, 1], [2, 1, 3]]
            .into_iter()
            .enumerate()
        {
            for balanced in [false, true] {
                for n in 0..3 {
                    out.push((
                        format!("{dims:?} balanced {balanced} #{n} ({k})"),
                        random_cut(&mut rng, dims, balanced),
                    ));
                }
            }
        }
        out
    }

    /// Rays along the axes through cell centres and along cell faces and edges, diagonals
    /// through corners, random rays starting inside and outside.
    pub fn rays(dims: [u32; 3], rng: &mut Rng) -> Vec<([f64; 3], [f64; 3], f64, f64)> {
        let g = dims.map(|v| v as f64);
        let mut out = Vec::new();
        for axis in 0..3 {
            for sign in [1.0, -1.0] {
                for (u, v) in [(0.5, 0.5), (1.0, 0.5), (1.0, 1.0), (0.0, 0.0), (2.0, 1.0)] {
                    let mut o = [u, v, u];
                    o[(axis + 1) % 3] = u;
                    o[(axis + 2) % 3] = v;
                    o[axis] = if sign > 0.0 { -1.0 } else { g[axis] + 1.0 };
                    let mut d = [0.0; 3];
                    d[axis] = sign;
                    out.push((o, d, 0.0, f64::INFINITY));
                }
            }
        }
        // Through grid corners and edges: integer points on the diagonal.
        for &d in &[
            [1.0, 1.0, 1.0],
            [1.0, -1.0, 1.0],
            [-1.0, 1.0, 0.0],
            [1.0, 0.0, -1.0],
            [1.0, 2.0, 0.0],
        ] {
            out.push((
                [
                    0.0,
                    if d[1] < 0.0 { g[1] } else { 0.0 },
                    if d[2] < 0.0 { g[2] } else { 0.0 },
                ],
                d,
                0.0,
                f64::INFINITY,
            ));
            out.push(([1.0, 1.0, 1.0], d, -10.0, f64::INFINITY));
        }
        for _ in 0..60 {
            let inside = rng.uniform() < 0.5;
            let o: [f64; 3] = std::array::from_fn(|a| {
                if inside {
                    rng.uniform() * g[a]
                } else {
                    (rng.uniform() * 3.0 - 1.0) * g[a]
                }
            });
            let d: [f64; 3] = std::array::from_fn(|_| rng.uniform() * 2.0 - 1.0);
            let t1 = if rng.uniform() < 0.3 {
                rng.uniform() * 4.0
            } else {
                f64::INFINITY
            };
            out.push((o, d, 0.0, t1));
        }
        out
    }
}

#[cfg(test)]
// The loops' indices are page positions (page_of_linear) and face numbers, not just indices.
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::test_cuts::*;
    use super::*;

    /// The tree by the dense rule, written out independently: a block whose in-grid cells
    /// all hold one entry is a leaf, else 8 children (pre-order; NULL outside the grid).
    fn dense_reference(table: &PageTable) -> Vec<(OctreeNodeShape, Option<PageEntry>)> {
        fn build(
            t: &PageTable,
            origin: [u32; 3],
            size: u8,
            out: &mut Vec<(OctreeNodeShape, Option<PageEntry>)>,
        ) {
            let d = t.page_dims;
            let hi = |a: usize| ((origin[a] as u64 + (1u64 << size)).min(d[a] as u64)) as u32;
            let first = t.get(origin);
            let uniform = (origin[2]..hi(2)).all(|z| {
                (origin[1]..hi(1)).all(|y| (origin[0]..hi(0)).all(|x| t.get([x, y, z]) == first))
            });
            if uniform || size == 0 {
                out.push(((origin, size), Some(first)));
                return;
            }
            out.push(((origin, size), None));
            let half = 1u32 << (size - 1);
            for c in 0..8usize {
                let o: [u32; 3] =
                    std::array::from_fn(|a| origin[a] + if c >> a & 1 == 1 { half } else { 0 });
                if (0..3).all(|a| o[a] < d[a]) {
                    build(t, o, size - 1, out);
                }
            }
        }
        let max = table.page_dims.iter().copied().max().unwrap().max(1);
        let mut out = Vec::new();
        build(
            table,
            [0; 3],
            (32 - (max - 1).leading_zeros()) as u8,
            &mut out,
        );
        out
    }

    type OctreeNodeShape = ([u32; 3], u8);

    fn shape(cut: &OctreeCut) -> Vec<(OctreeNodeShape, Option<PageEntry>)> {
        cut.nodes
            .iter()
            .map(|n| {
                let entry = match &n.kind {
                    NodeKind::Leaf { entry, .. } => Some(*entry),
                    NodeKind::Inner { .. } => None,
                };
                ((n.origin, n.size), entry)
            })
            .collect()
    }

    /// The cut's resident nodes as leaves (one block per node, not per cell; not-resident
    /// cells left out, so the builder fills them): the loader's input.
    fn node_leaves(table: &PageTable) -> Vec<CutLeaf> {
        let mut seen = std::collections::HashSet::new();
        (0..table.entries.len())
            .filter_map(|i| {
                let e = table.entries[i];
                let node = PageTable::node_of(table.page_of_linear(i), e.level);
                (e.resident && seen.insert((e.level, node))).then(|| CutLeaf {
                    origin: node.map(|c| c << e.level),
                    size: e.level,
                    entry: e,
                })
            })
            .collect()
    }

    #[test]
    fn the_tree_from_the_cuts_leaves_equals_the_dense_tables() {
        for (name, table) in cuts() {
            let reference = dense_reference(&table);
            let from_cells = OctreeCut::from_page_table(&table);
            assert_eq!(shape(&from_cells), reference, "{name}: from the page table");
            let mut leaves = node_leaves(&table);
            // Any order: the builder sorts.
            leaves.reverse();
            let from_leaves = OctreeCut::from_leaves(table.page_dims, leaves);
            assert_eq!(from_leaves, from_cells, "{name}: from the cut's leaves");
        }
    }

    /// CPU memory of the octree path is O(cut): nodes per leaf bounded whatever the grid.
    #[test]
    fn the_trees_cpu_bytes_grow_with_the_leaves_not_the_grid() {
        for (name, table) in cuts() {
            let leaves = node_leaves(&table);
            let cut = OctreeCut::from_leaves(table.page_dims, leaves);
            let leaf_count = cut.nodes.iter().filter(|n| n.is_leaf()).count();
            // An octree has fewer inner nodes than leaves, except chains of one in-grid child
            // along a thin grid's edge (at most one per level).
            let depth = 16;
            assert!(
                cut.nodes.len() <= 2 * leaf_count + depth,
                "{name}: {} nodes for {leaf_count} leaves",
                cut.nodes.len()
            );
            assert!(cut.cpu_bytes() <= 64 * (2 * leaf_count + depth), "{name}");
        }
        // A 32768² × 1 grid with one coarse leaf holding it all: a handful of nodes, where
        // the dense table has a billion cells.
        let dims = [1 << 15, 1 << 15, 1];
        let cut = OctreeCut::from_leaves(
            dims,
            vec![CutLeaf {
                origin: [0; 3],
                size: 15,
                entry: PageEntry::resident(0, 15),
            }],
        );
        assert_eq!(cut.nodes.len(), 1);
        assert_eq!(cut.leaf_at([12345, 30000, 0]), Some(0));
    }

    #[test]
    fn leaves_tile_the_grid_and_carry_the_table() {
        for (name, table) in cuts() {
            let cut = OctreeCut::from_page_table(&table);
            for i in 0..table.entries.len() {
                let p = table.page_of_linear(i);
                let leaf = cut
                    .leaf_at(p)
                    .unwrap_or_else(|| panic!("{name}: no leaf at {p:?}"));
                let node = &cut.nodes[leaf as usize];
                let NodeKind::Leaf { entry, .. } = node.kind else {
                    panic!("{name}: leaf_at gave an inner node");
                };
                assert_eq!(entry, table.entries[i], "{name}: page {p:?}");
                // Exactly one leaf holds each cell.
                let holders = cut
                    .nodes
                    .iter()
                    .filter(|n| n.is_leaf() && n.contains_cell(p))
                    .count();
                assert_eq!(holders, 1, "{name}: page {p:?}");
            }
        }
    }

    #[test]
    fn ropes_point_at_the_same_size_or_coarser_face_neighbour_and_are_null_on_volume_faces() {
        for (name, table) in cuts() {
            let cut = OctreeCut::from_page_table(&table);
            for (i, n) in cut.nodes.iter().enumerate() {
                let NodeKind::Leaf { ropes, .. } = n.kind else {
                    continue;
                };
                for face in 0..6 {
                    let axis = face / 2;
                    let outside = if face % 2 == 1 {
                        n.origin[axis] as u64 + n.side() >= table.page_dims[axis] as u64
                    } else {
                        n.origin[axis] == 0
                    };
                    let rope = ropes[face];
                    if outside {
                        assert_eq!(
                            rope, NULL,
                            "{name}: leaf {i} face {face} on the volume face"
                        );
                        continue;
                    }
                    assert_ne!(rope, NULL, "{name}: leaf {i} face {face}");
                    let r = &cut.nodes[rope as usize];
                    // Same size, or a coarser leaf.
                    assert!(
                        r.size == n.size || (r.size > n.size && r.is_leaf()),
                        "{name}: leaf {i} face {face}: rope to {r:?}"
                    );
                    // It covers every cell across the face (within the grid), and nothing
                    // smaller would: it is where a ray leaving through that face descends from.
                    let target = if face % 2 == 1 {
                        n.origin[axis] as u64 + n.side()
                    } else {
                        n.origin[axis] as u64 - 1
                    } as u32;
                    let (a1, a2) = ((axis + 1) % 3, (axis + 2) % 3);
                    let span = |a: usize| {
                        n.origin[a]
                            ..(n.origin[a] as u64 + n.side()).min(table.page_dims[a] as u64) as u32
                    };
                    for u in span(a1) {
                        for v in span(a2) {
                            let mut cell = [0u32; 3];
                            cell[axis] = target;
                            cell[a1] = u;
                            cell[a2] = v;
                            assert!(
                                r.contains_cell(cell),
                                "{name}: leaf {i} face {face} misses {cell:?}"
                            );
                            // The leaf there is the rope or below it.
                            let leaf = cut.leaf_at(cell).unwrap();
                            assert_eq!(cut.descend(rope, cell), Some(leaf));
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn traversal_visits_the_brute_force_leaves_in_order() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        let mut visits = 0;
        for (name, table) in cuts() {
            let cut = OctreeCut::from_page_table(&table);
            for (o, d, t0, t1) in rays(table.page_dims, &mut rng) {
                let got = cut.traverse(o, d, t0, t1);
                let want = cut.leaves_on_ray_brute_force(o, d, t0, t1);
                let nodes = |v: &[LeafVisit]| v.iter().map(|x| x.node).collect::<Vec<_>>();
                assert_eq!(
                    nodes(&got),
                    nodes(&want),
                    "{name}: ray {o:?} + t {d:?} [{t0}, {t1}]"
                );
                for (g, w) in got.iter().zip(&want) {
                    assert!(
                        (g.t_enter - w.t_enter).abs() < 1e-9 && (g.t_exit - w.t_exit).abs() < 1e-9,
                        "{name}: {g:?} vs {w:?}"
                    );
                }
                visits += got.len();
            }
        }
        assert!(
            visits > 1000,
            "rays crossed too few leaves to prove much: {visits}"
        );
    }
}
