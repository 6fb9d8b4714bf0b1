//! The editable label layer of a viewer session (issue 52): a strata-segment [`LabelLayer`]
//! shown through the overlay (overlay.rs samples it directly, so a stroke shows on the next
//! sampled slice), the brush and eraser of the slice views, and the journal of completed edits.
//!
//! A stroke is applied as it is drawn, one small edit per pointer event (each the swept disc
//! between the last two pointer positions), and becomes one edit when the button is released:
//! that edit is one undo step in the viewer's history (history.rs) and one journal record.
//! Undo and redo are journaled too (as the edit reversed, or again), so replaying the journal
//! gives the layer as the user left it.
//!
//! The journal lives beside the autosaved session (`segmentation.journal`), with a small
//! `segmentation.journal.json` naming the primary store and the label file the layer started
//! from; the next start on the same primary offers to recover it (app.rs).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};

use glam::DVec3;
use strata_render::{ValueMapping, VolumeGeometry};
use strata_segment::history::merge_edits;
use strata_segment::intensity::{Intensity, ValueRange};
use strata_segment::journal::{Journal, Recovery};
use strata_segment::stats::{segment_statistics, Statistics};
use strata_segment::tools::brush::{self, Brush, BrushAction, BrushShape, EraseTarget, SlicePlane};
use strata_segment::tools::grow::{grow_from_seed, GrowCriterion};
use strata_segment::tools::morphology::{
    combine, margin, remove_islands, Islands, LogicalOp, Operand,
};
use strata_segment::tools::Outcome;
use strata_segment::{
    BrickKey, Edit, Label, LabelGrid, LabelLayer, SegmentError, SegmentTable, TableChange,
};
use strata_source::VolumeSource;
use strata_types::BrickId;

/// A label layer shared between the UI (which edits it) and the overlay's reader thread (which
/// samples it); `revision` counts changes so the reader knows a slice it sampled is stale.
pub struct SharedLayer {
    layer: RwLock<LabelLayer>,
    revision: AtomicU64,
}

impl SharedLayer {
    pub fn new(layer: LabelLayer) -> Self {
        SharedLayer {
            layer: RwLock::new(layer),
            revision: AtomicU64::new(0),
        }
    }

    pub fn read(&self) -> RwLockReadGuard<'_, LabelLayer> {
        self.layer.read().unwrap_or_else(|e| e.into_inner())
    }

    /// The layer for a change; the revision moves on when the guard is taken, so a reader that
    /// sampled before it sees its slice as stale.
    pub(crate) fn write(&self) -> RwLockWriteGuard<'_, LabelLayer> {
        let guard = self.layer.write().unwrap_or_else(|e| e.into_inner());
        self.revision.fetch_add(1, Ordering::AcqRel);
        guard
    }

    pub fn revision(&self) -> u64 {
        self.revision.load(Ordering::Acquire)
    }

    pub fn geometry(&self) -> VolumeGeometry {
        self.read().grid().geometry().clone()
    }
}

/// The tool the left button uses on a slice view: the Segment section's, shared with the
/// browser page (strata-viewer-ui's segment_panel).
pub use strata_viewer_ui::segment_panel::SegmentTool;
use strata_viewer_ui::segment_panel::ValueSettings;

/// Most voxels one slice fill takes (a 4096² slice); beyond it the fill stops, keeping what it
/// took.
pub const FILL_MAX_VOXELS: u64 = 1 << 24;

/// A region growing running on its own thread, on a clone of the layer.
struct GrowJob {
    thread: std::thread::JoinHandle<Result<(Outcome, ValueRange), SegmentError>>,
    progress: Arc<AtomicU64>,
    cancel: Arc<AtomicBool>,
}

/// The one-click operations of the panel, on the active segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Operation {
    /// Interpolate the slices between drawn ones along the plane's normal.
    FillBetween(SlicePlane),
    Islands(Islands),
    /// Grow (> 0) or shrink (< 0) by this many mm.
    Margin(f64),
    /// The active segment combined with another.
    Combine(LogicalOp, Label),
}

/// The file formats Save As writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SaveFormat {
    Nifti,
    DicomSeg,
    /// `labels/segmentation` inside the chosen OME-Zarr image folder.
    OmeZarr,
}

impl SaveFormat {
    pub const ALL: [SaveFormat; 3] = [SaveFormat::Nifti, SaveFormat::DicomSeg, SaveFormat::OmeZarr];

    pub fn label(self) -> &'static str {
        match self {
            SaveFormat::Nifti => "NIfTI label map",
            SaveFormat::DicomSeg => "DICOM SEG",
            SaveFormat::OmeZarr => "OME-Zarr labels",
        }
    }

    pub fn default_name(self) -> &'static str {
        match self {
            SaveFormat::Nifti => "segmentation.nii.gz",
            SaveFormat::DicomSeg => "segmentation.dcm",
            SaveFormat::OmeZarr => "image.zarr",
        }
    }
}

/// Writes `layer` to `path` as `format`; the file replaces an earlier one only once complete.
pub fn save_layer(
    layer: &LabelLayer,
    path: &Path,
    format: SaveFormat,
) -> Result<PathBuf, SegmentError> {
    use strata_segment::io;
    match format {
        SaveFormat::Nifti => io::write_nifti(layer, path).map(|()| path.to_path_buf()),
        SaveFormat::DicomSeg => {
            io::write_dicom_seg(layer, path, &io::SegOptions::default()).map(|_| path.to_path_buf())
        }
        SaveFormat::OmeZarr => io::write_omezarr_labels(layer, path, "segmentation"),
    }
}

/// A stroke being drawn: its plane, the pointer positions so far (LPS mm) and the small edits
/// already applied.
struct StrokeInProgress {
    /// A disc in a view's plane (the slice views) or a ball (the 3D view).
    shape: BrushShape,
    action: BrushAction,
    positions: Vec<DVec3>,
    edits: Vec<Edit>,
}

/// Where the journal and its note live: beside the autosaved session of `data_folder`
/// (`last-session.json`, session_restore.rs), i.e. beside the data folder.
pub fn journal_path(data_folder: &Path) -> PathBuf {
    data_folder
        .parent()
        .unwrap_or(data_folder)
        .join("segmentation.journal")
}

/// The note beside a journal: what its edits apply to.
pub fn note_path(journal: &Path) -> PathBuf {
    let mut name = journal.as_os_str().to_owned();
    name.push(".json");
    PathBuf::from(name)
}

/// What the journal's edits apply to.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct JournalNote {
    /// The primary store the layer was drawn over.
    pub primary: PathBuf,
    /// The label file the layer started from; `None` for a new, empty segmentation.
    pub base: Option<PathBuf>,
}

/// Why the segmentation journal or its note could not be opened, read or written. The
/// messages name the file and the problem.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    /// The note beside a journal is not the JSON this viewer writes.
    #[error("{}: not a journal note: {source}", path.display())]
    BadNote {
        path: PathBuf,
        source: serde_json::Error,
    },
    /// A file or folder of the journal could not be read, created or removed.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The note could not be encoded (it holds only paths, so this is not expected).
    #[error("{0}")]
    EncodeNote(serde_json::Error),
    /// The note could not be written.
    #[error("journal note: {0}")]
    WriteNote(SegmentError),
    /// The journal itself could not be opened or recovered (strata-segment says why).
    #[error("{0}")]
    Journal(SegmentError),
}

/// A journal left by an earlier session with edits in it, offered for recovery.
pub struct PendingRecovery {
    pub journal: PathBuf,
    pub note: JournalNote,
    pub recovery: Recovery,
}

impl PendingRecovery {
    /// The journal beside the session of `data_folder`, if it holds edits made over `primary`.
    /// A journal that cannot be read at all is reported, not offered.
    pub fn find(data_folder: &Path, primary: &Path) -> Result<Option<Self>, JournalError> {
        let journal = journal_path(data_folder);
        if !journal.exists() {
            return Ok(None);
        }
        let note_file = note_path(&journal);
        let note: JournalNote = match std::fs::read(&note_file) {
            Ok(bytes) => {
                serde_json::from_slice(&bytes).map_err(|source| JournalError::BadNote {
                    path: note_file.clone(),
                    source,
                })?
            }
            Err(source) => {
                return Err(JournalError::Io {
                    path: note_file,
                    source,
                })
            }
        };
        if note.primary != primary {
            return Ok(None);
        }
        let recovery = strata_segment::journal::recover(&journal).map_err(JournalError::Journal)?;
        if recovery.edits.is_empty() {
            return Ok(None);
        }
        Ok(Some(PendingRecovery {
            journal,
            note,
            recovery,
        }))
    }

    /// Rebuilds the layer: the base (empty on the primary's grid, or the label file), then
    /// every recovered edit in order.
    pub fn layer(&self, primary: &VolumeGeometry) -> Result<LabelLayer, SegmentError> {
        let mut layer = match &self.note.base {
            Some(file) => strata_segment::io::load_label_file(file)?,
            None => LabelLayer::new_empty(primary.clone())?,
        };
        if layer.grid().geometry() != &self.recovery.geometry {
            return Err(SegmentError::Format {
                path: self.journal.clone(),
                message: "the journal was written for another label grid than its base now has"
                    .into(),
            });
        }
        self.recovery.replay_onto(&mut layer);
        Ok(layer)
    }

    /// Removes the journal and its note (the user discarded the edits).
    pub fn discard(&self) -> std::io::Result<()> {
        std::fs::remove_file(&self.journal)?;
        match std::fs::remove_file(note_path(&self.journal)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

/// The primary's physical values on the label grid, when that grid is the primary's own (a new
/// segmentation): a label brick is exactly the store's level-0 brick core.
pub struct PrimaryIntensity {
    store: Arc<dyn VolumeSource>,
    mapping: ValueMapping,
}

impl Intensity for PrimaryIntensity {
    fn value(&self, grid: &LabelGrid, voxel: [u32; 3]) -> Result<f32, SegmentError> {
        let (key, at) = grid.brick_of(voxel);
        let mut out = vec![0.0; strata_segment::LABEL_BRICK_VOXELS];
        self.read_brick(grid, key, &mut out)?;
        Ok(out[at])
    }

    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [f32],
    ) -> Result<(), SegmentError> {
        let stored =
            self.store
                .read_brick(BrickId::new(0, key.0))
                .map_err(|e| SegmentError::BaseRead {
                    brick: key.0,
                    message: format!("primary volume: {e}"),
                })?;
        let mapping = self.mapping;
        strata_segment::intensity::label_brick_from_level0(
            grid,
            key,
            &stored,
            &|s| mapping.physical(f64::from(s)),
            out,
        )
    }
}

/// Distinguishes layers, so an undo step of a layer since removed is never applied to another.
static NEXT_LAYER_ID: AtomicU64 = AtomicU64::new(1);

/// The editable label layer of a session and its tools' settings.
pub struct Segmentation {
    pub id: u64,
    pub layer: Arc<SharedLayer>,
    /// The label file it started from (`None`: a new segmentation).
    pub base_file: Option<PathBuf>,
    journal: Option<Journal>,
    /// The segment table as last journaled (a change is journaled once the gesture ends).
    journaled_segments: SegmentTable,
    /// The primary store (the journal's note names it).
    primary_path: PathBuf,
    /// Records written to the journal so far, and how many there were when the running save
    /// copied the layer: a save that holds every journaled record restarts the journal.
    journaled_records: u64,
    records_at_save: u64,
    /// The primary's values, for a brush limited to a value range (only on the primary's grid).
    intensity: Option<Arc<dyn Intensity>>,
    pub tool: SegmentTool,
    pub diameter_mm: f64,
    /// The value range (paint only where the primary's value lies in it, when enabled) and
    /// region growing's settings: the shared panel's (strata-viewer-ui's segment_panel).
    pub values: ValueSettings,
    /// The segment the brush paints.
    pub active: Label,
    stroke: Option<StrokeInProgress>,
    /// The pointer positions (LPS mm) of the last completed stroke, as applied (tests, status).
    pub last_stroke: Vec<DVec3>,
    /// The last tool or journal error, shown in the panel until the next success.
    pub error: Option<String>,
    /// Completed edits not yet in the viewer's history (app.rs moves them there each frame).
    completed: Vec<Edit>,
    /// The statistics being computed on their own thread.
    stats_job: Option<std::thread::JoinHandle<Result<Statistics, SegmentError>>>,
    /// The last statistics computed (or why they could not be).
    pub stats: Option<Result<Statistics, String>>,
    grow_job: Option<GrowJob>,
    /// What the last tool said that is not an error (a grow stopped at its cap, cancelled).
    pub notice: Option<String>,
    /// A save running on its own thread, and the last save's file or error.
    save_job: Option<std::thread::JoinHandle<Result<PathBuf, SegmentError>>>,
    pub saved: Option<Result<PathBuf, String>>,
    /// The plane of the last stroke (fill between slices interpolates along its normal).
    pub last_plane: SlicePlane,
}

impl Segmentation {
    /// A layer ready for editing, journaling to `journal` (a new journal: any earlier one there
    /// is replaced, its edits having been recovered or discarded).
    pub fn start(
        layer: LabelLayer,
        base_file: Option<PathBuf>,
        primary: (&Path, &VolumeGeometry, &Arc<dyn VolumeSource>, ValueMapping),
        journal: Option<&Path>,
        fresh_journal: bool,
    ) -> Self {
        let (primary_path, primary_geometry, store, mapping) = primary;
        let geometry = layer.grid().geometry().clone();
        let intensity: Option<Arc<dyn Intensity>> = (geometry == *primary_geometry).then(|| {
            Arc::new(PrimaryIntensity {
                store: store.clone(),
                mapping,
            }) as Arc<dyn Intensity>
        });
        let mut error = None;
        let journal = journal.and_then(|path| {
            let opened = open_journal(
                path,
                &geometry,
                &JournalNote {
                    primary: primary_path.to_path_buf(),
                    base: base_file.clone(),
                },
                fresh_journal,
            );
            opened.map_err(|e| error = Some(e.to_string())).ok()
        });
        let segments = layer.segments().clone();
        let active = segments.iter().next().map_or(0, |s| s.value);
        let mut seg = Segmentation {
            id: NEXT_LAYER_ID.fetch_add(1, Ordering::Relaxed),
            layer: Arc::new(SharedLayer::new(layer)),
            base_file,
            journal,
            journaled_segments: SegmentTable::new(),
            primary_path: primary_path.to_path_buf(),
            journaled_records: 0,
            records_at_save: 0,
            intensity,
            tool: SegmentTool::None,
            diameter_mm: strata_viewer_ui::segment_panel::DEFAULT_BRUSH_DIAMETER_MM,
            values: ValueSettings::default(),
            active,
            stroke: None,
            last_stroke: Vec::new(),
            error,
            completed: Vec::new(),
            stats_job: None,
            stats: None,
            grow_job: None,
            notice: None,
            save_job: None,
            saved: None,
            last_plane: SlicePlane::Axial,
        };
        seg.journal_segments_if_changed();
        seg
    }

    pub fn segments(&self) -> SegmentTable {
        self.layer.read().segments().clone()
    }

    /// Changes the segment table (panel edits); journaled by [`Self::journal_segments_if_changed`].
    pub fn with_segments<T>(&self, f: impl FnOnce(&mut SegmentTable) -> T) -> T {
        f(self.layer.write().segments_mut())
    }

    /// Adds a segment named after its value and makes it the active one.
    pub fn add_segment(&mut self) {
        let added = self.with_segments(|t| {
            let name = format!("Segment {}", t.len() + 1);
            t.add(name)
        });
        match added {
            Ok(value) => self.active = value,
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// Removes a segment: its voxels become background and its entry leaves the table, as one
    /// edit (the undo brings back the voxels, the name and the colour).
    pub fn remove_segment(&mut self, value: Label) {
        let result = self.layer.write().remove_segment(value);
        match result {
            Ok(edit) => {
                self.journal(&edit);
                self.completed.push(edit);
                if self.active == value {
                    self.active = self.segments().iter().next().map_or(0, |s| s.value);
                }
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// Journals the segment table when it differs from the last journaled one.
    pub fn journal_segments_if_changed(&mut self) {
        let now = self.segments();
        if now == self.journaled_segments {
            return;
        }
        if let Some(j) = self.journal.as_mut() {
            self.journaled_records += 1;
            if let Err(e) = j.append_segments(&now) {
                self.error = Some(format!("journal: {e} (edits are kept in memory)"));
            }
        }
        self.journaled_segments = now;
    }

    pub fn journal_file(&self) -> Option<&Path> {
        self.journal.as_ref().map(|j| j.path())
    }

    /// The brush as the panel sets it, as a disc in `plane`.
    pub fn brush(&self, plane: SlicePlane) -> Result<Brush, SegmentError> {
        self.brush_shaped(BrushShape::Disc(plane))
    }

    /// The brush with the current size and range, as `shape`.
    pub fn brush_shaped(&self, shape: BrushShape) -> Result<Brush, SegmentError> {
        let value_range = if self.values.limit_to_range {
            Some(ValueRange::new(self.values.range.0, self.values.range.1)?)
        } else {
            None
        };
        Ok(Brush {
            shape,
            diameter_mm: self.diameter_mm,
            value_range,
        })
    }

    /// The pointer is down (or moved while down) at `position_lps` on `plane`: the stroke
    /// starts there or is swept on to it, shown at once.
    pub fn stroke_to(&mut self, plane: SlicePlane, position_lps: DVec3) {
        self.stroke_shaped(BrushShape::Disc(plane), position_lps);
    }

    /// The 3D view's brush: a ball of the brush's diameter at `position_lps` (the surface point
    /// picked under the pointer), swept on from the last one while the button is down.
    pub fn sphere_stroke_to(&mut self, position_lps: DVec3) {
        self.stroke_shaped(BrushShape::Sphere, position_lps);
    }

    fn stroke_shaped(&mut self, shape: BrushShape, position_lps: DVec3) {
        if self.busy() {
            return;
        }
        let stroke = self.stroke.get_or_insert_with(|| StrokeInProgress {
            shape,
            action: match self.tool {
                SegmentTool::Eraser => BrushAction::Erase(EraseTarget::AnyUnlocked),
                _ => BrushAction::Paint(self.active),
            },
            positions: Vec::new(),
            edits: Vec::new(),
        });
        let from = stroke.positions.last().copied();
        if from == Some(position_lps) {
            return;
        }
        stroke.positions.push(position_lps);
        let (shape, action) = (stroke.shape, stroke.action);
        // The disc swept from the last position to this one (the first: a disc there).
        let segment: Vec<DVec3> = from.into_iter().chain([position_lps]).collect();
        let brush = match self.brush_for(shape) {
            Ok(b) => b,
            Err(e) => {
                self.error = Some(e.to_string());
                return;
            }
        };
        let result = {
            let mut layer = self.layer.write();
            brush::stroke(
                &mut layer,
                &brush,
                action,
                &segment,
                self.intensity.as_deref(),
            )
        };
        match result {
            Ok(edit) => {
                if let (Some(edit), Some(s)) = (edit, self.stroke.as_mut()) {
                    s.edits.push(edit);
                }
                self.error = None;
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    fn brush_for(&self, shape: BrushShape) -> Result<Brush, SegmentError> {
        if self.values.limit_to_range && self.intensity.is_none() {
            return Err(SegmentError::BadParameter(
                "a value range needs the labels on the primary's own grid".into(),
            ));
        }
        self.brush_shaped(shape)
    }

    /// The button was released: the stroke becomes one edit, journaled, and waits for the
    /// history ([`Self::take_completed`]).
    pub fn end_stroke(&mut self) {
        let Some(stroke) = self.stroke.take() else {
            return;
        };
        let name = match stroke.action {
            BrushAction::Paint(_) => "Brush",
            BrushAction::Erase(_) => "Eraser",
        };
        self.last_stroke = stroke.positions;
        if let BrushShape::Disc(plane) = stroke.shape {
            // Fill between slices interpolates along the last disc's plane; a ball has none.
            self.last_plane = plane;
        }
        if let Some(edit) = merge_edits(name, stroke.edits) {
            self.journal(&edit);
            self.completed.push(edit);
        }
    }

    /// The edits completed since the last call, for the history.
    pub fn take_completed(&mut self) -> Vec<Edit> {
        std::mem::take(&mut self.completed)
    }

    pub fn stroke_in_progress(&self) -> bool {
        self.stroke.is_some()
    }

    fn journal(&mut self, edit: &Edit) {
        self.journal_segments_if_changed();
        if let Some(j) = self.journal.as_mut() {
            self.journaled_records += 1;
            if let Err(e) = j.append(edit) {
                self.error = Some(format!("journal: {e} (edits are kept in memory)"));
            }
        }
    }

    /// Undo: the layer as before `edit`, journaled as the edit reversed.
    pub fn revert(&mut self, edit: &Edit) {
        self.layer.write().revert(edit);
        let reversed = Edit {
            name: format!("Undo {}", edit.name),
            changes: edit
                .changes
                .iter()
                .map(|c| strata_segment::BrickChange {
                    key: c.key,
                    before: c.after.clone(),
                    after: c.before.clone(),
                })
                .collect(),
            table: edit.table.as_ref().map(TableChange::reversed),
        };
        self.journal(&reversed);
    }

    /// Redo: `edit` again, journaled again.
    pub fn reapply(&mut self, edit: &Edit) {
        self.layer.write().apply(edit);
        self.journal(edit);
    }

    /// A grow is running (the layer's other tools wait for it: its edit is made on a clone).
    pub fn busy(&self) -> bool {
        self.grow_job.is_some()
    }

    /// A completed tool edit (already on the layer): journaled and handed to the history.
    fn finish(&mut self, edit: Option<Edit>) {
        if let Some(edit) = edit {
            self.journal(&edit);
            self.completed.push(edit);
        }
    }

    /// The label-grid voxel nearest to `position_lps`, if it lies in the grid.
    fn voxel_at(&self, position_lps: DVec3) -> Option<[u32; 3]> {
        let layer = self.layer.read();
        let index = layer.grid().index_from_patient(position_lps).round();
        let v = [index.x, index.y, index.z].map(|c| c as i64);
        layer.grid().contains(v).then(|| v.map(|c| c as u32))
    }

    /// A click with the fill or grow tool at `position_lps` on `plane`.
    pub fn click_at(
        &mut self,
        plane: SlicePlane,
        position_lps: DVec3,
        repaint: super::sync::Repaint,
    ) {
        if self.busy() {
            return;
        }
        let Some(seed) = self.voxel_at(position_lps) else {
            self.error = Some("the click is outside the label grid".into());
            return;
        };
        match self.tool {
            SegmentTool::Fill => {
                let range = match self.value_range() {
                    Ok(r) => r,
                    Err(e) => {
                        self.error = Some(e.to_string());
                        return;
                    }
                };
                let intensity = self.intensity.clone();
                let result = strata_segment::tools::fill::fill_in_slice(
                    &mut self.layer.write(),
                    &plane,
                    seed,
                    self.active,
                    range,
                    intensity.as_deref(),
                    FILL_MAX_VOXELS,
                );
                self.take_outcome(result);
            }
            SegmentTool::Grow => self.start_grow(seed, repaint),
            _ => {}
        }
    }

    fn value_range(&self) -> Result<Option<ValueRange>, SegmentError> {
        if !self.values.limit_to_range {
            return Ok(None);
        }
        if self.intensity.is_none() {
            return Err(SegmentError::BadParameter(
                "a value range needs the labels on the primary's own grid".into(),
            ));
        }
        ValueRange::new(self.values.range.0, self.values.range.1).map(Some)
    }

    fn take_outcome(&mut self, result: Result<Outcome, SegmentError>) {
        match result {
            Ok(outcome) => {
                self.error = None;
                self.notice = outcome.stopped_at_cap.then(|| {
                    format!(
                        "stopped at {} voxels, the cap; what it took is kept",
                        outcome.voxels
                    )
                });
                self.finish(outcome.edit);
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// Grows the active segment from `seed` on a named thread, on a clone of the layer; the
    /// edit is applied when it ends ([`Self::poll_grow`]).
    pub fn start_grow(&mut self, seed: [u32; 3], repaint: super::sync::Repaint) {
        let Some(intensity) = self.intensity.clone() else {
            self.error = Some("region growing needs the labels on the primary's own grid".into());
            return;
        };
        let criterion = if self.values.grow_by_sigma {
            GrowCriterion::MeanSigma { k: self.values.k }
        } else {
            match ValueRange::new(self.values.range.0, self.values.range.1) {
                Ok(r) => GrowCriterion::Range(r),
                Err(e) => {
                    self.error = Some(e.to_string());
                    return;
                }
            }
        };
        let mut copy = self.layer.read().clone();
        let (label, max_voxels) = (self.active, self.values.max_voxels);
        let progress = Arc::new(AtomicU64::new(0));
        let cancel = Arc::new(AtomicBool::new(false));
        let (thread_progress, thread_cancel) = (progress.clone(), cancel.clone());
        let spawned = std::thread::Builder::new()
            .name("strata-segment-grow".into())
            .spawn(move || {
                let mut last_wake = 0u64;
                let result = grow_from_seed(
                    &mut copy,
                    intensity.as_ref(),
                    seed,
                    label,
                    criterion,
                    max_voxels,
                    &mut |n| {
                        thread_progress.store(n, Ordering::Relaxed);
                        // The progress bar moves every million voxels, not every voxel.
                        if n >= last_wake + 1_000_000 {
                            last_wake = n;
                            repaint();
                        }
                    },
                    Some(thread_cancel.as_ref()),
                );
                repaint();
                result
            });
        match spawned {
            Ok(thread) => {
                self.notice = None;
                self.grow_job = Some(GrowJob {
                    thread,
                    progress,
                    cancel,
                })
            }
            Err(e) => self.error = Some(format!("could not start growing: {e}")),
        }
    }

    /// Voxels the running grow has taken so far, and its cap.
    pub fn grow_progress(&self) -> Option<(u64, u64)> {
        self.grow_job
            .as_ref()
            .map(|j| (j.progress.load(Ordering::Relaxed), self.values.max_voxels))
    }

    pub fn cancel_grow(&self) {
        if let Some(j) = &self.grow_job {
            j.cancel.store(true, Ordering::Relaxed);
        }
    }

    /// Takes a finished grow in: its edit goes onto the layer, the journal and the history.
    pub fn poll_grow(&mut self) {
        if !self
            .grow_job
            .as_ref()
            .is_some_and(|j| j.thread.is_finished())
        {
            return;
        }
        let Some(job) = self.grow_job.take() else {
            return;
        };
        match job.thread.join() {
            Ok(Ok((outcome, _range))) => {
                if let Some(edit) = &outcome.edit {
                    self.layer.write().apply(edit);
                }
                self.take_outcome(Ok(outcome));
            }
            Ok(Err(SegmentError::Cancelled)) => {
                self.notice = Some("growing cancelled; nothing changed".into());
            }
            Ok(Err(e)) => self.error = Some(e.to_string()),
            Err(_) => self.error = Some("the growing thread failed".into()),
        }
    }

    /// One of the panel's operations on the active segment, as one edit.
    pub fn operate(&mut self, operation: Operation) {
        if self.busy() {
            return;
        }
        let label = self.active;
        let result = {
            let mut layer = self.layer.write();
            match operation {
                Operation::FillBetween(plane) => {
                    strata_segment::tools::interpolate::fill_between_slices(
                        &mut layer, label, &plane,
                    )
                }
                Operation::Islands(which) => remove_islands(&mut layer, label, which).map(|r| r.0),
                Operation::Margin(mm) => margin(&mut layer, label, mm),
                Operation::Combine(op, other) => {
                    combine(&mut layer, label, op, Operand::Segment(other))
                }
            }
        };
        match result {
            Ok(edit) => {
                self.error = None;
                self.notice = edit.is_none().then(|| "nothing changed".to_string());
                self.finish(edit);
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// Saves a copy of the layer as it is now to `path` on a named thread.
    pub fn start_save(&mut self, path: PathBuf, format: SaveFormat, repaint: super::sync::Repaint) {
        if self.save_job.is_some() {
            return;
        }
        let copy = self.layer.read().clone();
        self.records_at_save = self.journaled_records;
        let spawned = std::thread::Builder::new()
            .name("strata-segment-save".into())
            .spawn(move || {
                let result = save_layer(&copy, &path, format);
                repaint();
                result
            });
        match spawned {
            Ok(handle) => self.save_job = Some(handle),
            Err(e) => self.saved = Some(Err(format!("could not start saving: {e}"))),
        }
    }

    pub fn saving(&self) -> bool {
        self.save_job.is_some()
    }

    pub fn poll_save(&mut self) {
        if !self.save_job.as_ref().is_some_and(|h| h.is_finished()) {
            return;
        }
        if let Some(handle) = self.save_job.take() {
            let saved = match handle.join() {
                Ok(result) => result.map_err(|e| e.to_string()),
                Err(_) => Err("the saving thread failed".into()),
            };
            if let Ok(file) = &saved {
                if self.journaled_records == self.records_at_save {
                    self.restart_journal_on(file);
                }
            }
            self.saved = Some(saved);
        }
    }

    /// The saved file holds every journaled edit: the journal starts again with that file as
    /// its base, so a crash after a save offers only the edits made since (not the saved ones
    /// again, replayed over a base that lacks them). An edit made while the save ran keeps the
    /// old journal, which still replays onto the old base.
    fn restart_journal_on(&mut self, file: &Path) {
        let Some(path) = self.journal.take().map(|j| j.path().to_path_buf()) else {
            return;
        };
        let geometry = self.layer.read().grid().geometry().clone();
        let note = JournalNote {
            primary: self.primary_path.clone(),
            base: Some(file.to_path_buf()),
        };
        match open_journal(&path, &geometry, &note, true) {
            Ok(journal) => {
                self.journal = Some(journal);
                self.base_file = Some(file.to_path_buf());
                self.journaled_records = 0;
                self.records_at_save = 0;
                // The new journal starts with the table (names and colours a label file may
                // not keep).
                self.journaled_segments = SegmentTable::new();
                self.journal_segments_if_changed();
            }
            Err(e) => self.error = Some(format!("journal: {e} (edits are kept in memory)")),
        }
    }

    /// Starts computing every segment's statistics (voxels, mL, the primary's values under
    /// it) on a named thread; `repaint` wakes the UI when they are ready.
    pub fn start_statistics(&mut self, repaint: super::sync::Repaint) {
        if self.stats_job.is_some() {
            return;
        }
        let layer = self.layer.clone();
        let intensity = self.intensity.clone();
        let spawned = std::thread::Builder::new()
            .name("strata-segment-stats".into())
            .spawn(move || {
                let result =
                    segment_statistics(&layer.read(), intensity.as_deref(), None, &mut |_, _| {});
                repaint();
                result
            });
        match spawned {
            Ok(handle) => self.stats_job = Some(handle),
            Err(e) => self.stats = Some(Err(format!("could not start: {e}"))),
        }
    }

    pub fn statistics_running(&self) -> bool {
        self.stats_job.is_some()
    }

    /// Takes finished statistics in.
    pub fn poll_statistics(&mut self) {
        if !self.stats_job.as_ref().is_some_and(|h| h.is_finished()) {
            return;
        }
        if let Some(handle) = self.stats_job.take() {
            self.stats = Some(match handle.join() {
                Ok(result) => result.map_err(|e| e.to_string()),
                Err(_) => Err("the statistics thread failed".into()),
            });
        }
    }

    /// The voxels a brush of the current size covers at `position_lps` in `plane` (the cursor
    /// outline the slice view could draw; tests compare strokes with it).
    pub fn footprint(&self, plane: SlicePlane, position_lps: DVec3) -> Vec<[u32; 3]> {
        let layer = self.layer.read();
        self.brush(plane)
            .and_then(|b| brush::footprint(layer.grid(), &b, position_lps, &plane))
            .unwrap_or_default()
    }
}

/// Opens (or, `fresh`, re-creates) the journal at `path` and writes its note.
fn open_journal(
    path: &Path,
    geometry: &VolumeGeometry,
    note: &JournalNote,
    fresh: bool,
) -> Result<Journal, JournalError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|source| JournalError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    if fresh {
        if let Err(source) = std::fs::remove_file(path) {
            if source.kind() != std::io::ErrorKind::NotFound {
                return Err(JournalError::Io {
                    path: path.to_path_buf(),
                    source,
                });
            }
        }
    }
    let note_file = note_path(path);
    let bytes = serde_json::to_vec_pretty(note).map_err(JournalError::EncodeNote)?;
    strata_segment::io::atomic::write_file_atomically(&note_file, |out| {
        out.write_all(&bytes).map_err(|e| SegmentError::Io {
            path: note_file.clone(),
            source: e,
        })
    })
    .map_err(JournalError::WriteNote)?;
    let (journal, _) = Journal::open_or_create(path, geometry).map_err(JournalError::Journal)?;
    Ok(journal)
}

/// The brush plane of a slice view: the label grid's index plane with the same normal when the
/// labels lie on the primary's grid, else the view's plane through `centre_lps` (oblique to
/// the labels' own grid).
pub fn plane_for_view(
    normal_axis: usize,
    across_axis: usize,
    down_axis: usize,
    primary: &VolumeGeometry,
    labels: &VolumeGeometry,
    centre_lps: DVec3,
) -> SlicePlane {
    if primary == labels {
        return match normal_axis {
            0 => SlicePlane::Sagittal,
            1 => SlicePlane::Coronal,
            _ => SlicePlane::Axial,
        };
    }
    SlicePlane::Oblique {
        centre_lps,
        u: DVec3::from(primary.direction[across_axis]).normalize_or_zero(),
        v: DVec3::from(primary.direction[down_axis]).normalize_or_zero(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A journal whose note is missing or damaged is reported (never offered, never a panic),
    /// the message naming the note and the problem; without a journal nothing is offered.
    #[test]
    fn a_journal_whose_note_is_missing_or_not_json_is_reported_naming_the_note() {
        let dir = tempfile::tempdir().expect("temp dir");
        let data_folder = dir.path().join("imported");
        let primary = dir.path().join("primary.strata");
        let journal = journal_path(&data_folder);
        let note = note_path(&journal);
        assert!(matches!(
            PendingRecovery::find(&data_folder, &primary),
            Ok(None)
        ));
        std::fs::write(&journal, b"not a journal").expect("writing the journal");
        let missing = PendingRecovery::find(&data_folder, &primary)
            .err()
            .expect("a journal without its note is an error");
        assert!(matches!(missing, JournalError::Io { .. }), "{missing:?}");
        assert!(
            missing
                .to_string()
                .starts_with(&format!("{}: ", note.display())),
            "{missing}"
        );
        std::fs::write(&note, b"{ not json").expect("writing the note");
        let damaged = PendingRecovery::find(&data_folder, &primary)
            .err()
            .expect("a damaged note is an error");
        assert!(
            matches!(damaged, JournalError::BadNote { .. }),
            "{damaged:?}"
        );
        assert!(
            damaged
                .to_string()
                .starts_with(&format!("{}: not a journal note: ", note.display())),
            "{damaged}"
        );
    }
}
