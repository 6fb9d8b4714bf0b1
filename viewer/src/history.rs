//! Undo and redo (Ctrl+Z, Ctrl+Shift+Z or Ctrl+Y) of what the user adjusts: the transfer
//! function, the slice window, the crop box and the measurements. A change becomes one step
//! when its gesture ends (no button held), so a drag is undone as a whole, not per frame.
//! Label edits (a brush stroke, segmentation.rs) are steps of their own in the same list: the
//! edit's brick images, reverted or applied again on the layer they were made on.

use strata_render::{CropBox, TransferFunction};
use strata_segment::Edit;

use super::segmentation::Segmentation;

use super::scene::{Scene, Window};
use strata_viewer_ui::measurements::Measurement;

/// Steps kept; older ones are dropped.
const MAX_STEPS: usize = 200;

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

/// One undo step: the scene before it, or a label edit of the layer `layer_id`.
#[derive(Clone, Debug)]
enum Step {
    Scene(Snapshot),
    Labels { layer_id: u64, edit: Edit },
}

pub struct History {
    undo: Vec<Step>,
    redo: Vec<Step>,
    /// The state the last step ended in.
    committed: Snapshot,
}

impl History {
    pub fn new(scene: &Scene) -> Self {
        History {
            undo: Vec::new(),
            redo: Vec::new(),
            committed: Snapshot::of(scene),
        }
    }

    /// Called once per frame after the views and panels: a change with no gesture in progress
    /// becomes an undo step.
    pub fn observe(&mut self, scene: &Scene, gesture_in_progress: bool) {
        if gesture_in_progress {
            return;
        }
        let now = Snapshot::of(scene);
        if now != self.committed {
            let before = std::mem::replace(&mut self.committed, now);
            self.push(Step::Scene(before));
        }
    }

    fn push(&mut self, step: Step) {
        self.undo.push(step);
        if self.undo.len() > MAX_STEPS {
            self.undo.remove(0);
        }
        self.redo.clear();
    }

    /// A completed label edit (already applied to the layer) becomes one undo step.
    pub fn push_label_edit(&mut self, segmentation: &Segmentation, edit: Edit) {
        self.push(Step::Labels {
            layer_id: segmentation.id,
            edit,
        });
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }

    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Restores the state before the last step; false if there is none. A label step of a
    /// layer no longer open is dropped (there is nothing left to undo it on).
    pub fn undo(&mut self, scene: &mut Scene, mut labels: Option<&mut Segmentation>) -> bool {
        self.observe(scene, false);
        while let Some(step) = self.undo.pop() {
            match step {
                Step::Scene(previous) => {
                    let current = std::mem::replace(&mut self.committed, previous);
                    self.redo.push(Step::Scene(current));
                    self.committed.apply(scene);
                    return true;
                }
                Step::Labels { layer_id, edit } => {
                    if let Some(seg) = labels.as_deref_mut().filter(|s| s.id == layer_id) {
                        seg.revert(&edit);
                        self.redo.push(Step::Labels { layer_id, edit });
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Re-applies the last undone step; false if there is none.
    pub fn redo(&mut self, scene: &mut Scene, mut labels: Option<&mut Segmentation>) -> bool {
        while let Some(step) = self.redo.pop() {
            match step {
                Step::Scene(next) => {
                    let current = std::mem::replace(&mut self.committed, next);
                    self.undo.push(Step::Scene(current));
                    self.committed.apply(scene);
                    return true;
                }
                Step::Labels { layer_id, edit } => {
                    if let Some(seg) = labels.as_deref_mut().filter(|s| s.id == layer_id) {
                        seg.reapply(&edit);
                        self.undo.push(Step::Labels { layer_id, edit });
                        return true;
                    }
                }
            }
        }
        false
    }
}
