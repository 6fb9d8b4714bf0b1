//! strata-web: the Strata viewer in a web browser (issue 39). eframe's web runner draws the UI
//! on a canvas; the volume is drawn by the same `strata-render` raycaster as on the desktop,
//! on the browser's WebGPU device, into a texture egui shows without a copy.
//!
//! # Modules
//! - [`view_state`]: the URL fragment ⇄ the view (camera, mode, preset, size). Platform
//!   independent: the native tests render the same view to check the browser's pixels.
//! - [`compact_tf`]: an edited transfer function's stops as a link's `tf=` value, exact and
//!   bounded.
//! - [`view_motion`]: the 3D view in motion: the target-fps control's controller
//!   (strata_render::control::target_rate, the desktop's) while the view moves, full quality at rest.
//! - [`volume_menu`]: the Volume menu's entries (the sample, then the server's stores from
//!   `GET /v1/stores`) and what a choice does to the view; platform independent, tested natively
//!   against a real server's list.
//! - [`orbit_movie`]: the orbit movie as one animated PNG download (strata-viewer-ui's shared
//!   orbit path, each frame the page's final still view); the model and encoder platform
//!   independent, the side panel's section the browser's.
//! - `adaptive` (wasm32 only): the still view drawn by the adaptive pass (the desktop's
//!   adaptive sampling), its block oracle built a few slots per animation frame from the CPU
//!   copies of the cut's bricks, the frame shown without a readback.
//! - `browser` (wasm32 only): the page's entry point, the viewer app, the frame capture.
//! - `canvas_attributes` (wasm32 only): the canvas attributes the browser tests read.
//! - `embed_bridge` (wasm32 only): the page in a notebook (issue 50): a postMessage bridge
//!   to the Jupyter widget `strata.Viewer` that embeds it (view state both ways, screenshots
//!   as PNG), listening only to the parent's origin the link names (`embed=`).
//! - `page_timing` (wasm32 only): time to first and converged image and the bench's frame
//!   times (`bench=N`), posted with the test capture (issue 39's benchmark).
//! - `picking` (wasm32 only): a click in the 3D view moves the crosshair to what is seen there,
//!   from one pixel of the frame's pick depth copied back without waiting.
//! - `page_tools` (wasm32 only): undo and redo (the shared history of the link's edits), the
//!   shared keyboard shortcuts and F1 help, the 3D view's screenshot as a PNG download.
//! - `refine` (wasm32 only): progressive refinement of the still 3D view (shadows, occlusion,
//!   scattering averaged over jittered frames, as the desktop does), at the page's frame loop.
//! - `served_store` (wasm32 only): `strata serve`'s client on `fetch()`, the volume source the
//!   streaming loader reads a served store through (`#store=NAME`), with the loader's work
//!   inline on the page's one thread (strata_loader::LoaderWork::Inline).
//! - `slice_views` (wasm32 only): a streamed store's three linked slice views (axial, coronal,
//!   sagittal) beside the 3D view, sliced by strata-slices' assembler (the desktop's) from
//!   bricks fetched asynchronously through the served store, window/level by right drag.
//! - `frames` (wasm32 only): a served 4-D store's frames: the shared Frames panel and cine
//!   clock, each frame's store opened without waiting, the views swapped to it (`frame=N`).
//! - [`frame_ahead`]: the next frame's bricks fetched ahead while one is shown, bounded (two
//!   requests at once, 32 MiB of records a frame), taken by that frame's fetchers; platform
//!   independent bookkeeping, tested natively.
//! - `measure` (wasm32 only): the desktop's rulers, angles and ROIs in the page
//!   (strata-viewer-ui's measurements): the side panel's tools and list, the list kept in the
//!   view (the link's `m=`), and what the page publishes of them for its tests.
//! - `oblique_view` (wasm32 only): the oblique view in the desktop's place for it, strata-slices'
//!   plane, drag and resampling (the desktop's) over bricks fetched as the slice views fetch
//!   theirs; shown while the link names it (`oblique=`).
//! - `overlay_view` (wasm32 only): a second served store over the slice views (`overlay=`),
//!   label map or continuous, strata-viewer-ui's overlay sampling and colouring (the
//!   desktop's) on level-0 bricks fetched as the slice views fetch theirs; the Overlay section.
//! - `segment_editor` (wasm32 only): segmentation editing on the slice views (issue 52 item
//!   7): strata-segment's label layer, brush, eraser, fill and history, the shared Segment
//!   section (strata-viewer-ui's segment_panel), labels over the slices, Download as NIfTI.
//! - [`primary_values`]: the primary's level-0 values for the segmentation tools that read
//!   them, out of core: a bounded cache of resident bricks, strata-segment's `Intensity` over
//!   them, naming the bricks not resident yet; `primary_values_page` (wasm32 only) fetches
//!   them through the served store (or copies the sample's).
//! - `segment_3d` (wasm32 only): the segment tools in the 3D view (the desktop's gesture): a
//!   brush or eraser stroke of balls at the surface points picked along a drag, a grow seeded
//!   at a picked point, through picking.rs's asynchronous picks taken in order.
//! - `segment_values` (wasm32 only): region growing from a clicked seed and the statistics
//!   per segment in the page, run over the resident bricks and again as missing ones arrive.
//! - `segment_downloads` (wasm32 only): the segmentation as a DICOM SEG and as zipped OME-Zarr
//!   labels, strata-segment's writers in memory, as browser downloads.
//! - `side_panel` (wasm32 only): the side panel, the desktop's transfer-function editor and
//!   Performance panel from strata-viewer-ui, on the page's 3D view.
//!
//! Without `store=` the page shows the built-in sample volume (the render crate's CT phantom,
//! made in the page).

// The link format lives in strata-viewer-ui, shared with the desktop viewer (issue 47); the
// paths stay `strata_web::view_state`, `strata_web::compact_tf`.
pub use strata_viewer_ui::{compact_tf, view_state};
pub mod frame_ahead;
pub mod orbit_movie;
pub mod view_motion;
pub mod volume_menu;

#[cfg(target_arch = "wasm32")]
mod adaptive;
#[cfg(target_arch = "wasm32")]
mod browser;
#[cfg(target_arch = "wasm32")]
mod canvas_attributes;
#[cfg(target_arch = "wasm32")]
mod embed_bridge;
#[cfg(target_arch = "wasm32")]
mod frames;
#[cfg(target_arch = "wasm32")]
mod measure;
#[cfg(target_arch = "wasm32")]
mod oblique_view;
#[cfg(target_arch = "wasm32")]
mod overlay_view;
#[cfg(target_arch = "wasm32")]
mod page_timing;
#[cfg(target_arch = "wasm32")]
mod page_tools;
#[cfg(target_arch = "wasm32")]
mod picking;
pub mod primary_values;
#[cfg(target_arch = "wasm32")]
mod primary_values_page;
#[cfg(target_arch = "wasm32")]
mod refine;
#[cfg(target_arch = "wasm32")]
mod segment_3d;
#[cfg(target_arch = "wasm32")]
mod segment_downloads;
#[cfg(target_arch = "wasm32")]
mod segment_editor;
#[cfg(target_arch = "wasm32")]
mod segment_values;
#[cfg(target_arch = "wasm32")]
mod served_store;
#[cfg(target_arch = "wasm32")]
mod side_panel;
#[cfg(target_arch = "wasm32")]
mod slice_views;
