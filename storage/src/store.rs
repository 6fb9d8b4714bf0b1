//! The store: one directory holding a marker file and a sled database with three trees.
//!
//! - `meta`: `header` (JSON [`StoreHeader`]), `skeleton` (binary, checksummed: per-node min, max,
//!   flags of every level, loaded in one read), `histogram` (JSON), `stats` (JSON) and, written
//!   last, `complete`. A store without `complete` is an interrupted import and refuses to open.
//! - `bricks`: key [`brick_key`], value an encoded brick ([`crate::brick`]).
//!
//! Creating a store over an existing one deletes it first, so a second import starts clean; a
//! directory that is not a store is never deleted.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
pub use strata_types::ValueMapping;
use xxhash_rust::xxh3::xxh3_64;

use crate::brick::{brick_key, decode_brick, BrickDecodeError};
use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::histogram::Histogram;
use crate::octree::{BrickId, OctreeLayout};
use crate::source::{SampleType, WindowPreset};

pub use crate::quantize::StoredScalar;

pub const STORE_FORMAT_VERSION: u32 = 1;
const MARKER_FILE: &str = "STRATA-STORE";
const DB_DIR: &str = "db";
const KEY_HEADER: &[u8] = b"header";
const KEY_SKELETON: &[u8] = b"skeleton";
const KEY_HISTOGRAM: &[u8] = b"histogram";
const KEY_STATS: &[u8] = b"stats";
const KEY_COMPLETE: &[u8] = b"complete";
/// sled's page cache when reading; counted by the loader in its CPU budget.
pub const DEFAULT_READ_CACHE_BYTES: u64 = 64 << 20;

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

/// A fresh 128-bit generation id (hex): time, process and a per-process random hasher key,
/// so two imports of the same name (even in the same second) never share one.
pub fn new_generation_id() -> String {
    use std::hash::{BuildHasher, Hasher};
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let mut hi = std::collections::hash_map::RandomState::new().build_hasher();
    hi.write_u128(now);
    hi.write_u32(std::process::id());
    let mut lo = std::collections::hash_map::RandomState::new().build_hasher();
    lo.write_u64(hi.finish());
    lo.write_u128(now);
    format!("{:016x}{:016x}", hi.finish(), lo.finish())
}

/// Per-node range and flags, kept for the whole octree in memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct NodeInfo {
    pub min: u16,
    pub max: u16,
    pub flags: u8,
}

impl NodeInfo {
    pub const CONSTANT: u8 = 1;
    pub fn is_constant(&self) -> bool {
        self.flags & Self::CONSTANT != 0
    }
}

/// Every node's [`NodeInfo`], level by level in the layout's brick order.
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton {
    pub levels: Vec<Vec<NodeInfo>>,
}

impl Skeleton {
    pub fn new(layout: &OctreeLayout) -> Self {
        Skeleton {
            levels: (0..layout.level_count())
                .map(|l| vec![NodeInfo::default(); layout.brick_count_in_level(l) as usize])
                .collect(),
        }
    }

    /// The skeleton as stored (and served): levels, per node min/max/flags, an xxh3 checksum.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&(self.levels.len() as u32).to_le_bytes());
        for level in &self.levels {
            out.extend_from_slice(&(level.len() as u64).to_le_bytes());
            for n in level {
                out.extend_from_slice(&n.min.to_le_bytes());
                out.extend_from_slice(&n.max.to_le_bytes());
                out.push(n.flags);
            }
        }
        let sum = xxh3_64(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Parses [`Skeleton::encode`]'s bytes; `None` when the checksum or the framing is wrong.
    pub fn decode(bytes: &[u8]) -> Option<Skeleton> {
        let (body, sum) = bytes.split_at(bytes.len().checked_sub(8)?);
        if xxh3_64(body) != u64::from_le_bytes(sum.try_into().ok()?) {
            return None;
        }
        let mut pos = 0usize;
        let mut take = |n: usize| -> Option<&[u8]> {
            let s = body.get(pos..pos + n)?;
            pos += n;
            Some(s)
        };
        let level_count = u32::from_le_bytes(take(4)?.try_into().ok()?) as usize;
        let mut levels = Vec::with_capacity(level_count.min(64));
        for _ in 0..level_count {
            let n = u64::from_le_bytes(take(8)?.try_into().ok()?) as usize;
            let raw = take(n.checked_mul(5)?)?;
            levels.push(
                raw.chunks_exact(5)
                    .map(|c| NodeInfo {
                        min: u16::from_le_bytes([c[0], c[1]]),
                        max: u16::from_le_bytes([c[2], c[3]]),
                        flags: c[4],
                    })
                    .collect(),
            );
        }
        Some(Skeleton { levels })
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

fn db_error(path: &Path) -> impl Fn(sled::Error) -> StorageError + '_ {
    move |e| StorageError::db(path, e)
}

/// A complete, read-only store.
pub struct Store {
    path: PathBuf,
    db: sled::Db,
    bricks: sled::Tree,
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    stats: StoreStats,
}

impl Store {
    pub fn open(path: &Path) -> Result<Store> {
        Self::open_with_cache(path, DEFAULT_READ_CACHE_BYTES)
    }

    /// Opens with an explicit sled page-cache size (part of the caller's memory budget).
    pub fn open_with_cache(path: &Path, sled_cache_bytes: u64) -> Result<Store> {
        if !path.exists() {
            return Err(StorageError::invalid(path, "store does not exist"));
        }
        if !path.join(MARKER_FILE).is_file() {
            return Err(StorageError::NotAStore {
                path: path.to_path_buf(),
                message: format!("no {MARKER_FILE} marker"),
            });
        }
        let db = open_db_when_unlocked(
            sled::Config::new()
                .path(path.join(DB_DIR))
                .cache_capacity(sled_cache_bytes),
        )
        .map_err(db_error(path))?;
        let meta = db.open_tree("meta").map_err(db_error(path))?;
        if meta.get(KEY_COMPLETE).map_err(db_error(path))?.is_none() {
            return Err(StorageError::IncompleteImport {
                path: path.to_path_buf(),
            });
        }
        let get = |key: &[u8]| -> Result<sled::IVec> {
            meta.get(key).map_err(db_error(path))?.ok_or_else(|| {
                StorageError::corrupted(path, format!("missing {}", String::from_utf8_lossy(key)))
            })
        };
        let json = |key: &[u8]| -> Result<sled::IVec> { get(key) };
        let header: StoreHeader = serde_json::from_slice(&json(KEY_HEADER)?)
            .map_err(|e| StorageError::corrupted(path, format!("header: {e}")))?;
        if header.format_version != STORE_FORMAT_VERSION {
            return Err(StorageError::unsupported(
                path,
                format!("store format version {}", header.format_version),
            ));
        }
        let skeleton = Skeleton::decode(&get(KEY_SKELETON)?)
            .ok_or_else(|| StorageError::corrupted(path, "octree skeleton fails its checksum"))?;
        if skeleton.levels.len() != header.layout.level_count()
            || skeleton
                .levels
                .iter()
                .enumerate()
                .any(|(l, v)| v.len() as u64 != header.layout.brick_count_in_level(l))
        {
            return Err(StorageError::corrupted(
                path,
                "octree skeleton does not match the header's layout",
            ));
        }
        let histogram: Histogram = serde_json::from_slice(&json(KEY_HISTOGRAM)?)
            .map_err(|e| StorageError::corrupted(path, format!("histogram: {e}")))?;
        let stats: StoreStats = serde_json::from_slice(&json(KEY_STATS)?)
            .map_err(|e| StorageError::corrupted(path, format!("stats: {e}")))?;
        let bricks = db.open_tree("bricks").map_err(db_error(path))?;
        Ok(Store {
            path: path.to_path_buf(),
            db,
            bricks,
            header,
            skeleton,
            histogram,
            stats,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
    pub fn header(&self) -> &StoreHeader {
        &self.header
    }
    pub fn layout(&self) -> &OctreeLayout {
        &self.header.layout
    }
    pub fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }
    pub fn histogram(&self) -> &Histogram {
        &self.histogram
    }
    pub fn stats(&self) -> &StoreStats {
        &self.stats
    }

    pub fn node(&self, id: BrickId) -> Option<NodeInfo> {
        let i = self.header.layout.index_in_level(id)?;
        Some(self.skeleton.levels[id.level as usize][i])
    }

    /// Reads, verifies and decompresses one brick: 36³ stored values, x fastest.
    pub fn read_brick(&self, id: BrickId) -> Result<Vec<u16>> {
        if !self.header.layout.contains(id) {
            return Err(StorageError::invalid(
                &self.path,
                format!("brick {id:?} is outside the octree"),
            ));
        }
        let record = self
            .bricks
            .get(brick_key(id))
            .map_err(db_error(&self.path))?
            .ok_or_else(|| {
                StorageError::corrupted(&self.path, format!("brick {id:?} is missing"))
            })?;
        decode_brick(id, &record).map_err(|e| brick_error(&self.path, id, e))
    }

    /// One brick's record exactly as stored (kind, checksum, compressed body): what the data
    /// service sends, so nothing is decoded or re-encoded on the way. Not verified here.
    pub fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>> {
        if !self.header.layout.contains(id) {
            return Err(StorageError::invalid(
                &self.path,
                format!("brick {id:?} is outside the octree"),
            ));
        }
        Ok(self
            .bricks
            .get(brick_key(id))
            .map_err(db_error(&self.path))?
            .ok_or_else(|| StorageError::corrupted(&self.path, format!("brick {id:?} is missing")))?
            .to_vec())
    }

    /// Size of the stored record of a brick (compressed), for I/O accounting.
    pub fn stored_brick_bytes(&self, id: BrickId) -> Result<u64> {
        Ok(self
            .bricks
            .get(brick_key(id))
            .map_err(db_error(&self.path))?
            .map_or(0, |r| r.len() as u64))
    }

    /// Checks every brick: present, checksum, decompression, and range equal to the skeleton's.
    /// Returns one message per problem found (empty when the store is sound).
    pub fn verify(&self, mut on_progress: impl FnMut(u64, u64)) -> Result<Vec<String>> {
        let mut problems = Vec::new();
        let total = self.header.layout.total_bricks();
        let mut seen = 0u64;
        for level in 0..self.header.layout.level_count() {
            let n = self.header.layout.bricks_in_level(level);
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let id = BrickId::new(level as u8, [x, y, z]);
                        seen += 1;
                        match self.read_brick(id) {
                            Err(e) => problems.push(e.to_string()),
                            Ok(voxels) => {
                                let r = crate::brick::value_range(&voxels);
                                let node = self.node(id).unwrap_or_default();
                                if (r.min, r.max) != (node.min, node.max) {
                                    problems.push(format!(
                                        "{}: brick {id:?} range {}..{} differs from the skeleton's {}..{}",
                                        self.path.display(), r.min, r.max, node.min, node.max
                                    ));
                                }
                            }
                        }
                    }
                }
                on_progress(seen, total);
            }
        }
        let stored = self.bricks.len() as u64;
        if stored != total {
            problems.push(format!(
                "{}: {stored} brick records for {total} octree nodes",
                self.path.display()
            ));
        }
        Ok(problems)
    }

    /// Overwrites one byte of a stored brick record. Only for tests of corruption handling.
    #[doc(hidden)]
    pub fn corrupt_brick_for_tests(path: &Path, id: BrickId, byte: usize) -> Result<()> {
        let db = open_db_when_unlocked(sled::Config::new().path(path.join(DB_DIR)))
            .map_err(db_error(path))?;
        let bricks = db.open_tree("bricks").map_err(db_error(path))?;
        let mut record = bricks
            .get(brick_key(id))
            .map_err(db_error(path))?
            .ok_or_else(|| StorageError::corrupted(path, "no such brick"))?
            .to_vec();
        let at = byte.min(record.len() - 1);
        record[at] ^= 0x01;
        bricks
            .insert(brick_key(id), record)
            .map_err(db_error(path))?;
        db.flush().map_err(db_error(path))?;
        Ok(())
    }

    pub fn close(self) -> Result<()> {
        self.db.flush().map_err(db_error(&self.path))?;
        Ok(())
    }
}

/// sled releases its file lock from background threads a moment after the last handle drops, so
/// opening a store right after writing it can briefly find it locked. Retry for a short while
/// instead of failing; a store held by another live process still fails after the wait.
fn open_db_when_unlocked(config: sled::Config) -> sled::Result<sled::Db> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(3);
    loop {
        match config.open() {
            Err(sled::Error::Io(e))
                if e.to_string().contains("acquire lock")
                    && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            other => return other,
        }
    }
}

fn brick_error(path: &Path, id: BrickId, e: BrickDecodeError) -> StorageError {
    StorageError::corrupted(
        path,
        format!("brick level {} at {:?}: {e}", id.level, id.coords),
    )
}

/// Writes a new store. Nothing it writes is visible as complete until [`StoreWriter::finish`].
pub struct StoreWriter {
    path: PathBuf,
    db: sled::Db,
    bricks: sled::Tree,
}

impl StoreWriter {
    /// Prepares `path` for a fresh import: deletes a previous store there (complete or not),
    /// refuses to touch a non-empty directory or file that is not a store.
    pub fn create(path: &Path, sled_cache_bytes: u64) -> Result<StoreWriter> {
        if path.exists() {
            let is_store = path.join(MARKER_FILE).is_file();
            let is_empty_dir = path.is_dir()
                && std::fs::read_dir(path)
                    .map_err(|e| StorageError::io(path, e))?
                    .next()
                    .is_none();
            if is_store {
                std::fs::remove_dir_all(path).map_err(|e| StorageError::io(path, e))?;
            } else if !is_empty_dir {
                return Err(StorageError::NotAStore {
                    path: path.to_path_buf(),
                    message: "refusing to overwrite a file or non-empty directory that is not a Strata store".into(),
                });
            }
        }
        std::fs::create_dir_all(path).map_err(|e| StorageError::io(path, e))?;
        std::fs::write(
            path.join(MARKER_FILE),
            format!("strata store format {STORE_FORMAT_VERSION}\n"),
        )
        .map_err(|e| StorageError::io(path.join(MARKER_FILE), e))?;
        let db = open_db_when_unlocked(
            sled::Config::new()
                .path(path.join(DB_DIR))
                .cache_capacity(sled_cache_bytes)
                .mode(sled::Mode::HighThroughput),
        )
        .map_err(db_error(path))?;
        let bricks = db.open_tree("bricks").map_err(db_error(path))?;
        Ok(StoreWriter {
            path: path.to_path_buf(),
            db,
            bricks,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes bricks in one sled batch (give them in key order).
    pub fn put_bricks(&self, records: Vec<(BrickId, Vec<u8>)>) -> Result<()> {
        let mut batch = sled::Batch::default();
        for (id, record) in records {
            batch.insert(&brick_key(id)[..], record);
        }
        self.bricks
            .apply_batch(batch)
            .map_err(db_error(&self.path))?;
        Ok(())
    }

    /// Writes the metadata, flushes everything, then marks the store complete and flushes again:
    /// a crash at any point before the last flush leaves a store that opens as incomplete.
    pub fn finish(
        self,
        header: &StoreHeader,
        skeleton: &Skeleton,
        histogram: &Histogram,
        stats: &StoreStats,
    ) -> Result<()> {
        let path = &self.path;
        let meta = self.db.open_tree("meta").map_err(db_error(path))?;
        let to_json = |v: &dyn erased::Json| {
            v.json()
                .map_err(|e| StorageError::corrupted(path, e.to_string()))
        };
        meta.insert(KEY_HEADER, to_json(header)?)
            .map_err(db_error(path))?;
        meta.insert(KEY_SKELETON, skeleton.encode())
            .map_err(db_error(path))?;
        meta.insert(KEY_HISTOGRAM, to_json(histogram)?)
            .map_err(db_error(path))?;
        meta.insert(KEY_STATS, to_json(stats)?)
            .map_err(db_error(path))?;
        self.db.flush().map_err(db_error(path))?;
        meta.insert(KEY_COMPLETE, &b"1"[..])
            .map_err(db_error(path))?;
        self.db.flush().map_err(db_error(path))?;
        Ok(())
    }
}

/// Lets `finish` serialise its differently typed parts through one closure.
mod erased {
    pub trait Json {
        fn json(&self) -> serde_json::Result<Vec<u8>>;
    }
    impl<T: serde::Serialize> Json for T {
        fn json(&self) -> serde_json::Result<Vec<u8>> {
            serde_json::to_vec(self)
        }
    }
}
