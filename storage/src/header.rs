//! The store's document types: its header, statistics and the format versions and features
//! a reader must know. Pure (no disk, no C): a remote viewer reads these from the data service
//! (see `strata-service`), a local one from the sled store (`crate::store`, which re-exports
//! them under their old paths).

use std::path::Path;

use serde::{Deserialize, Serialize};
pub use strata_types::ValueMapping;
use xxhash_rust::xxh3::xxh3_64;

pub use crate::brick::BrickCodec;
use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::octree::OctreeLayout;
pub use crate::skeleton::{NodeInfo, Skeleton, FEATURE_SPARSE_SKELETON};
use crate::source_info::{LabelInfo, SampleType, WindowPreset};

/// Format 2: the brick codec is a per-store choice named in the header ([`StoreHeader::codec`]),
/// and a header may list [`StoreHeader::required_features`] that a reader must know. Format 1
/// (lz4 bricks, no codec field) still opens: its records decode by their kind byte. Format 3:
/// the same records and documents in pack files behind a read-only index (`crate::packs`)
/// instead of sled; formats 1 and 2 still open (read-only).
pub const STORE_FORMAT_VERSION: u32 = 3;
/// The oldest format this build opens.
pub const OLDEST_READABLE_FORMAT_VERSION: u32 = 1;
/// Features of format 2 this build reads. A later wave extends format 2 without a version bump
/// by adding a feature here (the octree's sparse skeleton, say) and naming it in the header of
/// the stores that use it; a build that lacks it refuses those stores with a clear message
/// instead of misreading them. `predicted-u8-bricks`: u8 bricks of kinds 6 and 7;
/// `linear3d-u8-bricks`: u8 bricks of kind 8; `column-delta-u8-bricks`: u8 bricks of kind 9
/// (see [`crate::brick`]); `frames`: see [`FEATURE_FRAMES`]; `sparse-skeleton`: see
/// [`FEATURE_SPARSE_SKELETON`].
pub const KNOWN_STORE_FEATURES: &[&str] = &[
    crate::brick::PREDICTED_U8_FEATURE,
    crate::brick::LINEAR3D_U8_FEATURE,
    crate::brick::COLUMN_DELTA_U8_FEATURE,
    FEATURE_FRAMES,
    FEATURE_SPARSE_SKELETON,
];
/// A 4-D store: [`StoreHeader::frames`] volumes on one grid. Frame 0 is stored exactly as a
/// single volume is (tree `bricks`, meta `skeleton`), so everything that reads one volume reads
/// frame 0 unchanged; frame f ≥ 1 has its bricks in tree `bricks-frame-f` (same keys) and its
/// skeleton at meta `skeleton-frame-f`. All frames share the header's value mapping; the
/// histogram and statistics are frame 0's.
pub const FEATURE_FRAMES: &str = "frames";

/// The header's value mapping: physical = slope · stored + intercept (strata-types'
/// [`ValueMapping`], flattened so the header JSON keeps its shape) and the unit it yields.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueMappingWithUnit {
    #[serde(flatten)]
    pub mapping: ValueMapping,
    /// "HU" for CT, empty when the unit is arbitrary (MR).
    pub unit: String,
}

impl ValueMappingWithUnit {
    pub fn physical(&self, stored: u16) -> f64 {
        self.mapping.physical(f64::from(stored))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    pub inputs: Vec<String>,
    pub source_format: String,
    pub imported_at_unix_seconds: u64,
    pub tool_version: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreHeader {
    pub format_version: u32,
    pub geometry: VolumeGeometry,
    pub stored: StoredScalar,
    pub value_mapping: ValueMappingWithUnit,
    pub source_sample_type: SampleType,
    /// Worst-case physical error from quantising the source (0 for exact imports).
    pub quantization_error: f64,
    /// NaN/±Inf samples in a float source (see `quantize` for the policy).
    pub non_finite_samples: u64,
    pub modality: String,
    pub windows: Vec<WindowPreset>,
    pub description: String,
    pub provenance: Provenance,
    pub layout: OctreeLayout,
    pub brick_core: u64,
    pub brick_apron: u64,
    /// Lowest and highest stored value at level 0.
    pub stored_range: [u16; 2],
    /// Identifies this import: written once when the store is created, different for every
    /// import of the same name, so a served brick URL that carries it can be cached for ever.
    /// Empty for stores written before it existed (see [`StoreHeader::generation_id`]).
    #[serde(default)]
    pub generation: String,
    /// How the bricks are compressed. Absent in format-1 headers (which are all lz4); written
    /// only when it is not lz4, so a format-1 header written today reads exactly as before.
    #[serde(
        default = "format_1_codec",
        skip_serializing_if = "BrickCodec::is_format_1"
    )]
    pub codec: BrickCodec,
    /// Format-2 extensions this store uses, each of which a reader must understand (see
    /// [`KNOWN_STORE_FEATURES`]). Empty for every store this build writes.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub required_features: Vec<String>,
    /// A label map's labels (names, colours), from a DICOM SEG; absent for other stores, and
    /// ignored by builds that predate it (the voxels read the same without it).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub labels: Vec<LabelInfo>,
    /// Volumes in a 4-D store (time points, cardiac phases); 1 (and absent) otherwise. More
    /// than one requires the feature [`FEATURE_FRAMES`].
    #[serde(default = "one_frame", skip_serializing_if = "is_one_frame")]
    pub frames: u32,
}

fn one_frame() -> u32 {
    1
}

fn is_one_frame(frames: &u32) -> bool {
    *frames == 1
}

fn format_1_codec() -> BrickCodec {
    BrickCodec::Lz4
}

impl StoreHeader {
    /// The import's generation; for stores written before generations existed, one derived
    /// from what differs between two imports (import time, layout, value range, source).
    pub fn generation_id(&self) -> String {
        if !self.generation.is_empty() {
            return self.generation.clone();
        }
        let derived = serde_json::to_vec(self).map_or(0, |json| xxh3_64(&json));
        format!("h{derived:016x}")
    }
}

/// What the import wrote, for `strata info`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StoreStats {
    /// Per level: (bricks, constant bricks).
    pub bricks_per_level: Vec<(u64, u64)>,
    pub compressed_bytes: u64,
    /// Bytes the bricks would take uncompressed, aprons included.
    pub uncompressed_bytes: u64,
    pub source_bytes: u64,
    pub import_seconds: f64,
}

/// How the stored samples are kept: u8 or u16 voxels (both decode to u16).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum StoredScalar {
    U8,
    U16,
}

impl StoredScalar {
    pub fn max_value(self) -> u16 {
        match self {
            StoredScalar::U8 => u8::MAX as u16,
            StoredScalar::U16 => u16::MAX,
        }
    }
}

/// What a build that knows only the store features `known` says of `header`: lets the tests
/// show that an older build (one whose list lacks a feature) refuses a store cleanly.
#[doc(hidden)]
pub fn check_format_knowing(path: &Path, header: &StoreHeader, known: &[&str]) -> Result<()> {
    let rebuild = || rebuild_command(path, header);
    let v = header.format_version;
    if !(OLDEST_READABLE_FORMAT_VERSION..=STORE_FORMAT_VERSION).contains(&v) {
        return Err(StorageError::unsupported(
            path,
            format!(
                "store format version {v} (this build reads versions {OLDEST_READABLE_FORMAT_VERSION} to {STORE_FORMAT_VERSION}); rebuild it with: {}",
                rebuild()
            ),
        ));
    }
    if v == 1 && header.codec != BrickCodec::Lz4 {
        return Err(StorageError::corrupted(
            path,
            format!(
                "its format-1 header names the {} codec, which format 1 does not have",
                header.codec.name()
            ),
        ));
    }
    if let Some(unknown) = header
        .required_features
        .iter()
        .find(|f| !known.contains(&f.as_str()))
    {
        return Err(StorageError::unsupported(
            path,
            format!(
                "store feature '{unknown}' of a newer Strata; update Strata, or rebuild the store with: {}",
                rebuild()
            ),
        ));
    }
    Ok(())
}

/// The `strata import` command line that rebuilds a store from its recorded source.
pub fn rebuild_command(path: &Path, header: &StoreHeader) -> String {
    let input = match header.provenance.inputs.as_slice() {
        [one] => one.clone(),
        // A DICOM series records its files: their folder is what `strata import` takes.
        [first, ..] => Path::new(first)
            .parent()
            .map_or_else(|| first.clone(), |p| p.display().to_string()),
        [] => "SOURCE".into(),
    };
    format!("strata import --replace '{input}' '{}'", path.display())
}
