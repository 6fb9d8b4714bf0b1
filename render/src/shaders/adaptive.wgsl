// Adaptive sampling in three dimensions (adaptive-sampling-3d §3.1-3.4) as one compute pass:
// the tiled twin of adaptive/transcription.rs (Figs. 3, 5, 6), composed after the field files
// and preintegration.wgsl by shaders.rs.
//
// One workgroup per TILE² screen tile of level-0 pixels. Levels 1..L_MAX of the image pyramid
// live in workgroup memory with a one-pixel apron per level: a pixel's state depends only on
// its own history and its 2×2 parents, so the tile, apron included, evolves exactly as the
// same pixels of the global algorithm, and the tiled image equals the global one. Level-0
// pixels belong to one invocation each (TILE²/64 per invocation) and live in its registers.
// All loops around barriers run over the frame's slices and the levels l_slice..1, which are
// the same for the whole workgroup (WGSL requires barriers in uniform control flow).

override TILE: u32 = 16u;
override L_MAX: u32 = 3u;
override ORACLE: u32 = 0u;       // 0 per page entry, 1 constant, 2 hash (tests), 3 per block
// The tile's decisions (transcription.rs TileRules, which the CPU side follows too), at the
// early-termination opacity: a level-0 pixel that reached it stops sampling; every 2^L_MAX
// slices (where every pixel has just accumulated) a coarser pixel closes once every finer
// pixel it feeds is closed, and the tile stops once all its pixels are.
override EARLY_TERMINATION: bool = false;
// Data oracles: a tile none of whose rays meets the box is written transparent without
// marching, and each tile marches only over the slices its rays can meet the box in.
override TILE_SLICE_RANGES: bool = true;
// A clip plane is set (the outside distance then includes the plane's).
override CLIPPED: bool = false;
// Maximum intensity projection (transcription.rs SegmentOptics::maximum_intensity): level-0
// pixels keep their largest accumulated value and its slice (in acc: value, slice, taken)
// instead of compositing, and are coloured by the TF at it at the end.
override MIP: bool = false;
// Idle slices: a slice of l_slice < L_MAX changes nothing unless some open pixel of levels
// 0..l_slice has d < 2^(l_slice+1) (no probe, synthesis or segment happens otherwise, by the
// rules below), and d changes only where something happens. So after each slice the tile
// takes the least d over its open pixels of levels 0..L_MAX−1 (slices of l_slice = L_MAX are
// never idle) and goes straight to the next multiple of 2^⌊log2 d⌋: the image and every
// counter stay those of the full march, with fewer passes through the slice loop, whose
// barriers and per-pixel checks (not the samples) bound the frame on a CPU rasteriser.
override SKIP_IDLE_SLICES: bool = true;
// Shaded DVR: the pyramid carries the field's gradient beside the value (sampled where the
// value is sampled, synthesised with the same weights where it is synthesised), and each
// level-0 segment is lit at its back sample's gradient, as the raycaster lights a
// pre-integrated segment (shading.wgsl); the transcription does the same (SegmentOptics::shade).
override SHADED: bool = false;
// The key light (shadows.wgsl KEY_LIGHT, SHADOWS; ambient_occlusion.wgsl OCCLUSION,
// scattering.wgsl SCATTERING), with SHADED only: each lit level-0 segment is lit by
// shade_key_light at its back sample, so an exact shadow ray is traced per segment the pass
// composites, and the segments adaptive sampling saves are shadow rays saved. shadow_span
// needs the raycaster's names for the clip plane and empty skipping: the adaptive pass sets
// CLIP_PLANE with CLIPPED, SKIP_EMPTY from the settings.
override CLIP_PLANE: bool = false;
override SKIP_EMPTY: bool = true;

// THREADS (8×8), MAX_OWNED (level-0 pixels an invocation owns at the largest tile),
// PYRAMID_CAP (levels 1..3 with apron at the largest tile), the bindings below and the
// counters' slots are generated from adaptive/gpu.rs.

struct AdaptiveParams {
    frame: vec4<f32>,      // t_front (mm), slice spacing (mm), default value, constant distance
    pyramid: vec4<u32>,    // padded width, padded height, last slice, hash seed
    viewport: vec4<u32>,   // width, height, the cache's slots along x and y
};

// The oracle's distances come from the data (per page entry or per block): the tile may then
// skip what its rays cannot meet.
fn data_oracle() -> bool {
    return ORACLE == 0u || ORACLE == 3u;
}

// Index of the per-block oracle's table (block_oracle.rs): slot · blocks per slot + in-slot block of a
// location, from the in-slot coordinate (voxel centres at integers, core voxel i at i + apron)
// kept apart from the slot's corner, so the block does not depend on where the brick landed.
fn adaptive_block(slot_base: vec3<f32>, coord: vec3<f32>) -> u32 {
    let slot = vec3<u32>(round(slot_base / f32(PAYLOAD)));
    let slot_linear = slot.x + A.viewport.z * (slot.y + A.viewport.w * slot.z);
    let n = ORACLE_BLOCKS_PER_AXIS;
    let b = vec3<u32>(clamp(floor((coord - vec3<f32>(APRON - 0.5)) / ORACLE_BLOCK), vec3<f32>(0.0), vec3<f32>(f32(n - 1u))));
    return slot_linear * (n * n * n) + b.x + n * (b.y + n * b.z);
}

@group(0) @binding(BINDING_ADAPTIVE_PARAMS) var<uniform> A: AdaptiveParams;
@group(0) @binding(BINDING_ORACLE) var<storage, read> oracle_distance: array<f32>;
@group(0) @binding(BINDING_OUT_COLOR) var out_color: texture_storage_2d<rgba8unorm, write>;
// 16 is shadows.wgsl's light cache (bound, never read: the pass has no cache-mode shadows).
@group(0) @binding(BINDING_OUT_RGBA) var<storage, read_write> out_rgba: array<vec4<f32>>;
@group(0) @binding(BINDING_OUT_DEPTH) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(BINDING_VISIBILITY) var<storage, read_write> visibility: array<u32>;
// Samples per level (owned pixels), syntheses per level (owned), segments, apron samples per
// level (the tiling's overhead), slices the tiles marched, shadow rays traced (KEY_LIGHT with
// SHADOWS: one per lit level-0 segment), invocations whose slice loop the device cut short
// (see the end of main): slots COUNTER_* (adaptive/gpu.rs).
@group(0) @binding(BINDING_COUNTERS) var<storage, read_write> counters: array<atomic<u32>, COUNTERS>;

var<workgroup> pyramid_s: array<f32, PYRAMID_CAP>;
var<workgroup> tile_vote: atomic<u32>;
var<workgroup> tile_decision: u32;
// The tile's slice range: the nearest entry and farthest exit (t as f32 bits, t ≥ 0 so the
// bits order like the values) over every ray the tile samples, then the slices they allow.
var<workgroup> tile_t_entry: atomic<u32>;
var<workgroup> tile_t_exit: atomic<u32>;
var<workgroup> tile_first_slice: u32;
var<workgroup> tile_last_slice: u32;
var<workgroup> pyramid_d: array<f32, PYRAMID_CAP>;
// SHADED: the gradient (index space, physical units per index step) per pyramid pixel.
var<workgroup> pyramid_g: array<vec3<f32>, PYRAMID_CAP>;
// Early termination's closed pixels: one bit per level-0 pixel of the tile (32² / 32 words),
// and a flag per pixel of levels 1..L_MAX, apron included (an apron pixel never closes).
var<workgroup> closed_level0: array<atomic<u32>, 32>;
var<workgroup> pyramid_closed: array<u32, PYRAMID_CAP>;
// The least d over the tile's open pixels after a marched slice (f32 bits; d > 0, so the
// bits order like the values). Three in turn: the n-th marched slice gathers into n mod 3 and
// resets n + 2 mod 3, which nobody reads or writes until two barriers later.
var<workgroup> tile_least_distance: array<atomic<u32>, 3>;

// Edge of level l's tile with its apron, and where level l starts in the pyramid arrays.
fn extent(l: u32) -> u32 {
    return (TILE >> l) + 2u;
}

fn level_offset(l: u32) -> u32 {
    var o = 0u;
    for (var k = 1u; k < l; k++) {
        let e = extent(k);
        o += e * e;
    }
    return o;
}

fn adaptive_pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// oracle.rs hash_distance.
fn adaptive_hash(level: u32, x: u32, y: u32, slice: u32) -> f32 {
    let h = adaptive_pcg(x ^ adaptive_pcg(y ^ adaptive_pcg(slice ^ adaptive_pcg(level ^ adaptive_pcg(A.pyramid.w)))));
    return f32(1u + h % (2u << L_MAX));
}

// The shadow ray's traversal (shadows.wgsl shadow_span calls these; raycast.wgsl has its own
// with the octree): raycast.wgsl's flat-table path with node extents. The decoded page is
// kept until the ray leaves its cell; a whole node or not-resident block is crossed without
// reading its (identical) entries.
fn locate_on_ray(o: vec3<f32>, d: vec3<f32>, t: f32, cached: ptr<function, Page>) -> Location {
    let pc = clamp_to_volume(o + d * t);
    if t >= (*cached).t_exit {
        let cell = cell_of(pc);
        let shift = vec3<u32>((*cached).level);
        let same_region = ((*cached).whole_node || !(*cached).resident)
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

// Where the ray leaves page cell `cell` (index-space box of CORE voxel cells).
fn cell_exit(o: vec3<f32>, d: vec3<f32>, cell: vec3<f32>) -> f32 {
    let lo = cell * CORE - vec3<f32>(0.5);
    let bound = select(lo, lo + vec3<f32>(CORE), d > vec3<f32>(0.0));
    let t = select((bound - o) / d, vec3<f32>(3.0e38), abs(d) < vec3<f32>(1e-20));
    return min(t.x, min(t.y, t.z));
}

// Where the ray leaves the region a skipped entry stands for: its whole node or not-resident
// block, else its cell (raycast.wgsl skip_exit, flat table).
fn skip_exit(o: vec3<f32>, d: vec3<f32>, pg: Page) -> f32 {
    if (pg.whole_node || !pg.resident) && pg.level > 0u {
        let cells = f32(1u << pg.level);
        let node = vec3<f32>(vec3<u32>(pg.cell) >> vec3<u32>(pg.level));
        let lo = node * (CORE * cells) - vec3<f32>(0.5);
        let bound = select(lo, lo + vec3<f32>(CORE * cells), d > vec3<f32>(0.0));
        let t = select((bound - o) / d, vec3<f32>(3.0e38), abs(d) < vec3<f32>(1e-20));
        return min(t.x, min(t.y, t.z));
    }
    return pg.t_exit;
}

struct Probe {
    value: f32,
    distance: f32,
    // SHADED: the field's gradient there (zero where nothing is resident).
    gradient: vec3<f32>,
    page: u32,
    hit: bool,
};

struct PixelRay {
    o: vec3<f32>,
    d: vec3<f32>,
    // The ray's interval in the cropped box and the clip half-space; t1 < t0 if it misses.
    t0: f32,
    t1: f32,
    // Clip plane along this ray: a point at t is on the clipped side by rhs − t·nd (mm).
    plane_nd: f32,
    plane_rhs: f32,
};

// The ray through level-0 pixel coordinates (u, v) (frame.rs SliceFrame::ray) and its
// interval, as reference.rs ray_interval (a zero clip row when there is none changes nothing).
fn pixel_ray(u: f32, v: f32) -> PixelRay {
    let half_extent = P.eye_idx.w;
    let sx = (2.0 * (u + 0.5) / f32(A.viewport.x) - 1.0) * P.right_idx.w * half_extent;
    let sy = (1.0 - 2.0 * (v + 0.5) / f32(A.viewport.y)) * half_extent;
    var r: PixelRay;
    // Selects, not an `if` on a uniform: see main in raycast.wgsl (lavapipe recompiles).
    let orthographic = P.up_idx.w > 0.5;
    let len = sqrt(1.0 + sx * sx + sy * sy);
    r.o = select(P.eye_idx.xyz, P.eye_idx.xyz + sx * P.right_idx.xyz + sy * P.up_idx.xyz,
                 orthographic);
    r.d = select((P.forward_idx.xyz + sx * P.right_idx.xyz + sy * P.up_idx.xyz) / len,
                 P.forward_idx.xyz, orthographic);
    let plane_nd = select((P.clip.x + sx * P.clip.y + sy * P.clip.z) / len, P.clip.x,
                          orthographic);
    let plane_rhs = select(P.clip.w, P.clip.w - sx * P.clip.y - sy * P.clip.z, orthographic);
    var t0 = 0.0;
    var t1 = 3.0e38;
    var miss = false;
    for (var a = 0u; a < 3u; a++) {
        if abs(r.d[a]) < 1e-12 {
            if r.o[a] < P.box_lo[a] || r.o[a] > P.box_hi[a] {
                miss = true;
            }
        } else {
            let ta = (P.box_lo[a] - r.o[a]) / r.d[a];
            let tb = (P.box_hi[a] - r.o[a]) / r.d[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
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
    r.t0 = t0;
    r.t1 = select(t1, -1.0, miss);
    r.plane_nd = plane_nd;
    r.plane_rhs = plane_rhs;
    return r;
}

// The per-node oracle outside the cropped box and clip half-space: the largest power of two
// of slices not longer than a lower bound of the distance to them (the larger of the distance
// to the box, in finest voxels, and to the plane), so a ray arriving from outside has slowed
// down to d = 1 when it enters (oracle.rs outside_distance).
fn outside_distance(ray: PixelRay, t: f32) -> f32 {
    let p = ray.o + ray.d * t;
    let box_mm = length(max(P.box_lo.xyz - p, vec3<f32>(0.0)) + max(p - P.box_hi.xyz, vec3<f32>(0.0))) * P.box_hi.w;
    var plane_mm = 0.0;
    if CLIPPED {
        plane_mm = max(ray.plane_rhs - t * ray.plane_nd, 0.0);
    }
    let slices = max(box_mm, plane_mm) / A.frame.y;
    return clamp(exp2(floor(log2(max(slices, 1.0)))), 1.0, f32(1u << L_MAX));
}

fn level_coordinate(level: u32, x: u32) -> f32 {
    return f32(1u << level) * (f32(x) + 0.5) - 0.5;
}

// SAMPLE and ORACLE (Fig. 5) of level-l pixel (x, y) on slice `slice`: the ray through
// level-0 pixel coordinates 2^l(x + ½) − ½ (frame.rs), at the slice's distance.
fn probe(level: u32, x: u32, y: u32, slice: u32) -> Probe {
    let ray = pixel_ray(level_coordinate(level, x), level_coordinate(level, y));
    let o = ray.o;
    let d = ray.d;
    let t0 = ray.t0;
    let t1 = ray.t1;
    let t = A.frame.x + f32(slice) * A.frame.y;
    var r: Probe;
    r.value = A.frame.z;
    r.distance = f32(1u << L_MAX);
    r.page = 0u;
    r.hit = false;
    r.gradient = vec3<f32>(0.0);
    var inside = false;
    if t >= t0 && t <= t1 {
        let loc = locate(o + d * t);
        inside = true;
        if loc.resident {
            r.value = physical(field(loc));
            if SHADED {
                r.gradient = field_gradient(loc);
            }
            r.page = loc.page;
            r.hit = true;
            if ORACLE == 0u {
                r.distance = oracle_distance[loc.page];
            } else if ORACLE == 3u {
                // A slot past the table's end (uploaded after it was built) is sampled finely.
                let k = adaptive_block(loc.slot_base, loc.coord);
                r.distance = select(1.0, oracle_distance[min(k, arrayLength(&oracle_distance) - 1u)], k < arrayLength(&oracle_distance));
            }
        }
    }
    if data_oracle() && !inside {
        r.distance = outside_distance(ray, t);
    }
    if ORACLE == 1u {
        r.distance = A.frame.w;
    } else if ORACLE == 2u {
        r.distance = adaptive_hash(level, x, y, slice);
    }
    return r;
}

// Pages whose samples the TF does not hide are visible (the loader refines by these words).
fn mark_visible(p: Probe) {
    if p.hit && extinction_at(p.value) > 0.0 {
        visibility[p.page] = 1u;
    }
}

struct Synthesis {
    value: f32,
    distance: f32,
    // SHADED only.
    gradient: vec3<f32>,
};

// SYNTHESIZE (Fig. 5) of level-l pixel (gx, gy) from level l+1 in workgroup memory: s, d (and
// the gradient when SHADED). Parents outside the image are clamped to its edge, as in
// transcription.rs.
fn synthesize(l: u32, gx: u32, gy: u32, tile_x: u32, tile_y: u32) -> Synthesis {
    let pl = l + 1u;
    let pw = i32(A.pyramid.x >> pl);
    let ph = i32(A.pyramid.y >> pl);
    let e = i32(extent(pl));
    let off = level_offset(pl);
    let ox = i32(tile_x >> pl) - 1;
    let oy = i32(tile_y >> pl) - 1;
    let hx = i32((gx + 1u) / 2u);
    let hy = i32((gy + 1u) / 2u);
    let fx = select(0.0, 0.5, (gx & 1u) == 1u);
    let fy = select(0.0, 0.5, (gy & 1u) == 1u);
    let xs = array<i32, 2>(clamp(hx - 1, 0, pw - 1) - ox, clamp(hx, 0, pw - 1) - ox);
    let ys = array<i32, 2>(clamp(hy - 1, 0, ph - 1) - oy, clamp(hy, 0, ph - 1) - oy);
    let wx = array<f32, 2>(0.25 + fx, 0.75 - fx);
    let wy = array<f32, 2>(0.25 + fy, 0.75 - fy);
    var sum = vec2<f32>(0.0);
    var gradient = vec3<f32>(0.0);
    for (var j = 0u; j < 2u; j++) {
        for (var i = 0u; i < 2u; i++) {
            let k = off + u32(ys[j] * e + xs[i]);
            let w = wx[i] * wy[j];
            sum += w * vec2<f32>(pyramid_s[k], pyramid_d[k]);
            if SHADED {
                gradient += w * pyramid_g[k];
            }
        }
    }
    return Synthesis(sum.x, sum.y, gradient);
}

// Early termination's closing step (transcription.rs TileRules::early_termination): level-0
// pixels at the opacity threshold are closed; a pixel of level l ≥ 1 closes when it is the
// tile's own (not apron) and every child its synthesis feeds (2p−1..2p+2 per axis, inside the
// level) is a closed pixel of this tile. Called in uniform control flow.
fn close_opaque_pixels(tile_x: u32, tile_y: u32, lid: u32, acc: ptr<function, array<vec4<f32>, MAX_OWNED>>) {
    for (var w = lid; w < 32u; w += THREADS) {
        atomicStore(&closed_level0[w], 0u);
    }
    workgroupBarrier();
    for (var j = 0u; j < (TILE * TILE) / THREADS; j++) {
        let idx = lid + j * THREADS;
        if tile_x + idx % TILE < A.pyramid.x && tile_y + idx / TILE < A.pyramid.y && (*acc)[j].a >= P.dims.w {
            atomicOr(&closed_level0[idx / 32u], 1u << (idx % 32u));
        }
    }
    workgroupBarrier();
    for (var l = 1u; l <= L_MAX; l++) {
        let e = extent(l);
        let off = level_offset(l);
        let ox = i32(tile_x >> l) - 1;
        let oy = i32(tile_y >> l) - 1;
        let wf = i32(A.pyramid.x >> (l - 1u));
        let hf = i32(A.pyramid.y >> (l - 1u));
        let ec = i32(extent(l - 1u));
        let offc = level_offset(l - 1u);
        let oxc = i32(tile_x >> (l - 1u)) - 1;
        let oyc = i32(tile_y >> (l - 1u)) - 1;
        for (var idx = lid; idx < e * e; idx += THREADS) {
            let lx = idx % e;
            let ly = idx / e;
            let gx = ox + i32(lx);
            let gy = oy + i32(ly);
            var all_closed = lx >= 1u && ly >= 1u && lx + 2u <= e && ly + 2u <= e;
            for (var cy = max(2 * gy - 1, 0); cy < min(2 * gy + 3, hf) && all_closed; cy++) {
                for (var cx = max(2 * gx - 1, 0); cx < min(2 * gx + 3, wf) && all_closed; cx++) {
                    if l == 1u {
                        let tx = cx - i32(tile_x);
                        let ty = cy - i32(tile_y);
                        let inside = tx >= 0 && ty >= 0 && tx < i32(TILE) && ty < i32(TILE);
                        if inside {
                            let bit = u32(ty) * TILE + u32(tx);
                            all_closed = (atomicLoad(&closed_level0[bit / 32u]) & (1u << (bit % 32u))) != 0u;
                        } else {
                            all_closed = false;
                        }
                    } else {
                        let lxc = cx - oxc;
                        let lyc = cy - oyc;
                        let child_owned = lxc >= 1 && lyc >= 1 && lxc + 2 <= ec && lyc + 2 <= ec;
                        all_closed = child_owned && pyramid_closed[offc + u32(lyc * ec + lxc)] != 0u;
                    }
                }
            }
            pyramid_closed[off + idx] = select(0u, 1u, all_closed);
        }
        workgroupBarrier();
    }
}

// SKIP_IDLE_SLICES: the largest k ≤ L_MAX with 2^k ≤ the least d over the tile's open pixels
// of levels 0..L_MAX−1 (inside the image, not closed), so slices of l_slice < k are idle.
// Compared as powers of two, not through log2, whose rounding could skip a slice that acts.
// Called in uniform control flow (it holds the tile's barrier).
fn least_distance_level(
    tile_x: u32,
    tile_y: u32,
    lid: u32,
    marched: u32,
    d0: ptr<function, array<f32, MAX_OWNED>>,
    acc: ptr<function, array<vec4<f32>, MAX_OWNED>>,
) -> u32 {
    var least = positive_infinity();
    for (var j = 0u; j < (TILE * TILE) / THREADS; j++) {
        let idx = lid + j * THREADS;
        let open = !EARLY_TERMINATION || (*acc)[j].a < P.dims.w;
        if open && tile_x + idx % TILE < A.pyramid.x && tile_y + idx / TILE < A.pyramid.y {
            least = min(least, (*d0)[j]);
        }
    }
    for (var l = 1u; l < L_MAX; l++) {
        let e = extent(l);
        let off = level_offset(l);
        let ox = i32(tile_x >> l) - 1;
        let oy = i32(tile_y >> l) - 1;
        let wl = i32(A.pyramid.x >> l);
        let hl = i32(A.pyramid.y >> l);
        for (var idx = lid; idx < e * e; idx += THREADS) {
            let gx = ox + i32(idx % e);
            let gy = oy + i32(idx / e);
            let inside = gx >= 0 && gy >= 0 && gx < wl && gy < hl;
            if inside && !(EARLY_TERMINATION && pyramid_closed[off + idx] != 0u) {
                least = min(least, pyramid_d[off + idx]);
            }
        }
    }
    atomicMin(&tile_least_distance[marched % 3u], bitcast<u32>(least));
    let tile_least = bitcast<f32>(workgroupUniformLoad(&tile_least_distance[marched % 3u]));
    if lid == 0u {
        atomicStore(&tile_least_distance[(marched + 2u) % 3u], 0x7f800000u);
    }
    var k = 0u;
    for (var c = 1u; c <= L_MAX; c++) {
        if f32(1u << c) <= tile_least {
            k = c;
        }
    }
    return k;
}

@compute @workgroup_size(THREADS_PER_AXIS, THREADS_PER_AXIS, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let tile_x = wid.x * TILE;
    let tile_y = wid.y * TILE;
    let owned = (TILE * TILE) / THREADS;
    let width = A.pyramid.x;
    let height = A.pyramid.y;
    let inf = positive_infinity();
    var s0: array<f32, MAX_OWNED>;
    var d0: array<f32, MAX_OWNED>;
    var g0: array<vec3<f32>, MAX_OWNED>;
    var s_prev: array<f32, MAX_OWNED>;
    var i_prev: array<u32, MAX_OWNED>;
    var acc: array<vec4<f32>, MAX_OWNED>;
    var depth: array<f32, MAX_OWNED>;
    for (var j = 0u; j < MAX_OWNED; j++) {
        acc[j] = vec4<f32>(0.0);
        depth[j] = inf;
        s0[j] = 0.0;
        d0[j] = 0.0;
        g0[j] = vec3<f32>(0.0);
        s_prev[j] = 0.0;
        i_prev[j] = 0u;
    }
    // Per-node oracle: does any ray this tile samples (level-0 pixels and every coarser
    // level's, apron included) meet the box in front of the last slice? If not, every sample
    // would be the default value: the tile is transparent (if the TF is there; a uniform
    // condition: the value is a frame parameter).
    if data_oracle() && TILE_SLICE_RANGES && extinction_at(A.frame.z) <= 0.0 {
        if lid == 0u {
            atomicStore(&tile_vote, 0u);
            atomicStore(&tile_t_entry, 0x7f800000u);
            atomicStore(&tile_t_exit, 0u);
        }
        workgroupBarrier();
        let t_last = A.frame.x + f32(A.pyramid.z) * A.frame.y;
        var hit = false;
        var t_entry = inf;
        var t_exit = 0.0;
        for (var j = 0u; j < owned; j++) {
            let idx = lid + j * THREADS;
            let r = pixel_ray(f32(tile_x + idx % TILE), f32(tile_y + idx / TILE));
            let meets = r.t1 >= r.t0 && r.t0 <= t_last;
            hit = hit || meets;
            if meets {
                t_entry = min(t_entry, r.t0);
                t_exit = max(t_exit, r.t1);
            }
        }
        for (var l = 1u; l <= L_MAX; l++) {
            let e = extent(l);
            for (var idx = lid; idx < e * e; idx += THREADS) {
                let gx = i32(tile_x >> l) - 1 + i32(idx % e);
                let gy = i32(tile_y >> l) - 1 + i32(idx / e);
                let u = f32(1u << l) * (f32(gx) + 0.5) - 0.5;
                let v = f32(1u << l) * (f32(gy) + 0.5) - 0.5;
                let r = pixel_ray(u, v);
                let meets = r.t1 >= r.t0 && r.t0 <= t_last;
                hit = hit || meets;
                if meets {
                    t_entry = min(t_entry, r.t0);
                    t_exit = max(t_exit, r.t1);
                }
            }
        }
        if hit {
            atomicOr(&tile_vote, 1u);
            atomicMin(&tile_t_entry, bitcast<u32>(max(t_entry, 0.0)));
            atomicMax(&tile_t_exit, bitcast<u32>(max(t_exit, 0.0)));
        }
        workgroupBarrier();
        if lid == 0u {
            tile_decision = atomicLoad(&tile_vote);
            // Before the first entry and after the last exit every sample is the transparent
            // default, and a segment between two of them adds nothing: march only from the
            // last slice of l_slice = l_max before every entry to the first one after every
            // exit (slices of l_max rebuild the whole pyramid, so the march from there is
            // the full march's, sample for sample). One block of margin each side for the
            // rounding of t.
            let block = 1u << L_MAX;
            let entry = (bitcast<f32>(atomicLoad(&tile_t_entry)) - A.frame.x) / A.frame.y;
            let exit = (bitcast<f32>(atomicLoad(&tile_t_exit)) - A.frame.x) / A.frame.y;
            var first = 0u;
            if entry > f32(2u * block) {
                first = (u32(entry) / block - 1u) * block;
            }
            var last = A.pyramid.z;
            if exit + f32(2u * block) < f32(A.pyramid.z) {
                last = min((u32(exit) / block + 2u) * block, A.pyramid.z);
            }
            tile_first_slice = min(first, A.pyramid.z);
            tile_last_slice = last;
        }
        if workgroupUniformLoad(&tile_decision) == 0u {
            for (var j = 0u; j < owned; j++) {
                let idx = lid + j * THREADS;
                let gx = tile_x + idx % TILE;
                let gy = tile_y + idx / TILE;
                if gx < A.viewport.x && gy < A.viewport.y {
                    let pixel = gy * A.viewport.x + gx;
                    out_rgba[pixel] = vec4<f32>(0.0);
                    out_depth[pixel] = inf;
                    textureStore(out_color, vec2<i32>(i32(gx), i32(gy)), vec4<f32>(0.0));
                }
            }
            return;
        }
    }
    var n_samples = array<u32, 4>(0u, 0u, 0u, 0u);
    var n_synth = array<u32, 4>(0u, 0u, 0u, 0u);
    var n_apron = array<u32, 4>(0u, 0u, 0u, 0u);
    var n_segments = 0u;
    var n_shadow_rays = 0u;
    var first_slice = 0u;
    var last_slice = A.pyramid.z;
    if data_oracle() && TILE_SLICE_RANGES && extinction_at(A.frame.z) <= 0.0 {
        first_slice = workgroupUniformLoad(&tile_first_slice);
        last_slice = workgroupUniformLoad(&tile_last_slice);
    }
    for (var j = 0u; j < MAX_OWNED; j++) {
        i_prev[j] = first_slice;
        s_prev[j] = A.frame.z;
    }
    if EARLY_TERMINATION {
        for (var idx = lid; idx < PYRAMID_CAP; idx += THREADS) {
            pyramid_closed[idx] = 0u;
        }
    }
    if lid == 0u {
        for (var k = 0u; k < 3u; k++) {
            atomicStore(&tile_least_distance[k], 0x7f800000u);
        }
    }
    workgroupBarrier();
    var marched = 0u;
    var stopped_by_tile = false;
    var i = first_slice;
    loop {
        if i > last_slice {
            break;
        }
        var ls = L_MAX;
        if i != 0u {
            ls = min(countTrailingZeros(i), L_MAX);
        }
        let skip_bound = f32(2u << ls);
        // Levels l_slice..1 of Fig. 3, apron included.
        for (var l = ls; l >= 1u; l--) {
            let e = extent(l);
            let off = level_offset(l);
            let ox = i32(tile_x >> l) - 1;
            let oy = i32(tile_y >> l) - 1;
            let wl = i32(width >> l);
            let hl = i32(height >> l);
            for (var idx = lid; idx < e * e; idx += THREADS) {
                let lx = idx % e;
                let ly = idx / e;
                let gx = ox + i32(lx);
                let gy = oy + i32(ly);
                if gx < 0 || gy < 0 || gx >= wl || gy >= hl {
                    continue;
                }
                let k = off + idx;
                if EARLY_TERMINATION && pyramid_closed[k] != 0u {
                    continue;
                }
                let is_owned = lx >= 1u && ly >= 1u && lx + 2u <= e && ly + 2u <= e;
                if l < ls && (ls == L_MAX || pyramid_d[k] < skip_bound) {
                    let syn = synthesize(l, u32(gx), u32(gy), tile_x, tile_y);
                    pyramid_d[k] = syn.distance;
                    pyramid_s[k] = syn.value;
                    if SHADED {
                        pyramid_g[k] = syn.gradient;
                    }
                    if is_owned {
                        n_synth[l] += 1u;
                    }
                }
                if l == L_MAX || pyramid_d[k] < f32(2u << l) {
                    let p = probe(l, u32(gx), u32(gy), i);
                    pyramid_d[k] = p.distance;
                    pyramid_s[k] = p.value;
                    if SHADED {
                        pyramid_g[k] = p.gradient;
                    }
                    mark_visible(p);
                    if is_owned {
                        n_samples[l] += 1u;
                    } else {
                        n_apron[l] += 1u;
                    }
                }
            }
            workgroupBarrier();
        }
        // Level 0: this invocation's own pixels, with ACCUMULATECOLOR (Fig. 6).
        for (var j = 0u; j < owned; j++) {
            let idx = lid + j * THREADS;
            let gx = tile_x + idx % TILE;
            let gy = tile_y + idx / TILE;
            if gx >= width || gy >= height {
                continue;
            }
            if EARLY_TERMINATION && acc[j].a >= P.dims.w {
                continue;
            }
            if 0u < ls && (ls == L_MAX || d0[j] < skip_bound) {
                let syn = synthesize(0u, gx, gy, tile_x, tile_y);
                d0[j] = syn.distance;
                s0[j] = syn.value;
                g0[j] = syn.gradient;
                n_synth[0] += 1u;
            }
            if d0[j] < 2.0 {
                let p = probe(0u, gx, gy, i);
                d0[j] = p.distance;
                s0[j] = p.value;
                g0[j] = p.gradient;
                mark_visible(p);
                n_samples[0] += 1u;
            }
            if MIP && (ls == L_MAX || d0[j] < skip_bound) {
                // The first of equal maxima stays, as in the transcription.
                if acc[j].z == 0.0 || s0[j] > acc[j].x {
                    acc[j] = vec4<f32>(s0[j], f32(i), 1.0, 0.0);
                }
                if i > first_slice {
                    n_segments += 1u;
                }
                s_prev[j] = s0[j];
                i_prev[j] = i;
            } else if ls == L_MAX || d0[j] < skip_bound {
                if i > first_slice {
                    let slices = i - i_prev[j];
                    var seg = preintegrated_segment(s_prev[j], s0[j], f32(slices) * A.frame.y);
                    if SHADED && seg.a > 0.0 {
                        // Lit at the back sample, as the raycaster's pre-integrated segments.
                        let ray = pixel_ray(f32(gx), f32(gy));
                        if KEY_LIGHT {
                            let p = ray.o + ray.d * (A.frame.x + f32(i) * A.frame.y);
                            seg = vec4<f32>(shade_key_light(seg.rgb / seg.a, g0[j], ray.d, p) * seg.a, seg.a);
                            if SHADOWS && P.light.w > 0.0 {
                                n_shadow_rays += 1u;
                            }
                        } else {
                            seg = vec4<f32>(shade_gradient(seg.rgb / seg.a, g0[j], ray.d) * seg.a, seg.a);
                        }
                    }
                    let before = acc[j].a;
                    acc[j] = acc[j] + (1.0 - acc[j].a) * seg;
                    if depth[j] == inf && before < DEPTH_OPACITY && acc[j].a >= DEPTH_OPACITY {
                        let f = (DEPTH_OPACITY - before) / (acc[j].a - before);
                        depth[j] = A.frame.x + (f32(i_prev[j]) + f * f32(slices)) * A.frame.y;
                    }
                    n_segments += 1u;
                }
                s_prev[j] = s0[j];
                i_prev[j] = i;
            }
        }
        // Level 0 read level 1; the next slice writes level 1 first only if its l_slice is 1
        // (a higher l_slice writes level l_slice first and barriers before reaching level 1,
        // l_slice 0 writes no shared level at all), so only then must it wait here. With idle
        // slices skipped, the least-distance load below is that barrier.
        if !SKIP_IDLE_SLICES && min(countTrailingZeros(i + 1u), L_MAX) == 1u {
            workgroupBarrier();
        }
        if EARLY_TERMINATION && ls == L_MAX && i > first_slice {
            if lid == 0u {
                atomicStore(&tile_vote, 0u);
            }
            workgroupBarrier();
            var open = false;
            for (var j = 0u; j < owned; j++) {
                let idx = lid + j * THREADS;
                if tile_x + idx % TILE < width && tile_y + idx / TILE < height {
                    open = open || acc[j].a < P.dims.w;
                }
            }
            if open {
                atomicOr(&tile_vote, 1u);
            }
            workgroupBarrier();
            if lid == 0u {
                tile_decision = atomicLoad(&tile_vote);
            }
            if workgroupUniformLoad(&tile_decision) == 0u {
                stopped_by_tile = true;
                break;
            }
            close_opaque_pixels(tile_x, tile_y, lid, &acc);
        }
        marched += 1u;
        var next = i + 1u;
        if SKIP_IDLE_SLICES {
            // The next multiple of 2^k after i, k = ⌊log2⌋ of the tile's least d.
            let k = least_distance_level(tile_x, tile_y, lid, marched, &d0, &acc);
            next = ((i >> k) + 1u) << k;
        }
        i = next;
    }
    if lid == 0u {
        atomicAdd(&counters[COUNTER_TILE_SLICES], marched);
    }
    // The march ends past the last slice or by the tile's early-termination decision; an
    // invocation that left it anywhere else was cut short by the device: llvmpipe (lavapipe)
    // ends every loop of an invocation once all its loops together have iterated 65535
    // times (gallivm LP_MAX_TGSI_LOOP_ITERATIONS), which exact shadow rays reach at 256³.
    if !stopped_by_tile && i <= last_slice {
        atomicAdd(&counters[COUNTER_CUT_SHORT], 1u);
    }
    for (var j = 0u; j < owned; j++) {
        let idx = lid + j * THREADS;
        let gx = tile_x + idx % TILE;
        let gy = tile_y + idx / TILE;
        if MIP {
            // The TF at the maximum: a segment of one opacity unit of that value
            // (SegmentOptics::point on the CPU side), the pick depth at the maximum.
            let best = acc[j];
            acc[j] = vec4<f32>(0.0);
            if best.z > 0.0 {
                acc[j] = preintegrated_segment(best.x, best.x, P.box_hi.w);
                if acc[j].a > 0.0 {
                    depth[j] = A.frame.x + best.y * A.frame.y;
                }
            }
        }
        if gx < A.viewport.x && gy < A.viewport.y {
            let pixel = gy * A.viewport.x + gx;
            out_rgba[pixel] = acc[j];
            out_depth[pixel] = depth[j];
            textureStore(out_color, vec2<i32>(i32(gx), i32(gy)), clamp(acc[j], vec4<f32>(0.0), vec4<f32>(1.0)));
        }
    }
    for (var l = 0u; l < 4u; l++) {
        if n_samples[l] > 0u {
            atomicAdd(&counters[COUNTER_SAMPLES + l], n_samples[l]);
        }
        if n_synth[l] > 0u {
            atomicAdd(&counters[COUNTER_SYNTHESES + l], n_synth[l]);
        }
        if n_apron[l] > 0u {
            atomicAdd(&counters[COUNTER_APRON_SAMPLES + l], n_apron[l]);
        }
    }
    if n_segments > 0u {
        atomicAdd(&counters[COUNTER_SEGMENTS], n_segments);
    }
    if n_shadow_rays > 0u {
        atomicAdd(&counters[COUNTER_SHADOW_RAYS], n_shadow_rays);
    }
}
