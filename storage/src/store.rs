//! The store: one directory holding a marker file and a sled database with three trees.
//!
//! - `meta`: `header` (JSON [`StoreHeader`]), `skeleton` (binary, checksummed: per-node min, max,
//!   flags of every level, loaded in one read), `histogram` (JSON), `stats` (JSON) and, written
//!   last, `complete`. A store without `complete` is an interrupted import and refuses to open.
//! - `bricks`: key [`brick_key`], value an encoded brick ([`crate::brick`]).
//!
//! Creating a store over an existing one deletes it first, so a second import starts clean; a
//! directory that is not a store is never deleted.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use std::time::Duration;

use crate::brick::{brick_id_from_key, brick_key, decode_brick, BrickDecodeError};
use crate::contained_db::{contained, SledHandles};
use crate::error::{Result, StorageError};
use crate::histogram::Histogram;
use crate::lock::{LockPurpose, SharedStoreLock, StoreLock, LOCK_FILE};
use crate::octree::{BrickId, OctreeLayout};
pub use crate::packs::MappedRecord;
use crate::packs::{PackWriter, Packs, INDEX_FILE};

// The document types live in `crate::header` (pure, also built for a remote viewer); their
// paths under `store` stay as they were.
#[doc(hidden)]
pub use crate::header::check_format_knowing;
pub use crate::header::{
    rebuild_command, BrickCodec, NodeInfo, Provenance, Skeleton, StoreHeader, StoreStats,
    StoredScalar, ValueMapping, ValueMappingWithUnit, FEATURE_FRAMES, FEATURE_SPARSE_SKELETON,
    KNOWN_STORE_FEATURES, OLDEST_READABLE_FORMAT_VERSION, STORE_FORMAT_VERSION,
};

const MARKER_FILE: &str = "STRATA-STORE";
/// The marker file's line that [`StoreWriter::finish`] adds last.
const MARKER_COMPLETE_LINE: &str = "complete";
const DB_DIR: &str = "db";
const KEY_HEADER: &[u8] = b"header";
const KEY_SKELETON: &[u8] = b"skeleton";
const KEY_HISTOGRAM: &[u8] = b"histogram";
const KEY_STATS: &[u8] = b"stats";
const KEY_COMPLETE: &[u8] = b"complete";
/// sled's page cache when reading; counted by the loader in its CPU budget.
pub const DEFAULT_READ_CACHE_BYTES: u64 = 64 << 20;

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

/// How long an explicit flush may take before it is called a failure (a full disk makes sled
/// wait forever; a healthy disk writes sled's whole cache in far less).
const FLUSH_LIMIT: Duration = Duration::from_secs(60);

/// A complete, read-only store.
pub struct Store {
    path: PathBuf,
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    stats: StoreStats,
    /// Frames 1.. of a 4-D store: each one's skeleton (frame 0's is above).
    later_skeletons: Vec<Skeleton>,
    backend: Backend,
}

/// Where the records are: sled (formats 1 and 2) or pack files (format 3).
enum Backend {
    Sled {
        bricks: sled::Tree,
        /// Frames 1..: each one's bricks tree.
        later_trees: Vec<sled::Tree>,
        // Dropped after the trees above: the database closes (bounded), then the lock goes.
        db: SledHandles,
        lock: StoreLock,
    },
    Packs {
        packs: Packs,
        _lock: Option<SharedStoreLock>,
    },
}

impl Store {
    pub fn open(path: &Path) -> Result<Store> {
        Self::open_with_cache(path, DEFAULT_READ_CACHE_BYTES)
    }

    /// Opens with an explicit sled page-cache size (part of the caller's memory budget).
    ///
    /// Fails at once, naming the store: when another process holds it ([`StorageError::InUse`],
    /// with the URL of the `strata serve` that streams it), on read-only media
    /// ([`StorageError::ReadOnly`]), for an interrupted import, and for damage (a panic inside
    /// sled is contained and reported as [`StorageError::Corrupted`]).
    pub fn open_with_cache(path: &Path, sled_cache_bytes: u64) -> Result<Store> {
        if !path.exists() {
            return Err(StorageError::invalid(path, "store does not exist"));
        }
        // Present at all (without following it or opening it): what it is and says is
        // checked by `read_marker` below.
        if std::fs::symlink_metadata(path.join(MARKER_FILE)).is_err() {
            return Err(StorageError::NotAStore {
                path: path.to_path_buf(),
                message: format!("no {MARKER_FILE} marker"),
            });
        }
        let marker = read_marker(path)?;
        if marker.format >= 3 {
            return Self::open_packs(path, &marker);
        }
        if !path.join(DB_DIR).is_dir() {
            return Err(StorageError::corrupted(
                path,
                format!("its database folder {DB_DIR}/ is missing"),
            ));
        }
        // sled opens every file under db/ itself; a FIFO there would block it for ever.
        refuse_non_regular_files(path, &path.join(DB_DIR), 2)?;
        let lock = StoreLock::acquire(path, LockPurpose::Read)?;
        let config = sled::Config::new()
            .path(path.join(DB_DIR))
            .cache_capacity(sled_cache_bytes);
        let db = contained(path, "opening the database", || {
            open_db_when_unlocked(config)
        })?;
        let meta = contained(path, "opening the metadata", || db.open_tree("meta"))?;
        let get = |key: &[u8]| -> Result<Option<sled::IVec>> {
            contained(path, "reading the metadata", || meta.get(key))
        };
        let require = |key: &[u8]| -> Result<sled::IVec> {
            get(key)?.ok_or_else(|| {
                StorageError::corrupted(
                    path,
                    format!("its {} record is missing", String::from_utf8_lossy(key)),
                )
            })
        };
        if get(KEY_COMPLETE)?.is_none() {
            // An interrupted import wrote bricks but no metadata yet. The marker file says
            // "complete" once the import finished (stores of older versions lack that line, so
            // metadata without the final record counts as damage too).
            return Err(if marker.complete {
                StorageError::corrupted(
                    path,
                    "the import finished, but the database lost its records (damaged database files)",
                )
            } else if get(KEY_HEADER)?.is_some() && get(KEY_STATS)?.is_some() {
                StorageError::corrupted(path, "its completion record is missing")
            } else {
                StorageError::IncompleteImport {
                    path: path.to_path_buf(),
                }
            });
        }
        let (header, skeleton, histogram, stats) = parse_documents(
            path,
            &marker,
            &require(KEY_HEADER)?,
            &require(KEY_SKELETON)?,
            &require(KEY_HISTOGRAM)?,
            &require(KEY_STATS)?,
        )?;
        let bricks = contained(path, "opening the bricks", || db.open_tree("bricks"))?;
        if header.frames == 0
            || header.frames as u64 > crate::geometry::MAX_AXIS_VOXELS
            || (header.frames > 1 && !header.required_features.iter().any(|f| f == FEATURE_FRAMES))
        {
            return Err(StorageError::corrupted(
                path,
                format!(
                    "its header claims {} frames (without the '{FEATURE_FRAMES}' feature, or absurd)",
                    header.frames
                ),
            ));
        }
        let mut later_skeletons = Vec::new();
        let mut later_trees = Vec::new();
        let mut trees = vec![meta.clone(), bricks.clone()];
        for f in 1..header.frames {
            let key = frame_skeleton_key(f);
            let frame_skeleton = Skeleton::decode(&require(key.as_bytes())?, &header.layout)
                .map_err(|e| {
                    StorageError::corrupted(path, format!("frame {f}'s octree skeleton {e}"))
                })?;
            let tree = contained(path, "opening a frame's bricks", || {
                db.open_tree(frame_bricks_tree(f))
            })?;
            trees.push(tree.clone());
            later_trees.push(tree);
            later_skeletons.push(frame_skeleton);
        }
        Ok(Store {
            path: path.to_path_buf(),
            later_skeletons,
            header,
            skeleton,
            histogram,
            stats,
            backend: Backend::Sled {
                bricks,
                later_trees,
                db: SledHandles::new(path, db, trees),
                lock,
            },
        })
    }

    /// Opens a format-3 store without writing anything: a shared lock on its existing lock
    /// file (none where it has none), the index read, the packs mapped (see [`crate::packs`]).
    fn open_packs(path: &Path, marker: &Marker) -> Result<Store> {
        let lock = SharedStoreLock::acquire(path)?;
        if !marker.complete {
            return Err(StorageError::IncompleteImport {
                path: path.to_path_buf(),
            });
        }
        let index = crate::packs::read_index(path)?;
        let docs = &index.docs;
        let (header, skeleton, histogram, stats) = parse_documents(
            path,
            marker,
            &docs.header,
            &docs.skeleton,
            &docs.histogram,
            &docs.stats,
        )?;
        // Frames 1..'s skeletons come with the index; the header must name exactly as many
        // frames (and the feature for more than one).
        let later = &docs.frame_skeletons;
        if header.frames as usize != later.len() + 1
            || (header.frames > 1 && !header.required_features.iter().any(|f| f == FEATURE_FRAMES))
        {
            return Err(StorageError::corrupted(
                path,
                format!(
                    "its header claims {} frames, its index {INDEX_FILE} holds skeletons of {} (or the '{FEATURE_FRAMES}' feature is missing)",
                    header.frames,
                    later.len() + 1
                ),
            ));
        }
        let mut later_skeletons = Vec::with_capacity(later.len());
        for (i, bytes) in later.iter().enumerate() {
            later_skeletons.push(Skeleton::decode(bytes, &header.layout).map_err(|e| {
                StorageError::corrupted(path, format!("frame {}'s octree skeleton {e}", i + 1))
            })?);
        }
        if let Some(e) = index.entries.iter().find(|e| e.frame >= header.frames) {
            return Err(StorageError::corrupted(
                path,
                format!(
                    "its index {INDEX_FILE} holds {} of frame {} in a store of {} frames",
                    entry_what(e),
                    e.frame,
                    header.frames
                ),
            ));
        }
        let packs = Packs::open(path, &index.pack_lengths, index.entries)?;
        Ok(Store {
            path: path.to_path_buf(),
            later_skeletons,
            header,
            skeleton,
            histogram,
            stats,
            backend: Backend::Packs { packs, _lock: lock },
        })
    }

    /// The store's format: 3 (packs) or 1-2 (sled).
    pub fn format_version(&self) -> u32 {
        self.header.format_version
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
        self.skeleton.node(id)
    }

    /// [`Store::node`] of frame `frame`.
    pub fn frame_node(&self, frame: u32, id: BrickId) -> Option<NodeInfo> {
        self.frame_skeleton(frame)?.node(id)
    }

    /// Whether constant nodes may lack a brick record (read from the skeleton instead).
    fn constant_bricks_implied(&self) -> bool {
        self.header
            .required_features
            .iter()
            .any(|f| f == FEATURE_SPARSE_SKELETON)
    }

    /// The record of `id` in frame `frame` (a slice of a pack's map in format 3, a copy out of
    /// sled before), or for a constant node without one in a store that may omit them, the
    /// constant record the skeleton implies; `None` when neither exists.
    fn record_or_implied(&self, frame: u32, id: BrickId) -> Result<Option<Cow<'_, [u8]>>> {
        let skeleton = match self.frame_skeleton(frame) {
            Some(s) => s,
            None => {
                return Err(StorageError::invalid(
                    &self.path,
                    format!(
                        "frame {frame} of a store with {} frames",
                        self.frame_count()
                    ),
                ))
            }
        };
        let stored: Option<Cow<'_, [u8]>> = match &self.backend {
            Backend::Sled {
                bricks,
                later_trees,
                ..
            } => {
                let tree = match frame {
                    0 => bricks,
                    f => &later_trees[f as usize - 1],
                };
                contained(&self.path, "reading a brick", || tree.get(brick_key(id)))?
                    .map(|r| Cow::Owned(r.to_vec()))
            }
            Backend::Packs { packs, .. } => packs.get(frame, id).map(Cow::Borrowed),
        };
        if stored.is_some() {
            return Ok(stored);
        }
        Ok(skeleton
            .node(id)
            .filter(|n| n.is_constant() && self.constant_bricks_implied())
            .map(|n| Cow::Owned(crate::brick::constant_record(id, n.min))))
    }

    /// The record of `id` in frame `frame`, or an error naming the store and the brick.
    fn record(&self, frame: u32, id: BrickId) -> Result<Cow<'_, [u8]>> {
        if !self.header.layout.contains(id) {
            return Err(StorageError::invalid(
                &self.path,
                format!("brick {id:?} is outside the octree"),
            ));
        }
        self.record_or_implied(frame, id)?.ok_or_else(|| {
            let which = if frame == 0 {
                String::new()
            } else {
                format!("frame {frame}: ")
            };
            StorageError::corrupted(
                &self.path,
                format!(
                    "{which}brick level {} at {:?} is missing",
                    id.level, id.coords
                ),
            )
        })
    }

    /// Volumes in this store (1 unless it is 4-D).
    pub fn frame_count(&self) -> u32 {
        self.header.frames.max(1)
    }

    /// Frame `frame`'s skeleton (frame 0's is [`Store::skeleton`]).
    pub fn frame_skeleton(&self, frame: u32) -> Option<&Skeleton> {
        match frame {
            0 => Some(&self.skeleton),
            f => self.later_skeletons.get(f as usize - 1),
        }
    }

    /// [`Store::read_brick_record`] of frame `frame`.
    pub fn read_frame_brick_record(&self, frame: u32, id: BrickId) -> Result<Vec<u8>> {
        Ok(self.record(frame, id)?.into_owned())
    }

    /// [`Store::read_brick`] of frame `frame`.
    pub fn read_frame_brick(&self, frame: u32, id: BrickId) -> Result<Vec<u16>> {
        let record = self.record(frame, id)?;
        self.decode_frame_brick_record(frame, id, &record)
    }

    /// Verifies and decodes `record`, read earlier as brick `id` of frame `frame`, with this
    /// store's error wording (the store, the pack, the brick): a reader that kept the record
    /// (to count its bytes) words a failure without reading it again.
    pub fn decode_frame_brick_record(
        &self,
        frame: u32,
        id: BrickId,
        record: &[u8],
    ) -> Result<Vec<u16>> {
        decode_brick(id, record).map_err(|e| self.brick_error(frame, id, e))
    }

    /// Reads, verifies and decompresses one brick: 36³ stored values, x fastest. In format 3
    /// the record is decoded straight from the pack's map (no copy).
    pub fn read_brick(&self, id: BrickId) -> Result<Vec<u16>> {
        self.read_frame_brick(0, id)
    }

    /// One brick's record exactly as stored (kind, checksum, compressed body): what the data
    /// service sends, so nothing is decoded or re-encoded on the way. Not verified here. A
    /// constant node of a store that omits their records answers the constant record.
    pub fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>> {
        self.read_frame_brick_record(0, id)
    }

    /// [`Store::read_brick_record`] without a copy where the store allows it (format 3: a slice
    /// of the pack's map).
    pub fn brick_record(&self, id: BrickId) -> Result<Cow<'_, [u8]>> {
        self.record(0, id)
    }

    /// A decoding error of brick `id`, naming the store and, in format 3, the pack.
    fn brick_error(&self, frame: u32, id: BrickId, e: BrickDecodeError) -> StorageError {
        match &self.backend {
            Backend::Packs { packs, .. } => {
                let pack = packs
                    .entry(frame, id)
                    .map(|x| format!("{}: ", crate::packs::pack_name(x.pack)))
                    .unwrap_or_default();
                let which = match frame {
                    0 => String::new(),
                    f => format!("frame {f}: "),
                };
                StorageError::corrupted(
                    &self.path,
                    format!(
                        "{pack}{which}brick level {} at {:?}: {e}",
                        id.level, id.coords
                    ),
                )
            }
            Backend::Sled { .. } => brick_error(&self.path, id, e),
        }
    }

    /// The stored record of `id` (frame 0) as a share of its pack's map, for a server to send
    /// without a copy; `None` where it is not a mapped record (a format 1-2 store, a constant
    /// node without one): read it with [`Store::read_brick_record`] then.
    pub fn brick_record_mapped(&self, id: BrickId) -> Option<MappedRecord> {
        match &self.backend {
            Backend::Packs { packs, .. } => packs.mapped(0, id),
            Backend::Sled { .. } => None,
        }
    }

    /// Records in this store's lock where `strata serve` streams it, so a local open of the
    /// same folder is refused at once with the URL to use instead.
    /// A format-3 store is read by any number of processes at once: nothing is recorded.
    pub fn advertise_url(&mut self, url: &str) -> Result<()> {
        match &mut self.backend {
            Backend::Sled { lock, .. } => lock.advertise_url(url),
            Backend::Packs { .. } => Ok(()),
        }
    }

    /// Size of the stored record of a brick (compressed), for I/O accounting.
    pub fn stored_brick_bytes(&self, id: BrickId) -> Result<u64> {
        match &self.backend {
            Backend::Sled { bricks, .. } => {
                Ok(
                    contained(&self.path, "reading a brick", || bricks.get(brick_key(id)))?
                        .map_or(0, |r| r.len() as u64),
                )
            }
            Backend::Packs { packs, .. } => Ok(packs.get(0, id).map_or(0, |r| r.len() as u64)),
        }
    }

    /// Where each record of a format-3 store lies: (frame, brick, pack file, offset, length),
    /// in index order; empty for formats 1-2. For benchmarks of the read path (`pack_read`).
    #[doc(hidden)]
    pub fn record_locations(&self) -> Vec<(u32, BrickId, PathBuf, u64, u32)> {
        match &self.backend {
            Backend::Packs { packs, .. } => packs
                .entries()
                .iter()
                .filter_map(|e| {
                    let path = crate::packs::pack_path(&self.path, e.pack);
                    Some((e.frame, e.id()?, path, e.offset, e.len))
                })
                .collect(),
            Backend::Sled { .. } => Vec::new(),
        }
    }

    /// The version of brick `id`'s record in a format-3 store: 1 as imported, one more for each
    /// new record appended since ([`append_brick_versions`]). `None` for a brick without a
    /// record, and in formats 1-2, which keep no versions.
    pub fn brick_version(&self, id: BrickId) -> Option<u32> {
        match &self.backend {
            Backend::Packs { packs, .. } => packs.entry(0, id).map(|e| e.version),
            Backend::Sled { .. } => None,
        }
    }

    /// Checks every brick of every frame: present, checksum, decompression, and range equal to
    /// the (frame's) skeleton's. In a store whose constant bricks may be implied
    /// ([`FEATURE_SPARSE_SKELETON`]) that is every record there is, each against its node, and
    /// every varying node must have one; elsewhere every node of the octree must have a record.
    /// Returns one message per problem found (empty when the store is sound).
    ///
    /// Terminates on any damage: the bricks are read on a named thread of their own and each read
    /// may take at most [`VERIFY_READ_LIMIT`]; a read that hangs inside sled (as on a damaged blob
    /// file) ends the check with a problem naming the brick, because the database is then stuck.
    pub fn verify(&self, on_progress: impl FnMut(u64, u64)) -> Result<Vec<String>> {
        self.verify_report(on_progress).map(|r| r.problems)
    }

    /// [`Store::verify`] with what could still be read and the verdict to print.
    pub fn verify_report(&self, on_progress: impl FnMut(u64, u64)) -> Result<VerifyReport> {
        self.verify_report_to(VerifyDepth::Decode, on_progress)
    }

    /// [`Store::verify_report`] to the depth asked: a format-3 store checked at
    /// [`VerifyDepth::Checksums`] streams its packs and checks each record's checksum and place
    /// without decoding it (the disk's speed); formats 1-2 always decode.
    pub fn verify_report_to(
        &self,
        depth: VerifyDepth,
        mut on_progress: impl FnMut(u64, u64),
    ) -> Result<VerifyReport> {
        let (bricks, later_trees) = match &self.backend {
            Backend::Sled {
                bricks,
                later_trees,
                ..
            } => (bricks, later_trees),
            Backend::Packs { packs, .. } => {
                return Ok(self.verify_packs(packs, depth, on_progress))
            }
        };
        let layout = self.header.layout.clone();
        let sparse = self.constant_bricks_implied();
        // Every frame of a 4-D store: frame 0 in `bricks`, frame f in its own tree.
        let frame_trees: Vec<(u32, sled::Tree)> = std::iter::once((0, bricks.clone()))
            .chain(
                later_trees
                    .iter()
                    .enumerate()
                    .map(|(i, tree)| (i as u32 + 1, tree.clone())),
            )
            .collect();
        let frame_skeletons: Vec<&Skeleton> = (0..frame_trees.len() as u32)
            .filter_map(|f| self.frame_skeleton(f))
            .collect();
        // Varying nodes: each needs a record (in a sparse store, the only ones that do).
        let varying: Vec<u64> = frame_skeletons
            .iter()
            .map(|s| {
                (0..s.level_count())
                    .map(|l| s.nodes_in_level(l) - s.constant_in_level(l))
                    .sum()
            })
            .collect();
        let per_frame = layout.total_bricks();
        let total = if sparse {
            frame_skeletons
                .iter()
                .map(|s| s.stored_nodes() as u64)
                .sum()
        } else {
            per_frame * frame_trees.len() as u64
        };
        let skeletons: Vec<Skeleton> = frame_skeletons.iter().map(|s| (*s).clone()).collect();
        let (results, received) = crossbeam_channel::bounded::<VerifyItem>(4);
        let path = self.path.clone();
        let reader = std::thread::Builder::new()
            .name("strata-verify-reader".into())
            .spawn(move || {
                let mut counted = Ok(0usize);
                for (frame, tree) in &frame_trees {
                    let skeleton = &skeletons[*frame as usize];
                    if sparse {
                        // One pass over the records in key order; each damaged record or page
                        // is reported once and the walk moves on (see `walk_records`).
                        let walked = walk_records(&path, tree, skeleton, |item| {
                            let item = match item {
                                Walked::Record(key, record) => match brick_id_from_key(&key) {
                                    Some(id) if layout.contains(id) => VerifyItem::Brick(
                                        *frame,
                                        id,
                                        record.and_then(|record| {
                                            decode_brick(id, &record)
                                                .map_err(|e| brick_error(&path, id, e))
                                        }),
                                    ),
                                    _ => VerifyItem::Stray(*frame, key),
                                },
                                Walked::Failed(e) => VerifyItem::Failed(e),
                            };
                            results.send(item).is_ok()
                        });
                        match walked {
                            Some(n) => {
                                if let Ok(c) = &mut counted {
                                    *c += n;
                                }
                            }
                            None => return,
                        }
                        continue;
                    }
                    for level in 0..layout.level_count() {
                        let n = layout.bricks_in_level(level);
                        for z in 0..n[2] {
                            for y in 0..n[1] {
                                for x in 0..n[0] {
                                    let id = BrickId::new(level as u8, [x, y, z]);
                                    let voxels = read_brick_record(&path, tree, id);
                                    if results.send(VerifyItem::Brick(*frame, id, voxels)).is_err()
                                    {
                                        return;
                                    }
                                }
                            }
                        }
                    }
                    // Stray records: count them, stopping at the first error (the keyed reads
                    // above already reported every damaged record once).
                    match (&mut counted, count_records(&path, tree)) {
                        (Ok(c), Ok(n)) => *c += n,
                        (c, Err(e)) => {
                            if c.is_ok() {
                                *c = Err(e);
                            }
                        }
                        (Err(_), Ok(_)) => {}
                    }
                }
                let _ = results.send(VerifyItem::Done(counted));
            });
        if let Err(e) = reader {
            return Err(StorageError::io(&self.path, e));
        }
        let mut problems = Problems::default();
        let mut seen = 0u64;
        let mut varying_with_records = vec![0u64; varying.len()];
        loop {
            let item = match received.recv_timeout(VERIFY_READ_LIMIT) {
                Ok(r) => r,
                Err(_) => {
                    problems.push(format!(
                        "{}: reading brick {} of {total} did not finish within {} s: the database is damaged (blob or segment files); the rest was not checked",
                        self.path.display(),
                        seen + 1,
                        VERIFY_READ_LIMIT.as_secs()
                    ));
                    return Ok(problems.finish(&self.path, &self.header, seen));
                }
            };
            let (frame, id, voxels) = match item {
                VerifyItem::Brick(frame, id, voxels) => (frame, id, voxels),
                VerifyItem::Failed(e) => {
                    problems.push(format!(
                        "{e} (the records after it are read one by one, by the skeleton's nodes)"
                    ));
                    continue;
                }
                VerifyItem::Stray(frame, key) => {
                    problems.push(format!(
                        "{}: frame {frame}: a brick record under key {key:02x?} outside the octree",
                        self.path.display()
                    ));
                    continue;
                }
                VerifyItem::Done(counted) => {
                    match counted {
                        Ok(stored) if !sparse && stored as u64 != total => problems.push(format!(
                            "{}: {stored} brick records for {total} octree nodes",
                            self.path.display()
                        )),
                        Ok(_) => {}
                        Err(e) => problems.push(e.to_string()),
                    }
                    break;
                }
            };
            seen += 1;
            // A record present but damaged counts as present: its damage is its own problem.
            if !self.frame_node(frame, id).unwrap_or_default().is_constant() {
                if let Some(n) = varying_with_records.get_mut(frame as usize) {
                    *n += 1;
                }
            }
            let which = if frame == 0 {
                String::new()
            } else {
                format!("frame {frame}, ")
            };
            match voxels {
                Err(e) if frame == 0 => problems.push(e.to_string()),
                Err(e) => problems.push(format!("frame {frame}: {e}")),
                Ok(voxels) => {
                    let r = crate::brick::value_range(&voxels);
                    let node = self.frame_node(frame, id).unwrap_or_default();
                    if (r.min, r.max) == (node.min, node.max) {
                        problems.intact += 1;
                    } else {
                        problems.push(format!(
                            "{}: {which}brick level {} at {:?}: range {}..{} differs from the skeleton's {}..{}",
                            self.path.display(), id.level, id.coords, r.min, r.max, node.min, node.max
                        ));
                    }
                }
            }
            if seen.is_multiple_of(64) || seen == total {
                on_progress(seen.min(total), total);
            }
        }
        if sparse {
            for (frame, (&want, &have)) in varying.iter().zip(&varying_with_records).enumerate() {
                if have != want {
                    problems.push(format!(
                        "{}: frame {frame}: {have} brick records for the skeleton's {want} varying nodes",
                        self.path.display()
                    ));
                }
            }
        }
        on_progress(total, total);
        Ok(problems.finish(&self.path, &self.header, seen))
    }

    /// [`Store::verify_report`] of a format-3 store: the packs streamed in order (entries by pack
    /// and offset, so the disk reads sequentially), every record checked against its checksum
    /// and the index (inside its pack, overlapping no other record, a brick of the octree; at
    /// [`VerifyDepth::Decode`] also decoded and its range compared with its node's); every bad
    /// brick reported by id with its pack.
    fn verify_packs(
        &self,
        packs: &Packs,
        depth: VerifyDepth,
        mut on_progress: impl FnMut(u64, u64),
    ) -> VerifyReport {
        let layout = &self.header.layout;
        let sparse = self.constant_bricks_implied();
        let mut order: Vec<&crate::packs::Entry> = packs.entries().iter().collect();
        order.sort_by_key(|e| (e.pack, e.offset));
        let chunk_len = match depth {
            VerifyDepth::Checksums => VERIFY_STREAM_CHUNK,
            VerifyDepth::Decode => VERIFY_CHUNK,
        };
        // The read is sequential, so the kernel may read ahead and drop what was read.
        packs.advise_sequential(true);
        let total = order.len() as u64;
        // What progress counts to: as format 2 does, the nodes that need a record (a sparse
        // store's stored nodes, every node otherwise).
        let frames = self.frame_count();
        let skeletons: Vec<&Skeleton> =
            (0..frames).filter_map(|f| self.frame_skeleton(f)).collect();
        let nodes = if sparse {
            skeletons.iter().map(|s| s.stored_nodes() as u64).sum()
        } else {
            layout.total_bricks() * u64::from(frames)
        };
        let mut problems = Problems::default();
        let mut seen = 0u64;
        // Per frame: records whose node varies.
        let mut varying_with_records = vec![0u64; frames as usize];
        let store = self.path.display();
        // Records that overlap the one before them in their pack: two index entries claim the
        // same bytes (an index written wrong), which no checksum would show.
        let mut previous: Option<&crate::packs::Entry> = None;
        for e in &order {
            if let Some(p) = previous.filter(|p| p.pack == e.pack) {
                if p.offset + u64::from(p.len) > e.offset {
                    problems.push(format!(
                        "{store}: {}: {} at bytes {}..{} overlaps {} at bytes {}..{}: the index is damaged",
                        crate::packs::pack_name(e.pack),
                        entry_what(e),
                        e.offset,
                        e.offset + u64::from(e.len),
                        entry_what(p),
                        p.offset,
                        p.offset + u64::from(p.len)
                    ));
                }
            }
            previous = Some(e);
        }
        // Ancestors of bricks edited since import: their ranges were widened to bound the edit
        // (see `append_brick_versions`), so they need only contain their records' ranges.
        let mut widened: std::collections::HashSet<(u32, BrickId)> =
            std::collections::HashSet::new();
        for (frame, id) in order
            .iter()
            .filter(|e| e.version > 1)
            .filter_map(|e| Some((e.frame, e.id()?)))
        {
            let mut at = id;
            while usize::from(at.level) + 1 < layout.level_count() {
                at = BrickId::new(at.level + 1, at.coords.map(|c| c / 2));
                if !widened.insert((frame, at)) {
                    break;
                }
            }
        }
        // Chunks in pack order, each checked on all cores: the disk still reads sequentially.
        for chunk in order.chunks(chunk_len) {
            use rayon::prelude::*;
            let checked: Vec<(u32, bool, Option<String>)> = chunk
                .par_iter()
                .map(|e| {
                    let (varying, problem) = self.check_pack_record(packs, e, depth, &widened);
                    (e.frame, varying, problem)
                })
                .collect();
            for (frame, varying, problem) in checked {
                seen += 1;
                if let Some(n) = varying_with_records.get_mut(frame as usize) {
                    *n += u64::from(varying);
                }
                match problem {
                    Some(p) => problems.push(p),
                    None => problems.intact += 1,
                }
            }
            on_progress(seen.min(nodes), nodes);
        }
        if sparse {
            for (frame, (skeleton, &have)) in
                skeletons.iter().zip(&varying_with_records).enumerate()
            {
                let want: u64 = (0..skeleton.level_count())
                    .map(|l| skeleton.nodes_in_level(l) - skeleton.constant_in_level(l))
                    .sum();
                if have != want {
                    let which = match frame {
                        0 => String::new(),
                        f => format!("frame {f}: "),
                    };
                    problems.push(format!(
                        "{store}: {which}{have} brick records for the skeleton's {want} varying nodes"
                    ));
                }
            }
        } else if total != layout.total_bricks() * u64::from(frames) {
            problems.push(format!(
                "{store}: {total} brick records for {} octree nodes{}",
                layout.total_bricks(),
                match frames {
                    1 => String::new(),
                    n => format!(" in each of {n} frames"),
                }
            ));
        }
        packs.advise_sequential(false);
        on_progress(nodes, nodes);
        problems.finish(&self.path, &self.header, seen)
    }

    /// One record of a format-3 store checked: whether its node varies, and its problem.
    fn check_pack_record(
        &self,
        packs: &Packs,
        e: &crate::packs::Entry,
        depth: VerifyDepth,
        widened: &std::collections::HashSet<(u32, BrickId)>,
    ) -> (bool, Option<String>) {
        let store = self.path.display();
        let pack = match e.frame {
            0 => crate::packs::pack_name(e.pack),
            f => format!("{} (frame {f})", crate::packs::pack_name(e.pack)),
        };
        let id = match e.id() {
            Some(id) if self.header.layout.contains(id) && e.frame < self.frame_count() => id,
            _ => {
                return (
                    false,
                    Some(format!(
                        "{store}: {pack}: a record under key {:02x?} (frame {}) outside the octree",
                        e.key, e.frame
                    )),
                )
            }
        };
        let node = self.frame_node(e.frame, id).unwrap_or_default();
        let varying = !node.is_constant();
        let Some(record) = packs.slice(e) else {
            return (
                varying,
                Some(format!(
                    "{store}: {pack}: brick level {} at {:?} lies outside its pack",
                    id.level, id.coords
                )),
            );
        };
        if depth == VerifyDepth::Checksums {
            let problem = crate::brick::verify_record(id, record).err().map(|err| {
                format!(
                    "{store}: {pack} at byte {}: brick level {} at {:?}: {err}",
                    e.offset, id.level, id.coords
                )
            });
            return (varying, problem);
        }
        let problem = match decode_brick(id, record) {
            Err(err) => Some(format!(
                "{store}: {pack} at byte {}: brick level {} at {:?}: {err}",
                e.offset, id.level, id.coords
            )),
            Ok(voxels) => {
                let r = crate::brick::value_range(&voxels);
                let fits = if widened.contains(&(e.frame, id)) {
                    node.min <= r.min && r.max <= node.max
                } else {
                    (r.min, r.max) == (node.min, node.max)
                };
                (!fits).then(|| {
                    format!(
                        "{store}: {pack}: brick level {} at {:?}: range {}..{} differs from the skeleton's {}..{}",
                        id.level, id.coords, r.min, r.max, node.min, node.max
                    )
                })
            }
        };
        (varying, problem)
    }

    /// Overwrites one byte of a stored brick record. Only for tests of corruption handling.
    #[cfg(any(test, feature = "test-hooks"))]
    pub fn corrupt_brick_for_tests(path: &Path, id: BrickId, byte: usize) -> Result<()> {
        Self::corrupt_frame_brick_for_tests(path, 0, id, byte)
    }

    /// [`Store::corrupt_brick_for_tests`] in frame `frame` of a 4-D store.
    #[cfg(any(test, feature = "test-hooks"))]
    pub fn corrupt_frame_brick_for_tests(
        path: &Path,
        frame: u32,
        id: BrickId,
        byte: usize,
    ) -> Result<()> {
        let _lock = StoreLock::acquire(path, LockPurpose::Import)?;
        if read_marker(path)?.format >= 3 {
            use std::os::unix::fs::FileExt;
            let index = crate::packs::read_index(path)?;
            let key = brick_key(id);
            let e = index
                .entries
                .iter()
                .find(|e| e.frame == frame && e.key == key)
                .ok_or_else(|| StorageError::corrupted(path, "no such brick"))?;
            let file = crate::packs::pack_path(path, e.pack);
            let f = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(&file)
                .map_err(|x| StorageError::io(&file, x))?;
            let at = e.offset + (byte as u64).min(u64::from(e.len).saturating_sub(1));
            let mut b = [0u8];
            f.read_exact_at(&mut b, at)
                .and_then(|()| f.write_all_at(&[b[0] ^ 0x01], at))
                .map_err(|x| StorageError::io(&file, x))?;
            return Ok(());
        }
        let db = contained(path, "opening the database", || {
            open_db_when_unlocked(sled::Config::new().path(path.join(DB_DIR)))
        })?;
        let tree_name = match frame {
            0 => "bricks".to_string(),
            f => frame_bricks_tree(f),
        };
        let bricks = contained(path, "opening the bricks", || db.open_tree(&tree_name))?;
        let mut record = contained(path, "reading a brick", || bricks.get(brick_key(id)))?
            .ok_or_else(|| StorageError::corrupted(path, "no such brick"))?
            .to_vec();
        let at = byte.min(record.len().saturating_sub(1));
        if let Some(b) = record.get_mut(at) {
            *b ^= 0x01;
        }
        contained(path, "writing a brick", || {
            bricks.insert(brick_key(id), record)
        })?;
        let db = SledHandles::new(path, db, vec![bricks]);
        db.flush(FLUSH_LIMIT)
    }

    /// Closes the store, reporting a failure to close (instead of hiding it in a drop).
    pub fn close(self) -> Result<()> {
        match self.backend {
            Backend::Sled { db, .. } => db.flush(FLUSH_LIMIT),
            Backend::Packs { .. } => Ok(()),
        }
    }
}

/// Refuses a header this build cannot read, naming the command that rebuilds the store.
fn check_format(path: &Path, header: &StoreHeader) -> Result<()> {
    check_format_knowing(path, header, KNOWN_STORE_FEATURES)
}

/// Decodes and checks a store's documents (header against the marker and this build, geometry,
/// layout, skeleton, histogram, statistics), naming the store in every error.
fn parse_documents(
    path: &Path,
    marker: &Marker,
    header: &[u8],
    skeleton: &[u8],
    histogram: &[u8],
    stats: &[u8],
) -> Result<(StoreHeader, Skeleton, Histogram, StoreStats)> {
    let header: StoreHeader = serde_json::from_slice(header)
        .map_err(|e| StorageError::corrupted(path, format!("its header is unreadable: {e}")))?;
    check_format(path, &header)?;
    if marker.format != header.format_version {
        return Err(StorageError::corrupted(
            path,
            format!(
                "its {MARKER_FILE} marker says format {} but its header format {}",
                marker.format, header.format_version
            ),
        ));
    }
    header
        .geometry
        .validate()
        .map_err(|e| StorageError::corrupted(path, format!("its header's geometry: {e}")))?;
    if header.layout != OctreeLayout::new(header.geometry.dims) {
        return Err(StorageError::corrupted(
            path,
            "its header's octree layout does not match its dimensions",
        ));
    }
    let skeleton = Skeleton::decode(skeleton, &header.layout)
        .map_err(|e| StorageError::corrupted(path, format!("its octree skeleton {e}")))?;
    let histogram: Histogram = serde_json::from_slice(histogram)
        .map_err(|e| StorageError::corrupted(path, format!("its histogram is unreadable: {e}")))?;
    let stats: StoreStats = serde_json::from_slice(stats).map_err(|e| {
        StorageError::corrupted(path, format!("its statistics are unreadable: {e}"))
    })?;
    Ok((header, skeleton, histogram, stats))
}

/// The skeleton's bytes for a store with `header`: sparse where the header names the feature,
/// the dense encoding of earlier builds otherwise (format-1 stores, which they must read).
fn encode_skeleton_for(header: &StoreHeader, skeleton: &Skeleton) -> Vec<u8> {
    if header
        .required_features
        .iter()
        .any(|f| f == FEATURE_SPARSE_SKELETON)
    {
        skeleton.encode()
    } else {
        skeleton.encode_dense()
    }
}

fn frame_skeleton_key(frame: u32) -> String {
    format!("skeleton-frame-{frame}")
}

fn frame_bricks_tree(frame: u32) -> String {
    format!("bricks-frame-{frame}")
}

/// Makes the complete store at `path` a 4-D store: the complete single-volume stores
/// `later_frames` (imported with the same value mapping onto the same grid) become its frames
/// 1.., their bricks and skeletons copied in; the header, rewritten last in one insert, then
/// names the frames and the feature. Until that insert the store is a valid single volume.
pub(crate) fn append_frames(path: &Path, later_frames: &[PathBuf]) -> Result<()> {
    let mut frame_stores = Vec::with_capacity(later_frames.len());
    for p in later_frames {
        frame_stores.push(Store::open(p)?);
    }
    if read_marker(path)?.format >= 3 {
        return append_frames_to_packs(path, &frame_stores);
    }
    let _lock = StoreLock::acquire(path, LockPurpose::Import)?;
    let config = sled::Config::new().path(path.join(DB_DIR));
    let db = contained(path, "opening the database", || {
        open_db_when_unlocked(config)
    })?;
    let meta = contained(path, "opening the metadata", || db.open_tree("meta"))?;
    let mut header: StoreHeader = contained(path, "reading the metadata", || meta.get(KEY_HEADER))?
        .and_then(|h| serde_json::from_slice(&h).ok())
        .ok_or_else(|| StorageError::corrupted(path, "its header is unreadable"))?;
    let mut trees = vec![meta.clone()];
    for (i, frame) in frame_stores.iter().enumerate() {
        let f = i as u32 + 1;
        let h = frame.header();
        if h.layout != header.layout || h.value_mapping != header.value_mapping {
            return Err(StorageError::invalid(
                path,
                format!("frame {f} has another grid or value mapping than frame 0"),
            ));
        }
        let tree = contained(path, "creating a frame's bricks", || {
            db.open_tree(frame_bricks_tree(f))
        })?;
        let mut batch = sled::Batch::default();
        let Backend::Sled { bricks, .. } = &frame.backend else {
            return Err(StorageError::invalid(
                path,
                format!("frame {f} is not a format-2 store"),
            ));
        };
        for entry in bricks.iter() {
            let (k, v) = contained(path, "copying a frame", || entry)?;
            batch.insert(k, v);
        }
        contained(path, "writing a frame's bricks", || tree.apply_batch(batch))?;
        contained(path, "writing a frame's skeleton", || {
            meta.insert(
                frame_skeleton_key(f).as_bytes(),
                encode_skeleton_for(&header, &frame.skeleton),
            )
        })?;
        header.stored_range = [
            header.stored_range[0].min(h.stored_range[0]),
            header.stored_range[1].max(h.stored_range[1]),
        ];
        trees.push(tree);
    }
    header.frames = later_frames.len() as u32 + 1;
    if !header.required_features.iter().any(|f| f == FEATURE_FRAMES) {
        header.required_features.push(FEATURE_FRAMES.into());
    }
    let handles = SledHandles::new(path, db, trees);
    handles.flush(FLUSH_LIMIT)?;
    let json = serde_json::to_vec(&header)
        .map_err(|e| StorageError::invalid(path, format!("encoding the header: {e}")))?;
    contained(path, "writing the header", || meta.insert(KEY_HEADER, json))?;
    handles.flush(FLUSH_LIMIT)?;
    drop(meta);
    drop(frame_stores);
    Ok(())
}

/// [`append_frames`] onto a format-3 store: every record of each frame store is appended to
/// new packs under its frame's number (as imported, version 1), and the new index, whose header
/// names the frames and which carries their skeletons, is renamed in last
/// (`packs::append_records`): until that rename the store is the complete single volume it was.
fn append_frames_to_packs(path: &Path, frame_stores: &[Store]) -> Result<()> {
    let (_shared, _write) = hold_for_writing(path)?;
    let index = crate::packs::read_index(path)?;
    let marker = read_marker(path)?;
    let docs = &index.docs;
    let (mut header, ..) = parse_documents(
        path,
        &marker,
        &docs.header,
        &docs.skeleton,
        &docs.histogram,
        &docs.stats,
    )?;
    if header.frames != 1 {
        return Err(StorageError::invalid(
            path,
            "frames appended to a 4-D store",
        ));
    }
    let mut frame_skeletons = Vec::with_capacity(frame_stores.len());
    let mut records: Vec<(u32, BrickId, Option<u32>, &[u8])> = Vec::new();
    for (f, frame) in (1u32..).zip(frame_stores) {
        let h = frame.header();
        let Backend::Packs { packs, .. } = &frame.backend else {
            return Err(StorageError::invalid(
                path,
                format!("frame {f} is not a format-3 store"),
            ));
        };
        if h.layout != header.layout || h.value_mapping != header.value_mapping || h.frames != 1 {
            return Err(StorageError::invalid(
                path,
                format!("frame {f} has another grid or value mapping than frame 0"),
            ));
        }
        for e in packs.entries() {
            let (Some(id), Some(record)) = (e.id(), packs.slice(e)) else {
                return Err(StorageError::corrupted(
                    frame.path(),
                    format!("its index holds a bad entry under key {:02x?}", e.key),
                ));
            };
            records.push((f, id, Some(e.version), record));
        }
        frame_skeletons.push(encode_skeleton_for(&header, &frame.skeleton));
        header.stored_range = [
            header.stored_range[0].min(h.stored_range[0]),
            header.stored_range[1].max(h.stored_range[1]),
        ];
    }
    header.frames = frame_stores.len() as u32 + 1;
    if !header.required_features.iter().any(|f| f == FEATURE_FRAMES) {
        header.required_features.push(FEATURE_FRAMES.into());
    }
    let docs = crate::packs::IndexDocs {
        header: serde_json::to_vec(&header)
            .map_err(|e| StorageError::invalid(path, format!("encoding the header: {e}")))?,
        skeleton: docs.skeleton.clone(),
        histogram: docs.histogram.clone(),
        stats: docs.stats.clone(),
        frame_skeletons,
    };
    crate::packs::append_records(
        path,
        &index,
        &docs,
        records.into_iter(),
        crate::packs::PACK_LIMIT_BYTES,
    )
}

/// What a store's marker file says.
struct Marker {
    format: u32,
    /// The `complete` line (stores written before it existed lack it).
    complete: bool,
}

/// The marker is a few dozen bytes; anything larger is not one.
const MARKER_MAX_BYTES: u64 = 4096;

/// Reads and checks the marker: a regular file (checked before opening it: a FIFO would block
/// the read) holding `strata store format N` with N a format this build reads, and at most
/// the `complete` line after it. Empty, junk, an unknown format or unknown lines are damage.
fn read_marker(path: &Path) -> Result<Marker> {
    let file = path.join(MARKER_FILE);
    let bad =
        |what: String| StorageError::corrupted(path, format!("its {MARKER_FILE} marker {what}"));
    let meta = std::fs::metadata(&file).map_err(|e| StorageError::io(&file, e))?;
    if !meta.is_file() {
        return Err(bad("is not a regular file".into()));
    }
    if meta.len() > MARKER_MAX_BYTES {
        return Err(bad(format!(
            "is {} bytes long (a marker is one or two lines)",
            meta.len()
        )));
    }
    let text = crate::regular_file::read_to_string(&file)?;
    let mut lines = text.lines().map(str::trim).filter(|l| !l.is_empty());
    let first = lines.next().unwrap_or_default();
    let format = first
        .strip_prefix("strata store format ")
        .and_then(|v| v.parse::<u32>().ok())
        .ok_or_else(|| {
            bad(format!(
                "does not say 'strata store format N' (it says {first:?})"
            ))
        })?;
    if !(OLDEST_READABLE_FORMAT_VERSION..=STORE_FORMAT_VERSION).contains(&format) {
        return Err(StorageError::unsupported(
            path,
            format!(
                "its {MARKER_FILE} marker names store format {format} (this build reads versions {OLDEST_READABLE_FORMAT_VERSION} to {STORE_FORMAT_VERSION})"
            ),
        ));
    }
    let mut complete = false;
    for line in lines {
        if line == MARKER_COMPLETE_LINE && !complete {
            complete = true;
        } else {
            return Err(bad(format!("has an unknown line {line:?}")));
        }
    }
    Ok(Marker { format, complete })
}

/// Refuses anything under `dir` (to `depth` folders down) that is neither a folder nor a
/// regular file: sled opens the database's files itself and a FIFO, socket or device among
/// them would block it (and every command) for ever. `read_dir`'s file types come without an
/// open; a symbolic link is judged by what it points at.
fn refuse_non_regular_files(store: &Path, dir: &Path, depth: u32) -> Result<()> {
    let entries = std::fs::read_dir(dir).map_err(|e| StorageError::io(dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| StorageError::io(dir, e))?;
        let p = entry.path();
        let mut kind = entry.file_type().map_err(|e| StorageError::io(&p, e))?;
        if kind.is_symlink() {
            kind = std::fs::metadata(&p)
                .map_err(|e| StorageError::io(&p, e))?
                .file_type();
        }
        if kind.is_dir() {
            if depth > 0 {
                refuse_non_regular_files(store, &p, depth - 1)?;
            }
        } else if !kind.is_file() {
            return Err(StorageError::corrupted(
                store,
                format!(
                    "{} is not a regular file (a FIFO, socket or device); the database is damaged: re-import the store",
                    p.display()
                ),
            ));
        }
    }
    Ok(())
}

/// Records of a format-3 store decoded at once by [`Store::verify`] (in pack order).
const VERIFY_CHUNK: usize = 256;
/// Records of a format-3 store checksummed at once at [`VerifyDepth::Checksums`]: a few MB, so
/// the cores share the work while the read stays sequential.
const VERIFY_STREAM_CHUNK: usize = 1024;

/// How deep [`Store::verify_report_to`] checks a format-3 store's records.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VerifyDepth {
    /// Each record's checksum (over its kind, brick key and body) and its place in the index:
    /// what a damaged disk or a torn write changes, at the disk's speed.
    Checksums,
    /// Also decode each record and compare its value range with its node's (a codec fault or a
    /// skeleton that disagrees with its bricks).
    Decode,
}

/// "brick level L at [x, y, z]", or the raw key of an entry that names no brick.
fn entry_what(e: &crate::packs::Entry) -> String {
    match e.id() {
        Some(id) => format!("brick level {} at {:?}", id.level, id.coords),
        None => format!("the record under key {:02x?}", e.key),
    }
}

/// Problem messages [`Store::verify`] keeps: a database damaged throughout yields one per
/// record, so the list is capped (memory stays bounded) and the rest only counted.
const VERIFY_PROBLEMS_KEPT: usize = 200;

#[derive(Default)]
struct Problems {
    kept: Vec<String>,
    more: u64,
    /// Records read whole whose range matches their node.
    intact: u64,
}

impl Problems {
    fn push(&mut self, message: String) {
        if self.kept.len() < VERIFY_PROBLEMS_KEPT {
            self.kept.push(message);
        } else {
            self.more += 1;
        }
    }

    /// The report: the messages kept, then how many more there were; with any problem, the
    /// verdict (what could still be read, and the command that rebuilds the store).
    fn finish(mut self, path: &Path, header: &StoreHeader, seen: u64) -> VerifyReport {
        let verdict = (!self.kept.is_empty()).then(|| {
            format!(
                "{}: damaged: re-import it ({} of the {seen} brick records read could still be read intact): {}",
                path.display(),
                self.intact,
                rebuild_command(path, header)
            )
        });
        if self.more > 0 {
            self.kept.push(format!(
                "{}: ... and {} more problems",
                path.display(),
                self.more
            ));
        }
        VerifyReport {
            problems: self.kept,
            records_read: seen,
            intact: self.intact,
            verdict,
        }
    }
}

/// What [`Store::verify_report`] found.
#[derive(Clone, Debug, Default)]
pub struct VerifyReport {
    /// One message per problem (at most 200, then one saying how many more): empty when sound.
    pub problems: Vec<String>,
    /// Brick records read (each at most once).
    pub records_read: u64,
    /// Of those, read whole with their node's range.
    pub intact: u64,
    /// With any problem: "damaged: re-import" with what could still be read and the command.
    pub verdict: Option<String>,
}

/// What [`walk_records`] hands on.
enum Walked {
    /// A record by key; `Err` when reading that key failed (after the walk fell back to keys).
    Record(Vec<u8>, Result<Vec<u8>>),
    /// Iterating the tree failed: reported once, then the walk reads the rest by key.
    Failed(StorageError),
}

/// Walks every record of a bricks tree in key order and hands each to `send` (false: stop).
/// Returns the records read, `None` when `send` stopped the walk.
///
/// Bounded on any damage: sled's iterator returns the same error again and again when a page
/// is damaged (it never moves past it), so the first failure is reported once and the walk
/// goes on by key over the nodes `skeleton` says may have records, after the last key read;
/// each of those reads fails at most once. Every sled call runs inside [`contained`], so a panic
/// inside sled is a damage message, not a printed panic.
fn walk_records(
    path: &Path,
    tree: &sled::Tree,
    skeleton: &Skeleton,
    mut send: impl FnMut(Walked) -> bool,
) -> Option<usize> {
    let mut count = 0usize;
    let mut last: Option<Vec<u8>> = None;
    let mut iter = tree.iter();
    loop {
        match contained(path, "reading the brick records", || {
            iter.next().transpose()
        }) {
            Ok(None) => return Some(count),
            Ok(Some((key, record))) => {
                count += 1;
                last = Some(key.to_vec());
                if !send(Walked::Record(key.to_vec(), Ok(record.to_vec()))) {
                    return None;
                }
            }
            Err(e) => {
                if !send(Walked::Failed(e)) {
                    return None;
                }
                break;
            }
        }
    }
    drop(iter);
    for level in 0..skeleton.level_count() {
        for (id, _) in skeleton.stored_in_level_iter(level) {
            let key = brick_key(id);
            if last.as_deref().is_some_and(|l| key.as_slice() <= l) {
                continue;
            }
            let what = format!("reading brick level {} at {:?}", id.level, id.coords);
            let read = contained(path, &what, || tree.get(key));
            let item = match read {
                Ok(None) => continue,
                Ok(Some(record)) => {
                    count += 1;
                    Walked::Record(key.to_vec(), Ok(record.to_vec()))
                }
                Err(e) => Walked::Record(key.to_vec(), Err(e)),
            };
            if !send(item) {
                return None;
            }
        }
    }
    Some(count)
}

/// The records in `tree`, or the first error (never a second: sled's iterator repeats it).
fn count_records(path: &Path, tree: &sled::Tree) -> Result<usize> {
    let mut iter = tree.iter();
    let mut n = 0;
    while contained(path, "counting the brick records", || {
        iter.next().transpose()
    })?
    .is_some()
    {
        n += 1;
    }
    Ok(n)
}

/// What [`Store::verify`]'s reader thread hands on.
enum VerifyItem {
    Brick(u32, BrickId, Result<Vec<u16>>),
    /// A record whose key names no node of the octree.
    Stray(u32, Vec<u8>),
    /// Reading the records failed (sled's error).
    Failed(StorageError),
    /// All read; the number of records in every frame's tree.
    Done(Result<usize>),
}

/// Per-brick time limit of [`Store::verify`]: a brick is at most a few hundred KB; seconds mean
/// sled is stuck, not slow.
pub const VERIFY_READ_LIMIT: Duration = Duration::from_secs(20);

/// Reads, verifies and decompresses brick `id` from the bricks tree of the store at `path`.
fn read_brick_record(path: &Path, bricks: &sled::Tree, id: BrickId) -> Result<Vec<u16>> {
    let record =
        contained(path, "reading a brick", || bricks.get(brick_key(id)))?.ok_or_else(|| {
            StorageError::corrupted(
                path,
                format!("brick level {} at {:?} is missing", id.level, id.coords),
            )
        })?;
    decode_brick(id, &record).map_err(|e| brick_error(path, id, e))
}

/// sled releases its file lock from background threads a moment after the last handle drops, so
/// opening a store right after writing it can briefly find it locked. Retry for a short while
/// instead of failing; a store held by another live process still fails after the wait.
fn open_db_when_unlocked(config: sled::Config) -> sled::Result<sled::Db> {
    let deadline = std::time::Instant::now() + Duration::from_secs(3);
    loop {
        match config.open() {
            Err(sled::Error::Io(e))
                if e.to_string().contains("acquire lock")
                    && std::time::Instant::now() < deadline =>
            {
                std::thread::sleep(Duration::from_millis(20));
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
///
/// Holds the store's lock from before it touches the folder until it is dropped, so a second
/// writer (or a reader) is refused with "in use by pid N" instead of deleting this one's files.
/// A writer dropped without `finish` (an error, a cancel) removes what it wrote: a failed import
/// leaves nothing that could be taken for a store, and frees the disk it filled.
pub struct StoreWriter {
    path: PathBuf,
    records: WriterBackend,
    finished: bool,
    lock: Option<StoreLock>,
    format_version: u32,
}

/// Where a [`StoreWriter`] puts records: sled (formats 1 and 2) or packs (format 3).
enum WriterBackend {
    Sled { bricks: sled::Tree, db: SledHandles },
    Packs(PackWriter),
}

impl StoreWriter {
    /// Prepares `path` for a fresh import: deletes a previous store there (complete or not),
    /// refuses to touch a non-empty directory or file that is not a store, or a store another
    /// process holds.
    pub fn create(path: &Path, sled_cache_bytes: u64) -> Result<StoreWriter> {
        Self::create_with_format(path, sled_cache_bytes, STORE_FORMAT_VERSION)
    }

    /// [`StoreWriter::create`] for a store of format `format_version` (1 only to produce
    /// format-1 stores in tests and benchmarks; [`StoreWriter::finish`] checks the header agrees).
    pub fn create_with_format(
        path: &Path,
        sled_cache_bytes: u64,
        format_version: u32,
    ) -> Result<StoreWriter> {
        let lock = if path.exists() {
            let is_store = path.join(MARKER_FILE).is_file();
            let is_empty_dir = path.is_dir()
                && std::fs::read_dir(path)
                    .map_err(|e| StorageError::io(path, e))?
                    .all(|entry| {
                        // The lock, and a marker a killed import staged but never renamed in.
                        entry.is_ok_and(|e| {
                            e.file_name() == LOCK_FILE
                                || e.file_name().to_string_lossy() == format!("{MARKER_FILE}.new")
                        })
                    });
            if !is_store && !is_empty_dir {
                return Err(StorageError::NotAStore {
                    path: path.to_path_buf(),
                    message: "refusing to overwrite a file or non-empty directory that is not a Strata store".into(),
                });
            }
            let lock = StoreLock::acquire(path, LockPurpose::Import)?;
            // The marker first says "incomplete" (renamed in whole), then the rest goes: a kill
            // midway leaves an incomplete store, refused as such and replaced by the next
            // import. (Removing the marker among the rest once left, killed midway, a folder
            // with index and packs but no marker: not a store, which no import would replace.)
            if is_store {
                write_incomplete_marker(path, format_version)?;
            }
            remove_all_but_lock_and_marker(path)?;
            lock
        } else {
            std::fs::create_dir_all(path).map_err(|e| StorageError::io(path, e))?;
            StoreLock::acquire(path, LockPurpose::Import)?
        };
        write_incomplete_marker(path, format_version)?;
        if format_version >= 3 {
            return Ok(StoreWriter {
                path: path.to_path_buf(),
                records: WriterBackend::Packs(PackWriter::create(path)?),
                finished: false,
                lock: Some(lock),
                format_version,
            });
        }
        let config = sled::Config::new()
            .path(path.join(DB_DIR))
            .cache_capacity(sled_cache_bytes)
            .mode(sled::Mode::HighThroughput);
        let db = contained(path, "creating the database", || {
            open_db_when_unlocked(config)
        })?;
        let bricks = contained(path, "creating the bricks", || db.open_tree("bricks"))?;
        Ok(StoreWriter {
            path: path.to_path_buf(),
            records: WriterBackend::Sled {
                db: SledHandles::new(path, db, vec![bricks.clone()]),
                bricks,
            },
            finished: false,
            lock: Some(lock),
            format_version,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// A record written earlier (by [`StoreWriter::put_bricks`]), for a writer that builds
    /// coarser levels from the finer ones it wrote.
    pub fn read_brick_record(&self, id: BrickId) -> Result<Option<Vec<u8>>> {
        match &self.records {
            WriterBackend::Sled { bricks, .. } => {
                Ok(
                    contained(&self.path, "reading a brick", || bricks.get(brick_key(id)))?
                        .map(|r| r.to_vec()),
                )
            }
            WriterBackend::Packs(packs) => packs.read_back(0, id),
        }
    }

    /// Whether [`StoreWriter::put_brick`] may be called from many threads at once with no
    /// batching (format 3); sled stores want ordered batches from one thread.
    pub fn writes_in_parallel(&self) -> bool {
        matches!(self.records, WriterBackend::Packs(_))
    }

    /// Writes one brick record; in format 3 from any thread, appended to a pack with `pwrite`.
    pub fn put_brick(&self, id: BrickId, record: &[u8]) -> Result<()> {
        match &self.records {
            WriterBackend::Packs(packs) => packs.append(0, id, 1, record),
            WriterBackend::Sled { .. } => self.put_bricks(vec![(id, record.to_vec())]),
        }
    }

    /// [`StoreWriter::put_brick`] of a record that is version `version` of its brick (format
    /// 3; compaction keeps each record's version). Formats 1-2 keep no versions.
    pub fn put_brick_version(&self, id: BrickId, version: u32, record: &[u8]) -> Result<()> {
        match &self.records {
            WriterBackend::Packs(packs) => packs.append(0, id, version, record),
            WriterBackend::Sled { .. } => self.put_bricks(vec![(id, record.to_vec())]),
        }
    }

    /// [`StoreWriter::put_brick_version`] into frame `frame` of a 4-D store (format 3; finish
    /// it with [`StoreWriter::finish_frames`]).
    pub fn put_frame_brick_version(
        &self,
        frame: u32,
        id: BrickId,
        version: u32,
        record: &[u8],
    ) -> Result<()> {
        match &self.records {
            WriterBackend::Packs(packs) => packs.append(frame, id, version, record),
            WriterBackend::Sled { .. } if frame == 0 => {
                self.put_bricks(vec![(id, record.to_vec())])
            }
            WriterBackend::Sled { .. } => Err(StorageError::invalid(
                &self.path,
                "frames after the first are written to format-2 stores by copying frame stores in",
            )),
        }
    }

    /// Writes bricks in one sled batch (give them in key order); appends them in format 3.
    pub fn put_bricks(&self, records: Vec<(BrickId, Vec<u8>)>) -> Result<()> {
        let bricks = match &self.records {
            WriterBackend::Sled { bricks, .. } => bricks,
            WriterBackend::Packs(packs) => {
                for (id, record) in records {
                    packs.append(0, id, 1, &record)?;
                }
                return Ok(());
            }
        };
        let mut batch = sled::Batch::default();
        for (id, record) in records {
            batch.insert(&brick_key(id)[..], record);
        }
        contained(&self.path, "writing bricks", || bricks.apply_batch(batch))
    }

    /// Writes the metadata, flushes everything, then marks the store complete and flushes again:
    /// a crash at any point before the last flush leaves a store that opens as incomplete. Every
    /// flush is bounded: a disk that fills up is an error, never a wait.
    pub fn finish(
        self,
        header: &StoreHeader,
        skeleton: &Skeleton,
        histogram: &Histogram,
        stats: &StoreStats,
    ) -> Result<()> {
        self.finish_frames(header, skeleton, histogram, stats, &[])
    }

    /// [`StoreWriter::finish`] of a 4-D store of format 3: `later_skeletons` are frames 1..'s
    /// (the header names `1 + later_skeletons.len()` frames).
    pub fn finish_frames(
        mut self,
        header: &StoreHeader,
        skeleton: &Skeleton,
        histogram: &Histogram,
        stats: &StoreStats,
        later_skeletons: &[Skeleton],
    ) -> Result<()> {
        let path = self.path.clone();
        let path = &path;
        if header.format_version != self.format_version {
            return Err(StorageError::invalid(
                path,
                format!(
                    "header of format {} for a store created as format {}",
                    header.format_version, self.format_version
                ),
            ));
        }
        check_format(path, header)?;
        if header.frames as usize != later_skeletons.len() + 1 {
            return Err(StorageError::invalid(
                path,
                format!(
                    "a header of {} frames finishing a store with {} skeletons",
                    header.frames,
                    later_skeletons.len() + 1
                ),
            ));
        }
        let db = match &self.records {
            WriterBackend::Sled { .. } if !later_skeletons.is_empty() => {
                return Err(StorageError::invalid(
                    path,
                    "frames after the first are written to format-2 stores by copying frame stores in",
                ))
            }
            WriterBackend::Sled { db, .. } => db,
            WriterBackend::Packs(packs) => {
                let json = |v: &dyn erased::Json| {
                    v.json().map_err(|e| {
                        StorageError::invalid(path, format!("encoding the header: {e}"))
                    })
                };
                packs.finish(&crate::packs::IndexDocs {
                    header: json(header)?,
                    skeleton: encode_skeleton_for(header, skeleton),
                    histogram: json(histogram)?,
                    stats: json(stats)?,
                    frame_skeletons: later_skeletons
                        .iter()
                        .map(|s| encode_skeleton_for(header, s))
                        .collect(),
                })?;
                return self.write_complete_marker();
            }
        };
        let meta = contained(path, "creating the metadata", || db.open_tree("meta"))?;
        let to_json = |v: &dyn erased::Json| {
            v.json()
                .map_err(|e| StorageError::invalid(path, format!("encoding the header: {e}")))
        };
        let put = |key: &[u8], value: Vec<u8>| {
            contained(path, "writing the metadata", || meta.insert(key, value)).map(|_| ())
        };
        put(KEY_HEADER, to_json(header)?)?;
        put(KEY_SKELETON, encode_skeleton_for(header, skeleton))?;
        put(KEY_HISTOGRAM, to_json(histogram)?)?;
        put(KEY_STATS, to_json(stats)?)?;
        db.flush(FLUSH_LIMIT)?;
        put(KEY_COMPLETE, b"1".to_vec())?;
        db.flush(FLUSH_LIMIT)?;
        drop(meta);
        self.write_complete_marker()
    }

    /// The marker's `complete` line, renamed into place last (and, in format 3, the folder
    /// fsync'd after it: the store is complete once this returns).
    fn write_complete_marker(&mut self) -> Result<()> {
        // Beside the database, so that damage which loses the database's records can be told
        // from an import that never finished. Written by rename: whole or not at all.
        let marker = self.path.join(MARKER_FILE);
        let staged = self.path.join(format!("{MARKER_FILE}.new"));
        std::fs::write(
            &staged,
            format!(
                "strata store format {}\n{MARKER_COMPLETE_LINE}\n",
                self.format_version
            ),
        )
        .and_then(|()| std::fs::File::open(&staged)?.sync_all())
        .and_then(|()| std::fs::rename(&staged, &marker))
        .map_err(|e| StorageError::io(&marker, e))?;
        if self.format_version >= 3 {
            crate::packs::sync_dir(&self.path)?;
        }
        self.finished = true;
        Ok(())
    }
}

impl Drop for StoreWriter {
    fn drop(&mut self) {
        if self.finished {
            return;
        }
        // Close sled first (bounded: after a full disk its close never returns), then remove the
        // partial store while still holding the lock, then the folder with its lock file.
        if let WriterBackend::Sled { db, .. } = &mut self.records {
            drop(std::mem::replace(db, SledHandles::closed(&self.path)));
        }
        self.remove_partial();
    }
}

impl StoreWriter {
    /// Removes a partial store while still holding the lock, then the folder with its lock file.
    fn remove_partial(&mut self) {
        let _ = remove_all_but_lock_and_marker(&self.path);
        let lock = self.lock.take();
        let _ = std::fs::remove_dir_all(&self.path);
        drop(lock);
    }
}

/// Writes the marker of an incomplete store of format `format_version` by rename: a kill never
/// leaves it empty or half written (which would read as a damaged store, not an incomplete one).
fn write_incomplete_marker(path: &Path, format_version: u32) -> Result<()> {
    let marker = path.join(MARKER_FILE);
    let staged = path.join(format!("{MARKER_FILE}.new"));
    std::fs::write(&staged, format!("strata store format {format_version}\n"))
        .and_then(|()| std::fs::rename(&staged, &marker))
        .map_err(|e| StorageError::io(&marker, e))
}

/// Deletes every entry of a store folder except its lock file (which a waiting process may be
/// about to lock) and its marker (which, saying "incomplete", keeps the folder a store that the
/// next import replaces while the rest goes).
fn remove_all_but_lock_and_marker(path: &Path) -> Result<()> {
    for entry in std::fs::read_dir(path).map_err(|e| StorageError::io(path, e))? {
        let entry = entry.map_err(|e| StorageError::io(path, e))?;
        if entry.file_name() == LOCK_FILE || entry.file_name() == MARKER_FILE {
            continue;
        }
        let p = entry.path();
        let removed = if entry.file_type().is_ok_and(|t| t.is_dir()) {
            std::fs::remove_dir_all(&p)
        } else {
            std::fs::remove_file(&p)
        };
        removed.map_err(|e| StorageError::io(&p, e))?;
    }
    Ok(())
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

/// Converts the format-2 store at `path` to format 3, atomically: the new store is written
/// beside it (`NAME.upgrading`), opened and verified; only then is the old one renamed away
/// (`NAME.format2-old`), the new one renamed to `path`, and the old one removed. A crash before
/// the first rename leaves the old store as it was (and an incomplete `NAME.upgrading`, which
/// the next upgrade replaces); between the two renames both stores are kept under their
/// suffixed names. Returns the verified store's problems-free report.
pub fn upgrade_store(path: &Path) -> Result<VerifyReport> {
    if std::fs::symlink_metadata(path.join(MARKER_FILE)).is_err() {
        return Err(StorageError::NotAStore {
            path: path.to_path_buf(),
            message: format!("no {MARKER_FILE} marker"),
        });
    }
    if read_marker(path)?.format >= 3 {
        return Err(StorageError::invalid(path, "already a format-3 store"));
    }
    // sled writes whenever it opens a database, and a process killed inside those writes can
    // leave the database damaged (the upgrade's crash fuzz: killed 9 ms in, the original no
    // longer opened). So the original is never opened here: a copy of it is, and only the
    // copy is written; the original is read by the copy alone, under a reader's lock.
    let source = sibling(path, "upgrade-source")?;
    let _ = std::fs::remove_dir_all(&source);
    {
        let _no_writer = StoreLock::acquire(path, LockPurpose::Read)?;
        copy_store_files(path, &source)?;
    }
    let upgraded = upgrade_from_copy(path, &source);
    let _ = std::fs::remove_dir_all(&source);
    upgraded
}

/// Copies a store's folder; its marker last, so a copy cut short is not a store at all.
fn copy_store_files(from: &Path, to: &Path) -> Result<()> {
    copy_tree(from, to, Some(MARKER_FILE))?;
    std::fs::copy(from.join(MARKER_FILE), to.join(MARKER_FILE))
        .map_err(|e| StorageError::io(from.join(MARKER_FILE), e))?;
    Ok(())
}

fn copy_tree(from: &Path, to: &Path, skip: Option<&str>) -> Result<()> {
    std::fs::create_dir_all(to).map_err(|e| StorageError::io(to, e))?;
    for entry in std::fs::read_dir(from).map_err(|e| StorageError::io(from, e))? {
        let entry = entry.map_err(|e| StorageError::io(from, e))?;
        let name = entry.file_name();
        if skip.is_some_and(|s| name == s) {
            continue;
        }
        let kind = entry
            .file_type()
            .map_err(|e| StorageError::io(entry.path(), e))?;
        let target = to.join(&name);
        if kind.is_dir() {
            copy_tree(&entry.path(), &target, None)?;
        } else if kind.is_file() {
            std::fs::copy(entry.path(), &target).map_err(|e| StorageError::io(entry.path(), e))?;
        } else {
            return Err(StorageError::corrupted(
                from,
                format!(
                    "{} is not a regular file or folder; re-import the store",
                    entry.path().display()
                ),
            ));
        }
    }
    Ok(())
}

/// [`upgrade_store`] from `source`, a copy of the store at `path`.
fn upgrade_from_copy(path: &Path, source: &Path) -> Result<VerifyReport> {
    let old = Store::open(source)?;
    let (trees, version) = match &old.backend {
        Backend::Sled {
            bricks,
            later_trees,
            ..
        } => (
            std::iter::once(bricks.clone())
                .chain(later_trees.iter().cloned())
                .collect::<Vec<sled::Tree>>(),
            old.header.format_version,
        ),
        Backend::Packs { .. } => {
            return Err(StorageError::invalid(path, "already a format-3 store"))
        }
    };
    if version != 2 {
        return Err(StorageError::Unsupported {
            path: path.to_path_buf(),
            message: format!(
                "upgrading a format-{version} store: only format-2 stores are upgraded; re-import it: {}",
                rebuild_command(path, &old.header)
            ),
        });
    }
    let staged = sibling(path, "upgrading")?;
    let parked = sibling(path, "format2-old")?;
    if parked.exists() {
        return Err(StorageError::invalid(
            &parked,
            "an earlier upgrade's old store is still here; remove it or move it away first",
        ));
    }
    let writer = StoreWriter::create_with_format(&staged, 0, 3)?;
    // Every frame's records (a 4-D store keeps frame f's in its own tree), each version 1.
    for (frame, bricks) in (0u32..).zip(&trees) {
        for entry in bricks.iter() {
            let (key, record) = contained(path, "reading the brick records", || entry)?;
            let id = brick_id_from_key(&key).ok_or_else(|| {
                StorageError::corrupted(
                    path,
                    format!("frame {frame}: a brick record under key {key:02x?}"),
                )
            })?;
            writer.put_frame_brick_version(frame, id, 1, &record)?;
        }
    }
    let mut header = old.header.clone();
    header.format_version = 3;
    writer.finish_frames(
        &header,
        &old.skeleton,
        &old.histogram,
        &old.stats,
        &old.later_skeletons,
    )?;
    drop(trees);
    old.close()?;
    let report = Store::open(&staged)?.verify_report(|_, _| {})?;
    if !report.problems.is_empty() {
        let _ = std::fs::remove_dir_all(&staged);
        return Err(StorageError::corrupted(
            path,
            format!(
                "the upgraded copy did not verify (the old store is kept): {}",
                report.problems.join("; ")
            ),
        ));
    }
    swap_in(path, &staged, &parked)?;
    Ok(report)
}

/// Replaces the store at `path` by the verified, complete store at `staged`: `path` renamed to
/// `parked`, `staged` to `path`, the parent folder fsync'd, `parked` removed. Taken under the
/// old store's exclusive lock, so no reader holds it while it moves (one that comes later finds
/// the new store). A crash before the first rename leaves the old store; between the renames
/// both stores are kept, complete, under their suffixed names; after the second, the new one.
fn swap_in(path: &Path, staged: &Path, parked: &Path) -> Result<()> {
    let lock = match StoreLock::acquire(path, LockPurpose::Import) {
        Ok(lock) => lock,
        Err(e) => {
            // Nothing moved: the verified copy goes, the store stays as it was.
            let _ = std::fs::remove_dir_all(staged);
            return Err(e);
        }
    };
    std::fs::rename(path, parked).map_err(|e| StorageError::io(path, e))?;
    std::fs::rename(staged, path).map_err(|e| StorageError::io(staged, e))?;
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        crate::packs::sync_dir(parent)?;
    }
    drop(lock);
    std::fs::remove_dir_all(parked).map_err(|e| StorageError::io(parked, e))
}

/// `NAME.suffix` beside the store at `path`.
fn sibling(path: &Path, suffix: &str) -> Result<PathBuf> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| StorageError::invalid(path, "a store path without a name"))?;
    Ok(path.with_file_name(format!("{name}.{suffix}")))
}

/// Checks that `path` is a complete format-3 store and takes, in order, its shared lock (no
/// import replaces it meanwhile) and its write lock (no other writer of versions).
fn hold_for_writing(path: &Path) -> Result<(Option<SharedStoreLock>, crate::packs::WriteLock)> {
    let marker = read_marker(path)?;
    if marker.format < 3 {
        return Err(StorageError::Unsupported {
            path: path.to_path_buf(),
            message: format!(
                "a format-{} store: new brick versions and compaction need format 3 (strata store upgrade)",
                marker.format
            ),
        });
    }
    let shared = SharedStoreLock::acquire(path)?;
    if !marker.complete {
        return Err(StorageError::IncompleteImport {
            path: path.to_path_buf(),
        });
    }
    let write = crate::packs::WriteLock::acquire(path)?;
    Ok((shared, write))
}

/// Appends new versions of brick records to the complete format-3 store at `path` (a label
/// edit, for one): each record is checked (its checksum, its brick inside the octree), written
/// to a new pack, and the index replaced atomically so that it points every given brick at the
/// given record; the superseded records stay in their packs until [`compact_store`].
///
/// Writers exclude each other (the store's write lock, [`StorageError::InUse`] for a second
/// one) and an import cannot replace the store meanwhile; readers are not excluded: one that
/// opened before keeps reading the old versions, one that opens after reads the new. A SIGKILL
/// or power loss at any moment leaves the old or the new index, each complete and naming only
/// fsync'd bytes (the write order is argued in `packs::append_versions`).
///
/// Each record is decoded for its value range: its node in the skeleton takes that range and
/// every ancestor's widens to include it (`Skeleton::record_edit`), so culling by range never
/// hides an edited brick; the new skeleton is committed with the index. An ancestor's own
/// record is not rewritten, so its range in the skeleton may now bound its voxels loosely
/// (`strata verify --decode` accepts a range containing the record's above a brick whose
/// version is past 1). The histogram follows the level-0 voxels an edit changes (the values a
/// level-0 record overwrites leave it, its new ones enter, see `Histogram::replace_values`);
/// the statistics are kept as imported. In a store whose
/// skeleton implies constant bricks without records (`sparse-skeleton`), an edit that would
/// make such a node vary (an ancestor inside a constant subtree) is refused unless a record of
/// that node comes in the same call, since a varying node is read, not implied.
pub fn append_brick_versions(path: &Path, records: &[(BrickId, Vec<u8>)]) -> Result<()> {
    let (_shared, _write) = hold_for_writing(path)?;
    let index = crate::packs::read_index(path)?;
    let marker = read_marker(path)?;
    let docs = &index.docs;
    let (header, mut skeleton, ..) = parse_documents(
        path,
        &marker,
        &docs.header,
        &docs.skeleton,
        &docs.histogram,
        &docs.stats,
    )?;
    let mut versions = Vec::with_capacity(records.len());
    // The level-0 voxels each edit overwrites, for the histogram: read from the store as it is
    // (a brick given twice in one call replaces its first new voxels).
    let current = Store::open(path)?;
    let mut histogram = current.histogram().clone();
    let mut level0_now: std::collections::HashMap<BrickId, Vec<u16>> =
        std::collections::HashMap::new();
    // Coarser bricks first: a brick edited with its ancestor in one call widens the ancestor's
    // new range, not the other way round.
    let mut coarse_first: Vec<&(BrickId, Vec<u8>)> = records.iter().collect();
    coarse_first.sort_by_key(|(id, _)| std::cmp::Reverse(id.level));
    for (id, record) in coarse_first {
        if !header.layout.contains(*id) {
            return Err(StorageError::invalid(
                path,
                format!("brick {id:?} is outside the octree"),
            ));
        }
        crate::brick::verify_record(*id, record).map_err(|e| {
            StorageError::invalid(
                path,
                format!(
                    "a new version of brick level {} at {:?} is not a valid record: {e}",
                    id.level, id.coords
                ),
            )
        })?;
        let voxels = decode_brick(*id, record).map_err(|e| {
            StorageError::invalid(
                path,
                format!(
                    "a new version of brick level {} at {:?} does not decode: {e}",
                    id.level, id.coords
                ),
            )
        })?;
        if id.level == 0 {
            let old = match level0_now.remove(id) {
                Some(v) => v,
                None => current.read_brick(*id)?,
            };
            let physical = |v: &[u16]| -> Vec<f64> {
                core_voxels(&header.layout, *id, v)
                    .map(|s| header.value_mapping.physical(s))
                    .collect()
            };
            histogram.replace_values(&physical(&old), &physical(&voxels));
            level0_now.insert(*id, voxels.clone());
        }
        let range = crate::brick::value_range(&voxels);
        skeleton
            .record_edit(*id, range.min, range.max)
            .ok_or_else(|| {
                StorageError::invalid(
                    path,
                    format!(
                        "brick level {} at {:?} has no node in the skeleton",
                        id.level, id.coords
                    ),
                )
            })?;
        versions.push((0u32, *id, record.clone()));
    }
    // A node an edit makes vary must have a record to read (a sparse skeleton's constant nodes
    // may have none, and a widened ancestor is read, not answered from the skeleton).
    for (id, _) in records {
        let mut at = Some(*id);
        while let Some(node_id) = at {
            let varies = skeleton.node(node_id).is_some_and(|n| !n.is_constant());
            let key = brick_key(node_id);
            let has_record = index
                .entries
                .binary_search_by(|e| (e.frame, e.key).cmp(&(0, key)))
                .is_ok()
                || records.iter().any(|(r, _)| *r == node_id);
            if varies && !has_record {
                return Err(StorageError::invalid(
                    path,
                    format!(
                        "the edit of brick level {} at {:?} makes brick level {} at {:?} vary, and it has no record (its constant subtree was implied): append a version of it too",
                        id.level, id.coords, node_id.level, node_id.coords
                    ),
                ));
            }
            at = (usize::from(node_id.level) + 1 < header.layout.level_count())
                .then(|| BrickId::new(node_id.level + 1, node_id.coords.map(|c| c / 2)));
        }
    }
    drop(current);
    let docs = crate::packs::IndexDocs {
        header: docs.header.clone(),
        skeleton: encode_skeleton_for(&header, &skeleton),
        histogram: serde_json::to_vec(&histogram)
            .map_err(|e| StorageError::invalid(path, format!("encoding the histogram: {e}")))?,
        stats: docs.stats.clone(),
        frame_skeletons: docs.frame_skeletons.clone(),
    };
    crate::packs::append_versions(
        path,
        &index,
        &docs,
        &versions,
        crate::packs::PACK_LIMIT_BYTES,
    )
}

/// The voxels of level-0 brick `id`'s payload `voxels` that lie inside the volume (its core,
/// cut at the volume's far faces; the apron and the padding past the volume are not voxels of
/// their own).
fn core_voxels<'a>(
    layout: &OctreeLayout,
    id: BrickId,
    voxels: &'a [u16],
) -> impl Iterator<Item = u16> + 'a {
    use strata_types::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
    let dims = layout.level_dims.first().copied().unwrap_or_default();
    let extent: [u32; 3] = std::array::from_fn(|a| {
        dims[a]
            .saturating_sub(id.coords[a] * BRICK_CORE)
            .min(BRICK_CORE)
    });
    let (p, a) = (BRICK_PAYLOAD as usize, BRICK_APRON as usize);
    (0..extent[2] as usize).flat_map(move |k| {
        (0..extent[1] as usize).flat_map(move |j| {
            (0..extent[0] as usize)
                .filter_map(move |i| voxels.get((i + a) + p * ((j + a) + p * (k + a))).copied())
        })
    })
}

/// What [`compact_store`] did.
#[derive(Clone, Debug)]
pub struct CompactReport {
    /// Records kept (the newest version of each brick).
    pub records: u64,
    /// Pack bytes before and after.
    pub bytes_before: u64,
    pub bytes_after: u64,
}

/// Rewrites the format-3 store at `path` without superseded record versions, atomically: the
/// newest record of each brick is copied into a new store beside it (`NAME.compacting`), which
/// is finished (packs fsync'd, index, marker), opened and verified; only then is it swapped in
/// as [`upgrade_store`] does (the old store renamed to `NAME.compact-old`, the new one to
/// `path`, the old one removed). A SIGKILL or power loss before the first rename leaves the old
/// store untouched (and an incomplete `NAME.compacting`, refused as incomplete, which the next
/// compaction replaces); between the renames both complete stores are kept under their suffixed
/// names; after the second, the compacted store. The write lock is held throughout, so no new
/// version is appended to the old store and lost; the swap needs the store free of readers.
pub fn compact_store(path: &Path) -> Result<CompactReport> {
    let (shared, write) = hold_for_writing(path)?;
    let staged = sibling(path, "compacting")?;
    let parked = sibling(path, "compact-old")?;
    if parked.exists() {
        return Err(StorageError::invalid(
            &parked,
            "an earlier compaction's old store is still here; remove it or move it away first",
        ));
    }
    let store = Store::open(path)?;
    let Backend::Packs { packs, .. } = &store.backend else {
        return Err(StorageError::invalid(path, "not a format-3 store"));
    };
    let bytes_before = packs.total_bytes();
    let writer = StoreWriter::create_with_format(&staged, 0, 3)?;
    let mut records = 0u64;
    for e in packs.entries() {
        let (Some(id), Some(record)) = (e.id(), packs.slice(e)) else {
            return Err(StorageError::corrupted(
                path,
                format!("its index holds a bad entry under key {:02x?}", e.key),
            ));
        };
        writer.put_frame_brick_version(e.frame, id, e.version, record)?;
        records += 1;
    }
    writer.finish_frames(
        &store.header,
        &store.skeleton,
        &store.histogram,
        &store.stats,
        &store.later_skeletons,
    )?;
    drop(store);
    let compacted = Store::open(&staged)?;
    let report = compacted.verify_report(|_, _| {})?;
    let bytes_after = match &compacted.backend {
        Backend::Packs { packs, .. } => packs.total_bytes(),
        Backend::Sled { .. } => 0,
    };
    drop(compacted);
    if !report.problems.is_empty() {
        let _ = std::fs::remove_dir_all(&staged);
        return Err(StorageError::corrupted(
            path,
            format!(
                "the compacted copy did not verify (the store is kept as it was): {}",
                report.problems.join("; ")
            ),
        ));
    }
    drop(shared);
    swap_in(path, &staged, &parked)?;
    drop(write);
    Ok(CompactReport {
        records,
        bytes_before,
        bytes_after,
    })
}
