//! The transfer-function panel: presets, the editor (strata_viewer_ui::tf_editor), save and load.

use strata_render::TransferFunction;

use crate::file_chooser::{ChooserKind, Chosen, FileChooser};
use crate::scene::{preset_for, Scene, VolumeData, PRESETS};
use strata_viewer_ui::presets::{self, ScanValues};
use strata_viewer_ui::tf_editor::{self, TfEditorState};

/// What a running file chooser of the panel is for.
#[derive(Clone, Copy, Debug, PartialEq)]
enum FileAction {
    Save,
    Load,
}

#[derive(Default)]
pub struct TfPanel {
    pub editor: TfEditorState,
    /// The file last saved or loaded (where the choosers open; empty before either).
    pub path: String,
    message: Option<String>,
    /// Save… and Load… ask where (issue 36: Save wrote to the current folder without asking).
    chooser: Option<(FileChooser, FileAction)>,
}

impl TfPanel {
    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        preset: &mut String,
        data: &VolumeData,
        scene: &mut Scene,
    ) {
        let unit = data.info.header.value_mapping.unit.clone();
        ui.horizontal_wrapped(|ui| {
            let scan = ScanValues::of(&data.info.header);
            for (name, label) in PRESETS {
                let current = *preset == name && !scene.tf_edited();
                // A preset that does not fit the scan (a CT preset on an MR) is greyed out and
                // says why; a fitted one says how (issue 47).
                let offer = presets::offer(name, &scan);
                let response =
                    ui.add_enabled(offer.is_offered(), egui::Button::selectable(current, label));
                let response = match offer.reason() {
                    Some(reason) if offer.is_offered() => response.on_hover_text(reason),
                    Some(reason) => response.on_disabled_hover_text(reason),
                    None => response,
                };
                if response.clicked() {
                    *preset = name.into();
                    scene.set_transfer_function(preset_for(name, &data.info));
                    self.editor = TfEditorState::default();
                }
            }
        });
        // Always one line, edited or not, so the plot below does not move when the first edit
        // of a drag adds "— edited" (issue 36: the point left the cursor mid-drag).
        let source = if scene.tf_edited() {
            format!("{} — edited", scene.tf_source.name)
        } else {
            scene.tf_source.name.clone()
        };
        ui.add(egui::Label::new(egui::RichText::new(source).weak()).truncate());
        tf_editor::show(
            ui,
            &mut self.editor,
            &mut scene.transfer_function,
            &data.histogram,
            data.info.physical_range,
            &unit,
        );
        ui.horizontal(|ui| {
            let idle = self.chooser.is_none();
            // Where the last file was, else the home folder (never the working folder).
            let start = if self.path.is_empty() {
                std::env::var_os("HOME").map_or_else(Default::default, std::path::PathBuf::from)
            } else {
                std::path::PathBuf::from(&self.path)
            };
            let name = std::path::Path::new(&self.path)
                .file_name()
                .map_or("transfer-function.json".to_string(), |n| {
                    n.to_string_lossy().into_owned()
                });
            if ui.add_enabled(idle, egui::Button::new("Save…")).clicked() {
                let chooser = FileChooser::start(
                    ui.ctx(),
                    ChooserKind::SaveFile,
                    "Save the transfer function",
                    &start,
                    Some(&name),
                );
                self.chooser = Some((chooser, FileAction::Save));
            }
            if ui.add_enabled(idle, egui::Button::new("Load…")).clicked() {
                let chooser = FileChooser::start(
                    ui.ctx(),
                    ChooserKind::OpenFile,
                    "Load a transfer function",
                    &start,
                    None,
                );
                self.chooser = Some((chooser, FileAction::Load));
            }
        });
        let outcome = self
            .chooser
            .as_mut()
            .and_then(|(chooser, action)| Some((chooser.poll(ui.ctx())?, *action)));
        if let Some((chosen, action)) = outcome {
            self.chooser = None;
            if let Chosen::Path(path) = chosen {
                self.path = path.display().to_string();
                self.message = Some(match action {
                    FileAction::Save => match scene.transfer_function.save(&path) {
                        Ok(()) => format!("saved {}", path.display()),
                        Err(e) => format!("could not save: {e}"),
                    },
                    FileAction::Load => match TransferFunction::load(&path) {
                        Ok(tf) => {
                            scene.set_transfer_function(tf);
                            // A file is no preset: the highlight must not stay on the one
                            // before (issue 36). The next volume opens with its default.
                            preset.clear();
                            self.editor = TfEditorState::default();
                            format!("loaded {}", path.display())
                        }
                        Err(e) => format!("could not load: {e}"),
                    },
                });
            }
        }
        if let Some(m) = &self.message {
            ui.weak(m);
        }
    }
}
