//! Region growing in 3D from a clicked seed: the 6-connected voxels whose primary value is in a
//! range, given or taken as mean ± k·σ of the seed's 3×3×3 neighbourhood. Locked segments are
//! neither painted nor crossed. A voxel cap bounds the work: at the cap the grow stops, keeps
//! what it has as one edit and says so.
//!
//! [`plan_grow`] works the region out without writing it and [`GrowPlan::apply`] writes it:
//! the desktop does both at once ([`grow_from_seed`]); the browser page, whose primary values
//! arrive brick by brick, drops a plan that met a brick not yet resident and plans again once
//! it is (web/src/segment_values.rs, tested against this grow in
//! web/tests/browser/segment_values.rs).

use std::sync::atomic::AtomicBool;

use crate::intensity::{Intensity, IntensityBricks, ValueRange};
use crate::layer::LabelLayer;
use crate::tools::flood::{Flood, FloodRegion, FloodWork};
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

/// A grow worked out on a layer and not yet written: the region and the range it took.
/// Splitting the work from the write lets a caller whose primary values are not all at hand
/// (the browser page, reading bricks as they arrive) discard a grow that met a missing brick
/// and run it again once the brick is in, without ever touching the layer or its history.
pub struct GrowPlan {
    region: FloodRegion,
    range: ValueRange,
    label: Label,
}

impl GrowPlan {
    /// The value range the region was grown in.
    pub fn range(&self) -> ValueRange {
        self.range
    }

    /// Voxels in the region.
    pub fn voxels(&self) -> u64 {
        self.region.voxels
    }

    /// Whether the cap stopped the grow with more to take.
    pub fn stopped_at_cap(&self) -> bool {
        self.region.stopped_at_cap
    }

    /// Writes the region as one edit into `layer`, the layer it was planned on (unchanged
    /// since).
    pub fn apply(self, layer: &mut LabelLayer) -> Result<Outcome, SegmentError> {
        let edit = layer.edit("Grow from seed", |w| self.region.write(w, self.label))?;
        Ok(Outcome {
            edit,
            voxels: self.region.voxels,
            stopped_at_cap: self.region.stopped_at_cap,
        })
    }
}

/// Works out the grow of `label` from `seed` on `layer` without writing it. `progress(voxels)`
/// is called as it goes; setting `cancel` ends it with [`SegmentError::Cancelled`].
#[allow(clippy::too_many_arguments)] // each is one of the tool's own settings
pub fn plan_grow(
    layer: &LabelLayer,
    intensity: &dyn Intensity,
    seed: [u32; 3],
    label: Label,
    criterion: GrowCriterion,
    max_voxels: u64,
    progress: &mut dyn FnMut(u64),
    cancel: Option<&AtomicBool>,
) -> Result<GrowPlan, SegmentError> {
    let mut planner = GrowPlanner::start(layer, intensity, seed, label, criterion, max_voxels)?;
    planner.step(layer, intensity, None, progress, cancel)?;
    Ok(planner.into_plan())
}

/// [`plan_grow`] in bounded steps, for a caller with one thread (the browser page, which runs
/// a few bricks of the grow each animation frame and draws between them): [`Self::step`]
/// drains at most a given number of bricks. Stepped to the end it gives exactly
/// [`plan_grow`]'s plan (which is this, in one step; checked below with one brick a step).
/// Between steps `layer` must stay as it was (the page plans on a copy) and `intensity` give
/// the same values.
pub struct GrowPlanner {
    work: FloodWork,
    range: ValueRange,
    label: Label,
    max_voxels: u64,
}

impl GrowPlanner {
    /// The range at the seed (read from `intensity`) and the flood's start; nothing grown yet.
    pub fn start(
        layer: &LabelLayer,
        intensity: &dyn Intensity,
        seed: [u32; 3],
        label: Label,
        criterion: GrowCriterion,
        max_voxels: u64,
    ) -> Result<Self, SegmentError> {
        check_tool_label(layer, label)?;
        layer.get(seed)?;
        let range = grow_range(layer, intensity, seed, criterion)?;
        let segments = layer.segments();
        let any_locked = segments.iter().any(|s| s.locked);
        let flood = Flood {
            layer,
            intensity: Some(intensity),
            axes: &[0, 1, 2],
            max_voxels,
            cancel: None,
        };
        let accept = |l: Label, v: f32| range.contains(v) && !segments.is_locked(l);
        let work = FloodWork::start(&flood, seed, any_locked, true, &accept)?;
        Ok(GrowPlanner {
            work,
            range,
            label,
            max_voxels,
        })
    }

    /// Grows on through at most `max_bricks` bricks (all with `None`); returns whether the
    /// grow is finished. `progress(voxels)` and `cancel` as for [`plan_grow`].
    pub fn step(
        &mut self,
        layer: &LabelLayer,
        intensity: &dyn Intensity,
        max_bricks: Option<usize>,
        progress: &mut dyn FnMut(u64),
        cancel: Option<&AtomicBool>,
    ) -> Result<bool, SegmentError> {
        let segments = layer.segments();
        let range = self.range;
        let flood = Flood {
            layer,
            intensity: Some(intensity),
            axes: &[0, 1, 2],
            max_voxels: self.max_voxels,
            cancel,
        };
        let accept = |l: Label, v: f32| range.contains(v) && !segments.is_locked(l);
        self.work.step(&flood, &accept, max_bricks, progress)
    }

    /// Voxels grown so far.
    pub fn voxels(&self) -> u64 {
        self.work.voxels()
    }

    pub fn finished(&self) -> bool {
        self.work.finished()
    }

    /// The plan (of what was grown so far, if not finished).
    pub fn into_plan(self) -> GrowPlan {
        GrowPlan {
            region: self.work.into_region(),
            range: self.range,
            label: self.label,
        }
    }
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
    let plan = plan_grow(
        layer, intensity, seed, label, criterion, max_voxels, progress, cancel,
    )?;
    let range = plan.range();
    Ok((plan.apply(layer)?, range))
}
