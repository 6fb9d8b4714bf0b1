//! What the viewer remembers between runs (eframe persistence): layout, focused view, render
//! and interaction settings, the screenshot folder, measurements per store.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use strata_render::{KeyLight, LightDirection, RenderMode, Shading, ShadowMode, Shadows};

use super::measurements::Measurement;
use super::orientation::SliceView;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Layout {
    /// One view filling the area (the focused one).
    Single,
    /// 3D on top, the three slices in a row below (Slicer's "conventional").
    ThreeDOverSlices,
    /// Axial, 3D / sagittal, coronal (Slicer's "four-up").
    TwoByTwo,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ViewSlot {
    ThreeD,
    Slice(SliceView),
    /// The oblique reformat (oblique_view.rs).
    Oblique,
}

/// ~/Pictures/Strata where there is a Pictures folder, else "screenshots" beside the stores
/// (never the working folder, which is wherever the viewer happened to start).
pub fn default_screenshot_folder() -> PathBuf {
    let pictures = std::env::var_os("HOME").map(|h| PathBuf::from(h).join("Pictures"));
    match pictures.filter(|p| p.is_dir()) {
        Some(p) => p.join("Strata"),
        None => {
            let stores = super::jobs::data_folder();
            stores.parent().unwrap_or(&stores).join("screenshots")
        }
    }
}

/// Remembered between runs (eframe persistence).
/// How the 3D view's raycaster finds the bricks (render's `Traversal`); a change restarts
/// the volume's loader.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum TraversalChoice {
    /// The flat page table unless it exceeds the device's storage-binding limit.
    #[default]
    Automatic,
    Flat,
    Octree,
}

impl TraversalChoice {
    pub const ALL: [(TraversalChoice, &'static str); 3] = [
        (TraversalChoice::Automatic, "Automatic"),
        (TraversalChoice::Flat, "Flat page table"),
        (TraversalChoice::Octree, "Octree"),
    ];

    pub fn traversal(self) -> Option<strata_render::Traversal> {
        match self {
            TraversalChoice::Automatic => None,
            TraversalChoice::Flat => Some(strata_render::Traversal::Flat),
            TraversalChoice::Octree => Some(strata_render::Traversal::Octree),
        }
    }

    pub fn label(self) -> &'static str {
        Self::ALL
            .iter()
            .find(|(c, _)| *c == self)
            .map_or("Automatic", |(_, l)| l)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Preferences {
    pub layout: Layout,
    pub focused: ViewSlot,
    pub last_opened: Option<PathBuf>,
    pub preset: String,
    pub mode: RenderMode,
    pub shading: bool,
    /// The key light, ambient term and shadows of shaded DVR and isosurfaces (issue 37).
    pub light: LightPrefs,
    /// Continuous field where bricks of different resolution meet (off: visible seams).
    pub smooth_transitions: bool,
    /// The raycaster's traversal (flat table or the cut's octree).
    pub traversal: TraversalChoice,
    /// The still view's final frame by the adaptive pass (adaptive_view.rs; DVR and MIP).
    pub adaptive_sampling: bool,
    /// The adaptive oracle's ε: the opacity change per slice a 2³ block may have.
    pub adaptive_epsilon: f64,
    pub orthographic: bool,
    pub target_fps_enabled: bool,
    pub target_fps: f64,
    /// Step in finest voxels when the target frame rate is off.
    pub step_voxels: f64,
    /// Fraction of the view's pixels the volume is rendered at.
    pub render_scale: f32,
    pub show_identifiers: bool,
    pub show_side_panel: bool,
    /// Show the oblique view in the layouts (in the sagittal's place in 2×2, as a fourth
    /// slice in 3D + 1×3).
    pub show_oblique: bool,
    /// Outline the three slice planes in the 3D view.
    pub show_planes_in_3d: bool,
    /// Draw the crop box in the 3D view, with a handle on each face to drag it.
    pub show_crop_box: bool,
    pub screenshot_folder: PathBuf,
    pub screenshot_scale: u32,
    /// Measurements per store (its path), restored when it is opened again.
    pub measurements: std::collections::BTreeMap<String, Vec<Measurement>>,
}

impl Default for Preferences {
    fn default() -> Self {
        Preferences {
            layout: Layout::ThreeDOverSlices,
            focused: ViewSlot::ThreeD,
            last_opened: None,
            preset: "ct-bone".into(),
            mode: RenderMode::Dvr,
            shading: true,
            light: LightPrefs::default(),
            smooth_transitions: true,
            traversal: TraversalChoice::Automatic,
            adaptive_sampling: false,
            adaptive_epsilon: super::adaptive_view::DEFAULT_EPSILON,
            orthographic: false,
            target_fps_enabled: true,
            target_fps: 10.0,
            step_voxels: 0.5,
            render_scale: 0.6,
            show_identifiers: false,
            show_side_panel: true,
            show_oblique: false,
            show_planes_in_3d: true,
            show_crop_box: false,
            screenshot_folder: default_screenshot_folder(),
            screenshot_scale: 1,
            measurements: Default::default(),
        }
    }
}

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
        }
    }
}

/// Degrees the direction angles span (the sliders and the gizmo square).
pub const AZIMUTH_RANGE: std::ops::RangeInclusive<f64> = -180.0..=180.0;
pub const ELEVATION_RANGE: std::ops::RangeInclusive<f64> = -90.0..=90.0;
/// Shadow-step range in finest voxels: the CLI's lower bound (render refuses smaller steps);
/// above a few voxels shadows only blur.
pub const SHADOW_STEP_RANGE: std::ops::RangeInclusive<f64> = 0.05..=8.0;

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

/// Why shadows cannot be drawn in these preferences, or None where they can: the CLI refuses
/// them for MIP and for the adaptive pass (neither traces shadow rays).
pub fn shadows_refused(prefs: &Preferences) -> Option<&'static str> {
    if prefs.mode == RenderMode::Mip {
        Some("Shadows light DVR and isosurfaces: MIP is never lit.")
    } else if prefs.adaptive_sampling && prefs.mode != RenderMode::Isosurface {
        Some(
            "The adaptive pass does not trace shadow rays: turn adaptive sampling off to              draw shadows.",
        )
    } else {
        None
    }
}

/// The lighting part of the 3D view's render settings: shading, key light and shadows.
/// Shadows turn shading on (as `strata render --shadows` does); isosurfaces are always shaded,
/// with the panel's ambient term.
pub fn render_lighting(prefs: &Preferences) -> (Option<Shading>, KeyLight, Shadows) {
    let light = &prefs.light;
    let shadows = Shadows {
        mode: match shadows_refused(prefs) {
            Some(_) => ShadowMode::Off,
            None => light.shadows,
        },
        step: if light.shadow_step.is_finite() {
            light.shadow_step.clamp(*SHADOW_STEP_RANGE.start(), 1000.0)
        } else {
            Shadows::default().step
        },
        ..Shadows::default()
    };
    let shaded =
        prefs.shading || shadows.mode != ShadowMode::Off || prefs.mode == RenderMode::Isosurface;
    (shaded.then(|| light.shading()), light.key_light(), shadows)
}
