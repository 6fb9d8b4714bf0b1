// Shading (reference.rs `shade`): Blinn-Phong with a headlight, shared by the raycaster and
// the adaptive pass.

// `g_idx` is the field's gradient in index space (physical units per index step), `d_idx` the
// ray direction mapped into index space, so g·d_idx = (A^T g)·d_patient without leaving index
// space.
fn shade_gradient(color: vec3<f32>, g_idx: vec3<f32>, d_idx: vec3<f32>) -> vec3<f32> {
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
