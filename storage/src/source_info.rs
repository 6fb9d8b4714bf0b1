//! What a source says of its voxels (sample type, byte order, windows, labels) and what a reader
//! learned from a file's header ([`SourceInfo`]). Pure: the store header holds some of these, so
//! a remote viewer needs them; the voxels themselves (`crate::source`) are local-only.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::geometry::VolumeGeometry;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SampleType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl SampleType {
    pub fn size_bytes(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::F64 => 8,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            SampleType::U8 => "uint8",
            SampleType::I8 => "int8",
            SampleType::U16 => "uint16",
            SampleType::I16 => "int16",
            SampleType::U32 => "uint32",
            SampleType::I32 => "int32",
            SampleType::F32 => "float32",
            SampleType::F64 => "float64",
        }
    }
    pub fn is_float(self) -> bool {
        matches!(self, SampleType::F32 | SampleType::F64)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ByteOrder {
    Little,
    Big,
}

/// A display window found in the source (DICOM WindowCenter/Width, NRRD/NIfTI cal_min/max, ...).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WindowPreset {
    pub name: String,
    /// Centre and width in physical units.
    pub center: f64,
    pub width: f64,
}

/// One label of a label map (a DICOM SEG segment): its stored value, name and display colour.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LabelInfo {
    pub value: u32,
    pub name: String,
    /// sRGB; `None` where the source recommends no colour (the viewer's table then decides).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rgb: Option<[u8; 3]>,
    /// What the segment is (a SEG's category and type codes), where the source says.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub category: Option<strata_types::SegmentCategory>,
}

/// Everything a reader learned from the header.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SourceInfo {
    /// The file (or folder, for a DICOM series) the user named.
    pub path: PathBuf,
    /// Short format name: "nifti-1", "nrrd", "metaimage", "dicom", "raw", "phantom".
    pub format: String,
    pub geometry: VolumeGeometry,
    pub sample_type: SampleType,
    /// physical = slope · sample + intercept (DICOM RescaleSlope/Intercept, NIfTI scl_*).
    pub slope: f64,
    pub intercept: f64,
    /// "CT", "MR", ... or empty when the source does not say.
    pub modality: String,
    pub windows: Vec<WindowPreset>,
    pub description: String,
    /// Every file that contributed voxels (a DICOM series lists all its slices' folder once).
    pub inputs: Vec<PathBuf>,
    /// The labels of a label map (DICOM SEG segments); empty for every other source.
    #[serde(default)]
    pub labels: Vec<LabelInfo>,
    /// Volumes on this grid (a 4-D NIfTI's time points); the data then holds them one after
    /// the other, `dims[2] · frames` slices in all.
    #[serde(default = "one_frame")]
    pub frames: u32,
}

/// Begins a note in [`SourceInfo::description`] that says a header value was not usable and
/// what was assumed instead; the import prints these (the description keeps them).
pub const WARNING_PREFIX: &str = "warning: ";

impl SourceInfo {
    /// The description's warnings (notes are joined with "; "): header values a scanner
    /// cannot mean, replaced by an assumption the user should know of.
    pub fn warnings(&self) -> Vec<&str> {
        self.description
            .split("; ")
            .filter_map(|n| n.strip_prefix(WARNING_PREFIX))
            .collect()
    }
}

fn one_frame() -> u32 {
    1
}
