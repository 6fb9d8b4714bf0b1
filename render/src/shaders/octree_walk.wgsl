// Test-only (feature `test-probe`, octree_probe.rs): the octree traversal's leaf walk in its
// own module (prelude + octree.wgsl + this file), one invocation per ray, written to a debug
// buffer: the GPU twin of OctreeCut::traverse (octree_cut.rs), in page-cell units (cell c
// spans [c, c + 1) per axis). Entry by a point query, then per leaf the exit face (ties to the
// lowest axis), the cell across it (the exit axis forced, a face point belonging to the cell
// the ray moves into) and octree_next_leaf: the rope and a descent, or a point query through
// an edge or a corner, exactly as the raycaster's march finds its next leaf.

struct WalkParams {
    // Page grid (xyz) and the number of rays (w).
    dims: vec4<u32>,
    // Visits kept per ray (x).
    limits: vec4<u32>,
};

@group(0) @binding(0) var<uniform> W: WalkParams;
// Per ray two vec4: (origin, t0), (direction, t1).
@group(0) @binding(1) var<storage, read> walk_rays: array<vec4<f32>>;
// Per ray 1 + 3·limits.x words: the visit count, then (leaf record, t_enter, t_exit) bits.
@group(0) @binding(2) var<storage, read_write> walk_out: array<u32>;

fn walk_cell_on_ray(o: vec3<f32>, d: vec3<f32>, t: f32) -> vec3<u32> {
    let p = o + d * t;
    var c = floor(p);
    c = select(c, c - vec3<f32>(1.0), d < vec3<f32>(0.0) & p == c);
    return vec3<u32>(clamp(c, vec3<f32>(0.0), vec3<f32>(W.dims.xyz) - vec3<f32>(1.0)));
}

@compute @workgroup_size(64, 1, 1)
fn octree_walk(@builtin(global_invocation_id) gid: vec3<u32>) {
    let ray = gid.x;
    if ray >= W.dims.w {
        return;
    }
    let o = walk_rays[2u * ray].xyz;
    let d = walk_rays[2u * ray + 1u].xyz;
    var t = walk_rays[2u * ray].w;
    var t_end = walk_rays[2u * ray + 1u].w;
    let grid = vec3<f32>(W.dims.xyz);
    let out = ray * (1u + 3u * W.limits.x);
    walk_out[out] = 0u;
    for (var k = 0u; k < 3u; k++) {
        if d[k] == 0.0 {
            if o[k] < 0.0 || o[k] >= grid[k] {
                return;
            }
        } else {
            let ta = (0.0 - o[k]) / d[k];
            let tb = (grid[k] - o[k]) / d[k];
            t = max(t, min(ta, tb));
            t_end = min(t_end, max(ta, tb));
        }
    }
    if !(t_end >= t) {
        return;
    }
    let root = octree[0];
    var leaf = octree_leaf_at(root, walk_cell_on_ray(o, d, t));
    var count = 0u;
    for (var step = 0u; step < 100000u; step++) {
        if !leaf.found {
            break;
        }
        let lo = vec3<f32>(leaf.origin);
        let hi = min(lo + vec3<f32>(f32(1u << leaf.size)), grid);
        var exit_t = 3.0e38;
        var face = 0u;
        for (var k = 0u; k < 3u; k++) {
            if d[k] == 0.0 {
                continue;
            }
            let up = d[k] > 0.0;
            let bound = select(lo[k], hi[k], up);
            let tk = (bound - o[k]) / d[k];
            if tk < exit_t {
                exit_t = tk;
                face = 2u * k + select(0u, 1u, up);
            }
        }
        let t_exit = min(exit_t, t_end);
        if t_exit > t && count < W.limits.x {
            walk_out[out + 1u + 3u * count] = leaf.record;
            walk_out[out + 2u + 3u * count] = bitcast<u32>(t);
            walk_out[out + 3u + 3u * count] = bitcast<u32>(t_exit);
            count += 1u;
        }
        if exit_t >= t_end {
            break;
        }
        t = exit_t;
        var cell = walk_cell_on_ray(o, d, t);
        let axis = face / 2u;
        let side = 1u << leaf.size;
        // Outside the grid (a volume face) the rope is null; the wrap makes the cell fail
        // every containment test, so octree_next_leaf finds nothing.
        cell[axis] = select(leaf.origin[axis] - 1u, leaf.origin[axis] + side, face % 2u == 1u);
        if cell[axis] >= W.dims[axis] {
            break;
        }
        leaf = octree_next_leaf(root, leaf, cell);
    }
    walk_out[out] = count;
}
