//! Statistics per segment: voxel count, volume, the primary's mean / SD / min / max / median in
//! its physical unit, and the bounding box in LPS mm; as a table and as CSV.
//!
//! One streaming pass brick by brick: only one label brick and one intensity brick are held at
//! a time, plus per segment a running sum (Welford's, so the SD does not cancel) and, for the
//! median, the segment's values. The median is exact: it is the middle of all the segment's
//! values (the mean of the two middle ones for an even count, as numpy's), which needs them all;
//! past [`MEDIAN_MAX_VALUES`] values in all the median is not computed (`None`), so that memory
//! stays bounded, and the other figures still are.

use std::sync::atomic::{AtomicBool, Ordering};

use glam::DVec3;
use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::intensity::Intensity;
use crate::layer::LabelLayer;
use crate::{Label, SegmentError};

/// Most values kept for medians, over all segments (1 GiB of f32).
pub const MEDIAN_MAX_VALUES: usize = 1 << 28;

/// One segment's figures. Value figures are `None` without a primary, or when the segment has no
/// voxel with a finite value.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentStatistics {
    pub label: Label,
    /// The segment's name ("" for a label value in the data that the table does not name).
    pub name: String,
    pub voxels: u64,
    pub volume_ml: f64,
    pub mean: Option<f64>,
    /// Population standard deviation (numpy's default, ddof = 0).
    pub sd: Option<f64>,
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// Exact; `None` also when the values exceeded [`MEDIAN_MAX_VALUES`].
    pub median: Option<f64>,
    /// First and last voxel index along i, j, k.
    pub index_box: Option<([u32; 3], [u32; 3])>,
    /// Smallest and largest L, P, S (mm) of the segment's voxel centres.
    pub lps_box_mm: Option<([f64; 3], [f64; 3])>,
}

/// The statistics of a layer's segments.
#[derive(Clone, Debug, PartialEq)]
pub struct Statistics {
    /// Physical unit of the value figures ("HU"; "" when unknown).
    pub unit: String,
    /// Every segment of the table, then labels found in the data without one, by label value.
    pub segments: Vec<SegmentStatistics>,
}

struct Accumulator {
    voxels: u64,
    values: u64,
    mean: f64,
    m2: f64,
    min: f64,
    max: f64,
    kept: Option<Vec<f32>>,
    index_lo: [u32; 3],
    index_hi: [u32; 3],
    lps_lo: [f64; 3],
    lps_hi: [f64; 3],
}

impl Default for Accumulator {
    /// Empty: the extremes start beyond any value so the first voxel sets them.
    fn default() -> Self {
        Accumulator {
            voxels: 0,
            values: 0,
            mean: 0.0,
            m2: 0.0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            kept: Some(Vec::new()),
            index_lo: [u32::MAX; 3],
            index_hi: [0; 3],
            lps_lo: [f64::INFINITY; 3],
            lps_hi: [f64::NEG_INFINITY; 3],
        }
    }
}

/// Computes every segment's statistics in one pass. `progress(done, total)` counts bricks;
/// `cancel` ends it with [`SegmentError::Cancelled`].
pub fn segment_statistics(
    layer: &LabelLayer,
    intensity: Option<&dyn Intensity>,
    cancel: Option<&AtomicBool>,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<Statistics, SegmentError> {
    let mut pass = StatisticsPass::new(layer);
    while !pass.step(layer, intensity, None, cancel, progress)? {}
    Ok(pass.finish(layer, intensity.map_or("", |i| i.unit())))
}

/// [`segment_statistics`] in bounded steps, for a caller with one thread (the browser page,
/// which reads a few bricks each animation frame and draws between them): [`Self::step`] reads
/// at most a given number of labelled bricks, in the same order (k, then j, then i) as the
/// pass in one go, so the sums, and so the figures, are exactly [`segment_statistics`]'s
/// (which is this, stepped to the end; checked in segment/tests/tools/stats.rs). Between steps
/// the layer and the values must stay as they were.
pub struct StatisticsPass {
    acc: FxHashMap<Label, Accumulator>,
    kept_values: usize,
    values: Vec<f32>,
    /// The next brick, as a linear index (i fastest), and the bricks in all.
    next: u64,
    total: u64,
}

impl StatisticsPass {
    pub fn new(layer: &LabelLayer) -> Self {
        let [bx, by, bz] = layer.grid().bricks();
        StatisticsPass {
            acc: FxHashMap::default(),
            kept_values: 0,
            values: vec![f32::NAN; LABEL_BRICK_VOXELS],
            next: 0,
            total: u64::from(bx) * u64::from(by) * u64::from(bz),
        }
    }

    /// Bricks visited so far and in all.
    pub fn bricks_done(&self) -> (u64, u64) {
        (self.next, self.total)
    }

    /// Reads on through at most `max_labelled` bricks that hold labels (all with `None`; empty
    /// bricks are skipped without counting); returns whether every brick is read.
    /// `progress(done, total)` is called after each row of bricks; `cancel` ends it with
    /// [`SegmentError::Cancelled`] at a row's start.
    pub fn step(
        &mut self,
        layer: &LabelLayer,
        intensity: Option<&dyn Intensity>,
        max_labelled: Option<usize>,
        cancel: Option<&AtomicBool>,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<bool, SegmentError> {
        let grid = layer.grid();
        let dims = grid.dims();
        let [bx, by, _] = grid.bricks();
        let row_bricks = u64::from(bx);
        let b = LABEL_BRICK as usize;
        let linear = grid.geometry().patient_from_index_linear();
        let origin = grid.geometry().origin();
        let mut labelled = 0usize;
        while self.next < self.total {
            if self.next.is_multiple_of(row_bricks)
                && cancel.is_some_and(|c| c.load(Ordering::Relaxed))
            {
                return Err(SegmentError::Cancelled);
            }
            let n = self.next;
            let (i, j, k) = (
                (n % row_bricks) as u32,
                (n / row_bricks % u64::from(by)) as u32,
                (n / (row_bricks * u64::from(by))) as u32,
            );
            let key = BrickKey([i, j, k]);
            let labels = if layer.brick_is_empty(key) {
                None
            } else {
                Some(layer.brick(key)?).filter(|labels| labels.iter().any(|&l| l != 0))
            };
            if let Some(labels) = labels {
                if max_labelled.is_some_and(|max| labelled >= max) {
                    return Ok(false);
                }
                labelled += 1;
                let values = &mut self.values;
                if let Some(intensity) = intensity {
                    intensity.read_brick(grid, key, values)?;
                }
                let o = grid.brick_origin(key);
                let extent = [0, 1, 2].map(|a| (dims[a] - o[a]).min(LABEL_BRICK) as usize);
                for lk in 0..extent[2] {
                    for lj in 0..extent[1] {
                        for li in 0..extent[0] {
                            let at = li + b * (lj + b * lk);
                            let label = labels[at];
                            if label == 0 {
                                continue;
                            }
                            let a = self.acc.entry(label).or_default();
                            let voxel = [o[0] + li as u32, o[1] + lj as u32, o[2] + lk as u32];
                            a.voxels += 1;
                            for (x, &at_x) in voxel.iter().enumerate() {
                                a.index_lo[x] = a.index_lo[x].min(at_x);
                                a.index_hi[x] = a.index_hi[x].max(at_x);
                            }
                            let lps = origin + linear * DVec3::from(voxel.map(f64::from));
                            for x in 0..3 {
                                a.lps_lo[x] = a.lps_lo[x].min(lps[x]);
                                a.lps_hi[x] = a.lps_hi[x].max(lps[x]);
                            }
                            if intensity.is_none() {
                                continue;
                            }
                            let value = values[at];
                            if !value.is_finite() {
                                continue;
                            }
                            let v = f64::from(value);
                            a.values += 1;
                            let delta = v - a.mean;
                            a.mean += delta / a.values as f64;
                            a.m2 += delta * (v - a.mean);
                            a.min = a.min.min(v);
                            a.max = a.max.max(v);
                            if self.kept_values < MEDIAN_MAX_VALUES {
                                if let Some(kept) = a.kept.as_mut() {
                                    kept.push(value);
                                    self.kept_values += 1;
                                }
                            } else {
                                a.kept = None;
                            }
                        }
                    }
                }
            }
            self.next += 1;
            if self.next.is_multiple_of(row_bricks) {
                progress(self.next, self.total);
            }
        }
        Ok(true)
    }

    /// The table, once every brick is read (of the bricks read so far before), its values in
    /// `unit` (the intensity's; "" without one).
    pub fn finish(mut self, layer: &LabelLayer, unit: &str) -> Statistics {
        let grid = layer.grid();
        let voxel_ml = grid.voxel_volume_ml();
        let mut labels: Vec<Label> = layer.segments().iter().map(|s| s.value).collect();
        labels.extend(self.acc.keys().copied());
        labels.sort_unstable();
        labels.dedup();
        let segments = labels
            .into_iter()
            .map(|label| {
                let name = layer
                    .segments()
                    .get(label)
                    .map(|s| s.name.clone())
                    .unwrap_or_default();
                let a = self.acc.remove(&label).unwrap_or_default();
                let has_values = a.values > 0;
                let median = a.kept.filter(|_| has_values).map(|mut kept| {
                    let n = kept.len();
                    let (_, &mut upper, _) = kept.select_nth_unstable_by(n / 2, f32::total_cmp);
                    if n % 2 == 1 {
                        f64::from(upper)
                    } else {
                        // The largest of the lower half, which select_nth left before n / 2.
                        let lower = kept[..n / 2]
                            .iter()
                            .copied()
                            .fold(f32::NEG_INFINITY, f32::max);
                        (f64::from(lower) + f64::from(upper)) / 2.0
                    }
                });
                let present = a.voxels > 0;
                SegmentStatistics {
                    label,
                    name,
                    voxels: a.voxels,
                    volume_ml: a.voxels as f64 * voxel_ml,
                    mean: has_values.then_some(a.mean),
                    sd: has_values.then(|| (a.m2 / a.values as f64).sqrt()),
                    min: has_values.then_some(a.min),
                    max: has_values.then_some(a.max),
                    median,
                    index_box: present.then_some((a.index_lo, a.index_hi)),
                    lps_box_mm: present.then_some((a.lps_lo, a.lps_hi)),
                }
            })
            .collect();
        Statistics {
            unit: unit.to_owned(),
            segments,
        }
    }
}

/// A CSV field: quoted when it must be, and a leading `= + - @` defused so that a spreadsheet
/// does not run a segment's name as a formula.
fn csv_text(s: &str) -> String {
    let s = if s.starts_with(['=', '+', '-', '@']) {
        format!("'{s}")
    } else {
        s.to_owned()
    };
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s
    }
}

fn csv_number(v: Option<f64>) -> String {
    v.map(|v| format!("{v}")).unwrap_or_default()
}

/// The table as CSV (one header line, one line per segment; empty fields where a figure is
/// unknown). Numbers are written in full (shortest round-trip form).
pub fn to_csv(stats: &Statistics) -> String {
    let unit = if stats.unit.is_empty() {
        String::new()
    } else {
        format!(" ({})", stats.unit)
    };
    let mut out = format!(
        "label,name,voxels,volume_ml,mean{unit},sd{unit},min{unit},max{unit},median{unit},\
         min_l_mm,min_p_mm,min_s_mm,max_l_mm,max_p_mm,max_s_mm\n"
    );
    for s in &stats.segments {
        let (lo, hi) = match s.lps_box_mm {
            Some((lo, hi)) => (lo.map(Some), hi.map(Some)),
            None => ([None; 3], [None; 3]),
        };
        let fields: Vec<String> = [
            s.label.to_string(),
            csv_text(&s.name),
            s.voxels.to_string(),
            format!("{}", s.volume_ml),
            csv_number(s.mean),
            csv_number(s.sd),
            csv_number(s.min),
            csv_number(s.max),
            csv_number(s.median),
        ]
        .into_iter()
        .chain(lo.into_iter().chain(hi).map(csv_number))
        .collect();
        out.push_str(&fields.join(","));
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::intensity::DenseIntensity;
    use strata_types::VolumeGeometry;

    #[test]
    fn a_small_layer_gives_hand_computed_figures_and_csv() {
        let dims = [4, 3, 2];
        let g = VolumeGeometry::axis_aligned(dims, [0.5, 2.0, 10.0]);
        let mut layer = LabelLayer::new_empty(g).unwrap();
        let a = layer.segments_mut().add("=liver, left").unwrap();
        layer.segments_mut().add("empty").unwrap();
        layer
            .edit("a", |w| {
                w.set([0, 0, 0], a)?;
                w.set([3, 2, 1], a)?;
                w.set([1, 0, 0], a)?;
                w.set([2, 2, 0], a)?;
                Ok(())
            })
            .unwrap();
        let values: Vec<f32> = (0..24).map(|n| n as f32).collect();
        let intensity = DenseIntensity::new(dims, values, "HU").unwrap();
        let mut calls = 0;
        let s = segment_statistics(&layer, Some(&intensity), None, &mut |_, _| calls += 1).unwrap();
        assert!(calls > 0);
        let first = &s.segments[0];
        // Values at the voxels: 0, 23, 1, 10.
        assert_eq!(first.voxels, 4);
        assert_eq!(first.volume_ml, 4.0 * 10.0 / 1000.0);
        assert_eq!(first.mean, Some(8.5));
        assert_eq!(first.min, Some(0.0));
        assert_eq!(first.max, Some(23.0));
        assert_eq!(first.median, Some(5.5));
        let var = [0.0f64, 23.0, 1.0, 10.0]
            .iter()
            .map(|v| (v - 8.5) * (v - 8.5))
            .sum::<f64>()
            / 4.0;
        assert!((first.sd.unwrap() - var.sqrt()).abs() < 1e-12);
        assert_eq!(first.lps_box_mm, Some(([0.0, 0.0, 0.0], [1.5, 4.0, 10.0])));
        assert_eq!(s.segments[1].voxels, 0);
        assert_eq!(s.segments[1].mean, None);
        let csv = to_csv(&s);
        let lines: Vec<&str> = csv.lines().collect();
        assert!(lines[0].starts_with("label,name,voxels,volume_ml,mean (HU)"));
        assert_eq!(
            lines[1],
            "1,\"'=liver, left\",4,0.04,8.5,9.233092656309694,0,23,5.5,0,0,0,1.5,4,10"
        );
        assert_eq!(lines[2], "2,empty,0,0,,,,,,,,,,,");
    }
}
