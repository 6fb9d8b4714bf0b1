//! The page's segmentation tools that read the primary's values (issue 52 item 7, wasm32
//! only): region growing from a clicked seed, the statistics per segment and the slice fill
//! limited to the brush's value range, the desktop's (strata-segment's `GrowPlanner`, the
//! stepped `plan_grow`; `StatisticsPass`, the stepped `segment_statistics`; `fill_in_slice`;
//! the shared panel's rows from strata-viewer-ui's segment_panel), run out of core over the
//! level-0 bricks resident in the page (primary_values.rs).
//!
//! A job runs over what is resident; if it met bricks that are not, its answer is dropped (a
//! grow's plan is never written: it is planned on a copy of the layer), the bricks are asked
//! for, and it runs again when they have arrived. A grow thus reaches one more ring of bricks
//! each run, and its last run (every brick it read resident) is the native grow exactly; the
//! statistics read only the bricks under labelled label bricks, so their first run names every
//! brick they need and the second completes. A run is spread over animation frames, never one
//! synchronous pass on the page's one thread: strata-segment's resumable `GrowPlanner` drains
//! [`GROW_BRICKS_PER_FRAME`] bricks a frame and its `StatisticsPass` reads
//! [`STATISTICS_BRICKS_PER_FRAME`] labelled bricks a frame, each giving exactly the pass in one
//! go (their tests in segment/tests/tools/), the run's reads gathered over its frames. Between
//! frames the page draws, shows progress (voxels taken or bricks read, bricks still fetching),
//! and Cancel drops the job with the layer unchanged. While a job runs the brush, eraser and
//! fill wait, as on the desktop. A finished grow is one undo step; one stopped at its cap says
//! so and keeps what it took, as on the desktop. A slice fill limited to the brush's value
//! range is a job too: it fills a copy of the layer (the bricks shared) each run and its edit
//! reaches the layer only from a run that read every value it needed, so the page's fill
//! honours the range exactly as the desktop's (`fill_in_slice` with the range) does.
//!
//! For the browser tests (web/tests/browser/segment_values.rs) the canvas carries
//! `data-segment-values` (`job=none|grow|statistics|fill;runs=N`, after a grow
//! `;seed=I,J,K;grown_after_runs=N`, then `;notice=…`) and, once computed,
//! `data-segment-stats` (the statistics as strata-segment's CSV, numbers in full).

use glam::DVec3;
use strata_segment::intensity::{Intensity, ValueRange};
use strata_segment::stats::{to_csv, Statistics, StatisticsPass};
use strata_segment::tools::brush::{self, stroke_voxels, Brush, BrushAction, SlicePlane};
use strata_segment::tools::fill::fill_in_slice;
use strata_segment::tools::grow::{GrowCriterion, GrowPlanner};
use strata_segment::{Edit, Label, LabelLayer, SegmentError};
use strata_viewer_ui::segment_panel::{self, SegmentTool, ValueSettings};

use crate::primary_values::BricksRead;
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
        /// Voxels the run has taken so far, for the progress bar.
        voxels: u64,
        runs: u32,
        /// The run under way (its planning spread over frames).
        run: Option<Run<GrowPlanner>>,
    },
    Statistics {
        runs: u32,
        /// The run under way (its bricks read over frames).
        run: Option<Run<StatisticsPass>>,
    },
    /// A slice fill limited to the brush's value range (the desktop's fill with the range):
    /// run on a copy of the layer until every brick it read is resident, then its edit is
    /// applied to the layer.
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
            Job::Grow { runs, .. } | Job::Statistics { runs, .. } | Job::Fill { runs, .. } => *runs,
        }
    }

    /// Whether a run is under way (it goes on each frame, whatever arrives).
    fn running(&self) -> bool {
        match self {
            Job::Grow { run, .. } => run.is_some(),
            Job::Statistics { run, .. } => run.is_some(),
            Job::Fill { .. } => false,
        }
    }
}

/// Bricks a grow's planning drains per frame: each is a 32³ flood over bit rows plus the
/// conversion of its values, well under a millisecond, so a frame keeps its pace.
pub const GROW_BRICKS_PER_FRAME: usize = 16;
/// Labelled bricks the statistics read per frame (a Welford update per voxel each).
pub const STATISTICS_BRICKS_PER_FRAME: usize = 16;

/// A run of the grow or the statistics spread over frames: the copy of the layer it reads (so
/// an undo meanwhile does not change what it sees; the copy shares the bricks), its resumable
/// work (strata-segment's `GrowPlanner`, `StatisticsPass`) and the bricks it read so far.
struct Run<W> {
    layer: LabelLayer,
    work: W,
    read: BricksRead,
}

/// Adds one frame's reads to a run's, each brick once.
fn merge_read(into: &mut BricksRead, frame: BricksRead) {
    for coords in frame.used {
        if !into.used.contains(&coords) {
            into.used.push(coords);
        }
    }
    for coords in frame.missing {
        if !into.missing.contains(&coords) {
            into.missing.push(coords);
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
            run: None,
        });
        Ok(())
    }

    /// A fill click with the brush's value range: fills the region around `seed` in `plane`'s
    /// slice with `label`, where the primary's value is in `range` (over the next frames).
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
        // A run under way goes on; a new one starts when a brick it lacked arrived (or is
        // resident already: it may have arrived while the last run was still reading).
        if !job.running()
            && job.runs() > 0
            && !primary.take_arrived()
            && primary.still_missing() > 0
        {
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
                run,
            } => {
                if run.is_none() {
                    *runs += 1;
                    let copy = layer.clone();
                    match GrowPlanner::start(
                        &copy,
                        &intensity,
                        *seed,
                        *label,
                        *criterion,
                        *max_voxels,
                    ) {
                        Ok(planner) => {
                            *run = Some(Run {
                                layer: copy,
                                work: planner,
                                read: BricksRead::default(),
                            })
                        }
                        Err(e) => {
                            // The seed's values may be missing yet: only a complete run's
                            // error is the grow's.
                            let read = intensity.read();
                            match primary.finish_run(read) {
                                Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                                Ok(RunVerdict::Complete) => {
                                    self.job = None;
                                    outcome.error = Some(e.to_string());
                                }
                                Err(e) => {
                                    self.job = None;
                                    outcome.error = Some(e.to_string());
                                }
                            }
                            self.end_if_done(primary);
                            return outcome;
                        }
                    }
                }
                let Some(going) = run.as_mut() else {
                    return outcome;
                };
                let stepped = going.work.step(
                    &going.layer,
                    &intensity,
                    Some(GROW_BRICKS_PER_FRAME),
                    &mut |_| {},
                    None,
                );
                *voxels = going.work.voxels();
                let read = intensity.read();
                // Fetched while the run goes on; the run is redone once they are in.
                primary.want(&read.missing);
                merge_read(&mut going.read, read);
                match stepped {
                    Ok(false) => {}
                    Ok(true) => {
                        let Some(done) = run.take() else {
                            return outcome;
                        };
                        match primary.finish_run(done.read) {
                            Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                            Ok(RunVerdict::Complete) => {
                                self.last_grow = Some((*seed, *runs));
                                self.job = None;
                                match done.work.into_plan().apply(layer) {
                                    Ok(grown) => {
                                        if grown.stopped_at_cap {
                                            // The desktop's words.
                                            self.notice = Some(format!(
                                                "stopped at {} voxels, the cap; what it took is \
                                                 kept",
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
                // A run over missing bricks fills too little (they read as NaN): it works on a
                // copy (bricks shared, copied on write) and is dropped unless complete.
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
            Job::Statistics { runs, run } => {
                let going = run.get_or_insert_with(|| {
                    *runs += 1;
                    Run {
                        work: StatisticsPass::new(layer),
                        layer: layer.clone(),
                        read: BricksRead::default(),
                    }
                });
                let stepped = going.work.step(
                    &going.layer,
                    Some(&intensity),
                    Some(STATISTICS_BRICKS_PER_FRAME),
                    None,
                    &mut |_, _| {},
                );
                let unit = intensity.unit().to_owned();
                let read = intensity.read();
                primary.want(&read.missing);
                merge_read(&mut going.read, read);
                match stepped {
                    Ok(false) => {}
                    Ok(true) => {
                        let Some(done) = run.take() else {
                            return outcome;
                        };
                        match primary.finish_run(done.read) {
                            Ok(RunVerdict::Waiting { missing }) => self.missing = missing,
                            Ok(RunVerdict::Complete) => {
                                self.job = None;
                                self.stats = Some(Ok(done.work.finish(&done.layer, &unit)));
                            }
                            Err(e) => {
                                self.job = None;
                                outcome.error = Some(e.to_string());
                            }
                        }
                    }
                    Err(e) => {
                        self.job = None;
                        self.stats = Some(Err(e.to_string()));
                    }
                }
            }
        }
        self.end_if_done(primary);
        outcome
    }

    /// A job that ended stops asking for bricks.
    fn end_if_done(&mut self, primary: &mut PagePrimaryValues) {
        if self.job.is_none() {
            primary.forget_wanted();
            self.missing = 0;
        }
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
            Job::Statistics { run, .. } => {
                let (done, total) = run.as_ref().map_or((0, 1), |r| r.work.bricks_done());
                Some((
                    (done as f64 / total.max(1) as f64) as f32,
                    format!("{done} of {total} bricks read, fetching {fetching}"),
                ))
            }
            Job::Fill { .. } => Some((0.0, format!("fetching {fetching} bricks"))),
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
        values.job = Some(Job::Statistics { runs: 0, run: None });
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
