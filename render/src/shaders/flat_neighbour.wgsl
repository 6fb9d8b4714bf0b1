// The transition blend's neighbour lookup (field.wgsl: transition_blend) for the passes that
// read only the flat page table (field probe, adaptive pass): the neighbour cell's word. The
// raycaster defines its own, which finds the leaf on the octree traversal (raycast.wgsl).
fn neighbour_page(cell: vec3<i32>) -> Page {
    return decode_entry(cell);
}
