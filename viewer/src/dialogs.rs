//! The dialogs: open or import (typed path, native file dialog on its own thread, DICOM series,
//! demo phantom, progress and errors of the running preparation) and keyboard-and-mouse help.

use std::path::PathBuf;

use egui::{Color32, RichText};
use strata_viewer_ui::shortcuts;

use super::file_chooser::{ChooserKind, Chosen, FileChooser};
use super::jobs::{PrepareJob, VolumeToOpen};
use super::widgets::{NOT_FOR_DIAGNOSIS, WARNING_COLOUR};

/// The open-or-import dialog.
pub struct OpenDialog {
    pub open: bool,
    pub path: String,
    series: String,
    /// The file chooser while it is open (the system dialog, or the egui one where no desktop
    /// portal answers: file_chooser.rs).
    file_dialog: Option<FileChooser>,
    ctx: egui::Context,
}

impl OpenDialog {
    pub fn new(ctx: egui::Context, path: String) -> Self {
        OpenDialog {
            open: false,
            path,
            series: String::new(),
            file_dialog: None,
            ctx,
        }
    }

    /// Draws the dialog while it is open; returns what to open when the user asked for it.
    pub fn ui(
        &mut self,
        ctx: &egui::Context,
        job: Option<&PrepareJob>,
        job_error: &mut Option<String>,
    ) -> Option<(VolumeToOpen, Option<String>)> {
        if !self.open {
            return None;
        }
        let mut open = true;
        let mut start: Option<VolumeToOpen> = None;
        egui::Window::new("Open or import").open(&mut open).resizable(false).default_width(460.0).show(ctx, |ui| {
            ui.label("A Strata store, or a scan to import: DICOM folder or file, NIfTI (.nii, .nii.gz), NRRD, MetaImage (.mha/.mhd).");
            ui.label("Scans are imported once into your data folder; the next open is instant.");
            ui.horizontal(|ui| {
                ui.label("Path");
                ui.add(egui::TextEdit::singleline(&mut self.path).desired_width(340.0).hint_text("/path/to/scan.nii.gz"));
            });
            ui.horizontal(|ui| {
                let idle = self.file_dialog.is_none();
                if ui.add_enabled(idle, egui::Button::new("Choose file…")).clicked() {
                    self.start_file_dialog(false);
                }
                if ui.add_enabled(idle, egui::Button::new("Choose folder…")).on_hover_text("A DICOM series folder, or a store").clicked() {
                    self.start_file_dialog(true);
                }
                if !idle {
                    ui.spinner();
                }
            });
            self.poll_file_dialog();
            ui.horizontal(|ui| {
                ui.label("DICOM series (optional)");
                ui.add(egui::TextEdit::singleline(&mut self.series).desired_width(200.0).hint_text("index or UID"));
            });
            ui.horizontal(|ui| {
                let busy = job.is_some();
                if ui.add_enabled(!busy && !self.path.trim().is_empty(), egui::Button::new("Open / import")).clicked() {
                    start = Some(VolumeToOpen::Path(PathBuf::from(self.path.trim())));
                }
                if ui.add_enabled(!busy, egui::Button::new("Demo phantom")).clicked() {
                    start = Some(super::demo_source());
                }
            });
            if let Some(job) = job {
                ui.separator();
                job_progress(ui, job);
            }
            if let Some(e) = job_error.clone() {
                ui.separator();
                egui::Frame::NONE.fill(Color32::from_rgb(70, 20, 20)).inner_margin(8.0).corner_radius(4.0).show(ui, |ui| {
                    ui.colored_label(Color32::from_rgb(255, 190, 190), RichText::new("Could not open").strong());
                    ui.label(RichText::new(&e).color(Color32::from_rgb(255, 220, 220)));
                    if ui.button("Dismiss").clicked() {
                        *job_error = None;
                    }
                });
            }
        });
        if !open {
            self.open = false;
        }
        start.map(|source| {
            let series = Some(self.series.trim().to_string()).filter(|s| !s.is_empty());
            (source, series)
        })
    }

    fn start_file_dialog(&mut self, folder: bool) {
        let (kind, title) = if folder {
            (ChooserKind::OpenFolder, "Open a DICOM folder or store")
        } else {
            (ChooserKind::OpenFile, "Open a scan")
        };
        let start = PathBuf::from(self.path.trim());
        self.file_dialog = Some(FileChooser::start(&self.ctx, kind, title, &start, None));
    }

    fn poll_file_dialog(&mut self) {
        let Some(chosen) = self.file_dialog.as_mut().and_then(|d| d.poll(&self.ctx)) else {
            return;
        };
        self.file_dialog = None;
        if let Chosen::Path(path) = chosen {
            self.path = path.display().to_string();
        }
    }
}

/// A running preparation's title, stage, progress bar and Cancel (the Open and the Open from
/// PACS dialogs).
pub fn job_progress(ui: &mut egui::Ui, job: &PrepareJob) {
    let (done, total, stage) = job.progress();
    ui.label(&job.title);
    ui.label(stage);
    let fraction = if total > 0 {
        done as f32 / total as f32
    } else {
        0.0
    };
    ui.add(egui::ProgressBar::new(fraction).show_percentage());
    if ui.button("Cancel").clicked() {
        job.cancel();
    }
}

/// The keyboard-and-mouse help window.
#[derive(Default)]
pub struct HelpWindow {
    pub open: bool,
}

impl HelpWindow {
    /// The help both viewers draw from one table (strata_viewer_ui::shortcuts), all of it.
    pub fn ui(&mut self, ctx: &egui::Context) {
        let footer = RichText::new(format!("{NOT_FOR_DIAGNOSIS}: research and education only."))
            .color(WARNING_COLOUR);
        shortcuts::help_window(ctx, &mut self.open, shortcuts::Viewer::Desktop, footer);
    }
}
