//! GPU resources: the device, the composed WGSL and its pipelines, the brick cache, the page
//! table, transfer function, overlay and octree buffers, the frame targets and readbacks.
//! Uses only the model below it (render/src/lib.rs draws the layers).

pub mod bricked_volume;
pub mod cache;
pub mod device;
pub mod dirty_spans;
pub(crate) mod frame_targets;
pub mod gpu_octree;
pub(crate) mod gpu_overlay;
pub mod gpu_page_table;
pub(crate) mod gpu_preintegration;
pub mod gpu_timing;
pub mod gpu_transfer_function;
pub mod light_cache;
pub mod pipelines;
pub(crate) mod readback_ring;
pub mod shaders;
