//! strata-storage: the out-of-core brick octree store (sled; byte-shuffled lz4 or zstd bricks) and the streaming importers.
//!
//! Knows nothing of GPUs. See ARCHITECTURE.md for the store layout and its invariants.
//!
//! The default feature `local` brings everything that needs a local disk, threads or C code:
//! the sled store ([`store::Store`]), import, the file readers, verification and locking.
//! Without it (`--no-default-features`, which builds for `wasm32-unknown-unknown`) the crate
//! keeps what a remote viewer needs to read a store through the data service: the header and
//! statistics ([`header`]), the skeleton ([`skeleton`]), brick records and their decoding
//! ([`brick`]; zstd through the pure-Rust ruzstd there), the xxh3 checksums and the error type.
//! The modules `store`, `source` and `quantize` then hold only their pure types, so a path such
//! as `strata_storage::store::Skeleton` is the same in both builds.

pub mod brick;
#[cfg(feature = "local")]
mod contained_db;
pub mod error;
pub mod geometry;
pub mod header;
pub mod histogram;
#[cfg(feature = "local")]
pub mod import;
#[cfg(feature = "local")]
pub mod inventory;
#[cfg(feature = "local")]
pub mod lock;
mod lock_holder;
pub mod octree;
#[cfg(feature = "local")]
mod packs;
#[cfg(feature = "local")]
pub mod phantom;
#[cfg(feature = "local")]
pub mod quantize;
#[cfg(feature = "local")]
pub mod readers;
#[cfg(feature = "local")]
pub mod regular_file;
pub mod skeleton;
#[cfg(feature = "local")]
pub mod source;
pub mod source_info;
#[cfg(feature = "local")]
pub mod sparse_phantom;
#[cfg(feature = "local")]
pub mod staging;
#[cfg(feature = "local")]
pub mod store;

/// Without `local`: the pure types of the sled store's module, under the same paths.
#[cfg(not(feature = "local"))]
pub mod store {
    pub use crate::header::*;
}

/// Without `local`: the pure types of the readers' module, under the same paths.
#[cfg(not(feature = "local"))]
pub mod source {
    pub use crate::source_info::*;
}

/// Without `local`: the stored scalar type of the quantiser's module, under the same path.
#[cfg(not(feature = "local"))]
pub mod quantize {
    pub use crate::header::StoredScalar;
}

pub use brick::BrickCodec;
pub use error::{Result, StorageError};
#[cfg(feature = "local")]
pub use source::{OpenedSource, RawVolume};
pub use source_info::{ByteOrder, LabelInfo, SampleType, SourceInfo, WindowPreset};
#[cfg(feature = "local")]
pub use store::Store;
pub use store::{StoreHeader, StoredScalar, ValueMapping, ValueMappingWithUnit};
