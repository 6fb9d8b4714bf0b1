//! The request queue of the asynchronous brick sources (the data service's `RemoteFetcher`,
//! the OME-Zarr source's object-store reader): every started request is one tokio task that
//! produces one brick, and the queue decides which request starts next and which one is no
//! longer wanted.
//!
//! The rules, shared by both sources so that they behave alike under the loader:
//! - `set_requests` replaces the queued wish list (demand before prefetch, then by priority;
//!   at most `capacity` entries, the rest counted as overflow and asked again next frame);
//! - at most `max_in_flight` requests run at once;
//! - a request on the wire that neither this view nor the previous one names is aborted: its
//!   task is dropped at its next await, which drops the client's pending request and so
//!   closes (or resets) its connection mid-transfer instead of letting stale bytes arrive. The
//!   one view of grace keeps a request that flickers at the edge of the wish list from being
//!   cancelled and asked for again;
//! - a delivered request holds its slot until the loader calls `complete`.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};

use crossbeam_channel::{Receiver, Sender};
use strata_types::BrickId;

use crate::{Brick, FetchResult, QueueCounters, RequestClass, SourceError};

/// What a started request produces: the brick's voxels and the bytes it cost as stored (what
/// crossed the disk or the network for it).
pub type BrickJobOutcome = Result<(Brick, u64), SourceError>;

/// Makes the future that fetches one brick; dropping the future cancels its requests.
pub type BrickJob =
    Arc<dyn Fn(BrickId) -> Pin<Box<dyn Future<Output = BrickJobOutcome> + Send>> + Send + Sync>;

struct InFlight {
    /// `set_requests` call that last named it.
    named_at: u64,
    /// The result is in the channel; only `complete` ends it now.
    delivered: bool,
    abort: Option<tokio::task::AbortHandle>,
}

struct QueueState {
    queued: HashMap<BrickId, (RequestClass, f64)>,
    in_flight: HashMap<BrickId, InFlight>,
    counters: QueueCounters,
    calls: u64,
}

struct Shared {
    state: Mutex<QueueState>,
    wake: tokio::sync::Notify,
    results: Sender<FetchResult>,
    capacity: usize,
    max_in_flight: usize,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A queue of brick requests run as tasks on a tokio runtime (see the module comment).
pub struct TaskQueue {
    shared: Arc<Shared>,
    results: Receiver<FetchResult>,
    dispatcher: tokio::task::AbortHandle,
}

impl TaskQueue {
    /// Starts the dispatcher on `runtime`; `job` fetches one brick.
    pub fn start(
        runtime: &tokio::runtime::Handle,
        job: BrickJob,
        capacity: usize,
        max_in_flight: usize,
    ) -> Self {
        // Unbounded in type, bounded in fact: at most `max_in_flight` requests exist between
        // dispatch and `complete`, and each sends one result.
        let (tx, rx) = crossbeam_channel::unbounded();
        let shared = Arc::new(Shared {
            state: Mutex::new(QueueState {
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
        let dispatcher = runtime.spawn(dispatch(job, shared.clone())).abort_handle();
        TaskQueue {
            shared,
            results: rx,
            dispatcher,
        }
    }

    /// Replaces the wish list; returns how many requests are queued now.
    pub fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
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
        // slot (and the connection) for what the view wants now.
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

    pub fn try_results(&self) -> Vec<FetchResult> {
        self.results.try_iter().collect()
    }

    /// The loader has taken the delivered brick `id`: its slot is free.
    pub fn complete(&self, id: BrickId) {
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

    pub fn queued(&self) -> usize {
        self.shared.lock().queued.len()
    }

    pub fn in_flight(&self) -> usize {
        self.shared.lock().in_flight.len()
    }

    pub fn capacity(&self) -> usize {
        self.shared.capacity
    }

    pub fn counters(&self) -> QueueCounters {
        self.shared.lock().counters
    }
}

/// Starts the most urgent queued requests while fewer than `max_in_flight` are out.
async fn dispatch(job: BrickJob, shared: Arc<Shared>) {
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
                let task = tokio::spawn(run_one(job.clone(), shared.clone(), id, class));
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

async fn run_one(job: BrickJob, shared: Arc<Shared>, id: BrickId, class: RequestClass) {
    let outcome = job(id).await;
    let mut state = shared.lock();
    let Some(entry) = state.in_flight.get_mut(&id) else {
        return; // cancelled meanwhile
    };
    entry.delivered = true;
    entry.abort = None;
    let (outcome, stored_bytes) = match outcome {
        Ok((brick, bytes)) => (Ok(brick), bytes),
        Err(e) => (Err(e), 0),
    };
    let _ = shared.results.send(FetchResult {
        id,
        class,
        outcome,
        stored_bytes,
    });
}

impl Drop for TaskQueue {
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
