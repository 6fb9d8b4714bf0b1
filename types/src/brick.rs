//! The brick: 32³ core voxels with a 2-voxel apron on every side (octree paper §3).
//!
//! The apron lets trilinear filtering and central-difference gradients stay inside one brick.
//! The WGSL prelude in render is generated from these values, so shader and store agree.

/// Core voxels per brick edge.
pub const BRICK_CORE: u32 = 32;
/// Replicated voxels on each side of the core: trilinear needs 1, central-difference gradients
/// taken at ±1 voxel around a trilinear sample need 2.
pub const BRICK_APRON: u32 = 2;
/// Stored voxels per brick edge (core + both aprons).
pub const BRICK_PAYLOAD: u32 = BRICK_CORE + 2 * BRICK_APRON;
/// Voxels in one brick payload.
pub const BRICK_PAYLOAD_VOXELS: usize = (BRICK_PAYLOAD * BRICK_PAYLOAD * BRICK_PAYLOAD) as usize;
