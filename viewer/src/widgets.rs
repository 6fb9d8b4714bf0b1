//! Small pieces every view and dialog shares: the not-for-diagnosis wording and colour, view
//! titles, wheel input in lines, and what a view reports after drawing itself. (The widgets the
//! browser viewer shares, such as the slow spinner, are in strata_viewer_ui::widgets.)

use egui::{Color32, Rect, Sense, Vec2};

pub const NOT_FOR_DIAGNOSIS: &str = "NOT FOR DIAGNOSTIC USE";
pub const WARNING_COLOUR: Color32 = Color32::from_rgb(255, 170, 40);

/// What a view reports after drawing itself.
#[derive(Clone, Copy, Debug, Default)]
pub struct ViewResponse {
    /// Its title was double-clicked: focus (1×1) or unfocus it.
    pub toggle_focus: bool,
    /// It was clicked or dragged: it becomes the focused view (keys page it).
    pub focused: bool,
    /// The level-0 continuous index under the pointer (slices: on the slice; 3D: at the pick
    /// depth), for the readout.
    pub hover: Option<[f64; 3]>,
}

/// Wheel movement this frame in lines (up positive), whatever unit the platform reports it in.
pub fn wheel_lines(ui: &egui::Ui) -> f64 {
    ui.input(|i| {
        i.events
            .iter()
            .map(|e| match e {
                egui::Event::MouseWheel { unit, delta, .. } => match unit {
                    // egui-winit reports a wheel click as 40 points on most platforms.
                    egui::MouseWheelUnit::Point => delta.y as f64 / 40.0,
                    egui::MouseWheelUnit::Line => delta.y as f64,
                    egui::MouseWheelUnit::Page => delta.y as f64 * 10.0,
                },
                _ => 0.0,
            })
            .sum::<f64>()
    })
}

/// Paints a view's title; returns true when it was double-clicked (focus toggle).
pub fn view_title(ui: &mut egui::Ui, rect: Rect, id: &str, title: &str, colour: Color32) -> bool {
    let galley_rect = Rect::from_min_size(
        rect.min + Vec2::new(6.0, 4.0),
        Vec2::new(title.len() as f32 * 7.5 + 8.0, 16.0),
    );
    let response = ui.interact(
        galley_rect,
        ui.scope_id().with(("title", id)),
        Sense::click(),
    );
    ui.painter_at(rect).text(
        rect.min + Vec2::new(8.0, 4.0),
        egui::Align2::LEFT_TOP,
        title,
        egui::FontId::proportional(13.0),
        colour,
    );
    response
        .on_hover_text("Double-click to focus / unfocus this view")
        .double_clicked()
}
