//! Fill a closed region in an oblique slice: the voxels the brush paints in that plane (its
//! naive slab, brush.rs) connected to the clicked one and holding its label.
//!
//! Along the index axis whose step crosses the slab most steeply (the one that sets the slab's
//! thickness h), consecutive voxel centres are exactly h apart in the normal's direction, so the
//! half-open slab holds exactly one voxel of every column along that axis: the slab is a height
//! field over the other two index axes. The flood steps between 4-adjacent columns, which keeps
//! it inside the slab and bounded by a brush stroke drawn in the same view: two adjacent
//! columns' voxels are at most one step along each of two axes apart in the plane, less than
//! the width of any brush the viewer offers (its smallest diameter is two voxels).

use std::collections::VecDeque;

use glam::DVec3;
use rustc_hash::FxHashSet;

use crate::grid::LabelGrid;
use crate::intensity::{Intensity, IntensityBricks, ValueRange};
use crate::layer::LabelLayer;
use crate::tools::brush::{Resolved, SlicePlane};
use crate::tools::Outcome;
use crate::{Label, SegmentError};

/// The slab of an oblique plane as columns along its steepest index axis.
struct SlabColumns {
    slab: Resolved,
    /// The axis along which the slab holds one voxel per column.
    steep: usize,
    /// The two axes the columns are indexed by.
    across: [usize; 2],
    /// The step along `steep`, in mm along the plane's normal.
    step_mm: f64,
    normal: DVec3,
    centre: DVec3,
}

impl SlabColumns {
    fn of(grid: &LabelGrid, plane: &SlicePlane) -> Result<Self, SegmentError> {
        let SlicePlane::Oblique { centre_lps, .. } = plane else {
            return Err(SegmentError::BadParameter(
                "the oblique fill needs an oblique plane".into(),
            ));
        };
        let slab = Resolved::of(grid, Some(plane), *centre_lps)?;
        let Resolved::Oblique { centre, normal, .. } = slab else {
            return Err(SegmentError::BadParameter(
                "the oblique fill needs an oblique plane".into(),
            ));
        };
        let geometry = grid.geometry();
        let crossing = |a: usize| {
            geometry.spacing_mm[a] * normal.dot(DVec3::from(geometry.direction[a])).abs()
        };
        let steep = (0..3)
            .max_by(|&a, &b| crossing(a).total_cmp(&crossing(b)))
            .unwrap_or(2);
        let across = match steep {
            0 => [1, 2],
            1 => [0, 2],
            _ => [0, 1],
        };
        let mut one = DVec3::ZERO;
        one[steep] = 1.0;
        let step_mm =
            normal.dot(grid.patient_from_index(one) - grid.patient_from_index(DVec3::ZERO));
        Ok(SlabColumns {
            slab,
            steep,
            across,
            step_mm,
            normal,
            centre,
        })
    }

    /// The slab's voxel in column `(a, b)`, if it lies inside the grid.
    fn voxel(&self, grid: &LabelGrid, a: u32, b: u32) -> Option<[u32; 3]> {
        let mut index = DVec3::ZERO;
        index[self.across[0]] = f64::from(a);
        index[self.across[1]] = f64::from(b);
        let base = self
            .normal
            .dot(grid.patient_from_index(index) - self.centre);
        // The one whole step that brings the centre into the slab; its neighbours are tried
        // too, so the brush's own test (not this division's rounding) decides.
        let nearest = (-base / self.step_mm).round();
        let extent = f64::from(grid.dims()[self.steep]);
        for t in [nearest, nearest - 1.0, nearest + 1.0] {
            if !(0.0..extent).contains(&t) {
                continue;
            }
            index[self.steep] = t;
            let mut voxel = [0u32; 3];
            for axis in 0..3 {
                voxel[axis] = index[axis] as u32;
            }
            if self.slab.holds(voxel, grid.patient_from_index(index)) {
                return Some(voxel);
            }
        }
        None
    }
}

/// Fills the region of the oblique slice through `plane` around the column of `seed` with
/// `label`, as one edit: the slab's voxels 4-connected to the seed's across its columns that
/// hold the seed's label (and whose primary value is in `value_range`). Stops at `max_voxels`,
/// keeping what it has and saying so.
pub(crate) fn fill_in_oblique_slice(
    layer: &mut LabelLayer,
    plane: &SlicePlane,
    seed: [u32; 3],
    label: Label,
    value_range: Option<ValueRange>,
    intensity: Option<&dyn Intensity>,
    max_voxels: u64,
) -> Result<Outcome, SegmentError> {
    let grid = layer.grid().clone();
    let columns = SlabColumns::of(&grid, plane)?;
    let [pa, pb] = columns.across;
    let dims = grid.dims();
    let start = (seed[pa], seed[pb]);
    let Some(first) = columns.voxel(&grid, start.0, start.1) else {
        return Err(SegmentError::BadParameter(format!(
            "the oblique slice does not cross the grid at voxel {seed:?}"
        )));
    };
    let region_label = layer.get(first)?;
    if region_label == label {
        return Ok(Outcome::nothing());
    }
    if layer.segments().is_locked(region_label) {
        return Err(SegmentError::Locked(region_label));
    }
    if value_range.is_some() && intensity.is_none() {
        return Err(SegmentError::BadParameter(
            "a value range needs the primary's values".into(),
        ));
    }
    let mut values = intensity.map(|i| IntensityBricks::new(i, &grid));
    let mut admits = |layer: &LabelLayer, voxel: [u32; 3]| -> Result<bool, SegmentError> {
        if layer.get(voxel)? != region_label {
            return Ok(false);
        }
        match (value_range, values.as_mut()) {
            (Some(range), Some(values)) => Ok(range.contains(values.value(voxel)?)),
            _ => Ok(true),
        }
    };
    if !admits(layer, first)? {
        return Ok(Outcome::nothing());
    }
    let mut seen: FxHashSet<(u32, u32)> = FxHashSet::default();
    let mut queue = VecDeque::from([start]);
    seen.insert(start);
    let mut region = vec![first];
    let mut stopped_at_cap = region.len() as u64 >= max_voxels;
    'flood: while let Some((a, b)) = queue.pop_front() {
        if stopped_at_cap {
            break;
        }
        let neighbours = [
            (a.checked_sub(1), Some(b)),
            (a.checked_add(1).filter(|&x| x < dims[pa]), Some(b)),
            (Some(a), b.checked_sub(1)),
            (Some(a), b.checked_add(1).filter(|&x| x < dims[pb])),
        ];
        for (na, nb) in neighbours {
            let (Some(na), Some(nb)) = (na, nb) else {
                continue;
            };
            if !seen.insert((na, nb)) {
                continue;
            }
            let Some(voxel) = columns.voxel(&grid, na, nb) else {
                continue;
            };
            if admits(layer, voxel)? {
                region.push(voxel);
                queue.push_back((na, nb));
                if region.len() as u64 >= max_voxels {
                    stopped_at_cap = !queue.is_empty();
                    break 'flood;
                }
            }
        }
    }
    let voxels = region.len() as u64;
    let edit = layer.edit("Fill", |w| {
        for &voxel in &region {
            w.set(voxel, label)?;
        }
        Ok(())
    })?;
    Ok(Outcome {
        edit,
        voxels,
        stopped_at_cap,
    })
}
