//! The 3D view's camera and mouse handling: orbit (left drag), pan (middle or shift+left),
//! zoom (wheel), the six standard views, and the orientation marker.

use egui::{Color32, Pos2, Rect, Stroke, Vec2};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use strata_render::{Camera, Projection, VolumeGeometry};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrbitCamera {
    /// Degrees about the patient's superior axis; 0 looks at the patient's face (anterior view).
    pub azimuth_deg: f64,
    /// Degrees towards superior, within ±90.
    pub elevation_deg: f64,
    /// 1 frames the whole volume.
    pub zoom: f64,
    /// Target offset in the view plane, in units of the volume's bounding radius.
    pub pan: [f64; 2],
    pub orthographic: bool,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        OrbitCamera {
            azimuth_deg: 30.0,
            elevation_deg: 15.0,
            zoom: 1.0,
            pan: [0.0, 0.0],
            orthographic: false,
        }
    }
}

/// The six standard views, named for where the viewer stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StandardView {
    Anterior,
    Posterior,
    Left,
    Right,
    Superior,
    Inferior,
}

impl StandardView {
    pub const ALL: [StandardView; 6] = [
        StandardView::Anterior,
        StandardView::Posterior,
        StandardView::Left,
        StandardView::Right,
        StandardView::Superior,
        StandardView::Inferior,
    ];

    pub fn letter(self) -> &'static str {
        match self {
            StandardView::Anterior => "A",
            StandardView::Posterior => "P",
            StandardView::Left => "L",
            StandardView::Right => "R",
            StandardView::Superior => "S",
            StandardView::Inferior => "I",
        }
    }

    pub fn key(self) -> egui::Key {
        match self {
            StandardView::Anterior => egui::Key::A,
            StandardView::Posterior => egui::Key::P,
            StandardView::Left => egui::Key::L,
            StandardView::Right => egui::Key::R,
            StandardView::Superior => egui::Key::S,
            StandardView::Inferior => egui::Key::I,
        }
    }

    pub fn description(self) -> &'static str {
        match self {
            StandardView::Anterior => "from the front (anterior)",
            StandardView::Posterior => "from behind (posterior)",
            StandardView::Left => "from the patient's left",
            StandardView::Right => "from the patient's right",
            StandardView::Superior => "from above (superior)",
            StandardView::Inferior => "from below (inferior)",
        }
    }
}

impl OrbitCamera {
    pub fn standard(view: StandardView, orthographic: bool) -> Self {
        // Azimuth 90° puts the eye at +x (LPS left): the patient's left side faces us.
        let (azimuth_deg, elevation_deg) = match view {
            StandardView::Anterior => (0.0, 0.0),
            StandardView::Posterior => (180.0, 0.0),
            StandardView::Left => (90.0, 0.0),
            StandardView::Right => (-90.0, 0.0),
            StandardView::Superior => (0.0, 90.0),
            StandardView::Inferior => (0.0, -90.0),
        };
        OrbitCamera {
            azimuth_deg,
            elevation_deg,
            zoom: 1.0,
            pan: [0.0, 0.0],
            orthographic,
        }
    }

    /// Built here rather than with `Camera::orbit`, which takes -z (inferior in LPS) as up and
    /// so shows heads upside down; a radiologist expects superior at the top.
    pub fn camera(&self, geometry: &VolumeGeometry) -> Camera {
        let radius = geometry.bounding_radius_mm().max(1e-6);
        let zoom = if self.zoom.is_finite() && self.zoom > 1e-6 {
            self.zoom
        } else {
            1.0
        };
        let (az, el) = (
            self.azimuth_deg.to_radians(),
            self.elevation_deg.to_radians(),
        );
        let superior = DVec3::Z;
        let from_centre = DVec3::new(az.sin() * el.cos(), -az.cos() * el.cos(), el.sin());
        let fov_y_deg = 30.0f64;
        let (distance, projection) = if self.orthographic {
            (
                radius * 3.0,
                Projection::Orthographic {
                    height_mm: 2.0 * radius / zoom,
                },
            )
        } else {
            (
                radius / (fov_y_deg.to_radians() * 0.5).sin() / zoom,
                Projection::Perspective { fov_y_deg },
            )
        };
        // Looking straight down or up the superior axis: keep anterior at the top of the screen.
        let up = if from_centre.cross(superior).length() < 1e-6 {
            -DVec3::Y
        } else {
            superior
        };
        let (right, screen_up) = {
            let forward = -from_centre;
            let right = forward.cross(up).normalize_or_zero();
            (right, right.cross(forward))
        };
        let shift = (right * self.pan[0] + screen_up * self.pan[1]) * radius;
        let target = geometry.centre_patient() + shift;
        let eye = target + from_centre * distance;
        Camera::look_at(eye.into(), target.into(), up.into(), projection)
    }

    /// Orbit by a drag of `delta` points in a view `size` points tall.
    pub fn orbit_by(&mut self, delta: Vec2, size: Vec2) {
        let degrees_per_point = 180.0 / size.y.max(100.0) as f64;
        self.azimuth_deg =
            (self.azimuth_deg - delta.x as f64 * degrees_per_point).rem_euclid(360.0);
        self.elevation_deg =
            (self.elevation_deg + delta.y as f64 * degrees_per_point).clamp(-90.0, 90.0);
    }

    pub fn pan_by(&mut self, delta: Vec2, size: Vec2) {
        // A drag across the full view height moves the scene by one bounding diameter at zoom 1.
        let per_point = 2.0 / size.y.max(1.0) as f64 / self.zoom;
        self.pan[0] -= delta.x as f64 * per_point;
        self.pan[1] += delta.y as f64 * per_point;
    }

    /// Wheel: `scroll` points (positive = away from the user = zoom in).
    pub fn zoom_by(&mut self, scroll: f32) {
        self.zoom = (self.zoom * (scroll as f64 / 200.0).exp()).clamp(0.2, 20.0);
    }
}

/// Draws axes showing where L, P, S point (lines from the centre; R/A/I labels at the far
/// ends) in the corner of the 3D view, like Slicer's orientation marker.
pub fn paint_orientation_marker(painter: &egui::Painter, view_rect: Rect, camera: &Camera) {
    let basis = camera.basis();
    let radius = (view_rect.width().min(view_rect.height()) * 0.08).clamp(22.0, 48.0);
    let centre = Pos2::new(
        view_rect.left() + radius + 14.0,
        view_rect.bottom() - radius - 14.0,
    );
    painter.circle_filled(centre, radius + 10.0, Color32::from_black_alpha(120));
    let axes = [
        (DVec3::X, "L", "R", Color32::from_rgb(230, 80, 80)),
        (DVec3::Y, "P", "A", Color32::from_rgb(90, 200, 90)),
        (DVec3::Z, "S", "I", Color32::from_rgb(90, 140, 240)),
    ];
    // Far axes first so near ones draw on top.
    let mut order: Vec<_> = axes.iter().collect();
    order.sort_by(|a, b| b.0.dot(basis.forward).total_cmp(&a.0.dot(basis.forward)));
    for (axis, positive, negative, colour) in order {
        let screen = Vec2::new(axis.dot(basis.right) as f32, -axis.dot(basis.up) as f32) * radius;
        painter.line_segment(
            [centre - screen, centre + screen],
            Stroke::new(2.0, colour.gamma_multiply(0.5)),
        );
        painter.line_segment([centre, centre + screen], Stroke::new(3.0, *colour));
        let font = egui::FontId::proportional(12.0);
        painter.text(
            centre + screen * 1.22,
            egui::Align2::CENTER_CENTER,
            *positive,
            font.clone(),
            *colour,
        );
        painter.text(
            centre - screen * 1.22,
            egui::Align2::CENTER_CENTER,
            *negative,
            font,
            colour.gamma_multiply(0.7),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry() -> VolumeGeometry {
        VolumeGeometry::axis_aligned([64, 64, 64], [1.0, 1.0, 1.0])
    }

    #[test]
    fn standard_views_look_from_the_named_side() {
        let g = geometry();
        let centre = g.centre_patient();
        let from = |v: StandardView| {
            (DVec3::from(OrbitCamera::standard(v, false).camera(&g).eye) - centre)
                .try_normalize()
                .expect("the eye is away from the centre")
        };
        assert!(
            from(StandardView::Anterior).dot(-DVec3::Y) > 0.99,
            "anterior is -y in LPS"
        );
        assert!(from(StandardView::Posterior).dot(DVec3::Y) > 0.99);
        assert!(
            from(StandardView::Left).dot(DVec3::X) > 0.99,
            "patient left is +x in LPS"
        );
        assert!(from(StandardView::Right).dot(-DVec3::X) > 0.99);
        assert!(
            from(StandardView::Superior).dot(DVec3::Z) > 0.99,
            "superior is +z in LPS"
        );
        assert!(from(StandardView::Inferior).dot(-DVec3::Z) > 0.99);
    }

    #[test]
    fn superior_is_up_on_screen_and_the_patients_left_on_the_right_in_an_anterior_view() {
        let g = geometry();
        let basis = OrbitCamera::standard(StandardView::Anterior, false)
            .camera(&g)
            .basis();
        assert!(basis.up.dot(DVec3::Z) > 0.99, "superior at the top");
        // Facing the patient, their left (+x) is on the viewer's right.
        assert!(basis.right.dot(DVec3::X) > 0.99);
        let basis = OrbitCamera::standard(StandardView::Superior, false)
            .camera(&g)
            .basis();
        assert!(
            basis.up.dot(-DVec3::Y) > 0.99,
            "anterior at the top when looking down"
        );
    }

    #[test]
    fn pan_moves_eye_and_target_together() {
        let g = geometry();
        let mut orbit = OrbitCamera::default();
        let before = orbit.camera(&g);
        orbit.pan_by(Vec2::new(30.0, 0.0), Vec2::new(300.0, 300.0));
        let after = orbit.camera(&g);
        let eye_shift = DVec3::from(after.eye) - DVec3::from(before.eye);
        let target_shift = DVec3::from(after.target) - DVec3::from(before.target);
        assert!((eye_shift - target_shift).length() < 1e-9 && eye_shift.length() > 1.0);
    }
}
