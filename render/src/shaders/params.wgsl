// The per-frame parameters: `Params` and `build_params` in raycast.rs, binding 0. Everything
// is converted from f64 once per frame on the CPU, so the shader works in index space with
// well-conditioned f32 values.

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
    // The key light and shadows (shadows.rs GpuLight; read only by KEY_LIGHT pipelines).
    light: vec4<f32>,          // A·(unit direction to the light), w: intensity
    light_dual: vec4<f32>,     // A^-T·(direction), w: 1 = headlight (direction is −d)
    shadow: vec4<f32>,         // shadow step (mm), bias r0 (mm), optical depth limit
    clip_idx: vec4<f32>,       // clip plane in index space: kept where dot(xyz, p) + w >= 0
    // The light cache (light_cache.rs; read only by LIGHT_CACHE pipelines and its build):
    // x: lookup offset towards the light (mm), y: finest voxels per texel.
    light_cache: vec4<f32>,
    light_cache_dims: vec4<u32>, // texels per axis
    // x: occlusion radius (mm; OCCLUSION pipelines), y: scattering g, z: its blend
    // (SCATTERING pipelines).
    cinematic: vec4<f32>,
};

@group(0) @binding(0) var<uniform> P: Params;

// +inf: the depth of a ray that hit nothing, the bound of a search that found nothing yet. A
// runtime value on purpose: in WGSL a constant expression that evaluates to inf is a compile
// error, which Chrome's compiler (Tint) enforces and naga does not, so an inline
// `positive_infinity()` compiles natively and fails in the browser (issue 39).
fn positive_infinity() -> f32 {
    var bits = 0x7f800000u;
    return bitcast<f32>(bits);
}
