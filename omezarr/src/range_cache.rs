//! An object store in front of another that remembers the byte ranges it fetched and counts
//! what crossed the wire. A streamed brick needs its own chunk and the borders of its up to 26
//! neighbours; the neighbours' chunks are the next bricks' own, so without a cache every chunk
//! would be fetched up to 27 times. Ranges are cached as fetched (an inner chunk, a shard
//! index), within a byte budget, oldest first out; missing ranges of one call are merged where
//! they are less than [`MERGE_GAP`] apart (object_store's own default, 1 MiB, would fetch
//! whole stretches of unneeded chunks) and fetched concurrently. A range already on its way
//! for another caller is waited for, not fetched again (the streaming source has many bricks
//! in flight whose aprons share chunks); when that caller is cancelled or fails, the waiter
//! fetches the range itself. Object sizes (the HEAD zarrs
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
    /// Ranges on their way: a caller that needs one waits for it instead of fetching it again
    /// (many bricks in flight share their neighbours' chunks).
    pending: HashMap<RangeKey, tokio::sync::watch::Receiver<Option<Bytes>>>,
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

impl RangeCacheStore {
    async fn fetch_range(&self, location: &Path, range: Range<u64>) -> object_store::Result<Bytes> {
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
    }
}

/// Ranges a caller of `get_ranges` fetches for everyone; released when it is done, cancelled
/// (its future dropped) or failed, so that waiters then fetch them themselves.
struct PendingClaim<'a> {
    store: &'a RangeCacheStore,
    keys: Vec<RangeKey>,
}

impl Drop for PendingClaim<'_> {
    fn drop(&mut self) {
        let mut cache = self.store.lock();
        for key in &self.keys {
            cache.pending.remove(key);
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
        let mut out: Vec<Option<Bytes>> = vec![None; ranges.len()];
        let mut waiting = Vec::new();
        let mut claimed = Vec::new();
        let mut claim = PendingClaim {
            store: self,
            keys: Vec::new(),
        };
        {
            let mut cache = self.lock();
            for (i, r) in ranges.iter().enumerate() {
                let key = (name.clone(), r.start, r.end);
                if let Some(bytes) = cache.entries.get(&key) {
                    out[i] = Some(bytes.clone());
                } else if let Some(rx) = cache.pending.get(&key) {
                    waiting.push((i, rx.clone()));
                } else if !claim.keys.contains(&key) {
                    let (tx, rx) = tokio::sync::watch::channel(None);
                    cache.pending.insert(key.clone(), rx);
                    claim.keys.push(key);
                    claimed.push((i, tx));
                } else {
                    // The same range twice in one call: filled from the first below.
                    waiting.push((i, cache.pending[&key].clone()));
                }
            }
        }
        let hits = out.iter().filter(|b| b.is_some()).count() as u64 + waiting.len() as u64;
        self.counters.cache_hits.fetch_add(hits, Ordering::Relaxed);
        // Own claims first, then the waits: a caller never waits while holding an unfetched
        // claim, so two callers waiting on each other's ranges cannot deadlock.
        if !claimed.is_empty() {
            let missing: Vec<Range<u64>> =
                claimed.iter().map(|(i, _)| ranges[*i].clone()).collect();
            let fetched = object_store::coalesce_ranges(
                &missing,
                |range| self.fetch_range(location, range),
                MERGE_GAP,
            )
            .await?;
            for ((i, tx), bytes) in claimed.into_iter().zip(fetched) {
                let r = &ranges[i];
                self.insert((name.clone(), r.start, r.end), bytes.clone());
                let _ = tx.send(Some(bytes.clone()));
                out[i] = Some(bytes);
            }
        }
        drop(claim);
        for (i, mut rx) in waiting {
            let arrived = rx
                .wait_for(Option::is_some)
                .await
                .ok()
                .and_then(|v| v.clone());
            out[i] = Some(match arrived {
                Some(bytes) => bytes,
                // Its fetcher was cancelled or failed: fetch it here.
                None => {
                    let r = &ranges[i];
                    let bytes = self.fetch_range(location, r.clone()).await?;
                    self.insert((name.clone(), r.start, r.end), bytes.clone());
                    bytes
                }
            });
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
