//! zarrs over object_store: the async object store behind zarrs' synchronous API, driven by
//! one shared tokio runtime (named I/O threads). Callers are plain threads (export, import,
//! the loader's fetch threads), never async tasks: zarrs' adapter must not block inside one.

use std::sync::{Arc, OnceLock};

use zarrs::storage::storage_adapter::async_to_sync::{
    AsyncToSyncBlockOn, AsyncToSyncStorageAdapter,
};
use zarrs::storage::ReadableWritableListableStorage;
use zarrs_object_store::AsyncObjectStore;

use crate::{ObjectLocation, OmeZarrError, Result};

/// Worker threads of the I/O runtime: requests in flight are futures, not threads, so a few
/// suffice however many are outstanding.
const IO_THREADS: usize = 2;

pub(crate) fn runtime() -> Result<&'static tokio::runtime::Runtime> {
    static RUNTIME: OnceLock<std::io::Result<tokio::runtime::Runtime>> = OnceLock::new();
    RUNTIME
        .get_or_init(|| {
            // https:// and TLS S3 endpoints: rustls on ring (an error means another part of
            // the process installed a provider first, which serves as well).
            let _ = rustls::crypto::ring::default_provider().install_default();
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(IO_THREADS)
                .thread_name("strata-omezarr-io")
                .enable_all()
                .build()
        })
        .as_ref()
        .map_err(|e| OmeZarrError::access("the object-store runtime", e))
}

/// Runs a future on the I/O runtime from a plain thread.
pub(crate) fn block_on<F: std::future::Future>(future: F) -> Result<F::Output> {
    Ok(runtime()?.block_on(future))
}

pub(crate) struct TokioBlockOn(tokio::runtime::Handle);

impl AsyncToSyncBlockOn for TokioBlockOn {
    fn block_on<F: core::future::Future>(&self, future: F) -> F::Output {
        self.0.block_on(future)
    }
}

/// The location as a zarrs store (readable, writable, listable).
pub(crate) fn zarr_storage(location: &ObjectLocation) -> Result<ReadableWritableListableStorage> {
    let handle = runtime()?.handle().clone();
    let store = Arc::new(AsyncObjectStore::new(location.store.clone()));
    Ok(Arc::new(AsyncToSyncStorageAdapter::new(
        store,
        TokioBlockOn(handle),
    )))
}
