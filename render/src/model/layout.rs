//! The numbers everything else is laid out by, and the seam bricks come in through. Nothing
//! here depends on another module of the crate.
//!
//! - Brick sizes: the store's, from strata-types (32³ core, 2-voxel apron, 36³ payload).
//! - The GPU page word (page_table.rs, GpuPageTable): slot grid position, level, flags.
//! - The 26-neighbour mask bit of a face/edge/corner offset (smooth_transitions.rs).
//! - Shading thresholds shared by the reference and the shader; the raycast workgroup size.
//! - [`BrickSource`]: where the CPU side reads node payloads.
//!
//! Every constant the shader uses is written into its prelude from here (shaders.rs), so the
//! WGSL cannot drift from these definitions.

pub use strata_types::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};

/// GPU word layout: bits 0-7 / 8-15 / 16-23 the slot's x / y / z position in the cache's slot
/// grid (the shader then needs no integer division), 24-27 level, bit 28 whole node, bit 29
/// empty, bit 30 not resident, bit 31 has a coarser neighbour (smooth transitions). The CPU
/// side speaks slot indices; the cache's grid converts. A not-resident word has no slot, and
/// its level field says how far rays may skip instead: the largest aligned block of 2^level
/// page cells around it that is all not resident (written by [`crate::GpuPageTable::update`]).
pub const MAX_SLOTS_PER_AXIS: u32 = 255;
pub const MAX_SLOTS: u32 = MAX_SLOTS_PER_AXIS * MAX_SLOTS_PER_AXIS * MAX_SLOTS_PER_AXIS;
/// Bits per axis of the slot's grid position, and their mask (holds MAX_SLOTS_PER_AXIS).
pub const SLOT_AXIS_BITS: u32 = 8;
pub const SLOT_AXIS_MASK: u32 = (1 << SLOT_AXIS_BITS) - 1;
pub const LEVEL_SHIFT: u32 = 24;
/// The level field's mask after the shift (4 bits: levels 0-15, i.e. up to 2^15 pages =
/// 1M voxels per axis; [`crate::GpuPageTable::new`] refuses larger grids).
pub const LEVEL_MASK: u32 = 15;
/// Set by [`crate::GpuPageTable::update`] where every page cell of the entry's node holds this
/// same word (the node is a leaf of the cut, not a parent standing in for some of its
/// children): a ray may then treat the whole node as one region (node-extent exit: skip an
/// empty node at once, cross its cells without reading their entries).
pub const FLAG_WHOLE_NODE: u32 = 1 << 28;
pub const FLAG_EMPTY: u32 = 1 << 29;
pub const FLAG_NOT_RESIDENT: u32 = 1 << 30;
/// Set by [`crate::GpuPageTable::update`] where the node has a coarser neighbour: the shader
/// reads the transition mask only for those entries (one gather less per page elsewhere).
pub const FLAG_TRANSITION: u32 = 1 << 31;

/// Bit of neighbour offset `o` ∈ {−1, 0, 1}³ in a transition mask: `(x+1) + 3(y+1) + 9(z+1)`.
/// Bit 13 (the node itself) is never set.
pub fn neighbour_bit(o: [i32; 3]) -> u32 {
    ((o[0] + 1) + 3 * (o[1] + 1) + 9 * (o[2] + 1)) as u32
}

/// The offset of mask bit `bit` (inverse of [`neighbour_bit`]).
pub fn neighbour_offset(bit: u32) -> [i32; 3] {
    let b = bit as i32;
    [b % 3 - 1, (b / 3) % 3 - 1, b / 9 - 1]
}

/// All 26 neighbour offsets (faces, edges, corners).
pub fn neighbour_offsets() -> impl Iterator<Item = [i32; 3]> {
    (0..27).filter(|&b| b != 13).map(neighbour_offset)
}

/// The depth a DVR ray reports (the pick depth: what a click in the 3D view lands on) is the
/// distance where its accumulated opacity first reaches this: where the user sees the surface,
/// not the first faint contribution, which is haze. MIP reports the maximum's distance, an
/// isosurface its hit; a DVR ray that never gets this opaque reports +inf (nothing to pick).
/// Every pass that writes depth (the reference, the raycast pass, any later one) uses it.
pub const DEPTH_OPACITY: f64 = 0.5;

/// The raycast pass's workgroup edge: one invocation per pixel, in 8×8 tiles.
pub const WORKGROUP_SIZE: u32 = 8;

/// Gradient magnitudes below G0 (in TF-range fractions per finest voxel) count as flat and get
/// unlit colour, above G1 fully lit, smooth in between: zero gradients cannot make NaNs, and
/// f32 noise on a flat field cannot flicker the shading.
pub const SHADING_FLAT_BELOW: f64 = 2e-4;
pub const SHADING_LIT_ABOVE: f64 = 2e-3;

/// Where the reference renderer (and uploads) get node payloads: 36³ u16, x fastest.
pub trait BrickSource: Sync {
    fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]>;
}

/// The GPU node buffer of the octree traversal (gpu_octree.rs ↔ shaders/octree.wgsl): records
/// of [`OCTREE_RECORD_WORDS`] u32; record 0 a header (root reference, leaf count), record
/// 1..=leaves the cut's leaves (octree_cut.rs; leaf index = record − 1: per-leaf MIP bound and
/// visibility word), then its inner nodes. An inner record holds 8 child references (x
/// fastest); a leaf record its page word, 6 ropes (−x, +x, −y, +y, −z, +z) and its leaf index.
pub const OCTREE_RECORD_WORDS: u32 = 8;
/// A node reference: record id in the low bits, the node's size (it spans 2^size page cells
/// per axis) from [`OCTREE_SIZE_SHIFT`], [`OCTREE_LEAF_BIT`] for a leaf; [`OCTREE_NULL`] for
/// no node (a volume face, a child outside the grid). The size travels with the reference, so
/// the shader computes every box from the cell it looks up (octree §5.2: no box in memory).
pub const OCTREE_ID_MASK: u32 = (1 << 27) - 1;
pub const OCTREE_SIZE_SHIFT: u32 = 27;
pub const OCTREE_LEAF_BIT: u32 = 1 << 31;
pub const OCTREE_NULL: u32 = u32::MAX;
