//! The overlay panel: open a second volume (a store, or a scan imported first) as a label map
//! or as a continuous overlay over the primary's slices and in 3D, then its opacity, visibility
//! (on the slices, in 3D), the labels (colour swatch, show/hide each) or the colour map, range
//! and threshold.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use egui::{Color32, RichText};

use crate::jobs::{PrepareJob, VolumeToOpen};
use crate::overlay::{Overlay, OverlayKind};
use crate::scene::VolumeData;

/// The panel's own state: what the user typed and the overlay being prepared.
pub struct OverlayPanel {
    pub path: String,
    pub kind: OverlayKind,
    /// The job, the kind asked for and the file the user gave (the overlay is listed by it,
    /// not by the imported store's internal name).
    job: Option<(PrepareJob, OverlayKind, PathBuf)>,
    pub error: Option<String>,
}

impl Default for OverlayPanel {
    fn default() -> Self {
        OverlayPanel {
            path: String::new(),
            kind: OverlayKind::Labels,
            job: None,
            error: None,
        }
    }
}

impl OverlayPanel {
    /// Starts preparing `path` as an overlay of `kind` (the panel's button, tests).
    pub fn open(&mut self, ctx: &egui::Context, path: PathBuf, kind: OverlayKind, folder: &Path) {
        self.error = None;
        let ctx = ctx.clone();
        match PrepareJob::start(
            VolumeToOpen::Path(path.clone()),
            None,
            folder.to_path_buf(),
            Arc::new(move || ctx.request_repaint()),
        ) {
            Ok(job) => self.job = Some((job, kind, path)),
            Err(e) => self.error = Some(format!("could not start: {e:#}")),
        }
    }

    /// Moves a preparing overlay on; once its store is open it replaces `overlay`.
    pub fn poll(&mut self, ctx: &egui::Context, data: &VolumeData, overlay: &mut Option<Overlay>) {
        let Some((job, kind, source)) = &self.job else {
            return;
        };
        let Some(result) = job.take_result() else {
            return;
        };
        let kind = *kind;
        let source = source.display().to_string();
        self.job = None;
        let repaint_ctx = ctx.clone();
        let started = match result {
            Ok(store) => Overlay::start(
                store,
                kind,
                data.info.geometry.clone(),
                data.info.header.layout.level_dims.clone(),
                Arc::new(move || repaint_ctx.request_repaint()),
            )
            .map_err(|e| format!("{e:#}")),
            Err(e) => Err(crate::error_report::describe(&e)),
        };
        match started {
            Ok(mut o) => {
                // "labels.nii.gz", not "labels.nii.gz-9998ee….strata" (issue 36).
                o.name = source;
                *overlay = Some(o);
            }
            Err(e) => {
                eprintln!("strata: overlay: {e}");
                self.error = Some(e);
            }
        }
    }

    pub fn ui(&mut self, ui: &mut egui::Ui, overlay: &mut Option<Overlay>, import_folder: &Path) {
        ui.horizontal(|ui| {
            ui.label("File");
            ui.add(
                egui::TextEdit::singleline(&mut self.path)
                    .hint_text("label map or overlay (.nii, .nrrd, DICOM SEG, store)")
                    .desired_width(200.0),
            );
        });
        ui.horizontal(|ui| {
            ui.radio_value(&mut self.kind, OverlayKind::Labels, "Label map");
            ui.radio_value(&mut self.kind, OverlayKind::Continuous, "Continuous");
            let busy = self.job.is_some();
            if ui
                .add_enabled(
                    !busy && !self.path.trim().is_empty(),
                    egui::Button::new("Open overlay"),
                )
                .on_hover_text(
                    "Open a second volume over the slices, resampled into this scan's patient \
                     space",
                )
                .clicked()
            {
                let path = PathBuf::from(self.path.trim());
                self.open(ui.ctx(), path, self.kind, import_folder);
            }
            if busy {
                ui.spinner();
            }
        });
        if let Some(e) = &self.error {
            ui.colored_label(Color32::LIGHT_RED, e);
        }
        let mut remove = false;
        if let Some(o) = overlay.as_mut() {
            ui.separator();
            ui.horizontal(|ui| {
                ui.checkbox(&mut o.style.visible, "Show");
                ui.checkbox(&mut o.style.show_in_3d, "Show in 3D")
                    .on_hover_text(
                        "Draw the overlay in the 3D view too (resampled once in the background; \
                     style changes only recolour it)",
                    );
                ui.label(RichText::new(short_name(&o.name)).strong())
                    .on_hover_text(&o.name);
                remove = ui.small_button("Remove").clicked();
            });
            if let Some(e) = o.error() {
                ui.colored_label(Color32::LIGHT_RED, e);
            }
            // The controls the page's Overlay section draws too (strata-viewer-ui's overlay).
            let (kind, range, seen) = (o.kind, o.physical_range, o.labels_seen());
            strata_viewer_ui::overlay::style_controls(ui, kind, &mut o.style, range, &seen);
        }
        if remove {
            *overlay = None;
        }
    }
}

fn short_name(location: &str) -> String {
    Path::new(location)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| location.to_string())
}
