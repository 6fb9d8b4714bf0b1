//! Where the voxels sit in the patient: LPS millimetres, as DICOM defines them.
//!
//! `patient = origin + Σ_a direction[a] · spacing[a] · index[a]`, with `index` at voxel centres.
//! Oblique frames are kept as they are; the renderer and the importers use this one definition.

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

/// Largest extent accepted on one axis; beyond this a header is taken as corrupt, not as data.
pub const MAX_AXIS_VOXELS: u64 = 1 << 20;
/// Largest voxel count accepted (2^44 ≈ 17.6 T voxels, about 26000³): room for the mostly-air
/// 16384³ micro-CT sizes of the sparse skeleton (issue 18), small enough to catch garbage.
pub const MAX_TOTAL_VOXELS: u64 = 1 << 44;

/// What is wrong with a geometry. Callers add the file (storage) or the scene (render).
/// Smallest voxel spacing accepted: 1 nm.
pub const MIN_SPACING_MM: f64 = 1e-6;
/// Largest voxel spacing accepted: 100 m.
pub const MAX_SPACING_MM: f64 = 1e5;
/// Largest origin coordinate accepted: 1000 km.
pub const MAX_ORIGIN_MM: f64 = 1e9;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    #[error("zero dimension in {0:?}")]
    ZeroDimension([u64; 3]),
    #[error("absurd dimensions {0:?}")]
    AbsurdDimensions([u64; 3]),
    #[error("voxel spacing must be between 1 nm and 100 m (0.000001 to 100000 mm), got {0:?} mm")]
    BadSpacing([f64; 3]),
    #[error("origin must be finite and within 1000 km, got {0:?} mm")]
    NonFiniteOrigin([f64; 3]),
    #[error("direction cosines not unit length: {0:?}")]
    NonUnitDirection([[f64; 3]; 3]),
    #[error("degenerate direction cosines: {0:?}")]
    DegenerateDirection([[f64; 3]; 3]),
}

/// Index (i, j, k) to patient space (LPS mm).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VolumeGeometry {
    /// Level-0 voxels along i, j, k (i varies fastest in memory).
    pub dims: [u32; 3],
    /// Voxel size along i, j, k in millimetres.
    pub spacing_mm: [f64; 3],
    /// Patient-space (LPS, mm) position of the centre of voxel (0, 0, 0).
    pub origin_lps_mm: [f64; 3],
    /// `direction[a]` = unit LPS vector of index axis `a`.
    pub direction: [[f64; 3]; 3],
}

impl VolumeGeometry {
    pub fn axis_aligned(dims: [u32; 3], spacing_mm: [f64; 3]) -> Self {
        VolumeGeometry {
            dims,
            spacing_mm,
            origin_lps_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    /// Extents read from a file header, checked before they become dimensions: zero or absurd
    /// sizes are rejected here, so no reader allocates from a corrupt header.
    pub fn checked_dims(dims: [u64; 3]) -> Result<[u32; 3], GeometryError> {
        if dims.contains(&0) {
            return Err(GeometryError::ZeroDimension(dims));
        }
        let total = dims.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d));
        if dims.iter().any(|&d| d > MAX_AXIS_VOXELS) || total.is_none_or(|n| n > MAX_TOTAL_VOXELS) {
            return Err(GeometryError::AbsurdDimensions(dims));
        }
        // MAX_AXIS_VOXELS < 2^32, so every axis fits.
        Ok(dims.map(|d| d as u32))
    }

    pub fn dims_u64(&self) -> [u64; 3] {
        self.dims.map(u64::from)
    }

    pub fn voxel_count(&self) -> u64 {
        self.dims_u64().iter().product()
    }

    /// Rejects what no real scan has: zero or absurd sizes, non-finite or non-positive spacing,
    /// a non-finite origin, non-unit or degenerate direction cosines.
    /// Rejects what no real scan has: zero or absurd extents, spacings outside
    /// [`MIN_SPACING_MM`]..[`MAX_SPACING_MM`], origins beyond [`MAX_ORIGIN_MM`], degenerate axes.
    pub fn validate(&self) -> Result<(), GeometryError> {
        Self::checked_dims(self.dims_u64())?;
        // Electron microscopy is at nanometres, a whole-body CT at a few millimetres: spacings
        // outside 1 nm..100 m are header damage, and render as nothing (f32 positions).
        if self
            .spacing_mm
            .iter()
            .any(|s| !s.is_finite() || !(MIN_SPACING_MM..=MAX_SPACING_MM).contains(s))
        {
            return Err(GeometryError::BadSpacing(self.spacing_mm));
        }
        if self
            .origin_lps_mm
            .iter()
            .any(|v| !v.is_finite() || v.abs() > MAX_ORIGIN_MM)
        {
            return Err(GeometryError::NonFiniteOrigin(self.origin_lps_mm));
        }
        for axis in &self.direction {
            let norm = DVec3::from(*axis).length();
            if !norm.is_finite() || (norm - 1.0).abs() > 1e-3 {
                return Err(GeometryError::NonUnitDirection(self.direction));
            }
        }
        let det = self.direction_matrix().determinant();
        let linear_det = self.patient_from_index_linear().determinant();
        if !det.is_finite()
            || det.abs() < 1e-3
            || !linear_det.is_finite()
            || linear_det.abs() < 1e-12
        {
            return Err(GeometryError::DegenerateDirection(self.direction));
        }
        Ok(())
    }

    /// Columns are the unit direction of each index axis.
    fn direction_matrix(&self) -> DMat3 {
        DMat3::from_cols(
            DVec3::from(self.direction[0]),
            DVec3::from(self.direction[1]),
            DVec3::from(self.direction[2]),
        )
    }

    /// Linear part of index → patient: columns are direction[a] · spacing[a].
    pub fn patient_from_index_linear(&self) -> DMat3 {
        let col = |a: usize| DVec3::from(self.direction[a]) * self.spacing_mm[a];
        DMat3::from_cols(col(0), col(1), col(2))
    }

    pub fn index_from_patient_linear(&self) -> DMat3 {
        self.patient_from_index_linear().inverse()
    }

    pub fn origin(&self) -> DVec3 {
        DVec3::from(self.origin_lps_mm)
    }

    /// Patient position (LPS mm) of a continuous index.
    pub fn patient_from_index(&self, index: impl Into<DVec3>) -> DVec3 {
        self.origin() + self.patient_from_index_linear() * index.into()
    }

    /// Continuous index of a patient position (inverse of [`Self::patient_from_index`]).
    pub fn index_from_patient(&self, patient: impl Into<DVec3>) -> DVec3 {
        self.index_from_patient_linear() * (patient.into() - self.origin())
    }

    /// Centre of the voxel-cell box [-0.5, dims-0.5] in patient space.
    pub fn centre_patient(&self) -> DVec3 {
        let c = DVec3::new(
            self.dims[0] as f64,
            self.dims[1] as f64,
            self.dims[2] as f64,
        ) * 0.5
            - 0.5;
        self.patient_from_index(c)
    }

    /// Radius of the sphere around the centre that encloses the whole voxel-cell box.
    pub fn bounding_radius_mm(&self) -> f64 {
        let half = DVec3::new(
            self.dims[0] as f64,
            self.dims[1] as f64,
            self.dims[2] as f64,
        ) * 0.5;
        (self.patient_from_index_linear() * half)
            .length()
            .max((self.patient_from_index_linear() * DVec3::new(half.x, -half.y, half.z)).length())
            .max((self.patient_from_index_linear() * DVec3::new(half.x, half.y, -half.z)).length())
            .max((self.patient_from_index_linear() * DVec3::new(-half.x, half.y, half.z)).length())
    }

    /// Finest voxel edge in mm: the unit of the base step and of opacity.
    pub fn finest_spacing_mm(&self) -> f64 {
        self.spacing_mm
            .iter()
            .cloned()
            .fold(f64::INFINITY, f64::min)
    }

    /// Level-0 brick positions per axis (the page grid).
    pub fn page_dims(&self) -> [u32; 3] {
        self.dims.map(|d| d.div_ceil(crate::BRICK_CORE))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_patient_round_trip_on_oblique_frame() {
        let c = 0.6f64;
        let s = 0.8f64;
        let g = VolumeGeometry {
            dims: [10, 20, 30],
            spacing_mm: [0.5, 1.5, 3.0],
            origin_lps_mm: [-10.0, 5.0, 2.0],
            direction: [[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, -1.0]],
        };
        g.validate().unwrap();
        let idx = DVec3::new(3.25, 7.5, 11.0);
        let back = g.index_from_patient(g.patient_from_index(idx));
        assert!(
            (back - idx).abs().max_element() < 1e-9,
            "{back:?} vs {idx:?}"
        );
    }

    #[test]
    fn validate_rejects_bad_headers() {
        let mut g = VolumeGeometry::axis_aligned([4, 4, 4], [1.0, 1.0, 1.0]);
        g.spacing_mm[1] = f64::NAN;
        assert!(matches!(g.validate(), Err(GeometryError::BadSpacing(_))));
        let g = VolumeGeometry::axis_aligned([0, 4, 4], [1.0; 3]);
        assert!(g
            .validate()
            .unwrap_err()
            .to_string()
            .contains("zero dimension"));
        assert!(VolumeGeometry::checked_dims([1 << 21, 4, 4])
            .unwrap_err()
            .to_string()
            .contains("absurd"));
        assert!(VolumeGeometry::checked_dims([1 << 20, 1 << 20, 1 << 6]).is_err());
        // 16384³ (mostly-air micro-CT, a sparse store) is data, not garbage.
        assert!(VolumeGeometry::checked_dims([1 << 14, 1 << 14, 1 << 14]).is_ok());
        assert_eq!(VolumeGeometry::checked_dims([3, 4, 5]), Ok([3, 4, 5]));
        let mut g = VolumeGeometry::axis_aligned([4, 4, 4], [1.0; 3]);
        g.direction[2] = g.direction[0];
        assert!(matches!(
            g.validate(),
            Err(GeometryError::DegenerateDirection(_))
        ));
    }
}
