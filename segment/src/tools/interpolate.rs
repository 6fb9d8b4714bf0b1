//! Fill between slices: a segment drawn on a few non-adjacent slices along an axis is
//! interpolated into the slices between them by its signed distance (in mm, in the plane,
//! anisotropic spacing included), as 3D Slicer's "fill between slices" does with its
//! distance-based method.
//!
//! For two consecutive drawn slices k0 < k1 and a slice k between them (t = (k − k0)/(k1 − k0)),
//! a voxel joins the segment when `(1 − t)·sd0 + t·sd1 ≤ 0`, where sd is the signed distance of
//! the drawn shape in that slice: distance to the nearest voxel of it outside, minus distance
//! to the nearest voxel not of it inside. Concentric discs of radii r0 and r1 thus become discs
//! of radius (1 − t)·r0 + t·r1: the frustum. Only background voxels are filled: interpolation
//! never takes voxels from another segment.

use crate::layer::{Edit, LabelLayer};
use crate::tools::brush::SlicePlane;
use crate::tools::check_tool_label;
use crate::tools::distance::squared_distance;
use crate::tools::region::{check_box, for_each_voxel_of, read_box};
use crate::{Label, SegmentError};

/// Largest in-plane box (voxels) interpolated at once.
pub const INTERPOLATE_MAX_PLANE_VOXELS: u64 = 1 << 26;

struct Gap {
    lo: [u32; 3],
    hi: [u32; 3],
    k0: u32,
    k1: u32,
    sd0: Vec<f64>,
    sd1: Vec<f64>,
}

/// Fills the slices between the drawn slices of `label` along the plane's normal axis, as one
/// edit (`None` when there was nothing to fill).
pub fn fill_between_slices(
    layer: &mut LabelLayer,
    label: Label,
    plane: &SlicePlane,
) -> Result<Option<Edit>, SegmentError> {
    check_tool_label(layer, label)?;
    let axis = match plane {
        SlicePlane::Axial => 2,
        SlicePlane::Coronal => 1,
        SlicePlane::Sagittal => 0,
        SlicePlane::Oblique { .. } => {
            return Err(SegmentError::BadParameter(
                "fill between slices works along k, j or i, not in oblique views".into(),
            ))
        }
    };
    let (p, q) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let dims = layer.grid().dims();
    // Per slice along the axis: the in-plane box of the segment there ([p lo, p hi, q lo, q hi]).
    let mut boxes: std::collections::BTreeMap<u32, [u32; 4]> = Default::default();
    for_each_voxel_of(layer, label, |v| {
        let b = boxes.entry(v[axis]).or_insert([u32::MAX, 0, u32::MAX, 0]);
        b[0] = b[0].min(v[p]);
        b[1] = b[1].max(v[p]);
        b[2] = b[2].min(v[q]);
        b[3] = b[3].max(v[q]);
    })?;
    let drawn: Vec<(u32, [u32; 4])> = boxes.into_iter().collect();
    let spacing = layer.grid().geometry().spacing_mm;
    // Per gap: its box and both drawn slices' signed distances (the slices between are made
    // inside the edit, one at a time, so memory is two planes per gap, not one per slice).
    let mut gaps: Vec<Gap> = Vec::new();
    for pair in drawn.windows(2) {
        let ((k0, b0), (k1, b1)) = (pair[0], pair[1]);
        if k1 - k0 < 2 {
            continue;
        }
        // The union of both shapes' boxes, one voxel wider so that "outside" exists around
        // them (clipped to the grid: beyond it nothing counts).
        let mut lo = [0u32; 3];
        let mut hi = [0u32; 3];
        lo[p] = b0[0].min(b1[0]).saturating_sub(1);
        hi[p] = (b0[1].max(b1[1]) + 1).min(dims[p] - 1);
        lo[q] = b0[2].min(b1[2]).saturating_sub(1);
        hi[q] = (b0[3].max(b1[3]) + 1).min(dims[q] - 1);
        let signed = |k: u32| -> Result<Vec<f64>, SegmentError> {
            let (mut slo, mut shi) = (lo, hi);
            slo[axis] = k;
            shi[axis] = k;
            let d = check_box(
                "fill between slices",
                slo,
                shi,
                INTERPOLATE_MAX_PLANE_VOXELS,
            )?;
            let labels = read_box(layer, slo, shi)?;
            let inside: Vec<bool> = labels.iter().map(|&l| l == label).collect();
            let outside: Vec<bool> = inside.iter().map(|&x| !x).collect();
            let to_inside = squared_distance(d, spacing, &inside);
            let to_outside = squared_distance(d, spacing, &outside);
            Ok(to_inside
                .iter()
                .zip(&to_outside)
                .map(|(a, b)| a.sqrt() - b.sqrt())
                .collect())
        };
        gaps.push(Gap {
            lo,
            hi,
            k0,
            k1,
            sd0: signed(k0)?,
            sd1: signed(k1)?,
        });
    }
    layer.edit("Fill between slices", |w| {
        for gap in &gaps {
            for k in gap.k0 + 1..gap.k1 {
                let t = f64::from(k - gap.k0) / f64::from(gap.k1 - gap.k0);
                let (mut lo, mut hi) = (gap.lo, gap.hi);
                lo[axis] = k;
                hi[axis] = k;
                let d = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
                for (n, (a, b)) in gap.sd0.iter().zip(&gap.sd1).enumerate() {
                    if (1.0 - t) * a + t * b > 0.0 {
                        continue;
                    }
                    let local = [n % d[0], (n / d[0]) % d[1], n / (d[0] * d[1])];
                    let voxel = [0, 1, 2].map(|x| lo[x] + local[x] as u32);
                    if w.get(voxel)? == 0 {
                        w.set(voxel, label)?;
                    }
                }
            }
        }
        Ok(())
    })
}
