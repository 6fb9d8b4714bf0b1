//! strata-render: the wgpu raycaster and its f64 CPU reference. Knows nothing of sled or the loader.
//!
//! The sampled field is defined once ([`model::field`]) over a [`PageTable`] plus bricks
//! ([`BrickSource`]): the GPU raycaster (its WGSL twin `shaders/field.wgsl`, composed by
//! [`gpu::shaders`]) and the f64 reference ([`mod@reference`]) both integrate exactly that
//! field, so every GPU pixel can be checked against ground truth, mixed-level cuts and smooth
//! transitions included.
//!
//! # Folders and modules, as a layered DAG
//! Each folder is a layer, lowest first: a module uses only modules of lower layers and of its
//! own layer on earlier lines (via `crate::`); no cycles. `tests/tidy.rs`
//! (`render_folders_follow_the_layered_graph`, its `RENDER_LAYERS`) checks the layers. The
//! WGSL twins stay together in `shaders/` (composed by `gpu::shaders`).
//!
//! ```text
//! error                                (RenderError, every layer's)
//! model/ (the model and its CPU twins)
//!   camera, layout          (layout: brick sizes, page-word bits, slot limits,
//!                            neighbour-mask bits, shading thresholds, BrickSource)
//!   settings, transfer_function         → error
//!   page_table          → layout, transfer_function, error      (topology, coarser neighbours)
//!   field               → page_table, layout                    (the one field definition)
//!   smooth_transitions  → field, page_table, layout             (masks, near-side closure)
//!   octree_cut          → page_table                            (the cut as an octree with ropes)
//!   sparse_page_table   → octree_cut, page_table, layout        (the cut's table per leaf)
//!   overlay             → field, error    (3D overlay: grid sampling, LUT, the blend rule)
//!   blinn_phong         → layout, settings                      (headlight Blinn-Phong, f64)
//!   shadows             → blinn_phong, camera, layout, settings (key light, shadow model)
//!   ambient_occlusion   → shadows                               (AO model, f64)
//!   scattering          → shadows, settings                     (HG + hybrid model, f64)
//!   preintegration      → transfer_function             (the former 2D table; f64 segments)
//!   segment_integral    → preintegration, transfer_function (length-free pre-integration)
//! gpu/ (GPU resources)
//!   device              → error
//!   readback_ring                      (staging ring read 1-2 frames late)
//!   frame_targets       → readback_ring, device, error
//!                          (every pass's colour, depth, visibility targets and their readback)
//!   dirty_spans                        (changed spans of a buffer, written alone)
//!   shaders             → layout, overlay, shadows, ambient_occlusion
//!                                     (composed WGSL, generated constants prelude, naga)
//!   pipelines           → shaders, settings, frame_targets
//!                                     (PipelineKey, bind-group layout, cache, compiler)
//!   cache               → layout, error                         (the brick cache texture)
//!   bricked_volume      → cache, page_table, layout, transfer_function, error
//!                                     (an in-memory octree of bricks, uploaded to the cache)
//!   gpu_timing          → readback_ring
//!   gpu_octree          → octree_cut, sparse_page_table, page_table, smooth_transitions,
//!                         layout, error                         (node buffer, per-leaf)
//!   gpu_page_table      → gpu_octree, sparse_page_table, page_table, smooth_transitions,
//!                         dirty_spans, cache, octree_cut, layout, error
//!   gpu_transfer_function → transfer_function
//!   gpu_overlay         → overlay, error                        (overlay grid + LUT textures)
//!   gpu_preintegration  → gpu_transfer_function, segment_integral, transfer_function
//!   light_cache         → settings, transfer_function, pipelines, device, error
//!                                                        (the cache's grid and its key)
//! reference/ (the f64 reference)
//!   reference (mod.rs)  → field, smooth_transitions, page_table, layout, camera, settings,
//!                         transfer_function, overlay, blinn_phong, shadows, light_cache,
//!                         ambient_occlusion, scattering, error  (f64 renderer)
//!   metrics             → error           (image error between two RGBA8 images)
//! passes/
//!   raycast             → shaders, pipelines, gpu_page_table, gpu_transfer_function, gpu_overlay,
//!                         gpu_preintegration, gpu_timing, gpu_octree, frame_targets, light_cache,
//!                         cache, camera, overlay, shadows, layout, settings, device, error
//!                                                               (the pass)
//!   probe               → raycast, shaders, frame_targets, device, error  (feature test-probe)
//!   octree_probe        → gpu_octree, octree_cut, shaders, frame_targets, device, error
//!                                                               (feature test-probe)
//!   offscreen           → raycast, gpu_page_table, gpu_transfer_function, bricked_volume,
//!                         cache, page_table, camera, device, settings, transfer_function, error
//!   progressive         → raycast, frame_targets, camera, device, settings, error
//!                                          (running mean of a still view's jittered frames)
//!   adaptive/ (adaptive sampling in 3D, its own pass beside the raycaster)
//!     adaptive::transcription                 (Figs. 3, 5, 6 in f64)
//!     adaptive::frame     → transcription, camera, reference, settings (slices, pixel rays)
//!     adaptive::oracle    → page_table, layout, transfer_function, settings (distance per entry)
//!     adaptive::block_oracle → oracle, page_table, layout, transfer_function (per 2³ block)
//!     adaptive::scene     → transcription, frame, oracle, field, reference, preintegration,
//!                           segment_integral, smooth_transitions, settings   (CPU twin)
//!     adaptive::gpu       → frame, oracle, block_oracle, shaders, raycast, frame_targets,
//!                           gpu_preintegration, cache, device, settings, error
//!                                          (the tiled pass; its shader's generated constants)
//! control/ (controllers)
//!   time_critical       → gpu_timing, settings
//!   target_rate         → time_critical, gpu_timing, settings
//! testdata/
//!   phantom             → bricked_volume, transfer_function, error
//! ```
//!
//! Each item is imported from the module that defines it (no re-exports keep old paths alive).
//! Tests add `pipelines` → `shaders`.

pub mod control;
pub mod error;
pub mod gpu;
pub mod model;
pub mod passes;
pub mod reference;
pub mod testdata;

pub use control::time_critical::{
    ControllerConfig, FrameQuality, LodConfig, Observation, SamplingRateController,
    TimeCriticalConfig, TimeCriticalController,
};
pub use error::RenderError;
pub use gpu::bricked_volume::BrickedVolume;
pub use gpu::cache::{BrickCache, CacheConfig, CacheFormat};
pub use gpu::device::GpuContext;
pub use gpu::gpu_octree::LeafVisibility;
pub use gpu::gpu_octree::Traversal;
pub use gpu::gpu_page_table::{
    check_flat_table_fits, flat_table_limit, GpuPageTable, PageTableLayout, PreparedPageTable,
};
pub use gpu::gpu_timing::{FrameTiming, FrameTimingSource};
pub use gpu::gpu_transfer_function::GpuTransferFunction;
pub use gpu::pipelines::PipelineKey;
pub use model::camera::{Camera, Projection};
pub use model::layout::{BrickSource, DEPTH_OPACITY};
pub use model::overlay::{OverlayKind, OverlayLut, OverlayScene, OverlayVolume};
pub use model::page_table::{PageEntry, PageTable};
pub use model::preintegration::PreintegrationTable;
pub use model::segment_integral::SegmentIntegralTable;
pub use model::settings::{
    ClipPlane, CropBox, KeyLight, LightDirection, Occlusion, RenderMode, RenderSettings,
    Scattering, Shading, ShadowMode, Shadows,
};
pub use model::sparse_page_table::{IndexTable, PageLookup, SparsePageTable};
pub use model::transfer_function::{TransferFunction, TransferFunctionTable};
pub use passes::offscreen::OffscreenRenderer;
pub use passes::progressive::{Accumulator, ViewKey};
pub use passes::raycast::{
    FrameInputs, FrameReadback, Raycaster, VisibilityFrame, PER_PAGE_VISIBILITY_CELLS,
};
pub use reference::metrics::{compare_rgba8, ImageComparison};
pub use reference::{
    render_reference, render_reference_with_overlay, ReferenceImage, ReferenceOptions,
    ReferenceScene,
};
pub use strata_types::{ValueMapping, VolumeGeometry};

/// The brick constants are the store's (one definition in strata-types, through layout.rs).
pub use model::layout::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};
