//! Asynchronous brick fetching (octree paper §4: "all data access requests are performed
//! asynchronously by a separate thread, and refinement continues only if data is immediately
//! available") for a source without an asynchronous path of its own (the local store).
//! Named worker threads take the most urgent request, read it from the source
//! (checksum-verified, decompressed by its codec) and send it back over a bounded crossbeam
//! channel; the frame loop moves it into the CPU cache. [`InlineReads`] is the same without
//! threads: a few reads per frame on the frame thread.
//!
//! Which request is read next is the shared policy of
//! [`WishList`](strata_source::wish_list::WishList): replaced every frame (stale requests
//! dropped, so a fast-moving camera cannot pile up work; at most `capacity` queued), demand
//! before prefetch, and requests already being read are not queued twice. A read cannot be
//! stopped, so nothing started here is cancelled.
//!
//! A record is read once: a decoding failure is worded by the source from the record already
//! read (`VolumeSource::decode_brick_record`: a store names its file and the brick), checked
//! by `a_damaged_brick_is_read_once_and_its_error_names_the_store_and_the_brick`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender};
use strata_source::wish_list::{Started, WishList};
use strata_source::{BrickFetcher, FetchResult, QueueCounters, SourceError, VolumeSource};
use strata_types::BrickId;

use crate::error::LoaderError;

/// A source that sleeps before every brick read: slow disks and network storage in tests.
pub struct SlowReader<R> {
    pub inner: R,
    pub delay: Duration,
}

impl<R: VolumeSource> VolumeSource for SlowReader<R> {
    fn location(&self) -> String {
        self.inner.location()
    }
    fn header(&self) -> &strata_storage::StoreHeader {
        self.inner.header()
    }
    fn skeleton(&self) -> &strata_storage::store::Skeleton {
        self.inner.skeleton()
    }
    fn histogram(&self) -> &strata_storage::histogram::Histogram {
        self.inner.histogram()
    }
    fn stats(&self) -> &strata_storage::store::StoreStats {
        self.inner.stats()
    }
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        std::thread::sleep(self.delay);
        self.inner.read_brick_record(id)
    }
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, SourceError> {
        std::thread::sleep(self.delay);
        self.inner.read_brick(id)
    }
    fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
        self.inner.decode_brick_record(id, record)
    }
}

struct QueueState {
    wishes: WishList,
    shutdown: bool,
}

struct Shared {
    state: Mutex<QueueState>,
    wake: Condvar,
    busy_workers: AtomicU64,
}

impl Shared {
    /// A poisoned lock means a worker panicked mid-update; the queue's data is still a valid
    /// set of requests, so carry on rather than cascade the panic into the frame loop.
    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

pub struct FetchWorkers {
    shared: Arc<Shared>,
    results: Receiver<FetchResult>,
    threads: Vec<JoinHandle<()>>,
    capacity: usize,
}

impl FetchWorkers {
    /// Starts `workers` threads named `strata-fetch-N`. The result channel holds at most
    /// `in_transit` bricks, which bounds the memory between a read and the CPU cache.
    pub fn start(
        reader: Arc<dyn VolumeSource>,
        workers: usize,
        capacity: usize,
        in_transit: usize,
    ) -> Result<Self, LoaderError> {
        let workers = workers.max(1);
        let wishes = WishList::new(capacity);
        let capacity = wishes.capacity();
        let shared = Arc::new(Shared {
            state: Mutex::new(QueueState {
                wishes,
                shutdown: false,
            }),
            wake: Condvar::new(),
            busy_workers: AtomicU64::new(0),
        });
        let (tx, rx) = crossbeam_channel::bounded(in_transit.max(1));
        let mut threads = Vec::with_capacity(workers);
        for i in 0..workers {
            let shared = shared.clone();
            let reader = reader.clone();
            let tx = tx.clone();
            let handle = std::thread::Builder::new()
                .name(format!("strata-fetch-{i}"))
                .spawn(move || worker_loop(&shared, reader.as_ref(), &tx))
                .map_err(|e| LoaderError::Worker(format!("cannot start fetch thread: {e}")))?;
            threads.push(handle);
        }
        Ok(FetchWorkers {
            shared,
            results: rx,
            threads,
            capacity,
        })
    }

    /// Replaces the queue with this frame's wishes (demand first, then prefetch, each in
    /// priority order; ids must already exclude what is cached). Returns how many were queued.
    pub fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let queued = {
            let mut state = self.shared.lock();
            state.wishes.replace(demand, prefetch);
            state.wishes.queued()
        };
        if queued > 0 {
            self.shared.wake.notify_all();
        }
        queued
    }

    /// Results ready now; never blocks.
    pub fn try_results(&self) -> Vec<FetchResult> {
        self.results.try_iter().collect()
    }

    /// The frame loop has stored a result: the id is no longer in flight.
    pub fn complete(&self, id: BrickId) {
        self.shared.lock().wishes.complete(id);
    }

    pub fn queued(&self) -> usize {
        self.shared.lock().wishes.queued()
    }

    pub fn in_flight(&self) -> usize {
        self.shared.lock().wishes.in_flight()
    }

    pub fn is_in_flight(&self, id: BrickId) -> bool {
        self.shared.lock().wishes.is_in_flight(id)
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn counters(&self) -> QueueCounters {
        self.shared.lock().wishes.counters()
    }

    /// Workers currently inside a read.
    pub fn busy(&self) -> u64 {
        self.shared.busy_workers.load(Ordering::Relaxed)
    }
}

impl Drop for FetchWorkers {
    fn drop(&mut self) {
        self.shared.lock().shutdown = true;
        self.shared.wake.notify_all();
        // Unblock workers waiting on a full result channel.
        while self.results.try_recv().is_ok() {}
        for t in self.threads.drain(..) {
            while !t.is_finished() {
                while self.results.try_recv().is_ok() {}
                std::thread::sleep(Duration::from_millis(1));
            }
            let _ = t.join();
        }
    }
}

fn worker_loop(shared: &Shared, reader: &dyn VolumeSource, results: &Sender<FetchResult>) {
    loop {
        let started = {
            let mut state = shared.lock();
            loop {
                if state.shutdown {
                    return;
                }
                if let Some(next) = state.wishes.take_most_urgent() {
                    break next;
                }
                state = shared.wake.wait(state).unwrap_or_else(|p| p.into_inner());
            }
        };
        shared.busy_workers.fetch_add(1, Ordering::Relaxed);
        let result = read_request(reader, started);
        shared.busy_workers.fetch_sub(1, Ordering::Relaxed);
        // Delivered before it is sent, so that the frame loop's `complete` finds it so.
        shared.lock().wishes.deliver(started.id, started.ticket);
        if results.send(result).is_err() {
            return;
        }
    }
}

/// Reads one request: record and decode separately (same checks and wording as
/// `read_brick`) to count the bytes read.
fn read_request(reader: &dyn VolumeSource, started: Started) -> FetchResult {
    let Started { id, class, .. } = started;
    let mut stored_bytes = 0;
    let outcome = reader.read_brick_record(id).and_then(|record| {
        stored_bytes = record.len() as u64;
        reader.decode_brick_record(id, &record).map(Arc::new)
    });
    FetchResult {
        id,
        class,
        outcome,
        stored_bytes,
    }
}

/// The reader threads' queue without the threads (`LoaderWork::Inline`): each
/// [`BrickFetcher::try_results`] reads the most urgent requests, at most `reads_per_call` of
/// them, on the calling (frame) thread: bounded work per frame, for a source without its own
/// asynchronous path where no thread can be started.
pub struct InlineReads {
    reader: Arc<dyn VolumeSource>,
    wishes: Mutex<WishList>,
    capacity: usize,
    reads_per_call: usize,
}

impl InlineReads {
    pub fn new(reader: Arc<dyn VolumeSource>, reads_per_call: usize, capacity: usize) -> Self {
        let wishes = WishList::new(capacity);
        InlineReads {
            reader,
            capacity: wishes.capacity(),
            wishes: Mutex::new(wishes),
            reads_per_call: reads_per_call.max(1),
        }
    }

    /// Poisoned only by a panic mid-update, which leaves a valid set of requests.
    fn lock(&self) -> MutexGuard<'_, WishList> {
        self.wishes.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl BrickFetcher for InlineReads {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let mut wishes = self.lock();
        wishes.replace(demand, prefetch);
        wishes.queued()
    }
    fn try_results(&self) -> Vec<FetchResult> {
        let mut results = Vec::new();
        while results.len() < self.reads_per_call {
            // Not held across the read: the source may take a while.
            let Some(started) = self.lock().take_most_urgent() else {
                break;
            };
            results.push(read_request(self.reader.as_ref(), started));
            self.lock().deliver(started.id, started.ticket);
        }
        results
    }
    fn complete(&self, id: BrickId) {
        self.lock().complete(id);
    }
    fn queued(&self) -> usize {
        self.lock().queued()
    }
    fn in_flight(&self) -> usize {
        self.lock().in_flight()
    }
    fn capacity(&self) -> usize {
        self.capacity
    }
    fn counters(&self) -> QueueCounters {
        self.lock().counters()
    }
}

impl BrickFetcher for FetchWorkers {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        FetchWorkers::set_requests(self, demand, prefetch)
    }
    fn try_results(&self) -> Vec<FetchResult> {
        FetchWorkers::try_results(self)
    }
    fn complete(&self, id: BrickId) {
        FetchWorkers::complete(self, id)
    }
    fn queued(&self) -> usize {
        FetchWorkers::queued(self)
    }
    fn in_flight(&self) -> usize {
        FetchWorkers::in_flight(self)
    }
    fn capacity(&self) -> usize {
        FetchWorkers::capacity(self)
    }
    fn counters(&self) -> QueueCounters {
        FetchWorkers::counters(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// A real (small) store that logs which bricks were read and takes 20 ms per read.
    struct Counting {
        log: Mutex<Vec<BrickId>>,
        store: strata_storage::Store,
        _dir: tempfile::TempDir,
    }
    impl Counting {
        fn new() -> Self {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("p.strata");
            strata_storage::phantom::Phantom::cube(40)
                .write_store(&path, &strata_storage::import::ImportOptions::default())
                .unwrap();
            let store = strata_storage::Store::open(&path).unwrap();
            Counting {
                log: Mutex::new(Vec::new()),
                store,
                _dir: dir,
            }
        }
    }
    impl VolumeSource for Counting {
        fn location(&self) -> String {
            self.store.location()
        }
        fn header(&self) -> &strata_storage::StoreHeader {
            self.store.header()
        }
        fn skeleton(&self) -> &strata_storage::store::Skeleton {
            self.store.skeleton()
        }
        fn histogram(&self) -> &strata_storage::histogram::Histogram {
            self.store.histogram()
        }
        fn stats(&self) -> &strata_storage::store::StoreStats {
            self.store.stats()
        }
        fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
            self.log.lock().unwrap_or_else(|p| p.into_inner()).push(id);
            std::thread::sleep(Duration::from_millis(20));
            // Ids outside the phantom's octree come back as errors: still a result.
            VolumeSource::read_brick_record(&self.store, id)
        }
    }

    #[test]
    fn stale_requests_are_dropped_and_the_queue_stays_bounded() {
        let reader = Arc::new(Counting::new());
        let workers = FetchWorkers::start(reader.clone(), 1, 8, 2).unwrap();
        let ids: Vec<(BrickId, f64)> = (0..100)
            .map(|i| (BrickId::new(0, [i, 0, 0]), i as f64))
            .collect();
        assert_eq!(
            workers.set_requests(&ids, &[]),
            8,
            "capacity bounds the queue"
        );
        assert!(workers.counters().overflow_dropped >= 92);
        // A new view wants something else: the old requests go.
        let other = [(BrickId::new(1, [0, 0, 0]), 1.0)];
        workers.set_requests(&other, &[]);
        assert!(workers.queued() <= 1);
        assert!(workers.counters().stale_dropped >= 7);
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut got = Vec::new();
        while got.len() < 2 && Instant::now() < deadline {
            for r in workers.try_results() {
                workers.complete(r.id);
                got.push(r.id);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(got.contains(&BrickId::new(1, [0, 0, 0])));
        let read = reader.log.lock().unwrap().clone();
        assert!(read.len() <= 3, "stale requests were read anyway: {read:?}");
    }

    /// A store whose reads are counted: records read, and decodings worded by the store.
    struct ReadCounting {
        records_read: std::sync::atomic::AtomicUsize,
        store: strata_storage::Store,
    }
    impl VolumeSource for ReadCounting {
        fn location(&self) -> String {
            self.store.location()
        }
        fn header(&self) -> &strata_storage::StoreHeader {
            self.store.header()
        }
        fn skeleton(&self) -> &strata_storage::store::Skeleton {
            self.store.skeleton()
        }
        fn histogram(&self) -> &strata_storage::histogram::Histogram {
            self.store.histogram()
        }
        fn stats(&self) -> &strata_storage::store::StoreStats {
            self.store.stats()
        }
        fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
            self.records_read.fetch_add(1, Ordering::Relaxed);
            VolumeSource::read_brick_record(&self.store, id)
        }
        fn decode_brick_record(&self, id: BrickId, record: &[u8]) -> Result<Vec<u16>, SourceError> {
            self.store.decode_brick_record(id, record)
        }
    }

    #[test]
    fn a_damaged_brick_is_read_once_and_its_error_names_the_store_and_the_brick() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("damaged.strata");
        strata_storage::phantom::Phantom::cube(40)
            .write_store(&path, &strata_storage::import::ImportOptions::default())
            .unwrap();
        let root = BrickId::new(1, [0, 0, 0]);
        strata_storage::Store::corrupt_brick_for_tests(&path, root, 20).unwrap();
        let reader = Arc::new(ReadCounting {
            records_read: std::sync::atomic::AtomicUsize::new(0),
            store: strata_storage::Store::open(&path).unwrap(),
        });
        let inline = InlineReads::new(reader.clone(), 4, 8);
        inline.set_requests(&[(root, 1.0)], &[]);
        let results = inline.try_results();
        assert_eq!(results.len(), 1);
        let error = match &results[0].outcome {
            Err(e) => e.to_string(),
            Ok(_) => panic!("a brick damaged on disk decoded"),
        };
        for named in ["damaged.strata", "pack-", "brick level 1 at [0, 0, 0]"] {
            assert!(error.contains(named), "{named:?} missing from: {error}");
        }
        assert_eq!(
            reader.records_read.load(Ordering::Relaxed),
            1,
            "the record was read again to word the error"
        );
        assert!(results[0].stored_bytes > 0);
        inline.complete(root);
        assert_eq!(inline.in_flight(), 0);
    }

    #[test]
    fn demand_overtakes_prefetch() {
        let reader = Arc::new(Counting::new());
        let workers = FetchWorkers::start(reader.clone(), 1, 16, 2).unwrap();
        let prefetch: Vec<(BrickId, f64)> = (0..4)
            .map(|i| (BrickId::new(0, [i, 0, 0]), 100.0))
            .collect();
        let demand = [(BrickId::new(0, [9, 0, 0]), 0.1)];
        // Occupy the worker first so ordering is decided from a full queue.
        workers.set_requests(&[(BrickId::new(0, [50, 0, 0]), 1.0)], &[]);
        std::thread::sleep(Duration::from_millis(5));
        workers.set_requests(&demand, &prefetch);
        let deadline = Instant::now() + Duration::from_secs(5);
        while reader.log.lock().unwrap().len() < 3 && Instant::now() < deadline {
            for r in workers.try_results() {
                workers.complete(r.id);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let read = reader.log.lock().unwrap().clone();
        assert_eq!(
            read.get(1),
            Some(&BrickId::new(0, [9, 0, 0])),
            "demand first: {read:?}"
        );
    }
}
