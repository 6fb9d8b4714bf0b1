//! The rendering panel: mode, iso value, shading and light, smooth transitions, traversal,
//! adaptive sampling, slice planes in 3D, projection, crop box and clip plane.

use strata_render::RenderMode;

use strata_viewer_ui::adaptive;
use strata_viewer_ui::lighting::{cinematic_buttons, light_controls, LightOffer};

use crate::preferences::{effects_refused, CinematicPreset, Preferences, TraversalChoice};
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

/// The cinematic presets (the shared buttons, strata-viewer-ui's lighting.rs): one click sets
/// the transfer function and the lighting that suits it (issue 37). True when one was applied.
fn cinematic_presets(
    ui: &mut egui::Ui,
    prefs: &mut Preferences,
    data: &VolumeData,
    scene: &mut Scene,
) -> bool {
    let scan = strata_viewer_ui::presets::ScanValues::of(&data.info.header);
    let edited = scene.tf_edited();
    let current = |preset: &CinematicPreset| prefs.is_cinematic(preset) && !edited;
    let (Some(preset), _) = cinematic_buttons(ui, &scan, current) else {
        return false;
    };
    prefs.apply_cinematic(&preset);
    scene.set_transfer_function(preset_for(preset.tf_preset, &data.info));
    true
}

/// Adaptive sampling of the still view and its oracle's ε (viewer-ui's shared controls).
fn adaptive_sampling(ui: &mut egui::Ui, prefs: &mut Preferences) {
    adaptive::controls(
        ui,
        prefs.mode,
        &mut prefs.adaptive_sampling,
        &mut prefs.adaptive_epsilon,
    );
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

/// The key light, its effects and the shading switch they turn on: the shared controls.
fn light(ui: &mut egui::Ui, prefs: &mut Preferences) {
    let offer = LightOffer {
        effects_refused: effects_refused(prefs),
    };
    light_controls(ui, &mut prefs.light, &mut prefs.shading, offer);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preferences::render_lighting;
    use strata_render::{LightDirection, ShadowMode};
    use strata_viewer_ui::lighting::LightPrefs;

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
                prefs.apply_cinematic(&preset);
                assert!(prefs.is_cinematic(&preset));
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
