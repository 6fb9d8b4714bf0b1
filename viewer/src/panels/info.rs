//! The volume information panel: modality, geometry, values, storage, levels, the scan's
//! windows; identifiers only when the user asks.

use crate::preferences::Preferences;
use crate::scene::VolumeData;

pub fn ui(ui: &mut egui::Ui, prefs: &mut Preferences, data: &VolumeData) {
    let v = data;
    let h = &v.info.header;
    let g = &h.geometry;
    egui::Grid::new("info")
        .num_columns(2)
        .striped(true)
        .show(ui, |ui| {
            let mut row = |k: &str, val: String| {
                ui.label(k);
                ui.label(val);
                ui.end_row();
            };
            row(
                "Modality",
                if h.modality.is_empty() {
                    "(unknown)".into()
                } else {
                    h.modality.clone()
                },
            );
            row(
                "Dimensions",
                format!("{} × {} × {}", g.dims[0], g.dims[1], g.dims[2]),
            );
            row(
                "Spacing",
                format!(
                    "{:.3} × {:.3} × {:.3} mm",
                    g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2]
                ),
            );
            row(
                "Extent",
                format!(
                    "{:.0} × {:.0} × {:.0} mm",
                    g.dims[0] as f64 * g.spacing_mm[0],
                    g.dims[1] as f64 * g.spacing_mm[1],
                    g.dims[2] as f64 * g.spacing_mm[2]
                ),
            );
            row(
                "Origin (LPS)",
                format!(
                    "{:.1}, {:.1}, {:.1} mm",
                    g.origin_lps_mm[0], g.origin_lps_mm[1], g.origin_lps_mm[2]
                ),
            );
            let code: String = g.direction.iter().map(|d| orientation_letter(*d)).collect();
            row("Orientation", format!("{code} (index axes point towards)"));
            row(
                "Values",
                format!(
                    "{:.1} … {:.1} {}",
                    v.info.physical_range.0, v.info.physical_range.1, h.value_mapping.unit
                ),
            );
            row(
                "Stored as",
                format!(
                    "{:?}, physical = {} × stored + {}",
                    h.stored, h.value_mapping.mapping.slope, h.value_mapping.mapping.intercept
                ),
            );
            row("Levels", h.layout.level_count().to_string());
            for w in &h.windows {
                row(
                    "Window",
                    format!("{}: W {:.0} / L {:.0}", w.name, w.width, w.center),
                );
            }
        });
    ui.checkbox(
        &mut prefs.show_identifiers,
        "Show identifiers (description, source file names)",
    );
    if prefs.show_identifiers {
        ui.label(format!("Description: {}", h.description));
        for input in &h.provenance.inputs {
            ui.label(format!("Source: {input}"));
        }
    } else {
        ui.weak("Patient identifiers hidden.");
    }
}

fn orientation_letter(direction: [f64; 3]) -> char {
    let a = direction.map(f64::abs);
    if a[0] >= a[1] && a[0] >= a[2] {
        if direction[0] > 0.0 {
            'L'
        } else {
            'R'
        }
    } else if a[1] >= a[2] {
        if direction[1] > 0.0 {
            'P'
        } else {
            'A'
        }
    } else if direction[2] > 0.0 {
        'S'
    } else {
        'I'
    }
}
