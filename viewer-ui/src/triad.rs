//! The orientation triad in the 3D view's bottom-left corner, like Slicer's orientation
//! marker (issue 47): lines from a centre showing where the patient's L, P and S point (R, A,
//! I labelled at the far ends), turned with the camera. Both viewers draw it with
//! [`paint_triad`]; [`triad`] is its geometry, which the page's browser test aims at.

use egui::{Color32, Pos2, Rect, Stroke, Vec2};
use glam::DVec3;
use strata_render::Camera;

/// One patient axis of the triad.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriadAxis {
    /// The patient axis (LPS: x to the left, y posterior, z superior).
    pub axis: DVec3,
    /// The label at its positive end ("L", "P", "S") and at its negative end.
    pub positive: &'static str,
    pub negative: &'static str,
    pub colour: Color32,
    /// The positive end relative to the centre, in points (screen y down).
    pub tip: Vec2,
    /// How far the axis points away from the viewer (the camera's forward · axis): the
    /// farthest is drawn first so the nearer ones cover it.
    pub depth: f64,
}

/// Where the triad goes in a view and its axes in drawing order (farthest first).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triad {
    pub centre: Pos2,
    pub radius: f32,
    pub axes: [TriadAxis; 3],
}

/// The axes' colours: red L, green P, blue S, as Slicer's.
pub const L_COLOUR: Color32 = Color32::from_rgb(230, 80, 80);
pub const P_COLOUR: Color32 = Color32::from_rgb(90, 200, 90);
pub const S_COLOUR: Color32 = Color32::from_rgb(90, 140, 240);
/// Width of an axis' positive half (points); its negative half is drawn thinner and dimmer.
pub const AXIS_WIDTH: f32 = 3.0;

/// The triad of a view at `view_rect` seen through `camera`.
pub fn triad(view_rect: Rect, camera: &Camera) -> Triad {
    let basis = camera.basis();
    let radius = (view_rect.width().min(view_rect.height()) * 0.08).clamp(22.0, 48.0);
    let centre = Pos2::new(
        view_rect.left() + radius + 14.0,
        view_rect.bottom() - radius - 14.0,
    );
    let axis = |axis: DVec3, positive, negative, colour| TriadAxis {
        axis,
        positive,
        negative,
        colour,
        tip: Vec2::new(axis.dot(basis.right) as f32, -axis.dot(basis.up) as f32) * radius,
        depth: axis.dot(basis.forward),
    };
    let mut axes = [
        axis(DVec3::X, "L", "R", L_COLOUR),
        axis(DVec3::Y, "P", "A", P_COLOUR),
        axis(DVec3::Z, "S", "I", S_COLOUR),
    ];
    axes.sort_by(|a, b| b.depth.total_cmp(&a.depth));
    Triad {
        centre,
        radius,
        axes,
    }
}

/// Draws the triad of `camera` in the corner of the view at `view_rect`.
pub fn paint_triad(painter: &egui::Painter, view_rect: Rect, camera: &Camera) {
    let triad = triad(view_rect, camera);
    let centre = triad.centre;
    painter.circle_filled(centre, triad.radius + 10.0, Color32::from_black_alpha(120));
    for axis in &triad.axes {
        let tip = axis.tip;
        painter.line_segment(
            [centre - tip, centre + tip],
            Stroke::new(2.0, axis.colour.gamma_multiply(0.5)),
        );
        painter.line_segment([centre, centre + tip], Stroke::new(AXIS_WIDTH, axis.colour));
        let font = egui::FontId::proportional(12.0);
        painter.text(
            centre + tip * 1.22,
            egui::Align2::CENTER_CENTER,
            axis.positive,
            font.clone(),
            axis.colour,
        );
        painter.text(
            centre - tip * 1.22,
            egui::Align2::CENTER_CENTER,
            axis.negative,
            font,
            axis.colour.gamma_multiply(0.7),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::orbit::StandardView;
    use strata_render::{Projection, VolumeGeometry};

    fn camera(view: StandardView) -> Camera {
        let geometry = VolumeGeometry::axis_aligned([32, 32, 32], [1.0; 3]);
        let (az, el) = view.angles_deg();
        Camera::orbit_panned(
            &geometry,
            az,
            el,
            1.0,
            [0.0, 0.0],
            Projection::Perspective { fov_y_deg: 30.0 },
        )
    }

    #[test]
    fn from_the_front_left_points_right_on_screen_and_superior_up() {
        let rect = Rect::from_min_size(Pos2::ZERO, egui::vec2(400.0, 300.0));
        let front = triad(rect, &camera(StandardView::Anterior));
        let find =
            |t: &Triad, label: &str| *t.axes.iter().find(|a| a.positive == label).expect("axis");
        // Facing the patient: their left on the viewer's right, superior up, posterior away.
        let l = find(&front, "L");
        assert!(l.tip.x > 0.9 * front.radius && l.tip.y.abs() < 0.05 * front.radius);
        let s = find(&front, "S");
        assert!(s.tip.y < -0.9 * front.radius && s.tip.x.abs() < 0.05 * front.radius);
        let p = find(&front, "P");
        assert!(p.tip.length() < 0.05 * front.radius && p.depth > 0.9);
        assert_eq!(
            front.axes[0].positive, "P",
            "the farthest axis is drawn first"
        );
        // In the bottom-left corner.
        assert!(front.centre.x < 100.0 && front.centre.y > 200.0);
        // From the patient's left: posterior points right on screen (a left lateral view).
        let left = triad(rect, &camera(StandardView::Left));
        let p = find(&left, "P");
        assert!(p.tip.length() > 0.9 * left.radius, "{p:?}");
        assert!(find(&left, "L").tip.length() < 0.05 * left.radius);
    }
}
