// The page table (page_table.rs; GpuPageTable writes binding 3): one u32 per level-0 brick
// position, decoded into the covering node's level and its payload's place in the cache.
// Bit layout (slot grid x | y << 8 | z << 16, level << 24, FLAG_*) as in PageEntry::encode;
// PageTable::encoded_for_gpu adds FLAG_WHOLE_NODE, FLAG_TRANSITION and, in a not-resident
// word's level field, its skip level (an aligned block of 2^level cells all not resident).

@group(0) @binding(3) var<storage, read> page_table: array<u32>;

// One page entry decoded into the affine map from level-0 index to cache texel coordinate
// (Eq. 1 of the mixed-resolution paper: x' = x · t_w + t with t_w = 2^-L).
struct Page {
    resident: bool,
    empty: bool,
    linear: u32,
    cell: vec3<i32>,
    level: u32,
    inv_scale: f32,
    // Texel coordinate in the cache = slot_base + (level-0 position · inv_scale + offset).
    // The slot's corner is kept apart from the in-slot offset so that the in-slot coordinate,
    // and with it the trilinear weights, do not depend on which slot a brick landed in.
    slot_base: vec3<f32>,
    offset: vec3<f32>,
    // The node has a coarser neighbour (entry bit 31); its mask is read only then.
    has_transition: bool,
    transition: u32,
    near_side_closure: u32,
    // Level-0 index box of the node minus half a voxel on every side: a sample's side code is
    // where it leaves this box.
    inner_lo: vec3<f32>,
    inner_hi: vec3<f32>,
    // Ray distance at which the ray leaves this page cell (cached lookups only).
    t_exit: f32,
    // Every cell of the node (level L) holds this word (FLAG_WHOLE_NODE); for a not-resident
    // word the 2^level block around `cell` is all not resident.
    whole_node: bool,
    // The octree traversal's leaf (octree.wgsl; 0: none yet, record 0 is the header): its
    // box (first page cell, 2^leaf_size cells per axis) is the region the word stands for.
    leaf_record: u32,
    leaf_origin: vec3<u32>,
    leaf_size: u32,
};

// Page-table words read by this invocation (decode_entry calls): the raycaster's debug counter
// (COUNT_SAMPLES) reports it; unused, the compiler drops it.
var<private> page_reads: u32 = 0u;

fn cell_of(pc: vec3<f32>) -> vec3<i32> {
    let last = vec3<i32>(P.pages.xyz) - vec3<i32>(1);
    return clamp(vec3<i32>(floor((pc + vec3<f32>(0.5)) * (1.0 / CORE))), vec3<i32>(0), last);
}

// The page entry alone: where its node's payload sits (no transition data).
fn decode_entry(cell: vec3<i32>) -> Page {
    let c = vec3<u32>(cell);
    let linear = c.x + P.pages.x * (c.y + P.pages.y * c.z);
    page_reads += 1u;
    return decode_word(page_table[linear], cell, linear);
}

// A page word decoded for page cell `cell`; `linear` indexes the per-entry buffers (the page
// cell in the flat table, the leaf in the octree traversal).
fn decode_word(e: u32, cell: vec3<i32>, linear: u32) -> Page {
    var pg: Page;
    let c = vec3<u32>(cell);
    pg.cell = cell;
    pg.linear = linear;
    pg.resident = (e & FLAG_NOT_RESIDENT) == 0u;
    pg.empty = (e & FLAG_EMPTY) != 0u;
    pg.has_transition = (e & FLAG_TRANSITION) != 0u;
    pg.whole_node = (e & FLAG_WHOLE_NODE) != 0u;
    pg.level = (e >> LEVEL_SHIFT) & LEVEL_MASK;
    pg.inv_scale = 1.0 / f32(1u << pg.level);
    let node = c >> vec3<u32>(pg.level);
    // The entry stores the slot's grid position (8 bits per axis), not its index: no integer
    // division per lookup (scalarised and slow on CPU rasterisers such as lavapipe).
    let slot_xyz = vec3<u32>(e & SLOT_AXIS_MASK, (e >> SLOT_AXIS_BITS) & SLOT_AXIS_MASK,
                             (e >> (2u * SLOT_AXIS_BITS)) & SLOT_AXIS_MASK);
    // Level-L voxel i is centred at level-0 index (i + 0.5)·2^L - 0.5 (cell-centred octree):
    // q = (p + 0.5)·2^-L - 0.5, local = q - (32·node - 2), coord = slot·36 + local.
    pg.slot_base = vec3<f32>(slot_xyz * PAYLOAD);
    pg.offset = vec3<f32>(APRON) - vec3<f32>(node) * CORE + vec3<f32>(0.5 * pg.inv_scale - 0.5);
    return pg;
}
