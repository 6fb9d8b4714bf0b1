// The transfer function table (transfer_function.rs; GpuTransferFunction writes binding 4).

@group(0) @binding(4) var tf_table: texture_1d<f32>;

// Transfer function, linearly interpolated between table entries.
fn transfer(v: f32) -> vec4<f32> {
    let n = P.image.w;
    let x = clamp((v - P.value_map.z) * P.value_map.w, 0.0, f32(n - 1u));
    let i = min(u32(floor(x)), n - 1u);
    let j = min(i + 1u, n - 1u);
    return mix(textureLoad(tf_table, i32(i), 0), textureLoad(tf_table, i32(j), 0), x - f32(i));
}
