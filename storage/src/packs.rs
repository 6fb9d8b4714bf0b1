//! Format 3's brick container: records appended to pack files, found through one sorted,
//! checksummed, read-only index file written last.
//!
//! A store of format 3 is a folder of
//! - `STRATA-STORE`: the marker, `strata store format 3`, and the `complete` line renamed in last;
//! - `packs/pack-NNNNN.pack`: brick records exactly as format 2 stores them (kind, xxh3, body),
//!   back to back, each pack at most [`PACK_LIMIT_BYTES`] (one larger record gets a pack alone);
//! - `index.v3`: [`INDEX_MAGIC`], the header, skeleton, histogram and statistics, each pack's
//!   length, the entries (frame, brick key, pack, offset, length, record version) sorted by frame
//!   and key, and an xxh3-64 of all of it. A 4-D store's index ([`INDEX_MAGIC_FRAMES`]) also
//!   holds the skeleton of each frame after the first, after the statistics; a single volume's
//!   keeps [`INDEX_MAGIC`], so builds that predate frames in format 3 still read it. An import writes version 1 of every record; each
//!   append of a brick's new record ([`append_versions`]) gives it the next version, and
//!   compaction keeps them. Indexes written before versions were recorded
//!   ([`INDEX_MAGIC_UNVERSIONED`], entries without the field) read every record as version 1.
//!   Written to `index.v3.new`, fsync'd, renamed, after every pack is fsync'd: an index names
//!   only bytes already on disk.
//!
//! **Writing.** Every import worker appends its own records: it reserves the bytes with an atomic
//! add on the current pack's end and writes them with `pwrite`, so no writer thread or lock is
//! on the hot path (a lock is taken only to start the next pack, once per GiB, and to note the
//! entry). A crash before the index is renamed leaves a store without index and marker line:
//! incomplete, refused as such.
//!
//! **Reading.** Opening writes nothing: the index is read, the packs are mapped (memmap2) and a
//! record is a slice of its pack's map. Mapped bytes that vanish under a reader raise SIGBUS;
//! that cannot happen here because a pack is immutable once its store is complete (writers
//! create packs with `create_new` in a folder they hold exclusively, never reopen, truncate or
//! rewrite one; replacing a store removes its files, and an unlinked file stays mapped whole),
//! a writer's exclusive lock excludes the shared lock every reader holds, and each pack's
//! length is checked against the file (`fstat` on the open descriptor) before it is mapped,
//! and every entry against its pack's indexed length.

use std::collections::HashMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use crate::brick::brick_key;
use crate::error::{Result, StorageError};
use crate::octree::BrickId;

pub(crate) const PACKS_DIR: &str = "packs";
pub(crate) const INDEX_FILE: &str = "index.v3";
/// The largest a pack grows before the next one is started.
pub const PACK_LIMIT_BYTES: u64 = 1 << 30;
pub(crate) const INDEX_MAGIC: &[u8; 16] = b"STRATA-IDX-v3.1\n";
/// The magic of an index that carries frames 1..'s skeletons (a 4-D store); otherwise as
/// [`INDEX_MAGIC`].
pub(crate) const INDEX_MAGIC_FRAMES: &[u8; 16] = b"STRATA-IDX-v3.2\n";
/// The magic of the first format-3 indexes, whose entries carry no record version.
pub(crate) const INDEX_MAGIC_UNVERSIONED: &[u8; 16] = b"STRATA-INDEX-v3\n";
/// Bytes of one index entry: frame u32, key 13, pack u32, offset u64, length u32, version u32.
const ENTRY_BYTES: usize = 4 + 13 + 4 + 8 + 4 + 4;
/// Bytes of one entry of an [`INDEX_MAGIC_UNVERSIONED`] index (no version).
const ENTRY_BYTES_UNVERSIONED: usize = ENTRY_BYTES - 4;
/// An index is entries of a few dozen bytes and a skeleton: a larger file is not one.
const INDEX_MAX_BYTES: u64 = 4 << 30;

pub(crate) fn pack_name(pack: u32) -> String {
    format!("pack-{pack:05}.pack")
}

pub(crate) fn pack_path(store: &Path, pack: u32) -> PathBuf {
    store.join(PACKS_DIR).join(pack_name(pack))
}

fn describe(id: BrickId) -> String {
    format!("brick level {} at {:?}", id.level, id.coords)
}

/// Where one record lies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Entry {
    pub frame: u32,
    pub key: [u8; 13],
    pub pack: u32,
    pub offset: u64,
    pub len: u32,
    /// 1 for the record an import wrote, one more for each new record appended since.
    pub version: u32,
}

impl Entry {
    pub fn id(&self) -> Option<BrickId> {
        crate::brick::brick_id_from_key(&self.key)
    }
    fn what(&self) -> String {
        match self.id() {
            Some(id) => describe(id),
            None => format!("the record under key {:02x?}", self.key),
        }
    }
}

/// The metadata documents an index carries, encoded.
pub(crate) struct IndexDocs {
    pub header: Vec<u8>,
    pub skeleton: Vec<u8>,
    pub histogram: Vec<u8>,
    pub stats: Vec<u8>,
    /// Frames 1..'s skeletons, encoded (empty for a single volume).
    pub frame_skeletons: Vec<Vec<u8>>,
}

struct ActivePack {
    id: u32,
    file: File,
    /// Reserved end: the next record's offset.
    next: AtomicU64,
    /// Largest end written.
    end: AtomicU64,
}

/// Appends records to packs from many threads at once (see the module's documentation).
pub(crate) struct PackWriter {
    store: PathBuf,
    limit: u64,
    current: RwLock<Arc<ActivePack>>,
    packs: Mutex<Vec<Arc<ActivePack>>>,
    entries: Mutex<HashMap<(u32, [u8; 13]), Entry>>,
}

fn poisoned(store: &Path) -> StorageError {
    StorageError::invalid(store, "a pack writer thread panicked")
}

impl PackWriter {
    pub fn create(store: &Path) -> Result<PackWriter> {
        Self::with_limit(store, PACK_LIMIT_BYTES)
    }

    pub fn with_limit(store: &Path, limit: u64) -> Result<PackWriter> {
        let dir = store.join(PACKS_DIR);
        std::fs::create_dir(&dir).map_err(|e| StorageError::io(&dir, e))?;
        let first = Arc::new(Self::new_pack(store, 0)?);
        Ok(PackWriter {
            store: store.to_path_buf(),
            limit: limit.max(1),
            current: RwLock::new(first.clone()),
            packs: Mutex::new(vec![first]),
            entries: Mutex::new(HashMap::new()),
        })
    }

    fn new_pack(store: &Path, id: u32) -> Result<ActivePack> {
        let path = pack_path(store, id);
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| StorageError::io(&path, e))?;
        Ok(ActivePack {
            id,
            file,
            next: AtomicU64::new(0),
            end: AtomicU64::new(0),
        })
    }

    /// Appends one record of frame `frame` (a later one for the same brick supersedes it).
    /// Appends `record` as version `version` of brick `id` in frame `frame`.
    pub fn append(&self, frame: u32, id: BrickId, version: u32, record: &[u8]) -> Result<()> {
        use std::os::unix::fs::FileExt;
        let len = record.len() as u64;
        let len32 = u32::try_from(record.len()).map_err(|_| {
            StorageError::invalid(&self.store, format!("{}: record too large", describe(id)))
        })?;
        loop {
            let pack = self
                .current
                .read()
                .map_err(|_| poisoned(&self.store))?
                .clone();
            let offset = pack.next.fetch_add(len, Ordering::SeqCst);
            if offset + len <= self.limit || offset == 0 {
                let path = pack_path(&self.store, pack.id);
                pack.file
                    .write_all_at(record, offset)
                    .map_err(|e| write_error(&path, id, e))?;
                pack.end.fetch_max(offset + len, Ordering::SeqCst);
                let key = brick_key(id);
                self.entries
                    .lock()
                    .map_err(|_| poisoned(&self.store))?
                    .insert(
                        (frame, key),
                        Entry {
                            frame,
                            key,
                            pack: pack.id,
                            offset,
                            len: len32,
                            version,
                        },
                    );
                return Ok(());
            }
            // This pack is full: the first thread to see it starts the next one.
            let mut current = self.current.write().map_err(|_| poisoned(&self.store))?;
            if current.id == pack.id {
                let next = Arc::new(Self::new_pack(&self.store, pack.id + 1)?);
                self.packs
                    .lock()
                    .map_err(|_| poisoned(&self.store))?
                    .push(next.clone());
                *current = next;
            }
        }
    }

    /// A record appended earlier, read back (for writers that build coarser levels from it).
    pub fn read_back(&self, frame: u32, id: BrickId) -> Result<Option<Vec<u8>>> {
        use std::os::unix::fs::FileExt;
        let entry = self
            .entries
            .lock()
            .map_err(|_| poisoned(&self.store))?
            .get(&(frame, brick_key(id)))
            .copied();
        let Some(entry) = entry else { return Ok(None) };
        let pack = self
            .packs
            .lock()
            .map_err(|_| poisoned(&self.store))?
            .get(entry.pack as usize)
            .cloned()
            .ok_or_else(|| poisoned(&self.store))?;
        let mut out = vec![0u8; entry.len as usize];
        pack.file
            .read_exact_at(&mut out, entry.offset)
            .map_err(|e| StorageError::io(pack_path(&self.store, entry.pack), e))?;
        Ok(Some(out))
    }

    /// fsyncs every pack and the packs folder, then writes the index (fsync'd, renamed into
    /// place, folder fsync'd). The store is complete only when the caller's marker follows.
    pub fn finish(&self, docs: &IndexDocs) -> Result<()> {
        let packs = self.packs.lock().map_err(|_| poisoned(&self.store))?;
        let mut lengths = Vec::with_capacity(packs.len());
        for pack in packs.iter() {
            let path = pack_path(&self.store, pack.id);
            pack.file
                .sync_all()
                .map_err(|e| StorageError::io(&path, e))?;
            lengths.push(pack.end.load(Ordering::SeqCst));
        }
        sync_dir(&self.store.join(PACKS_DIR))?;
        let mut entries: Vec<Entry> = self
            .entries
            .lock()
            .map_err(|_| poisoned(&self.store))?
            .values()
            .copied()
            .collect();
        entries.sort_by_key(|e| (e.frame, e.key));
        let bytes = encode_index(docs, &lengths, &entries);
        let index = self.store.join(INDEX_FILE);
        let staged = self.store.join(format!("{INDEX_FILE}.new"));
        write_synced(&staged, &bytes)?;
        std::fs::rename(&staged, &index).map_err(|e| StorageError::io(&index, e))?;
        sync_dir(&self.store)
    }
}

/// A failed pack write: a full disk (or file-size limit) said as such, naming the brick.
fn write_error(path: &Path, id: BrickId, e: std::io::Error) -> StorageError {
    if crate::error::is_disk_full(&e) {
        StorageError::DiskFull {
            path: path.to_path_buf(),
            message: format!(
                "the disk is full, or the file-size limit was reached, while writing {} ({e})",
                describe(id)
            ),
        }
    } else {
        StorageError::io(
            path,
            std::io::Error::new(e.kind(), format!("writing {}: {e}", describe(id))),
        )
    }
}

/// Writes `bytes` to a new file at `path` and fsyncs it.
pub(crate) fn write_synced(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let mut file = File::create(path).map_err(|e| StorageError::io(path, e))?;
    file.write_all(bytes)
        .and_then(|()| file.sync_all())
        .map_err(|e| StorageError::io(path, e))
}

/// fsyncs a folder, so the names created in it survive a power loss.
pub(crate) fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| StorageError::io(dir, e))
}

fn encode_index(docs: &IndexDocs, pack_lengths: &[u64], entries: &[Entry]) -> Vec<u8> {
    let mut out = Vec::with_capacity(
        64 + docs.header.len() + docs.skeleton.len() + entries.len() * ENTRY_BYTES,
    );
    if docs.frame_skeletons.is_empty() {
        out.extend_from_slice(INDEX_MAGIC);
    } else {
        out.extend_from_slice(INDEX_MAGIC_FRAMES);
    }
    for doc in [&docs.header, &docs.skeleton, &docs.histogram, &docs.stats] {
        out.extend_from_slice(&(doc.len() as u64).to_le_bytes());
        out.extend_from_slice(doc);
    }
    if !docs.frame_skeletons.is_empty() {
        out.extend_from_slice(&(docs.frame_skeletons.len() as u32).to_le_bytes());
        for doc in &docs.frame_skeletons {
            out.extend_from_slice(&(doc.len() as u64).to_le_bytes());
            out.extend_from_slice(doc);
        }
    }
    out.extend_from_slice(&(pack_lengths.len() as u32).to_le_bytes());
    for len in pack_lengths {
        out.extend_from_slice(&len.to_le_bytes());
    }
    out.extend_from_slice(&(entries.len() as u64).to_le_bytes());
    for e in entries {
        out.extend_from_slice(&e.frame.to_le_bytes());
        out.extend_from_slice(&e.key);
        out.extend_from_slice(&e.pack.to_le_bytes());
        out.extend_from_slice(&e.offset.to_le_bytes());
        out.extend_from_slice(&e.len.to_le_bytes());
        out.extend_from_slice(&e.version.to_le_bytes());
    }
    let sum = xxhash_rust::xxh3::xxh3_64(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

/// A decoded index.
pub(crate) struct Index {
    pub docs: IndexDocs,
    pub pack_lengths: Vec<u64>,
    /// Sorted by (frame, key), no two alike.
    pub entries: Vec<Entry>,
}

/// Reads bounded fields off the index bytes.
struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: u64) -> Option<&'a [u8]> {
        let n = usize::try_from(n).ok()?;
        let end = self.at.checked_add(n)?;
        let out = self.bytes.get(self.at..end)?;
        self.at = end;
        Some(out)
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
}

/// Reads and checks `index.v3` of the store at `store` (regular file, size, magic, checksum,
/// counts bounded by its length, entries sorted and inside their packs' indexed lengths).
pub(crate) fn read_index(store: &Path) -> Result<Index> {
    let path = store.join(INDEX_FILE);
    let bad =
        |what: String| StorageError::corrupted(store, format!("its index {INDEX_FILE} {what}"));
    let file = crate::regular_file::open(&path)?;
    let len = file
        .metadata()
        .map_err(|e| StorageError::io(&path, e))?
        .len();
    if len > INDEX_MAX_BYTES {
        return Err(bad(format!(
            "is {len} bytes long, more than an index can be"
        )));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    {
        use std::io::Read;
        (&file)
            .take(INDEX_MAX_BYTES)
            .read_to_end(&mut bytes)
            .map_err(|e| StorageError::io(&path, e))?;
    }
    let long_enough = bytes.len() >= INDEX_MAGIC.len() + 8;
    let (versioned, with_frames) = match bytes.get(..INDEX_MAGIC.len()) {
        Some(m) if m == INDEX_MAGIC && long_enough => (true, false),
        Some(m) if m == INDEX_MAGIC_FRAMES && long_enough => (true, true),
        Some(m) if m == INDEX_MAGIC_UNVERSIONED && long_enough => (false, false),
        _ => return Err(bad("does not start as an index of format 3".into())),
    };
    let entry_bytes = if versioned {
        ENTRY_BYTES
    } else {
        ENTRY_BYTES_UNVERSIONED
    };
    let (body, sum) = bytes.split_at(bytes.len() - 8);
    let sum = u64::from_le_bytes(sum.try_into().unwrap_or_default());
    if xxhash_rust::xxh3::xxh3_64(body) != sum {
        return Err(bad("is damaged (its checksum does not match)".into()));
    }
    let mut c = Cursor {
        bytes: body,
        at: INDEX_MAGIC.len(),
    };
    let truncated = || bad("is cut short".into());
    let mut doc = || -> Result<Vec<u8>> {
        let n = c.u64().ok_or_else(truncated)?;
        Ok(c.take(n).ok_or_else(truncated)?.to_vec())
    };
    let header = doc()?;
    let skeleton = doc()?;
    let histogram = doc()?;
    let stats = doc()?;
    let mut frame_skeletons = Vec::new();
    if with_frames {
        let count = c.u32().ok_or_else(truncated)?;
        // Each skeleton takes at least its 8-byte length: a count past that is damage, not
        // an allocation.
        if u64::from(count) * 8 > (body.len() - c.at) as u64 {
            return Err(truncated());
        }
        for _ in 0..count {
            let n = c.u64().ok_or_else(truncated)?;
            frame_skeletons.push(c.take(n).ok_or_else(truncated)?.to_vec());
        }
    }
    let docs = IndexDocs {
        header,
        skeleton,
        histogram,
        stats,
        frame_skeletons,
    };
    let packs = c.u32().ok_or_else(truncated)?;
    if u64::from(packs) * 8 > (body.len() - c.at) as u64 {
        return Err(truncated());
    }
    let pack_lengths: Vec<u64> = (0..packs)
        .map(|_| c.u64().ok_or_else(truncated))
        .collect::<Result<_>>()?;
    let count = c.u64().ok_or_else(truncated)?;
    if count.saturating_mul(entry_bytes as u64) != (body.len() - c.at) as u64 {
        return Err(bad(format!(
            "claims {count} entries in {} bytes",
            body.len() - c.at
        )));
    }
    let mut entries = Vec::with_capacity(count as usize);
    for _ in 0..count {
        let frame = c.u32().ok_or_else(truncated)?;
        let key: [u8; 13] = c
            .take(13)
            .and_then(|k| k.try_into().ok())
            .ok_or_else(truncated)?;
        let pack = c.u32().ok_or_else(truncated)?;
        let offset = c.u64().ok_or_else(truncated)?;
        let len = c.u32().ok_or_else(truncated)?;
        let version = if versioned {
            c.u32().ok_or_else(truncated)?
        } else {
            1
        };
        let e = Entry {
            frame,
            key,
            pack,
            offset,
            len,
            version,
        };
        let Some(&pack_len) = pack_lengths.get(pack as usize) else {
            return Err(bad(format!(
                "points {} into pack {pack}, which it does not list",
                e.what()
            )));
        };
        if offset
            .checked_add(u64::from(len))
            .is_none_or(|end| end > pack_len)
        {
            return Err(bad(format!(
                "points {} at bytes {offset}..{} of {}, which holds {pack_len} bytes",
                e.what(),
                offset.saturating_add(u64::from(len)),
                pack_name(pack)
            )));
        }
        if let Some(prev) = entries.last() {
            let prev: &Entry = prev;
            if (prev.frame, prev.key) >= (frame, key) {
                return Err(bad("has entries out of order".into()));
            }
        }
        entries.push(e);
    }
    Ok(Index {
        docs,
        pack_lengths,
        entries,
    })
}

/// The packs of a complete store, mapped, and its entries.
pub(crate) struct Packs {
    /// One map per pack, exactly its indexed length (`None` for an empty pack); shared with
    /// the [`MappedRecord`]s handed out.
    maps: Vec<Option<Arc<memmap2::Mmap>>>,
    entries: Vec<Entry>,
}

impl Packs {
    /// Opens and maps every pack the index lists, checking each is a regular file at least as
    /// long as the index says.
    pub fn open(store: &Path, pack_lengths: &[u64], entries: Vec<Entry>) -> Result<Packs> {
        let mut maps = Vec::with_capacity(pack_lengths.len());
        for (i, &want) in pack_lengths.iter().enumerate() {
            let path = pack_path(store, i as u32);
            let file = match crate::regular_file::open(&path) {
                Ok(f) => f,
                Err(e) => {
                    return Err(StorageError::corrupted(
                        store,
                        format!("its pack {}: {e}", pack_name(i as u32)),
                    ))
                }
            };
            let have = file
                .metadata()
                .map_err(|e| StorageError::io(&path, e))?
                .len();
            if have < want {
                let first = entries
                    .iter()
                    .find(|e| e.pack == i as u32 && e.offset + u64::from(e.len) > have);
                return Err(StorageError::corrupted(
                    store,
                    format!(
                        "its pack {} is {have} bytes, its index says {want} (cut short){}",
                        pack_name(i as u32),
                        first
                            .map(|e| format!(": {} is lost", e.what()))
                            .unwrap_or_default()
                    ),
                ));
            }
            if want == 0 {
                maps.push(None);
                continue;
            }
            let len = usize::try_from(want).map_err(|_| {
                StorageError::corrupted(
                    store,
                    format!("its pack {} is too large", pack_name(i as u32)),
                )
            })?;
            // SAFETY: the file is a regular file at least `len` bytes long, and packs of a
            // complete store are never truncated or rewritten (see the module's documentation).
            let map = unsafe { memmap2::MmapOptions::new().len(len).map(&file) }
                .map_err(|e| StorageError::io(&path, e))?;
            maps.push(Some(Arc::new(map)));
        }
        Ok(Packs { maps, entries })
    }

    pub fn entries(&self) -> &[Entry] {
        &self.entries
    }

    /// Bytes of all packs, as the index gives their lengths (superseded records included).
    pub fn total_bytes(&self) -> u64 {
        self.maps
            .iter()
            .map(|m| m.as_ref().map_or(0, |m| m.len() as u64))
            .sum()
    }

    /// The index entry of `id` in frame `frame`.
    pub fn entry(&self, frame: u32, id: BrickId) -> Option<&Entry> {
        let key = brick_key(id);
        let i = self
            .entries
            .binary_search_by(|e| (e.frame, e.key).cmp(&(frame, key)))
            .ok()?;
        self.entries.get(i)
    }

    /// The record of `id` in frame `frame`: a slice of its pack's map (checked at open).
    pub fn get(&self, frame: u32, id: BrickId) -> Option<&[u8]> {
        let key = brick_key(id);
        let i = self
            .entries
            .binary_search_by(|e| (e.frame, e.key).cmp(&(frame, key)))
            .ok()?;
        self.slice(&self.entries[i])
    }

    /// The record of `id` in frame `frame` as a [`MappedRecord`]: no copy, and it stays valid
    /// after this `Packs` is dropped (it holds its pack's map).
    pub fn mapped(&self, frame: u32, id: BrickId) -> Option<MappedRecord> {
        let key = brick_key(id);
        let i = self
            .entries
            .binary_search_by(|e| (e.frame, e.key).cmp(&(frame, key)))
            .ok()?;
        let e = &self.entries[i];
        let len = self.slice(e)?.len();
        Some(MappedRecord {
            map: self.maps.get(e.pack as usize)?.as_ref()?.clone(),
            start: usize::try_from(e.offset).ok()?,
            len,
        })
    }

    /// Tells the kernel the maps are about to be read front to back (verify: read ahead
    /// further), or (`false`) back to random reads by brick. Advice only: a refusal changes
    /// nothing but speed.
    pub fn advise_sequential(&self, sequential: bool) {
        let advice = if sequential {
            memmap2::Advice::Sequential
        } else {
            memmap2::Advice::Normal
        };
        for map in self.maps.iter().flatten() {
            let _ = map.advise(advice);
        }
    }

    pub fn slice(&self, e: &Entry) -> Option<&[u8]> {
        let map = self.maps.get(e.pack as usize)?.as_ref()?;
        let start = usize::try_from(e.offset).ok()?;
        map.get(start..start.checked_add(e.len as usize)?)
    }
}

/// The lock file that writers of new record versions into a complete store hold exclusively
/// (readers never take it, so they keep reading while a writer appends).
pub(crate) const WRITE_LOCK_FILE: &str = "strata.write.lock";

/// An exclusive hold on a complete store's [`WRITE_LOCK_FILE`]; released when dropped (and by
/// the OS when its process dies).
pub(crate) struct WriteLock {
    _file: File,
}

impl WriteLock {
    pub fn acquire(store: &Path) -> Result<WriteLock> {
        let path = store.join(WRITE_LOCK_FILE);
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| StorageError::io(&path, e))?;
        match file.try_lock() {
            Ok(()) => Ok(WriteLock { _file: file }),
            Err(std::fs::TryLockError::WouldBlock) => Err(StorageError::InUse {
                path: store.to_path_buf(),
                holder: crate::lock::LockHolder {
                    pid: 0,
                    purpose: crate::lock::LockPurpose::Import,
                    url: None,
                },
            }),
            Err(std::fs::TryLockError::Error(e)) => Err(StorageError::io(
                &path,
                std::io::Error::new(e.kind(), format!("locking the store for writing: {e}")),
            )),
        }
    }
}

/// Appends new versions of brick records (frame, id, record) to the complete format-3 store at
/// `store`, whose index is `index`; the caller holds its [`WriteLock`]. Afterwards the index
/// points every given brick at its newest record; the older records stay in their packs,
/// superseded, until a compaction drops them.
///
/// **Order of writes, and why a SIGKILL or power loss at any point is safe.**
/// 1. Pack files numbered at or past the index's pack count are removed: they are the leftovers
///    of an append killed before its index was renamed in, and no index names them.
/// 2. The records go to new packs (`create_new`, numbered after the index's last), each
///    fsync'd, then the packs folder fsync'd. Existing packs are never opened for writing, so a
///    reader's maps of them stay valid, and the index in place still names only their bytes.
/// 3. The new index (the old entries with these replaced, each one version past the record it
///    supersedes; the new packs' lengths; `docs`, the caller's skeleton updated) is written to
///    `index.v3.new`, fsync'd, renamed over `index.v3`, and the store folder fsync'd. The rename
///    is the commit point: before it every reader sees the old versions, after it the new;
///    either index is whole (checksummed) and names only bytes already on disk.
///
/// The marker's `complete` line is never touched: the store is complete throughout. A reader
/// that opened before the rename keeps its old index and maps (packs only grow by whole new
/// files and are never truncated); one that opens after sees the new records.
pub(crate) fn append_versions(
    store: &Path,
    index: &Index,
    docs: &IndexDocs,
    records: &[(u32, BrickId, Vec<u8>)],
    limit: u64,
) -> Result<()> {
    append_records(
        store,
        index,
        docs,
        records
            .iter()
            .map(|(frame, id, record)| (*frame, *id, None, record.as_slice())),
        limit,
    )
}

/// [`append_versions`] of records given as (frame, id, version, record): a record with a
/// version keeps it (a frame's records copied in as imported), one without takes the next
/// after its brick's newest. Same order of writes, same commit point.
pub(crate) fn append_records<'a>(
    store: &Path,
    index: &Index,
    docs: &IndexDocs,
    records: impl Iterator<Item = (u32, BrickId, Option<u32>, &'a [u8])>,
    limit: u64,
) -> Result<()> {
    use std::io::Write;
    let dir = store.join(PACKS_DIR);
    let first_new = u32::try_from(index.pack_lengths.len())
        .map_err(|_| StorageError::invalid(store, "too many packs"))?;
    // 1. Leftovers of a killed append.
    for entry in std::fs::read_dir(&dir).map_err(|e| StorageError::io(&dir, e))? {
        let entry = entry.map_err(|e| StorageError::io(&dir, e))?;
        let name = entry.file_name();
        let number = name
            .to_str()
            .and_then(|n| n.strip_prefix("pack-"))
            .and_then(|n| n.strip_suffix(".pack"))
            .and_then(|n| n.parse::<u32>().ok());
        if number.is_some_and(|n| n >= first_new) {
            let p = entry.path();
            std::fs::remove_file(&p).map_err(|e| StorageError::io(&p, e))?;
        }
    }
    let _ = std::fs::remove_file(store.join(format!("{INDEX_FILE}.new")));
    // 2. New packs, fsync'd.
    let mut lengths = index.pack_lengths.clone();
    let mut newest: HashMap<(u32, [u8; 13]), Entry> = HashMap::new();
    let mut current: Option<(u32, std::io::BufWriter<File>, u64)> = None;
    let close = |pack: u32, writer: std::io::BufWriter<File>| -> Result<()> {
        let path = pack_path(store, pack);
        let file = writer
            .into_inner()
            .map_err(|e| StorageError::io(&path, e.into_error()))?;
        file.sync_all().map_err(|e| StorageError::io(&path, e))
    };
    for (frame, id, given_version, record) in records {
        let (frame, id) = (&frame, &id);
        let len = u32::try_from(record.len()).map_err(|_| {
            StorageError::invalid(store, format!("{}: record too large", describe(*id)))
        })?;
        if current
            .as_ref()
            .is_some_and(|(_, _, end)| *end > 0 && end + u64::from(len) > limit)
        {
            if let Some((pack, writer, _)) = current.take() {
                close(pack, writer)?;
            }
        }
        if current.is_none() {
            let pack = lengths.len() as u32;
            let path = pack_path(store, pack);
            let file = std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
                .map_err(|e| StorageError::io(&path, e))?;
            lengths.push(0);
            current = Some((pack, std::io::BufWriter::new(file), 0));
        }
        let Some((pack, writer, end)) = current.as_mut() else {
            continue;
        };
        writer
            .write_all(record)
            .map_err(|e| write_error(&pack_path(store, *pack), *id, e))?;
        let key = brick_key(*id);
        // The next version after the newest: one appended earlier in this call, else the
        // index's, else the import's (1: a constant brick a sparse skeleton implied).
        let version = match (given_version, newest.get(&(*frame, key))) {
            (Some(v), _) => v,
            (None, Some(e)) => e.version.saturating_add(1),
            (None, None) => index
                .entries
                .binary_search_by(|e| (e.frame, e.key).cmp(&(*frame, key)))
                .map_or(1, |i| index.entries[i].version)
                .saturating_add(1),
        };
        newest.insert(
            (*frame, key),
            Entry {
                frame: *frame,
                key,
                pack: *pack,
                offset: *end,
                len,
                version,
            },
        );
        *end += u64::from(len);
        lengths[*pack as usize] = *end;
    }
    // No records (a frame whose every brick the skeleton implies) still commits the index.
    if let Some((pack, writer, _)) = current.take() {
        close(pack, writer)?;
        sync_dir(&dir)?;
    }
    // 3. The new index, renamed in.
    let mut entries: Vec<Entry> = index
        .entries
        .iter()
        .filter(|e| !newest.contains_key(&(e.frame, e.key)))
        .copied()
        .collect();
    entries.extend(newest.into_values());
    entries.sort_by_key(|e| (e.frame, e.key));
    let bytes = encode_index(docs, &lengths, &entries);
    let target = store.join(INDEX_FILE);
    let staged = store.join(format!("{INDEX_FILE}.new"));
    write_synced(&staged, &bytes)?;
    std::fs::rename(&staged, &target).map_err(|e| StorageError::io(&target, e))?;
    sync_dir(store)
}

/// One record as a slice of its pack's map that owns a share of the map: a server hands it to
/// `bytes::Bytes::from_owner` and sends it without a copy. The bounds were checked when it was
/// made (see [`Packs::mapped`]).
#[derive(Clone)]
pub struct MappedRecord {
    map: Arc<memmap2::Mmap>,
    start: usize,
    len: usize,
}

impl AsRef<[u8]> for MappedRecord {
    fn as_ref(&self) -> &[u8] {
        &self.map[self.start..self.start + self.len]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(level: u8, x: u32, offset: u64, version: u32) -> Entry {
        Entry {
            frame: 0,
            key: brick_key(BrickId::new(level, [x, 0, 0])),
            pack: 0,
            offset,
            len: 10,
            version,
        }
    }

    /// An index of the first format-3 builds (its own magic, entries without a version) reads
    /// with every record at version 1; the current one keeps each entry's version.
    #[test]
    fn an_index_written_before_versions_reads_every_record_as_version_1() {
        let dir = tempfile::tempdir().unwrap();
        let docs = IndexDocs {
            header: b"h".to_vec(),
            skeleton: b"s".to_vec(),
            histogram: b"g".to_vec(),
            stats: b"t".to_vec(),
            frame_skeletons: Vec::new(),
        };
        let mut entries = vec![entry(0, 0, 0, 3), entry(0, 1, 10, 1), entry(1, 0, 20, 2)];
        entries.sort_by_key(|e| (e.frame, e.key));
        let current = encode_index(&docs, &[30], &entries);
        std::fs::write(dir.path().join(INDEX_FILE), &current).unwrap();
        let read = read_index(dir.path()).unwrap();
        assert_eq!(read.entries, entries);

        // The same index as the first builds wrote it: old magic, 4 bytes fewer per entry.
        let body = &current[..current.len() - 8];
        let entries_at = body.len() - entries.len() * ENTRY_BYTES;
        let mut old = INDEX_MAGIC_UNVERSIONED.to_vec();
        old.extend_from_slice(&body[INDEX_MAGIC.len()..entries_at]);
        for e in body[entries_at..].chunks(ENTRY_BYTES) {
            old.extend_from_slice(&e[..ENTRY_BYTES_UNVERSIONED]);
        }
        let sum = xxhash_rust::xxh3::xxh3_64(&old);
        old.extend_from_slice(&sum.to_le_bytes());
        std::fs::write(dir.path().join(INDEX_FILE), &old).unwrap();
        let read = read_index(dir.path()).unwrap();
        let as_version_1: Vec<Entry> = entries.iter().map(|e| Entry { version: 1, ..*e }).collect();
        assert_eq!(read.entries, as_version_1);
        assert_eq!(read.pack_lengths, vec![30]);
        assert_eq!(read.docs.skeleton, b"s");

        // Neither magic: refused, naming the index.
        old[0] ^= 1;
        std::fs::write(dir.path().join(INDEX_FILE), &old).unwrap();
        let err = read_index(dir.path())
            .err()
            .expect("a foreign magic is refused");
        assert!(err.to_string().contains(INDEX_FILE), "{err}");
    }

    /// A 4-D store's index carries frames 1..'s skeletons under its own magic and reads them
    /// back; a count of skeletons past what the file holds is refused as cut short, without
    /// allocating for it.
    #[test]
    fn an_index_with_frame_skeletons_reads_them_back_and_refuses_a_lying_count() {
        let dir = tempfile::tempdir().unwrap();
        let docs = IndexDocs {
            header: b"h".to_vec(),
            skeleton: b"s".to_vec(),
            histogram: b"g".to_vec(),
            stats: b"t".to_vec(),
            frame_skeletons: vec![b"frame 1".to_vec(), b"frame 2!".to_vec()],
        };
        let entries = vec![
            entry(0, 0, 0, 1),
            Entry {
                frame: 2,
                ..entry(0, 0, 10, 1)
            },
        ];
        let bytes = encode_index(&docs, &[20], &entries);
        assert_eq!(&bytes[..INDEX_MAGIC_FRAMES.len()], INDEX_MAGIC_FRAMES);
        std::fs::write(dir.path().join(INDEX_FILE), &bytes).unwrap();
        let read = read_index(dir.path()).unwrap();
        assert_eq!(read.docs.frame_skeletons, docs.frame_skeletons);
        assert_eq!(read.entries, entries);

        // The count of skeletons (after the four documents) made huge, the checksum redone.
        let at = INDEX_MAGIC_FRAMES.len() + 4 * 8 + 4;
        let mut lying = bytes[..bytes.len() - 8].to_vec();
        lying[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let sum = xxhash_rust::xxh3::xxh3_64(&lying);
        lying.extend_from_slice(&sum.to_le_bytes());
        std::fs::write(dir.path().join(INDEX_FILE), &lying).unwrap();
        let err = read_index(dir.path())
            .err()
            .expect("a lying count is refused");
        assert!(err.to_string().contains("cut short"), "{err}");

        // A single volume keeps the magic older builds read.
        let single = IndexDocs {
            frame_skeletons: Vec::new(),
            ..docs
        };
        let bytes = encode_index(&single, &[20], &entries[..1]);
        assert_eq!(&bytes[..INDEX_MAGIC.len()], INDEX_MAGIC);
    }
}
