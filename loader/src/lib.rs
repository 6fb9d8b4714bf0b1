//! strata-loader: sits between storage and render. For now it loads a fixed cut of the octree
//! (one level per page position) from a store into memory and the GPU cache; the streaming
//! working set (cut selection per frame, fetch threads, LRU caches, upload budget, visibility
//! feedback) comes with the loader issue and will replace `load_cut` for interactive use.

pub mod store_volume;

pub use store_volume::{render_geometry, render_mapping, LoaderError, ResidentBricks};
