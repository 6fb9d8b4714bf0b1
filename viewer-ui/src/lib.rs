//! strata-viewer-ui: the views and panels the desktop viewer (`strata`, viewer/src/) and the
//! browser viewer (strata-web) share, so both builds draw one copy (issue 39). Everything here
//! builds natively and for wasm32-unknown-unknown: it takes plain inputs (the transfer function,
//! the histogram, the figures to show) from the caller and knows nothing of either app's state.
//!
//! # Modules
//! - [`adaptive`]: adaptive sampling of the still view as both viewers decide and report it:
//!   which views the adaptive pass draws, the oracle's key, ε's default and range, the status
//!   line (the desktop's oracle thread and the page's per-frame build apply the same key rule).
//! - [`tf_editor`]: the transfer-function editor (histogram, opacity points, colour stops).
//! - [`performance`]: [`performance::FrameClock`] (UI frame-time history and the frame log) and
//!   the Performance panel's figures, drawn from [`performance::PerformanceFigures`].
//! - [`target_fps`]: the target frame-rate control (checkbox + slider) the time-critical
//!   controller (strata_render::control::time_critical) is driven by.
//! - [`slice_canvas`]: what a slice view draws around its image (zoom and pan, screen ↔ image
//!   mapping, crosshair, orientation labels, the flipped image mesh, the colour-map choice).
//! - [`render_driver`]: the render driver both viewers call: what is applied to the streaming
//!   volume now, and a new render request as a typed difference of actions (issue 47).
//! - [`lighting`]: the light model (key light, shadows, occlusion, scattering), the one function
//!   that makes render settings of it, and its controls with the direction gizmo.
//! - [`orbit`]: the 3D view's drag-to-orbit mapping and the six standard views (A/P/L/R/S/I),
//!   so a drag or key turns both viewers' views alike.
//! - [`overlay`]: a label or continuous overlay over the slices: the mapping of a slice pixel
//!   into the overlay's grid, nearest-label and trilinear sampling of its level-0 bricks (which
//!   may not be resident yet), the colouring, its controls and its link keys (issue 47).
//! - [`overlay_3d`]: the overlay or the editable label layer resampled onto the 3D view's
//!   bounded grid (slice by slice over bricks that may not be resident yet, or edit by edit)
//!   and its colour table (issues 47 and 52).
//! - [`orbit_movie`]: the orbit movie's frame counts and each frame's azimuth, so the desktop's
//!   PNG frames and MP4 and the page's animated PNG turn through the same angles.
//! - [`picking`]: the volume position a click in the 3D view sees, from the frame's pick depth.
//! - [`measurements`]: rulers, angles and box/ellipse ROIs: the model, ROI statistics, a
//!   slice view's gestures and drawing, the list panel and the link's `m=` value.
//! - [`segment_panel`]: the Segment section's tool row, segment list and label opacity, and the
//!   colour a label is drawn with (issue 52 item 7: the desktop's panel and the page's).
//! - [`layouts`]: where the views go in the 2×2 and the 3D-over-slices layouts.
//! - [`frames`]: a 4-D volume's frame choice, the cine clock and the Frames panel.
//! - [`history`]: undo and redo (a drag one step, redo cleared by a new step, a cap on
//!   depth) of the desktop's scene snapshots and the page's link state without its navigation.
//! - [`shortcuts`]: the keyboard and mouse table (which the page has), the F1 help window and
//!   the key tests both viewers' key handling asks.
//! - [`triad`]: the orientation triad in the 3D view's corner, its geometry and painter.
//! - [`widgets`]: small widgets the panels need (the slow spinner).
//! - [`window_presets`]: the slice window/level presets (CT's windows, the scan's own, Auto)
//!   and the window a scan opens with.
//! - [`view_state`], [`compact_tf`]: the shareable link's format (`#store=…&az=…`, an edited
//!   transfer function as `tf=`), which both viewers read and write (issue 39; here since issue
//!   47, so that the desktop needs nothing of the browser crate).

pub mod adaptive;
pub mod compact_tf;
pub mod crop_clip;
pub mod frames;
pub mod history;
pub mod layouts;
pub mod lighting;
pub mod measurements;
pub mod orbit;
pub mod orbit_movie;
pub mod overlay;
pub mod overlay_3d;
pub mod performance;
pub mod picking;
pub mod presets;
pub mod render_driver;
pub mod segment_panel;
pub mod shortcuts;
pub mod slice_canvas;
pub mod target_fps;
pub mod tf_editor;
pub mod triad;
pub mod view_state;
pub mod widgets;
pub mod window_presets;
