//! Coded concepts (DICOM code sequence items): what a segment is, as DICOM SEG records it.
//! Here once so that a store's header (a SEG's labels) and the segmentation editor carry the
//! same category through every format that has one.

use serde::{Deserialize, Serialize};

/// A coded concept, e.g. SCT 85756007 "Tissue".
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Code {
    pub value: String,
    pub scheme: String,
    pub meaning: String,
}

/// What a segment is: its category and type (DICOM SEG's SegmentedPropertyCategoryCode and
/// SegmentedPropertyTypeCode).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SegmentCategory {
    pub category: Code,
    pub kind: Code,
}
