// The overlay in 3D (overlay.rs is the twin and states the sampling and the blend rule;
// gpu_overlay.rs writes bindings 13-15). Everything here is used only where OVERLAY is on, so
// a pipeline without an overlay is the shader it was before.
override OVERLAY: bool = false;

struct OverlayParams {
    grid: vec4<f32>,     // grid dims, w: 1 = continuous, 0 = labels
    scale: vec4<f32>,    // grid dims / primary dims per axis, w: LUT entries
    lut: vec4<f32>,      // continuous: lo, (entries - 1) / (hi - lo), threshold, w: 1 = empty range
    box_lo: vec4<f32>,   // primary-index box outside which nothing is drawn (overlay.rs
    box_hi: vec4<f32>,   //   occupied_box)
};

// The grid (R32Float: labels as LUT indices, or physical values), read with textureLoad only:
// labels are categories and are never filtered.
@group(0) @binding(13) var overlay_grid: texture_3d<f32>;
@group(0) @binding(14) var overlay_lut: texture_1d<f32>;
@group(0) @binding(15) var<uniform> O: OverlayParams;

fn overlay_voxel(i: vec3<i32>) -> f32 {
    return textureLoad(overlay_grid, i, 0).x;
}

// The overlay's straight colour and opacity at primary index `p` (alpha 0: nothing drawn).
fn overlay_at(p: vec3<f32>) -> vec4<f32> {
    let g = (p + vec3<f32>(0.5)) * O.scale.xyz;
    let last = O.grid.xyz - vec3<f32>(1.0);
    let n = u32(O.scale.w);
    if O.grid.w < 0.5 {
        let i = vec3<i32>(clamp(floor(g), vec3<f32>(0.0), last));
        let label = floor(overlay_voxel(i) + 0.5);
        if label < 1.0 || label >= f32(n) {
            return vec4<f32>(0.0);
        }
        return textureLoad(overlay_lut, i32(label), 0);
    }
    let q = clamp(g - vec3<f32>(0.5), vec3<f32>(0.0), last);
    let b = floor(q);
    let f = q - b;
    let lo = vec3<i32>(b);
    let hi = vec3<i32>(min(b + vec3<f32>(1.0), last));
    let c00 = mix(overlay_voxel(lo), overlay_voxel(vec3<i32>(hi.x, lo.y, lo.z)), f.x);
    let c10 = mix(overlay_voxel(vec3<i32>(lo.x, hi.y, lo.z)), overlay_voxel(vec3<i32>(hi.x, hi.y, lo.z)), f.x);
    let c01 = mix(overlay_voxel(vec3<i32>(lo.x, lo.y, hi.z)), overlay_voxel(vec3<i32>(hi.x, lo.y, hi.z)), f.x);
    let c11 = mix(overlay_voxel(vec3<i32>(lo.x, hi.y, hi.z)), overlay_voxel(hi), f.x);
    let v = mix(mix(c00, c10, f.y), mix(c01, c11, f.y), f.z);
    if v < O.lut.z {
        return vec4<f32>(0.0);
    }
    var t = 1.0;
    if O.lut.w < 0.5 {
        t = clamp((v - O.lut.x) * O.lut.y, 0.0, f32(n - 1u));
    } else {
        t = f32(n - 1u);
    }
    let i = min(u32(floor(t + 0.5)), n - 1u);
    return textureLoad(overlay_lut, i32(i), 0);
}

// The blend rule (overlay.rs `blend`): colour mixed toward the overlay by its opacity, opacity
// at least the overlay's times OVERLAY_VOXEL_OPACITY.
fn overlay_blend(tissue: vec4<f32>, ov: vec4<f32>) -> vec4<f32> {
    if ov.a <= 0.0 {
        return tissue;
    }
    return vec4<f32>(tissue.rgb + (ov.rgb - tissue.rgb) * ov.a, max(tissue.a, ov.a * OVERLAY_VOXEL_OPACITY));
}

// [t_enter, t_exit] of the ray o + t·d inside the overlay's box (empty: enter > exit).
fn overlay_interval(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    var t0 = -3.0e38;
    var t1 = 3.0e38;
    for (var a = 0u; a < 3u; a++) {
        if abs(d[a]) < 1e-12 {
            if o[a] < O.box_lo[a] || o[a] > O.box_hi[a] {
                return vec2<f32>(1.0, 0.0);
            }
        } else {
            let ta = (O.box_lo[a] - o[a]) / d[a];
            let tb = (O.box_hi[a] - o[a]) / d[a];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    return vec2<f32>(t0, t1);
}

// MIP: the first shown overlay sample along the ray (nearest the viewer) on the march's lattice
// (sample k at first + (k + ½)·base) within [t0, t1] and the overlay's box; zero if none.
fn overlay_first_on_ray(o: vec3<f32>, d: vec3<f32>, t0: f32, t1: f32, first: f32, base: f32) -> vec4<f32> {
    let span = overlay_interval(o, d);
    let lo = max(t0, span.x);
    let hi = min(t1, span.y);
    if !(hi > lo) {
        return vec4<f32>(0.0);
    }
    var k = max(ceil((lo - first) / base - 0.5), 0.0);
    for (var iter = 0u; iter < MAX_ITERATIONS; iter++) {
        let t = first + (k + 0.5) * base;
        if t >= hi {
            break;
        }
        let c = overlay_at(o + d * t);
        if c.a > 0.0 {
            return c;
        }
        k = k + 1.0;
    }
    return vec4<f32>(0.0);
}
