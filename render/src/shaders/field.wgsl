// The sampled field: the WGSL twin of field.rs (locate, trilinear, gradients, the transition
// blend), the one definition the f64 reference integrates too; keep the two in step.

override MANUAL_TRILINEAR: bool = false;

@group(0) @binding(1) var cache: texture_3d<f32>;
@group(0) @binding(2) var cache_sampler: sampler;

struct Location {
    resident: bool,
    empty: bool,
    page: u32,
    cell: vec3<f32>,
    level: u32,
    // Continuous texel coordinate within the node's cache slot (voxel centres at integers),
    // and the slot's corner texel: fetch() adds the two only after splitting off the fraction.
    coord: vec3<f32>,
    slot_base: vec3<f32>,
    // Level-0 index position (clamped to the volume) and the node's transition mask.
    pos: vec3<f32>,
    transition: u32,
    // Outside the node's band-free box: transition_blend must look.
    maybe_band: bool,
};

fn clamp_to_volume(p: vec3<f32>) -> vec3<f32> {
    return clamp(p, vec3<f32>(-0.5), P.dims.xyz - vec3<f32>(0.5));
}

fn location_in(pg: Page, pc: vec3<f32>) -> Location {
    var loc: Location;
    loc.resident = pg.resident;
    loc.empty = pg.empty;
    loc.page = pg.linear;
    loc.cell = vec3<f32>(pg.cell);
    loc.level = pg.level;
    loc.coord = pc * pg.inv_scale + pg.offset;
    loc.slot_base = pg.slot_base;
    loc.pos = pc;
    loc.transition = pg.transition;
    loc.maybe_band = false;
    if SMOOTH_TRANSITIONS && pg.near_side_closure != 0u {
        let side = select(select(vec3<u32>(1u), vec3<u32>(2u), pc > pg.inner_hi), vec3<u32>(0u), pc < pg.inner_lo);
        let bit = side.x + 3u * side.y + 9u * side.z;
        loc.maybe_band = ((pg.near_side_closure >> bit) & 1u) != 0u;
    }
    return loc;
}

fn locate(p: vec3<f32>) -> Location {
    let pc = clamp_to_volume(p);
    return location_in(decode_page(cell_of(pc)), pc);
}

// Normalised stored value (stored / 255 or / 65535, see cache.rs) at in-slot texel coordinate
// `coord` of the slot whose corner texel is `slot_base`.
fn fetch(slot_base: vec3<f32>, coord: vec3<f32>) -> f32 {
    if MANUAL_TRILINEAR {
        // Weights from the in-slot coordinate alone: the image does not depend on which slot
        // a brick was given (bricks arrive in another order from a server, after a restart or
        // under another budget), bit for bit.
        let i0f = floor(coord);
        let f = coord - i0f;
        let i0 = vec3<i32>(slot_base) + vec3<i32>(i0f);
        let c000 = textureLoad(cache, i0, 0).r;
        let c100 = textureLoad(cache, i0 + vec3<i32>(1, 0, 0), 0).r;
        let c010 = textureLoad(cache, i0 + vec3<i32>(0, 1, 0), 0).r;
        let c110 = textureLoad(cache, i0 + vec3<i32>(1, 1, 0), 0).r;
        let c001 = textureLoad(cache, i0 + vec3<i32>(0, 0, 1), 0).r;
        let c101 = textureLoad(cache, i0 + vec3<i32>(1, 0, 1), 0).r;
        let c011 = textureLoad(cache, i0 + vec3<i32>(0, 1, 1), 0).r;
        let c111 = textureLoad(cache, i0 + vec3<i32>(1, 1, 1), 0).r;
        let x00 = mix(c000, c100, f.x);
        let x10 = mix(c010, c110, f.x);
        let x01 = mix(c001, c101, f.x);
        let x11 = mix(c011, c111, f.x);
        return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
    } else {
        // The sampler takes one normalised coordinate, whose rounding depends on the slot's
        // place in the texture: a channel may move by one 8-bit step with the slot.
        return textureSampleLevel(cache, cache_sampler, (slot_base + coord + vec3<f32>(0.5)) * P.cache_inv.xyz, 0.0).r;
    }
}

// The coarser neighbour a sample blends towards, and how much (smooth_transitions.rs):
// w = 1 - 2·(L∞ distance in node voxels to the nearest coarser face, edge or corner region).
struct Blend {
    w: f32,
    coord: vec3<f32>,
    slot_base: vec3<f32>,
    level: u32,
};

fn transition_blend(loc: Location) -> Blend {
    var b: Blend;
    b.w = 0.0;
    let inv_scale = 1.0 / f32(1u << loc.level);
    let cell = vec3<i32>(loc.cell);
    let node = vec3<f32>(vec3<u32>(cell) >> vec3<u32>(loc.level));
    let q = (loc.pos + vec3<f32>(0.5)) * inv_scale - vec3<f32>(0.5);
    let d_lo = q - (node * CORE - vec3<f32>(0.5));
    let d_hi = (node * CORE + vec3<f32>(CORE - 0.5)) - q;
    let nearest_face = min(d_lo, d_hi);
    // Most samples of a transition node are farther than half a voxel from every face.
    if min(nearest_face.x, min(nearest_face.y, nearest_face.z)) >= 0.5 {
        return b;
    }
    // Only the sides within half a voxel can hold the nearest coarser neighbour: walk the
    // non-empty subsets of those sides (1 for a face band, up to 7 in a corner), no integer
    // division (scalarised on CPU rasterisers).
    let side = select(select(vec3<i32>(0), vec3<i32>(1), d_hi < vec3<f32>(0.5)), vec3<i32>(-1), d_lo < vec3<f32>(0.5));
    let side_d = select(d_hi, d_lo, side < vec3<i32>(0));
    var best = 0.5;
    for (var subset = 1u; subset < 8u; subset++) {
        let pick = vec3<bool>((subset & 1u) != 0u, (subset & 2u) != 0u, (subset & 4u) != 0u);
        if any(pick & (side == vec3<i32>(0))) {
            continue;
        }
        let o = select(vec3<i32>(0), side, pick);
        let bit = u32((o.x + 1) + 3 * (o.y + 1) + 9 * (o.z + 1));
        if (loc.transition & (1u << bit)) == 0u {
            continue;
        }
        let per_axis = select(vec3<f32>(-3.0e38), side_d, pick);
        let d = max(per_axis.x, max(per_axis.y, per_axis.z));
        if d >= best {
            continue;
        }
        let neighbour = cell + o;
        if any(neighbour < vec3<i32>(0)) || any(neighbour >= vec3<i32>(P.pages.xyz)) {
            continue;
        }
        // The module's traversal finds the neighbour's page (flat_neighbour.wgsl: its word in
        // the flat table; raycast.wgsl: a point query on the octree's node buffer).
        let pg = neighbour_page(neighbour);
        if !pg.resident || pg.level <= loc.level {
            continue;
        }
        best = d;
        b.w = clamp(1.0 - 2.0 * d, 0.0, 1.0);
        b.coord = loc.pos * pg.inv_scale + pg.offset;
        b.slot_base = pg.slot_base;
        b.level = pg.level;
    }
    return b;
}

// The sampled field at a location: the node's trilinear value, blended with its coarser
// neighbour inside a transition band.
fn field(loc: Location) -> f32 {
    if !SMOOTH_TRANSITIONS {
        return fetch(loc.slot_base, loc.coord);
    }
    var b: Blend;
    b.w = 0.0;
    if loc.maybe_band {
        b = transition_blend(loc);
    }
    // One fetch site, run twice by band samples only: a second fetch in a branch of its own
    // made every sample of the pipeline slower on lavapipe (its sampler is inlined code).
    var value = 0.0;
    var coord = loc.coord;
    var slot_base = loc.slot_base;
    var weight = 1.0 - b.w;
    for (var k = 0u; k < 2u; k++) {
        value += weight * fetch(slot_base, coord);
        if b.w <= 0.0 {
            break;
        }
        coord = b.coord;
        slot_base = b.slot_base;
        weight = b.w;
        b.w = 0.0;
    }
    return value;
}

// Central differences in the payload around `coord` (one voxel of `level` each way), in
// physical units per level-0 index step.
fn payload_gradient(slot_base: vec3<f32>, coord: vec3<f32>, level: u32) -> vec3<f32> {
    let h = 2.0 * f32(1u << level);
    let ex = vec3<f32>(1.0, 0.0, 0.0);
    let ey = vec3<f32>(0.0, 1.0, 0.0);
    let ez = vec3<f32>(0.0, 0.0, 1.0);
    return vec3<f32>(
        fetch(slot_base, coord + ex) - fetch(slot_base, coord - ex),
        fetch(slot_base, coord + ey) - fetch(slot_base, coord - ey),
        fetch(slot_base, coord + ez) - fetch(slot_base, coord - ez),
    ) * (P.value_map.x / h);
}

fn field_gradient(loc: Location) -> vec3<f32> {
    if !SMOOTH_TRANSITIONS {
        return payload_gradient(loc.slot_base, loc.coord, loc.level);
    }
    var b: Blend;
    b.w = 0.0;
    if loc.maybe_band {
        b = transition_blend(loc);
    }
    // One call site for the six fetches, as in field().
    var g = vec3<f32>(0.0);
    var coord = loc.coord;
    var slot_base = loc.slot_base;
    var level = loc.level;
    var weight = 1.0 - b.w;
    for (var k = 0u; k < 2u; k++) {
        g += weight * payload_gradient(slot_base, coord, level);
        if b.w <= 0.0 {
            break;
        }
        coord = b.coord;
        slot_base = b.slot_base;
        level = b.level;
        weight = b.w;
        b.w = 0.0;
    }
    return g;
}

fn physical(s: f32) -> f32 {
    return s * P.value_map.x + P.value_map.y;
}
