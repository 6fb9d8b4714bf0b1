//! The measurements panel: the tool the left button uses, the list (each deletable), clear all.

use crate::measurements::Tool;
use crate::scene::{Scene, VolumeData};

pub fn ui(ui: &mut egui::Ui, data: &VolumeData, scene: &mut Scene) {
    let m = &mut scene.measurements;
    ui.horizontal_wrapped(|ui| {
        for tool in Tool::ALL {
            if ui
                .selectable_label(m.tool == tool, tool.label())
                .on_hover_text(tool.hint())
                .clicked()
            {
                m.tool = tool;
                m.draft.points.clear();
            }
        }
    });
    ui.weak(m.tool.hint());
    if m.items.is_empty() {
        ui.weak("No measurements.");
        return;
    }
    let unit = data.unit();
    let mut delete = None;
    for item in &m.items {
        // The button first and the line elided in what is left, the full line on hover: a long
        // ROI statistics line in a grid widened the side panel and moved every view and button
        // under the cursor (issue 36).
        ui.horizontal(|ui| {
            if ui
                .small_button("Delete")
                .on_hover_text("Delete this measurement (Ctrl+Z brings it back)")
                .clicked()
            {
                delete = Some(item.id);
            }
            ui.add(egui::Label::new(item.describe(&data.info.geometry, &unit)).truncate());
        });
    }
    if let Some(id) = delete {
        m.remove(id);
    }
    if ui.button("Delete all").clicked() {
        m.items.clear();
    }
}
