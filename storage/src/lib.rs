//! strata-storage: the out-of-core brick octree store (sled; byte-shuffled lz4 or zstd bricks) and the streaming importers.
//!
//! Knows nothing of GPUs. See ARCHITECTURE.md for the store layout and its invariants.

pub mod brick;
mod contained_db;
pub mod error;
pub mod geometry;
pub mod histogram;
pub mod import;
pub mod inventory;
pub mod lock;
mod lock_holder;
pub mod octree;
pub mod phantom;
pub mod quantize;
pub mod readers;
pub mod regular_file;
pub mod skeleton;
pub mod source;
pub mod sparse_phantom;
pub mod staging;
pub mod store;

pub use brick::BrickCodec;
pub use error::{Result, StorageError};
pub use geometry::VolumeGeometry;
pub use octree::{
    BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS,
};
pub use source::{
    ByteOrder, LabelInfo, OpenedSource, RawVolume, SampleType, SourceInfo, WindowPreset,
};
pub use store::{Store, StoreHeader, StoredScalar, ValueMapping, ValueMappingWithUnit};
