//! The target frame-rate control: a checkbox (on: the time-critical controller holds the rate
//! while the camera moves; off: the caller's fixed sampling step) and the rate's slider.

use std::ops::RangeInclusive;

/// The rates the slider offers (frames per second).
pub const TARGET_FPS_RANGE: RangeInclusive<f64> = 2.0..=60.0;

/// The checkbox labelled "Target frame rate" and the slider (enabled with it). Returns true
/// when either changed.
pub fn target_fps_control(ui: &mut egui::Ui, enabled: &mut bool, fps: &mut f64) -> bool {
    ui.horizontal(|ui| {
        let checkbox = ui.checkbox(enabled, "Target frame rate");
        let slider = ui
            .add_enabled(
                *enabled,
                egui::Slider::new(fps, TARGET_FPS_RANGE)
                    .suffix(" fps")
                    .logarithmic(true),
            )
            .labelled_by(checkbox.id);
        checkbox.changed() || slider.changed()
    })
    .inner
}
