//! Store → OME-Zarr 0.5: each octree level, apron stripped, as a sharded Zarr v3 array.
//!
//! Arrays `0..N` (finest first), axes z, y, x, shape = the level's voxels. Shards of up to 256³
//! hold 32³ inner chunks (the bricks' cores, so chunk c of level L is brick c of level L),
//! zstd-compressed, with a crc32c-checked index at the shard's end. A shard whose bricks all
//! hold the fill value (read from the skeleton, without touching the bricks) is not written,
//! and zarrs leaves fill-valued inner chunks out of the shards it writes. Each varying
//! brick's core checksum goes to `strata-checksums.bin` ([`crate::checksums`]), so that import
//! and streaming tell a damaged or missing chunk from the fill value.
//!
//! Memory is bounded by one shard (256³ samples) plus its bricks in flight. The export is
//! cleanly restartable: a marker object is written first and removed last, after the group's
//! zarr.json; an interrupted export has no multiscales (no reader takes it for an image) and
//! exporting again to the same place clears it first.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use rayon::prelude::*;
use strata_source::VolumeSource;
use strata_storage::store::Provenance;
use strata_storage::StoredScalar;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
use zarrs::array::{codec, data_type, Array, ArrayBuilder};
use zarrs::storage::{
    ListableStorageTraits, ReadableStorageTraits, ReadableWritableListableStorage,
    ReadableWritableListableStorageTraits, StorePrefix, WritableStorageTraits,
};

use crate::metadata::{
    group_attributes, StrataAttributes, CHECKSUMS_KEY, SKELETON_KEY, STRATA_ATTRIBUTE_VERSION,
};
use crate::zarr_store::zarr_storage;
use crate::{ObjectLocation, OmeZarrError, Result};

/// Inner chunk edge: one brick core.
pub const INNER_CHUNK: u64 = BRICK_CORE as u64;
/// Largest shard edge (256³ u16 = 32 MiB per shard, 512 inner chunks).
pub const MAX_SHARD: u64 = 256;
/// Marks an export in progress (written first, removed last).
pub const IN_PROGRESS_KEY: &str = "strata-export-in-progress";
/// zstd level of the inner chunks: fast, and within a few percent of level 9 on CT.
const ZSTD_LEVEL: i32 = 3;

#[derive(Clone, Debug, Default)]
pub struct ExportOptions<'a> {
    /// Keep the store's description and provenance (input paths) in the `strata` attribute.
    pub expose_identifiers: bool,
    pub cancel: Option<&'a AtomicBool>,
    /// Name of the multiscale (default: "strata").
    pub name: Option<String>,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExportReport {
    pub levels: usize,
    /// Shards written (objects holding voxels).
    pub shards_written: u64,
    /// Shards left out because they held only the fill value.
    pub shards_skipped: u64,
    /// Bytes of voxel objects written (shards), and of metadata.
    pub shard_bytes: u64,
    pub metadata_bytes: u64,
    /// Level-0 voxel bytes (uncompressed), for throughput.
    pub level0_bytes: u64,
}

/// The shard edge for a level: the level's extent rounded up to whole inner chunks, at most
/// [`MAX_SHARD`] (a small level is one tight shard, not a mostly-empty 256³ one).
pub fn shard_shape(level_dims_zyx: [u64; 3]) -> [u64; 3] {
    level_dims_zyx.map(|d| {
        d.div_ceil(INNER_CHUNK)
            .max(1)
            .saturating_mul(INNER_CHUNK)
            .min(MAX_SHARD)
    })
}

/// Exports `source` (a local store, or any volume source) to `dest`. `on_progress(done, total)`
/// counts shards over all levels.
pub fn export(
    source: &dyn VolumeSource,
    dest: &ObjectLocation,
    options: &ExportOptions,
    on_progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<ExportReport> {
    let storage = zarr_storage(dest)?;
    prepare_destination(&storage, dest)?;
    let header = source.header().clone();
    let layout = header.layout.clone();
    let narrow = header.stored == StoredScalar::U8;
    let fill = header.stored_range[0];
    let mut report = ExportReport {
        levels: layout.level_count(),
        level0_bytes: header.geometry.voxel_count() * if narrow { 1 } else { 2 },
        ..ExportReport::default()
    };
    let shards_per_level: Vec<[u64; 3]> = layout
        .level_dims
        .iter()
        .map(|d| {
            let zyx = [d[2], d[1], d[0]].map(u64::from);
            let s = shard_shape(zyx);
            [0, 1, 2].map(|a| zyx[a].div_ceil(s[a]))
        })
        .collect();
    let total: u64 = shards_per_level
        .iter()
        .map(|n| n.iter().product::<u64>())
        .sum();
    let mut done = 0u64;
    // Each varying brick's core checksum, as the shards hold it (see `crate::checksums`).
    let checksums = std::sync::Mutex::new(Vec::new());
    on_progress(0, total);
    for (level, (d, &n)) in layout.level_dims.iter().zip(&shards_per_level).enumerate() {
        let zyx = [d[2], d[1], d[0]].map(u64::from);
        let shard = shard_shape(zyx);
        let array = create_level_array(&storage, level, zyx, shard, narrow, fill)
            .map_err(|e| OmeZarrError::access(&dest.display, format!("level {level}: {e}")))?;
        for sz in 0..n[0] {
            for sy in 0..n[1] {
                for sx in 0..n[2] {
                    if options.cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
                        return Err(OmeZarrError::Cancelled);
                    }
                    let written = export_shard(
                        source,
                        &array,
                        level as u8,
                        [sz, sy, sx],
                        shard,
                        zyx,
                        fill,
                        narrow,
                        &checksums,
                    )
                    .map_err(|e| match e {
                        OmeZarrError::Access { message, .. } => OmeZarrError::access(
                            &dest.display,
                            format!("level {level} shard {:?}: {message}", [sz, sy, sx]),
                        ),
                        other => other,
                    })?;
                    if written {
                        report.shards_written += 1;
                    } else {
                        report.shards_skipped += 1;
                    }
                    done += 1;
                    on_progress(done, total);
                }
            }
        }
    }
    // Sizes of what was written (listing the destination is cheaper than tracking encodings).
    let sizes = crate::zarr_store::block_on(list_sizes(dest))??;
    for (key, size) in &sizes {
        if key.ends_with("zarr.json") {
            report.metadata_bytes += size;
        } else {
            report.shard_bytes += size;
        }
    }
    // Metadata last: the skeleton, then the group (which makes it an image), then the marker.
    let skeleton = source.skeleton().encode();
    let put = |key: &str, bytes: Vec<u8>| {
        let key = zarrs::storage::StoreKey::new(key)
            .map_err(|e| OmeZarrError::access(&dest.display, e))?;
        storage
            .set(&key, bytes.into())
            .map_err(|e| OmeZarrError::access(&dest.display, e))
    };
    let mut checksums = checksums.into_inner().unwrap_or_else(|p| p.into_inner());
    checksums.sort_unstable_by_key(|(id, _)| (id.level, id.coords[2], id.coords[1], id.coords[0]));
    let checksums = crate::checksums::encode(&checksums);
    report.metadata_bytes += skeleton.len() as u64 + checksums.len() as u64;
    put(CHECKSUMS_KEY, checksums)?;
    put(SKELETON_KEY, skeleton)?;
    let mut exposed = header.clone();
    if !options.expose_identifiers {
        exposed.description = String::new();
        exposed.provenance = Provenance {
            inputs: Vec::new(),
            source_format: header.provenance.source_format.clone(),
            imported_at_unix_seconds: 0,
            tool_version: header.provenance.tool_version.clone(),
        };
    }
    let strata = StrataAttributes {
        version: STRATA_ATTRIBUTE_VERSION,
        header: exposed,
        histogram: source.histogram().clone(),
        stats: source.stats().clone(),
        skeleton: SKELETON_KEY.into(),
        checksums: Some(CHECKSUMS_KEY.into()),
    };
    let name = options.name.clone().unwrap_or_else(|| "strata".into());
    let mut group = zarrs::group::GroupBuilder::new()
        .build(storage.clone(), "/")
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    *group.attributes_mut() = group_attributes(&name, &strata)?;
    group
        .store_metadata()
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    let marker = zarrs::storage::StoreKey::new(IN_PROGRESS_KEY)
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    storage
        .erase(&marker)
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    Ok(report)
}

async fn list_sizes(dest: &ObjectLocation) -> Result<Vec<(String, u64)>> {
    use futures::TryStreamExt;
    let objects: Vec<object_store::ObjectMeta> = dest
        .store
        .list(None)
        .try_collect()
        .await
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    Ok(objects
        .into_iter()
        .map(|o| (o.location.to_string(), o.size))
        .collect())
}

/// Refuses a destination holding something other than a Strata export; clears a previous or
/// interrupted export; writes the in-progress marker.
fn prepare_destination(
    storage: &ReadableWritableListableStorage,
    dest: &ObjectLocation,
) -> Result<()> {
    let keys = storage
        .list()
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    if !keys.is_empty() {
        let ours = keys.iter().any(|k| k.as_str() == IN_PROGRESS_KEY)
            || storage
                .get(
                    &zarrs::storage::StoreKey::new("zarr.json")
                        .map_err(|e| OmeZarrError::access(&dest.display, e))?,
                )
                .ok()
                .flatten()
                .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
                .is_some_and(|doc| doc.pointer("/attributes/strata").is_some());
        if !ours {
            return Err(OmeZarrError::invalid(
                &dest.display,
                format!(
                    "the destination holds {} objects that are not a Strata export; choose an empty destination",
                    keys.len()
                ),
            ));
        }
        storage
            .erase_prefix(&StorePrefix::root())
            .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    }
    let marker = zarrs::storage::StoreKey::new(IN_PROGRESS_KEY)
        .map_err(|e| OmeZarrError::access(&dest.display, e))?;
    storage
        .set(&marker, b"export in progress\n".to_vec().into())
        .map_err(|e| OmeZarrError::access(&dest.display, e))
}

fn create_level_array(
    storage: &ReadableWritableListableStorage,
    level: usize,
    shape_zyx: [u64; 3],
    shard_zyx: [u64; 3],
    narrow: bool,
    fill: u16,
) -> std::result::Result<Array<dyn ReadableWritableListableStorageTraits>, LevelArrayError> {
    let mut builder = if narrow {
        ArrayBuilder::new(
            shape_zyx.to_vec(),
            shard_zyx.to_vec(),
            data_type::uint8(),
            fill as u8,
        )
    } else {
        ArrayBuilder::new(
            shape_zyx.to_vec(),
            shard_zyx.to_vec(),
            data_type::uint16(),
            fill,
        )
    };
    builder
        .subchunk_shape(vec![INNER_CHUNK; 3])
        .bytes_to_bytes_codecs(vec![Arc::new(codec::ZstdCodec::new(ZSTD_LEVEL, false))])
        .dimension_names(Some(["z", "y", "x"]));
    let array = builder.build(storage.clone(), &format!("/{level}"))?;
    array.store_metadata()?;
    Ok(array)
}

/// Why a level's array could not be created; the caller names the export and the level.
#[derive(Debug, thiserror::Error)]
enum LevelArrayError {
    #[error(transparent)]
    Create(#[from] zarrs::array::ArrayCreateError),
    #[error(transparent)]
    Metadata(#[from] zarrs::storage::StorageError),
}

/// Cuts one shard out of the level's bricks and stores it. Returns whether it was written.
#[allow(clippy::too_many_arguments)]
fn export_shard(
    source: &dyn VolumeSource,
    array: &Array<dyn ReadableWritableListableStorageTraits>,
    level: u8,
    shard_index: [u64; 3],
    shard: [u64; 3],
    level_zyx: [u64; 3],
    fill: u16,
    narrow: bool,
    checksums: &std::sync::Mutex<Vec<(BrickId, u32)>>,
) -> Result<bool> {
    let core = INNER_CHUNK;
    let start = [0, 1, 2].map(|a| shard_index[a] * shard[a]);
    let end = [0, 1, 2].map(|a| (start[a] + shard[a]).min(level_zyx[a]));
    // Bricks (x, y, z) of this shard.
    let brick_lo = [start[2] / core, start[1] / core, start[0] / core];
    let brick_hi = [
        end[2].div_ceil(core),
        end[1].div_ceil(core),
        end[0].div_ceil(core),
    ];
    let mut bricks = Vec::new();
    for bz in brick_lo[2]..brick_hi[2] {
        for by in brick_lo[1]..brick_hi[1] {
            for bx in brick_lo[0]..brick_hi[0] {
                bricks.push(BrickId::new(level, [bx as u32, by as u32, bz as u32]));
            }
        }
    }
    let all_fill = bricks.iter().all(|&id| {
        source
            .node(id)
            .is_some_and(|n| n.min == fill && n.max == fill)
    });
    if all_fill {
        return Ok(false);
    }
    let [sz, sy, sx] = shard.map(|s| s as usize);
    let mut voxels = vec![fill; sz * sy * sx];
    // One z-row of bricks fills a contiguous slab of 32 shard slices: slabs in parallel.
    let slab_len = core as usize * sy * sx;
    voxels
        .par_chunks_mut(slab_len)
        .enumerate()
        .try_for_each(|(slab, out)| -> Result<()> {
            let bz = brick_lo[2] + slab as u64;
            if bz >= brick_hi[2] {
                return Ok(());
            }
            for by in brick_lo[1]..brick_hi[1] {
                for bx in brick_lo[0]..brick_hi[0] {
                    let id = BrickId::new(level, [bx as u32, by as u32, bz as u32]);
                    let node = source.node(id);
                    if node.is_some_and(|n| n.min == fill && n.max == fill) {
                        continue;
                    }
                    let payload: Vec<u16> = match node {
                        Some(n) if n.min == n.max => vec![n.min; BRICK_PAYLOAD.pow(3) as usize],
                        _ => {
                            let payload = source
                                .read_brick(id)
                                .map_err(|e| OmeZarrError::access(source.location(), e))?;
                            let digest = crate::checksums::core_digest(
                                &payload,
                                id,
                                &source.header().layout,
                                narrow,
                            );
                            checksums
                                .lock()
                                .unwrap_or_else(|p| p.into_inner())
                                .push((id, digest.crc));
                            payload
                        }
                    };
                    copy_core(&payload, out, [bx, by, bz], start, end, [sy, sx]);
                }
            }
            Ok(())
        })?;
    let indices = shard_index.to_vec();
    let stored = if narrow {
        let bytes: Vec<u8> = voxels.iter().map(|&v| v as u8).collect();
        array.store_chunk(&indices, bytes)
    } else {
        array.store_chunk(&indices, voxels)
    };
    stored.map_err(|e| OmeZarrError::access("", e))?;
    Ok(true)
}

/// Copies a brick's core (clipped to the level) into its place in a slab of 32 shard slices.
fn copy_core(
    payload: &[u16],
    slab: &mut [u16],
    brick: [u64; 3],
    shard_start_zyx: [u64; 3],
    level_end_zyx: [u64; 3],
    [sy, sx]: [usize; 2],
) {
    let core = INNER_CHUNK;
    let p = BRICK_PAYLOAD as usize;
    let a = BRICK_APRON as usize;
    let [bx, by, bz] = brick;
    let nx = (level_end_zyx[2] - bx * core).min(core) as usize;
    let ny = (level_end_zyx[1] - by * core).min(core) as usize;
    let nz = (level_end_zyx[0] - bz * core).min(core) as usize;
    let ox = (bx * core - shard_start_zyx[2]) as usize;
    let oy = (by * core - shard_start_zyx[1]) as usize;
    for z in 0..nz {
        for y in 0..ny {
            let src = ((z + a) * p + (y + a)) * p + a;
            let dst = (z * sy + oy + y) * sx + ox;
            slab[dst..dst + nx].copy_from_slice(&payload[src..src + nx]);
        }
    }
}
