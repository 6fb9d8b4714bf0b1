// Ambient occlusion from local extinction (ambient_occlusion.rs, which documents the model and
// the reference that integrates it): the mean transmittance of OCCLUSION_DIRECTIONS short
// shadow rays (shadows.wgsl `shadow_span`, its step, bias and optical-depth limit) over the
// radius. An override constant, so a pipeline without it has none of this code.
override OCCLUSION: bool = false;

// The k-th direction of the spherical Fibonacci set in patient axes (ambient_occlusion.rs
// `direction`), mapped to index space (A·ν: distances along it stay in mm).
fn occlusion_direction(k: u32) -> vec3<f32> {
    let z = 1.0 - (2.0 * f32(k) + 1.0) / f32(OCCLUSION_DIRECTIONS);
    let r = sqrt(max(1.0 - z * z, 0.0));
    let phi = f32(k) * OCCLUSION_GOLDEN_ANGLE;
    let nu = vec3<f32>(r * cos(phi), r * sin(phi), z);
    return vec3<f32>(dot(P.a_row0.xyz, nu), dot(P.a_row1.xyz, nu), dot(P.a_row2.xyz, nu));
}

// AO at index-space point `p`: each ray from the bias to min(radius, where it leaves the
// cropped box or the clip plane's half-space). A radius within the bias is 1 exactly.
// Branch-free on that uniform-only condition (a `select`, the radius clamped to the bias so
// every span is empty): Mesa's lavapipe recompiles, on every frame whose uniforms changed, a
// shader that branches on uniforms alone (bench/lean-base/lavapipe.md).
fn ambient_occlusion(p: vec3<f32>) -> f32 {
    let radius = max(P.cinematic.x, P.shadow.y);
    var sum = 0.0;
    for (var k = 0u; k < OCCLUSION_DIRECTIONS; k++) {
        sum = sum + shadow_span(p, occlusion_direction(k), false, P.shadow.y, radius).x;
    }
    return select(sum / f32(OCCLUSION_DIRECTIONS), 1.0, P.cinematic.x <= P.shadow.y);
}
