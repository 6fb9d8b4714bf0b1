//! The segment tools in the page's 3D view (issue 52, wasm32 only), the desktop's gesture
//! (viewer/src/view3d.rs `segment_input`): with the brush or eraser chosen the left drag
//! sweeps a ball of the brush's diameter through the surface points picked under the pointer
//! (a click: one ball), one undo step per stroke (`PageSegmentation::sphere_stroke_to`, the
//! desktop's `Segmentation::sphere_stroke_to`); with the grow tool a click seeds the grow at
//! the picked point. A ray that meets nothing edits nothing.
//!
//! The page picks asynchronously (picking.rs, shared with the crosshair's click): each pointer
//! position of the drag starts its own one-pixel depth readback from the frame on screen, and
//! the readbacks are taken in the order started, so the balls are swept in the pointer's order
//! whenever the browser resolves them. The release ends the stroke once the last pick is in.
//!
//! For the browser tests (web/tests/browser/segment_3d.rs) the canvas carries
//! `data-segment-3d`: `strokes=N;points=I,J,K|I,J,K…`, the level-0 continuous indices of the
//! last finished stroke's picked points in the order swept (numbers in full, so the desktop's
//! stroke can be replayed on them exactly). Read it with `getAttribute`: a hyphen before a
//! digit stays in the dataset's name (`dataset['segment-3d']`, not `dataset.segment3d`).

use std::collections::VecDeque;

use egui::{PointerButton, Pos2, Response};
use glam::DVec3;
use strata_render::VolumeGeometry;
use strata_viewer_ui::segment_panel::SegmentTool;

use crate::picking::{PendingPick, PickError};
use crate::segment_editor::PageSegmentation;

/// What a picked point is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PickUse {
    /// A ball of the stroke.
    Ball,
    /// The grow's seed.
    Seed,
}

/// The 3D view's segment gesture: the picks on their way and the stroke they feed.
#[derive(Default)]
pub struct Segment3d {
    picks: VecDeque<(PendingPick, PickUse)>,
    /// The button was released: the stroke ends once its picks are in.
    released: bool,
    /// The last pointer position a ball was asked for (a still pointer asks for no readback).
    last_asked: Option<Pos2>,
    /// The current stroke's picked points (continuous level-0 index), for `data-segment-3d`.
    points: Vec<[f64; 3]>,
    strokes: u64,
}

impl Segment3d {
    /// Whether the left button in the 3D view is the segment tool's (not the orbit's and the
    /// crosshair's): a brush, eraser or grow chosen, shift not held (shift-drag pans on the
    /// desktop; the page keeps orbiting with it).
    pub fn takes_left_button(tool: SegmentTool, ui: &egui::Ui) -> bool {
        tool != SegmentTool::None && !ui.input(|i| i.modifiers.shift)
    }

    /// The pointer positions of this frame's gesture to pick, in order, for `tool`: the
    /// press, each move while dragging, the release (a click: one ball; with the grow: its
    /// seed). `start` starts a pick at a position (`None`: off the image or no frame yet).
    pub fn input(
        &mut self,
        ui: &egui::Ui,
        response: &Response,
        tool: SegmentTool,
        mut start: impl FnMut(Pos2) -> Option<PendingPick>,
    ) {
        let primary = PointerButton::Primary;
        let mut ask = |this: &mut Self, pos: Pos2, what: PickUse| {
            if what == PickUse::Ball && this.last_asked == Some(pos) {
                return;
            }
            if let Some(pick) = start(pos) {
                this.picks.push_back((pick, what));
                if what == PickUse::Ball {
                    this.last_asked = Some(pos);
                }
            }
        };
        if tool == SegmentTool::Grow {
            if response.clicked_by(primary) {
                if let Some(pos) = response.interact_pointer_pos() {
                    ask(self, pos, PickUse::Seed);
                }
            }
            return;
        }
        if !tool.drags() {
            return;
        }
        if response.drag_started_by(primary) {
            self.last_asked = None;
            if let Some(origin) = ui.input(|i| i.pointer.press_origin()) {
                ask(self, origin, PickUse::Ball);
            }
        }
        if response.dragged_by(primary) {
            if let Some(pos) = response.interact_pointer_pos() {
                ask(self, pos, PickUse::Ball);
            }
        }
        if response.drag_stopped_by(primary) {
            // The release's own position ends the stroke, as on the slice views.
            if let Some(pos) = response.interact_pointer_pos() {
                ask(self, pos, PickUse::Ball);
            }
            self.released = true;
        }
        if response.clicked_by(primary) {
            self.last_asked = None;
            if let Some(pos) = response.interact_pointer_pos() {
                ask(self, pos, PickUse::Ball);
            }
            self.released = true;
        }
        if !self.picks.is_empty() {
            // The readbacks wake the page when mapped; until then nothing else may.
            ui.ctx().request_repaint();
        }
    }

    /// Takes the picks that are in, in the order started, onto `seg` (a ball swept on, a
    /// grow seeded), and ends a released stroke once none is left. Returns a failed
    /// readback's error.
    pub fn apply(
        &mut self,
        geometry: &VolumeGeometry,
        seg: Option<&mut PageSegmentation>,
    ) -> Option<PickError> {
        let Some(seg) = seg else {
            // The segmentation was closed: its picks have nothing to edit.
            *self = Segment3d {
                strokes: self.strokes,
                ..Segment3d::default()
            };
            return None;
        };
        let mut error = None;
        while let Some((pick, what)) = self.picks.front() {
            let Some(result) = pick.poll(geometry) else {
                break;
            };
            let what = *what;
            self.picks.pop_front();
            let index = match result {
                Ok(Some(index)) => index,
                // The ray met nothing there: no ball, as on the desktop.
                Ok(None) => continue,
                Err(e) => {
                    error = Some(e);
                    continue;
                }
            };
            let position_lps = geometry.patient_from_index(DVec3::from(index));
            match what {
                PickUse::Ball => {
                    seg.sphere_stroke_to(position_lps);
                    if self.points.last() != Some(&index) {
                        self.points.push(index);
                    }
                }
                PickUse::Seed => seg.grow_at(position_lps),
            }
        }
        if self.released && self.picks.is_empty() {
            self.released = false;
            self.last_asked = None;
            seg.end_stroke();
            if !self.points.is_empty() {
                self.strokes += 1;
                let points: Vec<String> = std::mem::take(&mut self.points)
                    .iter()
                    .map(|p| format!("{},{},{}", p[0], p[1], p[2]))
                    .collect();
                crate::canvas_attributes::set(
                    "data-segment-3d",
                    &format!("strokes={};points={}", self.strokes, points.join("|")),
                );
            }
        }
        error
    }
}
