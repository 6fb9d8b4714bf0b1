//! The streaming source's own request path ([`VolumeSource::start_fetching`]): every brick
//! request is one tokio task on the object-store runtime that assembles the brick with zarrs'
//! asynchronous sharded reader. The queue, and the loader's fetcher, is the [`TaskQueue`] the
//! data service's client uses too (priorities, capacity, one view of grace): a request on the
//! wire that the loader's newer wish lists stop naming is aborted, which drops object_store's
//! pending requests and so closes their connections mid-transfer instead of letting stale
//! bytes finish arriving (`tests/cancel_on_wire.rs`). What differs from the data service is
//! the request: a brick assembled from chunks, with no retry loop of its own (object_store
//! retries transient failures itself).
//!
//! [`VolumeSource::start_fetching`]: strata_source::VolumeSource::start_fetching

use std::sync::Arc;

use strata_source::task_queue::{BrickJobFuture, BrickJobs, TaskQueue, TaskRuntime};
use strata_source::SourceError;
use strata_types::BrickId;

/// Assembles one brick asynchronously (the streaming source's reads, awaited on the I/O
/// runtime); dropping the future cancels its requests.
pub(crate) type AssembleBrick = Arc<
    dyn Fn(BrickId) -> futures::future::BoxFuture<'static, Result<Vec<u16>, SourceError>>
        + Send
        + Sync,
>;

/// The streaming source's (`OmeZarrSource`'s) asynchronous request queue: each request a task
/// on the object-store runtime that assembles its brick.
pub(crate) fn start_fetcher(
    runtime: &'static tokio::runtime::Runtime,
    assemble: AssembleBrick,
    bytes_per_sample: usize,
    capacity: usize,
    max_in_flight: usize,
) -> TaskQueue {
    // The stored samples' bytes count as the brick's cost (what crossed the wire is in the
    // source's transfer counters: chunks are shared between neighbouring bricks).
    let jobs: Arc<dyn BrickJobs> = Arc::new(move |id| -> BrickJobFuture {
        let assembled = assemble(id);
        Box::pin(async move {
            let voxels = assembled.await?;
            let bytes = (voxels.len() * bytes_per_sample) as u64;
            Ok((Arc::new(voxels), bytes))
        })
    });
    TaskQueue::start(TaskRuntime::Static(runtime), jobs, capacity, max_in_flight)
}
