use egui::accesskit::Role;
use egui_kittest::kittest::{NodeT, Queryable};
use egui_kittest::Harness;
use strata_viewer_ui::target_fps::target_fps_control;

#[derive(Default)]
struct Control {
    enabled: bool,
    fps: f64,
    changes: usize,
}

fn control(enabled: bool, fps: f64) -> Harness<'static, Control> {
    let mut harness = Harness::new_ui_state(
        |ui, c: &mut Control| {
            if target_fps_control(ui, &mut c.enabled, &mut c.fps) {
                c.changes += 1;
            }
        },
        Control {
            enabled,
            fps,
            changes: 0,
        },
    );
    harness.run();
    harness
}

#[test]
fn the_checkbox_switches_the_target_and_the_slider_writes_the_rate() {
    let mut h = control(false, 10.0);
    h.get_by_role_and_label(Role::CheckBox, "Target frame rate")
        .click();
    h.run();
    assert!(h.state().enabled);
    assert_eq!(h.state().changes, 1);
    h.get_by_role(Role::Slider).set_value_accesskit(24.0);
    h.run();
    assert!((h.state().fps - 24.0).abs() < 1e-9, "fps {}", h.state().fps);
    assert_eq!(h.state().changes, 2);
}

#[test]
fn the_slider_is_disabled_without_a_target() {
    let mut h = control(false, 10.0);
    assert!(h.get_by_role(Role::Slider).accesskit_node().is_disabled());
    h.get_by_role_and_label(Role::CheckBox, "Target frame rate")
        .click();
    h.run();
    assert!(!h.get_by_role(Role::Slider).accesskit_node().is_disabled());
}
