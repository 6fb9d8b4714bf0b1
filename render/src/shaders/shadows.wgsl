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

// Where in each shadow-ray segment its sample sits, as a fraction of the step: the midpoint
// (0.5) unless the main pass jitters (JITTER), which sets a per-pixel, per-frame value
// independent of its own ray-start jitter. Averaged over frames (progressive.rs) the shadow
// and occlusion rays then converge to their fine-step transmittance as the main ray does,
// instead of keeping their step's midpoint error. The light cache's build keeps 0.5: its grid
// is reused across frames and must not flicker.
var<private> shadow_jitter: f32 = 0.5;

// V at index-space point `p` towards the light (unit patient direction whose index-space
// image is `l`, so distances are mm): midpoint samples at the shadow step from the bias r0 to
// where the ray leaves the cropped box or the clip plane's half-space, through the resident
// cut with the main ray's page cache and empty skipping; stops at the optical-depth limit.
fn shadow_transmittance(p: vec3<f32>, l: vec3<f32>) -> f32 {
    return shadow_span(p, l, false, P.shadow.y, 3.0e38).x;
}

// The shadow ray from `r0` to min(exit, `cap`): x the transmittance, y 1 if the ray goes on
// inside past `cap`. `from_entry`: start no earlier than where the ray enters the cropped box
// and the clip plane's half-space (reference.rs `ray_interval`), and a ray that never enters
// them transmits everything: for the light cache's texel centres, which may lie outside
// them. A shaded sample lies inside, where its entry is behind it.
fn shadow_span(p: vec3<f32>, l: vec3<f32>, from_entry: bool, r0_in: f32, cap: f32) -> vec2<f32> {
    let ds = P.shadow.x;
    var r0 = r0_in;
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
            return vec2<f32>(1.0, 0.0);
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
            return vec2<f32>(1.0, 0.0);
        }
    }
    if from_entry {
        if enter >= r1 {
            return vec2<f32>(1.0, 0.0);
        }
        r0 = max(r0, enter);
    }
    let on = select(0.0, 1.0, r1 > cap);
    r1 = min(r1, cap);
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
        let loc = locate_on_ray(p, l, s + shadow_jitter * length, &pg);
        if !loc.resident || (SKIP_EMPTY && loc.empty) {
            if SKIP_EMPTY {
                // Every sample up to the region's exit is transparent: the first segment
                // whose sample lies beyond it is next (the main ray's rule).
                let next = ceil((skip_exit(p, l, pg) - r0) / ds - shadow_jitter);
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
    return vec2<f32>(exp(-tau), on);
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

// One slice of the light cache's sweep (light_cache.rs): x the slice's index along the sweep
// axis, y that axis, z 1 for the first slice (the one nearest the light). A dynamic offset
// per slice selects it (group 1 exists only in the build's pipeline layout).
@group(1) @binding(0) var<uniform> SWEEP: vec4<u32>;

fn light_cache_index(i: vec3<u32>) -> u32 {
    let n = P.light_cache_dims.xyz;
    return i.x + n.x * (i.y + n.y * i.z);
}

// V of slice SWEEP.x at the point p' of the slice before it (towards the light), bilinear in
// the two other axes, clamped to the grid (light_cache.rs `interpolate_in_slice`).
fn light_cache_previous(q: vec3<f32>, a: u32, slice: u32) -> f32 {
    let n = P.light_cache_dims.xyz;
    let u = clamp(
        (q + vec3<f32>(0.5)) / P.light_cache.y - vec3<f32>(0.5),
        vec3<f32>(0.0),
        vec3<f32>(n - 1u),
    );
    let b = (a + 1u) % 3u;
    let c = (a + 2u) % 3u;
    var i0 = vec3<u32>(floor(u));
    let f = u - floor(u);
    i0[a] = slice;
    var i1 = min(i0 + 1u, n - 1u);
    i1[a] = slice;
    var ib = i0;
    ib[b] = i1[b];
    var ic = i0;
    ic[c] = i1[c];
    var ibc = i1;
    let v00 = light_cache[light_cache_index(i0)];
    let v10 = light_cache[light_cache_index(ib)];
    let v01 = light_cache[light_cache_index(ic)];
    let v11 = light_cache[light_cache_index(ibc)];
    return mix(mix(v00, v10, f[b]), mix(v01, v11, f[b]), f[c]);
}

// The light cache's build, one slice per dispatch, from the light's side: a texel's V is the
// transmittance of its ray to the next slice towards the light (through the resident cut, as
// exact shadows) times that slice's V where the ray reaches it; the first slice's rays run to
// where they leave the box. Empty texels are not skipped: the shadow behind an occluder
// reaches a lit sample through them. The march skips empty pages as the main ray does.
@compute @workgroup_size(8, 8, 1)
fn build_light_cache(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = P.light_cache_dims.xyz;
    let a = SWEEP.y;
    let b = (a + 1u) % 3u;
    let c = (a + 2u) % 3u;
    if gid.x >= n[b] || gid.y >= n[c] {
        return;
    }
    var i = vec3<u32>(0u);
    i[a] = SWEEP.x;
    i[b] = gid.x;
    i[c] = gid.y;
    let res = P.light_cache.y;
    let p = (vec3<f32>(i) + vec3<f32>(0.5)) * res - vec3<f32>(0.5);
    let l = P.light.xyz;
    var v = 1.0;
    if SWEEP.z == 1u {
        v = shadow_span(p, l, true, 0.0, 3.0e38).x;
    } else {
        // To the previous slice's plane: res voxels along the sweep axis.
        let dt = res / abs(l[a]);
        let span = shadow_span(p, l, true, 0.0, dt);
        v = span.x;
        if span.y > 0.5 {
            var prev = SWEEP.x + 1u;
            if l[a] < 0.0 {
                prev = SWEEP.x - 1u;
            }
            v = v * light_cache_previous(p + l * dt, a, prev);
        }
    }
    light_cache[light_cache_index(i)] = v;
}

// shadows.rs `shade_lit` (with OCCLUSION or SCATTERING scattering.rs `shade_cinematic`):
// `g_idx` the field's index-space gradient, `d_idx` the ray direction
// and `p` the sample, both in index space.
fn shade_key_light(color: vec3<f32>, g_idx: vec3<f32>, d_idx: vec3<f32>, p: vec3<f32>) -> vec3<f32> {
    let g_patient = g_idx.x * P.a_row0.xyz + g_idx.y * P.a_row1.xyz + g_idx.z * P.a_row2.xyz;
    let mag = length(g_patient);
    let w = smoothstep(SHADING_FLAT_BELOW, SHADING_LIT_ABOVE, mag * P.iso.y);
    // Towards the light: −d for the headlight, else the frame's direction; l·d in patient
    // space through the dual vector (shadows.rs GpuLight).
    // Selects, not an `if` on a uniform: see main in raycast.wgsl (lavapipe recompiles).
    let headlight = P.light_dual.w > 0.5;
    let l = select(P.light.xyz, -d_idx, headlight);
    let l_dot_d = select(dot(P.light_dual.xyz, d_idx), -1.0, headlight);
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
    if OCCLUSION || SCATTERING {
        // scattering.rs `shade_cinematic`: AO scales the ambient term; the direct term blends
        // the BRDF (weight P) and the phase (1 − P) of the angle between light and view ray.
        var ambient = P.shading.x;
        if OCCLUSION {
            ambient = ambient * ambient_occlusion(p);
        }
        var surface = 1.0;
        var volume = 0.0;
        if SCATTERING && direct > 0.0 {
            surface = scattering_surface_weight(P.cinematic.z, mag * P.iso.y);
            volume = (1.0 - surface) * scattering_phase_4pi(P.cinematic.y, l_dot_d);
        }
        let gain = ambient + direct * P.shading.y * (surface * (1.0 + (ndl - 1.0) * w) + volume);
        return color * gain + vec3<f32>(direct * P.shading.z * spec * w * surface);
    }
    let gain = P.shading.x + direct * P.shading.y * (1.0 + (ndl - 1.0) * w);
    return color * gain + vec3<f32>(direct * P.shading.z * spec * w);
}
