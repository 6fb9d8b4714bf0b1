//! Where the voxels sit in the patient: LPS millimetres, as DICOM defines them.

use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::error::{Result, StorageError};

/// Largest extent accepted on one axis; beyond this a header is taken as corrupt, not as data.
pub const MAX_AXIS_VOXELS: u64 = 1 << 20;
/// Largest voxel count accepted (2^40 ≈ 1.1 T voxels): far beyond any scanner, small enough to catch garbage.
pub const MAX_TOTAL_VOXELS: u64 = 1 << 40;

/// Index (i, j, k) to patient space:
/// `patient = origin + Σ_a direction[a] · spacing[a] · index[a]`.
/// `direction[a]` is the unit LPS vector along index axis `a`; oblique frames are kept as they are.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Geometry {
    /// Voxels along i, j, k (i varies fastest in memory).
    pub dims: [u64; 3],
    /// Voxel size along i, j, k in millimetres.
    pub spacing_mm: [f64; 3],
    /// Patient-space (LPS, mm) position of the centre of voxel (0, 0, 0).
    pub origin_lps_mm: [f64; 3],
    /// Unit direction of each index axis in LPS.
    pub direction: [[f64; 3]; 3],
}

impl Geometry {
    pub fn axis_aligned(dims: [u64; 3], spacing_mm: [f64; 3]) -> Self {
        Geometry {
            dims,
            spacing_mm,
            origin_lps_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    pub fn voxel_count(&self) -> u64 {
        self.dims.iter().product()
    }

    /// Patient position (LPS mm) of a continuous index.
    pub fn patient_from_index(&self, index: [f64; 3]) -> [f64; 3] {
        let mut p = self.origin_lps_mm;
        for (a, &idx) in index.iter().enumerate() {
            for (c, pc) in p.iter_mut().enumerate() {
                *pc += self.direction[a][c] * self.spacing_mm[a] * idx;
            }
        }
        p
    }

    /// Continuous index of a patient position (inverse of [`Self::patient_from_index`]).
    pub fn index_from_patient(&self, patient: [f64; 3]) -> [f64; 3] {
        let m = self.index_to_patient_matrix();
        let inv = invert3(&m).unwrap_or([[0.0; 3]; 3]);
        let d = [
            patient[0] - self.origin_lps_mm[0],
            patient[1] - self.origin_lps_mm[1],
            patient[2] - self.origin_lps_mm[2],
        ];
        let mut out = [0.0; 3];
        for (r, o) in out.iter_mut().enumerate() {
            *o = inv[r][0] * d[0] + inv[r][1] * d[1] + inv[r][2] * d[2];
        }
        out
    }

    /// Row-major 3×3 matrix M with patient − origin = M · index.
    pub fn index_to_patient_matrix(&self) -> [[f64; 3]; 3] {
        let mut m = [[0.0; 3]; 3];
        for (r, row) in m.iter_mut().enumerate() {
            for (a, v) in row.iter_mut().enumerate() {
                *v = self.direction[a][r] * self.spacing_mm[a];
            }
        }
        m
    }

    /// Rejects what no real scan has: zero or absurd sizes, non-finite or non-positive spacing,
    /// degenerate direction cosines. `path` names the file in the error.
    pub fn validate(&self, path: &Path) -> Result<()> {
        if self.dims.iter().any(|&d| d == 0) {
            return Err(StorageError::invalid(
                path,
                format!("zero dimension in {:?}", self.dims),
            ));
        }
        if self.dims.iter().any(|&d| d > MAX_AXIS_VOXELS)
            || self
                .dims
                .iter()
                .try_fold(1u64, |acc, &d| acc.checked_mul(d))
                .map_or(true, |n| n > MAX_TOTAL_VOXELS)
        {
            return Err(StorageError::invalid(
                path,
                format!("absurd dimensions {:?}", self.dims),
            ));
        }
        if self.spacing_mm.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(StorageError::invalid(
                path,
                format!(
                    "voxel spacing must be finite and positive, got {:?}",
                    self.spacing_mm
                ),
            ));
        }
        if self.origin_lps_mm.iter().any(|v| !v.is_finite()) {
            return Err(StorageError::invalid(
                path,
                format!("non-finite origin {:?}", self.origin_lps_mm),
            ));
        }
        for axis in &self.direction {
            let norm = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
            if !norm.is_finite() || (norm - 1.0).abs() > 1e-3 {
                return Err(StorageError::invalid(
                    path,
                    format!("direction cosines not unit length: {:?}", self.direction),
                ));
            }
        }
        let det = det3(&self.direction);
        if !det.is_finite() || det.abs() < 1e-3 {
            return Err(StorageError::invalid(
                path,
                format!("degenerate direction cosines: {:?}", self.direction),
            ));
        }
        Ok(())
    }
}

fn det3(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

pub(crate) fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let det = det3(m);
    if det.abs() < 1e-300 || !det.is_finite() {
        return None;
    }
    let inv_det = 1.0 / det;
    let mut out = [[0.0; 3]; 3];
    out[0][0] = (m[1][1] * m[2][2] - m[1][2] * m[2][1]) * inv_det;
    out[0][1] = (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * inv_det;
    out[0][2] = (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * inv_det;
    out[1][0] = (m[1][2] * m[2][0] - m[1][0] * m[2][2]) * inv_det;
    out[1][1] = (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * inv_det;
    out[1][2] = (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * inv_det;
    out[2][0] = (m[1][0] * m[2][1] - m[1][1] * m[2][0]) * inv_det;
    out[2][1] = (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * inv_det;
    out[2][2] = (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * inv_det;
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_patient_round_trip_on_oblique_frame() {
        let c = 0.6f64;
        let s = 0.8f64;
        let g = Geometry {
            dims: [10, 20, 30],
            spacing_mm: [0.5, 1.5, 3.0],
            origin_lps_mm: [-10.0, 5.0, 2.0],
            direction: [[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, -1.0]],
        };
        g.validate(Path::new("x")).unwrap();
        let idx = [3.25, 7.5, 11.0];
        let back = g.index_from_patient(g.patient_from_index(idx));
        for a in 0..3 {
            assert!((back[a] - idx[a]).abs() < 1e-9, "{back:?} vs {idx:?}");
        }
    }

    #[test]
    fn validate_rejects_bad_headers() {
        let p = Path::new("bad.nrrd");
        let mut g = Geometry::axis_aligned([4, 4, 4], [1.0, 1.0, 1.0]);
        g.spacing_mm[1] = f64::NAN;
        assert!(g.validate(p).unwrap_err().to_string().contains("bad.nrrd"));
        let g = Geometry::axis_aligned([0, 4, 4], [1.0; 3]);
        assert!(g
            .validate(p)
            .unwrap_err()
            .to_string()
            .contains("zero dimension"));
        let g = Geometry::axis_aligned([1 << 21, 4, 4], [1.0; 3]);
        assert!(g.validate(p).unwrap_err().to_string().contains("absurd"));
    }
}
