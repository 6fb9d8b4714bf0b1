//! The 3D view's lighting, shared by the desktop's rendering panel and the browser's side panel
//! (issue 37; shared since issue 47): the light the user sets ([`LightPrefs`]: headlight or a
//! camera-relative key light, intensity, ambient, shadows, occlusion, scattering), when its
//! effects cannot be drawn ([`effects_refused`]), the one function that turns it into render
//! settings ([`render_lighting`]), its controls ([`light_controls`] with the direction gizmo),
//! and the one-click cinematic looks ([`CinematicPreset`], [`cinematic_buttons`]).
//!
//! Platform-independent: plain values in, egui out; the desktop persists [`LightPrefs`] in its
//! preferences, the browser carries it in the link (view_state.rs).

use serde::{Deserialize, Serialize};
use strata_render::{
    KeyLight, LightDirection, Occlusion, RenderMode, RenderSettings, Scattering, Shading,
    ShadowMode, Shadows,
};

/// The viewer's light controls (issue 37). The direction is kept as angles, not as render's
/// [`LightDirection`], so choosing the headlight and back keeps the direction the user set.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LightPrefs {
    /// Light at the eye (today's look); false: the directional key light of the angles below.
    pub headlight: bool,
    /// Camera-relative, degrees: 0 is along the view axis, positive to the right.
    pub azimuth_deg: f64,
    /// Camera-relative, degrees: positive is above.
    pub elevation_deg: f64,
    /// The key light's direct (diffuse and specular) term.
    pub intensity: f32,
    /// [`Shading::ambient`]: what shadows never darken.
    pub ambient: f32,
    pub shadows: ShadowMode,
    /// Shadow-ray step in finest voxels.
    pub shadow_step: f64,
    /// Ambient occlusion on (the radius is kept while it is off, as the direction is).
    pub occlusion: bool,
    /// Length of the occlusion rays, mm.
    pub occlusion_radius_mm: f64,
    /// Single scattering of the key light on.
    pub scattering: bool,
    /// Henyey-Greenstein asymmetry: > 0 forward (back-lit tissue glows).
    pub scattering_g: f64,
    /// Exposure Render's gradient factor: 0 volume-like everywhere, 1 surface-like at edges.
    pub scattering_blend: f64,
}

impl Default for LightPrefs {
    /// The headlight at render's defaults: the image Strata has always drawn.
    fn default() -> Self {
        let key = KeyLight::default();
        let shadows = Shadows::default();
        LightPrefs {
            headlight: true,
            azimuth_deg: -30.0,
            elevation_deg: 30.0,
            intensity: key.intensity,
            ambient: Shading::default().ambient,
            shadows: shadows.mode,
            shadow_step: shadows.step,
            occlusion: false,
            occlusion_radius_mm: 4.0,
            scattering: false,
            scattering_g: 0.4,
            scattering_blend: 0.5,
        }
    }
}

/// Degrees the direction angles span (the sliders and the gizmo square).
pub const AZIMUTH_RANGE: std::ops::RangeInclusive<f64> = -180.0..=180.0;
pub const ELEVATION_RANGE: std::ops::RangeInclusive<f64> = -90.0..=90.0;
/// Shadow-step range in finest voxels: the CLI's lower bound (render refuses smaller steps);
/// above a few voxels shadows only blur.
pub const SHADOW_STEP_RANGE: std::ops::RangeInclusive<f64> = 0.05..=8.0;
/// Occlusion radius in mm: below 1 mm it darkens little more than a voxel's own matter; the
/// rays' cost grows with the radius (render takes up to `strata render`'s 100 mm), and beyond
/// ~20 mm occlusion is no longer local shape but a second shadow.
pub const OCCLUSION_RADIUS_RANGE: std::ops::RangeInclusive<f64> = 1.0..=20.0;
/// Scattering asymmetry offered: past ±0.9 the phase is a narrow spike that only shows when
/// looking into the light.
pub const SCATTERING_G_RANGE: std::ops::RangeInclusive<f64> = -0.9..=0.9;
/// Scattering blend: Exposure Render's gradient factor, a fraction.
pub const SCATTERING_BLEND_RANGE: std::ops::RangeInclusive<f64> = 0.0..=1.0;
/// The key light's intensity offered: 2 already washes bone out at render's default ambient.
pub const INTENSITY_RANGE: std::ops::RangeInclusive<f64> = 0.0..=2.0;
/// The ambient term, a fraction of the TF colour.
pub const AMBIENT_RANGE: std::ops::RangeInclusive<f64> = 0.0..=1.0;

impl LightPrefs {
    /// The direction towards the light in camera axes (x right, y up, z towards the viewer),
    /// as `--light-dir` takes it.
    pub fn camera_direction(&self) -> [f64; 3] {
        let (az, el) = (
            self.azimuth_deg.to_radians(),
            self.elevation_deg.to_radians(),
        );
        [el.cos() * az.sin(), el.sin(), el.cos() * az.cos()]
    }

    pub fn key_light(&self) -> KeyLight {
        KeyLight {
            direction: if self.headlight {
                LightDirection::Headlight
            } else {
                LightDirection::Camera(self.camera_direction())
            },
            // A damaged or hand-edited file must not make every frame invalid.
            intensity: if self.intensity.is_finite() {
                self.intensity.max(0.0)
            } else {
                KeyLight::default().intensity
            },
        }
    }

    /// Whether any effect that needs the lit path is on (shadows, occlusion, scattering).
    pub fn any_effect(&self) -> bool {
        self.shadows != ShadowMode::Off || self.occlusion || self.scattering
    }

    /// Turns shadows, occlusion and scattering off (shading was turned off: each of them
    /// would keep the view shaded otherwise, so the checkbox would not do what it says).
    pub fn effects_off(&mut self) {
        self.shadows = ShadowMode::Off;
        self.occlusion = false;
        self.scattering = false;
    }

    pub fn shading(&self) -> Shading {
        Shading {
            ambient: if self.ambient.is_finite() {
                self.ambient.clamp(0.0, 1.0)
            } else {
                Shading::default().ambient
            },
            ..Shading::default()
        }
    }
}

/// What besides the light decides how the 3D view is lit: the mode, the "Shading" switch and
/// whether the adaptive pass draws the still view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LitView {
    pub mode: RenderMode,
    pub shading: bool,
    pub adaptive_sampling: bool,
}

/// Why shadows, occlusion and scattering cannot be drawn in this view, or None where they can:
/// the CLI refuses them for MIP (never lit), and the adaptive pass draws none of them.
pub fn effects_refused(view: LitView) -> Option<&'static str> {
    if view.mode == RenderMode::Mip {
        Some("Shadows, occlusion and scattering light DVR and isosurfaces: MIP is never lit.")
    } else if view.adaptive_sampling && view.mode != RenderMode::Isosurface {
        Some(
            "The adaptive pass draws no shadows, occlusion or scattering: turn adaptive \
             sampling off to draw them.",
        )
    } else {
        None
    }
}

/// The lighting part of the 3D view's render settings (issue 37).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    pub shading: Option<Shading>,
    pub light: KeyLight,
    pub shadows: Shadows,
    pub occlusion: Option<Occlusion>,
    pub scattering: Option<Scattering>,
}

impl Lighting {
    pub fn apply_to(&self, settings: &mut RenderSettings) {
        settings.shading = self.shading;
        settings.light = self.light;
        settings.shadows = self.shadows;
        settings.occlusion = self.occlusion;
        settings.scattering = self.scattering;
    }
}

/// A finite value clamped to `range`, else `fallback` (a damaged or hand-edited file must not
/// make every frame invalid).
fn sane(v: f64, range: std::ops::RangeInclusive<f64>, fallback: f64) -> f64 {
    if v.is_finite() {
        v.clamp(*range.start(), *range.end())
    } else {
        fallback
    }
}

/// The 3D view's lighting: shading, key light, shadows, occlusion and scattering. Each effect
/// turns shading on (as `strata render` does); isosurfaces are always shaded, with the light's
/// ambient term. Where [`effects_refused`], none is drawn (the choices are kept for the modes
/// that draw them). Both viewers build their settings' lighting here and nowhere else.
pub fn render_lighting(light: &LightPrefs, view: LitView) -> Lighting {
    let allowed = effects_refused(view).is_none();
    let key_light = light.key_light();
    let defaults = LightPrefs::default();
    let shadows = Shadows {
        mode: match light.shadows {
            _ if !allowed => ShadowMode::Off,
            // The cache holds one direction and the headlight's is each ray's own (render
            // refuses it); the panel makes the light directional when the cache is chosen, so
            // only a hand-edited file or link gets here: exact shadows are the same picture.
            ShadowMode::Cache if key_light.direction == LightDirection::Headlight => {
                ShadowMode::Exact
            }
            mode => mode,
        },
        step: if light.shadow_step.is_finite() {
            light.shadow_step.clamp(*SHADOW_STEP_RANGE.start(), 1000.0)
        } else {
            Shadows::default().step
        },
        ..Shadows::default()
    };
    let occlusion = (allowed && light.occlusion).then(|| Occlusion {
        radius_mm: sane(
            light.occlusion_radius_mm,
            OCCLUSION_RADIUS_RANGE,
            defaults.occlusion_radius_mm,
        ),
    });
    let scattering = (allowed && light.scattering).then(|| Scattering {
        g: sane(
            light.scattering_g,
            SCATTERING_G_RANGE,
            defaults.scattering_g,
        ),
        blend: sane(
            light.scattering_blend,
            SCATTERING_BLEND_RANGE,
            defaults.scattering_blend,
        ),
    });
    let shaded = view.shading
        || shadows.mode != ShadowMode::Off
        || occlusion.is_some()
        || scattering.is_some()
        || view.mode == RenderMode::Isosurface;
    Lighting {
        shading: shaded.then(|| light.shading()),
        light: key_light,
        shadows,
        occlusion,
        scattering,
    }
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
pub const CACHE_SHADOWS_LABEL: &str = "Cached shadows";
pub const OCCLUSION_LABEL: &str = "Ambient occlusion";
pub const OCCLUSION_RADIUS_LABEL: &str = "Occlusion radius";
pub const SCATTERING_LABEL: &str = "Scattering";
pub const SCATTERING_G_LABEL: &str = "Scattering g";
pub const SCATTERING_BLEND_LABEL: &str = "Scattering blend";
pub const SHADOW_STEP_LABEL: &str = "Shadow step";
/// Side of the direction gizmo, points: small enough never to widen the panel (issue 36).
const GIZMO_SIDE: f32 = 64.0;

/// What a viewer's light controls offer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightOffer {
    /// [`effects_refused`] for the view: shadows, occlusion and scattering are shown disabled
    /// with this reason.
    pub effects_refused: Option<&'static str>,
}

/// The key light (headlight or a camera-relative direction), its intensity, the ambient term,
/// shadows, occlusion and scattering (issue 37; the same settings as `strata render
/// --light-dir --shadows --occlusion --scattering`). `shading` is the view's "Shading" switch:
/// an effect turned on turns it on, as `strata render` does. Both viewers offer all of it:
/// each refines shadows, occlusion and scattering progressively while the view is still.
pub fn light_controls(
    ui: &mut egui::Ui,
    light: &mut LightPrefs,
    shading: &mut bool,
    offer: LightOffer,
) {
    ui.horizontal(|ui| {
        ui.label("Key light");
        ui.radio_value(&mut light.headlight, true, HEADLIGHT_LABEL)
            .on_hover_text("The light at the eye, as Strata has always lit.");
        ui.radio_value(&mut light.headlight, false, DIRECTIONAL_LABEL)
            .on_hover_text(
                "A directional light placed relative to the camera: it turns with the view.",
            );
    });
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
    let (lo, hi) = (
        *INTENSITY_RANGE.start() as f32,
        *INTENSITY_RANGE.end() as f32,
    );
    ui.add(egui::Slider::new(&mut light.intensity, lo..=hi).text("intensity"))
        .on_hover_text("The key light's diffuse and specular term.")
        .accessible_name(INTENSITY_LABEL);
    let (lo, hi) = (*AMBIENT_RANGE.start() as f32, *AMBIENT_RANGE.end() as f32);
    ui.add(egui::Slider::new(&mut light.ambient, lo..=hi).text("ambient"))
        .on_hover_text("Light from everywhere: what shadows never darken.")
        .accessible_name(AMBIENT_LABEL);
    ui.add_enabled_ui(offer.effects_refused.is_none(), |ui| {
        let why = offer.effects_refused.unwrap_or_default();
        let before = *light;
        ui.horizontal_wrapped(|ui| {
            ui.label("Shadows");
            ui.radio_value(&mut light.shadows, ShadowMode::Off, NO_SHADOWS_LABEL)
                .on_disabled_hover_text(why);
            ui.radio_value(&mut light.shadows, ShadowMode::Exact, EXACT_SHADOWS_LABEL)
                .on_hover_text(
                    "A shadow ray towards the key light from every shaded sample: exact, and \
                     slower by the shadow ray's length. Turns shading on.",
                )
                .on_disabled_hover_text(why);
            ui.radio_value(&mut light.shadows, ShadowMode::Cache, CACHE_SHADOWS_LABEL)
                .on_hover_text(
                    "One lookup per shaded sample in a coarse grid of the light reaching each \
                     point, rebuilt when the light, transfer function or loaded bricks \
                     change: fast, with softer edges. Needs a directional light (chosen if \
                     the headlight is on). Turns shading on.",
                )
                .on_disabled_hover_text(why);
        });
        if light.shadows == ShadowMode::Cache && before.shadows != ShadowMode::Cache {
            // The cache holds one light direction; the headlight's is each ray's own.
            light.headlight = false;
        }
        if light.shadows != ShadowMode::Off {
            ui.add(
                egui::Slider::new(&mut light.shadow_step, SHADOW_STEP_RANGE)
                    .logarithmic(true)
                    .text("shadow step (voxels)"),
            )
            .on_hover_text(
                "The shadow ray's step in finest voxels: smaller is more exact and slower.",
            )
            .accessible_name(SHADOW_STEP_LABEL);
        }
        occlusion_and_scattering(ui, light, why);
        if light.any_effect() && !before.any_effect() {
            // As `strata render` does: each effect needs the lit path.
            *shading = true;
        }
    });
}

/// The occlusion and scattering checkboxes and, where on, their sliders.
fn occlusion_and_scattering(ui: &mut egui::Ui, light: &mut LightPrefs, why: &str) {
    ui.checkbox(&mut light.occlusion, OCCLUSION_LABEL)
        .on_hover_text(
            "Darken the ambient light where nearby matter hides a sample (creases, \
             cavities): short rays around each shaded sample. Turns shading on.",
        )
        .on_disabled_hover_text(why);
    if light.occlusion {
        ui.add(
            egui::Slider::new(&mut light.occlusion_radius_mm, OCCLUSION_RADIUS_RANGE)
                .suffix(" mm")
                .text("radius"),
        )
        .on_hover_text(
            "How far the occlusion rays look: larger darkens broader folds and is slower.",
        )
        .accessible_name(OCCLUSION_RADIUS_LABEL);
    }
    ui.checkbox(&mut light.scattering, SCATTERING_LABEL)
        .on_hover_text(
            "Light scattered once inside tissue (Henyey-Greenstein phase), blended with \
             the surface reflection where edges are strong. Turns shading on.",
        )
        .on_disabled_hover_text(why);
    if light.scattering {
        ui.add(egui::Slider::new(&mut light.scattering_g, SCATTERING_G_RANGE).text("g"))
            .on_hover_text(
                "Asymmetry: > 0 scatters forward (tissue lit from behind glows), 0 evenly, \
                 < 0 back towards the light.",
            )
            .accessible_name(SCATTERING_G_LABEL);
        ui.add(
            egui::Slider::new(&mut light.scattering_blend, SCATTERING_BLEND_RANGE).text("blend"),
        )
        .on_hover_text(
            "0: volume-like scattering everywhere; 1: surface-like reflection wherever \
                 the gradient is strong (bone), scattering in the smooth interior.",
        )
        .accessible_name(SCATTERING_BLEND_LABEL);
    }
}

/// A one-click cinematic look (issue 37): a transfer-function preset and the lighting that
/// suits it. The headlight stays the viewers' default; these are opt-in. Shared by the desktop's
/// rendering panel and the page's side panel ([`cinematic_buttons`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CinematicPreset {
    /// The button's label (the UI tests find it by this).
    pub label: &'static str,
    /// The transfer-function preset it sets (`TransferFunction::preset`).
    pub tf_preset: &'static str,
    /// Occlusion radius, mm.
    pub occlusion_radius_mm: f64,
    pub scattering_g: f64,
    pub scattering_blend: f64,
}

impl CinematicPreset {
    pub const ALL: [CinematicPreset; 2] = [
        // Bone is a surface: mostly the BRDF at its strong edges (high blend), mild forward
        // scattering, and a short occlusion radius that darkens foramina and joint gaps
        // without greying the cortex.
        CinematicPreset {
            label: "Cinematic bone",
            tf_preset: "ct-bone",
            occlusion_radius_mm: 4.0,
            scattering_g: 0.3,
            scattering_blend: 0.8,
        },
        // Soft tissue is translucent with weak gradients: mostly the phase (low blend), more
        // forward scattering so back-lit tissue glows, and a wider radius for the broad
        // folds between organs.
        CinematicPreset {
            label: "Cinematic soft tissue",
            tf_preset: "ct-soft-tissue",
            occlusion_radius_mm: 6.0,
            scattering_g: 0.5,
            scattering_blend: 0.3,
        },
    ];

    /// The preset's lighting: a key light from the upper left of the view (the painter's
    /// convention, which reads as relief rather than as craters), shadows from the light cache
    /// (one fetch per sample, affordable while moving), occlusion and scattering on; the
    /// intensity and ambient at render's defaults.
    pub fn light(&self) -> LightPrefs {
        LightPrefs {
            headlight: false,
            azimuth_deg: -45.0,
            elevation_deg: 45.0,
            shadows: ShadowMode::Cache,
            occlusion: true,
            occlusion_radius_mm: self.occlusion_radius_mm,
            scattering: true,
            scattering_g: self.scattering_g,
            scattering_blend: self.scattering_blend,
            ..LightPrefs::default()
        }
    }

    /// Sets the preset's lighting on a view: its light, shading on, and DVR where the mode
    /// could not show it (MIP is never lit). The caller sets the transfer function (and, on
    /// the desktop, turns the adaptive pass off: it draws none of these effects).
    pub fn light_view(&self, light: &mut LightPrefs, shading: &mut bool, mode: &mut RenderMode) {
        *light = self.light();
        *shading = true;
        if *mode == RenderMode::Mip {
            *mode = RenderMode::Dvr;
        }
    }
}

/// The cinematic preset buttons, each selected where `is_current` says so and disabled, with
/// the reason, where its transfer function does not fit the scan (issue 47: a CT preset on an
/// MR painted a solid red cube that never converged). Returns the preset clicked, and where
/// each button was drawn (the page publishes them for its tests).
pub fn cinematic_buttons(
    ui: &mut egui::Ui,
    scan: &crate::presets::ScanValues,
    is_current: impl Fn(&CinematicPreset) -> bool,
) -> (Option<CinematicPreset>, Vec<(CinematicPreset, egui::Rect)>) {
    let mut clicked = None;
    let mut rects = Vec::with_capacity(CinematicPreset::ALL.len());
    ui.horizontal_wrapped(|ui| {
        for preset in CinematicPreset::ALL {
            let offer = crate::presets::offer(preset.tf_preset, scan);
            let mut response = ui.add_enabled(
                offer.is_offered(),
                egui::Button::selectable(is_current(&preset), preset.label),
            );
            if let (false, Some(reason)) = (offer.is_offered(), offer.reason()) {
                response = response.on_disabled_hover_text(reason);
            }
            rects.push((preset, response.rect));
            if response
                .on_hover_text(format!(
                    "The {} transfer function lit by a key light from the upper left, with \
                     shadows from the light cache, ambient occlusion over {} mm and \
                     scattering (g {}, blend {}). Draws DVR (MIP is never lit) with the \
                     raycaster (adaptive sampling off), refined while the view is still.",
                    preset.tf_preset,
                    preset.occlusion_radius_mm,
                    preset.scattering_g,
                    preset.scattering_blend,
                ))
                .clicked()
            {
                clicked = Some(preset);
            }
        }
    });
    (clicked, rects)
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
    fn a_cinematic_preset_lights_a_mip_view_as_dvr_with_every_effect() {
        for preset in CinematicPreset::ALL {
            let (mut light, mut shading, mut mode) =
                (LightPrefs::default(), false, RenderMode::Mip);
            preset.light_view(&mut light, &mut shading, &mut mode);
            assert_eq!(
                (light, shading, mode),
                (preset.light(), true, RenderMode::Dvr)
            );
            let lit = render_lighting(
                &light,
                LitView {
                    mode,
                    shading,
                    adaptive_sampling: false,
                },
            );
            assert_eq!(lit.shadows.mode, ShadowMode::Cache, "{}", preset.label);
            assert!(lit.occlusion.is_some() && lit.scattering.is_some());
            let mut iso = RenderMode::Isosurface;
            preset.light_view(&mut light, &mut shading, &mut iso);
            assert_eq!(iso, RenderMode::Isosurface, "a lit mode stays");
        }
    }

    #[test]
    fn the_shared_lighting_follows_the_view() {
        let light = LightPrefs {
            headlight: false,
            azimuth_deg: 40.0,
            elevation_deg: 20.0,
            shadows: ShadowMode::Exact,
            ..LightPrefs::default()
        };
        let unshaded_dvr = LitView {
            mode: RenderMode::Dvr,
            shading: false,
            adaptive_sampling: false,
        };
        let lit = render_lighting(&light, unshaded_dvr);
        assert_eq!(lit.shadows.mode, ShadowMode::Exact);
        assert!(lit.shading.is_some(), "shadows turn shading on");
        assert_eq!(
            lit.light.direction,
            LightDirection::Camera(light.camera_direction())
        );
        let mip = LitView {
            mode: RenderMode::Mip,
            ..unshaded_dvr
        };
        assert!(effects_refused(mip).is_some());
        let lit = render_lighting(&light, mip);
        assert_eq!((lit.shadows.mode, lit.shading), (ShadowMode::Off, None));
        // The default light is render's default: a view with it draws what it always drew.
        let mut settings = RenderSettings::default();
        render_lighting(
            &LightPrefs::default(),
            LitView {
                shading: true,
                ..unshaded_dvr
            },
        )
        .apply_to(&mut settings);
        assert_eq!(settings.light, KeyLight::default());
        assert_eq!(settings.shadows, Shadows::default());
        assert_eq!(settings.shading, Some(Shading::default()));
    }
}
