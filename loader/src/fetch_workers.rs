//! Asynchronous brick fetching (octree paper §4: "all data access requests are performed
//! asynchronously by a separate thread, and refinement continues only if data is immediately
//! available"). Named worker threads take the most urgent request, read it from the store
//! (checksum-verified, lz4-decompressed) and send it back over a bounded crossbeam channel; the
//! frame loop moves it into the CPU cache.
//!
//! The queue holds at most `capacity` requests. Each frame the loader replaces its contents
//! with what the current view wants: requests the new view no longer names are dropped as
//! stale (so a fast-moving camera cannot pile up work), demand always sorts before prefetch,
//! and requests already being read are not queued twice.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender};
use strata_storage::{BrickId, StorageError, Store};

use crate::cpu_cache::Brick;
use crate::error::LoaderError;

/// Where bricks come from. `Store` is the real one; tests wrap it to inject latency.
pub trait BrickReader: Send + Sync {
    /// Reads, verifies and decompresses one 36³ brick.
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, StorageError>;
    /// Compressed bytes the read took from the store (I/O accounting).
    fn stored_brick_bytes(&self, id: BrickId) -> u64;
}

impl BrickReader for Store {
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, StorageError> {
        Store::read_brick(self, id)
    }
    fn stored_brick_bytes(&self, id: BrickId) -> u64 {
        Store::stored_brick_bytes(self, id).unwrap_or(0)
    }
}

/// A reader that sleeps before every read: slow disks and network storage in tests.
pub struct SlowReader<R> {
    pub inner: R,
    pub delay: Duration,
}

impl<R: BrickReader> BrickReader for SlowReader<R> {
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, StorageError> {
        std::thread::sleep(self.delay);
        self.inner.read_brick(id)
    }
    fn stored_brick_bytes(&self, id: BrickId) -> u64 {
        self.inner.stored_brick_bytes(id)
    }
}

impl<R: BrickReader + ?Sized> BrickReader for Arc<R> {
    fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, StorageError> {
        (**self).read_brick(id)
    }
    fn stored_brick_bytes(&self, id: BrickId) -> u64 {
        (**self).stored_brick_bytes(id)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum RequestClass {
    /// Speculative; any demand request overtakes it.
    Prefetch,
    /// The current cut is waiting for it.
    Demand,
}

pub struct FetchResult {
    pub id: BrickId,
    pub class: RequestClass,
    pub outcome: Result<Brick, StorageError>,
    pub stored_bytes: u64,
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct QueueCounters {
    /// Requests removed because a newer view no longer wanted them.
    pub stale_dropped: u64,
    /// Requests not queued because the queue was full (asked again next frame if still wanted).
    pub overflow_dropped: u64,
    pub demand_started: u64,
    pub prefetch_started: u64,
}

struct QueueState {
    queued: HashMap<BrickId, (RequestClass, f64)>,
    in_flight: HashSet<BrickId>,
    counters: QueueCounters,
    shutdown: bool,
}

struct Shared {
    state: Mutex<QueueState>,
    wake: Condvar,
    capacity: usize,
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
}

impl FetchWorkers {
    /// Starts `workers` threads named `strata-fetch-N`. The result channel holds at most
    /// `in_transit` bricks, which bounds the memory between a read and the CPU cache.
    pub fn start(
        reader: Arc<dyn BrickReader>,
        workers: usize,
        capacity: usize,
        in_transit: usize,
    ) -> Result<Self, LoaderError> {
        let workers = workers.max(1);
        let shared = Arc::new(Shared {
            state: Mutex::new(QueueState {
                queued: HashMap::new(),
                in_flight: HashSet::new(),
                counters: QueueCounters::default(),
                shutdown: false,
            }),
            wake: Condvar::new(),
            capacity: capacity.max(1),
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
        })
    }

    /// Replaces the queue with this frame's wishes (demand first, then prefetch, each in
    /// priority order; ids must already exclude what is cached). Returns how many were queued.
    pub fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let mut state = self.shared.lock();
        let mut wanted: HashMap<BrickId, (RequestClass, f64)> = HashMap::new();
        let candidates = demand
            .iter()
            .map(|&(id, p)| (id, RequestClass::Demand, p))
            .chain(
                prefetch
                    .iter()
                    .map(|&(id, p)| (id, RequestClass::Prefetch, p)),
            );
        let mut overflow = 0;
        for (id, class, priority) in candidates {
            if state.in_flight.contains(&id) || wanted.contains_key(&id) {
                continue;
            }
            if wanted.len() >= self.shared.capacity {
                overflow += 1;
                continue;
            }
            wanted.insert(id, (class, priority));
        }
        let stale = state
            .queued
            .keys()
            .filter(|id| !wanted.contains_key(id))
            .count() as u64;
        state.counters.stale_dropped += stale;
        state.counters.overflow_dropped += overflow;
        state.queued = wanted;
        let n = state.queued.len();
        drop(state);
        if n > 0 {
            self.shared.wake.notify_all();
        }
        n
    }

    /// Results ready now; never blocks.
    pub fn try_results(&self) -> Vec<FetchResult> {
        self.results.try_iter().collect()
    }

    /// The frame loop has stored a result: the id is no longer in flight.
    pub fn complete(&self, id: BrickId) {
        self.shared.lock().in_flight.remove(&id);
    }

    pub fn queued(&self) -> usize {
        self.shared.lock().queued.len()
    }

    pub fn in_flight(&self) -> usize {
        self.shared.lock().in_flight.len()
    }

    pub fn is_in_flight(&self, id: BrickId) -> bool {
        self.shared.lock().in_flight.contains(&id)
    }

    pub fn capacity(&self) -> usize {
        self.shared.capacity
    }

    pub fn counters(&self) -> QueueCounters {
        self.shared.lock().counters
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

fn worker_loop(shared: &Shared, reader: &dyn BrickReader, results: &Sender<FetchResult>) {
    loop {
        let (id, class) = {
            let mut state = shared.lock();
            loop {
                if state.shutdown {
                    return;
                }
                let best = state
                    .queued
                    .iter()
                    .max_by(|a, b| {
                        (a.1 .0, a.1 .1)
                            .partial_cmp(&(b.1 .0, b.1 .1))
                            .unwrap_or(std::cmp::Ordering::Equal)
                    })
                    .map(|(&id, &(class, _))| (id, class));
                if let Some((id, class)) = best {
                    state.queued.remove(&id);
                    state.in_flight.insert(id);
                    match class {
                        RequestClass::Demand => state.counters.demand_started += 1,
                        RequestClass::Prefetch => state.counters.prefetch_started += 1,
                    }
                    break (id, class);
                }
                state = shared.wake.wait(state).unwrap_or_else(|p| p.into_inner());
            }
        };
        shared.busy_workers.fetch_add(1, Ordering::Relaxed);
        let outcome = reader.read_brick(id).map(Arc::new);
        let stored_bytes = if outcome.is_ok() {
            reader.stored_brick_bytes(id)
        } else {
            0
        };
        shared.busy_workers.fetch_sub(1, Ordering::Relaxed);
        if results
            .send(FetchResult {
                id,
                class,
                outcome,
                stored_bytes,
            })
            .is_err()
        {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    struct Counting(Mutex<Vec<BrickId>>);
    impl BrickReader for Counting {
        fn read_brick(&self, id: BrickId) -> Result<Vec<u16>, StorageError> {
            self.0.lock().unwrap_or_else(|p| p.into_inner()).push(id);
            std::thread::sleep(Duration::from_millis(20));
            Ok(vec![id.coords[0] as u16; 4])
        }
        fn stored_brick_bytes(&self, _: BrickId) -> u64 {
            8
        }
    }

    #[test]
    fn stale_requests_are_dropped_and_the_queue_stays_bounded() {
        let reader = Arc::new(Counting(Mutex::new(Vec::new())));
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
        let read = reader.0.lock().unwrap().clone();
        assert!(read.len() <= 3, "stale requests were read anyway: {read:?}");
    }

    #[test]
    fn demand_overtakes_prefetch() {
        let reader = Arc::new(Counting(Mutex::new(Vec::new())));
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
        while reader.0.lock().unwrap().len() < 3 && Instant::now() < deadline {
            for r in workers.try_results() {
                workers.complete(r.id);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let read = reader.0.lock().unwrap().clone();
        assert_eq!(
            read.get(1),
            Some(&BrickId::new(0, [9, 0, 0])),
            "demand first: {read:?}"
        );
    }
}
