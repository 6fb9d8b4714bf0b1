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
//! and the skeleton object of a Strata export. A foreign pyramid (no `strata` attribute) streams
//! when, for each of Strata's levels (each the ceiling half of the one before, down to one
//! brick), one of its datasets has that shape (datasets of other shapes, such as levels binned
//! along some axes only, are passed over); its node ranges are unknown and count as non-empty.
//! Its samples map onto stored values as `strata import` maps them, decided at open:
//! - uint8 / uint16 as they are, int8 / int16 shifted by 128 / 32768 (exact: CT in HU keeps
//!   every value); the data range, for the transfer function's table, is the `omero` window's
//!   `min`/`max` when given, else the type's full range;
//! - float32/64 and (u)int32 scaled onto 16 bits over the `omero` window's `min`/`max` when
//!   given, else over the range of the coarsest level (read at open, one brick): level-0
//!   values outside that range are clamped, which the source's notes say. Import computes the
//!   exact range of level 0 instead.
//!
//! Whatever cannot be streamed (other axes, too few levels of Strata's shapes, other types) is
//! refused with the URL and the remedy: `strata import URL STORE`, which rebuilds the pyramid.

use std::sync::Arc;

use strata_source::{BrickFetcher, FetchOptions, SourceError, VolumeSource};
use strata_storage::brick::{encode_brick, value_range};
use strata_storage::histogram::Histogram;
use strata_storage::quantize::Quantizer;
use strata_storage::store::{NodeInfo, Skeleton, StoreStats};
use strata_storage::{StoreHeader, StoredScalar};
use strata_types::{
    BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS,
};
use zarrs::array::{
    Array, ArrayShardedReadableExt, ArrayShardedReadableExtCache, ArraySubset,
    AsyncArrayShardedReadableExt, AsyncArrayShardedReadableExtCache, CodecOptions,
};
use zarrs::storage::ReadableWritableListableStorageTraits;
use zarrs_object_store::AsyncObjectStore;

use crate::import::{data_type_name, open_level, open_multiscale, read_skeleton, OpenedMultiscale};
use crate::range_cache::{RangeCacheStore, TransferCounters};
use crate::{ObjectLocation, OmeZarrError, Result};

type LevelArray = Array<dyn ReadableWritableListableStorageTraits>;

struct Level {
    array: LevelArray,
    /// Shard indices (partial decoders) fetched so far.
    cache: ArrayShardedReadableExtCache,
}

/// How a level's samples become stored values (decided at open, the same for every level).
#[derive(Clone, Debug)]
enum Sampling {
    U8,
    U16,
    /// int8 / int16: shifted by 128 / 32768, exact (as `Quantizer::plan`).
    I8,
    I16,
    /// Read as f64 (float32/64, (u)int32) and quantised with `quantizer`.
    Scaled {
        sample: ScaledSample,
        quantizer: Quantizer,
    },
}

#[derive(Clone, Copy, Debug)]
enum ScaledSample {
    F32,
    F64,
    I32,
    U32,
}

impl Sampling {
    fn of_data_type(dtype: &str, quantizer: Option<Quantizer>) -> Option<Sampling> {
        let scaled = |sample| quantizer.map(|quantizer| Sampling::Scaled { sample, quantizer });
        match dtype {
            "uint8" => Some(Sampling::U8),
            "uint16" => Some(Sampling::U16),
            "int8" => Some(Sampling::I8),
            "int16" => Some(Sampling::I16),
            "float32" => scaled(ScaledSample::F32),
            "float64" => scaled(ScaledSample::F64),
            "int32" => scaled(ScaledSample::I32),
            "uint32" => scaled(ScaledSample::U32),
            _ => None,
        }
    }

    fn stored(&self) -> StoredScalar {
        match self {
            Sampling::U8 | Sampling::I8 => StoredScalar::U8,
            _ => StoredScalar::U16,
        }
    }
}

/// The samples `$read!(T)` returns (a `Vec<T>`), as stored values; `$sampling: &Sampling`.
macro_rules! convert_samples {
    ($sampling:expr, $read:ident) => {
        match $sampling {
            Sampling::U8 => $read!(u8).into_iter().map(u16::from).collect::<Vec<u16>>(),
            Sampling::U16 => $read!(u16),
            Sampling::I8 => $read!(i8)
                .into_iter()
                .map(|v| (i16::from(v) + 128) as u16)
                .collect(),
            Sampling::I16 => $read!(i16)
                .into_iter()
                .map(|v| (i32::from(v) + 32768) as u16)
                .collect(),
            Sampling::Scaled { sample, quantizer } => match sample {
                ScaledSample::F32 => $read!(f32)
                    .into_iter()
                    .map(|v| quantizer.to_stored(f64::from(v)))
                    .collect(),
                ScaledSample::F64 => $read!(f64)
                    .into_iter()
                    .map(|v| quantizer.to_stored(v))
                    .collect(),
                ScaledSample::I32 => $read!(i32)
                    .into_iter()
                    .map(|v| quantizer.to_stored(f64::from(v)))
                    .collect(),
                ScaledSample::U32 => $read!(u32)
                    .into_iter()
                    .map(|v| quantizer.to_stored(f64::from(v)))
                    .collect(),
            },
        }
    };
}

/// What a brick reads of its level: its core ± the apron, clamped to the level.
struct BrickRegion {
    id: BrickId,
    dims: [i64; 3],
    /// Per index axis (x, y, z): the payload's first voxel, and the clamped range read.
    start: [i64; 3],
    lo: [i64; 3],
    hi: [i64; 3],
    subset: ArraySubset,
}

impl BrickRegion {
    fn of(layout: &OctreeLayout, id: BrickId, display: &str) -> Result<Self, SourceError> {
        if !layout.contains(id) {
            return Err(SourceError::Refused {
                location: display.to_string(),
                message: format!("no brick level {} at {:?}", id.level, id.coords),
            });
        }
        let dims = layout.level_dims[id.level as usize].map(i64::from);
        let (core, apron, payload) = (
            i64::from(BRICK_CORE),
            i64::from(BRICK_APRON),
            i64::from(BRICK_PAYLOAD),
        );
        let start = [0, 1, 2].map(|a| i64::from(id.coords[a]) * core - apron);
        let lo = [0, 1, 2].map(|a| start[a].clamp(0, dims[a] - 1));
        let hi = [0, 1, 2].map(|a| (start[a] + payload).clamp(1, dims[a]));
        let subset = ArraySubset::new_with_ranges(&[
            lo[2] as u64..hi[2] as u64,
            lo[1] as u64..hi[1] as u64,
            lo[0] as u64..hi[0] as u64,
        ]);
        Ok(BrickRegion {
            id,
            dims,
            start,
            lo,
            hi,
            subset,
        })
    }

    /// A read that failed: damage (a codec failed, a checksum, a read the guard refused) is
    /// reported as such, the loader then keeping the parent; storage errors as unavailable.
    fn failed(&self, e: zarrs::array::ArrayError, display: &str) -> SourceError {
        let message = e.to_string();
        let storage = matches!(e, zarrs::array::ArrayError::StorageError(_));
        if !storage || message.contains("Generic strata error") {
            return SourceError::Damaged {
                location: display.to_string(),
                id: self.id,
                message,
            };
        }
        SourceError::Unavailable {
            location: display.to_string(),
            message: format!(
                "brick level {} at {:?}: {message}",
                self.id.level, self.id.coords
            ),
        }
    }

    /// The 36³ payload out of the region read: outside the level, the edge voxel replicated.
    fn gather(&self, region: &[u16]) -> Vec<u16> {
        let (start, lo, hi, dims) = (self.start, self.lo, self.hi, self.dims);
        let payload = i64::from(BRICK_PAYLOAD);
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
        out
    }
}

type AsyncLevelArray = Array<AsyncObjectStore<Arc<dyn object_store::ObjectStore>>>;

/// A level read through zarrs' asynchronous API, for the source's own request path.
struct AsyncLevel {
    array: AsyncLevelArray,
    cache: AsyncArrayShardedReadableExtCache,
}

/// What a brick request task needs, shared with it: the asynchronous levels and the mapping.
pub(crate) struct Assembler {
    display: String,
    layout: OctreeLayout,
    sampling: Sampling,
    levels: Vec<AsyncLevel>,
    /// A Strata export's skeleton and checksums, each brick's core checked against them.
    check: Option<Arc<crate::checksums::ChunkCheck>>,
    /// Chunks whose core passed the check (a brick's apron is read from its neighbours').
    verified: std::sync::Mutex<std::collections::HashSet<BrickId>>,
    /// Bricks assembled so far, for [`OmeZarrSource::needed_chunk_bytes`].
    bricks_read: std::sync::Mutex<std::collections::HashSet<BrickId>>,
}

impl Assembler {
    fn new(
        display: &str,
        layout: &OctreeLayout,
        sampling: &Sampling,
        store: &Arc<dyn object_store::ObjectStore>,
        levels: &[Level],
        check: Option<Arc<crate::checksums::ChunkCheck>>,
    ) -> Result<Self> {
        let storage = Arc::new(AsyncObjectStore::new(store.clone()));
        let levels = levels
            .iter()
            .map(|level| {
                let array = Array::new_with_metadata(
                    storage.clone(),
                    level.array.path().as_str(),
                    level.array.metadata().clone(),
                )
                .map_err(|e| OmeZarrError::invalid(display, e.to_string()))?;
                let cache = AsyncArrayShardedReadableExtCache::new(&array);
                Ok(AsyncLevel { array, cache })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Assembler {
            display: display.to_string(),
            layout: layout.clone(),
            sampling: sampling.clone(),
            levels,
            check,
            verified: Default::default(),
            bricks_read: Default::default(),
        })
    }

    /// The payload, once its core is checked against the export's skeleton and checksums.
    fn checked(&self, id: BrickId, payload: Vec<u16>) -> Result<Vec<u16>, SourceError> {
        if let Some(check) = &self.check {
            let digest = crate::checksums::core_digest(&payload, id, &self.layout, check.narrow);
            check.check(id, digest).map_err(|e| SourceError::Damaged {
                location: self.display.clone(),
                id,
                message: e.to_string(),
            })?;
            self.verified
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(id);
        }
        Ok(payload)
    }

    pub(crate) fn bytes_per_sample(&self) -> usize {
        if self.sampling.stored() == StoredScalar::U8 {
            1
        } else {
            2
        }
    }

    fn note_read(&self, id: BrickId) {
        self.bricks_read
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id);
    }

    /// The brick's payload, its reads awaited on the I/O runtime: dropping the future (an
    /// aborted task) drops object_store's pending requests, which closes their connections.
    pub(crate) async fn assemble(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        let region = BrickRegion::of(&self.layout, id, &self.display)?;
        self.note_read(id);
        let level = &self.levels[id.level as usize];
        let options = CodecOptions::default();
        macro_rules! read {
            ($t:ty) => {
                level
                    .array
                    .async_retrieve_array_subset_sharded_opt::<Vec<$t>>(
                        &level.cache,
                        &region.subset,
                        &options,
                    )
                    .await
                    .map_err(|e| region.failed(e, &self.display))?
            };
        }
        let values = convert_samples!(&self.sampling, read);
        let payload = self.checked(id, region.gather(&values))?;
        // The apron's sources: each neighbour chunk checked whole once (its bytes are in the
        // range cache already; only the decode repeats).
        for neighbour in self.unverified_neighbours(id) {
            let subset = core_subset(&self.layout, neighbour);
            macro_rules! read_core {
                ($t:ty) => {
                    level
                        .array
                        .async_retrieve_array_subset_sharded_opt::<Vec<$t>>(
                            &level.cache,
                            &subset,
                            &options,
                        )
                        .await
                        .map_err(|e| region.failed(e, &self.display))?
                };
            }
            let core = convert_samples!(&self.sampling, read_core);
            self.check_neighbour(id, neighbour, &core)?;
        }
        Ok(payload)
    }

    /// Neighbour chunks of `id` (its apron's sources, in its level) not checked yet.
    fn unverified_neighbours(&self, id: BrickId) -> Vec<BrickId> {
        if self.check.is_none() {
            return Vec::new();
        }
        let n = self
            .layout
            .bricks_in_level(id.level as usize)
            .map(i64::from);
        let verified = self.verified.lock().unwrap_or_else(|p| p.into_inner());
        let mut out = Vec::new();
        for dz in -1..=1i64 {
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let c = [dx, dy, dz]
                        .iter()
                        .zip(id.coords)
                        .map(|(d, c)| i64::from(c) + d)
                        .collect::<Vec<_>>();
                    if (0..3).all(|a| (0..n[a]).contains(&c[a])) {
                        let neighbour =
                            BrickId::new(id.level, [c[0] as u32, c[1] as u32, c[2] as u32]);
                        if !verified.contains(&neighbour) {
                            out.push(neighbour);
                        }
                    }
                }
            }
        }
        out
    }

    /// Checks a neighbour's core (z, y, x order, as read), for brick `id` whose apron it fed.
    fn check_neighbour(
        &self,
        id: BrickId,
        neighbour: BrickId,
        core: &[u16],
    ) -> Result<(), SourceError> {
        let Some(check) = &self.check else {
            return Ok(());
        };
        let dims = self.layout.level_dims[neighbour.level as usize];
        let nx = (dims[0] - neighbour.coords[0] * BRICK_CORE).min(BRICK_CORE) as usize;
        let mut state = crate::checksums::DigestState::default();
        for row in core.chunks_exact(nx) {
            state.add_row(row, check.narrow);
        }
        check
            .check(neighbour, state.finish())
            .map_err(|e| SourceError::Damaged {
                location: self.display.clone(),
                id,
                message: format!(
                    "its apron's source, brick level {} at {:?}, {e}",
                    neighbour.level, neighbour.coords
                ),
            })?;
        self.verified
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(neighbour);
        Ok(())
    }
}

/// The array subset of brick `id`'s core (its chunk, clipped to the level).
fn core_subset(layout: &OctreeLayout, id: BrickId) -> ArraySubset {
    let dims = layout.level_dims[id.level as usize].map(u64::from);
    let core = u64::from(BRICK_CORE);
    let range = |a: usize| {
        let lo = u64::from(id.coords[a]) * core;
        lo..(lo + core).min(dims[a])
    };
    ArraySubset::new_with_ranges(&[range(2), range(1), range(0)])
}

/// How a level's shards hold inner chunks (from its sharding codec's configuration).
struct ShardLayout {
    chunks_per_shard: [u64; 3],
    index_at_end: bool,
}

impl ShardLayout {
    fn of(array: &LevelArray, display: &str) -> Result<ShardLayout> {
        let metadata = serde_json::to_value(array.metadata()).unwrap_or_default();
        let sharding = metadata
            .pointer("/codecs/0")
            .filter(|c| {
                c.get("name").and_then(serde_json::Value::as_str) == Some("sharding_indexed")
            })
            .and_then(|c| c.get("configuration"))
            .ok_or_else(|| OmeZarrError::invalid(display, "the array is not sharded"))?;
        let inner: Vec<u64> = sharding
            .get("chunk_shape")
            .and_then(serde_json::Value::as_array)
            .map(|a| a.iter().filter_map(serde_json::Value::as_u64).collect())
            .unwrap_or_default();
        let outer: Vec<u64> = metadata
            .pointer("/chunk_grid/configuration/chunk_shape")
            .and_then(serde_json::Value::as_array)
            .map(|a| a.iter().filter_map(serde_json::Value::as_u64).collect())
            .unwrap_or_default();
        if inner.len() != 3 || outer.len() != 3 || inner.contains(&0) {
            return Err(OmeZarrError::invalid(
                display,
                "unexpected sharding configuration",
            ));
        }
        Ok(ShardLayout {
            chunks_per_shard: [0, 1, 2].map(|a| outer[a] / inner[a]),
            index_at_end: sharding
                .get("index_location")
                .and_then(serde_json::Value::as_str)
                != Some("start"),
        })
    }
}

/// The quantiser `strata import` plans for samples in [lo, hi] (`Quantizer::plan`'s rule,
/// written out because streaming knows the range before it reads the data): integers spanning
/// at most 65536 values shift exactly, anything else is scaled onto 0..=65535.
fn quantizer_for_range(lo: f64, hi: f64, integer: bool) -> Quantizer {
    let (lo, hi) = if lo <= hi { (lo, hi) } else { (0.0, 0.0) };
    if integer && hi - lo <= 65535.0 {
        return Quantizer {
            stored: StoredScalar::U16,
            offset: lo,
            scale: 1.0,
            max_error_physical: 0.0,
            non_finite_samples: 0,
        };
    }
    let half_span = hi / 2.0 - lo / 2.0;
    let scale = if half_span > 0.0 {
        (65535.0 / 2.0) / half_span
    } else {
        1.0
    };
    Quantizer {
        stored: StoredScalar::U16,
        offset: lo,
        scale,
        max_error_physical: (0.5 * half_span / (65535.0 / 2.0)).min(f64::MAX),
        non_finite_samples: 0,
    }
}

/// The refusal of what cannot be streamed, with the remedy.
fn import_instead(display: &str, why: impl std::fmt::Display) -> OmeZarrError {
    OmeZarrError::invalid(
        display,
        format!("{why}; it cannot be streamed: import it instead with `strata import {display} STORE.strata`, which rebuilds the pyramid"),
    )
}

/// An OME-Zarr multiscale streamed brick by brick.
pub struct OmeZarrSource {
    display: String,
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    stats: StoreStats,
    levels: Vec<Level>,
    sampling: Sampling,
    /// What was assumed or chosen to stream a foreign pyramid (levels taken, value mapping).
    notes: Vec<String>,
    counters: Arc<TransferCounters>,
    /// The (range-cached) object store under the levels.
    store: Arc<dyn object_store::ObjectStore>,
    /// The asynchronous side: what the source's request tasks assemble bricks with.
    assembler: Arc<Assembler>,
}

/// Bytes of fetched ranges (inner chunks, shard indices) kept for the neighbours that need them.
pub const RANGE_CACHE_BYTES: u64 = 256 << 20;

impl OmeZarrSource {
    /// Opens the multiscale at `location`: reads the group, each level's zarr.json and, for a
    /// Strata export, the skeleton object. No voxel is read.
    pub fn open(mut location: ObjectLocation) -> Result<Self> {
        let cached = RangeCacheStore::new(location.store.clone(), RANGE_CACHE_BYTES);
        let counters = cached.counters.clone();
        location.store = location.guard_again(Arc::new(cached));
        let opened = open_multiscale(location)?;
        let display = opened.location.display.clone();
        if let Some(strata) = &opened.multiscale.strata {
            let header = strata.header.clone();
            let skeleton = read_skeleton(&opened, &strata.skeleton, &header.layout)?;
            let layout = &header.layout;
            let sampling = if header.stored == StoredScalar::U8 {
                Sampling::U8
            } else {
                Sampling::U16
            };
            let mut levels = Vec::with_capacity(layout.level_count());
            for (level, d) in layout.level_dims.iter().enumerate() {
                let array = open_level(&opened, level)?;
                let expected = [d[2], d[1], d[0]].map(u64::from);
                if array.shape() != expected {
                    return Err(import_instead(
                        &display,
                        format!(
                            "level {level} has shape {:?} where the strata attribute's octree has {expected:?} (z, y, x)",
                            array.shape()
                        ),
                    ));
                }
                let dtype = data_type_name(&array);
                let wanted = if sampling.stored() == StoredScalar::U8 {
                    "uint8"
                } else {
                    "uint16"
                };
                if dtype != wanted {
                    return Err(import_instead(
                        &display,
                        format!(
                            "level {level} holds {dtype} where the strata attribute says {wanted}"
                        ),
                    ));
                }
                let cache = ArrayShardedReadableExtCache::new(&array);
                levels.push(Level { array, cache });
            }
            let check = crate::import::chunk_check(&opened)?.map(Arc::new);
            let assembler = Arc::new(Assembler::new(
                &display,
                &header.layout,
                &sampling,
                &opened.location.store,
                &levels,
                check,
            )?);
            return Ok(OmeZarrSource {
                store: opened.location.store.clone(),
                display,
                histogram: strata.histogram.clone(),
                stats: strata.stats.clone(),
                header,
                skeleton,
                levels,
                sampling,
                notes: Vec::new(),
                counters,
                assembler,
            });
        }
        let foreign = open_foreign(&opened)?;
        let place: &str = &display;
        for note in &foreign.notes {
            tracing::info!("{place}: {note}");
        }
        let assembler = Arc::new(Assembler::new(
            &display,
            &foreign.header.layout,
            &foreign.sampling,
            &opened.location.store,
            &foreign.levels,
            None,
        )?);
        Ok(OmeZarrSource {
            store: opened.location.store.clone(),
            assembler,
            display,
            header: foreign.header,
            skeleton: foreign.skeleton,
            histogram: foreign.histogram,
            stats: StoreStats::default(),
            levels: foreign.levels,
            sampling: foreign.sampling,
            notes: foreign.notes,
            counters,
        })
    }

    /// What was assumed or chosen to stream a foreign pyramid (empty for a Strata export).
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// Requests and bytes that crossed the wire so far (metadata included).
    pub fn transfer_counters(&self) -> Arc<TransferCounters> {
        self.counters.clone()
    }

    /// The brick's 36³ payload (x fastest): its core and apron, edge-replicated outside.
    /// Blocking (plain threads: `verify`, slice views, up-front loads).
    pub fn assemble_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        let region = BrickRegion::of(&self.header.layout, id, &self.display)?;
        self.assembler.note_read(id);
        let level = &self.levels[id.level as usize];
        let options = CodecOptions::default();
        macro_rules! read {
            ($t:ty) => {
                level
                    .array
                    .retrieve_array_subset_sharded_opt::<Vec<$t>>(
                        &level.cache,
                        &region.subset,
                        &options,
                    )
                    .map_err(|e| region.failed(e, &self.display))?
            };
        }
        let values = convert_samples!(&self.sampling, read);
        let payload = self.assembler.checked(id, region.gather(&values))?;
        for neighbour in self.assembler.unverified_neighbours(id) {
            let subset = core_subset(&self.header.layout, neighbour);
            macro_rules! read_core {
                ($t:ty) => {
                    level
                        .array
                        .retrieve_array_subset_sharded_opt::<Vec<$t>>(
                            &level.cache,
                            &subset,
                            &options,
                        )
                        .map_err(|e| region.failed(e, &self.display))?
                };
            }
            let core = convert_samples!(&self.sampling, read_core);
            self.assembler.check_neighbour(id, neighbour, &core)?;
        }
        Ok(payload)
    }

    /// Encoded bytes of the inner chunks the bricks read so far needed: each brick's own and its
    /// neighbours' (its apron's sources), each chunk counted once. The denominator of the
    /// bytes-fetched ratio; reads shard indices (already cached by the reads it accounts for).
    pub fn needed_chunk_bytes(&self) -> Result<u64> {
        let ids: Vec<BrickId> = self
            .assembler
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
        // zarrs' own `subchunk_byte_range` adds offset + size of an absent inner chunk
        // (u64::MAX twice): the shard indices are read here instead (from the range cache,
        // where the bricks' reads left them).
        let mut indices: std::collections::HashMap<(u8, [u64; 3]), Option<Vec<u64>>> =
            Default::default();
        let mut total = 0;
        for (level, z, y, x) in chunks {
            let array = &self.levels[level as usize].array;
            let layout = ShardLayout::of(array, &self.display)?;
            let chunk = [z, y, x];
            let shard = [0, 1, 2].map(|a| chunk[a] / layout.chunks_per_shard[a]);
            let index = match indices.get(&(level, shard)) {
                Some(index) => index.clone(),
                None => {
                    let index = self.read_shard_index(array, &layout, shard)?;
                    indices.insert((level, shard), index.clone());
                    index
                }
            };
            let Some(index) = index else { continue };
            let within = [0, 1, 2].map(|a| chunk[a] % layout.chunks_per_shard[a]);
            let n = layout.chunks_per_shard;
            let i = ((within[0] * n[1] + within[1]) * n[2] + within[2]) as usize;
            let (offset, size) = (index[2 * i], index[2 * i + 1]);
            if offset != u64::MAX || size != u64::MAX {
                total += size;
            }
        }
        Ok(total)
    }

    /// A shard's index (offset, size per inner chunk, C order); `None`: the shard is absent.
    fn read_shard_index(
        &self,
        array: &LevelArray,
        layout: &ShardLayout,
        shard: [u64; 3],
    ) -> Result<Option<Vec<u64>>> {
        use object_store::ObjectStoreExt;
        let key = array.chunk_key(&shard);
        let path = object_store::path::Path::from(key.as_str());
        let store = self.store.clone();
        let entries = layout.chunks_per_shard.iter().product::<u64>();
        let index_bytes = entries * 16;
        let display = self.display.clone();
        let bytes = crate::zarr_store::block_on(async move {
            let size = match store.head(&path).await {
                Ok(meta) => meta.size,
                Err(object_store::Error::NotFound { .. }) => return Ok(None),
                Err(e) => return Err(e),
            };
            // bytes codec + crc32c: the index, then its 4-byte checksum.
            let start = if layout.index_at_end {
                size.saturating_sub(index_bytes + 4)
            } else {
                0
            };
            store
                .get_range(&path, start..start + index_bytes)
                .await
                .map(Some)
        })?
        .map_err(|e| OmeZarrError::access(&display, format!("{key}: {e}")))?;
        Ok(bytes.map(|b| {
            b.chunks_exact(8)
                .map(|c| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                .collect()
        }))
    }

    /// Shard indices cached so far, over all levels (the blocking reader's and the request
    /// tasks').
    pub fn cached_shard_indices(&self) -> usize {
        let sync: usize = self.levels.iter().map(|l| l.cache.len()).sum();
        let tasks = crate::zarr_store::block_on(async {
            let mut n = 0;
            for level in &self.assembler.levels {
                n += level.cache.len().await;
            }
            n
        })
        .unwrap_or(0);
        sync + tasks
    }
}

/// A foreign pyramid, described for streaming.
struct Foreign {
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    levels: Vec<Level>,
    sampling: Sampling,
    notes: Vec<String>,
}

/// Header, skeleton (ranges unknown: full), empty histogram, the datasets taken as Strata's
/// levels and the value mapping of a foreign pyramid.
fn open_foreign(opened: &OpenedMultiscale) -> Result<Foreign> {
    let display = &opened.location.display;
    let array = open_level(opened, 0)?;
    let shape = array.shape().to_vec();
    let choice =
        crate::import::choose_axes(&opened.multiscale, &shape, &Default::default(), display)?;
    if shape.len() != 3 {
        return Err(import_instead(
            display,
            format!(
                "its arrays have {} axes ({}); streaming takes z, y, x arrays only (import picks a channel and a time point with --channel/--time)",
                shape.len(),
                opened
                    .multiscale
                    .axes
                    .iter()
                    .map(|a| a.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    let dims = strata_types::VolumeGeometry::checked_dims([shape[2], shape[1], shape[0]])
        .map_err(|e| OmeZarrError::invalid(display, e.to_string()))?;
    let dtype = data_type_name(&array);
    let (geometry, mut notes) =
        crate::import::foreign_geometry(&opened.multiscale, &choice, dims, display)?;
    // foreign_geometry's note on coarser levels is about import; streaming says its own below.
    notes.retain(|n| !n.contains("coarser levels in the source not read"));
    let layout = OctreeLayout::new(dims);

    // Strata's level L is the first dataset of its shape (level 0 is dataset 0).
    let mut arrays = vec![array];
    let mut taken = vec![0usize];
    let mut passed_over = Vec::new();
    let mut next_dataset = 1;
    for (level, d) in layout.level_dims.iter().enumerate().skip(1) {
        let expected = [d[2], d[1], d[0]].map(u64::from);
        let mut found = None;
        while next_dataset < opened.multiscale.datasets.len() {
            let candidate = open_level(opened, next_dataset)?;
            next_dataset += 1;
            if candidate.shape() == expected {
                found = Some(candidate);
                break;
            }
            passed_over.push(format!(
                "`{}` {:?}",
                opened.multiscale.datasets[next_dataset - 1].path,
                candidate.shape()
            ));
        }
        let Some(candidate) = found else {
            return Err(import_instead(
                display,
                format!(
                    "Strata's octree needs {} levels down to one 32³ brick, each the ceiling half of the one before; no dataset has level {level}'s shape {expected:?} (z, y, x){}",
                    layout.level_count(),
                    if passed_over.is_empty() {
                        String::new()
                    } else {
                        format!(" (passed over: {})", passed_over.join(", "))
                    }
                ),
            ));
        };
        let candidate_type = data_type_name(&candidate);
        if candidate_type != dtype {
            return Err(import_instead(
                display,
                format!(
                    "dataset `{}` holds {candidate_type} where level 0 holds {dtype}",
                    opened.multiscale.datasets[next_dataset - 1].path
                ),
            ));
        }
        arrays.push(candidate);
        taken.push(next_dataset - 1);
    }
    if opened.multiscale.datasets.len() > 1 {
        notes.push(format!(
            "datasets {} taken as Strata's levels 0..{}{}",
            taken
                .iter()
                .map(|&i| format!("`{}`", opened.multiscale.datasets[i].path))
                .collect::<Vec<_>>()
                .join(", "),
            layout.level_count() - 1,
            if passed_over.is_empty() {
                String::new()
            } else {
                format!(
                    "; passed over (not Strata's halving): {}",
                    passed_over.join(", ")
                )
            }
        ));
    }
    // Absent chunks are the fill value in a foreign pyramid, as Zarr has it; a whole level
    // without any is worth saying.
    notes.extend(
        taken
            .iter()
            .filter_map(|&i| crate::import::absent_level_note(opened, i)),
    );
    let levels: Vec<Level> = arrays
        .into_iter()
        .map(|array| {
            let cache = ArrayShardedReadableExtCache::new(&array);
            Level { array, cache }
        })
        .collect();

    // The value mapping, decided before any brick streams.
    let omero_range = opened.multiscale.channel_ranges.first().copied().flatten();
    let integer = matches!(dtype.as_str(), "int32" | "uint32");
    let quantizer = match dtype.as_str() {
        "float32" | "float64" | "int32" | "uint32" => {
            let [lo, hi] = match omero_range {
                Some(range) => {
                    notes.push(format!(
                        "{dtype} values scaled onto 16 bits over the omero window's data range [{}, {}]",
                        range[0], range[1]
                    ));
                    range
                }
                None => {
                    let range = coarsest_range(&levels, &dtype, display)?;
                    notes.push(format!(
                        "{dtype} values scaled onto 16 bits over the coarsest level's range [{}, {}] (no omero window): finer values outside it are clamped; `strata import` maps the exact range of level 0",
                        range[0], range[1]
                    ));
                    range
                }
            };
            Some(quantizer_for_range(lo, hi, integer))
        }
        _ => None,
    };
    let sampling = Sampling::of_data_type(&dtype, quantizer).ok_or_else(|| {
        import_instead(
            display,
            format!("its samples are {dtype}; streaming reads (u)int8/16/32 and float32/64"),
        )
    })?;
    let stored = sampling.stored();
    let max = stored.max_value();
    let (slope, intercept, source_sample_type, quantization_error) = match &sampling {
        Sampling::U8 => (1.0, 0.0, strata_storage::SampleType::U8, 0.0),
        Sampling::U16 => (1.0, 0.0, strata_storage::SampleType::U16, 0.0),
        Sampling::I8 => (1.0, -128.0, strata_storage::SampleType::I8, 0.0),
        Sampling::I16 => (1.0, -32768.0, strata_storage::SampleType::I16, 0.0),
        Sampling::Scaled { sample, quantizer } => {
            let (slope, intercept) = quantizer.physical_mapping(1.0, 0.0);
            let sample_type = match sample {
                ScaledSample::F32 => strata_storage::SampleType::F32,
                ScaledSample::F64 => strata_storage::SampleType::F64,
                ScaledSample::I32 => strata_storage::SampleType::I32,
                ScaledSample::U32 => strata_storage::SampleType::U32,
            };
            (slope, intercept, sample_type, quantizer.max_error_physical)
        }
    };
    // The data range (the transfer function's table spans it): the omero window's for
    // integers when given, else every stored value.
    let stored_range = match (&sampling, omero_range) {
        (Sampling::Scaled { quantizer, .. }, Some([lo, hi])) => {
            [quantizer.to_stored(lo), quantizer.to_stored(hi)]
        }
        (Sampling::Scaled { .. }, None) => [0, max],
        (_, Some([lo, hi])) => {
            let to_stored =
                |v: f64| ((v - intercept) / slope).round().clamp(0.0, f64::from(max)) as u16;
            [to_stored(lo), to_stored(hi)]
        }
        (_, None) => {
            if matches!(sampling, Sampling::I8 | Sampling::I16) {
                notes.push(format!(
                    "no omero window: the data range is taken as {dtype}'s full range"
                ));
            }
            [0, max]
        }
    };
    let skeleton = Skeleton::uniform(
        &layout,
        NodeInfo {
            min: 0,
            max,
            flags: 0,
        },
    );
    let header = StoreHeader {
        format_version: strata_storage::store::STORE_FORMAT_VERSION,
        geometry,
        stored,
        value_mapping: strata_storage::ValueMappingWithUnit {
            mapping: strata_storage::ValueMapping { slope, intercept },
            unit: String::new(),
        },
        source_sample_type,
        quantization_error,
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
        stored_range,
        generation: format!("ome-zarr:{display}"),
        // The records this source hands the loader (read_brick_record) use the default codec.
        codec: strata_storage::BrickCodec::default(),
        required_features: Vec::new(),
        labels: Vec::new(),
        frames: 1,
    };
    let histogram = Histogram::from_stored(
        &strata_storage::histogram::StoredValueCounts::default(),
        slope,
        intercept,
    );
    Ok(Foreign {
        header,
        skeleton,
        histogram,
        levels,
        sampling,
        notes,
    })
}

/// Finite min and max of the coarsest level (one brick: Strata's top level), as f64.
fn coarsest_range(levels: &[Level], dtype: &str, display: &str) -> Result<[f64; 2]> {
    let Some(level) = levels.last() else {
        return Err(OmeZarrError::invalid(display, "no levels"));
    };
    let subset = ArraySubset::new_with_shape(level.array.shape().to_vec());
    let fail = |e: zarrs::array::ArrayError| OmeZarrError::access(display, e);
    let values: Vec<f64> = match dtype {
        "float32" => level
            .array
            .retrieve_array_subset::<Vec<f32>>(&subset)
            .map_err(fail)?
            .into_iter()
            .map(f64::from)
            .collect(),
        "float64" => level
            .array
            .retrieve_array_subset::<Vec<f64>>(&subset)
            .map_err(fail)?,
        "int32" => level
            .array
            .retrieve_array_subset::<Vec<i32>>(&subset)
            .map_err(fail)?
            .into_iter()
            .map(f64::from)
            .collect(),
        _ => level
            .array
            .retrieve_array_subset::<Vec<u32>>(&subset)
            .map_err(fail)?
            .into_iter()
            .map(f64::from)
            .collect(),
    };
    let (lo, hi) = values
        .iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        return Err(import_instead(
            display,
            "its coarsest level holds no finite value to take a value range from",
        ));
    }
    Ok([lo, hi])
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
            self.sampling.stored() == StoredScalar::U8,
            self.header.codec,
        ))
    }
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        self.assemble_brick(id)
    }
    /// The source's own request path: one task per brick, aborted on the wire when stale.
    fn start_fetching(
        &self,
        options: FetchOptions,
    ) -> Option<Result<Box<dyn BrickFetcher>, SourceError>> {
        let runtime = match crate::zarr_store::runtime() {
            Ok(runtime) => runtime,
            Err(e) => {
                return Some(Err(SourceError::Unavailable {
                    location: self.display.clone(),
                    message: e.to_string(),
                }))
            }
        };
        let max_in_flight = options.max_in_transit.clamp(1, MAX_REQUESTS_IN_FLIGHT);
        let assembler = self.assembler.clone();
        let assemble: crate::fetcher::AssembleBrick = Arc::new(move |id| {
            let assembler = assembler.clone();
            Box::pin(async move { assembler.assemble(id).await })
        });
        Some(Ok(Box::new(crate::fetcher::start_fetcher(
            runtime,
            assemble,
            self.assembler.bytes_per_sample(),
            options.max_queued.max(1),
            max_in_flight,
        ))))
    }
}

/// Bricks assembled at once by the source's own request path (each a few ranged GETs; they
/// share object_store's connection pool).
pub const MAX_REQUESTS_IN_FLIGHT: usize = 64;

/// Opens `spec` as a streamed OME-Zarr source.
pub fn open_source(spec: &str, options: &crate::ObjectStoreOptions) -> Result<Arc<OmeZarrSource>> {
    Ok(Arc::new(OmeZarrSource::open(ObjectLocation::open(
        spec, options, false,
    )?)?))
}
