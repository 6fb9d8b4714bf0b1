//! The Segment section: start a segmentation (new on the primary's grid, or the open label
//! overlay made editable), the tools as one compact row (brush, eraser, slice fill, 3D grow;
//! size in mm, an optional value range), the segment list (active segment, colour, name,
//! shown, locked, remove), the operations on the active segment (fill between slices, islands,
//! margin, union / subtract / intersect), statistics with Copy as CSV, and Save As.
//!
//! The tool row, the value range and grow settings, the grow's progress and Cancel, the
//! segment list, the operations and the statistics table are strata-viewer-ui's
//! segment_panel, which the browser page draws too; the desktop runs the grow and the
//! statistics on threads of their own, and Save As is its own (files).
//!
//! Every row wraps inside the panel's width rather than widening the panel: a row wider than
//! the panel made the right-hand panel grow by 44 points on the frame after the segmentation
//! opened, moving every widget left under a pointer that had not moved (a click aimed at
//! "Brush" landed on "Eraser") and shrinking the views, as issue 36 saw for labels
//! (`ui_tests::segment_oblique::one_click_on_a_tool_button_chooses_that_tool`).

use std::path::PathBuf;
use std::sync::Arc;

use egui::{Color32, RichText};
use strata_viewer_ui::segment_panel::{
    self, OperationSettings, SegmentListChange, SegmentOperation,
};

use crate::file_chooser::{ChooserKind, Chosen, FileChooser};
use crate::overlay::{Overlay, OverlayKind};
use crate::segmentation::{Operation, SaveFormat, Segmentation};

/// What the section asks the app to do (it needs the volume's store and the journal's place).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SegmentRequest {
    /// An empty segmentation on the primary's grid.
    New,
    /// The label overlay's file as an editable layer.
    EditOverlay,
    /// Stop editing (the journal stays until the next segmentation replaces it).
    Close,
}

/// The section's own settings and the Save As chooser while it is open.
pub struct SegmentPanel {
    pub format: SaveFormat,
    /// Islands' N, the margin and the other segment (the shared operations rows').
    pub operations: OperationSettings,
    chooser: Option<(FileChooser, SaveFormat)>,
}

impl Default for SegmentPanel {
    fn default() -> Self {
        SegmentPanel {
            format: SaveFormat::Nifti,
            operations: OperationSettings::default(),
            chooser: None,
        }
    }
}

impl SegmentPanel {
    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        segmentation: &mut Option<Segmentation>,
        overlay: Option<&Overlay>,
        error: Option<&str>,
        save_folder: &std::path::Path,
    ) -> Option<SegmentRequest> {
        let mut request = None;
        let Some(seg) = segmentation.as_mut() else {
            ui.horizontal_wrapped(|ui| {
                if ui
                    .button("New segmentation")
                    .on_hover_text("An empty label layer on this volume's grid")
                    .clicked()
                {
                    request = Some(SegmentRequest::New);
                }
                let editable = overlay.is_some_and(|o| o.kind == OverlayKind::Labels);
                if ui
                    .add_enabled(editable, egui::Button::new("Edit overlay"))
                    .on_hover_text("Edit the open label overlay, on its own grid")
                    .on_disabled_hover_text("Open a label map or DICOM SEG as the overlay first")
                    .clicked()
                {
                    request = Some(SegmentRequest::EditOverlay);
                }
            });
            if let Some(e) = error {
                ui.colored_label(Color32::LIGHT_RED, e);
            }
            return request;
        };
        tools(ui, seg);
        segment_list(ui, seg);
        self.operations(ui, seg);
        statistics(ui, seg);
        self.save(ui, seg, save_folder);
        ui.horizontal_wrapped(|ui| {
            if ui
                .button("Close")
                .on_hover_text("Stop editing this segmentation")
                .clicked()
            {
                request = Some(SegmentRequest::Close);
            }
            if let Some(path) = seg.journal_file() {
                ui.label(RichText::new("Every edit is journaled").small())
                    .on_hover_text(path.display().to_string());
            }
        });
        if let Some(n) = &seg.notice {
            ui.label(n);
        }
        if let Some(e) = seg.error.as_deref().or(error) {
            ui.colored_label(Color32::LIGHT_RED, e);
        }
        request
    }

    /// The shared operations rows; the chosen one runs on the layer as one edit (Between
    /// slices along the last stroke's plane).
    fn operations(&mut self, ui: &mut egui::Ui, seg: &mut Segmentation) {
        let segments = seg.segments();
        let response =
            segment_panel::operations(ui, &mut self.operations, &segments, seg.active, !seg.busy());
        if let Some(chosen) = response.chosen {
            seg.operate(match chosen {
                SegmentOperation::FillBetween => Operation::FillBetween(seg.last_plane),
                SegmentOperation::Islands(which) => Operation::Islands(which),
                SegmentOperation::Margin(mm) => Operation::Margin(mm),
                SegmentOperation::Combine(op, other) => Operation::Combine(op, other),
            });
        }
    }

    fn save(&mut self, ui: &mut egui::Ui, seg: &mut Segmentation, folder: &std::path::Path) {
        ui.horizontal_wrapped(|ui| {
            egui::ComboBox::from_id_salt("segment save format")
                .selected_text(self.format.label())
                .show_ui(ui, |ui| {
                    for f in SaveFormat::ALL {
                        ui.selectable_value(&mut self.format, f, f.label());
                    }
                });
            let busy = self.chooser.is_some() || seg.saving();
            if ui
                .add_enabled(!busy, egui::Button::new("Save as…"))
                .on_hover_text(
                    "Write the segmentation where other tools read it; an earlier file is \
                     replaced only once the new one is complete",
                )
                .clicked()
            {
                let chooser = FileChooser::start(
                    ui.ctx(),
                    ChooserKind::SaveFile,
                    "Save segmentation as",
                    folder,
                    Some(self.format.default_name()),
                );
                self.chooser = Some((chooser, self.format));
            }
            if seg.saving() {
                ui.spinner();
            }
        });
        if let Some((chooser, format)) = self.chooser.as_mut() {
            match chooser.poll(ui.ctx()) {
                Some(Chosen::Path(path)) => {
                    let (ctx, format) = (ui.ctx().clone(), *format);
                    seg.start_save(path, format, Arc::new(move || ctx.request_repaint()));
                    self.chooser = None;
                }
                Some(Chosen::Nothing) => self.chooser = None,
                None => {}
            }
        }
        match &seg.saved {
            Some(Ok(path)) => {
                ui.label(RichText::new(format!("Saved {}", short(path))).small())
                    .on_hover_text(path.display().to_string());
            }
            Some(Err(e)) => {
                ui.colored_label(Color32::LIGHT_RED, e);
            }
            None => {}
        }
    }
}

fn short(path: &std::path::Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// The tool row, its size and value range, and the grow's settings and progress (the shared
/// panel's rows, as the page draws them).
fn tools(ui: &mut egui::Ui, seg: &mut Segmentation) {
    segment_panel::tool_row(ui, &mut seg.tool, &mut seg.diameter_mm, true);
    segment_panel::value_rows(ui, seg.tool, &mut seg.values);
    if let Some((done, cap)) = seg.grow_progress() {
        let fraction = (done as f64 / cap.max(1) as f64) as f32;
        let (cancel, _) = segment_panel::progress_row(ui, fraction, &format!("{done} voxels"));
        if cancel {
            seg.cancel_grow();
        }
    }
}

/// The segments: active one, colour, name, shown, locked, remove; and Add segment.
fn segment_list(ui: &mut egui::Ui, seg: &mut Segmentation) {
    let mut table = seg.segments();
    let before = table.clone();
    let mut active = seg.active;
    let change = segment_panel::segment_list(ui, &mut table, &mut active);
    seg.active = active;
    if table != before {
        seg.with_segments(|t| *t = table);
    }
    match change {
        Some(SegmentListChange::Remove(value)) => seg.remove_segment(value),
        Some(SegmentListChange::Add) => seg.add_segment(),
        None => {}
    }
}

/// The statistics table (computed on request, in the background) and Copy as CSV: the shared
/// panel's rows.
fn statistics(ui: &mut egui::Ui, seg: &mut Segmentation) {
    let asked = segment_panel::statistics_rows(ui, seg.statistics_running(), seg.stats.as_ref());
    if asked.compute {
        let ctx = ui.ctx().clone();
        seg.start_statistics(Arc::new(move || ctx.request_repaint()));
    }
    if asked.copy_csv {
        if let Some(Ok(stats)) = &seg.stats {
            ui.ctx().copy_text(strata_segment::stats::to_csv(stats));
        }
    }
}

/// Where Save As starts: the folder of the label file the layer came from, else `fallback`.
pub fn save_folder(seg: Option<&Segmentation>, fallback: &std::path::Path) -> PathBuf {
    seg.and_then(|s| s.base_file.as_ref())
        .and_then(|f| f.parent())
        .map_or_else(|| fallback.to_path_buf(), |p| p.to_path_buf())
}
