//! The 3D view's pointer gestures as both viewers read them (strata_viewer_ui::orbit:
//! `OrbitInput::read` then `OrbitCamera::follow`), driven by egui events as a user makes them:
//! a left drag orbits, Shift+left or a middle drag pans, the wheel zooms, and a left drag left
//! to another tool (the desktop's label brush) does not orbit.

use egui::{Event, Modifiers, MouseWheelUnit, PointerButton, Pos2, Sense, Vec2};
use egui_kittest::Harness;
use strata_viewer_ui::orbit::{OrbitCamera, OrbitInput};

struct View {
    orbit: OrbitCamera,
    orbit_allowed: bool,
    size: Vec2,
}

fn view(orbit_allowed: bool) -> Harness<'static, View> {
    let mut harness = Harness::builder()
        .with_size(Vec2::new(400.0, 300.0))
        .with_step_dt(1.0 / 60.0)
        .build_ui_state(
            |ui, v: &mut View| {
                let rect = ui.max_rect();
                let response = ui.interact(rect, ui.scope_id().with("3d"), Sense::drag());
                let input = OrbitInput::read(ui, &response, v.orbit_allowed);
                v.orbit.follow(input, rect.size());
                v.size = rect.size();
            },
            View {
                orbit: OrbitCamera::default(),
                orbit_allowed,
                size: Vec2::ZERO,
            },
        );
    harness.run();
    harness
}

/// A drag with `button` from `from` by `by` in four pointer moves, holding `modifiers`.
fn drag(
    h: &mut Harness<'static, View>,
    button: PointerButton,
    from: Pos2,
    by: Vec2,
    modifiers: Modifiers,
) {
    h.event_modifiers(Event::PointerMoved(from), modifiers);
    h.event_modifiers(
        Event::PointerButton {
            pos: from,
            button,
            pressed: true,
            modifiers,
        },
        modifiers,
    );
    h.run();
    for step in 1..=4 {
        h.event_modifiers(
            Event::PointerMoved(from + by * step as f32 / 4.0),
            modifiers,
        );
        h.run();
    }
    h.event_modifiers(
        Event::PointerButton {
            pos: from + by,
            button,
            pressed: false,
            modifiers,
        },
        modifiers,
    );
    h.run();
}

#[test]
fn a_left_drag_orbits_a_shifted_or_middle_drag_pans_and_the_wheel_zooms() {
    let start = Pos2::new(200.0, 150.0);
    let mut h = view(true);
    drag(
        &mut h,
        PointerButton::Primary,
        start,
        Vec2::new(40.0, -20.0),
        Modifiers::NONE,
    );
    let size = h.state().size;
    let mut expected = OrbitCamera::default();
    expected.orbit_by(Vec2::new(40.0, -20.0), size);
    let orbit = h.state().orbit;
    assert!(
        (orbit.azimuth_deg - expected.azimuth_deg).abs() < 1e-3
            && (orbit.elevation_deg - expected.elevation_deg).abs() < 1e-3,
        "a left drag of (40, -20) in {size:?} orbits as orbit_by: {orbit:?}, expected {expected:?}"
    );
    assert_ne!(orbit.azimuth_deg, OrbitCamera::default().azimuth_deg);
    assert_eq!(orbit.pan, [0.0, 0.0], "orbiting does not pan");

    let before = h.state().orbit;
    drag(
        &mut h,
        PointerButton::Primary,
        start,
        Vec2::new(30.0, 0.0),
        Modifiers::SHIFT,
    );
    let shifted = h.state().orbit;
    assert_eq!(
        (shifted.azimuth_deg, shifted.elevation_deg),
        (before.azimuth_deg, before.elevation_deg),
        "Shift+drag pans instead of orbiting"
    );
    assert!(
        shifted.pan[0] < -0.1,
        "a drag to the right moves the target left: {shifted:?}"
    );

    drag(
        &mut h,
        PointerButton::Middle,
        start,
        Vec2::new(0.0, 30.0),
        Modifiers::NONE,
    );
    let middle = h.state().orbit;
    assert!(
        middle.pan[1] - shifted.pan[1] > 0.1,
        "a middle drag down pans: {middle:?}"
    );
    assert_eq!(middle.azimuth_deg, shifted.azimuth_deg);

    h.event(Event::MouseWheel {
        unit: MouseWheelUnit::Line,
        delta: Vec2::new(0.0, 3.0),
        modifiers: Modifiers::NONE,
        phase: egui::TouchPhase::Move,
        source: egui::MouseWheelSource::Unknown,
    });
    // egui keeps repainting while it smooths its own scroll; the raw wheel event is read once.
    for _ in 0..30 {
        h.step();
    }
    let zoom = h.state().orbit.zoom;
    assert!(
        (zoom - 1.1f64.powi(3)).abs() < 1e-9,
        "three wheel clicks: zoom {zoom}"
    );
}

#[test]
fn a_left_drag_left_to_another_tool_does_not_orbit_and_shift_still_pans() {
    let start = Pos2::new(200.0, 150.0);
    let mut h = view(false);
    drag(
        &mut h,
        PointerButton::Primary,
        start,
        Vec2::new(40.0, -20.0),
        Modifiers::NONE,
    );
    assert_eq!(h.state().orbit, OrbitCamera::default(), "the brush's drag");
    drag(
        &mut h,
        PointerButton::Primary,
        start,
        Vec2::new(30.0, 0.0),
        Modifiers::SHIFT,
    );
    assert!(h.state().orbit.pan[0] < -0.1, "{:?}", h.state().orbit);
}
