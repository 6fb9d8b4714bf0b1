//! The streaming source's own request path ([`VolumeSource::start_fetching`]): every brick
//! request is one tokio task on the object-store runtime that assembles the brick with zarrs'
//! asynchronous sharded reader. The queue is the one the data service's client uses
//! ([`TaskQueue`]: priorities, capacity, one view of grace): a request on the wire that the
//! loader's newer wish lists stop naming is aborted, which drops object_store's pending
//! requests and so closes their connections mid-transfer instead of letting stale bytes finish
//! arriving. What differs from the data service is the request: a brick assembled from chunks,
//! with no retry loop of its own (object_store retries transient failures itself).
//!
//! [`VolumeSource::start_fetching`]: strata_source::VolumeSource::start_fetching

use std::sync::Arc;

use strata_source::task_queue::{BrickJob, TaskQueue};
use strata_source::{BrickFetcher, FetchResult, QueueCounters, SourceError};
use strata_types::BrickId;

/// Assembles one brick asynchronously (the streaming source's reads, awaited on the I/O
/// runtime); dropping the future cancels its requests.
pub(crate) type AssembleBrick = Arc<
    dyn Fn(BrickId) -> futures::future::BoxFuture<'static, Result<Vec<u16>, SourceError>>
        + Send
        + Sync,
>;

/// The asynchronous request queue of the streaming source (`OmeZarrSource`).
pub struct ZarrFetcher {
    queue: TaskQueue,
}

impl ZarrFetcher {
    pub(crate) fn start(
        runtime: &tokio::runtime::Runtime,
        assemble: AssembleBrick,
        bytes_per_sample: usize,
        capacity: usize,
        max_in_flight: usize,
    ) -> Self {
        // The stored samples' bytes count as the brick's cost (what crossed the wire is in the
        // source's transfer counters: chunks are shared between neighbouring bricks).
        let job: BrickJob = Arc::new(move |id| {
            let assembled = assemble(id);
            Box::pin(async move {
                let voxels = assembled.await?;
                let bytes = (voxels.len() * bytes_per_sample) as u64;
                Ok((Arc::new(voxels), bytes))
            })
        });
        ZarrFetcher {
            queue: TaskQueue::start(runtime.handle(), job, capacity, max_in_flight),
        }
    }
}

impl BrickFetcher for ZarrFetcher {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        self.queue.set_requests(demand, prefetch)
    }
    fn try_results(&self) -> Vec<FetchResult> {
        self.queue.try_results()
    }
    fn complete(&self, id: BrickId) {
        self.queue.complete(id)
    }
    fn queued(&self) -> usize {
        self.queue.queued()
    }
    fn in_flight(&self) -> usize {
        self.queue.in_flight()
    }
    fn capacity(&self) -> usize {
        self.queue.capacity()
    }
    fn counters(&self) -> QueueCounters {
        self.queue.counters()
    }
}
