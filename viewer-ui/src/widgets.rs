//! Small widgets the shared panels need.

use std::time::Duration;

use egui::{Pos2, Sense, Shape, Stroke, Vec2};

/// egui's spinner, stepped at 10 Hz: `egui::Spinner` asks for a repaint every frame it is
/// visible, which on a software rasteriser kept the UI thread drawing at full rate for as long
/// as anything was refining (issue 36). The render thread wakes the UI for each new frame anyway.
pub fn slow_spinner(ui: &mut egui::Ui) -> egui::Response {
    let size = ui.style().spacing.interact_size.y;
    let (rect, response) = ui.allocate_exact_size(Vec2::splat(size), Sense::hover());
    if ui.is_rect_visible(rect) {
        ui.ctx().request_repaint_after(Duration::from_millis(100));
        let colour = ui.visuals().strong_text_color();
        let radius = rect.height().min(rect.width()) * 0.5 - 2.0;
        // Whole tenths of a second: each repaint draws the next step.
        let time = (ui.input(|i| i.time) * 10.0).floor() / 10.0;
        let start = time * std::f64::consts::TAU;
        let end = start + 240f64.to_radians() * time.sin();
        let points: Vec<Pos2> = (0..16)
            .map(|i| {
                let angle = start + (end - start) * i as f64 / 16.0;
                rect.center() + radius * Vec2::new(angle.cos() as f32, angle.sin() as f32)
            })
            .collect();
        ui.painter()
            .add(Shape::line(points, Stroke::new(3.0, colour)));
    }
    response
}
