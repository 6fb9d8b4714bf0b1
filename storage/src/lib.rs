//! strata-storage: the out-of-core brick octree store (sled + lz4) and the streaming importers.
//!
//! Knows nothing of GPUs. See ARCHITECTURE.md for the store layout and its invariants.

pub mod error;
pub mod geometry;
pub mod source;
pub mod readers;
pub mod quantize;
pub mod octree;
pub mod brick;
pub mod store;
pub mod import;
pub mod phantom;
pub mod histogram;

pub use error::{StorageError, Result};
pub use geometry::Geometry;
pub use source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo, WindowPreset};
pub use octree::{BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_EDGE, BRICK_VOXELS};
pub use store::{Store, StoreHeader, StoredScalar, ValueMapping};
