//! Where the voxels sit in the patient (LPS mm) and what the stored integers mean physically.
//! Mirrors `strata_storage::Geometry` field for field so the app converts without thought.

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

use crate::error::RenderError;

/// `patient = origin + Σ_a direction[a] · spacing[a] · index[a]`, index of voxel centres.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VolumeGeometry {
    /// Level-0 voxels along i, j, k.
    pub dims: [u32; 3],
    pub spacing_mm: [f64; 3],
    /// Centre of voxel (0,0,0), LPS mm.
    pub origin_lps_mm: [f64; 3],
    /// `direction[a]` = unit LPS vector of index axis `a`.
    pub direction: [[f64; 3]; 3],
}

/// physical = slope · stored + intercept (e.g. Hounsfield units).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueMapping {
    pub slope: f64,
    pub intercept: f64,
}

impl Default for ValueMapping {
    fn default() -> Self {
        ValueMapping {
            slope: 1.0,
            intercept: 0.0,
        }
    }
}

impl ValueMapping {
    pub fn physical(&self, stored: f64) -> f64 {
        self.slope * stored + self.intercept
    }
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

    pub fn validate(&self) -> Result<(), RenderError> {
        if self.dims.contains(&0) {
            return Err(RenderError::InvalidVolume(format!(
                "zero extent in dims {:?}",
                self.dims
            )));
        }
        if self.spacing_mm.iter().any(|&s| !(s.is_finite() && s > 0.0)) {
            return Err(RenderError::InvalidVolume(format!(
                "spacing must be positive, got {:?}",
                self.spacing_mm
            )));
        }
        let det = self.patient_from_index_linear().determinant();
        if !det.is_finite() || det.abs() < 1e-12 {
            return Err(RenderError::InvalidVolume(
                "direction cosines are degenerate".into(),
            ));
        }
        Ok(())
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

    pub fn patient_from_index(&self, index: DVec3) -> DVec3 {
        self.origin() + self.patient_from_index_linear() * index
    }

    pub fn index_from_patient(&self, patient: DVec3) -> DVec3 {
        self.index_from_patient_linear() * (patient - self.origin())
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
