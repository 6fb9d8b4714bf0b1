// The octree traversal's index (octree paper §5.1-5.2): the cut's octree with ropes, as
// gpu_octree.rs encodes octree_cut.rs's tree into binding 12 (layout.rs OCTREE_*). Records of
// OCTREE_RECORD_WORDS u32: record 0 the header (word 0 the root's reference), records
// 1..=leaves the leaves [page word, 6 ropes, leaf index = record - 1], then the inner records
// (8 child references, x fastest).
// A reference carries the node's size, so a node's box is the looked-up cell snapped to its
// size grid: nothing but references is read (the paper's boxes computed on the fly).
// This file needs nothing but the prelude; the raycaster (raycast.wgsl) and the test-only leaf
// walk (octree_walk.wgsl) use it.

@group(0) @binding(12) var<storage, read> octree: array<u32>;

// Node-buffer words read by this invocation: the index reads the debug counter reports.
var<private> octree_reads: u32 = 0u;

// A leaf found by a descent: its record, its leaf index, its page word, its box (first page
// cell, 2^size cells per axis). `found` is false for a cell outside the tree.
struct OctreeLeaf {
    found: bool,
    record: u32,
    index: u32,
    word: u32,
    origin: vec3<u32>,
    size: u32,
};

fn octree_ref_size(r: u32) -> u32 {
    return (r >> OCTREE_SIZE_SHIFT) & 15u;
}

// Descends from the node referenced by `start` (which must contain `cell`) to the leaf holding
// `cell`: per level one child reference, picked by the cell's bit at the child size (the
// paper's step(P, box_mid): nodes are aligned blocks).
fn octree_descend(start: u32, cell: vec3<u32>) -> OctreeLeaf {
    var leaf: OctreeLeaf;
    leaf.found = false;
    var r = start;
    for (var depth = 0u; depth < 17u; depth++) {
        if r == OCTREE_NULL {
            return leaf;
        }
        let size = octree_ref_size(r);
        let base = (r & OCTREE_ID_MASK) * OCTREE_RECORD_WORDS;
        if (r & OCTREE_LEAF_BIT) != 0u {
            leaf.found = true;
            leaf.record = r & OCTREE_ID_MASK;
            leaf.size = size;
            leaf.origin = (cell >> vec3<u32>(size)) << vec3<u32>(size);
            leaf.word = octree[base];
            // Leaves take records 1..=leaves (gpu_octree.rs): the index costs no read.
            leaf.index = (r & OCTREE_ID_MASK) - 1u;
            octree_reads += 1u;
            return leaf;
        }
        if size == 0u {
            return leaf;
        }
        let bit = (cell >> vec3<u32>(size - 1u)) & vec3<u32>(1u);
        r = octree[base + bit.x + 2u * bit.y + 4u * bit.z];
        octree_reads += 1u;
    }
    return leaf;
}

// The point query: the leaf holding page cell `cell`, from the root (its reference `root`:
// the raycaster has it in its parameters, the header holds it too).
fn octree_leaf_at(root: u32, cell: vec3<u32>) -> OctreeLeaf {
    return octree_descend(root, cell);
}

// The leaf holding `cell`, coming from leaf `prev` (`cell` outside it): across one face, the
// rope of that face and a descent from the rope's node; through an edge or a corner (or a
// jump past more than one leaf) a point query from the root. The rope's node covers the
// face's far side: its box is the cell across the face snapped to the rope's size.
fn octree_next_leaf(root: u32, prev: OctreeLeaf, cell: vec3<u32>) -> OctreeLeaf {
    let side = vec3<u32>(1u << prev.size);
    let below = cell < prev.origin;
    let above = cell >= prev.origin + side;
    let outside = vec3<u32>(below | above);
    if outside.x + outside.y + outside.z == 1u {
        let axis = select(select(2u, 1u, outside.y == 1u), 0u, outside.x == 1u);
        let up = any(above);
        let face = 2u * axis + select(0u, 1u, up);
        let rope = octree[prev.record * OCTREE_RECORD_WORDS + 1u + face];
        octree_reads += 1u;
        if rope != OCTREE_NULL {
            var across = prev.origin;
            across[axis] = select(prev.origin[axis] - 1u, prev.origin[axis] + side[axis], up);
            let s = vec3<u32>(octree_ref_size(rope));
            if all((cell >> s) == (across >> s)) {
                return octree_descend(rope, cell);
            }
        }
    }
    return octree_leaf_at(root, cell);
}
