//! Headerless raw volumes: the caller supplies the layout in a [`RawSpec`].

use std::path::Path;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::volume_bytes;
use crate::readers::RawSpec;
use crate::source::{OpenedSource, RawVolume, SourceInfo};

pub(crate) fn open_raw(path: &Path, spec: &RawSpec) -> Result<OpenedSource> {
    let geometry = VolumeGeometry::axis_aligned(
        crate::geometry::checked_dims(spec.dims, path)?,
        spec.spacing_mm,
    );
    crate::geometry::validate(&geometry, path)?;
    let needed = volume_bytes(path, spec.dims, spec.sample_type.size_bytes())?;
    let expected = needed
        .checked_add(spec.header_bytes)
        .ok_or_else(|| StorageError::invalid(path, "header size overflows"))?;
    let actual = std::fs::metadata(path)
        .map_err(|e| StorageError::io(path, e))?
        .len();
    // Exact match: with no header to cross-check, a size mismatch is the only sign that the
    // dimensions or type the user typed are wrong, and a wrong guess renders as noise.
    if actual != expected {
        return Err(StorageError::invalid(
            path,
            format!(
                "size mismatch: {:?} {} voxels plus {} header bytes need {expected} bytes, the file has {actual}",
                spec.dims,
                spec.sample_type.name(),
                spec.header_bytes
            ),
        ));
    }
    let data = RawVolume::map_file(
        path,
        spec.header_bytes,
        spec.sample_type,
        spec.byte_order,
        spec.dims,
    )?;
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: "raw".into(),
            geometry,
            sample_type: spec.sample_type,
            slope: 1.0,
            intercept: 0.0,
            modality: String::new(),
            windows: Vec::new(),
            description: String::new(),
            inputs: vec![path.to_path_buf()],
            labels: Vec::new(),
            frames: 1,
        },
        data,
    })
}
