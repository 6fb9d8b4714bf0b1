//! An object store in front of another that bounds every read by what the metadata and the
//! objects' sizes allow, so damage is refused with its location before anything is allocated
//! or opened:
//! - in a local folder, an object that is not a regular file (a FIFO, a device, a socket, a
//!   folder where a shard should be) is refused before it is opened: opening a FIFO blocks
//!   until a writer comes, which for a damaged export is never;
//! - a ranged read must lie inside the object (zarrs takes a shard index's offsets as they
//!   are, and object_store's local reader allocates the length it is asked for: a damaged
//!   index entry asked for 700 TB and aborted the process) and, inside a sharded array, be no
//!   longer than an encoded inner chunk can be;
//! - a shard index, whenever its bytes pass here (a suffix read, or the whole shard), is
//!   range-checked entry by entry against the shard's length before zarrs sees it (zarrs adds
//!   offset and length unchecked). A missing crc32c on the index is allowed (the index is then
//!   read as the metadata says), but then these checks are all that stands between a damaged
//!   index and a wrong read, so they run whatever the codecs.
//!
//! Errors are never `NotFound`: that would read as an absent chunk, i.e. the fill value.

use std::collections::HashMap;
use std::fmt;
use std::ops::Range;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, RwLock};

use async_trait::async_trait;
use bytes::Bytes;
use futures::stream::{BoxStream, StreamExt};
use object_store::path::Path;
use object_store::{
    CopyOptions, GetOptions, GetRange, GetResult, GetResultPayload, ListResult, MultipartUpload,
    ObjectMeta, ObjectStore, ObjectStoreExt, PutMultipartOptions, PutOptions, PutPayload,
    PutResult,
};

/// How a sharded array lays out its shards, as far as reads need to know.
#[derive(Clone, Debug, PartialEq)]
pub struct ShardSpec {
    /// Inner chunks per shard (index entries).
    pub entries: u64,
    /// The index sits at the shard's end (the default), else at its start.
    pub index_at_end: bool,
    /// Bytes of the encoded index (16 per entry, plus 4 with a crc32c codec).
    pub index_bytes: u64,
}

/// What reads under one array (its key prefix) may ask for.
#[derive(Clone, Debug, PartialEq)]
pub struct ArrayLimits {
    /// `"0/"`: the array's folder, relative to the group.
    pub prefix: String,
    /// Longest an encoded (inner) chunk can be: its decoded size plus any codec's expansion.
    pub max_chunk_bytes: u64,
    pub shard: Option<ShardSpec>,
}

impl ArrayLimits {
    /// Longest a shard can be: every inner chunk at its longest, and the index.
    fn max_object_bytes(&self) -> u64 {
        match &self.shard {
            Some(s) => s
                .entries
                .saturating_mul(self.max_chunk_bytes)
                .saturating_add(s.index_bytes),
            None => self.max_chunk_bytes,
        }
    }
}

/// The arrays registered so far (levels are opened one by one, after the store).
#[derive(Debug, Default)]
pub struct ReadLimits {
    arrays: RwLock<Vec<ArrayLimits>>,
}

impl ReadLimits {
    pub fn register(&self, limits: ArrayLimits) {
        let mut arrays = self.arrays.write().unwrap_or_else(|p| p.into_inner());
        if !arrays.contains(&limits) {
            arrays.retain(|a| a.prefix != limits.prefix);
            arrays.push(limits);
        }
    }

    /// The array a key lies in (the longest prefix), unless the key is metadata.
    fn array_of(&self, key: &str) -> Option<ArrayLimits> {
        if key.ends_with("zarr.json") {
            return None;
        }
        let arrays = self.arrays.read().unwrap_or_else(|p| p.into_inner());
        arrays
            .iter()
            .filter(|a| key.starts_with(&a.prefix))
            .max_by_key(|a| a.prefix.len())
            .cloned()
    }
}

/// The upper bound of an encoded chunk of `decoded` bytes: general-purpose compressors expand
/// incompressible data by well under 1% plus a small header (zstd, blosc, gzip, lz4), a
/// checksum codec adds 4 bytes; a quarter and 64 KiB leave room for any sane codec chain.
pub fn max_encoded_bytes(decoded: u64) -> u64 {
    decoded.saturating_add(decoded / 4).saturating_add(64 << 10)
}

fn damaged(message: String) -> object_store::Error {
    object_store::Error::Generic {
        store: "strata",
        source: message.into(),
    }
}

pub struct ReadGuard {
    inner: Arc<dyn ObjectStore>,
    /// The folder the keys are relative to, for a local store (file types are checked there).
    local_root: Option<PathBuf>,
    limits: Arc<ReadLimits>,
    /// Object sizes of a remote store (HEAD answers), for range checks.
    sizes: Mutex<HashMap<String, u64>>,
}

impl ReadGuard {
    pub fn new(
        inner: Arc<dyn ObjectStore>,
        local_root: Option<PathBuf>,
        limits: Arc<ReadLimits>,
    ) -> Self {
        ReadGuard {
            inner,
            local_root,
            limits,
            sizes: Mutex::new(HashMap::new()),
        }
    }

    /// For a local store: refuses what is not a regular file, and answers its size (`None`:
    /// absent, or a remote store). `stat` never blocks, whatever the file is.
    fn check_local(&self, location: &Path) -> object_store::Result<Option<u64>> {
        let Some(root) = &self.local_root else {
            return Ok(None);
        };
        let path = root.join(location.as_ref());
        let Ok(meta) = std::fs::metadata(&path) else {
            return Ok(None);
        };
        if meta.is_file() {
            return Ok(Some(meta.len()));
        }
        let what = if meta.is_dir() {
            "a folder"
        } else {
            "not a regular file (a FIFO, device or socket)"
        };
        Err(damaged(format!(
            "{}: {what} where an object should be; refused before opening it",
            path.display()
        )))
    }

    async fn size_of(&self, location: &Path) -> object_store::Result<u64> {
        if let Some(size) = self.check_local(location)? {
            return Ok(size);
        }
        let key = location.to_string();
        if let Some(&size) = self
            .sizes
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(&key)
        {
            return Ok(size);
        }
        let size = self.inner.head(location).await?.size;
        self.sizes
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(key, size);
        Ok(size)
    }
}

/// Checks a shard's index bytes (without a checksum suffix, if any) against the shard's length
/// and the longest chunk; the error names the shard, the entry and what is wrong.
pub fn check_shard_index(
    key: &str,
    index: &[u8],
    shard: &ShardSpec,
    object_size: u64,
    max_chunk_bytes: u64,
) -> object_store::Result<()> {
    let (data_start, data_end) = if shard.index_at_end {
        (0, object_size.saturating_sub(shard.index_bytes))
    } else {
        (shard.index_bytes, object_size)
    };
    for (i, entry) in index.chunks_exact(16).enumerate() {
        let offset = u64::from_le_bytes(entry[..8].try_into().unwrap_or_default());
        let length = u64::from_le_bytes(entry[8..].try_into().unwrap_or_default());
        if offset == u64::MAX && length == u64::MAX {
            continue;
        }
        let end = offset.checked_add(length);
        let problem = if offset == u64::MAX || length == u64::MAX {
            Some("half of an empty-chunk marker".to_string())
        } else if length > max_chunk_bytes {
            Some(format!(
                "{length} bytes, longer than an encoded inner chunk can be ({max_chunk_bytes})"
            ))
        } else if offset < data_start || end.is_none_or(|e| e > data_end) {
            Some(format!(
                "bytes {offset}..{} lie outside the shard's chunk data ({data_start}..{data_end} of {object_size} bytes)",
                end.map_or_else(|| "overflow".to_string(), |e| e.to_string())
            ))
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(damaged(format!(
                "{key}: shard index entry {i} (offset {offset}, length {length}): {problem}; the shard or its index is damaged"
            )));
        }
    }
    Ok(())
}

impl ReadGuard {
    /// Whether `range` of an object of `size` bytes is the shard's index (as zarrs reads it).
    fn is_index_range(shard: &ShardSpec, range: &Range<u64>, size: u64) -> bool {
        let len = range.end.saturating_sub(range.start);
        len == shard.index_bytes
            && if shard.index_at_end {
                range.end == size
            } else {
                range.start == 0
            }
    }

    fn check_index_bytes(
        key: &str,
        limits: &ArrayLimits,
        shard: &ShardSpec,
        bytes: &[u8],
        size: u64,
    ) -> object_store::Result<()> {
        let entries_len = (shard.entries * 16).min(bytes.len() as u64) as usize;
        check_shard_index(
            key,
            &bytes[..entries_len],
            shard,
            size,
            limits.max_chunk_bytes,
        )
    }
}

impl fmt::Display for ReadGuard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ReadGuard({})", self.inner)
    }
}

impl fmt::Debug for ReadGuard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ReadGuard({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for ReadGuard {
    async fn put_opts(
        &self,
        location: &Path,
        payload: PutPayload,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        self.inner.put_opts(location, payload, opts).await
    }

    async fn put_multipart_opts(
        &self,
        location: &Path,
        opts: PutMultipartOptions,
    ) -> object_store::Result<Box<dyn MultipartUpload>> {
        self.inner.put_multipart_opts(location, opts).await
    }

    async fn get_opts(
        &self,
        location: &Path,
        options: GetOptions,
    ) -> object_store::Result<GetResult> {
        self.check_local(location)?;
        if options.head {
            return self.inner.get_opts(location, options).await;
        }
        let key = location.to_string();
        let array = self.limits.array_of(&key);
        let whole = options.range.is_none();
        let suffix = matches!(options.range, Some(GetRange::Suffix(_)));
        let result = self.inner.get_opts(location, options).await?;
        let Some(array) = array else {
            return Ok(result);
        };
        let size = result.meta.size;
        if whole && size > array.max_object_bytes() {
            return Err(damaged(format!(
                "{key}: {size} bytes, more than a chunk of this array can be ({}); damaged",
                array.max_object_bytes()
            )));
        }
        let Some(shard) = &array.shard else {
            return Ok(result);
        };
        if !(whole || suffix) {
            return Ok(result);
        }
        // The index passes here: read it (bounded above), check it, hand the bytes on.
        let meta = result.meta.clone();
        let range = result.range.clone();
        let attributes = result.attributes.clone();
        let bytes = result.bytes().await?;
        let index = if whole {
            let n = shard.index_bytes.min(size) as usize;
            if shard.index_at_end {
                bytes.slice(bytes.len() - n..)
            } else {
                bytes.slice(..n)
            }
        } else if Self::is_index_range(shard, &range, size) {
            bytes.clone()
        } else {
            Bytes::new()
        };
        Self::check_index_bytes(&key, &array, shard, &index, size)?;
        Ok(GetResult {
            payload: GetResultPayload::Stream(futures::stream::once(async { Ok(bytes) }).boxed()),
            meta,
            range,
            attributes,
            extensions: Default::default(),
        })
    }

    async fn get_ranges(
        &self,
        location: &Path,
        ranges: &[Range<u64>],
    ) -> object_store::Result<Vec<Bytes>> {
        let size = self.size_of(location).await?;
        let key = location.to_string();
        let array = self.limits.array_of(&key);
        // Ranges holding a shard's whole index (zarrs reads a whole shard as one range, an
        // index as a suffix): checked once they arrive, before zarrs decodes them.
        let mut holding_index = Vec::new();
        for (i, r) in ranges.iter().enumerate() {
            if r.start > r.end || r.end > size {
                return Err(damaged(format!(
                    "{key}: bytes {}..{} asked for, but the object holds {size}; its shard index or metadata is damaged",
                    r.start, r.end
                )));
            }
            let Some(array) = &array else { continue };
            let len = r.end - r.start;
            let whole = r.start == 0 && r.end == size;
            if let Some(shard) = &array.shard {
                let (index_start, index_end) = if shard.index_at_end {
                    (size.saturating_sub(shard.index_bytes), size)
                } else {
                    (0, shard.index_bytes.min(size))
                };
                if r.start <= index_start && r.end >= index_end && size >= shard.index_bytes {
                    holding_index.push((i, (index_start - r.start) as usize));
                }
            }
            let limit = if whole {
                array.max_object_bytes()
            } else {
                array
                    .max_chunk_bytes
                    .max(array.shard.as_ref().map_or(0, |s| s.index_bytes))
            };
            if len > limit {
                return Err(damaged(format!(
                    "{key}: bytes {}..{} asked for, longer than {} of this array can be ({limit}); its shard index or metadata is damaged",
                    r.start,
                    r.end,
                    if whole { "a shard" } else { "an encoded chunk" }
                )));
            }
        }
        let got = self.inner.get_ranges(location, ranges).await?;
        if let Some(array) = &array {
            if let Some(shard) = &array.shard {
                for (i, at) in holding_index {
                    let bytes = got[i].get(at..).unwrap_or_default();
                    Self::check_index_bytes(&key, array, shard, bytes, size)?;
                }
            }
        }
        Ok(got)
    }

    fn delete_stream(
        &self,
        locations: BoxStream<'static, object_store::Result<Path>>,
    ) -> BoxStream<'static, object_store::Result<Path>> {
        self.inner.delete_stream(locations)
    }

    fn list(&self, prefix: Option<&Path>) -> BoxStream<'static, object_store::Result<ObjectMeta>> {
        self.inner.list(prefix)
    }

    async fn list_with_delimiter(&self, prefix: Option<&Path>) -> object_store::Result<ListResult> {
        self.inner.list_with_delimiter(prefix).await
    }

    async fn copy_opts(
        &self,
        from: &Path,
        to: &Path,
        options: CopyOptions,
    ) -> object_store::Result<()> {
        self.inner.copy_opts(from, to, options).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> ShardSpec {
        ShardSpec {
            entries: 2,
            index_at_end: true,
            index_bytes: 36,
        }
    }

    fn index(entries: &[(u64, u64)]) -> Vec<u8> {
        entries
            .iter()
            .flat_map(|(o, l)| o.to_le_bytes().into_iter().chain(l.to_le_bytes()))
            .collect()
    }

    #[test]
    fn index_entries_are_range_checked() {
        // A shard of 100 + 36 bytes: chunk data 0..100.
        let ok = index(&[(0, 60), (u64::MAX, u64::MAX)]);
        check_shard_index("0/c/0/0/0", &ok, &spec(), 136, 1000).unwrap();
        for (bad, what) in [
            (index(&[(0, 1 << 63), (60, 40)]), "longer than"),
            (index(&[(50, 60), (0, 10)]), "outside"),
            (index(&[(0, 101), (0, 10)]), "longer than"),
            (index(&[(u64::MAX - 5, 10), (0, 10)]), "outside"),
            (
                index(&[(u64::MAX, 0), (0, 10)]),
                "half of an empty-chunk marker",
            ),
        ] {
            let e = check_shard_index("0/c/0/0/0", &bad, &spec(), 136, 100)
                .unwrap_err()
                .to_string();
            assert!(e.contains("0/c/0/0/0") && e.contains(what), "{e}");
        }
    }
}
