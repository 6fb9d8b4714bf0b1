//! The rendering panel: mode, iso value, shading and light, smooth transitions, traversal,
//! adaptive sampling, slice planes in 3D, projection, crop box and clip plane.

use strata_render::{RenderMode, ShadowMode};

use crate::adaptive_view::{format_epsilon, EPSILON_RANGE};
use crate::preferences::{
    effects_refused, CinematicPreset, LightPrefs, Preferences, TraversalChoice, AZIMUTH_RANGE,
    ELEVATION_RANGE, OCCLUSION_RADIUS_RANGE, SCATTERING_G_RANGE, SHADOW_STEP_RANGE,
};
use crate::scene::preset_for;
use crate::scene::{Scene, VolumeData};
use crate::view3d::View3d;

/// The render modes offered, with their labels (a new mode is one more line).
pub const RENDER_MODES: [(RenderMode, &str); 3] = [
    (RenderMode::Dvr, "DVR"),
    (RenderMode::Mip, "MIP"),
    (RenderMode::Isosurface, "Isosurface"),
];

/// Draws the panel; true when a cinematic preset replaced the transfer function (the caller
/// resets the TF editor's selection, which named points of the old one).
pub fn ui(
    ui: &mut egui::Ui,
    prefs: &mut Preferences,
    data: &VolumeData,
    scene: &mut Scene,
    view_3d: &mut View3d,
) -> bool {
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
    let tf_replaced = cinematic_presets(ui, prefs, data, scene);
    if ui.checkbox(&mut prefs.shading, "Shading (DVR)").changed() && !prefs.shading {
        // Shadows, occlusion and scattering are part of shading: unshaded DVR with one of
        // them on would be shaded anyway (render_lighting), so the checkbox would not do what
        // it says.
        prefs.light.effects_off();
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
    strata_viewer_ui::crop_clip::controls(ui, &mut scene.crop, &mut scene.clip);
    tf_replaced
}

/// The cinematic presets: one click sets the transfer function and the lighting that suits it
/// (issue 37). True when one was applied.
fn cinematic_presets(
    ui: &mut egui::Ui,
    prefs: &mut Preferences,
    data: &VolumeData,
    scene: &mut Scene,
) -> bool {
    let mut applied = false;
    ui.horizontal_wrapped(|ui| {
        let scan = strata_viewer_ui::presets::ScanValues::of(&data.info.header);
        for preset in CinematicPreset::ALL {
            let current = preset.is_current(prefs) && !scene.tf_edited();
            // A cinematic preset on a CT function is not offered for an MR (issue 47: a solid
            // red cube that never converged); it says why.
            let offer = strata_viewer_ui::presets::offer(preset.tf_preset, &scan);
            let mut response = ui.add_enabled(
                offer.is_offered(),
                egui::Button::selectable(current, preset.label),
            );
            if let (false, Some(reason)) = (offer.is_offered(), offer.reason()) {
                response = response.on_disabled_hover_text(reason);
            }
            if response
                .on_hover_text(format!(
                    "The {} transfer function lit by a key light from the upper left, with \
                     shadows from the light cache, ambient occlusion over {} mm and \
                     scattering (g {}, blend {}). Draws DVR (MIP is never lit) with the \
                     raycaster (adaptive sampling off).",
                    preset.tf_preset,
                    preset.occlusion_radius_mm,
                    preset.scattering_g,
                    preset.scattering_blend,
                ))
                .clicked()
            {
                preset.apply_to(prefs);
                scene.set_transfer_function(preset_for(preset.tf_preset, &data.info));
                applied = true;
            }
        }
    });
    applied
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
                prefs.adaptive_epsilon = crate::adaptive_view::DEFAULT_EPSILON;
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
    ui.add(
        egui::Slider::new(
            &mut prefs.progressive_frames,
            0..=crate::preferences::MAX_PROGRESSIVE_FRAMES,
        )
        .text(PROGRESSIVE_LABEL),
    )
    .on_hover_text(
        "With shadows, occlusion or scattering on, a still view keeps drawing jittered frames \
         of the same view and shows their mean, up to this many, then rests: the wood-grain \
         and shadow noise average out. 0: off. Any change starts again at 1.",
    );
}

/// Accessible name of the progressive refinement slider.
pub const PROGRESSIVE_LABEL: &str = "Progressive frames";

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
pub const CACHE_SHADOWS_LABEL: &str = "Cached shadows";
pub const OCCLUSION_LABEL: &str = "Ambient occlusion";
pub const OCCLUSION_RADIUS_LABEL: &str = "Occlusion radius";
pub const SCATTERING_LABEL: &str = "Scattering";
pub const SCATTERING_G_LABEL: &str = "Scattering g";
pub const SCATTERING_BLEND_LABEL: &str = "Scattering blend";
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

    let refused = effects_refused(prefs);
    ui.add_enabled_ui(refused.is_none(), |ui| {
        let why = refused.unwrap_or_default();
        let before = prefs.light;
        ui.horizontal_wrapped(|ui| {
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
            ui.radio_value(
                &mut prefs.light.shadows,
                ShadowMode::Cache,
                CACHE_SHADOWS_LABEL,
            )
            .on_hover_text(
                "One lookup per shaded sample in a coarse grid of the light reaching each \
                 point, rebuilt when the light, transfer function or loaded bricks change: \
                 fast, with softer edges. Needs a directional light (chosen if the headlight \
                 is on). Turns shading on.",
            )
            .on_disabled_hover_text(why);
        });
        if prefs.light.shadows == ShadowMode::Cache && before.shadows != ShadowMode::Cache {
            // The cache holds one light direction; the headlight's is each ray's own.
            prefs.light.headlight = false;
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
        ui.checkbox(&mut prefs.light.occlusion, OCCLUSION_LABEL)
            .on_hover_text(
                "Darken the ambient light where nearby matter hides a sample (creases, \
                 cavities): short rays around each shaded sample. Turns shading on.",
            )
            .on_disabled_hover_text(why);
        if prefs.light.occlusion {
            ui.add(
                egui::Slider::new(&mut prefs.light.occlusion_radius_mm, OCCLUSION_RADIUS_RANGE)
                    .suffix(" mm")
                    .text("radius"),
            )
            .on_hover_text(
                "How far the occlusion rays look: larger darkens broader folds and is slower.",
            )
            .accessible_name(OCCLUSION_RADIUS_LABEL);
        }
        ui.checkbox(&mut prefs.light.scattering, SCATTERING_LABEL)
            .on_hover_text(
                "Light scattered once inside tissue (Henyey-Greenstein phase), blended with \
                 the surface reflection where edges are strong. Turns shading on.",
            )
            .on_disabled_hover_text(why);
        if prefs.light.scattering {
            ui.add(egui::Slider::new(&mut prefs.light.scattering_g, SCATTERING_G_RANGE).text("g"))
                .on_hover_text(
                    "Asymmetry: > 0 scatters forward (tissue lit from behind glows), 0 evenly, \
                     < 0 back towards the light.",
                )
                .accessible_name(SCATTERING_G_LABEL);
            ui.add(egui::Slider::new(&mut prefs.light.scattering_blend, 0.0..=1.0).text("blend"))
                .on_hover_text(
                    "0: volume-like scattering everywhere; 1: surface-like reflection wherever \
                 the gradient is strong (bone), scattering in the smooth interior.",
                )
                .accessible_name(SCATTERING_BLEND_LABEL);
        }
        if prefs.light.any_effect() && !before.any_effect() {
            // As `strata render` does: each effect needs the lit path.
            prefs.shading = true;
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
    use crate::preferences::render_lighting;
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
    fn effects_are_refused_for_mip_and_the_adaptive_pass_and_turn_shading_on() {
        let mut prefs = Preferences {
            shading: false,
            ..Preferences::default()
        };
        prefs.light.shadows = ShadowMode::Exact;
        let lit = render_lighting(&prefs);
        assert_eq!(lit.shadows.mode, ShadowMode::Exact);
        assert!(
            lit.shading.is_some(),
            "shadows turn shading on, as the CLI does"
        );
        assert_eq!(lit.light.direction, LightDirection::Headlight);
        for effect in [
            |l: &mut LightPrefs| l.occlusion = true,
            |l: &mut LightPrefs| l.scattering = true,
        ] {
            let mut only = Preferences {
                shading: false,
                ..Preferences::default()
            };
            effect(&mut only.light);
            let lit = render_lighting(&only);
            assert!(lit.occlusion.is_some() || lit.scattering.is_some());
            assert!(lit.shading.is_some(), "each effect turns shading on");
        }
        prefs.light.occlusion = true;
        prefs.light.scattering = true;
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
            assert!(effects_refused(&refused).is_some());
            let lit = render_lighting(&refused);
            assert_eq!(lit.shadows.mode, ShadowMode::Off);
            assert_eq!(lit.occlusion, None);
            assert_eq!(lit.scattering, None);
            assert_eq!(lit.shading, None, "unshaded, as asked");
        }
    }

    #[test]
    fn cache_shadows_never_reach_render_with_the_headlight() {
        // Render refuses the cache with the headlight (one direction per cache): a
        // hand-edited file with both draws exact shadows instead of failing every frame.
        let mut prefs = Preferences::default();
        prefs.light.shadows = ShadowMode::Cache;
        prefs.light.occlusion_radius_mm = f64::NAN;
        prefs.light.scattering = true;
        prefs.light.scattering_g = 5.0;
        prefs.light.occlusion = true;
        let mut settings = strata_render::RenderSettings::default();
        render_lighting(&prefs).apply_to(&mut settings);
        assert_eq!(settings.shadows.mode, ShadowMode::Exact);
        settings
            .validate()
            .expect("the viewer's settings are valid");
        assert_eq!(settings.occlusion.map(|o| o.radius_mm), Some(4.0));
        assert_eq!(settings.scattering.map(|s| s.g), Some(0.9));
    }

    #[test]
    fn each_cinematic_preset_renders_valid_settings_for_dvr_and_isosurfaces() {
        for preset in CinematicPreset::ALL {
            for mode in [RenderMode::Dvr, RenderMode::Isosurface, RenderMode::Mip] {
                let mut prefs = Preferences {
                    mode,
                    adaptive_sampling: true,
                    shading: false,
                    ..Preferences::default()
                };
                preset.apply_to(&mut prefs);
                assert!(preset.is_current(&prefs));
                assert_eq!(
                    prefs.mode,
                    if mode == RenderMode::Mip {
                        RenderMode::Dvr
                    } else {
                        mode
                    },
                    "MIP, which is never lit, becomes DVR; other modes stay"
                );
                let mut settings = strata_render::RenderSettings {
                    mode: prefs.mode,
                    ..Default::default()
                };
                render_lighting(&prefs).apply_to(&mut settings);
                settings.validate().expect("valid settings");
                assert!(settings.effective_light_cache());
                assert!(settings.effective_occlusion().is_some());
                assert!(settings.effective_scattering().is_some());
                match settings.light.direction {
                    // Upper left of the view, in front of the volume.
                    LightDirection::Camera([x, y, z]) => {
                        assert!(x < 0.0 && y > 0.0 && z > 0.0, "{x} {y} {z}")
                    }
                    other => panic!("a camera-relative key light, got {other:?}"),
                }
            }
        }
        let [bone, soft] = CinematicPreset::ALL;
        assert!(
            bone.scattering_blend > soft.scattering_blend,
            "bone is surface-like, soft tissue volume-like"
        );
    }
}
