// Smooth transitions (smooth_transitions.rs): what GpuPageTable::update writes for nodes with
// a coarser neighbour (page bit FLAG_TRANSITION, binding 11), read with the page entry. The
// blend itself is part of the field (field.wgsl: transition_blend).

// C0 blend into coarser neighbours (smooth_transitions.rs); on only when the cut has transitions.
override SMOOTH_TRANSITIONS: bool = false;

// Per page entry (flat table) or per leaf (octree traversal: indexed by the leaf, as the MIP
// bound and the visibility word): x = 26-neighbour mask of the covering node, bit
// (x+1)+3(y+1)+9(z+1) set where that neighbour is coarser; y = its near-side closure: bit
// (s+1)·(1,3,9) set where a sample within half a voxel of the sides s can be in a band
// (smooth_transitions.rs).
@group(0) @binding(11) var<storage, read> page_transitions: array<vec2<u32>>;

fn decode_page(cell: vec3<i32>) -> Page {
    return with_transition(decode_entry(cell), cell);
}

// `pg` (decoded for page cell `cell`, `pg.linear` indexing binding 11) with its node's
// transition mask, closure and band-free box; nothing is read unless the word has
// FLAG_TRANSITION and the pipeline smooths.
fn with_transition(decoded: Page, cell: vec3<i32>) -> Page {
    var pg = decoded;
    pg.transition = 0u;
    pg.near_side_closure = 0u;
    if SMOOTH_TRANSITIONS && pg.has_transition {
        let t = page_transitions[pg.linear];
        pg.transition = t.x;
        pg.near_side_closure = t.y;
        let size = CORE * f32(1u << pg.level);
        let lo = vec3<f32>(vec3<u32>(cell) >> vec3<u32>(pg.level)) * size - vec3<f32>(0.5);
        let half = 0.5 * f32(1u << pg.level);
        pg.inner_lo = lo + vec3<f32>(half);
        pg.inner_hi = lo + vec3<f32>(size - half);
    }
    return pg;
}
