//! The streaming source's own request path ([`VolumeSource::start_fetching`]): every brick
//! request is one tokio task on the object-store runtime that assembles the brick with zarrs'
//! asynchronous sharded reader. A request that is on the wire when the loader's newer wish
//! lists stop naming it (one view of grace, as the data service's `RemoteFetcher`) is aborted:
//! the task is dropped at its next await, which drops object_store's pending requests and so
//! closes their connections mid-transfer instead of letting stale bytes finish arriving.
//!
//! The queue logic (priorities, capacity, grace, `complete`) is the data service client's
//! (`strata_service::client::RemoteFetcher`); what differs is the request (a brick assembled
//! from chunks, no retry loop: object_store retries transient failures itself).
//!
//! [`VolumeSource::start_fetching`]: strata_source::VolumeSource::start_fetching

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use crossbeam_channel::{Receiver, Sender};
use strata_source::{BrickFetcher, FetchResult, QueueCounters, RequestClass, SourceError};
use strata_storage::BrickId;

/// Assembles one brick asynchronously (the streaming source's reads, awaited on the I/O
/// runtime); dropping the future cancels its requests.
pub(crate) type AssembleBrick = Arc<
    dyn Fn(BrickId) -> futures::future::BoxFuture<'static, Result<Vec<u16>, SourceError>>
        + Send
        + Sync,
>;

/// What every request task needs.
struct Brickmaker {
    assemble: AssembleBrick,
    bytes_per_sample: usize,
}

struct InFlight {
    /// `set_requests` call that last named it.
    named_at: u64,
    /// The result is in the channel; only `complete` ends it now.
    delivered: bool,
    abort: Option<tokio::task::AbortHandle>,
}

struct FetchState {
    queued: HashMap<BrickId, (RequestClass, f64)>,
    in_flight: HashMap<BrickId, InFlight>,
    counters: QueueCounters,
    calls: u64,
}

struct FetchShared {
    state: Mutex<FetchState>,
    wake: tokio::sync::Notify,
    results: Sender<FetchResult>,
    capacity: usize,
    max_in_flight: usize,
}

impl FetchShared {
    fn lock(&self) -> MutexGuard<'_, FetchState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The asynchronous request queue of the streaming source (`OmeZarrSource`).
pub struct ZarrFetcher {
    shared: Arc<FetchShared>,
    results: Receiver<FetchResult>,
    dispatcher: tokio::task::AbortHandle,
}

impl ZarrFetcher {
    pub(crate) fn start(
        runtime: &tokio::runtime::Runtime,
        assemble: AssembleBrick,
        bytes_per_sample: usize,
        capacity: usize,
        max_in_flight: usize,
    ) -> Self {
        // Unbounded in type, bounded in fact: at most `max_in_flight` requests exist between
        // dispatch and `complete`, and each sends one result.
        let (tx, rx) = crossbeam_channel::unbounded();
        let shared = Arc::new(FetchShared {
            state: Mutex::new(FetchState {
                queued: HashMap::new(),
                in_flight: HashMap::new(),
                counters: QueueCounters::default(),
                calls: 0,
            }),
            wake: tokio::sync::Notify::new(),
            results: tx,
            capacity,
            max_in_flight,
        });
        let dispatcher = runtime
            .spawn(dispatch(
                Arc::new(Brickmaker {
                    assemble,
                    bytes_per_sample,
                }),
                shared.clone(),
            ))
            .abort_handle();
        ZarrFetcher {
            shared,
            results: rx,
            dispatcher,
        }
    }
}

/// Starts the most urgent queued requests while fewer than `max_in_flight` are out.
async fn dispatch(maker: Arc<Brickmaker>, shared: Arc<FetchShared>) {
    loop {
        {
            let mut state = shared.lock();
            while state.in_flight.len() < shared.max_in_flight {
                let best = state
                    .queued
                    .iter()
                    .max_by(|a, b| {
                        (a.1 .0, a.1 .1)
                            .partial_cmp(&(b.1 .0, b.1 .1))
                            .unwrap_or(std::cmp::Ordering::Equal)
                    })
                    .map(|(&id, &(class, _))| (id, class));
                let Some((id, class)) = best else { break };
                state.queued.remove(&id);
                match class {
                    RequestClass::Demand => state.counters.demand_started += 1,
                    RequestClass::Prefetch => state.counters.prefetch_started += 1,
                }
                let task = tokio::spawn(fetch_one(maker.clone(), shared.clone(), id, class));
                let named_at = state.calls;
                state.in_flight.insert(
                    id,
                    InFlight {
                        named_at,
                        delivered: false,
                        abort: Some(task.abort_handle()),
                    },
                );
                let n = state.in_flight.len() as u64;
                state.counters.max_in_flight = state.counters.max_in_flight.max(n);
            }
        }
        shared.wake.notified().await;
    }
}

async fn fetch_one(
    maker: Arc<Brickmaker>,
    shared: Arc<FetchShared>,
    id: BrickId,
    class: RequestClass,
) {
    let outcome = (maker.assemble)(id).await;
    let mut state = shared.lock();
    let Some(entry) = state.in_flight.get_mut(&id) else {
        return; // cancelled meanwhile
    };
    entry.delivered = true;
    entry.abort = None;
    // The stored samples' bytes (what crossed the wire is in the source's transfer counters:
    // chunks are shared between neighbouring bricks).
    let (outcome, stored_bytes) = match outcome {
        Ok(voxels) => {
            let bytes = (voxels.len() * maker.bytes_per_sample) as u64;
            (Ok(Arc::new(voxels)), bytes)
        }
        Err(e) => (Err(e), 0),
    };
    let _ = shared.results.send(FetchResult {
        id,
        class,
        outcome,
        stored_bytes,
    });
}

impl BrickFetcher for ZarrFetcher {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let mut state = self.shared.lock();
        state.calls += 1;
        let call = state.calls;
        let mut wanted: HashMap<BrickId, (RequestClass, f64)> = HashMap::new();
        let mut overflow = 0;
        let candidates = demand
            .iter()
            .map(|&(id, p)| (id, RequestClass::Demand, p))
            .chain(
                prefetch
                    .iter()
                    .map(|&(id, p)| (id, RequestClass::Prefetch, p)),
            );
        for (id, class, priority) in candidates {
            if let Some(f) = state.in_flight.get_mut(&id) {
                f.named_at = call;
                continue;
            }
            if wanted.contains_key(&id) {
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
        // On the wire but named by neither this view nor the previous one: abort, freeing the
        // slot (and the connection) for what the view wants now. One view of grace keeps a
        // request that flickers at the edge of the wish list from being cancelled and asked
        // for again.
        let cancel: Vec<BrickId> = state
            .in_flight
            .iter()
            .filter(|(_, f)| !f.delivered && f.named_at + 1 < call)
            .map(|(&id, _)| id)
            .collect();
        for id in &cancel {
            if let Some(f) = state.in_flight.remove(id) {
                if let Some(abort) = f.abort {
                    abort.abort();
                }
            }
        }
        state.counters.cancelled_in_flight += cancel.len() as u64;
        let n = state.queued.len();
        drop(state);
        self.shared.wake.notify_one();
        n
    }
    fn try_results(&self) -> Vec<FetchResult> {
        self.results.try_iter().collect()
    }
    fn complete(&self, id: BrickId) {
        let removed = {
            let mut state = self.shared.lock();
            match state.in_flight.get(&id) {
                Some(f) if f.delivered => state.in_flight.remove(&id).is_some(),
                _ => false,
            }
        };
        if removed {
            self.shared.wake.notify_one();
        }
    }
    fn queued(&self) -> usize {
        self.shared.lock().queued.len()
    }
    fn in_flight(&self) -> usize {
        self.shared.lock().in_flight.len()
    }
    fn capacity(&self) -> usize {
        self.shared.capacity
    }
    fn counters(&self) -> QueueCounters {
        self.shared.lock().counters
    }
}

impl Drop for ZarrFetcher {
    fn drop(&mut self) {
        self.dispatcher.abort();
        let mut state = self.shared.lock();
        for (_, f) in state.in_flight.drain() {
            if let Some(abort) = f.abort {
                abort.abort();
            }
        }
    }
}
