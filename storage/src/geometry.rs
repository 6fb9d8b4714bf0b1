//! Geometry checks with the file named: the rules are strata-types' [`VolumeGeometry::validate`];
//! here a failure becomes a [`StorageError`] that says which input it came from.

use std::path::Path;

pub use strata_types::{VolumeGeometry, MAX_AXIS_VOXELS, MAX_TOTAL_VOXELS};

use crate::error::{Result, StorageError};

/// Rejects what no real scan has; `path` names the file in the error.
pub fn validate(geometry: &VolumeGeometry, path: &Path) -> Result<()> {
    geometry
        .validate()
        .map_err(|e| StorageError::invalid(path, e.to_string()))
}

/// Extents from a file header as dimensions, or an error naming the file (zero or absurd sizes).
pub fn checked_dims(dims: [u64; 3], path: &Path) -> Result<[u32; 3]> {
    VolumeGeometry::checked_dims(dims).map_err(|e| StorageError::invalid(path, e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_the_file() {
        let p = Path::new("bad.nrrd");
        let mut g = VolumeGeometry::axis_aligned([4, 4, 4], [1.0, 1.0, 1.0]);
        g.spacing_mm[1] = f64::NAN;
        assert!(validate(&g, p)
            .unwrap_err()
            .to_string()
            .contains("bad.nrrd"));
        let err = checked_dims([1 << 21, 4, 4], p).unwrap_err().to_string();
        assert!(err.contains("bad.nrrd") && err.contains("absurd"), "{err}");
    }
}
