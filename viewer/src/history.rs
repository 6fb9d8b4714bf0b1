//! Undo and redo (Ctrl+Z, Ctrl+Shift+Z or Ctrl+Y) of what the user adjusts: the transfer
//! function, the slice window, the crop box and the measurements. A change becomes one step
//! when its gesture ends (no button held), so a drag is undone as a whole, not per frame.

use strata_render::{CropBox, TransferFunction};

use super::measurements::Measurement;
use super::scene::{Scene, Window};

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

pub struct History {
    undo: Vec<Snapshot>,
    redo: Vec<Snapshot>,
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
            self.undo.push(before);
            if self.undo.len() > MAX_STEPS {
                self.undo.remove(0);
            }
            self.redo.clear();
        }
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }

    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Restores the state before the last step; false if there is none.
    pub fn undo(&mut self, scene: &mut Scene) -> bool {
        self.observe(scene, false);
        let Some(previous) = self.undo.pop() else {
            return false;
        };
        let current = std::mem::replace(&mut self.committed, previous);
        self.redo.push(current);
        self.committed.apply(scene);
        true
    }

    /// Re-applies the last undone step; false if there is none.
    pub fn redo(&mut self, scene: &mut Scene) -> bool {
        let Some(next) = self.redo.pop() else {
            return false;
        };
        let current = std::mem::replace(&mut self.committed, next);
        self.undo.push(current);
        self.committed.apply(scene);
        true
    }
}
