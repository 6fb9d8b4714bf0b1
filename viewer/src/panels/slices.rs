//! The slices panel: window/level presets (CT's named windows, MR's auto percentile, the
//! scan's own), window and level values, and the colour map.

use crate::scene::{quantile_window, Scene, VolumeData, Window, CT_WINDOWS};

pub fn ui(ui: &mut egui::Ui, data: &VolumeData, scene: &mut Scene) {
    let is_ct = data.unit() == "HU";
    ui.horizontal_wrapped(|ui| {
        if is_ct {
            for preset in CT_WINDOWS {
                if ui
                    .selectable_label(scene.window == preset.window, preset.name)
                    .on_hover_text(format!(
                        "W {:.0} / L {:.0} HU",
                        preset.window.width, preset.window.centre
                    ))
                    .clicked()
                {
                    scene.window = preset.window;
                }
            }
        }
        // The scan's own windows (DICOM window presets), then the histogram's.
        for w in &data.info.header.windows {
            let window = Window::new(w.center, w.width.max(1e-6));
            if !CT_WINDOWS.iter().any(|p| p.window == window)
                && ui
                    .selectable_label(scene.window == window, format!("{} (scan)", w.name))
                    .clicked()
            {
                scene.window = window;
            }
        }
        let auto = quantile_window(&data.histogram, 0.01, 0.99);
        if ui
            .selectable_label(scene.window == auto, "Auto")
            .on_hover_text("1st to 99th percentile of the scan's values (MR, anything unscaled)")
            .clicked()
        {
            scene.window = auto;
        }
    });
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
