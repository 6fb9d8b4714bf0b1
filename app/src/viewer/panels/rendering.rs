//! The rendering panel: mode, iso value, shading, smooth transitions, traversal, adaptive
//! sampling, slice planes in 3D, projection, crop box and clip plane.

use strata_render::{CropBox, RenderMode};

use crate::viewer::adaptive_view::{format_epsilon, EPSILON_RANGE};
use crate::viewer::preferences::{Preferences, TraversalChoice};
use crate::viewer::scene::{Scene, VolumeData};
use crate::viewer::view3d::View3d;

/// The render modes offered, with their labels (a new mode is one more line).
pub const RENDER_MODES: [(RenderMode, &str); 3] = [
    (RenderMode::Dvr, "DVR"),
    (RenderMode::Mip, "MIP"),
    (RenderMode::Isosurface, "Isosurface"),
];

pub fn ui(
    ui: &mut egui::Ui,
    prefs: &mut Preferences,
    data: &VolumeData,
    scene: &mut Scene,
    view_3d: &mut View3d,
) {
    let unit = &data.info.header.value_mapping.unit;
    ui.horizontal(|ui| {
        for (mode, label) in RENDER_MODES {
            ui.radio_value(&mut prefs.mode, mode, label);
        }
    });
    if prefs.mode == RenderMode::Isosurface {
        let (lo, hi) = data.info.physical_range;
        ui.add(egui::Slider::new(&mut scene.iso_value, lo..=hi).text(format!("iso value {unit}")));
    }
    ui.checkbox(&mut prefs.shading, "Shading (DVR)");
    ui.checkbox(&mut prefs.smooth_transitions, "Smooth level transitions")
        .on_hover_text(
            "Blend across the half voxel where bricks of different resolution meet, \
             so coarse and fine bricks join without seams. Off shows the seams.",
        );
    egui::ComboBox::from_label("Traversal")
        .selected_text(prefs.traversal.label())
        .show_ui(ui, |ui| {
            for (choice, label) in TraversalChoice::ALL {
                ui.selectable_value(&mut prefs.traversal, choice, label);
            }
        })
        .response
        .on_hover_text(
            "How rays find the bricks: the flat page table (one entry per finest brick) or \
             the octree of the loaded bricks (memory grows with what is loaded). Automatic: \
             flat unless it exceeds the GPU's limit. A change reloads the volume.",
        );
    adaptive_sampling(ui, prefs);
    ui.checkbox(&mut prefs.show_planes_in_3d, "Slice planes in the 3D view");
    if ui
        .checkbox(&mut prefs.orthographic, "Orthographic projection")
        .changed()
    {
        view_3d.orbit.orthographic = prefs.orthographic;
    }
    ui.checkbox(
        &mut prefs.show_crop_box,
        "Show the crop box in 3D (drag its face handles)",
    );
    ui.label("Crop box (fraction of each index axis)");
    for (axis, name) in ["i", "j", "k"].iter().enumerate() {
        ui.horizontal(|ui| {
            ui.label(*name);
            let mut min = scene.crop.min[axis];
            let mut max = scene.crop.max[axis];
            ui.add(egui::DragValue::new(&mut min).speed(0.005).range(0.0..=1.0))
                .accessible_name(format!("Crop {name} from"));
            ui.add(egui::DragValue::new(&mut max).speed(0.005).range(0.0..=1.0))
                .accessible_name(format!("Crop {name} to"));
            scene.crop.min[axis] = min.min(max - 0.01).max(0.0);
            scene.crop.max[axis] = max.max(min + 0.01).min(1.0);
        });
    }
    let clip = &mut scene.clip;
    ui.horizontal(|ui| {
        ui.checkbox(&mut clip.enabled, "Clip plane");
        egui::ComboBox::from_id_salt("clip axis")
            .selected_text(["L–R", "A–P", "S–I"][clip.axis])
            .show_ui(ui, |ui| {
                ui.selectable_value(&mut clip.axis, 0, "L–R (sagittal)");
                ui.selectable_value(&mut clip.axis, 1, "A–P (coronal)");
                ui.selectable_value(&mut clip.axis, 2, "S–I (axial)");
            })
            .response
            .accessible_name("Clip plane axis");
        ui.checkbox(&mut clip.flip, "flip");
    });
    if clip.enabled {
        ui.add(egui::Slider::new(&mut clip.fraction, 0.0..=1.0).text("position"));
    }
    if ui.button("Reset crop and clip").clicked() {
        scene.crop = CropBox::default();
        scene.clip.enabled = false;
    }
}

/// The checkbox label (the UI tests find it by this text).
pub const ADAPTIVE_LABEL: &str = "Adaptive sampling (still view)";
/// The ε slider's accessible name.
pub const EPSILON_LABEL: &str = "Adaptive ε";

/// Adaptive sampling of the still view and its oracle's ε (logarithmic slider).
fn adaptive_sampling(ui: &mut egui::Ui, prefs: &mut Preferences) {
    let iso = prefs.mode == RenderMode::Isosurface;
    ui.add_enabled_ui(!iso, |ui| {
        ui.checkbox(&mut prefs.adaptive_sampling, ADAPTIVE_LABEL)
            .on_hover_text(
                "When the view is still and loaded, draw the final frame by adaptive sampling \
                 (samples on view-aligned slices, skipped where the data are smooth and \
                 synthesised from coarser ones): far fewer samples for nearly the same image. \
                 Moving the camera draws with the raycaster as usual.",
            )
            .on_disabled_hover_text(
                "Adaptive sampling draws DVR and MIP; the isosurface's hit search is the \
                 raycaster's own.",
            );
        if prefs.adaptive_sampling {
            let (lo, hi) = EPSILON_RANGE;
            if !prefs.adaptive_epsilon.is_finite() {
                prefs.adaptive_epsilon = crate::viewer::adaptive_view::DEFAULT_EPSILON;
            }
            ui.add(
                egui::Slider::new(&mut prefs.adaptive_epsilon, lo..=hi)
                    .logarithmic(true)
                    .custom_formatter(|v, _| format_epsilon(v))
                    .text("ε"),
            )
            .on_hover_text(
                "The oracle's ε: the opacity change per slice a 2³ block may have before it is \
                 sampled at every slice. Smaller is closer to the raycaster and slower; larger \
                 skips more and may step over thin features.",
            )
            .accessible_name(EPSILON_LABEL);
        }
    });
}
