//! The slices panel: window/level presets (strata-viewer-ui's window_presets, shared with the
//! browser: CT's named windows, MR's auto percentile, the scan's own), window and level values,
//! and the colour map.

use crate::scene::{Scene, VolumeData};

pub fn ui(ui: &mut egui::Ui, data: &VolumeData, scene: &mut Scene) {
    strata_viewer_ui::window_presets::preset_buttons(
        ui,
        data.unit() == "HU",
        &data.info.header.windows,
        &data.histogram,
        &mut scene.window,
    );
    let unit = data.unit();
    ui.horizontal(|ui| {
        let (lo, hi) = data.info.physical_range;
        let speed = ((hi - lo) / 1000.0).max(1e-6);
        ui.label("W");
        ui.add(
            egui::DragValue::new(&mut scene.window.width)
                .speed(speed)
                .range(1e-6..=f64::MAX)
                .suffix(format!(" {unit}")),
        )
        .accessible_name("Window width");
        ui.label("L");
        ui.add(
            egui::DragValue::new(&mut scene.window.centre)
                .speed(speed)
                .suffix(format!(" {unit}")),
        )
        .accessible_name("Window level");
    });
    ui.horizontal(|ui| {
        ui.label("Colour map");
        strata_viewer_ui::slice_canvas::colour_map_combo(ui, &mut scene.colour_map);
    });
}
