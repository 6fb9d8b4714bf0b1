// The key light and its volumetric shadows, exact mode (shadows.rs, which documents the model
// and the reference that integrates it). Composed into the raycast shader only; both effects
// are override constants, so a pipeline without them has none of this code.
//
// KEY_LIGHT: lighting by shade_key_light (a light direction of its own, intensity, ambient
// split from the direct term) instead of shading.wgsl's headlight Blinn-Phong. Off with the
// default headlight and no shadows, so default images are the old ones bit for bit.
// SHADOWS: the direct term times the transmittance of a shadow ray to the light.
// LIGHT_CACHE: the direct term times V read from the light cache (light_cache.rs), which the
// build_light_cache entry point fills with the same shadow rays from its texel centres.
override KEY_LIGHT: bool = false;
override SHADOWS: bool = false;
override LIGHT_CACHE: bool = false;

@group(0) @binding(16) var<storage, read_write> light_cache: array<f32>;

// V at index-space point `p` towards the light (unit patient direction whose index-space
// image is `l`, so distances are mm): midpoint samples at the shadow step from the bias r0 to
// where the ray leaves the cropped box or the clip plane's half-space, through the resident
// cut with the main ray's page cache and empty skipping; stops at the optical-depth limit.
fn shadow_transmittance(p: vec3<f32>, l: vec3<f32>) -> f32 {
    return shadow_ray(p, l, false);
}

// The shadow ray; `from_entry`: start where the ray enters the cropped box and the clip
// plane's half-space (reference.rs `ray_interval`), for the cache's texel centres, which may
// lie outside them. A shaded sample lies inside, where its entry is behind it.
fn shadow_ray(p: vec3<f32>, l: vec3<f32>, from_entry: bool) -> f32 {
    let ds = P.shadow.x;
    var r0 = P.shadow.y;
    var r1 = 3.0e38;
    var enter = 0.0;
    for (var a = 0u; a < 3u; a++) {
        if l[a] > 1e-12 {
            r1 = min(r1, (P.box_hi[a] - p[a]) / l[a]);
            enter = max(enter, (P.box_lo[a] - p[a]) / l[a]);
        } else if l[a] < -1e-12 {
            r1 = min(r1, (P.box_lo[a] - p[a]) / l[a]);
            enter = max(enter, (P.box_hi[a] - p[a]) / l[a]);
        } else if from_entry && (p[a] < P.box_lo[a] || p[a] > P.box_hi[a]) {
            return 1.0;
        }
    }
    if CLIP_PLANE {
        // Light enters through the cut: the ray ends where it leaves the kept half-space.
        let f = dot(P.clip_idx.xyz, p) + P.clip_idx.w;
        let df = dot(P.clip_idx.xyz, l);
        if df < 0.0 {
            r1 = min(r1, max(-f / df, 0.0));
        } else if df > 0.0 {
            enter = max(enter, -f / df);
        } else if from_entry && f < 0.0 {
            return 1.0;
        }
    }
    if from_entry {
        r0 = max(r0, enter);
    }
    var tau = 0.0;
    var pg: Page;
    pg.t_exit = -3.0e38;
    pg.resident = true;
    pg.whole_node = false;
    var k = 0u;
    for (var iter = 0u; iter < MAX_SHADOW_STEPS; iter++) {
        let s = r0 + f32(k) * ds;
        if s >= r1 {
            break;
        }
        let length = min(ds, r1 - s);
        let loc = locate_on_ray(p, l, s + 0.5 * length, &pg);
        if !loc.resident || (SKIP_EMPTY && loc.empty) {
            if SKIP_EMPTY {
                // Every sample up to the region's exit is transparent: the first segment
                // whose midpoint lies beyond it is next (the main ray's rule).
                let next = ceil((skip_exit(p, l, pg) - r0) / ds - 0.5);
                k = max(k + 1u, u32(clamp(next, 0.0, 4.0e9)));
            } else {
                k = k + 1u;
            }
            continue;
        }
        let alpha = transfer(physical(field(loc))).a;
        if alpha > 0.0 {
            tau = tau - log(1.0 - min(alpha, 0.999999)) * length / P.box_hi.w;
            if tau > P.shadow.z {
                break;
            }
        }
        k = k + 1u;
    }
    return exp(-tau);
}

// V from the light cache at the sample `p` (light_cache.rs `interpolate`): trilinear in the
// texels around p moved towards the light by the lookup offset, clamped to the grid.
fn light_cache_visibility(p: vec3<f32>, l: vec3<f32>) -> f32 {
    let n = vec3<i32>(P.light_cache_dims.xyz);
    let res = P.light_cache.y;
    let q = p + l * P.light_cache.x;
    let u = clamp((q + vec3<f32>(0.5)) / res - vec3<f32>(0.5), vec3<f32>(0.0), vec3<f32>(n - 1));
    let i0 = vec3<i32>(floor(u));
    let f = u - vec3<f32>(i0);
    let i1 = min(i0 + 1, n - 1);
    let sy = n.x;
    let sz = n.x * n.y;
    let c000 = light_cache[i0.x + sy * i0.y + sz * i0.z];
    let c100 = light_cache[i1.x + sy * i0.y + sz * i0.z];
    let c010 = light_cache[i0.x + sy * i1.y + sz * i0.z];
    let c110 = light_cache[i1.x + sy * i1.y + sz * i0.z];
    let c001 = light_cache[i0.x + sy * i0.y + sz * i1.z];
    let c101 = light_cache[i1.x + sy * i0.y + sz * i1.z];
    let c011 = light_cache[i0.x + sy * i1.y + sz * i1.z];
    let c111 = light_cache[i1.x + sy * i1.y + sz * i1.z];
    let y0 = mix(mix(c000, c100, f.x), mix(c010, c110, f.x), f.y);
    let y1 = mix(mix(c001, c101, f.x), mix(c011, c111, f.x), f.y);
    return mix(y0, y1, f.z);
}

// Whether no sample that reads the texel at `p` can have opacity: every page its ±2·res box
// touches is empty or not resident (light_cache.rs; the 8 corners find them all while
// 4·res <= the brick core, which the CPU checks before setting light_cache.z).
fn light_cache_texel_empty(p: vec3<f32>) -> bool {
    let r = 2.0 * P.light_cache.y;
    for (var c = 0u; c < 8u; c++) {
        let corner = p + r * vec3<f32>(
            select(-1.0, 1.0, (c & 1u) != 0u),
            select(-1.0, 1.0, (c & 2u) != 0u),
            select(-1.0, 1.0, (c & 4u) != 0u),
        );
        var pg: Page;
        pg.t_exit = -3.0e38;
        pg.resident = true;
        pg.whole_node = false;
        let loc = locate_on_ray(corner, vec3<f32>(1.0, 0.0, 0.0), 0.0, &pg);
        if loc.resident && !loc.empty {
            return false;
        }
    }
    return true;
}

// The light cache's build (light_cache.rs): one invocation per texel, its shadow ray from the
// texel centre towards the light through the resident cut (as exact shadows), or V = 1 where
// no sample with opacity reads it.
@compute @workgroup_size(4, 4, 4)
fn build_light_cache(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = P.light_cache_dims.xyz;
    if any(gid >= n) {
        return;
    }
    let p = (vec3<f32>(gid) + vec3<f32>(0.5)) * P.light_cache.y - vec3<f32>(0.5);
    var v = 1.0;
    if !(P.light_cache.z > 0.5 && light_cache_texel_empty(p)) {
        v = shadow_ray(p, P.light.xyz, true);
    }
    light_cache[gid.x + n.x * (gid.y + n.y * gid.z)] = v;
}

// shadows.rs `shade_lit`: `g_idx` the field's index-space gradient, `d_idx` the ray direction
// and `p` the sample, both in index space.
fn shade_key_light(color: vec3<f32>, g_idx: vec3<f32>, d_idx: vec3<f32>, p: vec3<f32>) -> vec3<f32> {
    let g_patient = g_idx.x * P.a_row0.xyz + g_idx.y * P.a_row1.xyz + g_idx.z * P.a_row2.xyz;
    let mag = length(g_patient);
    let w = smoothstep(SHADING_FLAT_BELOW, SHADING_LIT_ABOVE, mag * P.iso.y);
    // Towards the light: −d for the headlight, else the frame's direction; l·d in patient
    // space through the dual vector (shadows.rs GpuLight).
    var l = P.light.xyz;
    var l_dot_d = dot(P.light_dual.xyz, d_idx);
    if P.light_dual.w > 0.5 {
        l = -d_idx;
        l_dot_d = -1.0;
    }
    var ndl = 1.0;
    var spec = 0.0;
    if mag > 0.0 {
        // n·v and n·l in patient space (g_idx·x_idx = g_patient·x_patient); two-sided.
        var nv = -dot(g_idx, d_idx) / mag;
        var nl = dot(g_idx, l) / mag;
        if nv < 0.0 {
            nv = -nv;
            nl = -nl;
        }
        let half_len = sqrt(max(2.0 - 2.0 * l_dot_d, 0.0));
        var ndh = 0.0;
        if half_len > 1e-6 {
            ndh = max((nl + nv) / half_len, 0.0);
        }
        ndl = clamp(nl, 0.0, 1.0);
        spec = pow(min(ndh, 1.0), P.shading.w);
    }
    var direct = P.light.w;
    if SHADOWS && direct > 0.0 {
        direct = direct * shadow_transmittance(p, l);
    } else if LIGHT_CACHE && direct > 0.0 {
        direct = direct * light_cache_visibility(p, l);
    }
    let gain = P.shading.x + direct * P.shading.y * (1.0 + (ndl - 1.0) * w);
    return color * gain + vec3<f32>(direct * P.shading.z * spec * w);
}
