//! Region growing in 3D from a clicked seed: the 6-connected voxels whose primary value is in a
//! range, given or taken as mean ± k·σ of the seed's 3×3×3 neighbourhood. Locked segments are
//! neither painted nor crossed. A voxel cap bounds the work: at the cap the grow stops, keeps
//! what it has as one edit and says so.

use std::sync::atomic::AtomicBool;

use crate::intensity::{Intensity, IntensityBricks, ValueRange};
use crate::layer::LabelLayer;
use crate::tools::flood::{flood, Flood};
use crate::tools::{check_tool_label, Outcome};
use crate::{Label, SegmentError};

/// Which values the region takes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GrowCriterion {
    /// Values in this range.
    Range(ValueRange),
    /// Values within `k` standard deviations (population) of the mean of the seed's 3×3×3
    /// neighbourhood (the part inside the grid).
    MeanSigma { k: f64 },
}

/// The range a criterion stands for at a seed.
pub fn grow_range(
    layer: &LabelLayer,
    intensity: &dyn Intensity,
    seed: [u32; 3],
    criterion: GrowCriterion,
) -> Result<ValueRange, SegmentError> {
    let k = match criterion {
        GrowCriterion::Range(range) => return Ok(range),
        GrowCriterion::MeanSigma { k } => k,
    };
    if !(k.is_finite() && k >= 0.0) {
        return Err(SegmentError::BadParameter(format!(
            "k for mean ± k·σ must be a number ≥ 0, got {k}"
        )));
    }
    let grid = layer.grid();
    let mut values = IntensityBricks::new(intensity, grid);
    let (mut n, mut sum, mut sum2) = (0u32, 0.0f64, 0.0f64);
    for dk in -1i64..=1 {
        for dj in -1i64..=1 {
            for di in -1i64..=1 {
                let v = [
                    i64::from(seed[0]) + di,
                    i64::from(seed[1]) + dj,
                    i64::from(seed[2]) + dk,
                ];
                if !grid.contains(v) {
                    continue;
                }
                let value = f64::from(values.value(v.map(|c| c as u32))?);
                if value.is_finite() {
                    n += 1;
                    sum += value;
                    sum2 += value * value;
                }
            }
        }
    }
    if n == 0 {
        return Err(SegmentError::BadParameter(format!(
            "the primary has no value around the seed {seed:?}"
        )));
    }
    let mean = sum / f64::from(n);
    let sd = (sum2 / f64::from(n) - mean * mean).max(0.0).sqrt();
    ValueRange::new(mean - k * sd, mean + k * sd)
}

/// Grows `label` from `seed` as one edit. `progress(voxels)` is called as it goes; setting
/// `cancel` ends it with [`SegmentError::Cancelled`] and the layer unchanged.
#[allow(clippy::too_many_arguments)] // each is one of the tool's own settings
pub fn grow_from_seed(
    layer: &mut LabelLayer,
    intensity: &dyn Intensity,
    seed: [u32; 3],
    label: Label,
    criterion: GrowCriterion,
    max_voxels: u64,
    progress: &mut dyn FnMut(u64),
    cancel: Option<&AtomicBool>,
) -> Result<(Outcome, ValueRange), SegmentError> {
    check_tool_label(layer, label)?;
    layer.get(seed)?;
    let range = grow_range(layer, intensity, seed, criterion)?;
    let segments = layer.segments();
    let any_locked = segments.iter().any(|s| s.locked);
    let region = flood(
        &Flood {
            layer,
            intensity: Some(intensity),
            axes: &[0, 1, 2],
            max_voxels,
            cancel,
        },
        seed,
        any_locked,
        true,
        |l, v| range.contains(v) && !segments.is_locked(l),
        progress,
    )?;
    let edit = layer.edit("Grow from seed", |w| region.write(w, label))?;
    Ok((
        Outcome {
            edit,
            voxels: region.voxels,
            stopped_at_cap: region.stopped_at_cap,
        },
        range,
    ))
}
