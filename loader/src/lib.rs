//! strata-loader: sits between storage and render. `streaming` keeps the view's working set of
//! octree bricks on the GPU, refining over frames without ever waiting for a read; one module
//! per technique (see ARCHITECTURE.md's code map). `store_volume` loads a fixed cut up front,
//! which tests and benches use as the in-core baseline.

pub mod cpu_cache;
pub mod cut_payloads;
pub mod cut_selection;
pub mod cut_worker;
pub mod error;
pub mod fetch_workers;
pub mod gpu_slots;
pub mod malloc_arenas;
pub mod metrics;
pub mod octree_ranges;
pub mod predicted_cut;
pub mod prefetch;
#[cfg(feature = "local")]
pub mod store_volume;
pub mod streaming;
pub mod thread_cpu;
pub mod visibility;

pub use cut_payloads::CutPayloads;
pub use cut_worker::SelectionTiming;
pub use error::LoaderError;
pub use fetch_workers::SlowReader;
pub use metrics::{Distribution, FrameStats};
#[cfg(feature = "local")]
pub use store_volume::ResidentBricks;
pub use strata_source::{SourceStatus, VolumeSource};
pub use streaming::{BrickFailure, LoaderWork, StreamingConfig, StreamingVolume};
