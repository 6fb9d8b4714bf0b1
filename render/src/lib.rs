//! strata-render: the wgpu raycaster and its f64 CPU reference. Knows nothing of sled or the loader.
//!
//! The sampled field is defined once ([`field`]) over a [`PageTable`] plus bricks
//! ([`BrickSource`]): the GPU raycaster (its WGSL twin `shaders/field.wgsl`, composed by
//! [`shaders`]) and the f64 reference ([`mod@reference`]) both integrate exactly that field, so
//! every GPU pixel can be checked against ground truth, mixed-level cuts and smooth
//! transitions included.
//!
//! # Modules, as a DAG
//! Each module uses only modules on earlier lines (via `crate::`); no cycles.
//!
//! ```text
//! error, camera, layout          (layout: brick sizes, page-word bits, slot limits,
//!                                 neighbour-mask bits, shading thresholds, BrickSource)
//! settings, transfer_function, metrics, device       → error
//! CPU side
//!   page_table          → layout, transfer_function, error      (topology, coarser neighbours)
//!   smooth_transitions  → page_table, layout                    (masks, near-side closure)
//!   octree_cut          → page_table                            (the cut as an octree with ropes)
//!   sparse_page_table   → octree_cut, page_table, layout        (the cut's table per leaf)
//!   field               → page_table, layout                    (the one field definition)
//!   overlay             → error           (3D overlay: grid sampling, LUT, the blend rule)
//!   blinn_phong         → layout, settings                      (headlight Blinn-Phong, f64)
//!   shadows             → blinn_phong, camera, layout, settings (key light, shadow model)
//!   light_cache         → settings, transfer_function, pipelines, device, error
//!                                                        (the cache's grid and its key)
//!   ambient_occlusion   → shadows                               (AO model, f64)
//!   scattering          → shadows, settings                     (HG + hybrid model, f64)
//!   reference           → field, smooth_transitions, page_table, layout, camera, settings,
//!                         transfer_function, overlay, blinn_phong, shadows, light_cache,
//!                         ambient_occlusion, scattering, error  (f64 renderer)
//!   preintegration      → transfer_function             (the former 2D table; f64 segments)
//!   segment_integral    → transfer_function             (length-free pre-integration)
//!   cache               → layout, error
//!   bricked_volume      → cache, page_table, layout, transfer_function, error
//!   phantom             → bricked_volume, transfer_function, error
//! GPU side
//!   shaders             → layout, overlay, shadows, ambient_occlusion
//!                                     (composed WGSL, generated constants prelude, naga)
//!   readback_ring                      (staging ring read 1-2 frames late)
//!   frame_targets       → readback_ring, device, error
//!                          (every pass's colour, depth, visibility targets and their readback)
//!   pipelines           → settings, frame_targets (PipelineKey, bind-group layout, cache, compiler)
//!   dirty_spans                        (changed spans of a buffer, written alone)
//!   gpu_timing          → readback_ring
//!   gpu_octree          → octree_cut, sparse_page_table, page_table, layout, error
//!                                                               (node buffer, per-leaf)
//!   gpu_page_table      → gpu_octree, sparse_page_table, page_table, smooth_transitions, dirty_spans, cache,
//!                         layout, error
//!   gpu_transfer_function → transfer_function
//!   gpu_overlay         → overlay, error                        (overlay grid + LUT textures)
//!   gpu_preintegration  → gpu_transfer_function, segment_integral, transfer_function
//!   raycast             → shaders, pipelines, gpu_page_table, gpu_transfer_function, gpu_overlay, overlay,
//!                         gpu_preintegration, gpu_timing, frame_targets, cache, camera,
//!                         device, layout, settings, error       (the pass)
//!   probe               → raycast, shaders, frame_targets, device, error       (feature test-probe)
//!   octree_probe        → gpu_octree, octree_cut, shaders, frame_targets, device, error
//!                                                               (feature test-probe)
//!   offscreen           → raycast, gpu_page_table, gpu_transfer_function, bricked_volume,
//!                         cache, page_table, camera, device, settings, transfer_function, error
//!   time_critical       → gpu_timing, settings
//!   progressive         → raycast, frame_targets, camera, device, settings, error
//!                                          (running mean of a still view's jittered frames)
//! adaptive (adaptive sampling in 3D, its own pass beside the raycaster)
//!   adaptive::transcription                 (Figs. 3, 5, 6 in f64)
//!   adaptive::frame     → transcription, camera, settings          (slices, pixel rays)
//!   adaptive::oracle    → page_table, layout, transfer_function, settings (distance per entry)
//!   adaptive::scene     → transcription, frame, oracle, field, reference, preintegration,
//!                         segment_integral, smooth_transitions, settings   (CPU twin)
//!   adaptive::gpu       → frame, oracle, shaders, raycast, frame_targets, gpu_preintegration, cache,
//!                         device, settings, error                  (the tiled pass)
//! ```
//!
//! Older paths stay valid through re-exports that add no dependency of their own except one:
//! `smooth_transitions` re-exports the blend and `sample_field` from `field` (which does not
//! use `smooth_transitions`), so `smooth_transitions::sample_field` still resolves. Tests add
//! `pipelines` → `shaders`.

pub mod adaptive;
pub mod ambient_occlusion;
pub mod blinn_phong;
pub mod bricked_volume;
pub mod cache;
pub mod camera;
pub mod device;
pub mod dirty_spans;
pub mod error;
pub mod field;
pub(crate) mod frame_targets;
pub mod gpu_octree;
pub(crate) mod gpu_overlay;
pub mod gpu_page_table;
pub(crate) mod gpu_preintegration;
pub mod gpu_timing;
pub mod gpu_transfer_function;
pub mod layout;
pub mod light_cache;
pub mod metrics;
pub mod octree_cut;
#[cfg(feature = "test-probe")]
pub mod octree_probe;
pub mod offscreen;
pub mod overlay;
pub mod page_table;
pub mod phantom;
pub mod pipelines;
pub mod preintegration;
#[cfg(feature = "test-probe")]
pub mod probe;
pub mod progressive;
pub mod raycast;
mod readback_ring;
pub mod reference;
pub mod scattering;
pub mod segment_integral;
pub mod settings;
pub mod shaders;
pub mod shadows;
pub mod smooth_transitions;
pub mod sparse_page_table;
pub mod target_rate;
pub mod time_critical;
pub mod transfer_function;

pub use bricked_volume::BrickedVolume;
pub use cache::{BrickCache, CacheConfig, CacheFormat};
pub use camera::{Camera, Projection};
pub use device::GpuContext;
pub use error::RenderError;
pub use gpu_octree::LeafVisibility;
pub use gpu_octree::Traversal;
pub use gpu_page_table::{
    check_flat_table_fits, flat_table_limit, GpuPageTable, PageTableLayout, PreparedPageTable,
};
pub use gpu_timing::{FrameTiming, FrameTimingSource};
pub use gpu_transfer_function::GpuTransferFunction;
pub use layout::{BrickSource, DEPTH_OPACITY};
pub use metrics::{compare_rgba8, ImageComparison};
pub use offscreen::OffscreenRenderer;
pub use overlay::{OverlayKind, OverlayLut, OverlayScene, OverlayVolume};
pub use page_table::{PageEntry, PageTable};
pub use pipelines::PipelineKey;
pub use preintegration::PreintegrationTable;
pub use progressive::{Accumulator, ViewKey};
pub use raycast::{FrameReadback, Raycaster, Scene, VisibilityFrame, PER_PAGE_VISIBILITY_CELLS};
pub use reference::{
    render_reference, render_reference_with_overlay, ReferenceImage, ReferenceOptions,
    ReferenceScene,
};
pub use segment_integral::SegmentIntegralTable;
pub use settings::{
    ClipPlane, CropBox, KeyLight, LightDirection, Occlusion, RenderMode, RenderSettings,
    Scattering, Shading, ShadowMode, Shadows,
};
pub use sparse_page_table::{IndexTable, PageLookup, SparsePageTable};
pub use strata_types::{ValueMapping, VolumeGeometry};
pub use time_critical::{
    ControllerConfig, FrameQuality, LodConfig, Observation, SamplingRateController,
    TimeCriticalConfig, TimeCriticalController,
};
pub use transfer_function::{TransferFunction, TransferFunctionTable};

/// The brick constants are the store's (one definition in strata-types, through layout.rs).
pub use layout::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};
