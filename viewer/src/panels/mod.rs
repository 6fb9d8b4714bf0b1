//! The side panels, each a type owning its state with a `ui()`: transfer function, slices,
//! frames (4-D cine), measurements, overlay, segment (segmentation), rendering,
//! performance, screenshot, volume information. [`Panels::ui`] stacks them in the side bar.

pub mod frames;
pub mod info;
pub mod measurements;
pub mod overlay;
pub mod performance;
pub mod rendering;
pub mod screenshot;
pub mod segment;
pub mod slices;
pub mod transfer_function;

use super::overlay::Overlay;
use super::preferences::Preferences;
use super::scene::{Scene, VolumeData};
use super::view3d::View3d;

pub use strata_viewer_ui::performance::FrameClock;

/// Everything in the side bar that outlives one frame.
#[derive(Default)]
pub struct Panels {
    pub transfer_function: transfer_function::TfPanel,
    pub performance: performance::PerformancePanel,
    pub screenshot: screenshot::ScreenshotPanel,
    pub overlay: overlay::OverlayPanel,
    pub segment: segment::SegmentPanel,
    /// What the Segment section asked for this frame (the app carries it out).
    pub segment_request: Option<segment::SegmentRequest>,
}

/// What the side panels work on.
pub struct PanelContext<'a> {
    pub prefs: &'a mut Preferences,
    pub data: &'a VolumeData,
    pub scene: &'a mut Scene,
    pub view_3d: &'a mut View3d,
    pub clock: &'a FrameClock,
    pub overlay: &'a mut Option<Overlay>,
    /// The frame player of a 4-D volume.
    pub frames: &'a mut Option<super::frames::FramePlayer>,
    /// Where an overlay scan is imported to.
    pub import_folder: &'a std::path::Path,
    /// The editable label layer, if one is open.
    pub segmentation: &'a mut Option<super::segmentation::Segmentation>,
    pub segment_error: Option<&'a str>,
}

impl Panels {
    pub fn ui(&mut self, ui: &mut egui::Ui, cx: PanelContext<'_>) {
        let PanelContext {
            prefs,
            data,
            scene,
            view_3d,
            clock,
            overlay,
            frames,
            import_folder,
            segmentation,
            segment_error,
        } = cx;
        if let Some(player) = frames.as_mut() {
            egui::CollapsingHeader::new("Frames")
                .default_open(true)
                .show(ui, |ui| frames::ui(ui, player));
        }
        egui::CollapsingHeader::new("Transfer function")
            .default_open(true)
            .show(ui, |ui| {
                self.transfer_function
                    .ui(ui, &mut prefs.preset, data, scene);
            });
        egui::CollapsingHeader::new("Slices")
            .default_open(true)
            .show(ui, |ui| {
                slices::ui(ui, data, scene);
            });
        egui::CollapsingHeader::new("Overlay")
            .default_open(overlay.is_some())
            .show(ui, |ui| {
                self.overlay.ui(ui, overlay, import_folder);
            });
        egui::CollapsingHeader::new("Segment")
            .default_open(segmentation.is_some())
            .show(ui, |ui| {
                let folder = segment::save_folder(
                    segmentation.as_ref(),
                    import_folder.parent().unwrap_or(import_folder),
                );
                if let Some(r) =
                    self.segment
                        .ui(ui, segmentation, overlay.as_ref(), segment_error, &folder)
                {
                    self.segment_request = Some(r);
                }
            });
        egui::CollapsingHeader::new("Measurements")
            .default_open(true)
            .show(ui, |ui| {
                measurements::ui(ui, data, scene);
            });
        egui::CollapsingHeader::new("Rendering")
            .default_open(true)
            .show(ui, |ui| {
                if rendering::ui(ui, prefs, data, scene, view_3d) {
                    // A cinematic preset replaced the TF: the editor's selection named a
                    // point of the old one (as the TF panel's own presets do).
                    self.transfer_function.editor = Default::default();
                }
            });
        egui::CollapsingHeader::new("Performance")
            .default_open(true)
            .show(ui, |ui| {
                self.performance.ui(ui, prefs, data, clock);
            });
        egui::CollapsingHeader::new("Screenshots and movies")
            .default_open(false)
            .show(ui, |ui| {
                self.screenshot.ui(ui, prefs);
            });
        egui::CollapsingHeader::new("Volume information")
            .default_open(false)
            .show(ui, |ui| {
                info::ui(ui, prefs, data);
            });
    }
}
