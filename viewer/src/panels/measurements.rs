//! The measurements panel: strata-viewer-ui's (the tool row, the list, each deletable, delete
//! all), on the desktop's scene.

use crate::scene::{Scene, VolumeData};

pub fn ui(ui: &mut egui::Ui, data: &VolumeData, scene: &mut Scene) {
    let unit = data.unit();
    strata_viewer_ui::measurements::panel(ui, &mut scene.measurements, &data.info.geometry, &unit);
}
