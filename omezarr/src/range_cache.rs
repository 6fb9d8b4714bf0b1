//! An object store in front of another that remembers the byte ranges it fetched and counts
//! what crossed the wire. A streamed brick needs its own chunk and the borders of its up to 26
//! neighbours; the neighbours' chunks are the next bricks' own, so without a cache every chunk
//! would be fetched up to 27 times. Ranges are cached as fetched (an inner chunk, a shard
//! index), within a byte budget, oldest first out; missing ranges of one call are merged where
//! they are less than [`MERGE_GAP`] apart (object_store's own default, 1 MiB, would fetch
//! whole stretches of unneeded chunks) and fetched concurrently. Object sizes (the HEAD zarrs
//! sends before each ranged read) are cached too, absent objects (fill-only shards) included.
//! Sound because what it fronts is an immutable export, read-only.

use std::collections::{HashMap, VecDeque};
use std::fmt;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use async_trait::async_trait;
use bytes::Bytes;
use futures::stream::{BoxStream, StreamExt};
use object_store::path::Path;
use object_store::{
    CopyOptions, GetOptions, GetResult, GetResultPayload, ListResult, MultipartUpload, ObjectMeta,
    ObjectStore, PutMultipartOptions, PutOptions, PutPayload, PutResult,
};

/// Ranges closer than this are fetched as one request (a few compressed 32³ chunks).
pub const MERGE_GAP: u64 = 16 << 10;

/// What went over the wire, for benchmarks and tests.
#[derive(Debug, Default)]
pub struct TransferCounters {
    /// GET requests sent (ranged or whole).
    pub requests: AtomicU64,
    pub bytes: AtomicU64,
    /// Ranges answered from the cache.
    pub cache_hits: AtomicU64,
}

impl TransferCounters {
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }
    pub fn cache_hits(&self) -> u64 {
        self.cache_hits.load(Ordering::Relaxed)
    }
}

type RangeKey = (String, u64, u64);

#[derive(Default)]
struct Cache {
    /// Object sizes (HEAD answers; `None`: absent), asked before every ranged read by zarrs.
    heads: HashMap<String, Option<ObjectMeta>>,
    entries: HashMap<RangeKey, Bytes>,
    order: VecDeque<RangeKey>,
    bytes: u64,
}

pub struct RangeCacheStore {
    inner: Arc<dyn ObjectStore>,
    cache: Mutex<Cache>,
    budget_bytes: u64,
    pub counters: Arc<TransferCounters>,
}

impl RangeCacheStore {
    pub fn new(inner: Arc<dyn ObjectStore>, budget_bytes: u64) -> Self {
        RangeCacheStore {
            inner,
            cache: Mutex::new(Cache::default()),
            budget_bytes,
            counters: Arc::new(TransferCounters::default()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Cache> {
        // The cache holds only copies of fetched bytes: a panic elsewhere cannot leave it wrong.
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn insert(&self, key: RangeKey, bytes: Bytes) {
        let mut cache = self.lock();
        if cache.entries.contains_key(&key) {
            return;
        }
        cache.bytes += bytes.len() as u64;
        cache.entries.insert(key.clone(), bytes);
        cache.order.push_back(key);
        while cache.bytes > self.budget_bytes {
            let Some(old) = cache.order.pop_front() else {
                break;
            };
            if let Some(b) = cache.entries.remove(&old) {
                cache.bytes -= b.len() as u64;
            }
        }
    }
}

impl fmt::Display for RangeCacheStore {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "RangeCache({})", self.inner)
    }
}

impl fmt::Debug for RangeCacheStore {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "RangeCache({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for RangeCacheStore {
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
        let plain_head = options.head
            && options.range.is_none()
            && options.if_match.is_none()
            && options.if_none_match.is_none()
            && options.if_modified_since.is_none()
            && options.if_unmodified_since.is_none()
            && options.version.is_none();
        if plain_head {
            let name = location.to_string();
            let cached = self.lock().heads.get(&name).cloned();
            let meta = match cached {
                Some(meta) => meta,
                None => {
                    self.counters.requests.fetch_add(1, Ordering::Relaxed);
                    let meta = match self.inner.get_opts(location, options).await {
                        Ok(result) => Some(result.meta),
                        Err(object_store::Error::NotFound { .. }) => None,
                        Err(e) => return Err(e),
                    };
                    self.lock().heads.insert(name, meta.clone());
                    meta
                }
            };
            return match meta {
                Some(meta) => Ok(GetResult {
                    payload: GetResultPayload::Stream(futures::stream::empty().boxed()),
                    meta,
                    range: 0..0,
                    attributes: Default::default(),
                    extensions: Default::default(),
                }),
                None => Err(object_store::Error::NotFound {
                    path: location.to_string(),
                    source: "absent (cached answer)".into(),
                }),
            };
        }
        let result = self.inner.get_opts(location, options).await?;
        self.counters.requests.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes
            .fetch_add(result.range.end - result.range.start, Ordering::Relaxed);
        Ok(result)
    }

    async fn get_ranges(
        &self,
        location: &Path,
        ranges: &[Range<u64>],
    ) -> object_store::Result<Vec<Bytes>> {
        let name = location.to_string();
        let mut out: Vec<Option<Bytes>> = {
            let cache = self.lock();
            ranges
                .iter()
                .map(|r| cache.entries.get(&(name.clone(), r.start, r.end)).cloned())
                .collect()
        };
        let hits = out.iter().filter(|b| b.is_some()).count() as u64;
        self.counters.cache_hits.fetch_add(hits, Ordering::Relaxed);
        let missing: Vec<Range<u64>> = ranges
            .iter()
            .zip(&out)
            .filter(|(_, b)| b.is_none())
            .map(|(r, _)| r.clone())
            .collect();
        if !missing.is_empty() {
            let fetched = object_store::coalesce_ranges(
                &missing,
                |range| async move {
                    let got = self
                        .get_opts(
                            location,
                            GetOptions {
                                range: Some(range.into()),
                                ..GetOptions::default()
                            },
                        )
                        .await?;
                    got.bytes().await
                },
                MERGE_GAP,
            )
            .await?;
            let mut fetched = fetched.into_iter();
            for (slot, range) in out.iter_mut().zip(ranges) {
                if slot.is_none() {
                    let bytes = fetched.next().unwrap_or_default();
                    self.insert((name.clone(), range.start, range.end), bytes.clone());
                    *slot = Some(bytes);
                }
            }
        }
        Ok(out.into_iter().map(Option::unwrap_or_default).collect())
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
