//! The label grid: the voxel grid a label layer lives on, cut into edit bricks.

use glam::DVec3;
use strata_types::VolumeGeometry;

use crate::SegmentError;

/// Edge of an edit brick in voxels. Equal to the store's brick core (`BRICK_CORE`), so an edited
/// brick is exactly one brick of a label store and its level-0 octree node.
pub const LABEL_BRICK: u32 = strata_types::BRICK_CORE;
/// Voxels in one edit brick.
pub const LABEL_BRICK_VOXELS: usize = (LABEL_BRICK * LABEL_BRICK * LABEL_BRICK) as usize;

/// Which edit brick: its position in bricks along i, j, k.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub struct BrickKey(pub [u32; 3]);

/// A label layer's grid: its geometry (dims, spacing, LPS placement) and the brick cut.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelGrid {
    geometry: VolumeGeometry,
}

impl LabelGrid {
    pub fn new(geometry: VolumeGeometry) -> Result<Self, SegmentError> {
        geometry
            .validate()
            .map_err(|e| SegmentError::Grid(e.to_string()))?;
        Ok(LabelGrid { geometry })
    }

    pub fn geometry(&self) -> &VolumeGeometry {
        &self.geometry
    }

    pub fn dims(&self) -> [u32; 3] {
        self.geometry.dims
    }

    /// Bricks along i, j, k (the last one along an axis may be partly outside the volume).
    pub fn bricks(&self) -> [u32; 3] {
        self.geometry.dims.map(|d| d.div_ceil(LABEL_BRICK))
    }

    pub fn contains(&self, voxel: [i64; 3]) -> bool {
        (0..3).all(|a| voxel[a] >= 0 && voxel[a] < i64::from(self.geometry.dims[a]))
    }

    /// The brick holding an in-grid voxel and the voxel's index inside the brick
    /// (i fastest, then j, then k).
    pub fn brick_of(&self, voxel: [u32; 3]) -> (BrickKey, usize) {
        let key = BrickKey(voxel.map(|v| v / LABEL_BRICK));
        let [li, lj, lk] = voxel.map(|v| (v % LABEL_BRICK) as usize);
        let b = LABEL_BRICK as usize;
        (key, li + b * (lj + b * lk))
    }

    /// First voxel of a brick.
    pub fn brick_origin(&self, key: BrickKey) -> [u32; 3] {
        key.0.map(|b| b * LABEL_BRICK)
    }

    /// Patient (LPS, mm) position of a voxel centre.
    pub fn patient_from_index(&self, index: DVec3) -> DVec3 {
        self.geometry.patient_from_index(index)
    }

    /// Continuous voxel index of a patient (LPS, mm) position.
    pub fn index_from_patient(&self, patient: DVec3) -> DVec3 {
        self.geometry.index_from_patient(patient)
    }

    /// Volume of one voxel in millilitres.
    pub fn voxel_volume_ml(&self) -> f64 {
        self.geometry.spacing_mm.iter().product::<f64>() / 1000.0
    }
}
