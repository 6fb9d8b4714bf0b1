//! Undo and redo (Ctrl+Z, Ctrl+Shift+Z or Ctrl+Y) of what the user adjusts: the transfer
//! function, the slice window, the crop box and the measurements. A change becomes one step
//! when its gesture ends (no button held), so a drag is undone as a whole, not per frame.
//! Label edits (a brush stroke, segmentation.rs) are steps of their own in the same list: the
//! edit's brick images, reverted or applied again on the layer they were made on. The rules
//! (and the page's undo) are strata_viewer_ui::history's.

use strata_render::{CropBox, TransferFunction};
use strata_segment::Edit;
use strata_viewer_ui::history::{History as SharedHistory, Stepped};

use super::segmentation::Segmentation;

use super::scene::{Scene, Window};
use strata_viewer_ui::measurements::Measurement;

#[derive(Clone, Debug, PartialEq)]
struct Snapshot {
    transfer_function: TransferFunction,
    tf_source: TransferFunction,
    window: Window,
    crop: CropBox,
    measurements: Vec<Measurement>,
}

impl Snapshot {
    fn of(scene: &Scene) -> Self {
        Snapshot {
            transfer_function: scene.transfer_function.clone(),
            tf_source: scene.tf_source.clone(),
            window: scene.window,
            crop: scene.crop,
            measurements: scene.measurements.items.clone(),
        }
    }

    fn apply(&self, scene: &mut Scene) {
        scene.transfer_function = self.transfer_function.clone();
        scene.tf_source = self.tf_source.clone();
        scene.window = self.window;
        scene.crop = self.crop;
        scene.measurements.items = self.measurements.clone();
        scene.measurements.draft.points.clear();
    }
}

/// A label edit of the layer `layer_id`: an undo step the layer reverts itself.
#[derive(Clone, Debug)]
struct LabelStep {
    layer_id: u64,
    edit: Edit,
}

/// The shared history (strata_viewer_ui::history: a drag one step, redo cleared by a new
/// step, a cap on depth) of the scene's snapshots and the label edits.
pub struct History {
    steps: SharedHistory<Snapshot, LabelStep>,
}

impl History {
    pub fn new(scene: &Scene) -> Self {
        History {
            steps: SharedHistory::new(Snapshot::of(scene)),
        }
    }

    /// Called once per frame after the views and panels: a change with no gesture in progress
    /// becomes an undo step.
    pub fn observe(&mut self, scene: &Scene, gesture_in_progress: bool) {
        if gesture_in_progress {
            return;
        }
        self.steps.observe(&Snapshot::of(scene), false);
    }

    /// A completed label edit (already applied to the layer) becomes one undo step.
    pub fn push_label_edit(&mut self, segmentation: &Segmentation, edit: Edit) {
        self.steps.push_edit(LabelStep {
            layer_id: segmentation.id,
            edit,
        });
    }

    pub fn can_undo(&self) -> bool {
        self.steps.can_undo()
    }

    pub fn can_redo(&self) -> bool {
        self.steps.can_redo()
    }

    /// Restores the state before the last step; false if there is none. A label step of a
    /// layer no longer open is dropped (there is nothing left to undo it on).
    pub fn undo(&mut self, scene: &mut Scene, mut labels: Option<&mut Segmentation>) -> bool {
        let stepped = self.steps.undo(&Snapshot::of(scene), |step| {
            match labels.as_deref_mut().filter(|s| s.id == step.layer_id) {
                Some(seg) => {
                    seg.revert(&step.edit);
                    true
                }
                None => false,
            }
        });
        Self::restore(stepped, scene)
    }

    /// Re-applies the last undone step; false if there is none.
    pub fn redo(&mut self, scene: &mut Scene, mut labels: Option<&mut Segmentation>) -> bool {
        let stepped =
            self.steps.redo(
                |step| match labels.as_deref_mut().filter(|s| s.id == step.layer_id) {
                    Some(seg) => {
                        seg.reapply(&step.edit);
                        true
                    }
                    None => false,
                },
            );
        Self::restore(stepped, scene)
    }

    fn restore(stepped: Stepped<Snapshot>, scene: &mut Scene) -> bool {
        match stepped {
            Stepped::Nothing => false,
            Stepped::State(snapshot) => {
                snapshot.apply(scene);
                true
            }
            Stepped::Edit => true,
        }
    }
}
