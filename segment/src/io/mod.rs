//! Label layers to and from the files other tools read (issue 52 item 6): NIfTI-1 label maps,
//! DICOM SEG, OME-Zarr `labels/`, and Strata's own brick store ([`label_store`]). Every writer
//! streams slice by slice through [`crate::LabelRead`] and replaces its output only once the new
//! file is complete ([`atomic`]). [`primary`] reads the scan the labels were drawn on, for tools and statistics.

pub mod atomic;
pub mod dicom_seg;
pub mod label_store;
pub mod load;
pub mod nifti;
pub mod omezarr_labels;
pub mod primary;

pub use dicom_seg::{write_dicom_seg, SegOptions, SegSource, SegSummary};
pub use label_store::{load_label_store, write_label_store};
pub use load::load_label_file;
pub use nifti::write_nifti;
pub use omezarr_labels::{load_omezarr_labels, write_omezarr_labels};
pub use primary::SourceIntensity;
