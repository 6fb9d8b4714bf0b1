//! An OME-Zarr pyramid read in place (a folder, `s3://`, `https://`) as a
//! [`VolumeSource`]: what `strata render|flythrough|view` stream without importing.
//!
//! A brick of level L is its 32³ core (one inner chunk of a Strata export) plus the 2-voxel
//! apron, which lies in the borders of up to 26 neighbour chunks, in up to 8 shards. The brick
//! is read as one array subset (core ± 2, clamped to the level) through zarrs' sharded reader:
//! each shard's index is fetched once and cached (`ArrayShardedReadableExtCache`), the byte
//! ranges of the inner chunks it needs from one shard go out as one `get_ranges` call, which
//! object_store merges where they are near each other; outside the volume the edge voxel is
//! replicated, as the store's importer does. Many bricks are in flight at once: the loader's
//! fetch threads each read one, and their requests share the object store's connection pool.
//! Fetched ranges and object sizes are kept ([`RangeCacheStore`]), so a chunk that is the next
//! brick's own, or a shard's index, crosses the wire once.
//!
//! The header, histogram and octree skeleton (per-node ranges) come from the `strata` attribute
//! and the skeleton object of a Strata export. A foreign pyramid streams when its levels are
//! Strata's (each level the ceiling half of the one before, down to one brick) and its samples
//! 8- or 16-bit unsigned; its node ranges are unknown and count as non-empty (the full range).
//! Anything else is imported first (`strata import`), which rebuilds the pyramid.

use std::sync::Arc;

use strata_source::{SourceError, VolumeSource};
use strata_storage::brick::{encode_brick, value_range};
use strata_storage::histogram::Histogram;
use strata_storage::store::{NodeInfo, Skeleton, StoreStats};
use strata_storage::{
    BrickId, OctreeLayout, StoreHeader, StoredScalar, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD,
    BRICK_PAYLOAD_VOXELS,
};
use zarrs::array::{
    Array, ArrayShardedReadableExt, ArrayShardedReadableExtCache, ArraySubset, CodecOptions,
};
use zarrs::storage::ReadableWritableListableStorageTraits;

use crate::import::{data_type_name, open_level, open_multiscale, OpenedMultiscale};
use crate::metadata::SKELETON_KEY;
use crate::range_cache::{RangeCacheStore, TransferCounters};
use crate::{ObjectLocation, OmeZarrError, Result};

type LevelArray = Array<dyn ReadableWritableListableStorageTraits>;

struct Level {
    array: LevelArray,
    /// Shard indices (partial decoders) fetched so far.
    cache: ArrayShardedReadableExtCache,
}

/// An OME-Zarr multiscale streamed brick by brick.
pub struct OmeZarrSource {
    display: String,
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    stats: StoreStats,
    levels: Vec<Level>,
    narrow: bool,
    counters: Arc<TransferCounters>,
    /// Bricks assembled so far, for [`OmeZarrSource::needed_chunk_bytes`].
    bricks_read: std::sync::Mutex<std::collections::HashSet<BrickId>>,
}

/// Bytes of fetched ranges (inner chunks, shard indices) kept for the neighbours that need them.
pub const RANGE_CACHE_BYTES: u64 = 256 << 20;

impl OmeZarrSource {
    /// Opens the multiscale at `location`: reads the group, each level's zarr.json and, for a
    /// Strata export, the skeleton object. No voxel is read.
    pub fn open(mut location: ObjectLocation) -> Result<Self> {
        let cached = RangeCacheStore::new(location.store.clone(), RANGE_CACHE_BYTES);
        let counters = cached.counters.clone();
        location.store = Arc::new(cached);
        let opened = open_multiscale(location)?;
        let display = opened.location.display.clone();
        let (header, skeleton, histogram, stats) = match &opened.multiscale.strata {
            Some(strata) => {
                let skeleton = read_skeleton(&opened, &strata.skeleton)?;
                let layout = &strata.header.layout;
                if skeleton.levels.len() != layout.level_count()
                    || (0..layout.level_count())
                        .any(|l| skeleton.levels[l].len() as u64 != layout.brick_count_in_level(l))
                {
                    return Err(OmeZarrError::invalid(
                        &display,
                        "the skeleton object does not match the strata attribute's layout",
                    ));
                }
                (
                    strata.header.clone(),
                    skeleton,
                    strata.histogram.clone(),
                    strata.stats.clone(),
                )
            }
            None => foreign_description(&opened)?,
        };
        let narrow = header.stored == StoredScalar::U8;
        let mut levels = Vec::with_capacity(header.layout.level_count());
        for (level, d) in header.layout.level_dims.iter().enumerate() {
            let array = open_level(&opened, level)?;
            let expected = [d[2], d[1], d[0]].map(u64::from);
            if array.shape() != expected {
                return Err(OmeZarrError::invalid(
                    &display,
                    format!(
                        "level {level} has shape {:?}; Strata's octree needs {expected:?} (z, y, x): import it instead (strata import), which rebuilds the pyramid",
                        array.shape()
                    ),
                ));
            }
            let dtype = data_type_name(&array);
            let wanted = if narrow { "uint8" } else { "uint16" };
            if dtype != wanted {
                return Err(OmeZarrError::invalid(
                    &display,
                    format!("level {level} holds {dtype}, streaming needs {wanted}: import it instead (strata import)"),
                ));
            }
            let cache = ArrayShardedReadableExtCache::new(&array);
            levels.push(Level { array, cache });
        }
        Ok(OmeZarrSource {
            display,
            header,
            skeleton,
            histogram,
            stats,
            levels,
            narrow,
            counters,
            bricks_read: Default::default(),
        })
    }

    /// Requests and bytes that crossed the wire so far (metadata included).
    pub fn transfer_counters(&self) -> Arc<TransferCounters> {
        self.counters.clone()
    }

    /// The brick's 36³ payload (x fastest): its core and apron, edge-replicated outside.
    pub fn assemble_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        let layout = &self.header.layout;
        if !layout.contains(id) {
            return Err(SourceError::Refused {
                location: self.display.clone(),
                message: format!("no brick level {} at {:?}", id.level, id.coords),
            });
        }
        self.bricks_read
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id);
        let level = &self.levels[id.level as usize];
        let dims = layout.level_dims[id.level as usize].map(i64::from);
        let (core, apron, payload) = (
            i64::from(BRICK_CORE),
            i64::from(BRICK_APRON),
            i64::from(BRICK_PAYLOAD),
        );
        // Per index axis (x, y, z): the payload's first voxel, and the clamped range read.
        let start = [0, 1, 2].map(|a| i64::from(id.coords[a]) * core - apron);
        let lo = [0, 1, 2].map(|a| start[a].clamp(0, dims[a] - 1));
        let hi = [0, 1, 2].map(|a| (start[a] + payload).clamp(1, dims[a]));
        let subset = ArraySubset::new_with_ranges(&[
            lo[2] as u64..hi[2] as u64,
            lo[1] as u64..hi[1] as u64,
            lo[0] as u64..hi[0] as u64,
        ]);
        let options = CodecOptions::default();
        let fail = |e: zarrs::array::ArrayError| SourceError::Unavailable {
            location: self.display.clone(),
            message: format!("brick level {} at {:?}: {e}", id.level, id.coords),
        };
        let region: Vec<u16> = if self.narrow {
            level
                .array
                .retrieve_array_subset_sharded_opt::<Vec<u8>>(&level.cache, &subset, &options)
                .map_err(fail)?
                .into_iter()
                .map(u16::from)
                .collect()
        } else {
            level
                .array
                .retrieve_array_subset_sharded_opt::<Vec<u16>>(&level.cache, &subset, &options)
                .map_err(fail)?
        };
        let n = [0, 1, 2].map(|a| (hi[a] - lo[a]) as usize);
        let mut out = Vec::with_capacity(BRICK_PAYLOAD_VOXELS);
        let index = |a: usize, d: i64| ((start[a] + d).clamp(0, dims[a] - 1) - lo[a]) as usize;
        let xs: Vec<usize> = (0..payload).map(|d| index(0, d)).collect();
        for dz in 0..payload {
            let z = index(2, dz);
            for dy in 0..payload {
                let row = (z * n[1] + index(1, dy)) * n[0];
                out.extend(xs.iter().map(|&x| region[row + x]));
            }
        }
        Ok(out)
    }

    /// Encoded bytes of the inner chunks the bricks read so far needed: each brick's own and its
    /// neighbours' (its apron's sources), each chunk counted once. The denominator of the
    /// bytes-fetched ratio; reads shard indices (already cached by the reads it accounts for).
    pub fn needed_chunk_bytes(&self) -> Result<u64> {
        let ids: Vec<BrickId> = self
            .bricks_read
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .copied()
            .collect();
        let mut chunks = std::collections::HashSet::new();
        for id in ids {
            let n = self
                .header
                .layout
                .bricks_in_level(id.level as usize)
                .map(i64::from);
            for dz in -1..=1i64 {
                for dy in -1..=1i64 {
                    for dx in -1..=1i64 {
                        let c = [
                            i64::from(id.coords[0]) + dx,
                            i64::from(id.coords[1]) + dy,
                            i64::from(id.coords[2]) + dz,
                        ];
                        if (0..3).all(|a| (0..n[a]).contains(&c[a])) {
                            chunks.insert((id.level, c[2] as u64, c[1] as u64, c[0] as u64));
                        }
                    }
                }
            }
        }
        let mut total = 0;
        for (level, z, y, x) in chunks {
            let l = &self.levels[level as usize];
            let range = l
                .array
                .subchunk_byte_range(&l.cache, &[z, y, x])
                .map_err(|e| OmeZarrError::access(&self.display, e))?;
            if let Some(range) = range {
                total += range.length(u64::MAX);
            }
        }
        Ok(total)
    }

    /// Shard indices cached so far, over all levels.
    pub fn cached_shard_indices(&self) -> usize {
        self.levels.iter().map(|l| l.cache.len()).sum()
    }
}

fn read_skeleton(opened: &OpenedMultiscale, key: &str) -> Result<Skeleton> {
    if key != SKELETON_KEY {
        return Err(OmeZarrError::invalid(
            &opened.location.display,
            format!("unexpected skeleton object `{key}`"),
        ));
    }
    use object_store::ObjectStoreExt;
    let path = object_store::path::Path::from(key);
    let store = opened.location.store.clone();
    let bytes = crate::zarr_store::block_on(async move {
        let got = store.get(&path).await?;
        got.bytes().await
    })?
    .map_err(|e| OmeZarrError::access(&opened.location.display, format!("{key}: {e}")))?;
    Skeleton::decode(&bytes).ok_or_else(|| {
        OmeZarrError::invalid(
            &opened.location.display,
            format!("{key}: checksum or framing is wrong"),
        )
    })
}

/// Header, skeleton (ranges unknown: full), empty histogram and stats of a foreign pyramid.
fn foreign_description(
    opened: &OpenedMultiscale,
) -> Result<(StoreHeader, Skeleton, Histogram, StoreStats)> {
    let display = &opened.location.display;
    let array = open_level(opened, 0)?;
    let shape = array.shape().to_vec();
    let choice =
        crate::import::choose_axes(&opened.multiscale, &shape, &Default::default(), display)?;
    if !choice.fixed.iter().all(|&(axis, _)| shape[axis] == 1) {
        return Err(OmeZarrError::invalid(
            display,
            "streaming takes 3 space axes only: import it (strata import --channel/--time picks one)",
        ));
    }
    if shape.len() != 3 {
        return Err(OmeZarrError::invalid(
            display,
            "streaming takes z, y, x arrays only: import it instead (strata import)",
        ));
    }
    let dims = strata_storage::VolumeGeometry::checked_dims([shape[2], shape[1], shape[0]])
        .map_err(|e| OmeZarrError::invalid(display, e.to_string()))?;
    let dtype = data_type_name(&array);
    let stored = match dtype.as_str() {
        "uint8" => StoredScalar::U8,
        "uint16" => StoredScalar::U16,
        other => {
            return Err(OmeZarrError::invalid(
                display,
                format!("{other} samples cannot be streamed: import it instead (strata import)"),
            ))
        }
    };
    let (geometry, notes) =
        crate::import::foreign_geometry(&opened.multiscale, &choice, dims, display)?;
    for note in notes {
        let place: &str = display;
        tracing::info!("{place}: {note}");
    }
    let layout = OctreeLayout::new(dims);
    if opened.multiscale.datasets.len() < layout.level_count() {
        return Err(OmeZarrError::invalid(
            display,
            format!(
                "{} levels; Strata's octree needs {} (down to one 32³ brick): import it instead (strata import)",
                opened.multiscale.datasets.len(),
                layout.level_count()
            ),
        ));
    }
    let max = stored.max_value();
    let mut skeleton = Skeleton::new(&layout);
    for level in &mut skeleton.levels {
        level.fill(NodeInfo {
            min: 0,
            max,
            flags: 0,
        });
    }
    let header = StoreHeader {
        format_version: strata_storage::store::STORE_FORMAT_VERSION,
        geometry,
        stored,
        value_mapping: strata_storage::ValueMappingWithUnit {
            mapping: strata_storage::ValueMapping {
                slope: 1.0,
                intercept: 0.0,
            },
            unit: String::new(),
        },
        source_sample_type: if stored == StoredScalar::U8 {
            strata_storage::SampleType::U8
        } else {
            strata_storage::SampleType::U16
        },
        quantization_error: 0.0,
        non_finite_samples: 0,
        modality: String::new(),
        windows: Vec::new(),
        description: opened.multiscale.name.clone(),
        provenance: strata_storage::store::Provenance {
            inputs: vec![display.clone()],
            source_format: "ome-zarr".into(),
            imported_at_unix_seconds: 0,
            tool_version: String::new(),
        },
        layout: layout.clone(),
        brick_core: u64::from(BRICK_CORE),
        brick_apron: u64::from(BRICK_APRON),
        stored_range: [0, max],
        generation: format!("ome-zarr:{display}"),
        // The records this source hands the loader (read_brick_record) use the default codec.
        codec: strata_storage::BrickCodec::default(),
        required_features: Vec::new(),
        labels: Vec::new(),
        frames: 1,
    };
    let histogram = Histogram::from_stored(
        &strata_storage::histogram::StoredValueCounts::default(),
        1.0,
        0.0,
    );
    Ok((header, skeleton, histogram, StoreStats::default()))
}

impl VolumeSource for OmeZarrSource {
    fn location(&self) -> String {
        self.display.clone()
    }
    fn header(&self) -> &StoreHeader {
        &self.header
    }
    fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }
    fn histogram(&self) -> &Histogram {
        &self.histogram
    }
    fn stats(&self) -> &StoreStats {
        &self.stats
    }
    /// Assembles the brick and encodes it as the store would (the loader's threads decode and
    /// verify records the same way for every source).
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        let voxels = self.assemble_brick(id)?;
        Ok(encode_brick(
            id,
            &voxels,
            value_range(&voxels),
            self.narrow,
            self.header.codec,
        ))
    }
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        self.assemble_brick(id)
    }
}

/// Opens `spec` as a streamed OME-Zarr source.
pub fn open_source(spec: &str, options: &crate::ObjectStoreOptions) -> Result<Arc<OmeZarrSource>> {
    Ok(Arc::new(OmeZarrSource::open(ObjectLocation::open(
        spec, options, false,
    )?)?))
}
