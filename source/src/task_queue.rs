//! The request queue of the asynchronous brick sources (the data service's client, the
//! OME-Zarr source's object-store reader): every started request is one tokio task that
//! produces one brick. Which request starts next and which one is no longer wanted is the
//! [`WishList`]'s policy (demand before prefetch, then by priority; at most `capacity`
//! queued; a started request that neither this view nor the previous one names is
//! cancelled); this module runs it on tokio:
//! - at most `max_in_flight` requests run at once;
//! - a cancelled request's task is aborted: it is dropped at its next await, which drops the
//!   client's pending request and so closes (or resets) its connection mid-transfer instead of
//!   letting stale bytes arrive;
//! - a delivered request holds its slot until the loader calls `complete`.
//!
//! [`TaskQueue`] is the sources' [`BrickFetcher`] itself: a source hands the loader
//! `Box::new(TaskQueue::start(...))` with its [`BrickJobs`] (how to fetch one brick, what the
//! jobs count, how the source is doing).

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};

use crossbeam_channel::{Receiver, Sender};
use strata_types::BrickId;

use crate::wish_list::{Started, WishList};
use crate::{Brick, BrickFetcher, FetchResult, QueueCounters, SourceError, SourceStatus};

/// What a started request produces: the brick's voxels and the bytes it cost as stored (what
/// crossed the disk or the network for it).
pub type BrickJobOutcome = Result<(Brick, u64), SourceError>;

/// The future that fetches one brick; dropping it cancels its requests.
pub type BrickJobFuture = Pin<Box<dyn Future<Output = BrickJobOutcome> + Send>>;

/// What a source brings to a [`TaskQueue`]: how to fetch one brick, and what only its jobs
/// know. A closure `Fn(BrickId) -> BrickJobFuture` is one, with nothing to add.
pub trait BrickJobs: Send + Sync + 'static {
    /// Starts fetching brick `id`.
    fn fetch(&self, id: BrickId) -> BrickJobFuture;
    /// Adds what the jobs count themselves (retries, checksum failures) to the queue's counters.
    fn add_counters(&self, _counters: &mut QueueCounters) {}
    /// How the source is doing ("retrying", for the status line).
    fn status(&self) -> SourceStatus {
        SourceStatus::Available
    }
}

impl<F> BrickJobs for F
where
    F: Fn(BrickId) -> BrickJobFuture + Send + Sync + 'static,
{
    fn fetch(&self, id: BrickId) -> BrickJobFuture {
        self(id)
    }
}

/// The runtime a queue's tasks run on.
pub enum TaskRuntime {
    /// One that lives as long as the process (the OME-Zarr source's I/O runtime).
    Static(&'static tokio::runtime::Runtime),
    /// One the queue holds so that it outlives the queue's tasks. Held by the queue, never by
    /// a task: tokio refuses to drop a runtime inside one of its own tasks.
    Shared(Arc<tokio::runtime::Runtime>),
}

impl TaskRuntime {
    fn handle(&self) -> &tokio::runtime::Handle {
        match self {
            TaskRuntime::Static(runtime) => runtime.handle(),
            TaskRuntime::Shared(runtime) => runtime.handle(),
        }
    }
}

struct QueueState {
    wishes: WishList,
    /// The tasks of the started requests not yet delivered, to abort when cancelled.
    running: HashMap<BrickId, tokio::task::AbortHandle>,
}

struct Shared {
    state: Mutex<QueueState>,
    wake: tokio::sync::Notify,
    results: Sender<FetchResult>,
    max_in_flight: usize,
}

impl Shared {
    /// A poisoned lock means a task panicked mid-update; the wish list is still a valid set of
    /// requests, so carry on rather than cascade the panic into the frame loop.
    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A queue of brick requests run as tasks on a tokio runtime (see the module comment).
pub struct TaskQueue {
    shared: Arc<Shared>,
    results: Receiver<FetchResult>,
    dispatcher: tokio::task::AbortHandle,
    jobs: Arc<dyn BrickJobs>,
    capacity: usize,
    /// Declared last: dropped after `drop` has aborted the tasks.
    _runtime: TaskRuntime,
}

impl TaskQueue {
    /// Starts the dispatcher on `runtime`; `jobs` fetches one brick per request. At most
    /// `capacity` requests are queued and `max_in_flight` started at once.
    pub fn start(
        runtime: TaskRuntime,
        jobs: Arc<dyn BrickJobs>,
        capacity: usize,
        max_in_flight: usize,
    ) -> Self {
        // Unbounded in type, bounded in fact: at most `max_in_flight` requests exist between
        // dispatch and `complete`, and each sends one result.
        let (tx, rx) = crossbeam_channel::unbounded();
        let wishes = WishList::new(capacity);
        let capacity = wishes.capacity();
        let shared = Arc::new(Shared {
            state: Mutex::new(QueueState {
                wishes,
                running: HashMap::new(),
            }),
            wake: tokio::sync::Notify::new(),
            results: tx,
            max_in_flight: max_in_flight.max(1),
        });
        let dispatcher = runtime
            .handle()
            .spawn(dispatch(jobs.clone(), shared.clone()))
            .abort_handle();
        TaskQueue {
            shared,
            results: rx,
            dispatcher,
            jobs,
            capacity,
            _runtime: runtime,
        }
    }
}

impl BrickFetcher for TaskQueue {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let mut state = self.shared.lock();
        state.wishes.replace(demand, prefetch);
        // Started but named by neither this view nor the previous one: abort, freeing the
        // slot (and the connection) for what the view wants now.
        for (id, _) in state.wishes.cancel_unwanted() {
            if let Some(task) = state.running.remove(&id) {
                task.abort();
            }
        }
        let queued = state.wishes.queued();
        drop(state);
        self.shared.wake.notify_one();
        queued
    }

    fn try_results(&self) -> Vec<FetchResult> {
        self.results.try_iter().collect()
    }

    fn complete(&self, id: BrickId) {
        if self.shared.lock().wishes.complete(id) {
            // A slot is free.
            self.shared.wake.notify_one();
        }
    }

    fn queued(&self) -> usize {
        self.shared.lock().wishes.queued()
    }

    fn in_flight(&self) -> usize {
        self.shared.lock().wishes.in_flight()
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn counters(&self) -> QueueCounters {
        let mut counters = self.shared.lock().wishes.counters();
        self.jobs.add_counters(&mut counters);
        counters
    }

    fn status(&self) -> SourceStatus {
        self.jobs.status()
    }
}

/// Starts the most urgent queued requests while fewer than `max_in_flight` are out.
async fn dispatch(jobs: Arc<dyn BrickJobs>, shared: Arc<Shared>) {
    loop {
        {
            let mut state = shared.lock();
            while state.wishes.in_flight() < shared.max_in_flight {
                let Some(started) = state.wishes.take_most_urgent() else {
                    break;
                };
                let task = tokio::spawn(run_one(jobs.clone(), shared.clone(), started));
                state.running.insert(started.id, task.abort_handle());
            }
        }
        shared.wake.notified().await;
    }
}

async fn run_one(jobs: Arc<dyn BrickJobs>, shared: Arc<Shared>, started: Started) {
    let outcome = jobs.fetch(started.id).await;
    let mut state = shared.lock();
    if !state.wishes.deliver(started.id, started.ticket) {
        return; // cancelled meanwhile
    }
    state.running.remove(&started.id);
    let (outcome, stored_bytes) = match outcome {
        Ok((brick, bytes)) => (Ok(brick), bytes),
        Err(e) => (Err(e), 0),
    };
    let _ = shared.results.send(FetchResult {
        id: started.id,
        class: started.class,
        outcome,
        stored_bytes,
    });
}

impl Drop for TaskQueue {
    fn drop(&mut self) {
        self.dispatcher.abort();
        let mut state = self.shared.lock();
        for (_, task) in state.running.drain() {
            task.abort();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn brick(x: u32) -> BrickId {
        BrickId::new(0, [x, 0, 0])
    }

    fn runtime() -> Arc<tokio::runtime::Runtime> {
        Arc::new(
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .thread_name("strata-test-io")
                .enable_all()
                .build()
                .unwrap(),
        )
    }

    /// Polls until `count` results arrived (or a bound that only catches hangs).
    fn collect(queue: &TaskQueue, count: usize) -> Vec<FetchResult> {
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut results = Vec::new();
        while results.len() < count && Instant::now() < deadline {
            results.extend(queue.try_results());
            std::thread::sleep(Duration::from_millis(2));
        }
        results
    }

    #[test]
    fn a_task_queue_is_a_fetcher_that_starts_demand_first_and_aborts_what_two_views_leave_out() {
        // Brick 0 never finishes (until aborted); the others answer with their x coordinate.
        let started = Arc::new(Mutex::new(Vec::new()));
        let jobs: Arc<dyn BrickJobs> = {
            let started = started.clone();
            Arc::new(move |id: BrickId| -> BrickJobFuture {
                started.lock().unwrap().push(id);
                Box::pin(async move {
                    if id == brick(0) {
                        std::future::pending::<()>().await;
                    }
                    Ok((Arc::new(vec![id.coords[0] as u16]), 1))
                })
            })
        };
        let queue = TaskQueue::start(TaskRuntime::Shared(runtime()), jobs, 8, 1);
        let fetcher: &dyn BrickFetcher = &queue;
        fetcher.set_requests(&[(brick(0), 1.0)], &[]);
        let deadline = Instant::now() + Duration::from_secs(20);
        while fetcher.in_flight() == 0 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(2));
        }
        assert_eq!(fetcher.in_flight(), 1);
        // The one slot is taken: the rest waits, and brick 0 has one view of grace.
        fetcher.set_requests(&[(brick(1), 1.0)], &[(brick(2), 9.0)]);
        assert_eq!((fetcher.queued(), fetcher.in_flight()), (2, 1));
        assert_eq!(fetcher.counters().cancelled_in_flight, 0);
        fetcher.set_requests(&[(brick(1), 1.0)], &[(brick(2), 9.0)]);
        assert_eq!(fetcher.counters().cancelled_in_flight, 1);
        let first = collect(&queue, 1);
        assert_eq!(first.len(), 1);
        assert_eq!(first[0].id, brick(1), "demand before a higher prefetch");
        assert_eq!(first[0].outcome.as_ref().unwrap()[0], 1);
        fetcher.complete(brick(1));
        let second = collect(&queue, 1);
        assert_eq!(second.iter().map(|r| r.id).collect::<Vec<_>>(), [brick(2)]);
        fetcher.complete(brick(2));
        assert_eq!(fetcher.in_flight(), 0);
        let counters = fetcher.counters();
        assert_eq!((counters.demand_started, counters.prefetch_started), (2, 1));
        assert_eq!(*started.lock().unwrap(), [brick(0), brick(1), brick(2)]);
    }
}
