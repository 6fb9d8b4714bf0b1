//! The octree traversal's index on the GPU (octree paper §5.1): the cut's octree with ropes
//! ([`OctreeCut`], octree_cut.rs) encoded as one node buffer that `shaders/octree.wgsl` reads
//! (binding 12), plus what the flat table keeps per page cell kept per leaf: the MIP bound
//! (binding 9), the visibility word (binding 7) and the smooth-transition mask with its
//! near-side closure (binding 11; the leaf's word carries `FLAG_TRANSITION` as the flat
//! table's does). Every GPU buffer of the index grows with the cut (nodes and leaves), not
//! with the volume's page grid.
//!
//! Layout (layout.rs `OCTREE_*`): records of 8 u32. Record 0 is the header (word 0 the root's
//! reference, word 1 the leaf count); records 1..=leaves the leaves (leaf index = record − 1),
//! then the inner nodes. An inner record holds
//! its 8 children's references (x fastest; [`OCTREE_NULL`] outside the grid), a leaf record
//! its page word ([`PageEntry::encode`]), its 6 ropes (−x, +x, −y, +y, −z, +z, null on volume
//! faces) and its leaf index. A reference is `record | size << 27 | leaf bit`: the shader gets
//! every box from the cell it looks up and the size (no boxes in memory, as the paper's
//! level-tagged pointers).

use crate::error::RenderError;
use crate::model::layout::{
    FLAG_TRANSITION, OCTREE_ID_MASK, OCTREE_LEAF_BIT, OCTREE_NULL, OCTREE_RECORD_WORDS,
    OCTREE_SIZE_SHIFT,
};
use crate::model::octree_cut::{NodeKind, OctreeCut, NULL};
use crate::model::page_table::{physical_max_bound, PageTable};
use crate::model::smooth_transitions::near_side_closure;
use crate::model::sparse_page_table::PageLookup;
use strata_types::ValueMapping;

/// How the raycaster finds the data along a ray.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Traversal {
    /// The flat page table: one word per finest brick position (page_table.rs), node-extent
    /// exit. The default until the octree is proven on every path.
    #[default]
    Flat,
    /// The cut's octree with ropes (this module, octree.wgsl): index memory O(cut).
    Octree,
}

impl Traversal {
    pub fn name(self) -> &'static str {
        match self {
            Traversal::Flat => "flat",
            Traversal::Octree => "octree",
        }
    }
}

impl std::str::FromStr for Traversal {
    type Err = RenderError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "flat" => Ok(Traversal::Flat),
            "octree" => Ok(Traversal::Octree),
            other => Err(RenderError::InvalidSettings(format!(
                "traversal {other:?}: expected flat or octree"
            ))),
        }
    }
}

/// A leaf's block of page cells: 2^size per axis from `origin` (clipped to the grid).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LeafBox {
    pub origin: [u32; 3],
    pub size: u8,
}

/// A frame's per-leaf visibility words (non-zero: a sample in the leaf contributed) with the
/// leaves of the cut it was drawn with: the octree traversal's feedback, O(leaves).
#[derive(Clone, Debug, PartialEq)]
pub struct LeafVisibility {
    pub leaves: std::sync::Arc<OctreeLeaves>,
    pub marks: Vec<u32>,
}

/// The leaves of one encoded cut, in leaf-index order: what a per-leaf word covers.
#[derive(Clone, Debug, PartialEq)]
pub struct OctreeLeaves {
    pub page_dims: [u32; 3],
    pub boxes: Vec<LeafBox>,
}

impl OctreeLeaves {
    fn cells(&self, b: LeafBox) -> impl Iterator<Item = usize> + '_ {
        let d = self.page_dims;
        let hi = move |a: usize| ((b.origin[a] as u64 + (1u64 << b.size)).min(d[a] as u64)) as u32;
        (b.origin[2]..hi(2)).flat_map(move |z| {
            (b.origin[1]..hi(1)).flat_map(move |y| {
                (b.origin[0]..hi(0)).map(move |x| {
                    x as usize + d[0] as usize * (y as usize + d[1] as usize * z as usize)
                })
            })
        })
    }

    /// Per page cell, the word of the leaf holding it (a per-leaf visibility buffer read
    /// back as the per-page one the loader speaks). `per_leaf` shorter than the leaf list
    /// reads as 0 for the missing leaves.
    pub fn expand_to_pages(&self, per_leaf: &[u32]) -> Vec<u32> {
        let n: usize = self.page_dims.iter().map(|&d| d as usize).product();
        let mut out = vec![0u32; n];
        for (i, &b) in self.boxes.iter().enumerate() {
            let v = per_leaf.get(i).copied().unwrap_or(0);
            if v != 0 {
                for c in self.cells(b) {
                    out[c] = v;
                }
            }
        }
        out
    }

    /// Per leaf, the union of the per-page bit masks over its cells (the cells of a leaf share
    /// one entry, hence one node and one transition mask; the union is the safe choice should
    /// they not). Missing pages read as 0.
    pub fn reduce_or(&self, per_page: &[u32]) -> Vec<u32> {
        self.boxes
            .iter()
            .map(|&b| {
                self.cells(b)
                    .map(|c| per_page.get(c).copied().unwrap_or(0))
                    .fold(0, |a, m| a | m)
            })
            .collect()
    }

    /// Per leaf, the largest per-page bound over its cells (the cells of a leaf share one
    /// entry, so one bound; the maximum is the safe choice should they not). Missing pages
    /// read as +inf (never skip).
    pub fn reduce_max(&self, per_page: &[f32]) -> Vec<f32> {
        self.boxes
            .iter()
            .map(|&b| {
                self.cells(b)
                    .map(|c| per_page.get(c).copied().unwrap_or(f32::INFINITY))
                    .fold(f32::NEG_INFINITY, f32::max)
            })
            .collect()
    }
}

/// The node buffer's words for `cut` (see the module doc), its leaves in index order, and per
/// record the cut's node it holds (record 0, the header: [`NULL`]). Leaves take records
/// 1..=leaves in the cut's order, so a leaf's index is its record − 1 and the shader reads no
/// index word; inner nodes follow.
pub fn encode_node_buffer(
    cut: &OctreeCut,
    slots_per_axis: [u32; 3],
) -> Result<(Vec<u32>, OctreeLeaves, Vec<u32>), RenderError> {
    if cut.nodes.len() as u64 + 1 > OCTREE_ID_MASK as u64 {
        return Err(RenderError::PageTableMismatch(format!(
            "{} octree nodes exceed the node buffer's {} addressable records",
            cut.nodes.len(),
            OCTREE_ID_MASK
        )));
    }
    let leaf_count = cut.nodes.iter().filter(|n| n.is_leaf()).count() as u32;
    let mut record_of = vec![0u32; cut.nodes.len()];
    let mut node_of_record = vec![NULL; cut.nodes.len() + 1];
    let (mut next_leaf, mut next_inner) = (1u32, leaf_count + 1);
    for (i, n) in cut.nodes.iter().enumerate() {
        let r = if n.is_leaf() {
            next_leaf += 1;
            next_leaf - 1
        } else {
            next_inner += 1;
            next_inner - 1
        };
        record_of[i] = r;
        node_of_record[r as usize] = i as u32;
    }
    let reference = |i: u32| -> u32 {
        if i == NULL {
            return OCTREE_NULL;
        }
        let n = &cut.nodes[i as usize];
        let leaf = if n.is_leaf() { OCTREE_LEAF_BIT } else { 0 };
        record_of[i as usize] | ((n.size as u32) << OCTREE_SIZE_SHIFT) | leaf
    };
    let w = OCTREE_RECORD_WORDS as usize;
    let mut words = vec![0u32; (cut.nodes.len() + 1) * w];
    let mut boxes = vec![
        LeafBox {
            origin: [0; 3],
            size: 0
        };
        leaf_count as usize
    ];
    for (i, n) in cut.nodes.iter().enumerate() {
        let r = record_of[i] as usize;
        let rec = &mut words[r * w..(r + 1) * w];
        match &n.kind {
            NodeKind::Inner { children } => {
                for (slot, &c) in rec.iter_mut().zip(children) {
                    *slot = reference(c);
                }
            }
            NodeKind::Leaf { entry, ropes } => {
                rec[0] = entry.encode(slots_per_axis);
                for (slot, &r) in rec[1..7].iter_mut().zip(ropes) {
                    *slot = reference(r);
                }
                rec[7] = (r - 1) as u32;
                boxes[r - 1] = LeafBox {
                    origin: n.origin,
                    size: n.size,
                };
            }
        }
    }
    words[0] = if cut.nodes.is_empty() {
        OCTREE_NULL
    } else {
        reference(0)
    };
    words[1] = leaf_count;
    Ok((
        words,
        OctreeLeaves {
            page_dims: cut.page_dims,
            boxes,
        },
        node_of_record,
    ))
}

/// Per leaf, [transition mask, near-side closure] of its node from the table's per-page
/// `transition_masks` (smooth_transitions.rs), and `FLAG_TRANSITION` set on the page word of
/// every leaf with a mask in the node buffer `words` (as `PageTable::encoded_for_gpu` sets it
/// on the flat table's words): the shader reads a leaf's mask only then.
pub fn per_leaf_transitions(
    words: &mut [u32],
    leaves: &OctreeLeaves,
    transition_masks: &[u32],
) -> Vec<[u32; 2]> {
    flag_leaf_transitions(words, &leaves.reduce_or(transition_masks))
}

/// [`per_leaf_transitions`] from masks already per leaf (in leaf-index order).
fn flag_leaf_transitions(words: &mut [u32], masks: &[u32]) -> Vec<[u32; 2]> {
    let w = OCTREE_RECORD_WORDS as usize;
    for (leaf, &m) in masks.iter().enumerate() {
        if m != 0 {
            // Leaf `leaf` is record leaf + 1; its page word is the record's first.
            words[(leaf + 1) * w] |= FLAG_TRANSITION;
        }
    }
    masks.iter().map(|&m| [m, near_side_closure(m)]).collect()
}

/// Per leaf of `leaves`, the 26-neighbour mask of coarser neighbours of the node its entry
/// names (0 for a leaf that is not resident), each node's mask computed once: per leaf, not
/// per page cell (`smooth_transitions::transition_masks` is the per-page twin).
pub fn leaf_transition_masks(table: &impl PageLookup, leaves: &OctreeLeaves) -> Vec<u32> {
    let mut memo: std::collections::HashMap<(u8, [u32; 3]), u32> = Default::default();
    leaves
        .boxes
        .iter()
        .map(|b| {
            let e = table.entry_at(b.origin);
            if !e.resident {
                return 0;
            }
            let node = PageTable::node_of(b.origin, e.level);
            *memo
                .entry((e.level, node))
                .or_insert_with(|| table.coarser_neighbours(e.level, node).0)
        })
        .collect()
}

/// Per leaf, the largest physical value a sample in it can take (its node's range widened by
/// the coarser neighbours a transition band blends in, as `PageTable::value_max_physical`
/// gives per page cell; +inf where not resident or unknown): one computation per leaf.
pub fn leaf_value_max(
    table: &impl PageLookup,
    leaves: &OctreeLeaves,
    mapping: ValueMapping,
    mut range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
) -> Vec<f32> {
    let mut memo: std::collections::HashMap<(u8, [u32; 3]), f32> = Default::default();
    leaves
        .boxes
        .iter()
        .map(|b| {
            let e = table.entry_at(b.origin);
            if !e.resident {
                return f32::INFINITY;
            }
            let node = PageTable::node_of(b.origin, e.level);
            *memo.entry((e.level, node)).or_insert_with(|| {
                table
                    .sampled_range(e.level, node, &mut range_of)
                    .map_or(f32::INFINITY, |r| physical_max_bound(r, mapping))
            })
        })
        .collect()
}

/// The octree index of one cut encoded on the CPU, on any thread (the loader's selection
/// thread): the node buffer's words with `FLAG_TRANSITION` on the leaves that have a mask,
/// the leaves, and per leaf [transition mask, near-side closure]. Everything here is O(cut).
#[derive(Clone, Debug)]
pub struct EncodedOctree {
    pub words: Vec<u32>,
    pub leaves: std::sync::Arc<OctreeLeaves>,
    pub transitions: Vec<[u32; 2]>,
    /// Share of resident nodes with a coarser neighbour (`transition_node_fraction`'s).
    pub transition_fraction: f64,
}

impl EncodedOctree {
    /// Encodes `cut`, whose leaves hold `table`'s entries (the table answers the transition
    /// masks' neighbour queries, once per leaf).
    pub fn new(
        cut: &OctreeCut,
        table: &impl PageLookup,
        slots_per_axis: [u32; 3],
    ) -> Result<Self, RenderError> {
        let (mut words, leaves, _) = encode_node_buffer(cut, slots_per_axis)?;
        let masks = leaf_transition_masks(table, &leaves);
        let transitions = flag_leaf_transitions(&mut words, &masks);
        let mut nodes = std::collections::HashSet::new();
        let mut transition = std::collections::HashSet::new();
        for (b, &m) in leaves.boxes.iter().zip(&masks) {
            let e = table.entry_at(b.origin);
            if e.resident {
                let key = (e.level, PageTable::node_of(b.origin, e.level));
                nodes.insert(key);
                if m != 0 {
                    transition.insert(key);
                }
            }
        }
        let transition_fraction = if nodes.is_empty() {
            0.0
        } else {
            transition.len() as f64 / nodes.len() as f64
        };
        Ok(EncodedOctree {
            words,
            leaves: std::sync::Arc::new(leaves),
            transitions,
            transition_fraction,
        })
    }

    /// CPU bytes of the encoded index: node words, leaf boxes, per-leaf transitions.
    pub fn cpu_bytes(&self) -> usize {
        self.words.len() * 4
            + self.leaves.boxes.len() * size_of::<LeafBox>()
            + self.transitions.len() * 8
    }
}

/// The node buffer, the per-leaf MIP bounds and transition masks on the GPU, grown (recreated)
/// when a cut needs more than they hold; the leaves of the cut last written.
pub(crate) struct GpuOctreeIndex {
    pub(crate) nodes: wgpu::Buffer,
    pub(crate) leaf_value_max: wgpu::Buffer,
    /// Per leaf, [transition mask, near-side closure] of its node (smooth_transitions.rs), as
    /// the flat table's binding 11 holds them per page cell.
    pub(crate) leaf_transitions: wgpu::Buffer,
    pub(crate) leaves: std::sync::Arc<OctreeLeaves>,
    /// Words of the cut last written (the GPU bytes of the index are these, not the capacity).
    pub(crate) node_words: usize,
    /// The root's reference (header word 0), passed to the shader in the parameters.
    pub(crate) root: u32,
    /// The per-page bounds last given ([`crate::GpuPageTable::update_value_max`]), reduced per
    /// leaf whenever the cut changes (CPU memory only).
    page_bounds: Vec<f32>,
}

impl GpuOctreeIndex {
    pub(crate) fn new(device: &wgpu::Device, page_dims: [u32; 3]) -> Self {
        GpuOctreeIndex {
            nodes: node_buffer(device, OCTREE_RECORD_WORDS as u64 * 4),
            leaf_value_max: leaf_buffer(device, 4),
            leaf_transitions: transition_buffer(device, 8),
            leaves: std::sync::Arc::new(OctreeLeaves {
                page_dims,
                boxes: Vec::new(),
            }),
            node_words: 0,
            root: OCTREE_NULL,
            page_bounds: Vec::new(),
        }
    }

    /// Writes an encoded cut: its node buffer, per-leaf transition masks, and per-leaf
    /// bounds reduced from the per-page bounds last given (+inf without them, until
    /// [`GpuOctreeIndex::update_leaf_value_max`]).
    pub(crate) fn write_encoded(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoded: &EncodedOctree,
    ) {
        let EncodedOctree {
            words,
            leaves,
            transitions,
            ..
        } = encoded;
        let transition_bytes = (transitions.len().max(1) * 8) as u64;
        if self.leaf_transitions.size() < transition_bytes {
            self.leaf_transitions = transition_buffer(device, transition_bytes.next_power_of_two());
        }
        if !transitions.is_empty() {
            queue.write_buffer(&self.leaf_transitions, 0, bytemuck::cast_slice(transitions));
        }
        self.root = words[0];
        let bytes = (words.len() * 4) as u64;
        if self.nodes.size() < bytes {
            self.nodes = node_buffer(device, bytes.next_power_of_two());
        }
        queue.write_buffer(&self.nodes, 0, bytemuck::cast_slice(words));
        self.node_words = words.len();
        self.leaves = leaves.clone();
        self.write_bounds(device, queue);
    }

    /// Per-leaf MIP bounds for the cut last written ([`leaf_value_max`]), in leaf order.
    pub(crate) fn update_leaf_value_max(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        per_leaf: &[f32],
    ) -> Result<(), RenderError> {
        if per_leaf.len() != self.leaves.boxes.len() {
            return Err(RenderError::PageTableMismatch(format!(
                "{} value bounds for {} octree leaves",
                per_leaf.len(),
                self.leaves.boxes.len()
            )));
        }
        // Per-page bounds no longer describe the cut: a later cut starts unskipped (+inf).
        self.page_bounds.clear();
        self.write_leaf_bounds(device, queue, per_leaf);
        Ok(())
    }

    pub(crate) fn update_value_max(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        bounds: &[f32],
    ) {
        self.page_bounds.clear();
        self.page_bounds.extend_from_slice(bounds);
        self.write_bounds(device, queue);
    }

    fn write_bounds(&mut self, device: &wgpu::Device, queue: &wgpu::Queue) {
        // Without per-page bounds every leaf is +inf: no walk over its cells (a coarse leaf
        // of a 16384³ volume has 134 M of them; the loader gives per-leaf bounds next).
        let per_leaf = if self.page_bounds.is_empty() {
            vec![f32::INFINITY; self.leaves.boxes.len()]
        } else {
            self.leaves.reduce_max(&self.page_bounds)
        };
        self.write_leaf_bounds(device, queue, &per_leaf);
    }

    fn write_leaf_bounds(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, per_leaf: &[f32]) {
        let bytes = (per_leaf.len().max(1) * 4) as u64;
        if self.leaf_value_max.size() < bytes {
            self.leaf_value_max = leaf_buffer(device, bytes.next_power_of_two());
        }
        if !per_leaf.is_empty() {
            queue.write_buffer(&self.leaf_value_max, 0, bytemuck::cast_slice(per_leaf));
        }
    }

    /// GPU bytes of the index as written: node buffer, per-leaf MIP bounds and transition
    /// masks (the per-leaf visibility words are the raycaster's, one u32 per leaf more).
    pub(crate) fn bytes(&self) -> u64 {
        (self.node_words * 4 + self.leaves.boxes.len() * 12) as u64
    }
}

fn node_buffer(device: &wgpu::Device, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("octree nodes"),
        size,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

fn transition_buffer(device: &wgpu::Device, size: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("leaf transitions"),
        size,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

fn leaf_buffer(device: &wgpu::Device, size: u64) -> wgpu::Buffer {
    // Starts at +inf: a leaf without a bound is never skipped by MIP.
    wgpu::util::DeviceExt::create_buffer_init(
        device,
        &wgpu::util::BufferInitDescriptor {
            label: Some("leaf value max"),
            contents: bytemuck::cast_slice(&vec![f32::INFINITY; (size / 4) as usize]),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::page_table::PageEntry;

    /// The record of the leaf holding `cell`, by the GPU's descent rule (bit at the child
    /// size).
    fn leaf_record(words: &[u32], cell: [u32; 3]) -> usize {
        let w = OCTREE_RECORD_WORDS as usize;
        let mut r = words[0];
        while r & OCTREE_LEAF_BIT == 0 {
            let size = (r >> OCTREE_SIZE_SHIFT) & 15;
            let base = (r & OCTREE_ID_MASK) as usize * w;
            let bit = cell.map(|c| (c >> (size - 1)) & 1);
            r = words[base + (bit[0] + 2 * bit[1] + 4 * bit[2]) as usize];
            assert_ne!(r, OCTREE_NULL);
        }
        (r & OCTREE_ID_MASK) as usize
    }

    #[test]
    fn node_buffer_references_match_the_cut() {
        let mut table = PageTable::new([3, 2, 2]);
        for i in 0..table.entries.len() {
            table.entries[i] = PageEntry::resident(i as u32, 0);
        }
        table.entries[5] = PageEntry::NOT_RESIDENT;
        let cut = OctreeCut::from_page_table(&table);
        let (words, leaves, node_of_record) = encode_node_buffer(&cut, [16, 1, 1]).unwrap();
        let w = OCTREE_RECORD_WORDS as usize;
        assert_eq!(words.len(), (cut.nodes.len() + 1) * w);
        assert_eq!(words[1] as usize, leaves.boxes.len());
        // Every cell's leaf found by the GPU's descent rule (bit at the child size) holds the
        // table's entry.
        for i in 0..table.entries.len() {
            let cell = table.page_of_linear(i);
            let record = leaf_record(&words, cell);
            let base = record * w;
            assert_eq!(words[base], table.entries[i].encode([16, 1, 1]));
            let leaf = words[base + 7] as usize;
            assert_eq!(leaf, record - 1, "leaf index = record - 1");
            assert!(cut.nodes[node_of_record[leaf + 1] as usize].is_leaf());
            let b = leaves.boxes[leaf];
            assert!((0..3).all(|a| cell[a] >> b.size == b.origin[a] >> b.size));
        }
        // Per-leaf words expand back to their cells; bounds reduce per leaf.
        let ones = vec![1u32; leaves.boxes.len()];
        assert_eq!(leaves.expand_to_pages(&ones), vec![1; 12]);
        let bounds: Vec<f32> = (0..12).map(|i| i as f32).collect();
        let per_leaf = leaves.reduce_max(&bounds);
        for (b, m) in leaves.boxes.iter().zip(per_leaf) {
            let i = table.linear(b.origin);
            assert!(m >= bounds[i]);
        }
    }

    #[test]
    fn leaves_carry_their_nodes_transition_masks_and_flags() {
        use crate::model::smooth_transitions::transition_masks;
        // 4×4×4 pages: a level-1 block in the far half (x ≥ 2), level 0 elsewhere, one level-1
        // parent standing in for its children at (0, 2, 2)'s node (cell (1, 3, 3) only), a
        // not-resident corner: faces, edges and corners of coarser nodes, leaves of one cell
        // and of eight.
        let mut table = PageTable::new([4, 4, 4]);
        for i in 0..table.entries.len() {
            let p = table.page_of_linear(i);
            let level = u8::from(p[0] >= 2 || p == [1, 3, 3]);
            let node = PageTable::node_of(p, level);
            let slot = node[0] + 4 * (node[1] + 4 * node[2]) + 64 * level as u32;
            table.entries[i] = PageEntry::resident(slot, level);
        }
        let corner = table.linear([0, 0, 3]);
        table.entries[corner] = PageEntry::NOT_RESIDENT;
        let masks = transition_masks(&table);
        assert!(masks.iter().filter(|&&m| m != 0).count() > 8);
        let slots = [128, 1, 1];
        let flat = table.encoded_for_gpu(slots, &masks);
        let cut = OctreeCut::from_page_table(&table);
        let (mut words, leaves, _) = encode_node_buffer(&cut, slots).unwrap();
        assert!(leaves.boxes.iter().any(|b| b.size > 0), "no coarse leaf");
        let transitions = per_leaf_transitions(&mut words, &leaves, &masks);
        assert_eq!(transitions.len(), leaves.boxes.len());
        let w = OCTREE_RECORD_WORDS as usize;
        for (i, &mask) in masks.iter().enumerate() {
            let cell = table.page_of_linear(i);
            let record = leaf_record(&words, cell);
            let word = words[record * w];
            // The flat table's transition bit, and the leaf's entry otherwise untouched.
            assert_eq!(
                word & FLAG_TRANSITION,
                flat[i] & FLAG_TRANSITION,
                "{cell:?}"
            );
            assert_eq!(word & !FLAG_TRANSITION, table.entries[i].encode(slots));
            assert_eq!(
                transitions[record - 1],
                [mask, near_side_closure(mask)],
                "{cell:?}"
            );
        }
    }
}
