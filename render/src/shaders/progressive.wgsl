// Progressive refinement (progressive.rs): folds one raycast frame into the running mean.
// mean_N = mean_{N-1} + (x_N - mean_{N-1}) / N in f32, which stays within an ulp of the true
// mean for any N a still view reaches (a plain sum would lose 8-bit steps after ~2^16 frames).

struct AccumulateParams {
    // width, height, N (the frame being added, 1-based), unused
    dims: vec4<u32>,
}

@group(0) @binding(0) var<uniform> A: AccumulateParams;
@group(0) @binding(1) var frame: texture_2d<f32>;
@group(0) @binding(2) var<storage, read_write> mean: array<vec4<f32>>;
@group(0) @binding(3) var mean_out: texture_storage_2d<rgba8unorm, write>;

@compute @workgroup_size(8, 8, 1)
fn accumulate(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= A.dims.x || gid.y >= A.dims.y {
        return;
    }
    let i = gid.y * A.dims.x + gid.x;
    let x = textureLoad(frame, vec2<i32>(gid.xy), 0);
    var m = x;
    // N = 1 overwrites: the buffer's old contents (another view, or uninitialised) never leak.
    if A.dims.z > 1u {
        let prev = mean[i];
        m = prev + (x - prev) / f32(A.dims.z);
    }
    mean[i] = m;
    textureStore(mean_out, vec2<i32>(gid.xy), clamp(m, vec4<f32>(0.0), vec4<f32>(1.0)));
}
