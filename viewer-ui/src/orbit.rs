//! The 3D view's orbit as both viewers drive it (issue 47): how far a drag turns the view and
//! the six standard views the A/P/L/R/S/I keys jump to. One copy, so that a drag of N points or
//! a key gives the same angles on the desktop (viewer/src/view3d.rs) and in the page
//! (strata-web's browser.rs), and a shared link opens the view the other viewer showed.

/// Azimuth and elevation after a drag of `delta` points (x right, y down) across a 3D view
/// `view_height` points tall: a drag over the full height turns the view by 180°, so the
/// turn per point does not depend on the window's size in proportion to the view. Azimuth is
/// kept in 0..360 and elevation within the poles (±90°).
pub fn orbit_by_drag(
    azimuth_deg: f64,
    elevation_deg: f64,
    delta: [f64; 2],
    view_height: f64,
) -> (f64, f64) {
    // Views under 100 points (a squeezed layout) would turn too fast to aim.
    let degrees_per_point = 180.0 / view_height.max(100.0);
    (
        (azimuth_deg - delta[0] * degrees_per_point).rem_euclid(360.0),
        (elevation_deg + delta[1] * degrees_per_point).clamp(-90.0, 90.0),
    )
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

    /// The key that shows this view in either viewer.
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

    /// The orbit's (azimuth, elevation) in degrees. Azimuth 90° puts the eye at +x (LPS
    /// left): the patient's left side faces us.
    pub fn angles_deg(self) -> (f64, f64) {
        match self {
            StandardView::Anterior => (0.0, 0.0),
            StandardView::Posterior => (180.0, 0.0),
            StandardView::Left => (90.0, 0.0),
            StandardView::Right => (-90.0, 0.0),
            StandardView::Superior => (0.0, 90.0),
            StandardView::Inferior => (0.0, -90.0),
        }
    }

    /// The standard view whose key was pressed this frame, if any (the last of several).
    pub fn pressed(input: &egui::InputState) -> Option<StandardView> {
        StandardView::ALL
            .into_iter()
            .rev()
            .find(|view| input.key_pressed(view.key()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_drag_over_the_full_view_height_turns_the_view_half_round() {
        let (az, el) = orbit_by_drag(30.0, 15.0, [400.0, 0.0], 400.0);
        assert_eq!((az, el), (210.0, 15.0));
        // Down by a quarter of the height: 45° towards superior; past the pole it stops.
        assert_eq!(orbit_by_drag(30.0, 15.0, [0.0, 100.0], 400.0), (30.0, 60.0));
        assert_eq!(orbit_by_drag(30.0, 15.0, [0.0, 400.0], 400.0), (30.0, 90.0));
        // Right by 40 points in a 200-point view: 36° less azimuth, wrapped into 0..360.
        assert_eq!(orbit_by_drag(30.0, 0.0, [40.0, 0.0], 200.0), (354.0, 0.0));
        // A tiny view turns as a 100-point one.
        assert_eq!(orbit_by_drag(0.0, 0.0, [0.0, -10.0], 20.0), (0.0, -18.0));
    }

    #[test]
    fn each_key_names_one_standard_view() {
        let mut keys: Vec<_> = StandardView::ALL.iter().map(|v| v.key()).collect();
        keys.dedup();
        assert_eq!(keys.len(), 6);
        let mut angles: Vec<_> = StandardView::ALL.iter().map(|v| v.angles_deg()).collect();
        angles.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
        angles.dedup();
        assert_eq!(angles.len(), 6, "six distinct views");
    }
}
