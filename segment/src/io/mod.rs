//! Label layers to and from the files other tools read (issue 52 item 6): NIfTI-1 label maps,
//! DICOM SEG, OME-Zarr `labels/`, and Strata's own brick store ([`label_store`]). Every writer
//! streams slice by slice through [`crate::LabelRead`] and replaces its output only once the new
//! file is complete ([`atomic`]). [`primary`] reads the scan the labels were drawn on, for tools and statistics.
//!
//! Without `local` (the browser page, wasm32) the DICOM SEG and OME-Zarr writers build the
//! same files in memory ([`dicom_seg_bytes`], [`omezarr_labels_zip`]); everything that reads
//! or writes a disk is `local`.

#[cfg(feature = "local")]
pub mod atomic;
pub mod dicom_seg;
#[cfg(feature = "local")]
pub mod label_store;
#[cfg(feature = "local")]
pub mod load;
#[cfg(feature = "local")]
pub mod nifti;
pub mod omezarr_labels;
#[cfg(feature = "local")]
pub mod primary;
pub mod stored_zip;

#[cfg(feature = "local")]
pub use dicom_seg::write_dicom_seg;
pub use dicom_seg::{dicom_seg_bytes, SegOptions, SegSource, SegStamp, SegSummary};
#[cfg(feature = "local")]
pub use label_store::{load_label_store, write_label_store};
#[cfg(feature = "local")]
pub use load::load_label_file;
#[cfg(feature = "local")]
pub use nifti::write_nifti;
pub use omezarr_labels::omezarr_labels_zip;
#[cfg(feature = "local")]
pub use omezarr_labels::{load_omezarr_labels, write_omezarr_labels};
#[cfg(feature = "local")]
pub use primary::SourceIntensity;
