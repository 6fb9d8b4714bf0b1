//! Fill a closed region in a slice: from a clicked voxel, the 4-connected voxels of the slice
//! that hold the same label as it (so other labels bound the region) and, optionally, whose
//! primary value is in a range. Oblique slices: fill_oblique.rs.

use crate::intensity::{Intensity, ValueRange};
use crate::layer::LabelLayer;
use crate::tools::brush::SlicePlane;
use crate::tools::flood::{flood, Flood};
use crate::tools::{check_tool_label, Outcome};
use crate::{Label, SegmentError};

/// Fills the region around `seed` in the index slice of `plane` through it with `label`, as one
/// edit. Stops at `max_voxels` (keeping what it has, and saying so in the outcome).
pub fn fill_in_slice(
    layer: &mut LabelLayer,
    plane: &SlicePlane,
    seed: [u32; 3],
    label: Label,
    value_range: Option<ValueRange>,
    intensity: Option<&dyn Intensity>,
    max_voxels: u64,
) -> Result<Outcome, SegmentError> {
    check_tool_label(layer, label)?;
    let axes: &[usize] = match plane {
        SlicePlane::Axial => &[0, 1],
        SlicePlane::Coronal => &[0, 2],
        SlicePlane::Sagittal => &[1, 2],
        SlicePlane::Oblique { .. } => {
            return crate::tools::fill_oblique::fill_in_oblique_slice(
                layer,
                plane,
                seed,
                label,
                value_range,
                intensity,
                max_voxels,
            )
        }
    };
    let region_label = layer.get(seed)?;
    if region_label == label {
        return Ok(Outcome::nothing());
    }
    if layer.segments().is_locked(region_label) {
        return Err(SegmentError::Locked(region_label));
    }
    let region = flood(
        &Flood {
            layer,
            intensity,
            axes,
            max_voxels,
            cancel: None,
        },
        seed,
        true,
        value_range.is_some(),
        |l, v| l == region_label && value_range.is_none_or(|r| r.contains(v)),
        &mut |_| {},
    )?;
    let edit = layer.edit("Fill", |w| region.write(w, label))?;
    Ok(Outcome {
        edit,
        voxels: region.voxels,
        stopped_at_cap: region.stopped_at_cap,
    })
}
