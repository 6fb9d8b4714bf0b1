// The key light and its volumetric shadows, exact mode (shadows.rs, which documents the model
// and the reference that integrates it). Composed into the raycast shader only; both effects
// are override constants, so a pipeline without them has none of this code.
//
// KEY_LIGHT: lighting by shade_key_light (a light direction of its own, intensity, ambient
// split from the direct term) instead of shading.wgsl's headlight Blinn-Phong. Off with the
// default headlight and no shadows, so default images are the old ones bit for bit.
// SHADOWS: the direct term times the transmittance of a shadow ray to the light.
override KEY_LIGHT: bool = false;
override SHADOWS: bool = false;

// V at index-space point `p` towards the light (unit patient direction whose index-space
// image is `l`, so distances are mm): midpoint samples at the shadow step from the bias r0 to
// where the ray leaves the cropped box or the clip plane's half-space, through the resident
// cut with the main ray's page cache and empty skipping; stops at the optical-depth limit.
fn shadow_transmittance(p: vec3<f32>, l: vec3<f32>) -> f32 {
    let ds = P.shadow.x;
    let r0 = P.shadow.y;
    var r1 = 3.0e38;
    for (var a = 0u; a < 3u; a++) {
        if l[a] > 1e-12 {
            r1 = min(r1, (P.box_hi[a] - p[a]) / l[a]);
        } else if l[a] < -1e-12 {
            r1 = min(r1, (P.box_lo[a] - p[a]) / l[a]);
        }
    }
    if CLIP_PLANE {
        // Light enters through the cut: the ray ends where it leaves the kept half-space.
        let f = dot(P.clip_idx.xyz, p) + P.clip_idx.w;
        let df = dot(P.clip_idx.xyz, l);
        if df < 0.0 {
            r1 = min(r1, max(-f / df, 0.0));
        }
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
    }
    let gain = P.shading.x + direct * P.shading.y * (1.0 + (ndl - 1.0) * w);
    return color * gain + vec3<f32>(direct * P.shading.z * spec * w);
}
