//! The screenshot panel: the folder (typed, or chosen in the system dialog, or the egui one
//! where no desktop portal answers: file_chooser.rs) and the resolution.

use std::path::PathBuf;

use crate::file_chooser::{ChooserKind, Chosen, FileChooser};
use crate::preferences::Preferences;
use strata_viewer_ui::orbit_movie::{DEFAULT_ORBIT_FRAMES, OFFERED_ORBIT_FRAMES};

pub struct ScreenshotPanel {
    /// The folder chooser while it is open.
    dialog: Option<FileChooser>,
    /// Frames of the orbit movie; the save dialog for its folder while it is open; the folder
    /// chosen, until the shell starts the movie.
    pub orbit_frames: u32,
    movie_dialog: Option<FileChooser>,
    orbit_requested: Option<PathBuf>,
}

impl Default for ScreenshotPanel {
    fn default() -> Self {
        ScreenshotPanel {
            dialog: None,
            orbit_frames: DEFAULT_ORBIT_FRAMES,
            movie_dialog: None,
            orbit_requested: None,
        }
    }
}

impl ScreenshotPanel {
    /// The frame count when "Orbit movie" was pressed (the shell starts the movie).
    pub fn take_orbit_request(&mut self) -> Option<(u32, PathBuf)> {
        self.orbit_requested
            .take()
            .map(|folder| (self.orbit_frames, folder))
    }

    pub fn ui(&mut self, ui: &mut egui::Ui, prefs: &mut Preferences) {
        let closed = self.dialog.as_mut().and_then(|d| d.poll(ui.ctx()));
        if let Some(choice) = closed {
            self.dialog = None;
            if let Chosen::Path(folder) = choice {
                prefs.screenshot_folder = folder;
            }
        }
        ui.horizontal(|ui| {
            ui.label("Folder");
            let mut folder = prefs.screenshot_folder.display().to_string();
            if ui
                .add(egui::TextEdit::singleline(&mut folder).desired_width(170.0))
                .accessible_name("Screenshot folder")
                .changed()
            {
                prefs.screenshot_folder = PathBuf::from(folder);
            }
            if ui
                .add_enabled(self.dialog.is_none(), egui::Button::new("Choose…"))
                .clicked()
            {
                self.dialog = Some(FileChooser::start(
                    ui.ctx(),
                    ChooserKind::OpenFolder,
                    "Folder for screenshots and movies",
                    &prefs.screenshot_folder,
                    None,
                ));
            }
        });
        ui.horizontal(|ui| {
            ui.label("Resolution");
            for s in [1, 2, 4] {
                ui.selectable_value(&mut prefs.screenshot_scale, s, format!("{s}×"));
            }
        });
        ui.horizontal(|ui| {
            ui.add(egui::Slider::new(&mut self.orbit_frames, OFFERED_ORBIT_FRAMES).text("frames"));
            if ui
                .add_enabled(
                    self.movie_dialog.is_none(),
                    egui::Button::new("Orbit movie…"),
                )
                .on_hover_text(
                    "The 3D view turned once around the superior axis, as PNG frames in the \
                     folder you name (and orbit.mp4 in it when ffmpeg is installed)",
                )
                .clicked()
            {
                let stamp = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_secs());
                self.movie_dialog = Some(FileChooser::start(
                    ui.ctx(),
                    ChooserKind::SaveFile,
                    "Save the orbit movie (a folder of frames)",
                    &prefs.screenshot_folder,
                    Some(&format!("strata-orbit-{stamp}")),
                ));
            }
        });
        if let Some(chosen) = self.movie_dialog.as_mut().and_then(|d| d.poll(ui.ctx())) {
            self.movie_dialog = None;
            if let Chosen::Path(folder) = chosen {
                self.orbit_requested = Some(folder);
            }
        }
        if prefs.screenshot_scale > 1 {
            ui.weak("2× and 4×: the 3D image alone, rendered at that size (no annotations).");
        } else {
            ui.weak("1×: the view as seen, at the screen's full resolution, with annotations.");
        }
    }
}
