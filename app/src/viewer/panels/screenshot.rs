//! The screenshot panel: folder and resolution.

use std::path::PathBuf;

use crate::viewer::app::Preferences;

pub fn ui(ui: &mut egui::Ui, prefs: &mut Preferences) {
    ui.horizontal(|ui| {
        ui.label("Folder");
        let mut folder = prefs.screenshot_folder.display().to_string();
        if ui
            .text_edit_singleline(&mut folder)
            .accessible_name("Screenshot folder")
            .changed()
        {
            prefs.screenshot_folder = PathBuf::from(folder);
        }
    });
    ui.horizontal(|ui| {
        ui.label("Resolution");
        for s in [1, 2, 4] {
            ui.selectable_value(&mut prefs.screenshot_scale, s, format!("{s}×"));
        }
    });
}
