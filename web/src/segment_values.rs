//! The page's segmentation tools that read the primary's values (issue 52 item 7, wasm32
//! only): region growing from a clicked seed and the statistics per segment, the desktop's
//! (strata-segment's `tools::grow::plan_grow` and `stats::segment_statistics`, the shared
//! panel's rows from strata-viewer-ui's segment_panel), run out of core over the level-0 bricks
//! resident in the page (primary_values.rs).
//!
//! A job runs once over what is resident; if it met bricks that are not, its answer is
//! dropped (a grow's plan is never written: `plan_grow` works on the layer without touching
//! it), the bricks are asked for, and it runs again when one has arrived. A grow thus reaches
//! one more ring of bricks each run, and its last run (every brick it read resident) is the
//! native grow exactly; the statistics read only the bricks under labelled label bricks, so
//! their first run names every brick they need and the second completes. Each run is one
//! synchronous pass on the page's one thread, bounded by the grow's voxel cap and the bricks
//! resident ([`crate::primary_values::PRIMARY_VALUES_CACHE_BYTES`]); between runs the page
//! draws, shows progress (voxels taken, bricks still fetching), and Cancel drops the job with
//! the layer unchanged. A finished grow is one undo step; one stopped at its cap says so and
//! keeps what it took, as on the desktop. A slice fill limited to the brush's value range is
//! a job too: it fills a copy of the layer (the bricks shared) each run and its edit reaches
//! the layer only from a run that read every value it needed, so the page's fill honours the
//! range exactly as the desktop's (`fill_in_slice` with the range) does.
//!
//! For the browser tests (web/tests/browser/segment_values.rs) the canvas carries
//! `data-segment-values` (`job=none|grow|statistics|fill;runs=N`, after a grow
//! `;seed=I,J,K;grown_after_runs=N`, then `;notice=…`) and, once computed,
//! `data-segment-stats` (the statistics as strata-segment's CSV, numbers in full).

use glam::DVec3;
use strata_segment::intensity::ValueRange;
use strata_segment::stats::{segment_statistics, to_csv, Statistics};
use strata_segment::tools::brush::{self, stroke_voxels, Brush, BrushAction, SlicePlane};
use strata_segment::tools::fill::fill_in_slice;
use strata_segment::tools::grow::{plan_grow, GrowCriterion};
use strata_segment::{Edit, Label, LabelLayer, SegmentError};
use strata_viewer_ui::segment_panel::{self, SegmentTool, ValueSettings};

use crate::primary_values_page::{PagePrimaryValues, RunVerdict};

/// Why a value tool did not start.
#[derive(Debug, thiserror::Error)]
pub enum ValueToolError {
    #[error("a grow, the statistics or a fill are still running: wait for them or Cancel")]
    Busy,
    #[error(transparent)]
    Settings(#[from] SegmentError),
}

/// A job waiting for bricks or about to run.
enum Job {
    Grow {
        seed: [u32; 3],
        label: Label,
        criterion: GrowCriterion,
        max_voxels: u64,
        /// Voxels the last (incomplete) run took, for the progress bar.
        voxels: u64,
        runs: u32,
    },
    Statistics {
        runs: u32,
    },
    /// A slice fill limited to the brush's value range (the desktop's fill with the range).
    Fill {
        plane: SlicePlane,
        seed: [u32; 3],
        label: Label,
        range: ValueRange,
        max_voxels: u64,
        runs: u32,
    },
}

impl Job {
    fn runs(&self) -> u32 {
        match self {
            Job::Grow { runs, .. } | Job::Statistics { runs } | Job::Fill { runs, .. } => *runs,
        }
    }
}

/// What a frame of the value tools gave the editor.
#[derive(Default)]
pub struct ValuesOutcome {
    /// A finished grow's edit: one undo step.
    pub edit: Option<Edit>,
    pub error: Option<String>,
}

/// The value tools' settings, the running job and the last statistics.
#[derive(Default)]
pub struct SegmentValues {
    pub settings: ValueSettings,
    job: Option<Job>,
    /// The bricks the job still lacks after its last run.
    missing: usize,
    stats: Option<Result<Statistics, String>>,
    /// What the last job said that is not an error (stopped at its cap, cancelled).
    notice: Option<String>,
    /// The last finished grow's seed and the runs it took (published for the tests).
    last_grow: Option<([u32; 3], u32)>,
}

impl SegmentValues {
    /// Whether a grow or the statistics are under way.
    pub fn busy(&self) -> bool {
        self.job.is_some()
    }

    /// The brush's value range, when limited to one (`Err`: the panel's range is not one).
    pub fn brush_range(&self) -> Result<Option<ValueRange>, SegmentError> {
        let s = self.settings;
        if !s.limit_to_range {
            return Ok(None);
        }
        ValueRange::new(s.range.0, s.range.1).map(Some)
    }

    /// A grow click: grows `label` from `seed` with the panel's settings (over the next frames).
    pub fn start_grow(&mut self, seed: [u32; 3], label: Label) -> Result<(), ValueToolError> {
        if self.busy() {
            return Err(ValueToolError::Busy);
        }
        let s = self.settings;
        let criterion = if s.grow_by_sigma {
            GrowCriterion::MeanSigma { k: s.k }
        } else {
            GrowCriterion::Range(ValueRange::new(s.range.0, s.range.1)?)
        };
        self.notice = None;
        self.job = Some(Job::Grow {
            seed,
            label,
            criterion,
            max_voxels: s.max_voxels,
            voxels: 0,
            runs: 0,
        });
        Ok(())
    }

    /// A fill click with the brush's value range: fills the region around `seed` in `plane`'s
    /// slice with `label` where the primary's value is in `range` (over the next frames).
    pub fn start_fill(
        &mut self,
        plane: SlicePlane,
        seed: [u32; 3],
        label: Label,
        range: ValueRange,
        max_voxels: u64,
    ) -> Result<(), ValueToolError> {
        if self.busy() {
            return Err(ValueToolError::Busy);
        }
        self.notice = None;
        self.job = Some(Job::Fill {
            plane,
            seed,
            label,
            range,
            max_voxels,
            runs: 0,
        });
        Ok(())
    }

    /// One frame: takes the bricks that arrived and, when the job has something new to read,
    /// runs it once more.
    fn step(&mut self, layer: &mut LabelLayer, primary: &mut PagePrimaryValues) -> ValuesOutcome {
        let mut outcome = ValuesOutcome::default();
        let Some(job) = self.job.as_mut() else {
            return outcome;
        };
        if let Some(e) = primary.take_error() {
            self.job = None;
            primary.forget_wanted();
            outcome.error = Some(e);
            return outcome;
        }
        if job.runs() > 0 && !primary.take_arrived() {
            return outcome;
        }
        let intensity = primary.intensity();
        match job {
            Job::Grow {
                seed,
                label,
                criterion,
                max_voxels,
                voxels,
                runs,
            } => {
                *runs += 1;
                let plan = plan_grow(
                    layer,
                    &intensity,
                    *seed,
                    *label,
                    *criterion,
                    *max_voxels,
                    &mut |_| {},
                    None,
                );
                if let Ok(plan) = &plan {
                    *voxels = plan.voxels();
                }
                let read = intensity.read();
                match primary.finish_run(read) {
                    Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                    Ok(RunVerdict::Complete) => {
                        self.last_grow = Some((*seed, *runs));
                        self.job = None;
                        match plan.and_then(|plan| plan.apply(layer)) {
                            Ok(grown) => {
                                if grown.stopped_at_cap {
                                    // The desktop's words.
                                    self.notice = Some(format!(
                                        "stopped at {} voxels, the cap; what it took is kept",
                                        grown.voxels
                                    ));
                                }
                                outcome.edit = grown.edit;
                            }
                            Err(e) => outcome.error = Some(e.to_string()),
                        }
                    }
                    Err(e) => {
                        self.job = None;
                        outcome.error = Some(e.to_string());
                    }
                }
            }
            Job::Fill {
                plane,
                seed,
                label,
                range,
                max_voxels,
                runs,
            } => {
                *runs += 1;
                // A run over missing bricks fills too little (their values read as NaN, out of
                // any range): it fills a copy (bricks shared, copied on write), dropped unless
                // the run read every value it needed.
                let mut trial = layer.clone();
                let filled = fill_in_slice(
                    &mut trial,
                    plane,
                    *seed,
                    *label,
                    Some(*range),
                    Some(&intensity),
                    *max_voxels,
                );
                let read = intensity.read();
                match primary.finish_run(read) {
                    Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                    Ok(RunVerdict::Complete) => {
                        self.job = None;
                        match filled {
                            Ok(filled) => {
                                if filled.stopped_at_cap {
                                    // The desktop's words.
                                    self.notice = Some(format!(
                                        "stopped at {} voxels, the cap; what it took is kept",
                                        filled.voxels
                                    ));
                                }
                                if let Some(edit) = &filled.edit {
                                    // The copy was taken this frame: the layer is as it was.
                                    layer.apply(edit);
                                }
                                outcome.edit = filled.edit;
                            }
                            Err(e) => outcome.error = Some(e.to_string()),
                        }
                    }
                    Err(e) => {
                        self.job = None;
                        outcome.error = Some(e.to_string());
                    }
                }
            }
            Job::Statistics { runs } => {
                *runs += 1;
                let stats = segment_statistics(layer, Some(&intensity), None, &mut |_, _| {});
                let read = intensity.read();
                match primary.finish_run(read) {
                    Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                    Ok(RunVerdict::Complete) => {
                        self.job = None;
                        self.stats = Some(stats.map_err(|e| e.to_string()));
                    }
                    Err(e) => {
                        self.job = None;
                        outcome.error = Some(e.to_string());
                    }
                }
            }
        }
        if self.job.is_none() {
            primary.forget_wanted();
            self.missing = 0;
        }
        outcome
    }

    fn cancel(&mut self, primary: &mut PagePrimaryValues) {
        if let Some(job) = self.job.take() {
            primary.forget_wanted();
            self.missing = 0;
            self.notice = Some(match job {
                Job::Grow { .. } => "growing cancelled; nothing changed".into(),
                Job::Statistics { .. } => "statistics cancelled".into(),
                Job::Fill { .. } => "fill cancelled; nothing changed".into(),
            });
        }
    }

    /// The progress bar's fraction and text while a job runs.
    fn progress(&self, primary: &PagePrimaryValues) -> Option<(f32, String)> {
        let fetching = primary.still_missing().max(usize::from(self.missing > 0));
        match self.job.as_ref()? {
            Job::Grow {
                voxels, max_voxels, ..
            } => Some((
                (*voxels as f64 / (*max_voxels).max(1) as f64) as f32,
                format!("{voxels} voxels, fetching {fetching} bricks"),
            )),
            Job::Statistics { .. } | Job::Fill { .. } => {
                Some((0.0, format!("fetching {fetching} bricks")))
            }
        }
    }

    /// What `data-segment-values` carries.
    fn figures(&self) -> String {
        let job = match &self.job {
            None => "none",
            Some(Job::Grow { .. }) => "grow",
            Some(Job::Statistics { .. }) => "statistics",
            Some(Job::Fill { .. }) => "fill",
        };
        let runs = self.job.as_ref().map_or(0, Job::runs);
        let mut text = format!("job={job};runs={runs}");
        if let Some((seed, runs)) = self.last_grow {
            text.push_str(&format!(
                ";seed={},{},{};grown_after_runs={runs}",
                seed[0], seed[1], seed[2]
            ));
        }
        // Last, as it may hold any character.
        if let Some(notice) = &self.notice {
            text.push_str(&format!(";notice={notice}"));
        }
        text
    }
}

/// The Segment section's value rows (range, grow settings, progress and Cancel, statistics),
/// then one step of the running job over the primary's resident bricks. `buttons` gets the
/// rectangles the page publishes for its tests (`only-values`, `sigma`, `cancel`,
/// `statistics`, `copy-csv`).
pub fn rows(
    ui: &mut egui::Ui,
    values: &mut SegmentValues,
    tool: SegmentTool,
    layer: &mut LabelLayer,
    primary: Option<&mut PagePrimaryValues>,
    buttons: &mut Vec<(&'static str, egui::Rect)>,
) -> ValuesOutcome {
    buttons.extend(segment_panel::value_rows(ui, tool, &mut values.settings));
    let Some(primary) = primary else {
        ui.label("Region growing, statistics and the value range need the volume's values");
        return ValuesOutcome::default();
    };
    primary.pump(ui.ctx());
    let outcome = values.step(layer, primary);
    if let Some((fraction, text)) = values.progress(primary) {
        let (cancel, rect) = segment_panel::progress_row(ui, fraction, &text);
        buttons.push(("cancel", rect));
        if cancel {
            values.cancel(primary);
        }
        // The job goes on over the next frames, woken by nothing else.
        ui.ctx().request_repaint();
    }
    if let Some(notice) = &values.notice {
        ui.label(notice);
    }
    let stats = segment_panel::statistics_rows(ui, values.busy(), values.stats.as_ref());
    buttons.extend(stats.buttons);
    if stats.compute && !values.busy() {
        values.notice = None;
        values.job = Some(Job::Statistics { runs: 0 });
        ui.ctx().request_repaint();
    }
    if stats.copy_csv {
        if let Some(Ok(table)) = &values.stats {
            ui.ctx().copy_text(to_csv(table));
        }
    }
    crate::canvas_attributes::set("data-segment-values", &values.figures());
    if let Some(Ok(table)) = &values.stats {
        crate::canvas_attributes::set("data-segment-stats", &to_csv(table));
    }
    outcome
}

/// Applies, in order, the queued pieces of a stroke limited to a value range whose bricks are
/// all resident; asks for the bricks of the first that is not, and leaves it and the rest
/// queued. Returns the edits made (one per piece) and an error that ended the queue.
///
/// A piece waits rather than painting what is resident and skipping the rest: the brush's rule
/// is "paint where the value is in the range", and a voxel whose value is not known yet is
/// neither in nor out; painting it later, in order, gives exactly the stroke the desktop
/// paints (which reads its values synchronously), and the release merges the pieces into one
/// undo step once the last is applied.
pub fn apply_queued_strokes(
    layer: &mut LabelLayer,
    action: BrushAction,
    queued: &mut Vec<(Brush, Vec<DVec3>)>,
    primary: &mut PagePrimaryValues,
) -> (Vec<Edit>, Option<String>) {
    let mut edits = Vec::new();
    while let Some((brush, positions)) = queued.first() {
        let grid = layer.grid();
        let bricks: Vec<[u32; 3]> = match stroke_voxels(grid, brush, positions) {
            Ok(voxels) => {
                let mut bricks: Vec<[u32; 3]> =
                    voxels.iter().map(|v| grid.brick_of(*v).0 .0).collect();
                bricks.sort_unstable();
                bricks.dedup();
                bricks
            }
            Err(e) => {
                queued.clear();
                return (edits, Some(e.to_string()));
            }
        };
        if primary.want(&bricks) > 0 {
            break;
        }
        let intensity = primary.intensity();
        let result = brush::stroke(layer, brush, action, positions, Some(&intensity));
        primary.touch(&intensity.read());
        queued.remove(0);
        match result {
            Ok(Some(edit)) => edits.push(edit),
            Ok(None) => {}
            Err(e) => {
                queued.clear();
                return (edits, Some(e.to_string()));
            }
        }
    }
    (edits, None)
}
