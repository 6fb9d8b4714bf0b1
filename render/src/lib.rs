//! strata-render: the wgpu raycaster and its f64 CPU reference. Knows nothing of sled or the loader.
//!
//! The sampled field is defined once, on the CPU side, by a [`PageTable`] plus bricks
//! ([`BrickSource`]): the GPU raycaster (`raycast.rs` + `shaders/raycast.wgsl`) and the f64
//! reference (`reference.rs`) both integrate exactly that field, so every GPU pixel can be
//! checked against ground truth, including mixed-level cuts.

pub mod bricked_volume;
pub mod cache;
pub mod camera;
pub mod device;
pub mod error;
pub mod field;
pub mod gpu_page_table;
mod gpu_preintegration;
pub mod gpu_timing;
pub mod gpu_transfer_function;
pub mod layout;
pub mod metrics;
pub mod offscreen;
pub mod page_table;
pub mod phantom;
pub mod pipelines;
pub mod preintegration;
#[cfg(feature = "test-probe")]
pub mod probe;
pub mod raycast;
mod readback_ring;
pub mod reference;
pub mod settings;
pub mod shaders;
pub mod smooth_transitions;
pub mod time_critical;
pub mod transfer_function;

pub use bricked_volume::BrickedVolume;
pub use cache::{BrickCache, CacheConfig, CacheFormat};
pub use camera::{Camera, Projection};
pub use device::GpuContext;
pub use error::RenderError;
pub use gpu_page_table::GpuPageTable;
pub use gpu_timing::{FrameTiming, FrameTimingSource};
pub use gpu_transfer_function::GpuTransferFunction;
pub use layout::BrickSource;
pub use metrics::{compare_rgba8, ImageComparison};
pub use offscreen::OffscreenRenderer;
pub use page_table::{PageEntry, PageTable};
pub use pipelines::PipelineKey;
pub use preintegration::PreintegrationTable;
pub use raycast::{FrameReadback, Raycaster, Scene, VisibilityFrame};
pub use reference::{render_reference, ReferenceImage, ReferenceOptions, ReferenceScene};
pub use settings::{ClipPlane, CropBox, RenderMode, RenderSettings, Shading};
pub use strata_types::{ValueMapping, VolumeGeometry};
pub use time_critical::{
    ControllerConfig, FrameQuality, LodConfig, Observation, SamplingRateController,
    TimeCriticalConfig, TimeCriticalController,
};
pub use transfer_function::{TransferFunction, TransferFunctionTable};

/// The brick constants are the store's (one definition in strata-types, through layout.rs).
pub use layout::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};
