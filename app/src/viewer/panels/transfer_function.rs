//! The transfer-function panel: presets, the editor (tf_editor.rs), save and load.

use strata_render::TransferFunction;

use crate::viewer::scene::{preset_for, Scene, VolumeData, PRESETS};
use crate::viewer::tf_editor::{self, TfEditorState};

pub struct TfPanel {
    pub editor: TfEditorState,
    /// The file Save and Load use.
    pub path: String,
    message: Option<String>,
}

impl Default for TfPanel {
    fn default() -> Self {
        TfPanel {
            editor: TfEditorState::default(),
            path: "transfer-function.json".into(),
            message: None,
        }
    }
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
            for (name, label) in PRESETS {
                let current = *preset == name && !scene.tf_edited();
                if ui.selectable_label(current, label).clicked() {
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
            ui.add(egui::TextEdit::singleline(&mut self.path).desired_width(150.0))
                .accessible_name("Transfer function file");
            if ui.button("Save").clicked() {
                self.message = Some(
                    match scene
                        .transfer_function
                        .save(std::path::Path::new(&self.path))
                    {
                        Ok(()) => format!("saved {}", self.path),
                        Err(e) => format!("could not save: {e}"),
                    },
                );
            }
            if ui.button("Load").clicked() {
                self.message = Some(
                    match TransferFunction::load(std::path::Path::new(&self.path)) {
                        Ok(tf) => {
                            scene.set_transfer_function(tf);
                            // A file is no preset: the highlight must not stay on the one
                            // before (issue 36). The next volume opens with its default.
                            preset.clear();
                            self.editor = TfEditorState::default();
                            format!("loaded {}", self.path)
                        }
                        Err(e) => format!("could not load: {e}"),
                    },
                );
            }
        });
        if let Some(m) = &self.message {
            ui.weak(m);
        }
    }
}
