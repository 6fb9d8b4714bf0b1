// Single-pass raycaster over the mixed-resolution brick cache (one invocation per pixel).
// The field it integrates is defined in reference.rs; keep the two in step.
//
// Specialisation: every effect a scene may not use is an override constant, so the pipeline
// compiled for a scene contains only what that scene needs.
override MODE: u32 = 0u;              // 0 DVR, 1 MIP, 2 isosurface
override MANUAL_TRILINEAR: bool = false;
override SHADING: bool = false;
override JITTER: bool = false;
override SKIP_EMPTY: bool = true;
override EARLY_TERMINATION: bool = true;
override CLIP_PLANE: bool = false;
override COUNT_SAMPLES: bool = false;
override PREINTEGRATED: bool = false;
// C0 blend into coarser neighbours (smooth_transitions.rs); on only when the cut has transitions.
override SMOOTH_TRANSITIONS: bool = false;

const CORE: f32 = 32.0;
const APRON: f32 = 2.0;
const PAYLOAD: u32 = 36u;
const FLAG_EMPTY: u32 = 0x20000000u;
const FLAG_NOT_RESIDENT: u32 = 0x40000000u;
const FLAG_TRANSITION: u32 = 0x80000000u;
const BISECTION_STEPS: u32 = 10u;
// Below/above these gradient magnitudes (TF-range fractions per finest voxel) shading fades
// from unlit to lit; same constants as reference.rs.
const SHADING_FLAT_BELOW: f32 = 2e-4;
const SHADING_LIT_ABOVE: f32 = 2e-3;
const MAX_ITERATIONS: u32 = 1000000u;

struct Params {
    // Camera in volume index space (level-0 voxel centres at integers); t stays in patient mm
    // because the vectors are images of unit patient vectors.
    eye_idx: vec4<f32>,        // w: tan(fov/2) or ortho half height (mm)
    right_idx: vec4<f32>,      // w: aspect
    up_idx: vec4<f32>,         // w: 1 = orthographic
    forward_idx: vec4<f32>,
    // Rows of index_from_patient: the gradient in patient space is A^T g.
    a_row0: vec4<f32>,
    a_row1: vec4<f32>,
    a_row2: vec4<f32>,
    box_lo: vec4<f32>,         // w: base step (mm)
    box_hi: vec4<f32>,         // w: opacity unit = finest spacing (mm)
    dims: vec4<f32>,           // w: early termination threshold
    // Clip plane as n·forward, n·right, n·up, offset - n·eye.
    clip: vec4<f32>,
    // x: physical per normalised sample (255 or 65535 · slope), y: intercept,
    // z: TF table low end, w: table entries per physical unit.
    value_map: vec4<f32>,
    // x: iso (physical), y: shading flatness scale (per physical gradient/mm).
    iso: vec4<f32>,
    shading: vec4<f32>,        // ambient, diffuse, specular, shininess
    iso_color: vec4<f32>,      // TF colour at the iso value, evaluated exactly on the CPU
    cache_inv: vec4<f32>,      // 1 / cache texel dims
    image: vec4<u32>,          // width, height, frame index, TF table length
    pages: vec4<u32>,          // page grid dims
    slots: vec4<u32>,          // cache slots per axis
};

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var cache: texture_3d<f32>;
@group(0) @binding(2) var cache_sampler: sampler;
@group(0) @binding(3) var<storage, read> page_table: array<u32>;
@group(0) @binding(4) var tf_table: texture_1d<f32>;
@group(0) @binding(5) var out_color: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(6) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(7) var<storage, read_write> visibility: array<u32>;
@group(0) @binding(8) var<storage, read_write> sample_counter: array<atomic<u32>, 2>;
// Per page entry: no sample there exceeds this physical value (+inf when unknown).
@group(0) @binding(9) var<storage, read> page_value_max: array<f32>;
// Pre-integrated TF (preintegration.rs): texel (front, back) = premultiplied colour and opacity
// of a base-step segment whose value runs from front to back. 1×1 when unused.
@group(0) @binding(10) var preintegration_table: texture_2d<f32>;
// Per page entry: x = 26-neighbour mask of the covering node, bit (x+1)+3(y+1)+9(z+1) set where
// that neighbour is coarser; y = its near-side closure: bit (s+1)·(1,3,9) set where a sample
// within half a voxel of the sides s can be in a band (smooth_transitions.rs).
@group(0) @binding(11) var<storage, read> page_transitions: array<vec2<u32>>;

// One page entry decoded into the affine map from level-0 index to cache texel coordinate
// (Eq. 1 of the mixed-resolution paper: x' = x · t_w + t with t_w = 2^-L).
struct Page {
    resident: bool,
    empty: bool,
    linear: u32,
    cell: vec3<i32>,
    level: u32,
    inv_scale: f32,
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
};

struct Location {
    resident: bool,
    empty: bool,
    page: u32,
    cell: vec3<f32>,
    level: u32,
    // Continuous texel coordinate in the cache, voxel centres at integers.
    coord: vec3<f32>,
    // Level-0 index position (clamped to the volume) and the node's transition mask.
    pos: vec3<f32>,
    transition: u32,
    // Outside the node's band-free box: transition_blend must look.
    maybe_band: bool,
};

fn cell_of(pc: vec3<f32>) -> vec3<i32> {
    let last = vec3<i32>(P.pages.xyz) - vec3<i32>(1);
    return clamp(vec3<i32>(floor((pc + vec3<f32>(0.5)) * (1.0 / CORE))), vec3<i32>(0), last);
}

fn decode_page(cell: vec3<i32>) -> Page {
    var pg = decode_entry(cell);
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

// The page entry alone: where its node's payload sits (no transition data).
fn decode_entry(cell: vec3<i32>) -> Page {
    var pg: Page;
    let c = vec3<u32>(cell);
    pg.cell = cell;
    pg.linear = c.x + P.pages.x * (c.y + P.pages.y * c.z);
    let e = page_table[pg.linear];
    pg.resident = (e & FLAG_NOT_RESIDENT) == 0u;
    pg.empty = (e & FLAG_EMPTY) != 0u;
    pg.has_transition = (e & FLAG_TRANSITION) != 0u;
    pg.level = (e >> 24u) & 31u;
    pg.inv_scale = 1.0 / f32(1u << pg.level);
    let node = c >> vec3<u32>(pg.level);
    // The entry stores the slot's grid position (8 bits per axis), not its index: no integer
    // division per lookup (scalarised and slow on CPU rasterisers such as lavapipe).
    let slot_xyz = vec3<u32>(e & 0xffu, (e >> 8u) & 0xffu, (e >> 16u) & 0xffu);
    // Level-L voxel i is centred at level-0 index (i + 0.5)·2^L - 0.5 (cell-centred octree):
    // q = (p + 0.5)·2^-L - 0.5, local = q - (32·node - 2), coord = slot·36 + local.
    pg.offset = vec3<f32>(slot_xyz * PAYLOAD) - (vec3<f32>(node) * CORE - vec3<f32>(APRON))
        + vec3<f32>(0.5 * pg.inv_scale - 0.5);
    return pg;
}

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

// Same as locate for a ray marching forward: the decoded page is reused until the ray leaves
// its cell, so a sample costs a compare and three FMAs instead of a page read and decode.
// (A sample within rounding of a cell face may use the neighbour's payload; the apron makes
// that the same value at equal levels.)
fn locate_on_ray(o: vec3<f32>, d: vec3<f32>, t: f32, cached: ptr<function, Page>) -> Location {
    let pc = clamp_to_volume(o + d * t);
    if t >= (*cached).t_exit {
        let cell = cell_of(pc);
        *cached = decode_page(cell);
        (*cached).t_exit = cell_exit(o, d, vec3<f32>(cell));
    }
    return location_in(*cached, pc);
}

// Normalised stored value (stored / 255 or / 65535, see cache.rs) at a cache texel coordinate.
fn fetch(coord: vec3<f32>) -> f32 {
    if MANUAL_TRILINEAR {
        let i0f = floor(coord);
        let f = coord - i0f;
        let i0 = vec3<i32>(i0f);
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
        return textureSampleLevel(cache, cache_sampler, (coord + vec3<f32>(0.5)) * P.cache_inv.xyz, 0.0).r;
    }
}

// The coarser neighbour a sample blends towards, and how much (smooth_transitions.rs):
// w = 1 - 2·(L∞ distance in node voxels to the nearest coarser face, edge or corner region).
struct Blend {
    w: f32,
    coord: vec3<f32>,
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
        let pg = decode_entry(neighbour);
        if !pg.resident || pg.level <= loc.level {
            continue;
        }
        best = d;
        b.w = clamp(1.0 - 2.0 * d, 0.0, 1.0);
        b.coord = loc.pos * pg.inv_scale + pg.offset;
        b.level = pg.level;
    }
    return b;
}

// The sampled field at a location: the node's trilinear value, blended with its coarser
// neighbour inside a transition band.
fn field(loc: Location) -> f32 {
    if !SMOOTH_TRANSITIONS {
        return fetch(loc.coord);
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
    var weight = 1.0 - b.w;
    for (var k = 0u; k < 2u; k++) {
        value += weight * fetch(coord);
        if b.w <= 0.0 {
            break;
        }
        coord = b.coord;
        weight = b.w;
        b.w = 0.0;
    }
    return value;
}

// Central differences in the payload around `coord` (one voxel of `level` each way), in
// physical units per level-0 index step.
fn payload_gradient(coord: vec3<f32>, level: u32) -> vec3<f32> {
    let h = 2.0 * f32(1u << level);
    let ex = vec3<f32>(1.0, 0.0, 0.0);
    let ey = vec3<f32>(0.0, 1.0, 0.0);
    let ez = vec3<f32>(0.0, 0.0, 1.0);
    return vec3<f32>(
        fetch(coord + ex) - fetch(coord - ex),
        fetch(coord + ey) - fetch(coord - ey),
        fetch(coord + ez) - fetch(coord - ez),
    ) * (P.value_map.x / h);
}

fn field_gradient(loc: Location) -> vec3<f32> {
    if !SMOOTH_TRANSITIONS {
        return payload_gradient(loc.coord, loc.level);
    }
    var b: Blend;
    b.w = 0.0;
    if loc.maybe_band {
        b = transition_blend(loc);
    }
    // One call site for the six fetches, as in field().
    var g = vec3<f32>(0.0);
    var coord = loc.coord;
    var level = loc.level;
    var weight = 1.0 - b.w;
    for (var k = 0u; k < 2u; k++) {
        g += weight * payload_gradient(coord, level);
        if b.w <= 0.0 {
            break;
        }
        coord = b.coord;
        level = b.level;
        weight = b.w;
        b.w = 0.0;
    }
    return g;
}

fn physical(s: f32) -> f32 {
    return s * P.value_map.x + P.value_map.y;
}

// Transfer function, linearly interpolated between table entries.
fn transfer(v: f32) -> vec4<f32> {
    let n = P.image.w;
    let x = clamp((v - P.value_map.z) * P.value_map.w, 0.0, f32(n - 1u));
    let i = min(u32(floor(x)), n - 1u);
    let j = min(i + 1u, n - 1u);
    return mix(textureLoad(tf_table, i32(i), 0), textureLoad(tf_table, i32(j), 0), x - f32(i));
}

// Segment colour and opacity between two physical values, bilinear in the table, which spans
// the same value range as the TF texture.
fn preintegrated(front: f32, back: f32) -> vec4<f32> {
    let last = f32(textureDimensions(preintegration_table).x - 1u);
    let per_value = P.value_map.w * last / f32(P.image.w - 1u);
    let x = clamp((front - P.value_map.z) * per_value, 0.0, last);
    let y = clamp((back - P.value_map.z) * per_value, 0.0, last);
    let i0 = vec2<i32>(i32(floor(x)), i32(floor(y)));
    let i1 = min(i0 + vec2<i32>(1), vec2<i32>(i32(last)));
    let f = vec2<f32>(x, y) - floor(vec2<f32>(x, y));
    let c00 = textureLoad(preintegration_table, i0, 0);
    let c10 = textureLoad(preintegration_table, vec2<i32>(i1.x, i0.y), 0);
    let c01 = textureLoad(preintegration_table, vec2<i32>(i0.x, i1.y), 0);
    let c11 = textureLoad(preintegration_table, i1, 0);
    return mix(mix(c00, c10, f.x), mix(c01, c11, f.x), f.y);
}

// Blinn-Phong with a headlight; `d_idx` is the ray direction mapped into index space, so
// g·d_idx = (A^T g)·d_patient without leaving index space.
fn shade(color: vec3<f32>, loc: Location, d_idx: vec3<f32>) -> vec3<f32> {
    let g_idx = field_gradient(loc);
    let g_patient = g_idx.x * P.a_row0.xyz + g_idx.y * P.a_row1.xyz + g_idx.z * P.a_row2.xyz;
    let mag = length(g_patient);
    let w = smoothstep(SHADING_FLAT_BELOW, SHADING_LIT_ABOVE, mag * P.iso.y);
    var ndl = 1.0;
    if mag > 0.0 {
        ndl = min(abs(dot(g_idx, d_idx)) / mag, 1.0);
    }
    var spec = 0.0;
    if mag > 0.0 {
        spec = pow(ndl, P.shading.w);
    }
    let unlit = P.shading.x + P.shading.y;
    let lit = P.shading.x + P.shading.y * ndl;
    let gain = unlit + (lit - unlit) * w;
    return color * gain + vec3<f32>(P.shading.z * spec * w);
}

fn pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Where the ray leaves page cell `cell` (index-space box of 32 voxel cells).
fn cell_exit(o: vec3<f32>, d: vec3<f32>, cell: vec3<f32>) -> f32 {
    let lo = cell * CORE - vec3<f32>(0.5);
    let bound = select(lo, lo + vec3<f32>(CORE), d > vec3<f32>(0.0));
    let t = select((bound - o) / d, vec3<f32>(3.0e38), abs(d) < vec3<f32>(1e-20));
    return min(t.x, min(t.y, t.z));
}

// Everything a ray accumulates; one struct so the sample step can be shared by the general
// and the fast path of the march.
struct RayState {
    acc: vec4<f32>,
    depth: f32,
    samples: u32,
    best_value: f32,
    best_t: f32,
    have_best: bool,
    prev_t: f32,
    prev_valid: bool,
    hit: bool,
    last_marked: u32,
    done: bool,
    // Pre-integration: the previous sample (value, distance, step, location), the front of
    // the next segment; cleared where a run of samples ends (skip, not resident, ray end).
    run_value: f32,
    run_t: f32,
    run_delta: f32,
    run_loc: Location,
    run_open: bool,
};

// Marks a page visible once per visit: consecutive samples mostly share a page, and a
// scattered store per sample is expensive (per-lane on CPU rasterisers). Racing stores from
// different rays all write 1, so no atomics are needed.
fn mark_visible_in(st: ptr<function, RayState>, page: u32) {
    if page != (*st).last_marked {
        visibility[page] = 1u;
        (*st).last_marked = page;
    }
}

// Composites the pre-integrated segment of `length` (mm) from value `front` to `back`. The
// table is for the base step; other lengths (half segments, coarse levels, level changes)
// rescale opacity by the same power law as the classic opacity correction.
// Front-to-back "over" of a premultiplied colour and its opacity at ray distance t; the first
// contribution sets the depth, its page is marked visible, early termination is checked.
fn composite(st: ptr<function, RayState>, premultiplied: vec3<f32>, alpha: f32, page: u32, t: f32) {
    if (*st).depth == bitcast<f32>(0x7f800000u) {
        (*st).depth = t;
    }
    mark_visible_in(st, page);
    let w = 1.0 - (*st).acc.a;
    (*st).acc = vec4<f32>((*st).acc.rgb + w * premultiplied, (*st).acc.a + w * alpha);
    if EARLY_TERMINATION && (*st).acc.a >= P.dims.w {
        (*st).done = true;
    }
}

fn composite_segment(st: ptr<function, RayState>, front: f32, back: f32, length: f32,
                     back_loc: Location, t: f32, d: vec3<f32>) {
    var seg = preintegrated(front, back);
    let ratio = length / P.box_lo.w;
    if ratio != 1.0 && seg.a > 0.0 {
        let a = 1.0 - pow(1.0 - min(seg.a, 0.999999), ratio);
        seg = vec4<f32>(seg.rgb * (a / seg.a), a);
    }
    if seg.a <= 0.0 {
        return;
    }
    var color = seg.rgb;
    if SHADING {
        // Lit at the segment's nearer sample: the gradient is only known at samples.
        color = shade(seg.rgb / seg.a, back_loc, d) * seg.a;
    }
    composite(st, color, seg.a, back_loc.page, t);
}

// The constant half segment after the last sample of a run (see take_sample).
fn close_preintegrated_run(st: ptr<function, RayState>, d: vec3<f32>) {
    if MODE == 0u && PREINTEGRATED && (*st).run_open && !(*st).done {
        let v = (*st).run_value;
        composite_segment(st, v, v, 0.5 * (*st).run_delta, (*st).run_loc, (*st).run_t, d);
    }
    (*st).run_open = false;
}

fn take_sample(st: ptr<function, RayState>, loc: Location, t: f32, delta: f32, o: vec3<f32>, d: vec3<f32>) {
    (*st).samples = (*st).samples + 1u;
    let v = physical(field(loc));
    if MODE == 0u && PREINTEGRATED {
        // Segments join consecutive samples, which sit at segment midpoints; a run of samples
        // therefore starts with a constant half segment before its first sample and ends with
        // one after its last (close_preintegrated_run), so the integrated interval is the one
        // the classic path covers.
        if (*st).run_open {
            composite_segment(st, (*st).run_value, v, t - (*st).run_t, loc, t, d);
        } else {
            composite_segment(st, v, v, 0.5 * delta, loc, t, d);
        }
        (*st).run_value = v;
        (*st).run_t = t;
        (*st).run_delta = delta;
        (*st).run_loc = loc;
        (*st).run_open = true;
    } else if MODE == 0u {
        let tf = transfer(v);
        if tf.a > 0.0 {
            // Opacity correction: opacity is defined per finest voxel; a step of `delta` mm
            // must absorb as much as delta/unit such steps would.
            let alpha = 1.0 - pow(1.0 - min(tf.a, 0.999999), delta / P.box_hi.w);
            var color = tf.rgb;
            if SHADING {
                color = shade(color, loc, d);
            }
            composite(st, color * alpha, alpha, loc.page, t);
        }
    } else if MODE == 1u {
        if v > (*st).best_value {
            (*st).best_value = v;
            (*st).best_t = t;
            (*st).have_best = true;
        }
        if loc.page != (*st).last_marked && transfer(v).a > 0.0 {
            mark_visible_in(st, loc.page);
        }
    } else {
        if v >= P.iso.x {
            var t_hit = t;
            if (*st).prev_valid {
                var lo = (*st).prev_t;
                var hi = t;
                for (var b = 0u; b < BISECTION_STEPS; b++) {
                    let mid = 0.5 * (lo + hi);
                    let m = locate(o + d * mid);
                    if m.resident && physical(field(m)) >= P.iso.x {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                t_hit = hi;
            }
            (*st).hit = true;
            (*st).depth = t_hit;
            mark_visible_in(st, locate(o + d * t_hit).page);
            (*st).done = true;
        } else {
            (*st).prev_t = t;
            (*st).prev_valid = true;
        }
    }
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let width = P.image.x;
    let height = P.image.y;
    if gid.x >= width || gid.y >= height {
        return;
    }
    let pixel = gid.y * width + gid.x;
    let inf = bitcast<f32>(0x7f800000u);
    let half_extent = P.eye_idx.w;
    let sx = (2.0 * (f32(gid.x) + 0.5) / f32(width) - 1.0) * P.right_idx.w * half_extent;
    let sy = (1.0 - 2.0 * (f32(gid.y) + 0.5) / f32(height)) * half_extent;
    let orthographic = P.up_idx.w > 0.5;
    var o = P.eye_idx.xyz;
    var d = P.forward_idx.xyz;
    var plane_nd = P.clip.x;
    var plane_rhs = P.clip.w;
    if orthographic {
        o = o + sx * P.right_idx.xyz + sy * P.up_idx.xyz;
        plane_rhs = plane_rhs - sx * P.clip.y - sy * P.clip.z;
    } else {
        let len = sqrt(1.0 + sx * sx + sy * sy);
        d = (d + sx * P.right_idx.xyz + sy * P.up_idx.xyz) / len;
        plane_nd = (plane_nd + sx * P.clip.y + sy * P.clip.z) / len;
    }

    // Ray interval inside the cropped box (index space) and the clip half-space.
    var t0 = 0.0;
    var t1 = inf;
    var miss = false;
    for (var a = 0u; a < 3u; a++) {
        if abs(d[a]) < 1e-12 {
            if o[a] < P.box_lo[a] || o[a] > P.box_hi[a] {
                miss = true;
            }
        } else {
            let ta = (P.box_lo[a] - o[a]) / d[a];
            let tb = (P.box_hi[a] - o[a]) / d[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    if CLIP_PLANE {
        if abs(plane_nd) < 1e-12 {
            if plane_rhs > 0.0 {
                miss = true;
            }
        } else {
            let tc = plane_rhs / plane_nd;
            if plane_nd > 0.0 {
                t0 = max(t0, tc);
            } else {
                t1 = min(t1, tc);
            }
        }
    }
    if miss || !(t1 > t0) {
        textureStore(out_color, vec2<i32>(gid.xy), vec4<f32>(0.0));
        out_depth[pixel] = inf;
        return;
    }

    let base = P.box_lo.w;
    let unit = P.box_hi.w;
    var j = 0.5;
    if JITTER {
        j = min(f32(pcg(gid.x ^ pcg(gid.y ^ pcg(P.image.z)))) * 2.3283064e-10, 0.99999);
    }
    // Segment k spans [first + k·base, first + (k+1)·base): level-0 samples sit at
    // t0 + (k + j)·base, the midpoints when jitter is off. Coarse nodes take 2^L segments at
    // once, so every sample stays on one lattice and empty-space jumps cannot shift it.
    let first = t0 + (j - 0.5) * base;

    var st: RayState;
    st.acc = vec4<f32>(0.0);
    st.depth = inf;
    st.best_value = -3.0e38;
    st.best_t = inf;
    st.last_marked = 0xffffffffu;
    var k = 0u;
    // Start of the segment cut short by the ray's exit (none: +inf).
    var partial_start = inf;
    var page_cache: Page;
    page_cache.t_exit = -3.0e38;
    for (var iter = 0u; iter < MAX_ITERATIONS; iter++) {
        let seg = first + f32(k) * base;
        let probe_t = seg + 0.5 * base;
        if probe_t >= t1 {
            partial_start = seg;
            break;
        }
        let probe = locate_on_ray(o, d, probe_t, &page_cache);
        // MIP: a page whose bound cannot beat the running maximum cannot change the pixel
        // (ties keep the first maximum), so it is skipped like an empty one.
        // (Empty flags and MIP bounds cover the coarser field a transition band blends in:
        // PageTable::sampled_ranges.)
        let mip_cannot_win = MODE == 1u && SKIP_EMPTY && st.have_best
            && page_value_max[probe.page] <= st.best_value;
        if !probe.resident || (SKIP_EMPTY && probe.empty) || mip_cannot_win {
            if SKIP_EMPTY {
                let t_exit = page_cache.t_exit;
                let next = ceil((t_exit - first) / base - 0.5);
                k = max(k + 1u, u32(clamp(next, 0.0, 4.0e9)));
                st.prev_valid = false;
                close_preintegrated_run(&st, d);
                if MODE == 2u && probe.resident {
                    // Empty for an isosurface means below the iso value: the crossing lies
                    // after the cell face, so bisection may start there.
                    st.prev_t = max(t_exit, t0);
                    st.prev_valid = true;
                }
            } else {
                k = k + 1u;
                st.prev_valid = false;
                close_preintegrated_run(&st, d);
            }
            continue;
        }
        let level = probe.level;
        let stride = 1u << level;
        let delta = base * f32(stride);
        let t = seg + 0.5 * delta;
        if t >= t1 {
            partial_start = seg;
            break;
        }
        var loc = probe;
        if level != 0u {
            loc = locate_on_ray(o, d, t, &page_cache);
        }
        k = k + stride;
        if !loc.resident {
            st.prev_valid = false;
            close_preintegrated_run(&st, d);
            continue;
        }
        take_sample(&st, loc, t, delta, o, d);
        if st.done {
            break;
        }
        // Fast path: while the next sample stays in the decoded page at the same level, march
        // with nothing but position, fetch and compositing (the common case by far).
        if page_cache.level == level && page_cache.resident {
            var page_bound = bitcast<f32>(0x7f800000u);
            if MODE == 1u && SKIP_EMPTY {
                page_bound = page_value_max[page_cache.linear];
            }
            for (var inner = 0u; inner < MAX_ITERATIONS; inner++) {
                // MIP reached this page's bound: the rest of the page cannot win; the outer
                // loop skips it.
                if MODE == 1u && SKIP_EMPTY && st.best_value >= page_bound {
                    break;
                }
                let t_next = first + (f32(k) + 0.5 * f32(stride)) * base;
                if t_next >= t1 || t_next >= page_cache.t_exit {
                    break;
                }
                k = k + stride;
                take_sample(&st, location_in(page_cache, clamp_to_volume(o + d * t_next)), t_next, delta, o, d);
                if st.done {
                    break;
                }
            }
            if st.done {
                break;
            }
        }
    }
    // The last segment, cut at the exit, is sampled at its own midpoint and absorbs only for
    // its own length, as in the reference: a ray grazing a corner of the box still sees what
    // it passes, however short its path.
    if partial_start < t1 && !st.done {
        let length = t1 - partial_start;
        let t = partial_start + 0.5 * length;
        let loc = locate(o + d * t);
        if loc.resident && !(SKIP_EMPTY && loc.empty) {
            take_sample(&st, loc, t, length, o, d);
        }
    }
    close_preintegrated_run(&st, d);
    var acc = st.acc;
    var depth = st.depth;
    let samples = st.samples;
    let have_best = st.have_best;
    let best_value = st.best_value;
    let best_t = st.best_t;
    let hit = st.hit;
    var hit_loc: Location;
    if hit {
        hit_loc = locate(o + d * depth);
    }

    if MODE == 1u && have_best {
        let tf = transfer(best_value);
        acc = vec4<f32>(tf.rgb * tf.a, tf.a);
        if tf.a > 0.0 {
            depth = best_t;
        }
    }
    if MODE == 2u && hit {
        let base_color = P.iso_color.rgb;
        acc = vec4<f32>(shade(base_color, hit_loc, d), 1.0);
    }
    if COUNT_SAMPLES {
        let old = atomicAdd(&sample_counter[0], samples);
        if old > 0xffffffffu - samples {
            atomicAdd(&sample_counter[1], 1u);
        }
    }
    textureStore(out_color, vec2<i32>(gid.xy), clamp(acc, vec4<f32>(0.0), vec4<f32>(1.0)));
    out_depth[pixel] = depth;
}

// Field probe for tests: physical value of the field at level-0 index points (w ignored);
// NaN where nothing is resident. Uses the same field() as the raycaster.
@group(0) @binding(12) var<storage, read> probe_points: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> probe_values: array<f32>;

@compute @workgroup_size(64, 1, 1)
fn probe(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= arrayLength(&probe_values) {
        return;
    }
    let loc = locate(probe_points[i].xyz);
    if loc.resident {
        probe_values[i] = physical(field(loc));
    } else {
        probe_values[i] = bitcast<f32>(0x7fc00000u);
    }
}
