//! The Frames panel of a 4-D volume: strata-viewer-ui's shared panel (the page shows the same)
//! over the player's playback.

use crate::frames::FramePlayer;

pub fn ui(ui: &mut egui::Ui, player: &mut FramePlayer) {
    strata_viewer_ui::frames::ui(ui, &mut player.playback);
}
