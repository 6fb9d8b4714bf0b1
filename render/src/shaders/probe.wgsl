// Field probe for tests (probe.rs, feature test-probe): physical value of the field at level-0
// index points (w ignored); NaN where nothing is resident. Uses the same field() as the
// raycaster; composed with the field files into a module of its own, never into the raycast
// shader.
@group(0) @binding(12) var<storage, read> probe_points: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> probe_values: array<f32>;

@compute @workgroup_size(PROBE_WORKGROUP_SIZE, 1, 1)
fn probe(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if i >= arrayLength(&probe_values) {
        return;
    }
    let loc = locate(probe_points[i].xyz);
    if loc.resident {
        probe_values[i] = physical(field(loc));
    } else {
        probe_values[i] = bitcast<f32>(0x7fc00000u);
    }
}

