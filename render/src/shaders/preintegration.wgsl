// The pre-integrated transfer function (preintegration.rs), binding 10.

// Pre-integrated TF (preintegration.rs): texel (front, back) = premultiplied colour and opacity
// of a base-step segment whose value runs from front to back. 1×1 when unused.
@group(0) @binding(10) var preintegration_table: texture_2d<f32>;

// Segment colour and opacity between two physical values, bilinear in the table, which spans
// the same value range as the TF texture.
fn preintegrated(front: f32, back: f32) -> vec4<f32> {
    let last = f32(textureDimensions(preintegration_table).x - 1u);
    let per_value = P.value_map.w * last / f32(P.image.w - 1u);
    let x = clamp((front - P.value_map.z) * per_value, 0.0, last);
    let y = clamp((back - P.value_map.z) * per_value, 0.0, last);
    let i0 = vec2<i32>(i32(floor(x)), i32(floor(y)));
    let i1 = min(i0 + vec2<i32>(1), vec2<i32>(i32(last)));
    let f = vec2<f32>(x, y) - floor(vec2<f32>(x, y));
    let c00 = textureLoad(preintegration_table, i0, 0);
    let c10 = textureLoad(preintegration_table, vec2<i32>(i1.x, i0.y), 0);
    let c01 = textureLoad(preintegration_table, vec2<i32>(i0.x, i1.y), 0);
    let c11 = textureLoad(preintegration_table, i1, 0);
    return mix(mix(c00, c10, f.x), mix(c01, c11, f.x), f.y);
}
