// Single-pass raycaster over the mixed-resolution brick cache (one invocation per pixel): the
// entry point and the ray loop. The field it integrates is field.wgsl (twin of field.rs, which
// the f64 reference integrates); the optics mirror reference.rs. shaders.rs composes this file
// after the constants prelude and the files it uses.
//
// Specialisation: every effect a scene may not use is an override constant, so the pipeline
// compiled for a scene contains only what that scene needs (MANUAL_TRILINEAR is declared in
// field.wgsl, SMOOTH_TRANSITIONS in smooth_transitions.wgsl, OVERLAY in overlay.wgsl).
override MODE: u32 = 0u;              // 0 DVR, 1 MIP, 2 isosurface
override SHADING: bool = false;
override JITTER: bool = false;
override SKIP_EMPTY: bool = true;
override EARLY_TERMINATION: bool = true;
override CLIP_PLANE: bool = false;
override COUNT_SAMPLES: bool = false;
override PREINTEGRATED: bool = false;
// The octree traversal (octree paper §5.2; octree.wgsl, gpu_octree.rs): pages come from the
// cut's leaves, found by a point query at the ray's entry, then by the exit face's rope and a
// descent; a leaf's box is the region a ray crosses or skips at once; the MIP bound and the
// visibility word are per leaf. Off: the flat page table (one word per finest brick position).
override OCTREE: bool = false;

// Node-extent exit (page_table.rs FLAG_WHOLE_NODE, skip levels): a ray leaves an empty whole
// node, one its MIP maximum already beats, or a not-resident block at once instead of cell by
// cell, and crosses the cells of a whole node without reading their (identical) entries. The
// benches and tests build a variant with `const NODE_EXTENT: bool = false;` (cell by cell, the
// march before it) to count page reads and compare images.
const NODE_EXTENT: bool = true;
// MIP's own march (march_mip): no DVR/isosurface ray state, value-bound skipping at node
// extent. The benches and tests build a variant with `const LEAN_MIP: bool = false;` (MIP
// through the general march, as before) to compare images and time.
const LEAN_MIP: bool = true;
const BISECTION_STEPS: u32 = 10u;
const MAX_ITERATIONS: u32 = 1000000u;

@group(0) @binding(5) var out_color: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(6) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(7) var<storage, read_write> visibility: array<u32>;
// Debug counters (COUNT_SAMPLES): samples lo/hi, page-table reads lo/hi.
@group(0) @binding(8) var<storage, read_write> sample_counter: array<atomic<u32>, 4>;
// Per page entry: no sample there exceeds this physical value (+inf when unknown).
@group(0) @binding(9) var<storage, read> page_value_max: array<f32>;

// Same as locate for a ray marching forward: the decoded page is reused until the ray leaves
// its cell, so a sample costs a compare and three FMAs instead of a page read and decode.
// (A sample within rounding of a cell face may use the neighbour's payload; the apron makes
// that the same value at equal levels.)
// With NODE_EXTENT, a new cell in the same whole node (or not-resident block) holds the same
// word: only the cell and its linear index change, nothing is read.
fn locate_on_ray(o: vec3<f32>, d: vec3<f32>, t: f32, cached: ptr<function, Page>) -> Location {
    let pc = clamp_to_volume(o + d * t);
    if t >= (*cached).t_exit {
        let cell = cell_of(pc);
        if OCTREE {
            // Still in the leaf (a sample within rounding of its exit): nothing is read. Else
            // the rope of the face the ray left by, and a descent (octree_next_leaf).
            let c = vec3<u32>(cell);
            let s = vec3<u32>((*cached).leaf_size);
            let known = (*cached).leaf_record != 0u;
            if known && all((c >> s) == ((*cached).leaf_origin >> s)) {
                (*cached).cell = cell;
            } else if known {
                *cached = decode_leaf(octree_next_leaf(P.pages.w, leaf_of(*cached), c), cell);
            } else {
                *cached = decode_leaf(octree_leaf_at(P.pages.w, c), cell);
            }
            // The march's fast path samples a resident page up to t_exit without looking at its
            // flags. A sample can land in an empty leaf its probe was not in (a coarse stride);
            // the flat march then samples to that cell's exit and its next probe skips the node,
            // so an empty leaf ends at the cell too: the same samples, the same MIP maxima.
            // Skipping it still leaves the whole leaf (skip_exit).
            if (*cached).empty {
                (*cached).t_exit = cell_exit(o, d, vec3<f32>(cell));
            } else {
                (*cached).t_exit = region_exit(o, d, (*cached).leaf_origin, (*cached).leaf_size);
            }
            return location_in(*cached, pc);
        }
        let shift = vec3<u32>((*cached).level);
        let same_region = NODE_EXTENT && ((*cached).whole_node || !(*cached).resident)
            && all((vec3<u32>(cell) >> shift) == (vec3<u32>((*cached).cell) >> shift));
        if same_region {
            let c = vec3<u32>(cell);
            (*cached).cell = cell;
            (*cached).linear = c.x + P.pages.x * (c.y + P.pages.y * c.z);
        } else {
            *cached = decode_page(cell);
        }
        (*cached).t_exit = cell_exit(o, d, vec3<f32>(cell));
    }
    return location_in(*cached, pc);
}

// The octree traversal's page for `cell` from the leaf holding it (not found: not resident).
// Its per-entry index is the leaf's; its region the leaf's box.
fn decode_leaf(leaf: OctreeLeaf, cell: vec3<i32>) -> Page {
    // The leaf's transition data is per leaf (binding 11 indexed by the leaf, as the MIP
    // bound): the same mask as the flat table's entries of that node.
    var pg = with_transition(leaf_entry(leaf, cell), cell);
    pg.whole_node = true;
    pg.leaf_record = select(0u, leaf.record, leaf.found);
    pg.leaf_origin = leaf.origin;
    pg.leaf_size = leaf.size;
    return pg;
}

// The leaf's page word alone, decoded for `cell` (decode_entry's twin: no transition data).
fn leaf_entry(leaf: OctreeLeaf, cell: vec3<i32>) -> Page {
    var word = FLAG_NOT_RESIDENT;
    if leaf.found {
        word = leaf.word;
    }
    return decode_word(word, cell, leaf.index);
}

fn leaf_of(pg: Page) -> OctreeLeaf {
    var leaf: OctreeLeaf;
    leaf.found = true;
    leaf.record = pg.leaf_record;
    leaf.index = pg.linear;
    leaf.origin = pg.leaf_origin;
    leaf.size = pg.leaf_size;
    return leaf;
}

// Where the ray leaves the block of 2^size page cells from page cell `origin` (index space).
fn region_exit(o: vec3<f32>, d: vec3<f32>, origin: vec3<u32>, size: u32) -> f32 {
    let lo = vec3<f32>(origin) * CORE - vec3<f32>(0.5);
    let bound = select(lo, lo + vec3<f32>(CORE * f32(1u << size)), d > vec3<f32>(0.0));
    let t = select((bound - o) / d, vec3<f32>(3.0e38), abs(d) < vec3<f32>(1e-20));
    return min(t.x, min(t.y, t.z));
}

// locate_traversal, keeping the octree leaf found in `near` (zeroed: none yet) and reading
// nothing while later points stay in it; the flat table reads its word each time.
fn locate_cached(p: vec3<f32>, near: ptr<function, Page>) -> Location {
    if !OCTREE {
        return locate(p);
    }
    let pc = clamp_to_volume(p);
    let cell = cell_of(pc);
    let c = vec3<u32>(cell);
    let s = vec3<u32>((*near).leaf_size);
    if (*near).leaf_record != 0u && all((c >> s) == ((*near).leaf_origin >> s)) {
        (*near).cell = cell;
    } else {
        *near = decode_leaf(octree_leaf_at(P.pages.w, c), cell);
    }
    return location_in(*near, pc);
}

// The sample at `p` located by whichever traversal the pipeline has: a point query on the
// node buffer (OCTREE) or a page-table read (locate, field.wgsl).
fn locate_traversal(p: vec3<f32>) -> Location {
    if OCTREE {
        let pc = clamp_to_volume(p);
        let cell = cell_of(pc);
        return location_in(decode_leaf(octree_leaf_at(P.pages.w, vec3<u32>(cell)), cell), pc);
    }
    return locate(p);
}

// The transition blend's neighbour lookup (field.wgsl: transition_blend; the other passes
// take flat_neighbour.wgsl's): the page of a face, edge or corner neighbour cell. Six face
// ropes do not reach edge and corner neighbours, so the octree finds every one with a point
// query on the node buffer (the neighbour's leaf holds the flat table's word for that cell).
fn neighbour_page(cell: vec3<i32>) -> Page {
    if OCTREE {
        return leaf_entry(octree_leaf_at(P.pages.w, vec3<u32>(cell)), cell);
    }
    return decode_entry(cell);
}

// Where the ray leaves the region a skipped entry stands for: with NODE_EXTENT its whole node
// (FLAG_WHOLE_NODE) or its not-resident block, else (or for a parent standing in for some of
// its children) its cell.
fn skip_exit(o: vec3<f32>, d: vec3<f32>, pg: Page) -> f32 {
    if OCTREE {
        // The leaf's box.
        return region_exit(o, d, pg.leaf_origin, pg.leaf_size);
    }
    if NODE_EXTENT && (pg.whole_node || !pg.resident) && pg.level > 0u {
        let cells = f32(1u << pg.level);
        let node = vec3<f32>(vec3<u32>(pg.cell) >> vec3<u32>(pg.level));
        let lo = node * (CORE * cells) - vec3<f32>(0.5);
        let bound = select(lo, lo + vec3<f32>(CORE * cells), d > vec3<f32>(0.0));
        let t = select((bound - o) / d, vec3<f32>(3.0e38), abs(d) < vec3<f32>(1e-20));
        return min(t.x, min(t.y, t.z));
    }
    return pg.t_exit;
}

// Blinn-Phong at the field's gradient there: with the headlight (shading.wgsl), or with the
// key light and its shadows from the sample at index-space point `p` (shadows.wgsl).
fn shade(color: vec3<f32>, loc: Location, p: vec3<f32>, d_idx: vec3<f32>) -> vec3<f32> {
    if KEY_LIGHT {
        return shade_key_light(color, field_gradient(loc), d_idx, p);
    }
    return shade_gradient(color, field_gradient(loc), d_idx);
}

// The debug counters (COUNT_SAMPLES): this ray's samples and page-table reads, 64-bit sums.
fn count(samples: u32) {
    if COUNT_SAMPLES {
        let old = atomicAdd(&sample_counter[0], samples);
        if old > 0xffffffffu - samples {
            atomicAdd(&sample_counter[1], 1u);
        }
        // Index reads: page-table words (flat) or node-buffer words (octree).
        let reads = page_reads + octree_reads;
        let old_reads = atomicAdd(&sample_counter[2], reads);
        if old_reads > 0xffffffffu - reads {
            atomicAdd(&sample_counter[3], 1u);
        }
    }
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
    // Isosurface: where the hit is (take_sample), for its shading.
    hit_loc: Location,
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

// Front-to-back "over" of a premultiplied colour and its opacity at ray distance t; the
// contribution that takes the accumulated opacity to DEPTH_OPACITY sets the depth (layout.rs),
// its page is marked visible, early termination is checked.
fn composite(st: ptr<function, RayState>, premultiplied: vec3<f32>, alpha: f32, page: u32, t: f32) {
    mark_visible_in(st, page);
    let w = 1.0 - (*st).acc.a;
    (*st).acc = vec4<f32>((*st).acc.rgb + w * premultiplied, (*st).acc.a + w * alpha);
    if (*st).depth == positive_infinity() && (*st).acc.a >= DEPTH_OPACITY {
        (*st).depth = t;
    }
    if EARLY_TERMINATION && (*st).acc.a >= P.dims.w {
        (*st).done = true;
    }
}

// Composites the pre-integrated segment of `length` (mm) from value `front` to `back`
// (length-free: half segments, coarse levels and level changes are exact too).
fn composite_segment(st: ptr<function, RayState>, front: f32, back: f32, length: f32,
                     back_loc: Location, t: f32, o: vec3<f32>, d: vec3<f32>) {
    let seg = preintegrated_segment(front, back, length);
    if seg.a <= 0.0 {
        return;
    }
    var color = seg.rgb;
    if SHADING {
        // Lit at the segment's nearer sample: the gradient is only known at samples.
        color = shade(seg.rgb / seg.a, back_loc, o + d * t, d) * seg.a;
    }
    composite(st, color, seg.a, back_loc.page, t);
}

// The constant half segment after the last sample of a run (see take_sample).
fn close_preintegrated_run(st: ptr<function, RayState>, o: vec3<f32>, d: vec3<f32>) {
    if MODE == 0u && PREINTEGRATED && (*st).run_open && !(*st).done {
        let v = (*st).run_value;
        composite_segment(st, v, v, 0.5 * (*st).run_delta, (*st).run_loc, (*st).run_t, o, d);
    }
    (*st).run_open = false;
}

// `leaf`: the march's decoded page (with the octree, the leaf it holds), where an isosurface
// hit starts its bisection.
fn take_sample(st: ptr<function, RayState>, loc: Location, t: f32, delta: f32, o: vec3<f32>, d: vec3<f32>, leaf: Page) {
    (*st).samples = (*st).samples + 1u;
    let v = physical(field(loc));
    if MODE == 0u && PREINTEGRATED {
        // Segments join consecutive samples, which sit at segment midpoints; a run of samples
        // therefore starts with a constant half segment before its first sample and ends with
        // one after its last (close_preintegrated_run), so the integrated interval is the one
        // the classic path covers.
        if (*st).run_open {
            composite_segment(st, (*st).run_value, v, t - (*st).run_t, loc, t, o, d);
        } else {
            composite_segment(st, v, v, 0.5 * delta, loc, t, o, d);
        }
        (*st).run_value = v;
        (*st).run_t = t;
        (*st).run_delta = delta;
        (*st).run_loc = loc;
        (*st).run_open = true;
    } else if MODE == 0u {
        var tf = transfer(v);
        if OVERLAY {
            // overlay.wgsl: the blend rule, before opacity correction and shading.
            tf = overlay_blend(tf, overlay_at(o + d * t));
        }
        if tf.a > 0.0 {
            // Opacity correction: opacity is defined per finest voxel; a step of `delta` mm
            // must absorb as much as delta/unit such steps would.
            let alpha = 1.0 - pow(1.0 - min(tf.a, 0.999999), delta / P.box_hi.w);
            var color = tf.rgb;
            if SHADING {
                color = shade(color, loc, o + d * t, d);
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
            // The bisection's points mostly share one or two leaves: with the octree, a leaf
            // found is kept while the points stay in it (no descent per step), starting with
            // the leaf the march holds (the hit sample's, or the one before it): most hits
            // then need no point query at all. The hit's location (its shading gradient) is
            // the bisection's last leaf too. (locate_cached of a point in the leaf is that
            // leaf's page at the point's cell: the same Location a fresh query finds.)
            var near = leaf;
            if (*st).prev_valid {
                var lo = (*st).prev_t;
                var hi = t;
                for (var b = 0u; b < BISECTION_STEPS; b++) {
                    let mid = 0.5 * (lo + hi);
                    let m = locate_cached(o + d * mid, &near);
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
            (*st).hit_loc = locate_cached(o + d * t_hit, &near);
            mark_visible_in(st, (*st).hit_loc.page);
            (*st).done = true;
        } else {
            (*st).prev_t = t;
            (*st).prev_valid = true;
        }
    }
}

// What a MIP ray keeps: its maximum, where it was, what it marked, how many samples it took.
struct MipRay {
    best_value: f32,
    best_t: f32,
    have_best: bool,
    samples: u32,
    last_marked: u32,
};

// One MIP sample: the running maximum (ties keep the first), and the page marked visible once
// per visit where the TF makes a sample visible.
fn mip_sample(r: ptr<function, MipRay>, loc: Location, t: f32) {
    (*r).samples = (*r).samples + 1u;
    let v = physical(field(loc));
    if v > (*r).best_value {
        (*r).best_value = v;
        (*r).best_t = t;
        (*r).have_best = true;
    }
    if loc.page != (*r).last_marked && transfer(v).a > 0.0 {
        visibility[loc.page] = 1u;
        (*r).last_marked = loc.page;
    }
}

// MIP's lean march over [first, t1): the lattice, the coarse-node strides, the partial last
// segment and the skips of main's general march (so the same samples, the same image), with
// nothing but the maximum in flight. A region (whole node, not-resident block) that is
// skipped, empty, or whose value bound cannot beat the running maximum is left at its extent
// (skip_exit), and a page stops being sampled once the maximum reaches its bound.
fn march_mip(o: vec3<f32>, d: vec3<f32>, t1: f32, first: f32, base: f32) -> MipRay {
    var r: MipRay;
    r.best_value = -3.0e38;
    r.best_t = positive_infinity();
    r.have_best = false;
    r.samples = 0u;
    r.last_marked = 0xffffffffu;
    var k = 0u;
    var partial_start = positive_infinity();
    var pg: Page;
    pg.t_exit = -3.0e38;
    pg.resident = true;
    pg.whole_node = false;
    for (var iter = 0u; iter < MAX_ITERATIONS; iter++) {
        let seg = first + f32(k) * base;
        let probe_t = seg + 0.5 * base;
        if probe_t >= t1 {
            partial_start = seg;
            break;
        }
        let probe = locate_on_ray(o, d, probe_t, &pg);
        let cannot_win = SKIP_EMPTY && r.have_best && page_value_max[probe.page] <= r.best_value;
        if !probe.resident || (SKIP_EMPTY && probe.empty) || cannot_win {
            if SKIP_EMPTY {
                let next = ceil((skip_exit(o, d, pg) - first) / base - 0.5);
                k = max(k + 1u, u32(clamp(next, 0.0, 4.0e9)));
            } else {
                k = k + 1u;
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
            loc = locate_on_ray(o, d, t, &pg);
        }
        k = k + stride;
        if !loc.resident {
            continue;
        }
        mip_sample(&r, loc, t);
        if pg.level == level && pg.resident {
            var bound = positive_infinity();
            if SKIP_EMPTY {
                bound = page_value_max[pg.linear];
            }
            for (var inner = 0u; inner < MAX_ITERATIONS; inner++) {
                if r.best_value >= bound {
                    break;
                }
                let t_next = first + (f32(k) + 0.5 * f32(stride)) * base;
                if t_next >= t1 || t_next >= pg.t_exit {
                    break;
                }
                k = k + stride;
                mip_sample(&r, location_in(pg, clamp_to_volume(o + d * t_next)), t_next);
            }
        }
    }
    if partial_start < t1 {
        let t = partial_start + 0.5 * (t1 - partial_start);
        let loc = locate_traversal(o + d * t);
        if loc.resident && !(SKIP_EMPTY && loc.empty) {
            mip_sample(&r, loc, t);
        }
    }
    return r;
}

@compute @workgroup_size(WORKGROUP_SIZE, WORKGROUP_SIZE, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let width = P.image.x;
    let height = P.image.y;
    if gid.x >= width || gid.y >= height {
        return;
    }
    let pixel = gid.y * width + gid.x;
    let inf = positive_infinity();
    let half_extent = P.eye_idx.w;
    let sx = (2.0 * (f32(gid.x) + 0.5) / f32(width) - 1.0) * P.right_idx.w * half_extent;
    let sy = (1.0 - 2.0 * (f32(gid.y) + 0.5) / f32(height)) * half_extent;
    // Selects, not an `if`: a branch whose condition reads nothing but uniforms makes lavapipe
    // (Mesa 22.3) "inline" the uniform, i.e. clone, optimise and recompile the whole shader on
    // every dispatch whose uniform buffer changed (every frame): 3.6-7.4 ms per frame whatever
    // the image size (a 16² frame whose rays all miss: bench/lean-base/lavapipe.md).
    let orthographic = P.up_idx.w > 0.5;
    let len = sqrt(1.0 + sx * sx + sy * sy);
    let o = select(P.eye_idx.xyz, P.eye_idx.xyz + sx * P.right_idx.xyz + sy * P.up_idx.xyz,
                   orthographic);
    let d = select((P.forward_idx.xyz + sx * P.right_idx.xyz + sy * P.up_idx.xyz) / len,
                   P.forward_idx.xyz, orthographic);
    let plane_nd = select((P.clip.x + sx * P.clip.y + sy * P.clip.z) / len, P.clip.x,
                          orthographic);
    let plane_rhs = select(P.clip.w, P.clip.w - sx * P.clip.y - sy * P.clip.z, orthographic);

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
        let h = pcg(gid.x ^ pcg(gid.y ^ pcg(P.image.z)));
        j = min(f32(h) * 2.3283064e-10, 0.99999);
        // The shadow and occlusion rays' own offset (shadows.wgsl), from a further round of
        // the hash so that it does not follow the main ray's sample positions.
        shadow_jitter = min(f32(pcg(h ^ 0x9e3779b9u)) * 2.3283064e-10, 0.99999);
    }
    // Segment k spans [first + k·base, first + (k+1)·base): level-0 samples sit at
    // t0 + (k + j)·base, the midpoints when jitter is off. Coarse nodes take 2^L segments at
    // once, so every sample stays on one lattice and empty-space jumps cannot shift it.
    let first = t0 + (j - 0.5) * base;
    if MODE == 1u && LEAN_MIP {
        let r = march_mip(o, d, t1, first, base);
        var acc = vec4<f32>(0.0);
        var depth = inf;
        if r.have_best {
            var tf = transfer(r.best_value);
            if OVERLAY {
                // The overlay projected too: the first shown overlay sample on the ray,
                // blended as one DVR sample (overlay.rs).
                tf = overlay_blend(tf, overlay_first_on_ray(o, d, t0, t1, first, base));
            }
            acc = vec4<f32>(tf.rgb * tf.a, tf.a);
            if tf.a > 0.0 {
                depth = r.best_t;
            }
        }
        count(r.samples);
        textureStore(out_color, vec2<i32>(gid.xy), clamp(acc, vec4<f32>(0.0), vec4<f32>(1.0)));
        out_depth[pixel] = depth;
        return;
    }

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
    // Nothing decoded yet: the first lookup must read (locate_on_ray's same-region test).
    page_cache.resident = true;
    page_cache.whole_node = false;
    // DVR with an overlay: inside the overlay's box an empty page is sampled all the same (a
    // label may sit in tissue the TF makes transparent); before the box a skip stops at it.
    var overlay_span = vec2<f32>(1.0, 0.0);
    if OVERLAY && MODE == 0u {
        overlay_span = overlay_interval(o, d);
    }
    for (var iter = 0u; iter < MAX_ITERATIONS; iter++) {
        let seg = first + f32(k) * base;
        let probe_t = seg + 0.5 * base;
        if probe_t >= t1 {
            partial_start = seg;
            break;
        }
        let probe = locate_on_ray(o, d, probe_t, &page_cache);
        let in_overlay = OVERLAY && MODE == 0u && probe_t >= overlay_span.x
            && probe_t <= overlay_span.y;
        // MIP: a page whose bound cannot beat the running maximum cannot change the pixel
        // (ties keep the first maximum), so it is skipped like an empty one.
        // (Empty flags and MIP bounds cover the coarser field a transition band blends in:
        // PageTable::sampled_ranges.)
        let mip_cannot_win = MODE == 1u && SKIP_EMPTY && st.have_best
            && page_value_max[probe.page] <= st.best_value;
        if !probe.resident || (SKIP_EMPTY && probe.empty && !in_overlay) || mip_cannot_win {
            if SKIP_EMPTY {
                // Every cell of the region skip_exit leaves is skipped the same way (same
                // word, same bound, no sample in between to raise the MIP maximum).
                var t_exit = skip_exit(o, d, page_cache);
                if OVERLAY && MODE == 0u && probe_t < overlay_span.x
                    && overlay_span.x <= overlay_span.y {
                    t_exit = min(t_exit, overlay_span.x);
                }
                let next = ceil((t_exit - first) / base - 0.5);
                k = max(k + 1u, u32(clamp(next, 0.0, 4.0e9)));
                st.prev_valid = false;
                close_preintegrated_run(&st, o, d);
                if MODE == 2u && probe.resident {
                    // Empty for an isosurface means below the iso value: the crossing lies
                    // after the cell face, so bisection may start there.
                    st.prev_t = max(t_exit, t0);
                    st.prev_valid = true;
                }
            } else {
                k = k + 1u;
                st.prev_valid = false;
                close_preintegrated_run(&st, o, d);
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
            close_preintegrated_run(&st, o, d);
            continue;
        }
        take_sample(&st, loc, t, delta, o, d, page_cache);
        if st.done {
            break;
        }
        // Fast path: while the next sample stays in the decoded page at the same level, march
        // with nothing but position, fetch and compositing (the common case by far).
        if page_cache.level == level && page_cache.resident {
            var page_bound = positive_infinity();
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
                take_sample(&st, location_in(page_cache, clamp_to_volume(o + d * t_next)), t_next, delta, o, d, page_cache);
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
        let loc = locate_traversal(o + d * t);
        let in_overlay = OVERLAY && MODE == 0u && t >= overlay_span.x && t <= overlay_span.y;
        if loc.resident && !(SKIP_EMPTY && loc.empty && !in_overlay) {
            take_sample(&st, loc, t, length, o, d, page_cache);
        }
    }
    close_preintegrated_run(&st, o, d);
    var acc = st.acc;
    var depth = st.depth;
    let samples = st.samples;
    let have_best = st.have_best;
    let best_value = st.best_value;
    let best_t = st.best_t;
    let hit = st.hit;
    let hit_loc = st.hit_loc;

    if MODE == 1u && have_best {
        var tf = transfer(best_value);
        if OVERLAY {
            tf = overlay_blend(tf, overlay_first_on_ray(o, d, t0, t1, first, base));
        }
        acc = vec4<f32>(tf.rgb * tf.a, tf.a);
        if tf.a > 0.0 {
            depth = best_t;
        }
    }
    if MODE == 2u && hit {
        var base_color = P.iso_color.rgb;
        if OVERLAY {
            // The surface takes the overlay's colour at the hit, mixed by its opacity.
            let ov = overlay_at(o + d * depth);
            base_color = base_color + (ov.rgb - base_color) * ov.a;
        }
        acc = vec4<f32>(shade(base_color, hit_loc, o + d * depth, d), 1.0);
    }
    count(samples);
    textureStore(out_color, vec2<i32>(gid.xy), clamp(acc, vec4<f32>(0.0), vec4<f32>(1.0)));
    out_depth[pixel] = depth;
}
