//! The slice views' zoom and pan gestures (strata_viewer_ui::slice_canvas, both viewers'),
//! driven by egui events as a user makes them: Ctrl+wheel zooms about the pointer, middle
//! drag pans, a double-click resets.

use egui::{Event, Modifiers, MouseWheelUnit, PointerButton, Pos2, Rect, Sense, Vec2};
use egui_kittest::Harness;
use strata_viewer_ui::slice_canvas::{fraction_at, inner_rect, ZoomPan};

#[derive(Default)]
struct View {
    zoom_pan: ZoomPan,
    image_rect: Option<Rect>,
    double_clicks: usize,
}

fn view() -> Harness<'static, View> {
    let mut harness = Harness::builder()
        .with_size(Vec2::new(400.0, 300.0))
        // 60 frames a second, as a user's: the default quarter-second frames would put two
        // clicks further apart than egui's double-click delay.
        .with_step_dt(1.0 / 60.0)
        .build_ui_state(
            |ui, v: &mut View| {
                let rect = ui.max_rect();
                let response =
                    ui.interact(rect, ui.scope_id().with("slice"), Sense::click_and_drag());
                let inner = inner_rect(rect);
                if v.zoom_pan.input(ui, &response, inner) {
                    v.double_clicks += 1;
                }
                v.image_rect = Some(v.zoom_pan.image_rect(inner, (200.0, 100.0)));
            },
            View::default(),
        );
    harness.run();
    harness
}

fn under(h: &Harness<'static, View>, pointer: Pos2) -> (f64, f64) {
    fraction_at(h.state().image_rect.expect("drawn"), pointer)
}

fn event(h: &mut Harness<'static, View>, event: Event) {
    h.event(event);
    h.run();
}

fn button(h: &mut Harness<'static, View>, pos: Pos2, button: PointerButton, pressed: bool) {
    event(
        h,
        Event::PointerButton {
            pos,
            button,
            pressed,
            modifiers: Modifiers::NONE,
        },
    );
}

#[test]
fn ctrl_wheel_zooms_about_the_pointer_and_middle_drag_pans_and_a_double_click_resets() {
    let mut h = view();
    let pointer = Pos2::new(150.0, 120.0);
    event(&mut h, Event::PointerMoved(pointer));
    let before = under(&h, pointer);
    h.event_modifiers(
        Event::MouseWheel {
            unit: MouseWheelUnit::Line,
            delta: Vec2::new(0.0, 3.0),
            modifiers: Modifiers::COMMAND,
            phase: egui::TouchPhase::Move,
            source: egui::MouseWheelSource::Unknown,
        },
        Modifiers::COMMAND,
    );
    // Wheel input is smoothed over frames: let it arrive.
    for _ in 0..30 {
        h.step();
    }
    let zoom = h.state().zoom_pan.zoom;
    assert!(zoom > 1.2, "Ctrl+wheel up zooms in: {zoom}");
    let after = under(&h, pointer);
    assert!(
        (after.0 - before.0).abs() < 1e-3 && (after.1 - before.1).abs() < 1e-3,
        "the point under the pointer moved: {before:?} → {after:?}"
    );

    // Middle drag pans by the pointer's movement.
    let pan = h.state().zoom_pan.pan;
    button(&mut h, pointer, PointerButton::Middle, true);
    for step in 1..=4 {
        event(
            &mut h,
            Event::PointerMoved(pointer + Vec2::new(5.0 * step as f32, -2.0 * step as f32)),
        );
    }
    let dragged_to = pointer + Vec2::new(20.0, -8.0);
    button(&mut h, dragged_to, PointerButton::Middle, false);
    let moved = h.state().zoom_pan.pan - pan;
    assert!(
        (moved - Vec2::new(20.0, -8.0)).length() < 6.0,
        "the image follows the middle drag: {moved:?}"
    );
    assert_eq!(h.state().zoom_pan.zoom, zoom, "panning keeps the zoom");

    // A double-click puts zoom and pan back.
    for _ in 0..2 {
        for pressed in [true, false] {
            h.event(Event::PointerButton {
                pos: dragged_to,
                button: PointerButton::Primary,
                pressed,
                modifiers: Modifiers::NONE,
            });
        }
        h.step();
    }
    assert_eq!(h.state().double_clicks, 1);
    assert_eq!(h.state().zoom_pan, ZoomPan::default());
}
