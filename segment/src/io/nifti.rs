//! NIfTI-1 label maps: a layer written as one `.nii` or `.nii.gz` file of u16 labels (the
//! bytes are [`crate::nifti_map`]'s, which the browser page writes in memory).
//!
//! The header follows the NIfTI-1 standard (nifti1.h): `dim` = 3, nx, ny, nz; datatype
//! `NIFTI_TYPE_UINT16` (512); `intent_code` = `NIFTI_INTENT_LABEL` (1002); no scaling
//! (`scl_slope` 1, `scl_inter` 0); units mm. Strata's geometry is LPS and NIfTI's world is RAS,
//! so both the sform (exact, `sform_code` 1 = scanner) and the qform (the rotation part as a
//! quaternion with `qfac` for a left-handed grid, nifti1_io's `nifti_mat44_to_quatern`) carry
//! the first two world axes negated. Values are f32 in the header, so a reader gets the
//! placement to ~1e-7 relative.
//!
//! Voxels stream out one k-slice at a time through [`LabelRead::read_slice_k`] (memory: one
//! slice), and the file is replaced only once complete ([`super::atomic`]). Checked against
//! nibabel (voxels and affine) and Strata's own reader in `segment/tests/peers.rs`.

use std::path::Path;

use crate::io::atomic::write_file_atomically;
use crate::nifti_map::write_label_map;
use crate::{LabelRead, SegmentError};

/// Writes `labels` as a NIfTI-1 label map; gzip-compressed when `path` ends in `.gz`.
pub fn write_nifti(labels: &dyn LabelRead, path: &Path) -> Result<(), SegmentError> {
    let gz = path
        .file_name()
        .is_some_and(|n| n.to_string_lossy().to_ascii_lowercase().ends_with(".gz"));
    // The header first: a grid NIfTI-1 cannot hold is refused before any file is touched.
    crate::nifti_map::nifti_header(labels, path)?;
    write_file_atomically(path, |out| write_label_map(labels, out, gz, path))
}
