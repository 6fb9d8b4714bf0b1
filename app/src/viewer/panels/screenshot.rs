//! The screenshot panel: the folder (typed, or chosen in the system dialog on its own thread)
//! and the resolution.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use crate::viewer::preferences::Preferences;
use crate::viewer::sync::lock_ignoring_poison;

/// How a closed folder dialog ended.
enum Choice {
    Folder(PathBuf),
    /// Cancelled, or no desktop portal answered.
    Nothing,
}

pub struct ScreenshotPanel {
    /// A folder dialog running on its own thread: filled when it closes.
    dialog: Option<Arc<Mutex<Option<Choice>>>>,
    note: Option<String>,
    /// Frames of the orbit movie, and whether the button asked for one this frame.
    pub orbit_frames: u32,
    orbit_requested: bool,
}

impl Default for ScreenshotPanel {
    fn default() -> Self {
        ScreenshotPanel {
            dialog: None,
            note: None,
            orbit_frames: 36,
            orbit_requested: false,
        }
    }
}

impl ScreenshotPanel {
    /// The frame count when "Orbit movie" was pressed (the shell starts the movie).
    pub fn take_orbit_request(&mut self) -> Option<u32> {
        std::mem::take(&mut self.orbit_requested).then_some(self.orbit_frames)
    }

    pub fn ui(&mut self, ui: &mut egui::Ui, prefs: &mut Preferences) {
        let closed = self
            .dialog
            .as_ref()
            .and_then(|slot| lock_ignoring_poison(slot).take());
        {
            if let Some(choice) = closed {
                match choice {
                    Choice::Folder(folder) => {
                        prefs.screenshot_folder = folder;
                        self.note = None;
                    }
                    Choice::Nothing => {
                        self.note = Some(
                            "Nothing chosen (the dialog needs a desktop portal); type the folder."
                                .into(),
                        )
                    }
                }
                self.dialog = None;
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
                self.start_dialog(ui.ctx(), prefs.screenshot_folder.clone());
            }
        });
        if let Some(note) = &self.note {
            ui.weak(note);
        }
        ui.horizontal(|ui| {
            ui.label("Resolution");
            for s in [1, 2, 4] {
                ui.selectable_value(&mut prefs.screenshot_scale, s, format!("{s}×"));
            }
        });
        ui.horizontal(|ui| {
            ui.add(egui::Slider::new(&mut self.orbit_frames, 4..=360).text("frames"));
            if ui
                .button("Orbit movie")
                .on_hover_text(
                    "The 3D view turned once around the superior axis, as PNG frames in a new \
                     folder here (and orbit.mp4 when ffmpeg is installed)",
                )
                .clicked()
            {
                self.orbit_requested = true;
            }
        });
        if prefs.screenshot_scale > 1 {
            ui.weak("2× and 4×: the 3D image alone, rendered at that size (no annotations).");
        } else {
            ui.weak("1×: the view as seen, at the screen's full resolution, with annotations.");
        }
    }

    fn start_dialog(&mut self, ctx: &egui::Context, start: PathBuf) {
        let slot = Arc::new(Mutex::new(None));
        let thread_slot = slot.clone();
        let ctx = ctx.clone();
        let spawned = std::thread::Builder::new()
            .name("strata-folder-dialog".into())
            .spawn(move || {
                let mut dialog = rfd::FileDialog::new().set_title("Folder for screenshots");
                if start.is_dir() {
                    dialog = dialog.set_directory(&start);
                }
                let choice = dialog.pick_folder().map_or(Choice::Nothing, Choice::Folder);
                *lock_ignoring_poison(&thread_slot) = Some(choice);
                ctx.request_repaint();
            });
        match spawned {
            Ok(_) => self.dialog = Some(slot),
            Err(e) => self.note = Some(format!("no folder dialog: {e}; type the folder")),
        }
    }
}
