use egui::{Event, Modifiers, PointerButton, Pos2, Vec2};
use egui_kittest::Harness;
use strata_render::TransferFunction;
use strata_storage::histogram::Histogram;
use strata_viewer_ui::tf_editor::{self, Selection, TfEditorState};

/// The editor over 0..400 with four opacity points, and what it reported.
struct Editor {
    state: TfEditorState,
    tf: TransferFunction,
    histogram: Histogram,
    edits: usize,
}

const RANGE: (f64, f64) = (0.0, 400.0);

fn editor() -> Harness<'static, Editor> {
    let tf = TransferFunction::new(
        "test",
        &[(0.0, 0.0), (100.0, 0.2), (300.0, 0.8), (400.0, 1.0)],
        &[],
    );
    let histogram = Histogram {
        physical_min: RANGE.0,
        physical_max: RANGE.1,
        counts: (0..64).map(|i| (i * 37 % 101) as u64).collect(),
    };
    let mut harness = Harness::builder()
        .with_size(Vec2::new(420.0, 260.0))
        .build_ui_state(
            |ui, e: &mut Editor| {
                if tf_editor::show(ui, &mut e.state, &mut e.tf, &e.histogram, RANGE, "HU") {
                    e.edits += 1;
                }
            },
            Editor {
                state: TfEditorState::default(),
                tf,
                histogram,
                edits: 0,
            },
        );
    harness.run();
    harness
}

/// Where the editor draws `(value, opacity)`.
fn at(h: &Harness<'_, Editor>, value: f64, opacity: f64) -> Pos2 {
    let plot = h.state().state.plot_rect.expect("the plot was drawn");
    let x = (value - RANGE.0) / (RANGE.1 - RANGE.0);
    Pos2::new(
        plot.left() + x as f32 * plot.width(),
        plot.bottom() - opacity as f32 * plot.height(),
    )
}

fn press(h: &mut Harness<'_, Editor>, pos: Pos2, button: PointerButton, pressed: bool) {
    h.event(Event::PointerButton {
        pos,
        button,
        pressed,
        modifiers: Modifiers::NONE,
    });
}

/// The opacity the editor's plot maps a pixel row to is exact to about one pixel of its height.
fn pixel_tolerance(h: &Harness<'_, Editor>) -> f64 {
    let plot = h.state().state.plot_rect.expect("the plot was drawn");
    1.5 / plot.height() as f64
}

#[test]
fn dragging_an_opacity_point_changes_the_function_at_its_value() {
    let mut h = editor();
    let from = at(&h, 100.0, 0.2);
    let to = at(&h, 100.0, 0.9);
    h.event(Event::PointerMoved(from));
    h.step();
    press(&mut h, from, PointerButton::Primary, true);
    h.step();
    // In steps of about 2 points, as a hand moves: the first beyond egui's drag threshold starts
    // the drag, which takes the point within reach of the pointer there.
    for i in 1..=40 {
        h.event(Event::PointerMoved(from + (to - from) * (i as f32 / 40.0)));
        h.step();
    }
    press(&mut h, to, PointerButton::Primary, false);
    h.run();
    let e = h.state();
    assert!(e.edits > 0, "the editor reported no change");
    assert_eq!(
        e.tf.opacity.len(),
        4,
        "a drag must not add or remove points"
    );
    let tolerance = pixel_tolerance(&h);
    let opacity = e.tf.opacity_at(100.0);
    assert!(
        (opacity - 0.9).abs() <= tolerance,
        "opacity at 100 HU {opacity}, dragged to 0.9 (±{tolerance})"
    );
    // The other points stayed where they were.
    assert!((e.tf.opacity_at(300.0) - 0.8).abs() < 1e-9);
    assert_eq!(e.state.selection, Selection::Opacity(1));
}

#[test]
fn a_click_adds_a_point_and_a_right_click_removes_it() {
    let mut h = editor();
    let pos = at(&h, 200.0, 0.1);
    h.event(Event::PointerMoved(pos));
    press(&mut h, pos, PointerButton::Primary, true);
    press(&mut h, pos, PointerButton::Primary, false);
    h.run();
    let tolerance = pixel_tolerance(&h);
    {
        let e = h.state();
        assert_eq!(e.tf.opacity.len(), 5);
        let opacity = e.tf.opacity_at(200.0);
        assert!(
            (opacity - 0.1).abs() <= tolerance,
            "opacity at 200 HU {opacity} after the click at 0.1 (±{tolerance})"
        );
        assert!(e.tf.opacity.windows(2).all(|w| w[0].value <= w[1].value));
    }
    press(&mut h, pos, PointerButton::Secondary, true);
    press(&mut h, pos, PointerButton::Secondary, false);
    h.run();
    let e = h.state();
    assert_eq!(e.tf.opacity.len(), 4);
    // Back on the line between (100, 0.2) and (300, 0.8).
    assert!((e.tf.opacity_at(200.0) - 0.5).abs() < 1e-9);
}
