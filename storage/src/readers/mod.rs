//! Format readers. Each turns an input path into an [`OpenedSource`]:
//! DICOM (folder series, single and enhanced multi-frame files; uncompressed, RLE, JPEG baseline,
//! extended 12-bit and lossless, JPEG 2000, JPEG-LS; SEG segmentations as label maps), NIfTI-1/2, NRRD, MetaImage, FreeSurfer
//! MGH/MGZ, raw.
//!
//! Readers never decode a whole volume into memory. Uncompressed inputs are mapped in place;
//! compressed ones (gzip, zlib, DICOM pixel data) are streamed into a temporary raw file first,
//! which is then mapped. Every geometry ends in LPS millimetres (see [`crate::geometry`]).

mod common;
mod dicom;
mod dicom_bounds;
mod dicom_seg;
mod jpeg12;
mod metaimage;
mod mgh;
mod nifti;
mod nrrd;
mod raw;

use std::io::Read;
use std::path::{Path, PathBuf};

use crate::error::{Result, StorageError};
use crate::source::{ByteOrder, OpenedSource, SampleType};

pub use crate::staging::{remove_live_staging_files, remove_stale_staging_files, StagingFile};
pub use dicom::{list_dicom_series, DicomSeriesSummary};
pub use dicom_seg::dicom_lab_to_srgb;

/// What the user told us beyond the path.
#[derive(Default, Clone, Debug)]
pub struct ReadOptions {
    /// Which series of a multi-series DICOM folder to open: its SeriesInstanceUID, or its 0-based
    /// index in the listing the "several series" error prints.
    pub dicom_series: Option<String>,
    /// How to read a headerless raw file; required for files with no recognised extension.
    pub raw: Option<RawSpec>,
    /// Where decompressed voxels are staged; the system temp dir when `None`.
    pub staging_dir: Option<PathBuf>,
}

/// Layout of a headerless raw volume.
#[derive(Clone, Debug, PartialEq)]
pub struct RawSpec {
    pub dims: [u64; 3],
    pub sample_type: SampleType,
    pub spacing_mm: [f64; 3],
    pub byte_order: ByteOrder,
    /// Bytes to skip before the first voxel.
    pub header_bytes: u64,
}

pub(crate) const SUPPORTED: &str =
    "DICOM (.dcm file or a folder of slices), NIfTI (.nii, .nii.gz, .hdr/.img), \
NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd), FreeSurfer MGH (.mgh, .mgz), or raw with explicit dimensions and type";

/// Opens any supported volume; the format follows from the path (folder, extension, DICM magic).
pub fn open_source(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let meta = std::fs::metadata(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            StorageError::invalid(path, "does not exist")
        } else {
            StorageError::io(path, e)
        }
    })?;
    if meta.is_dir() {
        return dicom::open_series_dir(path, options);
    }
    if !meta.is_file() {
        // Reading a FIFO blocks until a writer comes, possibly forever; devices never end.
        return Err(StorageError::invalid(
            path,
            "not a regular file (a FIFO, socket or device): give the scan's file or folder",
        ));
    }
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if name.ends_with(".nii")
        || name.ends_with(".nii.gz")
        || name.ends_with(".hdr")
        || name.ends_with(".hdr.gz")
    {
        return nifti::open_nifti(path, options);
    }
    if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        return nrrd::open_nrrd(path, options);
    }
    if name.ends_with(".mha") || name.ends_with(".mhd") {
        return metaimage::open_metaimage(path, options);
    }
    if name.ends_with(".mgh") || name.ends_with(".mgz") || name.ends_with(".mgh.gz") {
        return mgh::open_mgh(path, options);
    }
    if name.ends_with(".dcm") || name.ends_with(".dicom") || has_dicom_preamble(path) {
        return dicom::open_dicom_file(path, options);
    }
    if let Some(spec) = &options.raw {
        return raw::open_raw(path, spec);
    }
    Err(StorageError::unsupported(
        path,
        format!("unrecognised file type (no raw layout given); supported formats: {SUPPORTED}"),
    ))
}

/// True when the file carries the Part 10 "DICM" magic: at byte 128 after the preamble, or at
/// byte 0 where a writer dropped the preamble (dicom-object reads both). A read failure means "no".
pub(crate) fn has_dicom_preamble(path: &Path) -> bool {
    let mut buf = [0u8; 132];
    let Ok(mut f) = crate::regular_file::open(path) else {
        return false;
    };
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(_) => return false,
        }
    }
    (n >= 132 && &buf[128..132] == b"DICM") || (n >= 4 && &buf[0..4] == b"DICM")
}
