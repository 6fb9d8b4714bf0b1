//! strata-types: the vocabulary storage, loader, render and app share.
//!
//! Geometry in patient space, the mapping from stored integers to physical values, the brick
//! constants and the octree's shape are defined here once, so the store and the renderer cannot
//! drift apart, and render still depends on neither storage nor loader (ARCHITECTURE.md).
//! Nothing here does I/O or touches a GPU.

pub mod brick;
pub mod coded_concept;
pub mod geometry;
pub mod octree;
pub mod trilinear;
pub mod value_mapping;

pub use brick::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};
pub use coded_concept::{Code, SegmentCategory};
pub use geometry::{
    GeometryError, VolumeGeometry, MAX_AXIS_VOXELS, MAX_ORIGIN_MM, MAX_SPACING_MM,
    MAX_TOTAL_VOXELS, MIN_SPACING_MM,
};
pub use octree::{level_count, level_dims, BrickId, OctreeLayout};
pub use trilinear::trilinear_corners;
pub use value_mapping::ValueMapping;
