//! The page's measurements (wasm32 only; issue 47): the desktop's rulers, angles and box and
//! ellipse ROIs, from strata-viewer-ui's measurements (the model, the slice views' gestures and
//! drawing, the statistics and the list panel are the desktop's code, not a copy). Here: the
//! side panel's section (the tool row and the list), keeping the list in the view's
//! [`ViewState::measurements`] (so the address carries it as `m=` and the page's undo, which
//! snapshots the view, undoes it), and what the page publishes for its tests:
//! - `data-measurements` on the canvas: one line per measurement,
//!   `ID|KIND|I,J,K;I,J,K[;I,J,K]|FIGURES|TEXT` with KIND `ruler`, `angle`, `box-VIEW` or
//!   `ellipse-VIEW`, the points' level-0 indices, FIGURES the millimetres, the degrees, or
//!   `voxels,mean,sd,min,max,area_mm2,level` (empty before a region's slice came), all written
//!   so that they read back exactly, and TEXT the line the list shows;
//! - `data-measure-tools`: each tool button's rectangle (`LABEL:x,y,w,h;…`, CSS pixels of the
//!   canvas), where the browser tests click to choose a tool;
//! - `data-measure-tool`: the tool chosen and the points placed of the one being drawn
//!   (`LABEL,N`), so a test knows that its click was taken (a click held too long by a busy
//!   machine is no click to egui) before it clicks on.
//!
//! Rulers and angles are placed by clicks in the 3D view too ([`picked_in_3d`]: each point is
//! the page's pick, web/src/picking.rs, the desktop's pixel, ray and depth) and drawn over it
//! by the desktop's `paint_in_3d` ([`paint_in_3d_view`]).
//!
//! web/tests/browser/measure.rs checks the page's figures against the desktop's functions.

use strata_render::{Camera, VolumeGeometry};
use strata_viewer_ui::measurements::{
    angle_deg, distance_mm, paint_in_3d, panel, Measurement, Shape, Tool,
};

use crate::slice_views::SliceViews;
use crate::view_state::ViewState;

/// The side panel's "Measurements" section for the slice views on screen: the list follows
/// the view (a link opened, an undo), the panel edits it, and the view takes it back.
pub fn side_panel_section(ui: &mut egui::Ui, view: &mut ViewState, slices: &mut SliceViews) {
    egui::CollapsingHeader::new("Measurements")
        .default_open(true)
        .show(ui, |ui| {
            let (measurements, geometry, unit) = slices.measurement_parts();
            measurements.follow(&view.measurements);
            let tool_rects = panel(ui, measurements, geometry, unit);
            if view.measurements != measurements.items {
                view.measurements = measurements.items.clone();
            }
            let text: Vec<String> = tool_rects
                .iter()
                .map(|(tool, r)| {
                    format!(
                        "{}:{},{},{},{}",
                        tool.label(),
                        r.min.x,
                        r.min.y,
                        r.width(),
                        r.height()
                    )
                })
                .collect();
            crate::canvas_attributes::set("data-measure-tools", &text.join(";"));
        });
}

/// Before the slice views draw: their list follows the view (a link opened this frame).
pub fn before_slice_views(view: &ViewState, slices: &mut SliceViews) {
    slices.measurement_parts().0.follow(&view.measurements);
}

/// After the slice views drew (and took gestures): the view takes their list, and the page
/// publishes it.
pub fn after_slice_views(view: &mut ViewState, slices: &mut SliceViews) {
    let (measurements, geometry, unit) = slices.measurement_parts();
    if view.measurements != measurements.items {
        view.measurements = measurements.items.clone();
    }
    let lines: Vec<String> = measurements
        .items
        .iter()
        .map(|m| published_line(m, geometry, unit))
        .collect();
    crate::canvas_attributes::set("data-measurements", &lines.join("\n"));
    let state = format!(
        "{},{}",
        measurements.tool.label(),
        measurements.draft.points.len()
    );
    crate::canvas_attributes::set("data-measure-tool", &state);
}

/// A position picked in the 3D view: with the ruler or the angle tool it is the next point of
/// the measurement being drawn (the view takes the list, so the link carries it) and true;
/// with another tool false (the click moves the crosshair).
pub fn picked_in_3d(view: &mut ViewState, slices: &mut SliceViews, index: [f64; 3]) -> bool {
    let (measurements, ..) = slices.measurement_parts();
    if !matches!(measurements.tool, Tool::Distance | Tool::Angle) {
        return false;
    }
    measurements.follow(&view.measurements);
    measurements.click(index);
    if view.measurements != measurements.items {
        view.measurements = measurements.items.clone();
    }
    true
}

/// The rulers and angles (and the points placed of one being drawn) over the 3D image drawn
/// with `camera` in `image_rect`: the desktop's drawing.
pub fn paint_in_3d_view(
    painter: &egui::Painter,
    image_rect: egui::Rect,
    camera: &Camera,
    view: &ViewState,
    slices: &mut SliceViews,
) {
    let (measurements, geometry, unit) = slices.measurement_parts();
    measurements.follow(&view.measurements);
    paint_in_3d(painter, image_rect, camera, geometry, unit, measurements);
}

/// One measurement as `data-measurements` lists it (see the module's doc).
fn published_line(m: &Measurement, geometry: &VolumeGeometry, unit: &str) -> String {
    let (kind, figures) = match &m.shape {
        Shape::Distance { a, b } => (
            "ruler".to_string(),
            format!("{}", distance_mm(geometry, *a, *b)),
        ),
        Shape::Angle { a, vertex, b } => (
            "angle".to_string(),
            format!("{}", angle_deg(geometry, *a, *vertex, *b)),
        ),
        Shape::Roi {
            view,
            ellipse,
            stats,
            ..
        } => (
            format!(
                "{}-{}",
                if *ellipse { "ellipse" } else { "box" },
                view.name().to_lowercase()
            ),
            stats
                .map(|s| {
                    format!(
                        "{},{},{},{},{},{},{}",
                        s.voxels, s.mean, s.sd, s.min, s.max, s.area_mm2, s.level
                    )
                })
                .unwrap_or_default(),
        ),
    };
    let points: Vec<String> = m
        .points()
        .iter()
        .map(|[i, j, k]| format!("{i},{j},{k}"))
        .collect();
    format!(
        "{}|{kind}|{}|{figures}|{}",
        m.id,
        points.join(";"),
        m.describe(geometry, unit)
    )
}
