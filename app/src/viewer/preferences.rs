//! What the viewer remembers between runs (eframe persistence): layout, focused view, render
//! and interaction settings, the screenshot folder, measurements per store.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use strata_render::RenderMode;

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
