//! The 3D view's orbit camera, one for both viewers (issue 47 item 5): azimuth, elevation,
//! zoom, pan and projection, what a drag, a pan, the wheel and the six standard views do to
//! them, and the camera they give. The desktop's 3D view (viewer/src/view3d.rs) and the page's
//! (web/src/browser.rs) both hold an [`OrbitCamera`], and a shared link (view_state.rs) carries
//! one, so the same link and the same drags give the same picture in both (tested in
//! view_state.rs: `the_page_and_the_desktop_orbit_alike_from_the_same_link`).
//!
//! Platform independent (builds for wasm32): it takes drag deltas and view sizes in points.

use egui::Vec2;
use serde::{Deserialize, Serialize};
use strata_render::{Camera, Projection, VolumeGeometry};

/// The perspective camera's vertical field of view, as `strata render`'s perspective default.
pub const FOV_Y_DEG: f64 = 30.0;

/// Zoom factor per wheel click in the 3D view.
pub const ZOOM_PER_WHEEL_LINE: f64 = 1.1;
/// The zoom's range: from a fifth of the framed volume to twenty times it (the wheel, the
/// page's zoom slider and its embedding parent's requests stop there).
pub const MIN_ZOOM: f64 = 0.2;
pub const MAX_ZOOM: f64 = 20.0;

/// What the pointer did to a 3D view this frame, read alike by both viewers
/// ([`OrbitInput::read`]) and applied by [`OrbitCamera::follow`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OrbitInput {
    /// A primary-button drag without Shift, in points: orbits.
    pub orbit_drag: Option<Vec2>,
    /// A middle-button drag, or Shift with the primary button, in points: pans.
    pub pan_drag: Option<Vec2>,
    /// Wheel clicks over the view (positive: away from the user, zoom in).
    pub wheel_lines: f64,
}

impl OrbitInput {
    /// This frame's pointer on the view's `response` (a rect sensing drags). `orbit_allowed`
    /// false leaves the primary drag to another tool (the desktop's label brushes; Shift-drag
    /// still pans).
    pub fn read(ui: &egui::Ui, response: &egui::Response, orbit_allowed: bool) -> Self {
        let (shift, pointer_delta) = ui.input(|i| (i.modifiers.shift, i.pointer.delta()));
        let primary = response.dragged_by(egui::PointerButton::Primary);
        let middle = response.dragged_by(egui::PointerButton::Middle);
        OrbitInput {
            orbit_drag: (primary && !shift && orbit_allowed).then_some(pointer_delta),
            pan_drag: (middle || (primary && shift)).then_some(pointer_delta),
            wheel_lines: if response.hovered() {
                crate::widgets::wheel_lines(ui)
            } else {
                0.0
            },
        }
    }
}

/// Where the 3D view looks from: the state a drag, the wheel and the standard views change,
/// and what a shared link's `az`, `el`, `zoom`, `pan` and `proj` say.
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

    /// The camera this orbit shows: [`Camera::orbit_panned`], as `strata render --azimuth
    /// --elevation --zoom` builds it (the same function: a link opens the same picture in the
    /// desktop viewer, the page and the command line).
    pub fn camera(&self, geometry: &VolumeGeometry) -> Camera {
        let projection = if self.orthographic {
            // orbit_panned sizes the height from the zoom.
            Projection::Orthographic { height_mm: 1.0 }
        } else {
            Projection::Perspective {
                fov_y_deg: FOV_Y_DEG,
            }
        };
        Camera::orbit_panned(
            geometry,
            self.azimuth_deg,
            self.elevation_deg,
            self.zoom,
            self.pan,
            projection,
        )
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

    /// Wheel: `lines` clicks (positive = away from the user = zoom in), 10 % per click, as
    /// Slicer's 3D view (egui's smoothed scroll in points made 3 clicks zoom ~4×).
    pub fn zoom_by_lines(&mut self, lines: f64) {
        self.zoom = (self.zoom * ZOOM_PER_WHEEL_LINE.powf(lines)).clamp(MIN_ZOOM, MAX_ZOOM);
    }

    /// Applies one frame's pointer `input` on a view `size` points large: orbit, then pan,
    /// then zoom. True when the view moved (the caller then draws the moving frames at the
    /// target rate).
    pub fn follow(&mut self, input: OrbitInput, size: Vec2) -> bool {
        if let Some(delta) = input.orbit_drag {
            self.orbit_by(delta, size);
        }
        if let Some(delta) = input.pan_drag {
            self.pan_by(delta, size);
        }
        if input.wheel_lines != 0.0 {
            self.zoom_by_lines(input.wheel_lines);
        }
        input.orbit_drag.is_some() || input.pan_drag.is_some() || input.wheel_lines != 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

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
    fn three_wheel_clicks_zoom_a_third_not_four_times() {
        let mut orbit = OrbitCamera::default();
        for _ in 0..3 {
            orbit.zoom_by_lines(1.0);
        }
        assert!((orbit.zoom - 1.331).abs() < 1e-9, "zoom {}", orbit.zoom);
        orbit.zoom_by_lines(-3.0);
        assert!((orbit.zoom - 1.0).abs() < 1e-9);
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
