//! strata-source: the volume-source seam. Everything that reads a volume (the streaming loader,
//! `strata render|flythrough|info|verify`, the viewer's slices) reads through
//! [`VolumeSource`]: the header, the octree skeleton (per-node ranges), the histogram and the
//! bricks in their stored form (compressed and checksummed, verified where they are decoded).
//! A local [`Store`] implements it here; the data service's client (strata-service) implements
//! it over HTTP; the OME-Zarr reader (strata-omezarr) is a third.
//!
//! Brick requests are asynchronous: [`VolumeSource::start_fetching`] returns a
//! [`BrickFetcher`], a priority queue the loader rewrites every frame (demand before prefetch,
//! then by priority) and polls without waiting. Its policy is written once, in
//! [`wish_list::WishList`] (pure: no threads, no async), and every executor runs it: the
//! loader's reader threads and inline reads for a source without its own asynchronous path
//! (the local store), `task_queue::TaskQueue` (itself a [`BrickFetcher`]) for the sources whose
//! requests are tokio tasks (the data service's client, the OME-Zarr reader), and the browser
//! viewer's `fetch()` queue.
//!
//! The default feature `local` brings the local store (strata-storage's `local`), the tokio
//! task queue and [`verify_source`]'s threads. Without it the crate builds for
//! `wasm32-unknown-unknown`: the seam, its errors and the data service's wire format ([`wire`]),
//! what the browser viewer's client implements.

#[cfg(feature = "local")]
pub mod task_queue;
pub mod wire;
pub mod wish_list;

use std::sync::Arc;

use strata_storage::brick::{decode_brick, BrickDecodeError};
use strata_storage::histogram::Histogram;
use strata_storage::store::{NodeInfo, Skeleton, StoreStats};
#[cfg(feature = "local")]
use strata_storage::Store;
use strata_storage::{StorageError, StoreHeader};
use strata_types::{BrickId, OctreeLayout};

/// A brick decoded to its 36³ stored values (x fastest), shared without copying.
pub type Brick = Arc<Vec<u16>>;

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(transparent)]
    Storage(#[from] StorageError),
    /// A brick whose record failed verification (after the re-request, for a remote source).
    #[error("{location}: brick level {} at {:?} is damaged: {message}", id.level, id.coords)]
    Damaged {
        location: String,
        id: BrickId,
        message: String,
    },
    /// The source cannot be reached (connection refused, timed out, server gone).
    #[error("{location}: {message}")]
    Unavailable { location: String, message: String },
    /// The source answered, but not with what was asked (unknown store, wrong token, ...).
    #[error("{location}: {message}")]
    Refused { location: String, message: String },
}

impl SourceError {
    pub fn damaged(location: &str, id: BrickId, e: BrickDecodeError) -> Self {
        SourceError::Damaged {
            location: location.to_string(),
            id,
            message: e.to_string(),
        }
    }
}

/// How a source is doing, for the status line ("connection lost, retrying").
#[derive(Clone, Debug, Default, PartialEq)]
pub enum SourceStatus {
    #[default]
    Available,
    /// Requests fail to reach the source and are being retried with backoff; what is loaded
    /// stays on screen.
    Retrying { since_seconds: f64, message: String },
}

impl SourceStatus {
    pub fn is_retrying(&self) -> bool {
        matches!(self, SourceStatus::Retrying { .. })
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum RequestClass {
    /// Speculative; any demand request overtakes it.
    Prefetch,
    /// The current cut is waiting for it.
    Demand,
}

/// One delivered request.
pub struct FetchResult {
    pub id: BrickId,
    pub class: RequestClass,
    pub outcome: Result<Brick, SourceError>,
    /// Bytes of the record as stored (what crossed the disk or the network).
    pub stored_bytes: u64,
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct QueueCounters {
    /// Queued requests removed because a newer view no longer wanted them.
    pub stale_dropped: u64,
    /// Requests not queued because the queue was full (asked again next frame if still wanted).
    pub overflow_dropped: u64,
    pub demand_started: u64,
    pub prefetch_started: u64,
    /// Requests already on the wire aborted because the view no longer wanted them.
    pub cancelled_in_flight: u64,
    /// Requests sent again: after a connection error, 429/503, or a checksum failure.
    pub retried: u64,
    /// Records that failed their checksum on arrival (each re-requested once).
    pub checksum_failures: u64,
    /// Most requests that were in flight at once.
    pub max_in_flight: u64,
}

/// Sizes for a source's asynchronous request path.
#[derive(Clone, Copy, Debug)]
pub struct FetchOptions {
    /// Bound on queued requests (stale ones are replaced every frame anyway).
    pub max_queued: usize,
    /// Bricks fetched but not yet taken by the loader, plus those being fetched.
    pub max_in_transit: usize,
    /// Local reader threads (sources with their own asynchronous path ignore it).
    pub threads: usize,
}

/// An asynchronous, cancellable, prioritised brick request queue. Never blocks.
pub trait BrickFetcher: Send {
    /// Replaces the queue with this frame's wishes (demand first, then prefetch, each in
    /// priority order, higher = sooner; ids must already exclude what is cached). Requests the
    /// new wishes no longer name are dropped, or cancelled when already on their way.
    /// Returns how many are queued.
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize;
    /// Results ready now.
    fn try_results(&self) -> Vec<FetchResult>;
    /// The loader has stored a result: the id is no longer in flight.
    fn complete(&self, id: BrickId);
    fn queued(&self) -> usize;
    /// Requests being read or transferred, plus results not yet taken.
    fn in_flight(&self) -> usize;
    fn capacity(&self) -> usize;
    fn counters(&self) -> QueueCounters;
    fn status(&self) -> SourceStatus {
        SourceStatus::Available
    }
}

/// One volume, wherever it lives.
pub trait VolumeSource: Send + Sync {
    /// A path or URL, for messages.
    fn location(&self) -> String;
    fn header(&self) -> &StoreHeader;
    fn skeleton(&self) -> &Skeleton;
    fn histogram(&self) -> &Histogram;
    fn stats(&self) -> &StoreStats;
    /// One brick's record as stored (kind, checksum, compressed body), unverified. Blocking:
    /// for reader threads, `verify`, the slice views and up-front loads; never a frame.
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError>;
    /// The asynchronous request path, when the source has one of its own (the remote client);
    /// `None` lets the loader read through [`VolumeSource::read_brick`] on its threads.
    fn start_fetching(
        &self,
        _options: FetchOptions,
    ) -> Option<Result<Box<dyn BrickFetcher>, SourceError>> {
        None
    }
    /// Whether the source is reachable (always, for a local one).
    fn status(&self) -> SourceStatus {
        SourceStatus::Available
    }
    /// Volumes in the source: a 4-D store's frames (time points, phases); 1 for most.
    fn frame_count(&self) -> u32 {
        1
    }
    /// Frame `frame` of a 4-D source as a volume source of its own (same header and grid,
    /// that frame's skeleton and bricks); `None` past the last frame or for a source without
    /// frames.
    fn frame_source(self: Arc<Self>, _frame: u32) -> Option<Arc<dyn VolumeSource>> {
        None
    }

    fn layout(&self) -> &OctreeLayout {
        &self.header().layout
    }
    fn node(&self, id: BrickId) -> Option<NodeInfo> {
        self.skeleton().node(id)
    }
    /// Reads, verifies (checksum) and decompresses one brick.
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        let record = self.read_brick_record(id)?;
        self.decode_brick_record(id, &record)
    }
    /// Verifies and decompresses `record`, read as brick `id` by
    /// [`VolumeSource::read_brick_record`], with this source's error wording (a store names
    /// its file and the brick): a reader that kept the record words a failure without a
    /// second read.
    fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
        decode_brick(id, record).map_err(|e| SourceError::damaged(&self.location(), id, e))
    }
}

/// The local store: a sled directory on this machine.
#[cfg(feature = "local")]
impl VolumeSource for Store {
    fn location(&self) -> String {
        self.path().display().to_string()
    }
    fn header(&self) -> &StoreHeader {
        Store::header(self)
    }
    fn skeleton(&self) -> &Skeleton {
        Store::skeleton(self)
    }
    fn histogram(&self) -> &Histogram {
        Store::histogram(self)
    }
    fn stats(&self) -> &StoreStats {
        Store::stats(self)
    }
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        Ok(Store::read_brick_record(self, id)?)
    }
    /// The store's own reader keeps its error wording (file name, level, coordinates).
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        Ok(Store::read_brick(self, id)?)
    }
    fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
        Ok(self.decode_frame_brick_record(0, id, record)?)
    }
    fn node(&self, id: BrickId) -> Option<NodeInfo> {
        Store::node(self, id)
    }
    fn frame_count(&self) -> u32 {
        Store::frame_count(self)
    }
    fn frame_source(self: Arc<Self>, frame: u32) -> Option<Arc<dyn VolumeSource>> {
        if frame == 0 {
            return Some(self);
        }
        (frame < Store::frame_count(&self))
            .then(|| Arc::new(StoreFrame { store: self, frame }) as Arc<dyn VolumeSource>)
    }
}

/// One frame ≥ 1 of a local 4-D store (frame 0 is the store itself).
#[cfg(feature = "local")]
struct StoreFrame {
    store: Arc<Store>,
    frame: u32,
}

#[cfg(feature = "local")]
impl VolumeSource for StoreFrame {
    fn location(&self) -> String {
        self.store.path().display().to_string()
    }
    fn header(&self) -> &StoreHeader {
        self.store.header()
    }
    fn skeleton(&self) -> &Skeleton {
        self.store
            .frame_skeleton(self.frame)
            .unwrap_or_else(|| self.store.skeleton())
    }
    fn histogram(&self) -> &Histogram {
        self.store.histogram()
    }
    fn stats(&self) -> &StoreStats {
        self.store.stats()
    }
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        Ok(self.store.read_frame_brick_record(self.frame, id)?)
    }
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        Ok(self.store.read_frame_brick(self.frame, id)?)
    }
    fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
        Ok(self
            .store
            .decode_frame_brick_record(self.frame, id, record)?)
    }
    fn frame_count(&self) -> u32 {
        self.store.frame_count()
    }
    fn frame_source(self: Arc<Self>, frame: u32) -> Option<Arc<dyn VolumeSource>> {
        self.store.clone().frame_source(frame)
    }
}

impl<S: VolumeSource + ?Sized> VolumeSource for Arc<S> {
    fn location(&self) -> String {
        (**self).location()
    }
    fn header(&self) -> &StoreHeader {
        (**self).header()
    }
    fn skeleton(&self) -> &Skeleton {
        (**self).skeleton()
    }
    fn histogram(&self) -> &Histogram {
        (**self).histogram()
    }
    fn stats(&self) -> &StoreStats {
        (**self).stats()
    }
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        (**self).read_brick_record(id)
    }
    fn start_fetching(
        &self,
        options: FetchOptions,
    ) -> Option<Result<Box<dyn BrickFetcher>, SourceError>> {
        (**self).start_fetching(options)
    }
    fn status(&self) -> SourceStatus {
        (**self).status()
    }
    fn node(&self, id: BrickId) -> Option<NodeInfo> {
        (**self).node(id)
    }
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        (**self).read_brick(id)
    }
    fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
        (**self).decode_brick_record(id, record)
    }
    fn frame_count(&self) -> u32 {
        (**self).frame_count()
    }
    fn frame_source(self: Arc<Self>, frame: u32) -> Option<Arc<dyn VolumeSource>> {
        S::frame_source(Arc::clone(&*self), frame)
    }
}

/// Checks every brick the skeleton stores a node for (every brick, for a dense skeleton;
/// implied nodes of collapsed constant subtrees are not read): present, checksum,
/// decompression, and range equal to the skeleton's. Reads through `read_brick` on `threads`
/// threads (many in flight for a remote source). Returns one message per problem found.
#[cfg(feature = "local")]
pub fn verify_source(
    source: &dyn VolumeSource,
    threads: usize,
    on_progress: &(dyn Fn(u64, u64) + Sync),
) -> Vec<String> {
    let skeleton = source.skeleton();
    let ids: Vec<BrickId> = (0..skeleton.level_count())
        .flat_map(|level| skeleton.stored_in_level_iter(level).map(|(id, _)| id))
        .collect();
    let total = ids.len() as u64;
    let next = std::sync::atomic::AtomicUsize::new(0);
    let problems = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for t in 0..threads.max(1) {
            let (ids, next, problems) = (&ids, &next, &problems);
            let spawned = std::thread::Builder::new()
                .name(format!("strata-verify-{t}"))
                .spawn_scoped(scope, move || loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(&id) = ids.get(i) else { break };
                    let problem = match source.read_brick(id) {
                        Err(e) => Some(e.to_string()),
                        Ok(voxels) => {
                            let r = strata_storage::brick::value_range(&voxels);
                            let node = source.node(id).unwrap_or_default();
                            ((r.min, r.max) != (node.min, node.max)).then(|| {
                                format!(
                                    "{}: brick {id:?} range {}..{} differs from the skeleton's {}..{}",
                                    source.location(),
                                    r.min,
                                    r.max,
                                    node.min,
                                    node.max
                                )
                            })
                        }
                    };
                    if let Some(p) = problem {
                        problems.lock().unwrap_or_else(|p| p.into_inner()).push(p);
                    }
                    on_progress(i as u64 + 1, total);
                });
            if let Err(e) = spawned {
                problems
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push(format!("cannot start a verify thread: {e}"));
            }
        }
    });
    problems.into_inner().unwrap_or_else(|p| p.into_inner())
}

#[cfg(all(test, feature = "local"))]
mod tests {
    use super::*;

    #[test]
    fn local_store_reads_records_as_stored_and_verifies_them() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.strata");
        strata_storage::phantom::Phantom::cube(40)
            .write_store(&path, &strata_storage::import::ImportOptions::default())
            .unwrap();
        let local = Store::open(&path).unwrap();
        let id = BrickId::new(0, [0, 0, 0]);
        let record = local.read_brick_record(id).unwrap();
        assert_eq!(
            decode_brick(id, &record).unwrap(),
            VolumeSource::read_brick(&local, id).unwrap()
        );
        assert!(verify_source(&local, 2, &|_, _| {}).is_empty());
        let source: &dyn VolumeSource = &local;
        assert_eq!(source.node(id), local.node(id));
        assert!(!local.header().generation_id().is_empty());
    }
}
