//! The Segment section: start a segmentation (new on the primary's grid, or the open label
//! overlay made editable), the tools as one compact row (brush, eraser, slice fill, 3D grow;
//! size in mm, an optional value range), the segment list (active segment, colour, name,
//! shown, locked, remove), the operations on the active segment (fill between slices, islands,
//! margin, union / subtract / intersect), statistics with Copy as CSV, and Save As.
//!
//! The tool row, the segment list and the operations are strata-viewer-ui's segment_panel,
//! which the browser page draws too; the value range, grow settings, statistics and Save As
//! are the desktop's own (they need the primary's values, threads or files).
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
use crate::segmentation::{Operation, SaveFormat, SegmentTool, Segmentation};

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

/// The tool row, its size and value range, and the grow's settings and progress.
fn tools(ui: &mut egui::Ui, seg: &mut Segmentation) {
    segment_panel::tool_row(ui, &mut seg.tool, &mut seg.diameter_mm, true);
    ui.horizontal_wrapped(|ui| {
        let growing_by_sigma = seg.tool == SegmentTool::Grow && seg.grow.mean_sigma;
        if seg.tool == SegmentTool::Grow {
            ui.label("Values");
        } else {
            ui.checkbox(&mut seg.limit_to_range, "Only values")
                .on_hover_text(
                    "Paint, erase or fill only where the volume's value lies in the range",
                );
        }
        let enabled = (seg.limit_to_range || seg.tool == SegmentTool::Grow) && !growing_by_sigma;
        ui.add_enabled(enabled, egui::DragValue::new(&mut seg.range.0).speed(1.0));
        ui.label("to");
        ui.add_enabled(enabled, egui::DragValue::new(&mut seg.range.1).speed(1.0));
    });
    if seg.tool == SegmentTool::Grow {
        ui.horizontal_wrapped(|ui| {
            ui.checkbox(&mut seg.grow.mean_sigma, "mean ± k·σ")
                .on_hover_text("The range from the 3×3×3 voxels around the seed");
            ui.add_enabled(
                seg.grow.mean_sigma,
                egui::DragValue::new(&mut seg.grow.k)
                    .range(0.0..=10.0)
                    .speed(0.05),
            );
            ui.label("cap");
            ui.add(
                egui::DragValue::new(&mut seg.grow.max_voxels)
                    .range(1..=u64::MAX)
                    .speed(10_000.0)
                    .suffix(" vx"),
            )
            .on_hover_text("The grow stops here, keeping what it took");
        });
    }
    if let Some((done, cap)) = seg.grow_progress() {
        ui.horizontal(|ui| {
            ui.add(
                egui::ProgressBar::new((done as f32 / cap.max(1) as f32).min(1.0))
                    .text(format!("{done} voxels"))
                    .desired_width(160.0),
            );
            if ui.button("Cancel").clicked() {
                seg.cancel_grow();
            }
        });
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

/// The statistics table (computed on request, in the background) and Copy as CSV.
fn statistics(ui: &mut egui::Ui, seg: &mut Segmentation) {
    ui.horizontal_wrapped(|ui| {
        let running = seg.statistics_running();
        if ui
            .add_enabled(!running, egui::Button::new("Statistics"))
            .on_hover_text("Voxels, volume and the volume's values in each segment")
            .clicked()
        {
            let ctx = ui.ctx().clone();
            seg.start_statistics(Arc::new(move || ctx.request_repaint()));
        }
        if running {
            ui.spinner();
        }
        if let Some(Ok(stats)) = &seg.stats {
            if ui.button("Copy as CSV").clicked() {
                ui.ctx().copy_text(strata_segment::stats::to_csv(stats));
            }
        }
    });
    match &seg.stats {
        Some(Ok(stats)) => {
            let unit = if stats.unit.is_empty() {
                String::new()
            } else {
                format!(" ({})", stats.unit)
            };
            let value = |v: Option<f64>| v.map_or_else(|| "–".to_string(), |v| format!("{v:.1}"));
            egui::Grid::new("segment statistics")
                .striped(true)
                .show(ui, |ui| {
                    ui.label("Segment");
                    ui.label("Voxels");
                    ui.label("mL");
                    ui.label(format!("Mean{unit}"));
                    ui.label("SD");
                    ui.end_row();
                    for s in &stats.segments {
                        ui.label(&s.name);
                        ui.label(s.voxels.to_string());
                        ui.label(format!("{:.2}", s.volume_ml));
                        ui.label(value(s.mean));
                        ui.label(value(s.sd));
                        ui.end_row();
                    }
                });
        }
        Some(Err(e)) => {
            ui.colored_label(Color32::LIGHT_RED, e);
        }
        None => {}
    }
}

/// Where Save As starts: the folder of the label file the layer came from, else `fallback`.
pub fn save_folder(seg: Option<&Segmentation>, fallback: &std::path::Path) -> PathBuf {
    seg.and_then(|s| s.base_file.as_ref())
        .and_then(|f| f.parent())
        .map_or_else(|| fallback.to_path_buf(), |p| p.to_path_buf())
}
