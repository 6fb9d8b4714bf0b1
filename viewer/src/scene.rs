//! The opened volume and what every view shares: the data handles (render session, slice
//! reader, header facts, histogram) and the scene the user adjusts (crosshair, slice window,
//! transfer function, iso value, crop and clip). Views and panels own their own state; they
//! read [`VolumeData`] and change [`Scene`].

use strata_render::{CropBox, TransferFunction};
use strata_storage::histogram::Histogram;
use strata_viewer_ui::crop_clip::ClipSettings;

use super::colour_maps::ColourMap;
use super::orientation::{SliceFrame, SliceView};
use super::slices::SliceReader;
use super::volume_session::{VolumeInfo, VolumeSession};
use strata_viewer_ui::measurements::Measurements;

/// A slice window in physical units (strata-slices', shared with the browser viewer).
pub use strata_slices::Window;

/// What the views read and never change: the render session, the slice reader and facts of
/// the store.
pub struct VolumeData {
    pub session: VolumeSession,
    pub slices: SliceReader,
    /// Resamples the oblique view's plane (oblique.rs).
    pub oblique: super::oblique::ObliqueReader,
    pub info: VolumeInfo,
    pub histogram: Histogram,
    /// How each slice view maps index axes to the screen (fixed by the geometry).
    pub frames: [SliceFrame; 3],
    /// The store's path (measurements are remembered per store).
    pub store_path: std::path::PathBuf,
}

/// What the user adjusts and every view shows.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// Linked crosshair, level-0 continuous index.
    pub cursor: [f64; 3],
    pub window: Window,
    /// How slices colour values through the window.
    pub colour_map: ColourMap,
    pub transfer_function: TransferFunction,
    /// The preset or file the transfer function came from: an edit is a difference from it.
    pub tf_source: TransferFunction,
    pub iso_value: f64,
    pub crop: CropBox,
    pub clip: ClipSettings,
    pub measurements: Measurements,
}

impl Scene {
    /// Sets a new transfer function from a preset or a file.
    pub fn set_transfer_function(&mut self, tf: TransferFunction) {
        self.tf_source = tf.clone();
        self.transfer_function = tf;
    }

    /// The transfer function differs from its preset or file.
    pub fn tf_edited(&self) -> bool {
        self.transfer_function.opacity != self.tf_source.opacity
            || self.transfer_function.color != self.tf_source.color
    }

    /// Names an edited transfer function "<source> (edited)" (and a restored one by its source
    /// again), so titles and the preset buttons never claim an edited function is the preset.
    pub fn name_tf_edits(&mut self) {
        let name = if self.tf_edited() {
            format!("{} (edited)", self.tf_source.name)
        } else {
            self.tf_source.name.clone()
        };
        if self.transfer_function.name != name {
            self.transfer_function.name = name;
        }
    }
}

/// The value readout: a voxel, where it is in the patient, and its physical value once the
/// slice reader has read it.
#[derive(Clone, Debug, PartialEq)]
pub struct Readout {
    /// Under the pointer (true) or at the crosshair.
    pub under_pointer: bool,
    pub index: [u32; 3],
    /// LPS millimetres of the voxel centre.
    pub patient_mm: [f64; 3],
    pub value: Option<f64>,
    pub unit: String,
    /// Every value of the volume is an integer (integer stored data under an integer slope
    /// and intercept, e.g. 8-bit data): printed without decimals.
    pub integer_values: bool,
}

impl Readout {
    /// "Pointer 40 HU · voxel (23, 23, 23) · R0.0 A8.3 S0.0 mm": value, index, and the patient
    /// position in the signed R/L, A/P, S/I a radiologist reads (LPS positive = L, P, S).
    pub fn text(&self) -> String {
        let side = |value: f64, pos: &str, neg: &str| {
            format!("{}{:.1}", if value >= 0.0 { pos } else { neg }, value.abs())
        };
        let [x, y, z] = self.patient_mm;
        let value = match self.value {
            // Issue 47: 8-bit data read "76.0000". The page's slice readout prints the same.
            Some(v) => readout_value(v, &self.unit, self.integer_values),
            None => "…".into(),
        };
        format!(
            "{} {} · voxel ({}, {}, {}) · {} {} {} mm",
            if self.under_pointer {
                "Pointer"
            } else {
                "Crosshair"
            },
            value.trim_end(),
            self.index[0],
            self.index[1],
            self.index[2],
            side(x, "L", "R"),
            side(y, "P", "A"),
            side(z, "S", "I"),
        )
    }
}

impl VolumeData {
    pub fn frame(&self, view: SliceView) -> SliceFrame {
        self.frames[view.index()]
    }

    /// The unit values are shown in: the header's, or HU for a CT that does not say.
    pub fn unit(&self) -> String {
        let h = &self.info.header;
        let unit = h.value_mapping.unit.trim();
        if unit.is_empty() && looks_like_ct(&h.modality, unit, self.info.physical_range) {
            "HU".into()
        } else {
            unit.to_string()
        }
    }

    /// The readout of the voxel at level-0 continuous index `at`; asks the slice reader for
    /// its value if it does not have it yet (the value arrives a frame or two later).
    pub fn readout(&self, at: [f64; 3], under_pointer: bool) -> Readout {
        let dims = self.info.geometry.dims;
        let k = voxel_index(at);
        let index = [0, 1, 2].map(|a| k[a].clamp(0, dims[a] as i64 - 1) as u32);
        self.slices.probe(index);
        let value = self
            .slices
            .probed()
            .filter(|p| p.index == index)
            .map(|p| self.info.mapping.physical(p.stored as f64));
        let p = self
            .info
            .geometry
            .patient_from_index(glam::DVec3::from(index.map(|i| i as f64)));
        Readout {
            under_pointer,
            index,
            patient_mm: p.into(),
            value,
            unit: self.unit(),
            integer_values: ScanValues::of(&self.info.header).integer_values,
        }
    }

    /// Moves the crosshair `step` displayed slices along `view`'s normal.
    pub fn page_slice(&self, scene: &mut Scene, view: SliceView, step: f64) {
        let frame = self.frame(view);
        let n = frame.normal_axis;
        let max = self.info.geometry.dims[n] as f64 - 1.0;
        // One displayed slice: a voxel of the level shown.
        let level = self.slices.latest(view).map_or(0, |i| i.request.level);
        let voxel = (1u64 << level) as f64;
        scene.cursor[n] = (scene.cursor[n].round() + step * voxel).clamp(0.0, max);
    }
}

/// The voxel a level-0 continuous index lies in (what the slice reader shows at level 0, the
/// slice header counts from and the status bar prints: one rounding for all three).
pub fn voxel_index(cursor: [f64; 3]) -> [i64; 3] {
    cursor.map(|c| c.round() as i64)
}

/// The crosshair a volume opens with: the centre voxel (a voxel centre, never between two
/// slices, so every readout names the same voxel).
pub fn start_cursor(dims: [u32; 3]) -> [f64; 3] {
    dims.map(|d| ((d as f64 - 1.0) * 0.5).floor().max(0.0))
}

pub use strata_viewer_ui::presets::looks_like_ct;
use strata_viewer_ui::presets::{readout_value, ScanValues};

/// The named presets in the transfer-function panel: (preset name, button label).
pub const PRESETS: [(&str, &str); 5] = [
    ("ct-bone", "Bone"),
    ("ct-soft-tissue", "Soft tissue"),
    ("ct-lung", "Lung"),
    ("ct-vessels", "Vessels"),
    ("mr-default", "MR"),
];

/// The preset `name` fitted to this volume ([`strata_viewer_ui::presets::fitted_preset`]).
pub fn preset_for(name: &str, info: &VolumeInfo) -> TransferFunction {
    strata_viewer_ui::presets::fitted_preset(name, info.physical_range)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 47: the readout printed "76.0000" for 8-bit data.
    #[test]
    fn the_readout_prints_integers_for_integer_data_and_the_unit_when_known() {
        let readout = |value: f64, unit: &str, integer_values: bool| {
            Readout {
                under_pointer: true,
                index: [1, 2, 3],
                patient_mm: [0.0; 3],
                value: Some(value),
                unit: unit.into(),
                integer_values,
            }
            .text()
        };
        assert!(readout(76.0, "", true).starts_with("Pointer 76 · voxel"));
        assert!(readout(-1000.0, "HU", true).starts_with("Pointer -1000 HU ·"));
        assert!(readout(0.25, "mm²/s", false).starts_with("Pointer 0.25 mm²/s ·"));
        assert!(readout(1.0 / 3.0, "", false).starts_with("Pointer 0.3333 ·"));
    }

    #[test]
    fn the_start_cursor_is_a_voxel_centre_every_readout_agrees_on() {
        for dims in [[6, 6, 6], [188, 256, 190], [1, 2, 3], [48, 48, 48]] {
            let c = start_cursor(dims);
            assert!(c.iter().all(|x| x.fract() == 0.0), "{dims:?} → {c:?}");
            let k = voxel_index(c);
            for axis in 0..3 {
                assert!(k[axis] >= 0 && k[axis] < dims[axis] as i64);
                // The slice reader's level-0 slice for this position.
                let read = ((c[axis] + 0.5) - 0.5).round() as i64;
                assert_eq!(read, k[axis], "{dims:?} axis {axis}");
            }
        }
        // enh.dcm's 6 slices: the header said 4/6 while the status bar said k=2.
        assert_eq!(voxel_index(start_cursor([6, 6, 6]))[2] + 1, 3);
    }

    #[test]
    fn a_ct_without_a_modality_tag_is_recognised_by_its_values() {
        assert!(looks_like_ct("CT", "", (0.0, 100.0)));
        assert!(looks_like_ct("", "HU", (0.0, 100.0)));
        // Strata's own int16 HU phantom written as NRRD: no tag, no unit.
        assert!(looks_like_ct("", "", (-1000.0, 1900.0)));
        assert!(looks_like_ct("", "", (-1024.0, 3071.0)));
        // MR: non-negative intensities, tagged or not.
        assert!(!looks_like_ct("", "", (0.0, 1200.0)));
        assert!(!looks_like_ct("MR", "", (-1000.0, 2000.0)));
        // A signed statistic map is not a CT.
        assert!(!looks_like_ct("", "", (-8.0, 8.0)));
    }
}
