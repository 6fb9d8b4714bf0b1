//! The rendering panel: mode, iso value, shading and light, smooth transitions, traversal,
//! adaptive sampling, slice planes in 3D, projection, crop box and clip plane.

use strata_render::{CropBox, RenderMode, ShadowMode};

use crate::viewer::adaptive_view::{format_epsilon, EPSILON_RANGE};
use crate::viewer::preferences::{
    shadows_refused, LightPrefs, Preferences, TraversalChoice, AZIMUTH_RANGE, ELEVATION_RANGE,
    SHADOW_STEP_RANGE,
};
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
    if ui.checkbox(&mut prefs.shading, "Shading (DVR)").changed() && !prefs.shading {
        // Shadows are part of shading: unshaded DVR with shadows on would be shaded anyway
        // (render_lighting), so the checkbox would not do what it says.
        prefs.light.shadows = ShadowMode::Off;
    }
    light(ui, prefs);
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

/// Accessible names of the light controls (the UI tests find them by these).
pub const HEADLIGHT_LABEL: &str = "Headlight";
pub const DIRECTIONAL_LABEL: &str = "Directional";
pub const AZIMUTH_LABEL: &str = "Light azimuth";
pub const ELEVATION_LABEL: &str = "Light elevation";
pub const INTENSITY_LABEL: &str = "Light intensity";
pub const AMBIENT_LABEL: &str = "Ambient";
pub const GIZMO_LABEL: &str = "Light direction gizmo";
pub const NO_SHADOWS_LABEL: &str = "No shadows";
pub const EXACT_SHADOWS_LABEL: &str = "Exact shadows";
pub const SHADOW_STEP_LABEL: &str = "Shadow step";
/// Side of the direction gizmo, points: small enough never to widen the panel (issue 36).
const GIZMO_SIDE: f32 = 64.0;

/// The key light (headlight or a camera-relative direction), its intensity, the ambient term
/// and shadows (issue 37; the same settings as `strata render --light-dir --shadows`).
fn light(ui: &mut egui::Ui, prefs: &mut Preferences) {
    ui.horizontal(|ui| {
        ui.label("Key light");
        ui.radio_value(&mut prefs.light.headlight, true, HEADLIGHT_LABEL)
            .on_hover_text("The light at the eye, as Strata has always lit.");
        ui.radio_value(&mut prefs.light.headlight, false, DIRECTIONAL_LABEL)
            .on_hover_text(
                "A directional light placed relative to the camera: it turns with the view.",
            );
    });
    let light = &mut prefs.light;
    if !light.headlight {
        ui.horizontal(|ui| {
            direction_gizmo(ui, light);
            ui.vertical(|ui| {
                ui.add(
                    egui::Slider::new(&mut light.azimuth_deg, AZIMUTH_RANGE)
                        .suffix("°")
                        .text("az."),
                )
                .on_hover_text("Left (−) or right (+) of the view axis.")
                .accessible_name(AZIMUTH_LABEL);
                ui.add(
                    egui::Slider::new(&mut light.elevation_deg, ELEVATION_RANGE)
                        .suffix("°")
                        .text("el."),
                )
                .on_hover_text("Below (−) or above (+) the view axis.")
                .accessible_name(ELEVATION_LABEL);
            });
        });
    }
    ui.add(egui::Slider::new(&mut light.intensity, 0.0..=2.0).text("intensity"))
        .on_hover_text("The key light's diffuse and specular term.")
        .accessible_name(INTENSITY_LABEL);
    ui.add(egui::Slider::new(&mut light.ambient, 0.0..=1.0).text("ambient"))
        .on_hover_text("Light from everywhere: what shadows never darken.")
        .accessible_name(AMBIENT_LABEL);

    let refused = shadows_refused(prefs);
    ui.add_enabled_ui(refused.is_none(), |ui| {
        let why = refused.unwrap_or_default();
        let before = prefs.light.shadows;
        ui.horizontal(|ui| {
            ui.label("Shadows");
            ui.radio_value(&mut prefs.light.shadows, ShadowMode::Off, NO_SHADOWS_LABEL)
                .on_disabled_hover_text(why);
            ui.radio_value(
                &mut prefs.light.shadows,
                ShadowMode::Exact,
                EXACT_SHADOWS_LABEL,
            )
            .on_hover_text(
                "A shadow ray towards the key light from every shaded sample: exact, and \
                 slower by the shadow ray's length. Turns shading on.",
            )
            .on_disabled_hover_text(why);
        });
        if prefs.light.shadows != before && prefs.light.shadows != ShadowMode::Off {
            // As `strata render --shadows` does: shadows need the lit path.
            prefs.shading = true;
        }
        if prefs.light.shadows != ShadowMode::Off {
            ui.add(
                egui::Slider::new(&mut prefs.light.shadow_step, SHADOW_STEP_RANGE)
                    .logarithmic(true)
                    .text("shadow step (voxels)"),
            )
            .on_hover_text(
                "The shadow ray's step in finest voxels: smaller is more exact and slower.",
            )
            .accessible_name(SHADOW_STEP_LABEL);
        }
    });
}

/// The gizmo square's point for a direction: azimuth across, elevation up (the same angles as
/// the sliders, so the two always agree); the centre is the view axis.
pub fn gizmo_point(rect: egui::Rect, light: &LightPrefs) -> egui::Pos2 {
    let u =
        (light.azimuth_deg - AZIMUTH_RANGE.start()) / (AZIMUTH_RANGE.end() - AZIMUTH_RANGE.start());
    let v = (ELEVATION_RANGE.end() - light.elevation_deg)
        / (ELEVATION_RANGE.end() - ELEVATION_RANGE.start());
    rect.lerp_inside(egui::vec2(
        u.clamp(0.0, 1.0) as f32,
        v.clamp(0.0, 1.0) as f32,
    ))
}

/// The direction at a point of the gizmo square (inverse of [`gizmo_point`], clamped to it).
pub fn gizmo_angles(rect: egui::Rect, at: egui::Pos2) -> (f64, f64) {
    let u = ((at.x - rect.left()) / rect.width()).clamp(0.0, 1.0) as f64;
    let v = ((at.y - rect.top()) / rect.height()).clamp(0.0, 1.0) as f64;
    let azimuth = AZIMUTH_RANGE.start() + u * (AZIMUTH_RANGE.end() - AZIMUTH_RANGE.start());
    let elevation = ELEVATION_RANGE.end() - v * (ELEVATION_RANGE.end() - ELEVATION_RANGE.start());
    (azimuth, elevation)
}

/// A small square to drag the light's direction in: a click or drag puts the light there.
fn direction_gizmo(ui: &mut egui::Ui, light: &mut LightPrefs) {
    let (rect, response) =
        ui.allocate_exact_size(egui::Vec2::splat(GIZMO_SIDE), egui::Sense::click_and_drag());
    if let Some(at) = response.interact_pointer_pos() {
        (light.azimuth_deg, light.elevation_deg) = gizmo_angles(rect, at);
    }
    let visuals = ui.style().interact(&response);
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 2.0, ui.visuals().extreme_bg_color);
    let faint = egui::Stroke::new(1.0, ui.visuals().weak_text_color());
    painter.line_segment([rect.center_top(), rect.center_bottom()], faint);
    painter.line_segment([rect.left_center(), rect.right_center()], faint);
    painter.circle_filled(gizmo_point(rect, light), 4.0, visuals.fg_stroke.color);
    response
        .on_hover_text(
            "Drag to place the light: the centre is the view axis, left and right turn it \
             to ±180°, up and down to ±90°.",
        )
        .accessible_name(GIZMO_LABEL);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::viewer::preferences::render_lighting;
    use strata_render::LightDirection;

    #[test]
    fn the_gizmo_and_the_sliders_name_the_same_direction() {
        let rect = egui::Rect::from_min_size(egui::pos2(10.0, 20.0), egui::Vec2::splat(64.0));
        // The centre is the view axis: light from behind the camera, along z.
        let (az, el) = gizmo_angles(rect, rect.center());
        assert!(az.abs() < 1e-9 && el.abs() < 1e-9, "{az} {el}");
        let light = LightPrefs {
            azimuth_deg: 45.0,
            elevation_deg: -30.0,
            ..LightPrefs::default()
        };
        let (az, el) = gizmo_angles(rect, gizmo_point(rect, &light));
        assert!(
            (az - 45.0).abs() < 1e-3 && (el + 30.0).abs() < 1e-3,
            "{az} {el}"
        );
        // Up in the square is up in the view; outside it clamps to the ranges.
        let (_, el) = gizmo_angles(rect, rect.center_top() - egui::vec2(0.0, 50.0));
        assert_eq!(el, 90.0);
        let along = LightPrefs {
            azimuth_deg: 0.0,
            elevation_deg: 0.0,
            ..LightPrefs::default()
        }
        .camera_direction();
        assert_eq!(along, [0.0, 0.0, 1.0]);
    }

    #[test]
    fn shadows_are_refused_for_mip_and_the_adaptive_pass_and_turn_shading_on() {
        let mut prefs = Preferences {
            shading: false,
            ..Preferences::default()
        };
        prefs.light.shadows = ShadowMode::Exact;
        let (shading, light, shadows) = render_lighting(&prefs);
        assert_eq!(shadows.mode, ShadowMode::Exact);
        assert!(
            shading.is_some(),
            "shadows turn shading on, as the CLI does"
        );
        assert_eq!(light.direction, LightDirection::Headlight);
        for refused in [
            Preferences {
                mode: RenderMode::Mip,
                ..prefs.clone()
            },
            Preferences {
                adaptive_sampling: true,
                ..prefs.clone()
            },
        ] {
            assert!(shadows_refused(&refused).is_some());
            let (shading, _, shadows) = render_lighting(&refused);
            assert_eq!(shadows.mode, ShadowMode::Off);
            assert_eq!(shading, None, "unshaded, as asked");
        }
    }
}
