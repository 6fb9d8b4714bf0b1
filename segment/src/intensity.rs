//! The primary volume as the tools read it: physical values (HU for CT) on the label grid.
//!
//! Tools never see the store: the viewer implements [`Intensity`] over its bricks (resampled to
//! the label grid when the labels came on a grid of their own), tests over a dense array
//! ([`DenseIntensity`]). Reads are by brick, the unit the store and the layer share, so a tool
//! that walks many voxels pays one read per brick, not one per voxel.

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::SegmentError;

/// Physical values of the primary volume at the voxels of a label grid.
pub trait Intensity: Send + Sync {
    /// The physical value at one voxel of the label grid (an error outside it).
    fn value(&self, grid: &LabelGrid, voxel: [u32; 3]) -> Result<f32, SegmentError>;

    /// Fills `out` (`LABEL_BRICK_VOXELS`, i fastest) with a brick's physical values; voxels
    /// outside the grid are NaN, so no value range ever admits them.
    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [f32],
    ) -> Result<(), SegmentError>;

    /// The physical unit ("HU", or "" when the volume has none), for tables and CSV headers.
    fn unit(&self) -> &str {
        ""
    }
}

/// A whole volume of physical values in memory (i fastest), for tests and small volumes.
pub struct DenseIntensity {
    dims: [u32; 3],
    values: Vec<f32>,
    unit: String,
}

impl DenseIntensity {
    /// Refuses a value array whose length is not the grid's voxel count.
    pub fn new(dims: [u32; 3], values: Vec<f32>, unit: &str) -> Result<Self, SegmentError> {
        let want = dims.iter().map(|&d| d as u64).product::<u64>();
        if values.len() as u64 != want {
            return Err(SegmentError::Grid(format!(
                "intensity of {dims:?} voxels needs {want} values, got {}",
                values.len()
            )));
        }
        Ok(DenseIntensity {
            dims,
            values,
            unit: unit.to_owned(),
        })
    }

    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    pub fn values(&self) -> &[f32] {
        &self.values
    }

    fn check_grid(&self, grid: &LabelGrid) -> Result<(), SegmentError> {
        if grid.dims() == self.dims {
            Ok(())
        } else {
            Err(SegmentError::Grid(format!(
                "intensity is {:?} voxels, the label grid {:?}",
                self.dims,
                grid.dims()
            )))
        }
    }
}

impl Intensity for DenseIntensity {
    fn value(&self, grid: &LabelGrid, voxel: [u32; 3]) -> Result<f32, SegmentError> {
        self.check_grid(grid)?;
        if !grid.contains(voxel.map(i64::from)) {
            return Err(SegmentError::OutOfBounds {
                voxel: voxel.map(i64::from),
                dims: self.dims,
            });
        }
        let [nx, ny, _] = self.dims.map(|d| d as usize);
        let [i, j, k] = voxel.map(|v| v as usize);
        Ok(self.values[i + nx * (j + ny * k)])
    }

    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [f32],
    ) -> Result<(), SegmentError> {
        self.check_grid(grid)?;
        if out.len() != LABEL_BRICK_VOXELS {
            return Err(SegmentError::Grid(format!(
                "a brick read needs {LABEL_BRICK_VOXELS} values, got {}",
                out.len()
            )));
        }
        out.fill(f32::NAN);
        let b = LABEL_BRICK as usize;
        let origin = key.0.map(|v| v as usize * b);
        let [nx, ny, nz] = self.dims.map(|d| d as usize);
        if origin[0] >= nx {
            return Ok(());
        }
        let n = b.min(nx - origin[0]);
        for lk in 0..b.min(nz.saturating_sub(origin[2])) {
            for lj in 0..b.min(ny.saturating_sub(origin[1])) {
                let row = origin[0] + nx * (origin[1] + lj + ny * (origin[2] + lk));
                let dst = b * (lj + b * lk);
                out[dst..dst + n].copy_from_slice(&self.values[row..row + n]);
            }
        }
        Ok(())
    }

    fn unit(&self) -> &str {
        &self.unit
    }
}

/// Fills `out` (`LABEL_BRICK_VOXELS`, i fastest) with label brick `key`'s physical values from
/// the primary's level-0 brick payload at the same coordinates (`BRICK_PAYLOAD`³ stored values,
/// apron included), when the label grid is the primary's own grid: a label brick is then exactly
/// a level-0 brick's core. Voxels outside the grid are NaN. One conversion for every reader of
/// a store's bricks (the page's resident bricks, a store read natively), so both give the same
/// values.
pub fn label_brick_from_level0(
    grid: &LabelGrid,
    key: BrickKey,
    payload: &[u16],
    physical: &dyn Fn(u16) -> f64,
    out: &mut [f32],
) -> Result<(), SegmentError> {
    let edge = strata_types::BRICK_PAYLOAD as usize;
    let apron = strata_types::BRICK_APRON as usize;
    if payload.len() != strata_types::BRICK_PAYLOAD_VOXELS || out.len() != LABEL_BRICK_VOXELS {
        return Err(SegmentError::BaseRead {
            brick: key.0,
            message: format!(
                "primary brick of {} values (expected {}) read into {} (expected {})",
                payload.len(),
                strata_types::BRICK_PAYLOAD_VOXELS,
                out.len(),
                LABEL_BRICK_VOXELS
            ),
        });
    }
    out.fill(f32::NAN);
    let b = LABEL_BRICK as usize;
    let origin = grid.brick_origin(key);
    let dims = grid.dims();
    let extent = [0, 1, 2].map(|a| dims[a].saturating_sub(origin[a]).min(LABEL_BRICK) as usize);
    for lk in 0..extent[2] {
        for lj in 0..extent[1] {
            let from = ((lk + apron) * edge + lj + apron) * edge + apron;
            let to = b * (lj + b * lk);
            for li in 0..extent[0] {
                out[to + li] = physical(payload[from + li]) as f32;
            }
        }
    }
    Ok(())
}

/// Bricks of an [`Intensity`] read once and kept for one operation, so a tool that asks voxel
/// by voxel reads each brick once. Memory grows with the bricks the operation reaches (128 KiB
/// each), which its own bounds (brush size, voxel cap) already limit.
pub struct IntensityBricks<'a> {
    intensity: &'a dyn Intensity,
    grid: &'a LabelGrid,
    bricks: FxHashMap<BrickKey, Box<[f32]>>,
}

impl<'a> IntensityBricks<'a> {
    pub fn new(intensity: &'a dyn Intensity, grid: &'a LabelGrid) -> Self {
        IntensityBricks {
            intensity,
            grid,
            bricks: FxHashMap::default(),
        }
    }

    /// The brick's values (read on first use).
    pub fn brick(&mut self, key: BrickKey) -> Result<&[f32], SegmentError> {
        if !self.bricks.contains_key(&key) {
            let mut out = vec![0.0; LABEL_BRICK_VOXELS].into_boxed_slice();
            self.intensity.read_brick(self.grid, key, &mut out)?;
            self.bricks.insert(key, out);
        }
        Ok(self.bricks.get(&key).map(|b| &b[..]).unwrap_or(&[]))
    }

    /// The value at an in-grid voxel.
    pub fn value(&mut self, voxel: [u32; 3]) -> Result<f32, SegmentError> {
        let (key, at) = self.grid.brick_of(voxel);
        Ok(self.brick(key)?.get(at).copied().unwrap_or(f32::NAN))
    }
}

/// An inclusive range of physical values (e.g. bone: 300 ≤ HU ≤ 3000). NaN is never inside.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValueRange {
    pub lo: f64,
    pub hi: f64,
}

impl ValueRange {
    /// Refuses NaN bounds and lo > hi (infinite bounds are fine: "HU ≥ 300" is `300..=inf`).
    pub fn new(lo: f64, hi: f64) -> Result<Self, SegmentError> {
        if lo.is_nan() || hi.is_nan() || lo > hi {
            return Err(SegmentError::BadParameter(format!(
                "value range {lo}..={hi} is empty or not a number"
            )));
        }
        Ok(ValueRange { lo, hi })
    }

    pub fn contains(&self, value: f32) -> bool {
        let v = f64::from(value);
        v >= self.lo && v <= self.hi
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_types::VolumeGeometry;

    #[test]
    fn a_brick_read_matches_voxel_reads_and_is_nan_outside_the_grid() {
        let dims = [40, 35, 33];
        let values: Vec<f32> = (0..40 * 35 * 33).map(|n| n as f32).collect();
        let grid = LabelGrid::new(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap();
        let dense = DenseIntensity::new(dims, values, "HU").unwrap();
        let mut out = vec![0.0; LABEL_BRICK_VOXELS];
        dense
            .read_brick(&grid, BrickKey([1, 1, 1]), &mut out)
            .unwrap();
        let b = LABEL_BRICK as usize;
        for (lk, lj, li) in [(0usize, 0usize, 0usize), (0, 2, 7), (0, 3, 8), (1, 0, 0)] {
            let got = out[li + b * (lj + b * lk)];
            if li < 8 && lj < 3 && lk < 1 {
                let want = dense
                    .value(&grid, [32 + li as u32, 32 + lj as u32, 32 + lk as u32])
                    .unwrap();
                assert_eq!(got, want);
            } else {
                assert!(got.is_nan(), "({li},{lj},{lk}) is outside the grid");
            }
        }
        assert!(DenseIntensity::new(dims, vec![0.0; 3], "").is_err());
        assert!(dense.value(&grid, [40, 0, 0]).is_err());
    }

    #[test]
    fn a_level0_payload_gives_its_core_in_physical_values_and_nan_outside_the_grid() {
        let dims = [40, 33, 35];
        let grid = LabelGrid::new(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap();
        let edge = strata_types::BRICK_PAYLOAD as usize;
        let apron = strata_types::BRICK_APRON as usize;
        // Each stored value names its payload position, so a shifted read shows.
        let payload: Vec<u16> = (0..strata_types::BRICK_PAYLOAD_VOXELS)
            .map(|n| n as u16)
            .collect();
        let mut out = vec![0.0; LABEL_BRICK_VOXELS];
        let physical = |s: u16| f64::from(s) * 0.5 - 1024.0;
        label_brick_from_level0(&grid, BrickKey([1, 0, 1]), &payload, &physical, &mut out).unwrap();
        let b = LABEL_BRICK as usize;
        for (li, lj, lk) in [(0usize, 0usize, 0usize), (7, 32 - 1, 2), (5, 4, 3)] {
            let got = out[li + b * (lj + b * lk)];
            // Brick [1, 0, 1] starts at i = 32, k = 32: 8 voxels along i, 33 along j, 3 along k.
            if li < 8 && lj < 33 && lk < 3 {
                let stored = payload[((lk + apron) * edge + lj + apron) * edge + li + apron];
                assert_eq!(got, physical(stored) as f32, "({li},{lj},{lk})");
            } else {
                assert!(got.is_nan(), "({li},{lj},{lk}) is outside the grid");
            }
        }
        assert!(out[8].is_nan() && out[b * b * 3].is_nan());
        assert!(label_brick_from_level0(
            &grid,
            BrickKey([0; 3]),
            &payload[1..],
            &physical,
            &mut out
        )
        .is_err());
    }

    #[test]
    fn a_value_range_is_inclusive_and_refuses_nan_and_reversed_bounds() {
        let r = ValueRange::new(300.0, f64::INFINITY).unwrap();
        assert!(r.contains(300.0) && r.contains(3000.0) && !r.contains(299.9));
        assert!(!r.contains(f32::NAN));
        assert!(ValueRange::new(2.0, 1.0).is_err());
        assert!(ValueRange::new(f64::NAN, 1.0).is_err());
    }
}
