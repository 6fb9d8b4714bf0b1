//! Crop box and clip plane: the settings a user adjusts, the plane they give in patient space,
//! and the controls that edit them. The desktop's rendering panel and the browser's side panel
//! both draw [`controls`], and a link carries both (view_state.rs), so a cut made in one
//! viewer opens the same in the other.

use serde::{Deserialize, Serialize};
use strata_render::{ClipPlane, CropBox};
use strata_types::VolumeGeometry;

/// The clip plane as the user sets it: an LPS axis, which side is cut, and where.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipSettings {
    pub enabled: bool,
    /// LPS axis of the plane's normal: 0 L–R, 1 A–P, 2 S–I.
    pub axis: usize,
    pub flip: bool,
    /// Position as a fraction of the volume's extent along the normal.
    pub fraction: f64,
}

impl Default for ClipSettings {
    fn default() -> Self {
        ClipSettings {
            enabled: false,
            axis: 1,
            flip: false,
            fraction: 0.5,
        }
    }
}

/// The axes' names in a link (`clip=ap,0.5`), in LPS order.
pub const CLIP_AXIS_NAMES: [&str; 3] = ["lr", "ap", "si"];

/// The smallest crop box edge, as a fraction of its axis: the controls keep `min < max` by
/// this much, and a link is held to the same.
pub const MIN_CROP_EXTENT: f32 = 0.01;

impl ClipSettings {
    /// The clip plane in patient space: normal along the LPS axis (negated when flipped), at
    /// `fraction` of the volume's extent along it (the extent of its voxels' outer faces).
    pub fn plane(&self, geometry: &VolumeGeometry) -> ClipPlane {
        let mut normal = [0.0; 3];
        normal[self.axis.min(2)] = if self.flip { -1.0 } else { 1.0 };
        let n = glam::DVec3::from(normal);
        let corner = |c: usize, axis: usize| {
            if c & (1 << axis) == 0 {
                -0.5
            } else {
                geometry.dims[axis] as f64 - 0.5
            }
        };
        let (lo, hi) = (0..8)
            .map(|c| {
                let index = glam::DVec3::new(corner(c, 0), corner(c, 1), corner(c, 2));
                geometry.patient_from_index(index).dot(n)
            })
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                (a.min(x), b.max(x))
            });
        ClipPlane {
            normal,
            offset_mm: lo + (hi - lo) * self.fraction,
        }
    }

    /// The plane to render with, if the clip is on.
    pub fn plane_if_enabled(&self, geometry: &VolumeGeometry) -> Option<ClipPlane> {
        self.enabled.then(|| self.plane(geometry))
    }
}

/// The crop box's and clip plane's controls; true when either changed.
pub fn controls(ui: &mut egui::Ui, crop: &mut CropBox, clip: &mut ClipSettings) -> bool {
    let (crop_before, clip_before) = (*crop, *clip);
    ui.label("Crop box (fraction of each index axis)");
    for (axis, name) in ["i", "j", "k"].iter().enumerate() {
        ui.horizontal(|ui| {
            ui.label(*name);
            let mut min = crop.min[axis];
            let mut max = crop.max[axis];
            ui.add(egui::DragValue::new(&mut min).speed(0.005).range(0.0..=1.0))
                .accessible_name(format!("Crop {name} from"));
            ui.add(egui::DragValue::new(&mut max).speed(0.005).range(0.0..=1.0))
                .accessible_name(format!("Crop {name} to"));
            crop.min[axis] = min.min(max - MIN_CROP_EXTENT).max(0.0);
            crop.max[axis] = max.max(min + MIN_CROP_EXTENT).min(1.0);
        });
    }
    ui.horizontal(|ui| {
        ui.checkbox(&mut clip.enabled, "Clip plane");
        egui::ComboBox::from_id_salt("clip axis")
            .selected_text(["L–R", "A–P", "S–I"][clip.axis.min(2)])
            .show_ui(ui, |ui| {
                ui.selectable_value(&mut clip.axis, 0, "L–R (sagittal)");
                ui.selectable_value(&mut clip.axis, 1, "A–P (coronal)");
                ui.selectable_value(&mut clip.axis, 2, "S–I (axial)");
            })
            .response
            .accessible_name("Clip plane axis");
        ui.checkbox(&mut clip.flip, "flip");
    });
    if clip.enabled {
        ui.add(egui::Slider::new(&mut clip.fraction, 0.0..=1.0).text("position"));
    }
    if ui.button("Reset crop and clip").clicked() {
        *crop = CropBox::default();
        clip.enabled = false;
    }
    *crop != crop_before || *clip != clip_before
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plane_sits_at_its_fraction_of_the_extent_along_its_axis() {
        // 10 × 20 × 30 voxels of 0.5 × 1 × 2 mm: the A–P extent is 20 mm from -0.5 mm.
        let geometry = VolumeGeometry::axis_aligned([10, 20, 30], [0.5, 1.0, 2.0]);
        let clip = ClipSettings {
            enabled: true,
            axis: 1,
            flip: false,
            fraction: 0.25,
        };
        let plane = clip.plane(&geometry);
        assert_eq!(plane.normal, [0.0, 1.0, 0.0]);
        let lo = geometry.patient_from_index(glam::DVec3::splat(-0.5)).y;
        assert!(
            (plane.offset_mm - (lo + 0.25 * 20.0)).abs() < 1e-9,
            "{plane:?}"
        );
        // Flipped: the normal turns, and the offset is measured along it.
        let flipped = ClipSettings { flip: true, ..clip }.plane(&geometry);
        assert_eq!(flipped.normal, [0.0, -1.0, 0.0]);
        let hi = geometry.patient_from_index(glam::DVec3::splat(19.5)).y;
        assert!(
            (flipped.offset_mm - (-hi + 0.25 * 20.0)).abs() < 1e-9,
            "{flipped:?}"
        );
        assert_eq!(ClipSettings::default().plane_if_enabled(&geometry), None);
    }
}
