//! What an axis-aligned slice view draws around its image, shared by the desktop's slice views
//! (viewer/src/slice_view.rs) and the page's (web/src/slice_views.rs): the image's place
//! in the view with zoom and pan ([`ZoomPan`]), screen ↔ image-fraction mapping, the
//! crosshair, the orientation labels, the readout line and the textured image with the view's
//! flips.
//!
//! Gestures, as the desktop has always had them: Ctrl+wheel (or a pinch) zooms about the
//! pointer, middle drag pans, a double-click resets both. Zoom is magnification over
//! fit-to-view (1 to [`MAX_ZOOM`]); pan is in points and always leaves the view's centre on
//! the image, so a slice can never be dragged out of sight.

use egui::{Color32, Pos2, Rect, Stroke, Vec2};
use strata_slices::{ColourMap, SliceFrame};

/// Space around the image for the title above, the readout below and the side labels.
pub const MARGIN_SIDES: f32 = 18.0;
pub const MARGIN_TOP: f32 = 38.0;
pub const MARGIN_BOTTOM: f32 = 36.0;
/// The largest magnification over fit-to-view.
pub const MAX_ZOOM: f32 = 32.0;
/// Half the crosshair's gap around its centre (points), so the voxel under it stays visible.
const CROSSHAIR_GAP: f32 = 8.0;

/// The part of a view's rectangle the image is fitted into (margins for the labels).
pub fn inner_rect(view_rect: Rect) -> Rect {
    Rect::from_min_max(
        view_rect.min + Vec2::new(MARGIN_SIDES, MARGIN_TOP),
        view_rect.max - Vec2::new(MARGIN_SIDES, MARGIN_BOTTOM),
    )
}

/// One view's zoom and pan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ZoomPan {
    /// Magnification over fit-to-view, in [1, MAX_ZOOM].
    pub zoom: f32,
    /// Offset of the image's centre from the view's centre, in points.
    pub pan: Vec2,
}

impl Default for ZoomPan {
    fn default() -> Self {
        ZoomPan {
            zoom: 1.0,
            pan: Vec2::ZERO,
        }
    }
}

impl ZoomPan {
    /// Multiplies the zoom by `factor` (clamped to [1, MAX_ZOOM]) keeping the image point
    /// under `pointer` where it is; without a pointer, about the image's centre.
    pub fn zoom_about(&mut self, factor: f32, pointer: Option<Pos2>, inner: Rect) {
        if !(factor.is_finite() && factor > 0.0) {
            return;
        }
        let old = self.zoom;
        self.zoom = (old * factor).clamp(1.0, MAX_ZOOM);
        if let Some(pointer) = pointer {
            let from_centre = pointer - inner.center() - self.pan;
            self.pan -= from_centre * (self.zoom / old - 1.0);
        }
    }

    pub fn pan_by(&mut self, delta: Vec2) {
        self.pan += delta;
    }

    pub fn reset(&mut self) {
        *self = ZoomPan::default();
    }

    /// Where an image of `extent_mm` (across, down) is drawn in `inner`: fitted keeping the
    /// patient's proportions, magnified by the zoom, moved by the pan. Clamps the pan first:
    /// none at zoom 1, and never so far that the image leaves the view's centre.
    pub fn image_rect(&mut self, inner: Rect, extent_mm: (f64, f64)) -> Rect {
        let (w_mm, h_mm) = extent_mm;
        let fit = (inner.width() as f64 / w_mm)
            .min(inner.height() as f64 / h_mm)
            .max(1e-6);
        let size = Vec2::new((w_mm * fit) as f32, (h_mm * fit) as f32) * self.zoom;
        if self.zoom <= 1.0 {
            self.pan = Vec2::ZERO;
        } else {
            let half = size * 0.5;
            self.pan = Vec2::new(
                self.pan.x.clamp(-half.x, half.x),
                self.pan.y.clamp(-half.y, half.y),
            );
        }
        Rect::from_center_size(inner.center() + self.pan, size)
    }

    /// The gestures over a view whose image is fitted into `inner`: Ctrl+wheel or pinch
    /// zooms about the pointer, middle drag pans, a double-click resets. Returns whether it
    /// was double-clicked (the caller may undo what that click's first half did).
    pub fn input(&mut self, ui: &egui::Ui, response: &egui::Response, inner: Rect) -> bool {
        if response.hovered() {
            let zoom = ui.input(|i| i.zoom_delta());
            if zoom != 1.0 {
                self.zoom_about(zoom, response.hover_pos(), inner);
            }
        }
        if response.dragged_by(egui::PointerButton::Middle) {
            self.pan_by(ui.input(|i| i.pointer.delta()));
        }
        let double_clicked = response.double_clicked();
        if double_clicked {
            self.reset();
        }
        double_clicked
    }
}

/// The fraction (0 at the image's left/top edge, 1 at its right/bottom) of screen point
/// `pos` in an image drawn in `image_rect`: what [`SliceFrame::index_at`] takes.
pub fn fraction_at(image_rect: Rect, pos: Pos2) -> (f64, f64) {
    (
        ((pos.x - image_rect.left()) / image_rect.width()) as f64,
        ((pos.y - image_rect.top()) / image_rect.height()) as f64,
    )
}

/// The screen point of fraction `(u, v)` of an image drawn in `image_rect` (the inverse of
/// [`fraction_at`]).
pub fn screen_at(image_rect: Rect, (u, v): (f64, f64)) -> Pos2 {
    Pos2::new(
        image_rect.left() + u as f32 * image_rect.width(),
        image_rect.top() + v as f32 * image_rect.height(),
    )
}

/// The linked crosshair through `centre`, across the whole image, with a gap around its
/// centre.
pub fn paint_crosshair(painter: &egui::Painter, image_rect: Rect, centre: Pos2) {
    let hair = Stroke::new(1.0, Color32::from_rgba_unmultiplied(120, 220, 255, 150));
    let c = centre;
    for (from, to) in [
        (
            Pos2::new(image_rect.left(), c.y),
            Pos2::new(c.x - CROSSHAIR_GAP, c.y),
        ),
        (
            Pos2::new(c.x + CROSSHAIR_GAP, c.y),
            Pos2::new(image_rect.right(), c.y),
        ),
        (
            Pos2::new(c.x, image_rect.top()),
            Pos2::new(c.x, c.y - CROSSHAIR_GAP),
        ),
        (
            Pos2::new(c.x, c.y + CROSSHAIR_GAP),
            Pos2::new(c.x, image_rect.bottom()),
        ),
    ] {
        painter.line_segment([from, to], hair);
    }
}

/// The patient-orientation letters (left, right, top, bottom) at the view's edges.
pub fn paint_orientation_labels(painter: &egui::Painter, view_rect: Rect, labels: [&str; 4]) {
    let font = egui::FontId::proportional(14.0);
    let colour = Color32::from_rgb(255, 220, 120);
    let [left, right, top, bottom] = labels;
    let r = view_rect;
    for (pos, align, text) in [
        (
            Pos2::new(r.left() + 5.0, r.center().y),
            egui::Align2::LEFT_CENTER,
            left,
        ),
        (
            Pos2::new(r.right() - 5.0, r.center().y),
            egui::Align2::RIGHT_CENTER,
            right,
        ),
        (
            Pos2::new(r.center().x, r.top() + 21.0),
            egui::Align2::CENTER_TOP,
            top,
        ),
        (
            Pos2::new(r.center().x, r.bottom() - 19.0),
            egui::Align2::CENTER_BOTTOM,
            bottom,
        ),
    ] {
        painter.text(pos, align, text, font.clone(), colour);
    }
}

/// `rect` moved (not resized) to lie inside `bounds`, as far as it fits: a label near the
/// view's edge stays readable. A rect larger than `bounds` keeps its left or top edge in.
pub fn keep_inside(rect: Rect, bounds: Rect) -> Rect {
    let shift = |lo: f32, hi: f32, min: f32, max: f32| {
        if lo < min || hi - lo > max - min {
            min - lo
        } else if hi > max {
            max - hi
        } else {
            0.0
        }
    };
    let dx = shift(rect.min.x, rect.max.x, bounds.min.x, bounds.max.x);
    let dy = shift(rect.min.y, rect.max.y, bounds.min.y, bounds.max.y);
    rect.translate(Vec2::new(dx, dy))
}

/// The line under the view (W/L, level, the value under the pointer).
pub fn paint_readout_line(painter: &egui::Painter, view_rect: Rect, text: String) {
    painter.text(
        view_rect.left_bottom() + Vec2::new(8.0, -4.0),
        egui::Align2::LEFT_BOTTOM,
        text,
        egui::FontId::proportional(11.0),
        Color32::LIGHT_GRAY,
    );
}

/// The slice image as a textured rectangle: the level grid's overhang cropped by
/// `inside_fraction`, the view's flips applied through the texture coordinates.
pub fn slice_mesh(
    texture: egui::TextureId,
    image_rect: Rect,
    inside_fraction: (f64, f64),
    frame: SliceFrame,
) -> egui::Mesh {
    let (fu, fv) = (inside_fraction.0 as f32, inside_fraction.1 as f32);
    let (u0, u1) = if frame.across_flipped {
        (fu, 0.0)
    } else {
        (0.0, fu)
    };
    let (v0, v1) = if frame.down_flipped {
        (fv, 0.0)
    } else {
        (0.0, fv)
    };
    let mut mesh = egui::Mesh::with_texture(texture);
    mesh.add_rect_with_uv(
        image_rect,
        Rect::from_min_max(Pos2::new(0.0, 0.0), Pos2::new(1.0, 1.0)),
        Color32::WHITE,
    );
    // Each vertex's uv from its place in the rectangle (add_rect_with_uv orders uv corners by
    // min/max, which would undo a flip).
    for vertex in &mut mesh.vertices {
        let fx = (vertex.pos.x - image_rect.left()) / image_rect.width();
        let fy = (vertex.pos.y - image_rect.top()) / image_rect.height();
        vertex.uv = Pos2::new(u0 + (u1 - u0) * fx, v0 + (v1 - v0) * fy);
    }
    mesh
}

/// The slices' colour-map choice (a combo box), as both viewers offer it.
pub fn colour_map_combo(ui: &mut egui::Ui, colour_map: &mut ColourMap) -> egui::Response {
    egui::ComboBox::from_id_salt("slice colour map")
        .selected_text(colour_map.label())
        .show_ui(ui, |ui| {
            for map in ColourMap::ALL {
                ui.selectable_value(colour_map, map, map.label());
            }
        })
        .response
        .accessible_name("Slice colour map")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_label_past_the_views_edge_moves_back_inside() {
        let view = Rect::from_min_max(Pos2::new(0.0, 0.0), Pos2::new(200.0, 100.0));
        let label = |x: f32, y: f32| Rect::from_min_size(Pos2::new(x, y), Vec2::new(60.0, 14.0));
        assert_eq!(keep_inside(label(10.0, 10.0), view), label(10.0, 10.0));
        assert_eq!(keep_inside(label(170.0, 10.0), view), label(140.0, 10.0));
        assert_eq!(keep_inside(label(-5.0, -8.0), view), label(0.0, 0.0));
        assert_eq!(keep_inside(label(150.0, 95.0), view), label(140.0, 86.0));
        // Wider than the view: its start stays in.
        let wide = Rect::from_min_size(Pos2::new(50.0, 0.0), Vec2::new(300.0, 14.0));
        assert_eq!(keep_inside(wide, view).min.x, 0.0);
    }

    fn inner() -> Rect {
        Rect::from_min_size(Pos2::new(10.0, 20.0), Vec2::new(200.0, 100.0))
    }

    /// The image point under `pointer` as a fraction of the image.
    fn under(zp: &mut ZoomPan, pointer: Pos2) -> (f64, f64) {
        fraction_at(zp.image_rect(inner(), (300.0, 100.0)), pointer)
    }

    #[test]
    fn fit_keeps_proportions_and_centres() {
        let r = ZoomPan::default().image_rect(inner(), (300.0, 100.0));
        // 300 × 100 mm into 200 × 100 points: width-limited, 200 × 66.7, centred.
        assert!((r.width() - 200.0).abs() < 1e-3);
        assert!((r.height() - 200.0 / 3.0).abs() < 1e-3);
        assert!((r.center() - inner().center()).length() < 1e-3);
    }

    #[test]
    fn zoom_about_the_pointer_keeps_the_point_under_it() {
        let mut zp = ZoomPan::default();
        let pointer = Pos2::new(60.0, 80.0);
        let before = under(&mut zp, pointer);
        for factor in [2.0, 1.5, 3.0, 0.7] {
            zp.zoom_about(factor, Some(pointer), inner());
            let after = under(&mut zp, pointer);
            assert!(
                (after.0 - before.0).abs() < 1e-4 && (after.1 - before.1).abs() < 1e-4,
                "×{factor}: {before:?} moved to {after:?}"
            );
        }
        assert!((zp.zoom - 6.3).abs() < 1e-4);
    }

    #[test]
    fn zoom_is_clamped_and_zoom_one_has_no_pan() {
        let mut zp = ZoomPan::default();
        zp.zoom_about(1000.0, Some(Pos2::new(20.0, 30.0)), inner());
        assert_eq!(zp.zoom, MAX_ZOOM);
        zp.zoom_about(1e-6, Some(Pos2::new(20.0, 30.0)), inner());
        assert_eq!(zp.zoom, 1.0);
        zp.pan_by(Vec2::new(40.0, -5.0));
        zp.image_rect(inner(), (300.0, 100.0));
        assert_eq!(zp.pan, Vec2::ZERO, "a fitted image does not move");
        // Nonsense factors change nothing.
        zp.zoom_about(f32::NAN, None, inner());
        zp.zoom_about(-2.0, None, inner());
        assert_eq!(zp, ZoomPan::default());
    }

    #[test]
    fn pan_keeps_the_view_centre_on_the_image() {
        let mut zp = ZoomPan {
            zoom: 2.0,
            pan: Vec2::ZERO,
        };
        zp.pan_by(Vec2::new(30.0, 10.0));
        let r = zp.image_rect(inner(), (300.0, 100.0));
        assert_eq!(zp.pan, Vec2::new(30.0, 10.0), "a pan within reach is kept");
        assert!(r.contains(inner().center()));
        zp.pan_by(Vec2::new(1e4, -1e4));
        let r = zp.image_rect(inner(), (300.0, 100.0));
        // 400 × 133.3 points at ×2: the pan stops at half of that.
        assert!((zp.pan.x - 200.0).abs() < 1e-3 && (zp.pan.y + 200.0 / 3.0).abs() < 1e-3);
        assert!((r.left() - inner().center().x).abs() < 1e-3, "{r:?}");
        assert!((r.bottom() - inner().center().y).abs() < 1e-3, "{r:?}");
        zp.reset();
        assert_eq!(zp, ZoomPan::default());
    }

    #[test]
    fn screen_voxel_screen_round_trips_zoomed_and_flipped() {
        let dims = [40, 30, 20];
        let plain = strata_render::VolumeGeometry::axis_aligned(dims, [1.0, 1.5, 2.0]);
        // i running to the patient's right and k to the feet: the views flip.
        let mut mirrored = plain.clone();
        mirrored.direction = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        let mut zp = ZoomPan::default();
        zp.zoom_about(3.0, Some(Pos2::new(70.0, 50.0)), inner());
        zp.pan_by(Vec2::new(-12.0, 7.0));
        let mut flips = 0;
        for (geometry, view) in [&plain, &mirrored]
            .into_iter()
            .flat_map(|g| strata_slices::SliceView::ALL.map(|v| (g, v)))
        {
            let frame = SliceFrame::for_view(view, geometry);
            flips += frame.across_flipped as u32 + frame.down_flipped as u32;
            let r = zp.image_rect(inner(), frame.extent_mm(geometry));
            for pos in [Pos2::new(60.0, 70.0), Pos2::new(150.0, 40.0), r.center()] {
                let (a, d) = frame.index_at(dims, fraction_at(r, pos).0, fraction_at(r, pos).1);
                let back = screen_at(r, frame.fraction_of(dims, a, d));
                assert!(
                    (back - pos).length() < 1e-2,
                    "{view:?}: {pos:?} → ({a}, {d}) → {back:?}"
                );
            }
        }
        assert!(flips > 0, "the round trip went through a flipped axis");
    }
}
