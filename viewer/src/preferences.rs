//! What the viewer remembers between runs (eframe persistence): layout, focused view, render
//! and interaction settings, the screenshot folder, measurements per store.
//!
//! Every field is `#[serde(default)]`, so older files load, and values from a damaged file are
//! clamped. `render_lighting` builds the 3D view's `RenderSettings` lighting from `LightPrefs` by
//! the function the browser uses too (viewer-ui's lighting.rs: effects turn shading on; none for
//! MIP or the adaptive pass; cache shadows never with the headlight).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use strata_render::RenderMode;

use super::orientation::SliceView;
use strata_viewer_ui::measurements::Measurement;

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

/// Progressive frames by default, the page's too (strata-viewer-ui's render driver says why).
pub use strata_viewer_ui::render_driver::DEFAULT_PROGRESSIVE_FRAMES;
/// The most the Rendering panel offers (as `strata render --progressive`'s bound is far above).
pub const MAX_PROGRESSIVE_FRAMES: u32 = 256;

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
    /// Jittered frames a still view with shadows, occlusion or scattering averages
    /// (progressive refinement, volume_session.rs); 0: off.
    pub progressive_frames: u32,
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
            adaptive_epsilon: strata_viewer_ui::adaptive::DEFAULT_EPSILON,
            progressive_frames: DEFAULT_PROGRESSIVE_FRAMES,
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

// The light model is shared with the browser's side panel (viewer-ui's lighting.rs).
use strata_viewer_ui::lighting::{LightPrefs, Lighting, LitView};

impl Preferences {
    /// What besides the light decides how the 3D view is lit.
    pub fn lit_view(&self) -> LitView {
        LitView {
            mode: self.mode,
            shading: self.shading,
            adaptive_sampling: self.adaptive_sampling,
        }
    }
}

/// Why shadows, occlusion and scattering cannot be drawn in these preferences, or None where
/// they can (the shared rule: [`strata_viewer_ui::lighting::effects_refused`]).
pub fn effects_refused(prefs: &Preferences) -> Option<&'static str> {
    strata_viewer_ui::lighting::effects_refused(prefs.lit_view())
}

/// The 3D view's lighting from the preferences, by the function the browser's links use too
/// ([`strata_viewer_ui::lighting::render_lighting`]).
pub fn render_lighting(prefs: &Preferences) -> Lighting {
    strata_viewer_ui::lighting::render_lighting(&prefs.light, prefs.lit_view())
}

/// The cinematic presets are shared with the page (strata-viewer-ui's lighting.rs).
pub use strata_viewer_ui::lighting::CinematicPreset;

impl Preferences {
    /// Sets a cinematic preset's lighting in the preferences (the caller sets the transfer
    /// function, which lives in the scene): shading on, DVR where the mode could not show it
    /// (MIP), and the adaptive pass off, which would draw the still frame without it.
    pub fn apply_cinematic(&mut self, preset: &CinematicPreset) {
        preset.light_view(&mut self.light, &mut self.shading, &mut self.mode);
        self.preset = preset.tf_preset.into();
        self.adaptive_sampling = false;
    }

    /// Whether the preferences are this preset's (its button shows selected).
    pub fn is_cinematic(&self, preset: &CinematicPreset) -> bool {
        self.preset == preset.tf_preset && self.light == preset.light()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::ShadowMode;

    /// Preferences persisted by a viewer with the first light controls (no occlusion or
    /// scattering fields) load, keep what they had, and draw no new effect.
    #[test]
    fn preferences_saved_before_occlusion_and_scattering_still_load() {
        let old = r#"{"layout":"Single","mode":"Dvr","light":{"headlight":false,
            "azimuth_deg":12.5,"elevation_deg":-10.0,"intensity":1.25,"ambient":0.2,
            "shadows":"Exact","shadow_step":1.5}}"#;
        let prefs: Preferences = serde_json::from_str(old).expect("old preferences load");
        assert_eq!(
            prefs.light,
            LightPrefs {
                headlight: false,
                azimuth_deg: 12.5,
                elevation_deg: -10.0,
                intensity: 1.25,
                ambient: 0.2,
                shadows: ShadowMode::Exact,
                shadow_step: 1.5,
                ..LightPrefs::default()
            }
        );
        assert!(!prefs.light.occlusion && !prefs.light.scattering);
        let lit = render_lighting(&prefs);
        assert_eq!(lit.shadows.mode, ShadowMode::Exact);
        assert_eq!((lit.occlusion, lit.scattering), (None, None));
    }
}
