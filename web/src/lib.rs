//! strata-web: the Strata viewer in a web browser (issue 39). eframe's web runner draws the UI
//! on a canvas; the volume is drawn by the same `strata-render` raycaster as on the desktop,
//! on the browser's WebGPU device, into a texture egui shows without a copy.
//!
//! # Modules
//! - [`view_state`]: the URL fragment ⇄ the view (camera, mode, preset, size). Platform
//!   independent: the native tests render the same view to check the browser's pixels.
//! - `browser` (wasm32 only): the page's entry point, the viewer app, the frame capture.
//! - `served_store` (wasm32 only): `strata serve`'s client on `fetch()`, the volume source the
//!   streaming loader reads a served store through (`#store=NAME`), with the loader's work
//!   inline on the page's one thread (strata_loader::LoaderWork::Inline).
//! - `side_panel` (wasm32 only): the side panel, the desktop's transfer-function editor and
//!   Performance panel from strata-viewer-ui, on the page's 3D view.
//!
//! Without `store=` the page shows the built-in sample volume (the render crate's CT phantom,
//! made in the page).

pub mod view_state;

#[cfg(target_arch = "wasm32")]
mod browser;
#[cfg(target_arch = "wasm32")]
mod served_store;
#[cfg(target_arch = "wasm32")]
mod side_panel;
