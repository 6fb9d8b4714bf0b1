//! Segmentation editing in the page (issue 52 item 7, wasm32 only): the desktop's editing
//! core, shared as code. "New segmentation" makes a strata-segment [`LabelLayer`] on the open
//! volume's grid, in memory; the Segment section is strata-viewer-ui's segment_panel (the
//! desktop's tool row and segment list) with Undo, Redo and Download; the brush, eraser and
//! slice fill of the three slice views are strata-segment's (`tools::brush`, `tools::fill`), a
//! stroke applied as it is drawn (one small edit per pointer event, each the disc swept from
//! the last pointer position, as the desktop's `Segmentation::stroke_to`) and merged into one
//! undo step when the button is released (`history::merge_edits` into a `History`). The labels
//! are drawn over each slice in their segment's colour at the panel's opacity, nearest voxel
//! (labels are never interpolated).
//!
//! The section's operations (fill between slices along the last stroke's plane, islands,
//! margin, union / subtract / intersect) are segment_panel's rows, run on the layer with the
//! desktop's strata-segment functions (`tools::interpolate`, `tools::morphology`) as one undo
//! step each, on the page's one thread: they read only the labels, and their work is bounded by
//! the bricks the page's strokes edited.
//!
//! The tools that read the primary's values (region growing from a clicked seed, the
//! statistics, the brush and eraser limited to a value range) are segment_values.rs's, over the
//! level-0 bricks the page fetches for them (primary_values.rs); a stroke limited to a range
//! is queued piece by piece and applied as the bricks under each piece arrive, its release
//! waiting for the last.
//!
//! Download writes the layer as the NIfTI-1 label map `strata seg export --format nifti`
//! writes (strata-segment's `nifti_map`, the primary's grid and affine) into a Blob, and an
//! anchor with `download=` saves it; Download SEG and Download OME-Zarr save the DICOM SEG
//! and the zipped OME-Zarr labels (segment_downloads.rs).
//!
//! Every completed edit is one step in the page's one history (page_tools.rs, [`SegmentStep`]),
//! in the order made among the view's edits: Ctrl+Z, Ctrl+Shift+Z, Ctrl+Y, the toolbar's and
//! the section's Undo and Redo all walk it, as the desktop's `history.undo(&mut scene,
//! segmentation)`.
//!
//! The labels show in the 3D view too, as the desktop's segmentation does (its layer is its
//! overlay): strata-viewer-ui's `LayerGrid` of the layer at the page's 3D grid bound, which
//! samples again only the grid voxels an edit's bricks reach (a new layer is all background,
//! so nothing is sampled whole), carried by the render request with the segments' colours,
//! visibility and the panel's opacity as its colour table ([`PageSegmentation::request_3d`]).
//!
//! For the browser tests (web/tests/browser/segment.rs) the canvas carries
//! `data-segmentation` (`segments=N;painted=V;checksum=H;undo=U;redo=R;stroke=0|1`, then
//! `;error=…` while the panel shows one; or `none`)
//! and `data-segment-buttons` (`name:x,y,w,h;…` in CSS pixels: new, brush, eraser, fill, the
//! operations' buttons named by `segment_panel::operations`, undo, redo, download,
//! download-seg, download-zarr), each
//! written only when it changes.

use egui::{Color32, Pos2, Rect, TextureHandle, TextureOptions};
use glam::DVec3;
use strata_render::VolumeGeometry;
use strata_segment::history::{merge_edits, History};
use strata_segment::nifti_map::label_map_gz_bytes;
use strata_segment::tools::brush::{self, Brush, BrushAction, BrushShape, EraseTarget, SlicePlane};
use strata_segment::tools::fill::fill_in_slice;
use strata_segment::tools::interpolate::fill_between_slices;
use strata_segment::tools::morphology::{combine, margin, remove_islands, Operand};
use strata_segment::{Edit, Label, LabelLayer, SegmentError, LABEL_BRICK};
use strata_slices::oblique::ObliquePlane;
use strata_slices::{SliceFrame, SliceView};
use strata_viewer_ui::overlay::{segment_labels, OverlayGrids, OverlayKind, OverlayStyle};
use strata_viewer_ui::overlay_3d::{
    grid_dims, lut_for, LayerGrid, Resampled, PAGE_OVERLAY_3D_MAX_VOXELS,
};
use strata_viewer_ui::render_driver::OverlayIn3d;
use strata_viewer_ui::segment_panel::{
    self, OperationSettings, SegmentListChange, SegmentOperation, SegmentTool,
    DEFAULT_BRUSH_DIAMETER_MM, DEFAULT_LABEL_OPACITY,
};
use strata_viewer_ui::slice_canvas::slice_mesh;
use wasm_bindgen::{JsCast, JsValue};

use crate::segment_downloads::{self, SegmentDownload};
use crate::slice_views::SliceViews;

/// Brick images the undo list keeps (before and after, 64 KiB each): about 2000 bricks, well
/// inside a page's memory; the oldest steps go first beyond it.
pub const HISTORY_BYTES: usize = 256 << 20;
/// Most voxels one slice fill takes (a 4096² slice), as on the desktop.
pub const FILL_MAX_VOXELS: u64 = 1 << 24;
/// The file name Download offers.
pub const DOWNLOAD_NAME: &str = "segmentation.nii.gz";

/// A stroke being drawn: its shape (a slice view's disc, the 3D view's ball), action, pointer
/// positions (LPS mm) and the small edits already applied.
struct Stroke {
    shape: BrushShape,
    action: BrushAction,
    positions: Vec<DVec3>,
    edits: Vec<Edit>,
    /// Pieces of a stroke limited to a value range waiting for the primary's bricks under
    /// them, applied in order as they arrive (segment_values.rs `apply_queued_strokes`).
    queued: Vec<(Brush, Vec<DVec3>)>,
    /// The button was released while pieces were queued: the stroke ends once they are in.
    released: bool,
}

/// A view's label image on screen and what it was made from (layer revision, slice, opacity).
struct LabelImage {
    texture: TextureHandle,
    made_from: (u64, i64, u32),
}

/// The labels on the oblique plane: the texture and the layer revision, plane, pixels and
/// opacity it was made from.
struct ObliqueLabelImage {
    texture: TextureHandle,
    made_from: (u64, ObliquePlane, usize, u32),
}

/// The labels in the 3D view: the layer's grid over the primary's index box, updated where the
/// edits since the layer revision it last saw reach, and the grid as last made.
struct Labels3d {
    grids: OverlayGrids,
    grid: LayerGrid,
    revision: Option<u64>,
    resampled: Option<std::sync::Arc<Resampled>>,
}

/// The page's editable label layer and its tools' settings.
pub struct PageSegmentation {
    layer: LabelLayer,
    history: History,
    tool: SegmentTool,
    diameter_mm: f64,
    active: Label,
    opacity: f32,
    operations: OperationSettings,
    /// The plane of the last stroke: fill between slices interpolates along its normal, as on
    /// the desktop.
    last_plane: SlicePlane,
    stroke: Option<Stroke>,
    /// Counts changes to the layer (strokes, undo, redo, segment table), so label images and
    /// the published figures are remade only when it moves.
    revision: u64,
    images: [Option<LabelImage>; 3],
    /// The labels on the oblique view's plane (oblique_view.rs) and what they were made from.
    oblique_image: Option<ObliqueLabelImage>,
    /// The last tool or download error, shown until the next success.
    error: Option<String>,
    /// The object URL of the last download, revoked at the next one (revoking it at once may
    /// cancel a download the browser has not started reading).
    download_url: Option<String>,
    /// The labelled voxels and checksum last counted, and the revision they are of.
    painted_at: Option<(u64, (u64, u64))>,
    /// Region growing, statistics and the value range: the tools that read the primary
    /// (segment_values.rs).
    values: crate::segment_values::SegmentValues,
    /// This layer's place in the page's one history (page_tools.rs, [`SegmentStep`]).
    page_history: PageHistoryLink,
    /// The labels in the 3D view.
    labels_3d: Labels3d,
}

/// A segmentation edit's place among the view's edits in the page's one history (page_tools.rs,
/// strata-viewer-ui's history, as the desktop's `History::push_label_edit`): the edit itself
/// stays in the layer's own history, whose memory is capped by bytes ([`HISTORY_BYTES`]); the
/// step names the layer, so a step of a closed layer is dropped when reached.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SegmentStep {
    layer: u64,
}

/// What the page's history and the layer tell each other once a frame.
#[derive(Debug, Default)]
struct PageHistoryLink {
    /// Distinguishes this layer's steps from a closed one's.
    layer: u64,
    /// Edits pushed onto the layer's history since the page's history took them.
    new_steps: usize,
    /// The section's Undo or Redo, done by the page's history (as Ctrl+Z, Ctrl+Y).
    asked: (bool, bool),
    /// Whether the page's history can undo, redo (the section's buttons).
    page_can: (bool, bool),
}

impl PageSegmentation {
    /// An empty segmentation on the primary's grid with one segment, the active one (as the
    /// desktop's New segmentation).
    pub fn new(primary: &VolumeGeometry) -> Result<Self, SegmentError> {
        let mut layer = LabelLayer::new_empty(primary.clone())?;
        let active = layer.segments_mut().add("Segment 1")?;
        let grids = OverlayGrids {
            primary: primary.clone(),
            primary_level_dims: strata_types::OctreeLayout::new(primary.dims).level_dims,
            overlay: layer.grid().geometry().clone(),
            overlay_mapping: Default::default(),
            kind: OverlayKind::Labels,
        };
        let dims = grid_dims(&grids.primary_level_dims, PAGE_OVERLAY_3D_MAX_VOXELS);
        let labels_3d = Labels3d {
            grids,
            grid: LayerGrid::for_empty_layer(dims),
            revision: None,
            resampled: None,
        };
        Ok(PageSegmentation {
            labels_3d,
            layer,
            history: History::new(HISTORY_BYTES),
            tool: SegmentTool::None,
            diameter_mm: DEFAULT_BRUSH_DIAMETER_MM,
            active,
            opacity: DEFAULT_LABEL_OPACITY,
            operations: OperationSettings::default(),
            last_plane: SlicePlane::Axial,
            stroke: None,
            revision: 0,
            images: [None, None, None],
            oblique_image: None,
            error: None,
            download_url: None,
            painted_at: None,
            values: Default::default(),
            page_history: PageHistoryLink {
                layer: {
                    static LAYERS: std::sync::atomic::AtomicU64 =
                        std::sync::atomic::AtomicU64::new(0);
                    LAYERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
                },
                ..PageHistoryLink::default()
            },
        })
    }

    /// What the 3D view draws of the labels (the render request's): the layer's grid, updated
    /// where the edits since the last call reach, coloured as the slices draw the segments
    /// (colour, shown, the panel's opacity); None until something is painted.
    pub fn request_3d(&mut self) -> Option<OverlayIn3d> {
        if self.layer.edited_brick_count() == 0 {
            return None;
        }
        let labels = &mut self.labels_3d;
        if labels.revision != Some(self.revision) {
            labels.revision = Some(self.revision);
            let updated = labels
                .grid
                .update(&self.layer, &labels.grids)
                .and_then(|changed| match changed || labels.resampled.is_none() {
                    true => labels
                        .grid
                        .resampled()
                        .map(|r| Some(std::sync::Arc::new(r))),
                    false => Ok(None),
                });
            match updated {
                Ok(Some(resampled)) => labels.resampled = Some(resampled),
                Ok(None) => {}
                Err(e) => self.error = Some(format!("the labels in 3D: {e}")),
            }
        }
        let resampled = self.labels_3d.resampled.as_ref()?;
        let (label_table, hidden_labels) = segment_labels(self.layer.segments());
        let style = OverlayStyle {
            opacity: self.opacity,
            hidden_labels,
            ..OverlayStyle::opening(label_table, (0.0, 1.0))
        };
        Some(OverlayIn3d {
            volume: resampled.volume.clone(),
            lut: lut_for(OverlayKind::Labels, &style, &resampled.labels),
        })
    }

    /// Whether the left button on a slice is the tool's (not the crosshair's).
    pub fn paints(&self) -> bool {
        self.tool.paints()
    }

    /// The left button on a slice view with a tool chosen: the desktop's gesture
    /// (viewer/src/slice_view.rs `segment_pointer_input`): a drag is one stroke from the
    /// press, a click a one-point stroke or a fill's seed. `to_lps` maps a screen point to
    /// patient space through the view's slice mapping.
    pub fn pointer(
        &mut self,
        ui: &egui::Ui,
        response: &egui::Response,
        image_rect: Rect,
        to_lps: &dyn Fn(Pos2) -> DVec3,
        plane: SlicePlane,
    ) {
        let primary = egui::PointerButton::Primary;
        if !self.tool.drags() {
            if response.clicked_by(primary) {
                if let Some(pos) = response
                    .interact_pointer_pos()
                    .filter(|p| image_rect.contains(*p))
                {
                    self.fill_at(plane, to_lps(pos));
                }
            }
            return;
        }
        if response.drag_started_by(primary) {
            if let Some(origin) = ui
                .input(|i| i.pointer.press_origin())
                .filter(|p| image_rect.contains(*p))
            {
                self.stroke_to(plane, to_lps(origin));
            }
        }
        if response.dragged_by(primary) && self.stroke.is_some() {
            if let Some(pos) = response.interact_pointer_pos() {
                self.stroke_to(plane, to_lps(pos));
            }
        }
        if response.drag_stopped_by(primary) {
            // The release's own position ends the stroke (a move and the release may arrive
            // in one frame).
            if let Some(pos) = response.interact_pointer_pos() {
                if self.stroke.is_some() {
                    self.stroke_to(plane, to_lps(pos));
                }
            }
            self.end_stroke();
        }
        if response.clicked_by(primary) {
            if let Some(pos) = response
                .interact_pointer_pos()
                .filter(|p| image_rect.contains(*p))
            {
                self.stroke_to(plane, to_lps(pos));
                self.end_stroke();
            }
        }
    }

    /// The stroke starts at `position_lps` or is swept on to it, applied at once.
    fn stroke_to(&mut self, plane: SlicePlane, position_lps: DVec3) {
        self.stroke_shaped(BrushShape::Disc(plane), position_lps);
    }

    /// The tool as the 3D view offers it (fill works within a slice: no 3D form), as on the
    /// desktop.
    pub fn tool_3d(&self) -> SegmentTool {
        self.tool.filter_3d()
    }

    /// The 3D view's brush (segment_3d.rs): a ball of the brush's diameter at `position_lps`,
    /// the surface point picked under the pointer, swept on from the last one while the
    /// button is down (the desktop's `Segmentation::sphere_stroke_to`).
    pub fn sphere_stroke_to(&mut self, position_lps: DVec3) {
        self.stroke_shaped(BrushShape::Sphere, position_lps);
    }

    /// A grow seeded in the 3D view at the picked `position_lps` (the grow is 3D: the plane
    /// is not used), as the desktop's 3D view seeds it.
    pub fn grow_at(&mut self, position_lps: DVec3) {
        if self.tool == SegmentTool::Grow {
            self.fill_at(SlicePlane::Axial, position_lps);
        }
    }

    fn stroke_shaped(&mut self, shape: BrushShape, position_lps: DVec3) {
        if self.values.busy() {
            // A grow, the statistics or a ranged fill are running (segment_values.rs): the
            // tools wait, as on the desktop.
            return;
        }
        let action = match self.tool {
            SegmentTool::Eraser => BrushAction::Erase(EraseTarget::AnyUnlocked),
            _ => BrushAction::Paint(self.active),
        };
        let value_range = match self.values.brush_range() {
            Ok(range) => range,
            Err(e) => {
                self.error = Some(e.to_string());
                return;
            }
        };
        let stroke = self.stroke.get_or_insert_with(|| Stroke {
            shape,
            action,
            positions: Vec::new(),
            edits: Vec::new(),
            queued: Vec::new(),
            released: false,
        });
        let from = stroke.positions.last().copied();
        if from == Some(position_lps) {
            return;
        }
        stroke.positions.push(position_lps);
        let brush = Brush {
            shape: stroke.shape,
            diameter_mm: self.diameter_mm,
            value_range,
        };
        // The disc or ball swept from the last position to this one (the first: one there).
        let segment: Vec<DVec3> = from.into_iter().chain([position_lps]).collect();
        if value_range.is_some() {
            // Applied once the primary's values under it are resident (segment_values.rs).
            stroke.queued.push((brush, segment));
            return;
        }
        match brush::stroke(&mut self.layer, &brush, stroke.action, &segment, None) {
            Ok(edit) => {
                if let Some(edit) = edit {
                    stroke.edits.push(edit);
                    self.revision += 1;
                }
                self.error = None;
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// The button was released: the stroke's edits become one undo step.
    pub fn end_stroke(&mut self) {
        if let Some(stroke) = self.stroke.as_mut().filter(|s| !s.queued.is_empty()) {
            stroke.released = true;
            return;
        }
        let Some(stroke) = self.stroke.take() else {
            return;
        };
        let name = match stroke.action {
            BrushAction::Paint(_) => "Brush",
            BrushAction::Erase(_) => "Eraser",
        };
        if let BrushShape::Disc(plane) = stroke.shape {
            // Fill between slices interpolates along the last disc's plane; a ball has none.
            self.last_plane = plane;
        }
        if let Some(edit) = merge_edits(name, stroke.edits) {
            self.push_step(edit);
        }
    }

    /// One of the section's operations on the active segment, as one undo step (the
    /// desktop's `Segmentation::operate`).
    fn operate(&mut self, operation: SegmentOperation) {
        let label = self.active;
        let layer = &mut self.layer;
        let result = match operation {
            SegmentOperation::FillBetween => fill_between_slices(layer, label, &self.last_plane),
            SegmentOperation::Islands(which) => remove_islands(layer, label, which).map(|r| r.0),
            SegmentOperation::Margin(mm) => margin(layer, label, mm),
            SegmentOperation::Combine(op, other) => {
                combine(layer, label, op, Operand::Segment(other))
            }
        };
        match result {
            Ok(edit) => {
                self.error = None;
                if let Some(edit) = edit {
                    self.push_step(edit);
                    self.revision += 1;
                }
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// A fill click: the closed region around the voxel under it, in the view's slice.
    fn fill_at(&mut self, plane: SlicePlane, position_lps: DVec3) {
        if self.values.busy() && self.tool != SegmentTool::Grow {
            // As the brush: the fill waits for the running job (a grow click says it is busy).
            return;
        }
        let grid = self.layer.grid();
        let index = grid.index_from_patient(position_lps).round();
        let voxel = [index.x, index.y, index.z].map(|c| c as i64);
        if !grid.contains(voxel) {
            self.error = Some("the click is outside the label grid".into());
            return;
        }
        let seed = voxel.map(|c| c as u32);
        if self.tool == SegmentTool::Grow {
            self.error = self
                .values
                .start_grow(seed, self.active)
                .err()
                .map(|e| e.to_string());
            return;
        }
        // Limited to the brush's value range, as on the desktop: the fill reads the primary's
        // values, so it runs over the next frames as their bricks arrive (segment_values.rs).
        let range = match self.values.brush_range() {
            Ok(range) => range,
            Err(e) => {
                self.error = Some(e.to_string());
                return;
            }
        };
        if let Some(range) = range {
            self.error = self
                .values
                .start_fill(plane, seed, self.active, range, FILL_MAX_VOXELS)
                .err()
                .map(|e| e.to_string());
            return;
        }
        let filled = fill_in_slice(
            &mut self.layer,
            &plane,
            seed,
            self.active,
            None,
            None,
            FILL_MAX_VOXELS,
        );
        match filled {
            Ok(outcome) => {
                self.error = None;
                if let Some(edit) = outcome.edit {
                    self.push_step(edit);
                    self.revision += 1;
                }
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// A completed edit (already on the layer) becomes an undo step: in the layer's history,
    /// and in the page's at its next frame.
    fn push_step(&mut self, edit: Edit) {
        // An edit too big for the layer's history empties it: no step to undo.
        if self.history.push(edit) {
            self.page_history.new_steps += 1;
        }
    }

    /// The page's history takes the steps made since it last looked, in the order made.
    pub fn take_new_steps(&mut self) -> Vec<SegmentStep> {
        let n = std::mem::take(&mut self.page_history.new_steps);
        vec![
            SegmentStep {
                layer: self.page_history.layer
            };
            n
        ]
    }

    /// The section's Undo, Redo clicked since the last frame (the page's history does them).
    pub fn take_asked(&mut self) -> (bool, bool) {
        std::mem::take(&mut self.page_history.asked)
    }

    /// What the page's history can do now, for the section's buttons.
    pub fn set_page_history(&mut self, can_undo: bool, can_redo: bool) {
        self.page_history.page_can = (can_undo, can_redo);
    }

    /// The page's history undoes `step`: false if it is another layer's or the layer's history
    /// no longer holds it (dropped for memory), so the page's history goes on to the one before.
    pub fn undo_step(&mut self, step: &SegmentStep) -> bool {
        let undone =
            step.layer == self.page_history.layer && self.history.undo(&mut self.layer).is_some();
        if undone {
            self.revision += 1;
        }
        undone
    }

    /// The page's history can redo nothing (a view edit after an undo cleared its redo): the
    /// layer's undone edits can no longer be reached, so they go too and the two agree.
    pub fn forget_redo(&mut self) {
        if self.history.can_redo() {
            self.history.clear_redo();
        }
    }

    /// The page's history redoes `step` (false as for [`Self::undo_step`]).
    pub fn redo_step(&mut self, step: &SegmentStep) -> bool {
        let redone =
            step.layer == self.page_history.layer && self.history.redo(&mut self.layer).is_some();
        if redone {
            self.revision += 1;
        }
        redone
    }

    /// Draws the labels of `view`'s slice at `position` (continuous index along its normal)
    /// over the slice image in `image_rect`, remade only when the layer, slice or opacity
    /// changed.
    pub fn paint_labels(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        view: SliceView,
        frame: SliceFrame,
        image_rect: Rect,
        position: f64,
    ) {
        if self.layer.edited_brick_count() == 0 {
            return;
        }
        let dims = self.layer.grid().dims();
        let n = frame.normal_axis;
        let slice = (position.round() as i64).clamp(0, i64::from(dims[n]) - 1);
        let made_from = (self.revision, slice, self.opacity.to_bits());
        let current = self.images[view.index()]
            .as_ref()
            .is_some_and(|i| i.made_from == made_from);
        if !current {
            let (width, height) = (
                dims[frame.across_axis] as usize,
                dims[frame.down_axis] as usize,
            );
            let rgba = self.label_slice_rgba(frame, slice as u32);
            let image = egui::ColorImage::from_rgba_unmultiplied([width, height], &rgba);
            match self.images[view.index()].as_mut() {
                Some(shown) => {
                    shown.texture.set(image, TextureOptions::NEAREST);
                    shown.made_from = made_from;
                }
                None => {
                    self.images[view.index()] = Some(LabelImage {
                        texture: ctx.load_texture(
                            format!("labels {}", view.name()),
                            image,
                            TextureOptions::NEAREST,
                        ),
                        made_from,
                    });
                }
            }
        }
        if let Some(shown) = &self.images[view.index()] {
            // Level 0, one texel a voxel: the whole image, flipped as the slice is.
            painter.add(egui::Shape::mesh(slice_mesh(
                shown.texture.id(),
                image_rect,
                (1.0, 1.0),
                frame,
            )));
        }
    }

    /// Draws the labels on the oblique view's `plane` over its image in `image_rect`: nearest
    /// voxel at the centre of each of `pixels` × `pixels` (the oblique image's own pixels, as
    /// the desktop samples its overlay there), remade only when the layer, plane, pixels or
    /// opacity changed.
    pub fn paint_oblique_labels(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        plane: &ObliquePlane,
        image_rect: Rect,
        pixels: usize,
    ) {
        if self.layer.edited_brick_count() == 0 || pixels == 0 {
            return;
        }
        let made_from = (self.revision, *plane, pixels, self.opacity.to_bits());
        if self
            .oblique_image
            .as_ref()
            .is_none_or(|shown| shown.made_from != made_from)
        {
            let grid = self.layer.grid();
            let segments = self.layer.segments();
            let mut rgba = Vec::with_capacity(pixels * pixels * 4);
            for y in 0..pixels {
                for x in 0..pixels {
                    let at = plane.patient_at(
                        (x as f64 + 0.5) / pixels as f64,
                        (y as f64 + 0.5) / pixels as f64,
                    );
                    let index = grid.index_from_patient(at).round();
                    let voxel = [index.x, index.y, index.z].map(|c| c as i64);
                    let label = if grid.contains(voxel) {
                        self.layer.get(voxel.map(|c| c as u32)).unwrap_or(0)
                    } else {
                        0
                    };
                    rgba.extend(segment_panel::label_rgba(segments, label, self.opacity));
                }
            }
            let image = egui::ColorImage::from_rgba_unmultiplied([pixels, pixels], &rgba);
            match self.oblique_image.as_mut() {
                Some(shown) => {
                    shown.texture.set(image, TextureOptions::NEAREST);
                    shown.made_from = made_from;
                }
                None => {
                    self.oblique_image = Some(ObliqueLabelImage {
                        texture: ctx.load_texture("labels oblique", image, TextureOptions::NEAREST),
                        made_from,
                    });
                }
            }
        }
        if let Some(shown) = &self.oblique_image {
            painter.image(
                shown.texture.id(),
                image_rect,
                Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                Color32::WHITE,
            );
        }
    }

    /// The labels of one slice as unmultiplied RGBA, across axis fastest (index order, flips
    /// applied by the mesh).
    fn label_slice_rgba(&self, frame: SliceFrame, slice: u32) -> Vec<u8> {
        let dims = self.layer.grid().dims();
        let (width, height) = (dims[frame.across_axis], dims[frame.down_axis]);
        let segments = self.layer.segments();
        let mut rgba = Vec::with_capacity(width as usize * height as usize * 4);
        let mut index = [0u32; 3];
        index[frame.normal_axis] = slice;
        for d in 0..height {
            index[frame.down_axis] = d;
            for a in 0..width {
                index[frame.across_axis] = a;
                let label = self.layer.get(index).unwrap_or(0);
                rgba.extend(segment_panel::label_rgba(segments, label, self.opacity));
            }
        }
        rgba
    }

    /// Labelled voxels and an order-independent checksum of their positions and labels.
    fn painted(&self) -> (u64, u64) {
        let grid = self.layer.grid();
        let dims = grid.dims();
        let b = LABEL_BRICK as usize;
        let (mut count, mut checksum) = (0u64, 0u64);
        for (key, voxels) in self.layer.edited_bricks() {
            let origin = grid.brick_origin(key);
            for (at, &label) in voxels.iter().enumerate() {
                if label == 0 {
                    continue;
                }
                let v = [
                    origin[0] + (at % b) as u32,
                    origin[1] + (at / b % b) as u32,
                    origin[2] + (at / (b * b)) as u32,
                ];
                if (0..3).any(|a| v[a] >= dims[a]) {
                    continue;
                }
                count += 1;
                let word = u64::from(v[0])
                    | u64::from(v[1]) << 16
                    | u64::from(v[2]) << 32
                    | u64::from(label) << 48;
                checksum = checksum.wrapping_add(splitmix64(word));
            }
        }
        (count, checksum)
    }

    /// The figures `data-segmentation` carries (the voxel count and checksum recomputed only
    /// when the layer changed).
    fn figures(&mut self) -> String {
        let (painted, checksum) = match self.painted_at {
            Some((revision, painted)) if revision == self.revision => painted,
            _ => {
                let painted = self.painted();
                self.painted_at = Some((self.revision, painted));
                painted
            }
        };
        let mut text = format!(
            "segments={};painted={painted};checksum={checksum:016x};undo={};redo={};stroke={}",
            self.layer.segments().len(),
            u8::from(self.history.can_undo()),
            u8::from(self.history.can_redo()),
            u8::from(self.stroke.is_some()),
        );
        // Last, as it may hold any character: what the panel shows in red.
        if let Some(error) = &self.error {
            text.push_str(&format!(";error={error}"));
        }
        text
    }

    /// Saves the layer as a `.nii.gz` label map through the browser's download.
    fn download(&mut self) {
        let saved = label_map_gz_bytes(&self.layer, DOWNLOAD_NAME)
            .map_err(|e| e.to_string())
            .and_then(|bytes| {
                save_bytes(&bytes, DOWNLOAD_NAME, self.download_url.take())
                    .map_err(|e| format!("download: {e:?}"))
            });
        match saved {
            Ok(url) => {
                self.download_url = Some(url);
                self.error = None;
            }
            Err(e) => self.error = Some(e),
        }
    }
}

impl PageSegmentation {
    /// Saves the layer as a DICOM SEG or zipped OME-Zarr labels (segment_downloads.rs).
    fn download_as(&mut self, what: SegmentDownload) {
        match segment_downloads::download(what, &self.layer, self.download_url.take()) {
            Ok(url) => {
                self.download_url = Some(url);
                self.error = None;
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }
}

/// A 64-bit mix (splitmix64's finaliser), so the checksum's sum is not fooled by voxels
/// trading places.
fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Hands `bytes` to the browser as a download named `name` (a Blob, an object URL, an anchor
/// with `download=` clicked); revokes `previous`, the last download's URL. Returns the URL.
fn save_bytes(bytes: &[u8], name: &str, previous: Option<String>) -> Result<String, JsValue> {
    if let Some(url) = previous {
        web_sys::Url::revoke_object_url(&url)?;
    }
    let parts = js_sys::Array::of1(&js_sys::Uint8Array::from(bytes));
    let options = web_sys::BlobPropertyBag::new();
    options.set_type("application/gzip");
    let blob = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &options)?;
    let url = web_sys::Url::create_object_url_with_blob(&blob)?;
    let document = web_sys::window()
        .and_then(|w| w.document())
        .ok_or_else(|| JsValue::from_str("no document"))?;
    let anchor: web_sys::HtmlAnchorElement = document.create_element("a")?.dyn_into()?;
    anchor.set_href(&url);
    anchor.set_download(name);
    anchor.click();
    Ok(url)
}

/// The Segment section of the page's side panel, on the slice views' volume: New
/// segmentation, then the shared tool row, opacity, segment list and operations, Undo, Redo,
/// Download and Close.
pub fn section(ui: &mut egui::Ui, slices: &mut SliceViews) {
    let mut buttons: Vec<(&'static str, Rect)> = Vec::new();
    let geometry = slices.geometry().clone();
    let seg_slot = &mut slices.segmentation;
    let primary_values = &mut slices.primary_values;
    let Some(seg) = seg_slot.as_mut() else {
        let new = ui
            .button("New segmentation")
            .on_hover_text("An empty label layer on this volume's grid, in the page's memory");
        buttons.push(("new", new.rect));
        if new.clicked() {
            match PageSegmentation::new(&geometry) {
                Ok(seg) => *seg_slot = Some(seg),
                Err(e) => {
                    ui.colored_label(Color32::LIGHT_RED, e.to_string());
                }
            }
        }
        crate::canvas_attributes::set("data-segment-buttons", &button_text(&buttons));
        crate::canvas_attributes::set("data-segmentation", "none");
        return;
    };
    for (tool, rect) in segment_panel::tool_row(ui, &mut seg.tool, &mut seg.diameter_mm, true) {
        let name = match tool {
            SegmentTool::None => "off",
            SegmentTool::Brush => "brush",
            SegmentTool::Eraser => "eraser",
            SegmentTool::Fill => "fill",
            SegmentTool::Grow => "grow",
        };
        buttons.push((name, rect));
    }
    let values = crate::segment_values::rows(
        ui,
        &mut seg.values,
        seg.tool,
        &mut seg.layer,
        primary_values.as_mut().ok(),
        &mut buttons,
    );
    if let Some(edit) = values.edit {
        seg.push_step(edit);
        seg.revision += 1;
        seg.error = None;
    }
    if let Some(e) = values.error {
        seg.error = Some(e);
    }
    apply_queued_strokes(seg, primary_values, ui.ctx());
    if segment_panel::opacity_row(ui, &mut seg.opacity).changed() {
        ui.ctx().request_repaint();
    }
    let mut table = seg.layer.segments().clone();
    let before = table.clone();
    let change = segment_panel::segment_list(ui, &mut table, &mut seg.active);
    if table != before {
        *seg.layer.segments_mut() = table;
        seg.revision += 1;
    }
    match change {
        Some(SegmentListChange::Add) => {
            let count = seg.layer.segments().len();
            match seg
                .layer
                .segments_mut()
                .add(format!("Segment {}", count + 1))
            {
                Ok(value) => {
                    seg.active = value;
                    seg.revision += 1;
                }
                Err(e) => seg.error = Some(e.to_string()),
            }
        }
        Some(SegmentListChange::Remove(value)) => match seg.layer.remove_segment(value) {
            Ok(edit) => {
                seg.push_step(edit);
                seg.revision += 1;
                if seg.active == value {
                    seg.active = seg.layer.segments().iter().next().map_or(0, |s| s.value);
                }
            }
            Err(e) => seg.error = Some(e.to_string()),
        },
        None => {}
    }
    let table = seg.layer.segments().clone();
    let operations = segment_panel::operations(
        ui,
        &mut seg.operations,
        &table,
        seg.active,
        seg.stroke.is_none(),
    );
    buttons.extend(operations.buttons);
    if let Some(operation) = operations.chosen {
        seg.operate(operation);
    }
    let mut close = false;
    ui.horizontal_wrapped(|ui| {
        // The page's Undo and Redo (Ctrl+Z, Ctrl+Y): segment edits and view edits in one order.
        let (can_undo, can_redo) = seg.page_history.page_can;
        let undo = ui.add_enabled(can_undo, egui::Button::new("Undo"));
        let redo = ui.add_enabled(can_redo, egui::Button::new("Redo"));
        let download = ui
            .button("Download")
            .on_hover_text(format!("Save as a NIfTI label map ({DOWNLOAD_NAME})"));
        buttons.extend([
            ("undo", undo.rect),
            ("redo", redo.rect),
            ("download", download.rect),
        ]);
        let mut download_as = None;
        for what in SegmentDownload::ALL {
            let button = ui.button(what.label()).on_hover_text(what.hover());
            buttons.push((what.button_name(), button.rect));
            if button.clicked() {
                download_as = Some(what);
            }
        }
        if let Some(what) = download_as {
            seg.download_as(what);
        }
        if undo.clicked() {
            seg.page_history.asked.0 = true;
        }
        if redo.clicked() {
            seg.page_history.asked.1 = true;
        }
        if download.clicked() {
            seg.download();
        }
        close = ui
            .button("Close")
            .on_hover_text("Stop editing (the labels are discarded: download them first)")
            .clicked();
    });
    if let Some(e) = &seg.error {
        ui.colored_label(Color32::LIGHT_RED, e);
    }
    crate::canvas_attributes::set("data-segment-buttons", &button_text(&buttons));
    crate::canvas_attributes::set("data-segmentation", &seg.figures());
    if close {
        *seg_slot = None;
    }
}

/// Applies the queued pieces of a stroke limited to a value range whose bricks arrived, and
/// ends a released stroke once none is left.
fn apply_queued_strokes(
    seg: &mut PageSegmentation,
    primary_values: &mut Result<crate::primary_values_page::PagePrimaryValues, String>,
    ctx: &egui::Context,
) {
    let Some(stroke) = seg.stroke.as_mut().filter(|s| !s.queued.is_empty()) else {
        return;
    };
    let (edits, error) = match primary_values {
        Ok(primary) => crate::segment_values::apply_queued_strokes(
            &mut seg.layer,
            stroke.action,
            &mut stroke.queued,
            primary,
        ),
        Err(e) => {
            stroke.queued.clear();
            (Vec::new(), Some(e.clone()))
        }
    };
    if !edits.is_empty() {
        stroke.edits.extend(edits);
        seg.revision += 1;
    }
    if error.is_some() {
        seg.error = error;
    }
    if stroke.queued.is_empty() {
        if stroke.released {
            seg.end_stroke();
        }
    } else {
        // Bricks are on their way and wake nothing: poll until they are in.
        ctx.request_repaint();
    }
}

fn button_text(buttons: &[(&str, Rect)]) -> String {
    buttons
        .iter()
        .map(|(name, r)| {
            format!(
                "{name}:{},{},{},{}",
                r.min.x,
                r.min.y,
                r.width(),
                r.height()
            )
        })
        .collect::<Vec<_>>()
        .join(";")
}

/// The brush plane of a slice view: the labels lie on the primary's grid, so the index plane
/// with the view's normal (the desktop's `plane_for_view` on the primary's own grid).
pub fn plane_of(frame: SliceFrame) -> SlicePlane {
    match frame.normal_axis {
        0 => SlicePlane::Sagittal,
        1 => SlicePlane::Coronal,
        _ => SlicePlane::Axial,
    }
}
