//! The Frames panel of a 4-D volume: the frame slider, cine play/pause and its frame rate.

use egui::Color32;

use crate::frames::{FramePlayer, FPS_RANGE};

pub fn ui(ui: &mut egui::Ui, player: &mut FramePlayer) {
    let mut frame = player.requested.unwrap_or(player.current);
    let last = player.count - 1;
    ui.horizontal(|ui| {
        if ui
            .button(if player.playing { "Pause" } else { "Play" })
            .on_hover_text("Cine: step through the frames at the frame rate, looping")
            .clicked()
        {
            player.playing = !player.playing;
        }
        if ui
            .add(egui::Slider::new(&mut frame, 0..=last).text("Frame"))
            .on_hover_text("Every view and the readout show this frame")
            .changed()
        {
            player.requested = Some(frame);
        }
    });
    ui.add(
        egui::Slider::new(&mut player.fps, FPS_RANGE)
            .text("frames/s")
            .logarithmic(true),
    );
    ui.label(format!(
        "frame {} of {} (frames numbered from 0)",
        player.current, player.count
    ));
    if let Some(line) = player.rate_line() {
        ui.colored_label(crate::widgets::WARNING_COLOUR, line);
    }
    if let Some(e) = &player.error {
        ui.colored_label(Color32::LIGHT_RED, e);
    }
}
