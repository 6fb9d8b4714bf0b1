//! Brush and eraser: a disc in a slice plane or a sphere in 3D, swept along a stroke.
//!
//! A voxel belongs to the brush when its *centre* lies within the shape in patient space (LPS
//! mm): the size is a diameter in mm, so anisotropic spacing and rotated grids paint the same
//! physical disc. A stroke is a polyline of pointer positions; the segment between two samples
//! is filled as the disc (or sphere) swept along it (a capsule), so a fast pointer leaves no
//! gaps. The whole stroke is one [`Edit`], one undo step.
//!
//! Which voxels a plane holds:
//! - axial, coronal, sagittal: the index slice nearest to the stroke's first position (k, j,
//!   i = round of its continuous index); every position is projected into that slice;
//! - oblique (centre, two orthonormal in-plane LPS directions u, v): the voxels whose centre
//!   lies in the slab `-h/2 ≤ n·(x − centre) < h/2`, n = u × v, h = max over index axes of
//!   `spacing_a · |n · direction_a|`: the thinnest slab with no hole along the axis closest to
//!   n (a "naive" digital plane), so a plane equal to an axial one holds exactly that slice.
//!   Distances are measured in the plane (positions and centres projected onto it).

use glam::DVec3;

use crate::grid::LabelGrid;
use crate::intensity::{Intensity, IntensityBricks, ValueRange};
use crate::layer::{Edit, EditWriter, LabelLayer};
use crate::{Label, SegmentError};

/// Largest box of voxels one stroke segment may examine (a 1 m brush on a 0.1 mm grid would
/// otherwise examine 10^12): beyond it the stroke is refused with [`SegmentError::TooLarge`].
pub const BRUSH_MAX_BOX_VOXELS: u64 = 1 << 26;

/// A centre this close outside the rim (mm) still counts, so a centre exactly on the rim is
/// inside whatever the rounding of the transform.
pub const RIM_TOLERANCE_MM: f64 = 1e-9;

/// The plane of a view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SlicePlane {
    /// Constant k.
    Axial,
    /// Constant j.
    Coronal,
    /// Constant i.
    Sagittal,
    /// A plane through `centre_lps` spanned by the orthonormal LPS directions `u` and `v`.
    Oblique {
        centre_lps: DVec3,
        u: DVec3,
        v: DVec3,
    },
}

/// The brush's shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BrushShape {
    /// A disc in a view's plane.
    Disc(SlicePlane),
    /// A ball in 3D.
    Sphere,
}

/// A brush: shape, size and an optional value range of the primary it paints within.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Brush {
    pub shape: BrushShape,
    pub diameter_mm: f64,
    /// Paint (or erase) only where the primary's physical value is in this range.
    pub value_range: Option<ValueRange>,
}

/// What the brush does to the voxels it covers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BrushAction {
    /// Paint this segment over background and unlocked segments.
    Paint(Label),
    /// Set voxels to background.
    Erase(EraseTarget),
}

/// Which voxels the eraser clears.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EraseTarget {
    /// Only this segment's voxels.
    Segment(Label),
    /// Any segment's voxels except locked ones.
    AnyUnlocked,
}

/// A plane resolved against a grid and a stroke (also the oblique fill's slab: fill_oblique.rs).
#[derive(Clone, Copy, Debug)]
pub(crate) enum Resolved {
    /// Index axis of the normal and the slice along it (may lie outside the grid).
    AxisSlice {
        axis: usize,
        slice: i64,
    },
    Oblique {
        centre: DVec3,
        normal: DVec3,
        half_thickness_mm: f64,
    },
    Ball,
}

impl Resolved {
    pub(crate) fn of(
        grid: &LabelGrid,
        plane: Option<&SlicePlane>,
        first: DVec3,
    ) -> Result<Self, SegmentError> {
        let axis_slice = |axis: usize| {
            let index = grid.index_from_patient(first)[axis].round();
            // Any index far outside the grid is simply "outside"; clamping keeps it an i64.
            Resolved::AxisSlice {
                axis,
                slice: index.clamp(-1.0, f64::from(u32::MAX)) as i64,
            }
        };
        Ok(match plane {
            None => Resolved::Ball,
            Some(SlicePlane::Axial) => axis_slice(2),
            Some(SlicePlane::Coronal) => axis_slice(1),
            Some(SlicePlane::Sagittal) => axis_slice(0),
            Some(SlicePlane::Oblique { centre_lps, u, v }) => {
                let finite = centre_lps.is_finite() && u.is_finite() && v.is_finite();
                if !finite
                    || (u.length() - 1.0).abs() > 1e-6
                    || (v.length() - 1.0).abs() > 1e-6
                    || u.dot(*v).abs() > 1e-6
                {
                    return Err(SegmentError::BadParameter(format!(
                        "an oblique plane needs a finite centre and two orthonormal directions, got u {u} v {v}"
                    )));
                }
                let normal = u.cross(*v);
                let geometry = grid.geometry();
                let thickness = (0..3)
                    .map(|a| {
                        geometry.spacing_mm[a]
                            * normal.dot(DVec3::from(geometry.direction[a])).abs()
                    })
                    .fold(0.0, f64::max);
                Resolved::Oblique {
                    centre: *centre_lps,
                    normal,
                    half_thickness_mm: thickness / 2.0,
                }
            }
        })
    }

    /// A position moved into the plane (unchanged for a ball).
    fn project(&self, grid: &LabelGrid, p: DVec3) -> DVec3 {
        match *self {
            Resolved::AxisSlice { axis, slice } => {
                let mut index = grid.index_from_patient(p);
                index[axis] = slice as f64;
                grid.patient_from_index(index)
            }
            Resolved::Oblique { centre, normal, .. } => p - normal * normal.dot(p - centre),
            Resolved::Ball => p,
        }
    }

    /// Whether a voxel (index and centre) lies in the plane.
    pub(crate) fn holds(&self, voxel: [u32; 3], centre_mm: DVec3) -> bool {
        match *self {
            Resolved::AxisSlice { axis, slice } => i64::from(voxel[axis]) == slice,
            Resolved::Oblique {
                centre,
                normal,
                half_thickness_mm,
            } => {
                let off = normal.dot(centre_mm - centre);
                -half_thickness_mm <= off && off < half_thickness_mm
            }
            Resolved::Ball => true,
        }
    }
}

/// Distance from `x` to the segment `[a, b]`.
fn distance_to_segment(x: DVec3, a: DVec3, b: DVec3) -> f64 {
    let ab = b - a;
    let len2 = ab.length_squared();
    let t = if len2 > 0.0 {
        ((x - a).dot(ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (x - (a + ab * t)).length()
}

fn check_brush(brush: &Brush, positions: &[DVec3]) -> Result<(), SegmentError> {
    if !(brush.diameter_mm.is_finite() && brush.diameter_mm > 0.0) {
        return Err(SegmentError::BadParameter(format!(
            "brush diameter must be a positive number of mm, got {}",
            brush.diameter_mm
        )));
    }
    if let Some(p) = positions.iter().find(|p| !p.is_finite()) {
        return Err(SegmentError::BadParameter(format!(
            "stroke position {p} is not finite"
        )));
    }
    Ok(())
}

/// Calls `f` for every voxel of the shape swept along `positions` in `plane` (a voxel may come
/// more than once where stroke segments overlap).
fn for_each_swept_voxel(
    grid: &LabelGrid,
    shape: &Resolved,
    radius_mm: f64,
    positions: &[DVec3],
    mut f: impl FnMut([u32; 3]) -> Result<(), SegmentError>,
) -> Result<(), SegmentError> {
    if positions.is_empty() {
        return Ok(());
    }
    let projected: Vec<DVec3> = positions.iter().map(|&p| shape.project(grid, p)).collect();
    let pairs: Vec<(DVec3, DVec3)> = if projected.len() == 1 {
        vec![(projected[0], projected[0])]
    } else {
        projected.windows(2).map(|w| (w[0], w[1])).collect()
    };
    let dims = grid.dims();
    for (a, b) in pairs {
        // The capsule's patient box, mapped to index space corner by corner.
        let lo = a.min(b) - DVec3::splat(radius_mm);
        let hi = a.max(b) + DVec3::splat(radius_mm);
        let mut index_lo = DVec3::splat(f64::INFINITY);
        let mut index_hi = DVec3::splat(f64::NEG_INFINITY);
        for corner in 0..8 {
            let c = DVec3::new(
                if corner & 1 == 0 { lo.x } else { hi.x },
                if corner & 2 == 0 { lo.y } else { hi.y },
                if corner & 4 == 0 { lo.z } else { hi.z },
            );
            let index = grid.index_from_patient(c);
            index_lo = index_lo.min(index);
            index_hi = index_hi.max(index);
        }
        let mut range = [(0i64, -1i64); 3];
        for axis in 0..3 {
            let first = index_lo[axis].floor().max(0.0);
            let last = index_hi[axis].ceil().min(f64::from(dims[axis]) - 1.0);
            range[axis] = (first as i64, last as i64);
        }
        if let Resolved::AxisSlice { axis, slice } = *shape {
            range[axis] = (range[axis].0.max(slice), range[axis].1.min(slice));
        }
        if range.iter().any(|&(s, e)| e < s) {
            continue;
        }
        let box_voxels: u64 = range.iter().map(|&(s, e)| (e - s + 1) as u64).product();
        if box_voxels > BRUSH_MAX_BOX_VOXELS {
            return Err(SegmentError::TooLarge {
                what: "a brush stroke segment",
                voxels: box_voxels,
                limit: BRUSH_MAX_BOX_VOXELS,
            });
        }
        for k in range[2].0..=range[2].1 {
            for j in range[1].0..=range[1].1 {
                for i in range[0].0..=range[0].1 {
                    let voxel = [i as u32, j as u32, k as u32];
                    let centre = grid.patient_from_index(DVec3::new(i as f64, j as f64, k as f64));
                    if !shape.holds(voxel, centre) {
                        continue;
                    }
                    let in_plane = shape.project(grid, centre);
                    if distance_to_segment(in_plane, a, b) <= radius_mm + RIM_TOLERANCE_MM {
                        f(voxel)?;
                    }
                }
            }
        }
    }
    Ok(())
}

fn shape_plane(brush: &Brush) -> Option<&SlicePlane> {
    match &brush.shape {
        BrushShape::Disc(plane) => Some(plane),
        BrushShape::Sphere => None,
    }
}

/// The voxels a stroke covers (sorted by k, j, i; each once), before value range and locks.
pub fn stroke_voxels(
    grid: &LabelGrid,
    brush: &Brush,
    positions_lps: &[DVec3],
) -> Result<Vec<[u32; 3]>, SegmentError> {
    check_brush(brush, positions_lps)?;
    let Some(&first) = positions_lps.first() else {
        return Ok(Vec::new());
    };
    let shape = Resolved::of(grid, shape_plane(brush), first)?;
    let mut out = Vec::new();
    for_each_swept_voxel(grid, &shape, brush.diameter_mm / 2.0, positions_lps, |v| {
        out.push(v);
        Ok(())
    })?;
    out.sort_unstable_by_key(|v| [v[2], v[1], v[0]]);
    out.dedup();
    Ok(out)
}

/// The cursor's outline: the brush's voxels at `position_lps` that lie in the view's plane (for
/// a disc, the disc; for a sphere, its cut by the view), sorted by k, j, i.
pub fn footprint(
    grid: &LabelGrid,
    brush: &Brush,
    position_lps: DVec3,
    view: &SlicePlane,
) -> Result<Vec<[u32; 3]>, SegmentError> {
    let voxels = stroke_voxels(grid, brush, &[position_lps])?;
    let view = Resolved::of(grid, Some(view), position_lps)?;
    Ok(voxels
        .into_iter()
        .filter(|&v| {
            let centre = grid.patient_from_index(DVec3::from(v.map(f64::from)));
            view.holds(v, centre)
        })
        .collect())
}

/// Applies one stroke as one edit (`None` when it changed nothing). Locked segments are never
/// painted over or erased; painting with, or erasing, a locked segment is refused.
pub fn stroke(
    layer: &mut LabelLayer,
    brush: &Brush,
    action: BrushAction,
    positions_lps: &[DVec3],
    intensity: Option<&dyn Intensity>,
) -> Result<Option<Edit>, SegmentError> {
    check_brush(brush, positions_lps)?;
    let segments = layer.segments();
    let tool_label = match action {
        BrushAction::Paint(label) | BrushAction::Erase(EraseTarget::Segment(label)) => Some(label),
        BrushAction::Erase(EraseTarget::AnyUnlocked) => None,
    };
    if let Some(label) = tool_label {
        if segments.get(label).is_none() {
            return Err(SegmentError::NoSuchSegment(label));
        }
        if segments.is_locked(label) {
            return Err(SegmentError::Locked(label));
        }
    }
    let range = match (brush.value_range, intensity) {
        (Some(range), Some(intensity)) => Some((range, intensity)),
        (None, _) => None,
        (Some(_), None) => {
            return Err(SegmentError::BadParameter(
                "a brush limited to a value range needs the primary volume".into(),
            ))
        }
    };
    let Some(&first) = positions_lps.first() else {
        return Ok(None);
    };
    let shape = Resolved::of(layer.grid(), shape_plane(brush), first)?;
    let radius_mm = brush.diameter_mm / 2.0;
    let grid = layer.grid().clone();
    let name = match action {
        BrushAction::Paint(_) => "Brush",
        BrushAction::Erase(_) => "Eraser",
    };
    layer.edit(name, |w: &mut EditWriter<'_>| {
        let mut values = range.map(|(r, i)| (r, IntensityBricks::new(i, &grid)));
        for_each_swept_voxel(&grid, &shape, radius_mm, positions_lps, |voxel| {
            if let Some((range, values)) = values.as_mut() {
                if !range.contains(values.value(voxel)?) {
                    return Ok(());
                }
            }
            match action {
                BrushAction::Paint(label) => {
                    w.paint(voxel, label)?;
                }
                BrushAction::Erase(EraseTarget::Segment(label)) => {
                    if w.get(voxel)? == label {
                        w.set(voxel, 0)?;
                    }
                }
                BrushAction::Erase(EraseTarget::AnyUnlocked) => {
                    w.paint(voxel, 0)?;
                }
            }
            Ok(())
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_types::VolumeGeometry;

    fn grid(dims: [u32; 3], spacing: [f64; 3]) -> LabelGrid {
        LabelGrid::new(VolumeGeometry::axis_aligned(dims, spacing)).unwrap()
    }

    #[test]
    fn a_one_point_disc_on_a_unit_grid_is_the_digital_disc() {
        let g = grid([20, 20, 20], [1.0; 3]);
        let brush = Brush {
            shape: BrushShape::Disc(SlicePlane::Axial),
            diameter_mm: 5.0,
            value_range: None,
        };
        let v = stroke_voxels(&g, &brush, &[DVec3::new(10.0, 10.0, 7.2)]).unwrap();
        // Radius 2.5: offsets with di² + dj² ≤ 6.25 → 21 voxels, all on slice 7.
        assert_eq!(v.len(), 21);
        assert!(v.iter().all(|p| p[2] == 7));
        assert!(v.contains(&[12, 11, 7]) && !v.contains(&[12, 12, 7]));
    }

    #[test]
    fn an_oblique_plane_equal_to_an_axial_one_holds_the_same_voxels() {
        let g = grid([24, 24, 24], [1.0, 1.0, 2.0]);
        let p = DVec3::new(11.3, 12.1, 2.0 * 9.0);
        let axial = Brush {
            shape: BrushShape::Disc(SlicePlane::Axial),
            diameter_mm: 7.0,
            value_range: None,
        };
        let oblique = Brush {
            shape: BrushShape::Disc(SlicePlane::Oblique {
                centre_lps: DVec3::new(0.0, 0.0, 18.0),
                u: DVec3::X,
                v: DVec3::Y,
            }),
            ..axial
        };
        let a = stroke_voxels(&g, &axial, &[p]).unwrap();
        assert!(!a.is_empty());
        assert_eq!(a, stroke_voxels(&g, &oblique, &[p]).unwrap());
    }

    #[test]
    fn bad_sizes_planes_and_huge_brushes_are_errors() {
        let g = grid([16, 16, 16], [0.001; 3]);
        let mut brush = Brush {
            shape: BrushShape::Sphere,
            diameter_mm: f64::NAN,
            value_range: None,
        };
        assert!(stroke_voxels(&g, &brush, &[DVec3::ZERO]).is_err());
        brush.diameter_mm = 1.0;
        assert!(stroke_voxels(&g, &brush, &[DVec3::splat(f64::INFINITY)]).is_err());
        brush.diameter_mm = 1.0e6;
        let big = grid([1024, 1024, 1024], [0.001; 3]);
        assert!(matches!(
            stroke_voxels(&big, &brush, &[DVec3::ZERO]),
            Err(SegmentError::TooLarge { .. })
        ));
        brush.shape = BrushShape::Disc(SlicePlane::Oblique {
            centre_lps: DVec3::ZERO,
            u: DVec3::X,
            v: DVec3::X,
        });
        brush.diameter_mm = 1.0;
        assert!(stroke_voxels(&g, &brush, &[DVec3::ZERO]).is_err());
    }
}
