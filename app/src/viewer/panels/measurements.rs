//! The measurements panel: the tool the left button uses, the list (each deletable), clear all.

use crate::viewer::measurements::Tool;
use crate::viewer::scene::{Scene, VolumeData};

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
    egui::Grid::new("measurements")
        .num_columns(2)
        .striped(true)
        .show(ui, |ui| {
            for item in &m.items {
                ui.label(item.describe(&data.info.geometry, &unit));
                if ui
                    .small_button("Delete")
                    .on_hover_text("Delete this measurement (Ctrl+Z brings it back)")
                    .clicked()
                {
                    delete = Some(item.id);
                }
                ui.end_row();
            }
        });
    if let Some(id) = delete {
        m.remove(id);
    }
    if ui.button("Delete all").clicked() {
        m.items.clear();
    }
}
